"""`dovesei bench`: the paper's experiment, automatically judged and resumable.

N seeded start positions uniform over each world at 100 m, the same starts for every policy, one
episode per (world, policy, start) run by the in-process runner (`dovesei.episode`, the same
service cores as `dovesei up`), on a local process pool or as Ray tasks (`--engine ray`). Each
finished episode is appended to `episodes.jsonl` at once, so an interrupted bench continues where
it stopped. At the end:

    results.json   {"episodes": [...], "summary": {policy: {...}}, "config": {...}, "per_world": [...]}
    summary.md     a table shaped like the paper's Table I with Wilson 95 % intervals, success
                   against the time limit (60/300/600/1200 paper seconds), one row per world
    paths.png      every policy's path from the same starts over the world image (one per world)
    tracks/        one .npy path per episode (t_s, x_m, y_m, alt_agl_m)

Every flag, world and engine is checked before the output folder is created.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from dovesei.bench import shift
from dovesei.bench.run import Grid, Variant, run_grid, summary_markdown
from dovesei.bench.shift import parse_shift
from dovesei.controller.policies.registry import policy_names
from dovesei.controller.policies.config_file import load_policy_config, policy_values, preset_config
from dovesei.episode import DEFAULT_PERCEPTION
from dovesei.flight_defaults import default_start_margin_m, default_timing
from dovesei.episode import perception_names as _perception_names
from dovesei.bench.stats import SUMMARY_KEYS, summarise, wilson_interval
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import timing as shared_timing
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.mission import (
    HANDOVER_ALT_M, MIN_DESCENT_M, PERSON_SEPARATION_M, VEHICLE_SEPARATION_M, check_handover_below_start,
)
from dovesei.shared.validate import in_range, non_negative, positive
from dovesei.shared.validate import one_of as validate_one_of
from dovesei.sim.estimator import VEHICLE_PROFILE_NAMES, default_vehicle_profile
from dovesei.sim.starts import START_ALT_MAX_M, START_ALT_MIN_M, check_start_alt_m
from dovesei.sim.suite import suite as world_suite

__all__ = ["DEFAULT_POLICIES", "SUMMARY_KEYS", "build_parser", "main", "paper_time_limit_s", "parse_policies",
           "run_bench", "summarise", "summary_markdown", "wilson_interval", "suite_worlds", "perception_names"]

log = logging.getLogger(__name__)

DEFAULT_POLICIES = "dovesei,dovesei-nofocus"
BENCH_GNSS_DENIED = ("off", "external-nav")  # what a sim vehicle can fly (attitude needs a MAVLink autopilot)
PAPER_TIME_LIMIT_S = shared_timing.PAPER_TIME_LIMIT_S


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    where = p.add_mutually_exclusive_group()
    where.add_argument("--world", default=None, help="synthetic[:seed=N,...], dubai or a world folder (default: synthetic)")
    where.add_argument("--suite", default=None, help="a world suite of the repository: 'default' (every world of it)")
    p.add_argument("--episodes", type=int, default=50, help="start positions per world (each flown by every policy)")
    p.add_argument("--seed", type=int, default=0, help="seed of the start positions and of the perception noise")
    p.add_argument("--policy", default=DEFAULT_POLICIES, help="comma-separated policies")
    p.add_argument("--segmenter", default="sim", choices=("sim",),
                   help="perception backend (the bench flies simulated perception; CLIPSeg runs in `dovesei up`)")
    p.add_argument("--perception", default=None, help="simulated perception profile (default: realistic)")
    p.add_argument("--noise", type=float, default=None, help="simulated perception noise scale (default: the profile's)")
    p.add_argument("--perception-shift", default=None, metavar="A_LO,A_HI,B", help=shift.HELP)
    p.add_argument("--shift-only", action="store_true",
                   help="with --perception-shift: fly only the shifted runs (their plain twins are the same bench "
                        "without --perception-shift, the same seed and starts)")
    p.add_argument("--timing", default=None, help=f"timing preset: reference or real (default: real with `clearance` "
                                                   f"flown, else {shared_timing.DEFAULT_TIMING}; as `dovesei up`)")
    p.add_argument("--time-limit-s", type=float, default=None,
                   help="sim-time limit of an episode (default: the paper's 1200 s on the preset's clock)")
    p.add_argument("--start-alt-m", type=float, default=100.0,
                   help=f"start altitude of every episode, {START_ALT_MIN_M:g}-{START_ALT_MAX_M:g} m (default: the "
                        "paper's 100 m; a flow-navigating ArduCopter holds 48-69 m)")
    p.add_argument("--handover-alt-m", type=float, default=HANDOVER_ALT_M,
                   help="hand-over altitude: every policy hands over, and the judge judges, here (default: "
                        f"{HANDOVER_ALT_M:g} m; at least {MIN_DESCENT_M:g} m below the start)")
    p.add_argument("--person-separation-m", type=float, default=PERSON_SEPARATION_M,
                   help="the judge calls a landing unsafe with a person closer than this to the touchdown "
                        f"(default: {PERSON_SEPARATION_M:g} m; 0 turns the rule off)")
    p.add_argument("--vehicle-separation-m", type=float, default=VEHICLE_SEPARATION_M,
                   help="... or a vehicle closer than this (default: "
                        f"{VEHICLE_SEPARATION_M:g} m; 0 turns the rule off)")
    p.add_argument("--no-close-look", dest="close_look", action="store_false",
                   help="fly clearance without its close looks (full-resolution crops of the spot before committing)")
    p.add_argument("--policy-config", type=Path, default=None, metavar="FILE",
                   help="TOML file of the policy's constants (one --policy; `dovesei policy-config --defaults "
                        "POLICY` prints them all); recorded in results.json")
    p.add_argument("--vehicle-profile", default=None, choices=VEHICLE_PROFILE_NAMES,
                   help="what the vehicle reports and how it flies: ideal (the truth, a gimbal), realistic (an "
                        "optical-flow EKF without GNSS, a body-fixed camera, ArduCopter's limits) or harsh "
                        f"(default: {default_vehicle_profile('real')} with --timing real, "
                        f"{default_vehicle_profile('reference')} with --timing reference)")
    p.add_argument("--gnss-denied", default="off", choices=BENCH_GNSS_DENIED,
                   help="off: the vehicle flies on its profile's own estimate (default); external-nav: its "
                        "autopilot also fuses the camera's visual velocity (10 Hz views rendered at the true pose, "
                        "as `up --gnss-denied external-nav` feeds a real one); not with --vehicle-profile ideal")
    p.add_argument("--start-margin-m", type=float, default=None,
                   help="starts lie this far inside the area where the start footprint is on the map "
                        "(default: with `clearance` flown, its search radius + fence + a drift allowance, so its "
                        "whole search area is on the map; else 5 m)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="episodes in parallel (local workers; with --engine ray and no --address, the local Ray CPUs)")
    p.add_argument("--engine", default="local", choices=("local", "ray"), help="local process pool or Ray tasks")
    p.add_argument("--address", default=None, help="Ray cluster address (with --engine ray; default: a private local Ray)")
    p.add_argument("--out", type=Path, default=Path("runs/bench"), help="output folder (resumes if it exists)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    return p


def parse_policies(text: str) -> list[str]:
    names = [p.strip() for p in text.split(",") if p.strip()]
    known = policy_names()
    unknown = [n for n in names if n not in known]
    if not names or unknown:
        raise ConfigError(f"--policy {text!r}: unknown {unknown or 'empty list'}; known: {', '.join(known)}")
    return list(dict.fromkeys(names))


def paper_time_limit_s(timing: str) -> float:
    """The paper's 1200 s limit on the clock of a timing preset (see dovesei.shared.timing)."""
    return shared_timing.timing(timing).time_limit_s


def perception_names() -> tuple[str, ...]:
    """The simulated perception profiles the segmenter offers."""
    return _perception_names()


def check_perception(name: str | None) -> str:
    name = DEFAULT_PERCEPTION if name is None else name.strip()
    known = perception_names()
    if name not in known:
        raise ConfigError(f"--perception {name!r}: choose one of {', '.join(known)}")
    return name


def suite_worlds(name: str) -> tuple[str, ...]:
    """The world specs of a named suite of the repository (dovesei.sim.suite)."""
    try:
        return world_suite(name)
    except ConfigError as exc:
        raise ConfigError(f"--{exc}") from None


def _at_least_one(flag: str, value: int) -> int:
    if value < 1:
        raise ConfigError(f"{flag} must be at least 1, got {value}")
    return value


def run_bench(*, jobs: int, out: Path, engine: str = "local", address: str | None = None, progress: bool = True,
              **settings) -> dict:
    """Run (or resume) a bench into `out`; returns the results.json content. `settings`: `make_grid`'s."""
    _at_least_one("--jobs", jobs)
    if address and engine != "ray":
        raise ConfigError("--address names a Ray cluster: use it with --engine ray")
    return run_grid(make_grid(**settings), out=out, workers=jobs, engine=engine, address=address, progress=progress)


def make_grid(*, world_spec: str | None = None, worlds: tuple[str, ...] | None = None, episodes: int, seed: int,
              policies, noise: float | None, timing: str, time_limit_s: float, start_alt_m: float,
              start_margin_m: float = 5.0, segmenter: str = "sim", perception: str | None = None,
              world_label: str = "", seed_note: str = "", vehicle_profile: str | None = None,
              handover_alt_m: float = HANDOVER_ALT_M, policy_config: Path | None = None,
              separation_m: tuple[float, float] = (PERSON_SEPARATION_M, VEHICLE_SEPARATION_M),
              perception_shift: str | tuple | None = None, shift_only: bool = False,
              close_look: bool = True, gnss_denied: str = "off") -> Grid:
    """The bench's grid, every setting checked (one line naming the flag otherwise).

    With `perception_shift` ("A_LO,A_HI,B") every start is flown plainly and shifted (dovesei.bench.shift);
    with `shift_only` too, only shifted.
    """
    shifted = None if perception_shift is None else parse_shift(perception_shift)
    if shift_only and shifted is None:
        raise ConfigError("--shift-only needs --perception-shift A_LO,A_HI,B (there is nothing to shift)")
    _at_least_one("--episodes", episodes)
    if seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {seed}")
    if noise is not None:
        in_range("--noise", noise, 0.0, 4.0)
    positive("--time-limit-s", time_limit_s)
    check_start_alt_m("--start-alt-m", start_alt_m)
    check_handover_below_start(handover_alt_m, start_alt_m)
    non_negative("--person-separation-m", separation_m[0])
    non_negative("--vehicle-separation-m", separation_m[1])
    changed: dict = {}
    if policy_config is not None:
        if len(policies) != 1:
            raise ConfigError(f"--policy-config is one policy's: fly it with one --policy, not {', '.join(policies)}")
        (name,) = policies
        flown = policy_values(name, load_policy_config(name, policy_config, timing))
        changed = {k: v for k, v in flown.items() if v != policy_values(name, preset_config(name, timing))[k]}
    vehicle_profile = default_vehicle_profile(timing) if vehicle_profile is None else vehicle_profile
    validate_one_of("--vehicle-profile", vehicle_profile, VEHICLE_PROFILE_NAMES)
    validate_one_of("--gnss-denied", gnss_denied, BENCH_GNSS_DENIED)
    if gnss_denied != "off" and vehicle_profile == "ideal":
        raise ConfigError("--gnss-denied external-nav needs a vehicle that estimates its velocity: "
                          "--vehicle-profile realistic or harsh, not ideal")
    non_negative("--start-margin-m", start_margin_m)
    shared_timing.timing(timing)
    specs = tuple(worlds) if worlds else (world_spec or "synthetic",)
    plain = Variant(perception=check_perception(perception))
    if shifted is None:
        variants: tuple[Variant, ...] = (plain,)
    else:
        moved = Variant(perception=plain.perception, shift=shifted)
        variants = (moved,) if shift_only else (plain, moved)
    return Grid(worlds=specs, episodes=episodes, seed=seed, policies=tuple(policies),
                variants=variants, noise=noise, timing=timing,
                time_limit_s=float(time_limit_s), start_alt_m=float(start_alt_m), segmenter=segmenter,
                start_margin_m=float(start_margin_m), world_label=world_label or specs[0], extra={"seed_note": seed_note} if seed_note else {},
                vehicle_profile=vehicle_profile, handover_alt_m=float(handover_alt_m), policy_config=changed,
                separation_m=(float(separation_m[0]), float(separation_m[1])), close_look=bool(close_look),
                gnss_denied=gnss_denied)


def settings_from_args(args: argparse.Namespace) -> dict:
    """`make_grid`'s settings from the flags; what is left out is `dovesei.flight_defaults`' (as `up`)."""
    policies = parse_policies(args.policy)
    timing = args.timing or default_timing(policies)
    return dict(world_spec=args.world, worlds=suite_worlds(args.suite.strip()) if args.suite is not None else None,
                episodes=args.episodes, seed=args.seed, policies=policies, noise=args.noise, timing=timing,
                time_limit_s=paper_time_limit_s(timing) if args.time_limit_s is None else args.time_limit_s,
                start_alt_m=args.start_alt_m,
                start_margin_m=default_start_margin_m(policies) if args.start_margin_m is None else args.start_margin_m,
                segmenter=args.segmenter, perception=args.perception, vehicle_profile=args.vehicle_profile,
                handover_alt_m=args.handover_alt_m, policy_config=args.policy_config,
                separation_m=(args.person_separation_m, args.vehicle_separation_m),
                perception_shift=args.perception_shift, shift_only=args.shift_only, close_look=args.close_look, gnss_denied=args.gnss_denied, world_label=f"suite:{args.suite.strip()}" if args.suite is not None else "")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        doc = run_bench(jobs=args.jobs, out=args.out, engine=args.engine, address=args.address,
                        progress=not args.no_progress, **settings_from_args(args))
    except DoveseiError as exc:  # a user error: one line, no traceback
        print(f"dovesei bench: {exc}", file=sys.stderr)
        return 2
    print((args.out / "summary.md").read_text())
    print(json.dumps(doc["summary"]))
    print(wrote_line(args.out))
    return 0


def wrote_line(out: Path) -> str:
    """The last line of a bench: where its files are, the page first (what a person opens)."""
    names = [n for n in ("report.html", "results.json", "summary.md", "paths.png") if (out / n).is_file()]
    return f"dovesei bench: wrote {out.resolve()} ({', '.join(names)})"


if __name__ == "__main__":
    sys.exit(main())
