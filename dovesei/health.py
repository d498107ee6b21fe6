"""`dovesei health`: exit 0 when a service's liveliness token is visible on the Zenoh network.

Used by compose healthchecks and by operators: `dovesei health --service segmenter --vehicle-id uav1`.
"""

from __future__ import annotations

import argparse
import sys

import zenoh

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import keys, validate
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import is_alive
from dovesei.shared.zconfig import add_zenoh_args, zenoh_config_from_args


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei health", description=__doc__)
    p.add_argument("--service", required=True, choices=keys.SERVICES)
    p.add_argument("--vehicle-id", default="uav1", help="vehicle id, or 'any' for a service that serves all vehicles")
    p.add_argument("--timeout-s", type=float, default=3.0)
    add_zenoh_args(p)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        # Checked before any session opens: a bad flag is one usage line (exit 2), never a traceback.
        validate.positive("--timeout-s", args.timeout_s)
        vehicle = keys.ANY_VEHICLE if args.vehicle_id == "any" else keys.check_vehicle_id(args.vehicle_id)
        conf = zenoh_config_from_args(args)
    except ConfigError as exc:
        parser.error(str(exc))
    with zenoh.open(conf) as session:
        alive = is_alive(session, vehicle, args.service, timeout_s=args.timeout_s)
    print(f"{args.service} ({args.vehicle_id}): {'alive' if alive else 'NOT alive'}")
    return 0 if alive else 1


if __name__ == "__main__":
    sys.exit(main())
