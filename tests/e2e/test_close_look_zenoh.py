"""The close look over Zenoh (issue 24): sim, segmenter and controller as three services on three
real sessions, in lockstep, fly the lawn with people standing on it exactly as the in-process
episode does: the controller asks the sim's crop key and the segmenter's segment key, and the same
looks reject the same spot."""

from __future__ import annotations

import threading

import numpy as np
import zenoh

from dovesei.controller import service as ctrl_service
from dovesei.controller.core import ControllerConfig
from dovesei.segmenter import service as seg_service
from dovesei.segmenter.core import SegmenterConfig
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.zconfig import free_port, loopback_config
from dovesei.sim import service as sim_service
from dovesei.sim.core import SimConfig
from tests.controller.test_close_look import CENTRE, LAWN_M, SMALL_WORLD, fly, lawn_world, person

LIMIT_S = 150.0


def test_three_services_on_zenoh_fly_the_close_looks_as_the_in_process_episode(tmp_path) -> None:
    lo = CENTRE[0] - LAWN_M / 2 + 2.5
    grid = np.arange(lo, CENTRE[0] + LAWN_M / 2 - 2.5 + 0.01, 5.0)
    world = lawn_world([person(x + 0.3, y - 0.2) for x in grid for y in grid])
    statuses, _looks, expected = fly(world, time_limit_s=LIMIT_S)
    assert any("close look: never set" in s.policy_reason for s in statuses)  # the in-process flight rejects

    # The controller service reads the in-process flight's small-world setting from its file.
    settings = tmp_path / "clearance.toml"
    settings.write_text("".join(f"{k} = {str(v).lower()}\n" for k, v in SMALL_WORLD), encoding="utf-8")
    port = free_port()
    sessions = [zenoh.open(loopback_config(listen_port=port))]
    sessions += [zenoh.open(loopback_config(connect_ports=[port])) for _ in range(2)]
    stop = threading.Event()
    out: dict[str, object] = {}

    def sim() -> None:
        config = sim_service.SimServiceConfig(
            sim=SimConfig(timing="real", vehicle_profile="ideal", time_limit_s=LIMIT_S, seed=0),
            start_xy_alt_m=(CENTRE[0], CENTRE[1], 100.0), wait_for=("segmenter", "controller"), wait_timeout_s=60.0,
            cmd_timeout_s=60.0)
        out["result"] = sim_service.run(sessions[0], config=config, stop=stop, world=world,
                                        stats=out.setdefault("sim", sim_service.SimStats()))

    def seg() -> None:
        config = seg_service.ServiceConfig(segmenter=SegmenterConfig(backend="sim", sim_profile="realistic", sim_seed=0),
                                           lockstep=True)
        out["segmenter"] = seg_service.run(sessions[1], config=config, stop=stop)

    def ctrl() -> None:
        config = ControllerConfig(policy="clearance", timing="real", lockstep=True, close_look=True,
                                  policy_config_file=str(settings))
        out["controller"] = ctrl_service.run(sessions[2], config=config, stop=stop)

    threads = [threading.Thread(target=f, daemon=True) for f in (seg, ctrl, sim)]
    try:
        for t in threads:
            t.start()
        assert wait_until(lambda: "result" in out, 600.0, poll_s=0.2), "the episode did not end"
    finally:
        stop.set()
        for t in threads:
            t.join(30.0)
        for s in reversed(sessions):
            s.close()
    result = out["result"]
    assert result is not None and result.outcome == expected.result.outcome
    assert (result.final_x_m, result.final_y_m) == (expected.result.final_x_m, expected.result.final_y_m)
    stats = out["sim"]
    assert stats.crops_answered >= 3 and stats.crops_refused == 0
    assert out["segmenter"]["processed_crops"] == stats.crops_answered
