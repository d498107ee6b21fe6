"""`dovesei policy-config`: print a policy's constants as a TOML file, or check one.

    dovesei policy-config --defaults clearance > clearance.toml   # edit, keep what you change
    dovesei policy-config --check clearance.toml --policy clearance
    dovesei up --policy clearance --policy-config clearance.toml

The file's format and checks are the controller's (`dovesei.controller.policies.config_file`).
"""

from __future__ import annotations

import argparse
import sys

from dovesei.controller.policies.registry import policy_names
from dovesei.controller.policies.config_file import defaults_toml, load_policy_config, policy_values
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.errors import ConfigError
from dovesei.shared.timing import TIMING_NAMES


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei policy-config", description=__doc__,
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--defaults", metavar="POLICY", choices=policy_names(),
                      help=f"print every constant of this policy with its default ({', '.join(policy_names())})")
    what.add_argument("--check", metavar="FILE", help="check a policy file and print the values it gives")
    p.add_argument("--policy", choices=policy_names(), default="clearance", help="with --check: the policy it is for")
    p.add_argument("--timing", choices=TIMING_NAMES, default="real", help="the timing preset the values apply to")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.defaults is not None:
        sys.stdout.write(defaults_toml(args.defaults, args.timing))
        return 0
    try:
        config = load_policy_config(args.policy, args.check, args.timing)
    except ConfigError as exc:
        print(f"dovesei policy-config: {exc}", file=sys.stderr)
        return 2
    for name, value in policy_values(args.policy, config).items():
        print(f"{name} = {value!r}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
