"""`dovesei faults`: the fault suite. Each run flies a short episode (real time; lockstep for the
`-lockstep` variants) with the three services as real processes through a loopback router, injects
one fault mid-descent and checks the rules of `dovesei.faults.checks` (no descent while blind, hold
within one tick, resumption, no hand-over above the hand-over altitude, a report that names the
fault when it should).

    dovesei faults [--runs N] [--fault NAME,...] [--seed S] [--out DIR] [--json]

    for each fault, for i in 0..N-1: run_scenario(fault, seed + i) --> <out>/<fault>-<i>/run.json,
                                     logs/<service>.log
    --> a table per fault and the totals (runs, void, unsafe, mid_air_handovers, violations per
        fault) in <out>/faults.json (and on stdout with --json)

A run whose fault was never injected (the vehicle left the world or landed first) is void: counted
as such, never as violations, and no evidence either way.

Exit codes: 0 every run kept every rule and every fault was injected at least once, 1 some run
broke one or some fault was never injected at all (nothing tested it), 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

from dovesei.faults.scenario import FAULTS, RunResult, run_scenario
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.errors import ConfigError
from dovesei.sim.estimator import VEHICLE_PROFILE_NAMES

log = logging.getLogger("dovesei.faults")


def parse_faults(text: str | None) -> list[str]:
    if not text:
        return list(FAULTS)
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in FAULTS]
    if unknown or not names:
        raise ConfigError(f"--fault {text!r}: unknown {', '.join(unknown) or '(empty)'}; choose among "
                          f"{', '.join(FAULTS)}")
    return names


def totals(results: Sequence[RunResult]) -> dict:
    per: dict[str, dict] = {}
    for r in results:
        p = per.setdefault(r.fault, {"runs": 0, "void": 0, "unsafe": 0, "mid_air_handovers": 0, "violations": 0,
                                     "held": 0, "resumed": 0, "exit_codes": {}})
        p["runs"] += 1
        p["void"] += int(r.void is not None)
        p["unsafe"] += int(r.unsafe)
        p["mid_air_handovers"] += int(r.mid_air_handover)
        p["violations"] += len(r.violations)
        p["held"] += int(r.held)
        p["resumed"] += int(bool(r.resumed))
        p["exit_codes"][str(r.exit_code)] = p["exit_codes"].get(str(r.exit_code), 0) + 1
    return {"runs": len(results), "void": sum(r.void is not None for r in results),
            "untested": sorted(name for name, p in per.items() if p["void"] == p["runs"]),
            "unsafe": sum(r.unsafe for r in results),
            "mid_air_handovers": sum(r.mid_air_handover for r in results),
            "violations": sum(len(r.violations) for r in results), "per_fault": per}


def table(summary: dict) -> str:
    rows = [f"{'fault':<24} {'runs':>4} {'void':>4} {'unsafe':>6} {'mid-air':>7} {'viol.':>5} {'held':>4} "
            f"{'resumed':>7}  exit codes"]
    for name, p in summary["per_fault"].items():
        codes = ", ".join(f"{c}x{n}" for c, n in sorted(p["exit_codes"].items()))
        resumed = str(p["resumed"]) if FAULTS[name].resumes else "-"
        rows.append(f"{name:<24} {p['runs']:>4} {p['void']:>4} {p['unsafe']:>6} {p['mid_air_handovers']:>7} "
                    f"{p['violations']:>5} {p['held']:>4} {resumed:>7}  {codes}")
    rows.append(f"{'total':<24} {summary['runs']:>4} {summary['void']:>4} {summary['unsafe']:>6} "
                f"{summary['mid_air_handovers']:>7} {summary['violations']:>5}")
    if summary["untested"]:
        rows.append(f"never injected (every run void, nothing tested): {', '.join(summary['untested'])}")
    return "\n".join(rows)


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei faults", description=__doc__.split("\n\n")[0],
                                epilog=f"faults: {'; '.join(f'{f.name}: {f.text}' for f in FAULTS.values())}")
    p.add_argument("--runs", type=int, default=1, help="runs per fault (seeds S, S+1, ...)")
    p.add_argument("--fault", help=f"comma list (default: all): {','.join(FAULTS)}")
    p.add_argument("--seed", type=int, default=0, help="first seed (start position and relay losses)")
    p.add_argument("--out", type=Path, help="folder for the runs (default: runs/faults-<timestamp>)")
    p.add_argument("--json", action="store_true", help="print the totals as JSON instead of the table")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.add_argument("--vehicle-profile", choices=VEHICLE_PROFILE_NAMES,
                   help="the simulated vehicle the faults are flown with (default: as `dovesei up` at the faults' "
                        "timing)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        names = parse_faults(args.fault)
        if args.runs < 1:
            raise ConfigError(f"--runs {args.runs}: at least 1")
        if args.seed < 0:
            raise ConfigError(f"--seed {args.seed}: a seed is >= 0")
        out = args.out or Path("runs") / f"faults-{datetime.now().strftime('%Y%m%d-%H%M%S')}"
        if out.exists() and not out.is_dir():
            raise ConfigError(f"--out {str(out)!r} is a file; give a folder")
    except ConfigError as exc:
        print(f"dovesei faults: {exc}", file=sys.stderr)
        return 2
    results: list[RunResult] = []
    t0 = time.monotonic()
    for i in range(args.runs):
        for name in names:
            run_out = out / f"{name}-{i}"
            r = run_scenario(FAULTS[name], args.seed + i, run_out, vehicle_profile=args.vehicle_profile)
            (run_out / "run.json").write_text(json.dumps(r.to_dict(), indent=1, default=str))
            results.append(r)
            status = "ok" if not r.violations else f"{len(r.violations)} violation(s): {r.violations[0]}"
            if r.void is not None:
                status = f"void, {r.void}" + ("" if not r.violations else f"; {status}")
            print(f"{name} seed {r.seed}: exit {r.exit_code}, {r.outcome}, {r.wall_s:.0f} s: {status}",
                  file=sys.stderr)
    summary = totals(results)
    summary["wall_s"] = round(time.monotonic() - t0, 1)
    summary["command"] = "dovesei faults " + " ".join(argv if argv is not None else sys.argv[2:])
    out.mkdir(parents=True, exist_ok=True)
    (out / "faults.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1) if args.json else table(summary))
    return 0 if summary["violations"] == 0 and not summary["untested"] else 1


if __name__ == "__main__":
    sys.exit(main())
