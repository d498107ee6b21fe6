"""`dovesei smoke`: proves an install works end to end at the transport level.

Opens two Zenoh peers on loopback, publishes one of each message type from one and decodes it
on the other, and prints what it checked. It is what the README's main command ran before the
services existed, and stays as a quick health check of a machine.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import zenoh

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.lifecycle import Inbox, wait_until
from dovesei.shared.messages import SafetyHeatmap, Stamp
from dovesei.shared.zconfig import free_port, loopback_config




def main(argv: list[str] | None = None) -> int:
    OneLineParser(prog="dovesei smoke", description=__doc__).parse_args(argv)
    port = free_port()
    hm = SafetyHeatmap("smoke", 0, Stamp(0.0, "sim"), np.zeros((352, 352), np.uint8), 100.0, 1.274,
                       "simulated", True, "none", "grouped", 0.0)
    with zenoh.open(loopback_config(listen_port=port)) as a, zenoh.open(loopback_config(connect_ports=[port])) as b:
        with Inbox(b, keys.heatmap("smoke"), SafetyHeatmap, newest_only=True) as inbox:
            got: list[SafetyHeatmap] = []
            ok = wait_until(lambda: (a.put(keys.heatmap("smoke"), encode(hm)),
                                     (m := inbox.poll()) is not None and got.append(m) is None)[1], 10.0)
    result = {"zenoh_loopback": ok, "heatmap_round_trip": bool(got) and got[0].prob_safe.shape == (352, 352)}
    print(json.dumps(result))
    return 0 if all(result.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
