"""`dovesei health`: exit 0 when a service's liveliness token is visible on the Zenoh network.

Used by compose healthchecks and by operators: `dovesei health --service segmenter --vehicle-id uav1`.
"""

from __future__ import annotations

import argparse
import sys

import zenoh

from dovesei.shared import keys
from dovesei.shared.lifecycle import is_alive
from dovesei.shared.zconfig import add_zenoh_args, zenoh_config_from_args


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dovesei health", description=__doc__)
    p.add_argument("--service", required=True, choices=keys.SERVICES)
    p.add_argument("--vehicle-id", default="uav1", help="vehicle id, or 'any' for a service that serves all vehicles")
    p.add_argument("--timeout-s", type=float, default=3.0)
    add_zenoh_args(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    vehicle = keys.ANY_VEHICLE if args.vehicle_id == "any" else args.vehicle_id
    with zenoh.open(zenoh_config_from_args(args)) as session:
        alive = is_alive(session, vehicle, args.service, timeout_s=args.timeout_s)
    print(f"{args.service} ({args.vehicle_id}): {'alive' if alive else 'NOT alive'}")
    return 0 if alive else 1


if __name__ == "__main__":
    sys.exit(main())
