"""A controller process flying a fake autopilot at 10 m/s, for the stop and kill tests.

`python -m tests.controller.flying_controller URL`: the real service loop (`run`) with a policy
double that asks forward 10 m/s, level, and a perception stand-in in the same process (a heatmap
every 0.2 s stamped with the newest state the controller published). SIGTERM stops it the way it
stops in flight; SIGKILL is a crash.
"""

from __future__ import annotations

import logging
import sys
import threading

import numpy as np
import zenoh

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.policies.base import Decision, Observation
from dovesei.controller.service import run
from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.lifecycle import Inbox, install_stop_handlers
from dovesei.shared.messages import SafetyHeatmap, VehicleState
from dovesei.shared.zconfig import loopback_config


class Forward10:
    name = "forward10"

    def step(self, obs: Observation) -> Decision:
        return Decision((10.0, 0.0, 0.0), 0.0, "RESTARTING", None, 10.0, 0.5)

    def reset(self) -> None:
        pass


def _perceive(session: zenoh.Session, stop: threading.Event) -> None:
    states = Inbox(session, keys.state("uav1"), VehicleState, newest_only=True)
    prob, seq, newest = np.full((32, 32), 200, np.uint8), 0, None
    try:
        while not stop.wait(0.2):
            newest = states.poll() or newest
            if newest is not None:
                session.put(keys.heatmap("uav1"), encode(SafetyHeatmap(
                    "uav1", seq, newest.stamp, prob, newest.alt_agl_m, 1.27, "simulated", True, "p", "f", 0.01)))
                seq += 1
    finally:
        states.close()


def main(url: str) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = install_stop_handlers()
    config = ControllerConfig(lockstep=False, timing="real", vehicle_url=url, state_stale_after_s=1.0,
                              geofence_radius_m=0.0)
    with zenoh.open(loopback_config()) as session:
        perception = threading.Thread(target=_perceive, args=(session, stop), daemon=True)
        perception.start()
        run(session, config=config, stop=stop, core=ControllerCore(config, policy=Forward10()))
        perception.join(2.0)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
