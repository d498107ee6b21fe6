"""`dovesei sweep FILE`: one experiment over a grid of policies x perception profiles x worlds x
prompt sets, described in a small YAML or JSON file, on either engine, resumable.

    # sweep.yaml
    worlds: [synthetic, dubai]        # or: suite: default
    episodes: 20                      # starts per world, the same for every cell
    seed: 0
    timing: reference                 # one preset per sweep (its limits differ)
    policies: [dovesei, dovesei-nofocus]
    perception: [clean, realistic, harsh]
    prompts:                          # name -> prompt set; null = the reference prompts
      reference: null
      lawns-only: {positive: [grass, lawn], negative: [building, road, water, tree]}
    perception_shift: [null, "0.6,1.6,0.8"]   # optional axis: null = plain; "A_LO,A_HI,B" as in
                                      # `dovesei bench --perception-shift` (a, b drawn per start)
    # optional: noise, time_limit_s, start_alt_m, vehicle_profile (ideal | realistic | harsh; default
    # as `dovesei bench` at this timing)

Every cell flies the same starts. The grid is one bench run (`dovesei.bench.run.run_grid`), so
it shares the journal, resuming and engines of `dovesei bench`; the output folder holds
results.json (each episode tagged with world, policy, perception, prompts), summary.md with one
row per cell and Wilson 95 % intervals, and sweep.png (success per cell with its interval).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from dovesei.bench import check_perception, paper_time_limit_s, parse_policies, suite_worlds
from dovesei.bench.run import Grid, Variant, run_grid
from dovesei.bench.shift import parse_shift
from dovesei.episode import prompt_set
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import timing as shared_timing
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.validate import in_range, one_of, positive
from dovesei.sim.estimator import VEHICLE_PROFILE_NAMES, default_vehicle_profile
from dovesei.sim.starts import check_start_alt_m

log = logging.getLogger(__name__)

KEYS = {"worlds", "suite", "episodes", "seed", "timing", "policies", "perception", "prompts", "noise", "time_limit_s",
        "start_alt_m", "vehicle_profile", "perception_shift"}


def _shifts(doc: dict) -> list[tuple[float, float, float] | None]:
    """The shift axis: null (plain) or "A_LO,A_HI,B" / [A_LO, A_HI, B] entries, each checked."""
    value = doc.get("perception_shift", [None])
    if not isinstance(value, list) or not value:
        raise ConfigError(f"sweep file: 'perception_shift' must be a non-empty list of null or \"A_LO,A_HI,B\", "
                          f"got {value!r}")
    out = [None if v is None else parse_shift(v, "sweep file: 'perception_shift'") for v in value]
    return list(dict.fromkeys(out))


def _names(doc: dict, key: str, default: list[str] | None = None) -> list[str]:
    value = doc.get(key, default)
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",")]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v.strip() for v in value):
        raise ConfigError(f"sweep file: {key!r} must be a non-empty list of names, got {value!r}")
    return list(dict.fromkeys(v.strip() for v in value))


def _int(doc: dict, key: str, default: int, lo: int) -> int:
    value = doc.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ConfigError(f"sweep file: {key!r} must be an integer >= {lo}, got {value!r}")
    return value


def read_sweep_file(path: Path) -> dict:
    """The file's mapping (YAML for .yaml/.yml, else JSON), or one ConfigError naming the file."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"sweep file {str(path)!r}: {exc.strerror or exc}") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise ConfigError(f"sweep file {str(path)!r}: YAML needs PyYAML (pip install \"dovesei[scale]\"), "
                              "or write the same grid as JSON") from None
        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"sweep file {str(path)!r}: not valid YAML ({str(exc).splitlines()[0]})") from None
    else:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"sweep file {str(path)!r}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"sweep file {str(path)!r}: expected a mapping of settings, got {type(doc).__name__}")
    return doc


def grid_from_doc(doc: dict) -> Grid:
    """The sweep's grid, every value checked (unknown keys, names, numbers) before any work."""
    unknown = sorted(set(doc) - KEYS)
    if unknown:
        raise ConfigError(f"sweep file: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(KEYS))}")
    if "worlds" in doc and "suite" in doc:
        raise ConfigError("sweep file: give 'worlds' or 'suite', not both")
    if "suite" in doc:
        if not isinstance(doc["suite"], str):
            raise ConfigError(f"sweep file: 'suite' must be a name, got {doc['suite']!r}")
        worlds, label = suite_worlds(doc["suite"].strip()), f"suite:{doc['suite'].strip()}"
    else:
        worlds = tuple(_names(doc, "worlds", ["synthetic"]))
        label = ",".join(worlds)
    timing = doc.get("timing", shared_timing.DEFAULT_TIMING)
    if not isinstance(timing, str):
        raise ConfigError(f"sweep file: 'timing' must be one preset name, got {timing!r}")
    shared_timing.timing(timing)
    policies = parse_policies(",".join(_names(doc, "policies", ["dovesei", "dovesei-nofocus"])))
    perceptions = [check_perception(p) for p in _names(doc, "perception", ["realistic"])]
    prompts = doc.get("prompts", {"reference": None})
    if not isinstance(prompts, dict) or not prompts:
        raise ConfigError(f"sweep file: 'prompts' must map names to prompt sets, got {prompts!r}")
    prompt_sets: dict[str, dict | None] = {}
    for name, value in prompts.items():
        if value is not None and not isinstance(value, dict):
            raise ConfigError(f"sweep file: prompt set {name!r} must be {{positive, negative[, template]}} or null")
        if value is not None:
            extra = sorted(set(value) - {"positive", "negative", "template"})
            if extra:
                raise ConfigError(f"sweep file: prompt set {name!r}: unknown key(s) {', '.join(extra)}")
            ps = prompt_set(value)  # checks words and template the way the segmenter does
            value = {"positive": list(ps.positive), "negative": list(ps.negative), "template": ps.template}
        prompt_sets[str(name)] = value
    noise = doc.get("noise")
    if noise is not None:
        noise = in_range("sweep file: 'noise'", noise, 0.0, 4.0)
    limit = doc.get("time_limit_s")
    limit = paper_time_limit_s(timing) if limit is None else positive("sweep file: 'time_limit_s'", limit)
    variants = tuple(Variant(perception=p, prompts_name=n, prompts=v, labelled=True, shift=s)
                     for p in perceptions for n, v in prompt_sets.items() for s in _shifts(doc))
    return Grid(worlds=worlds, episodes=_int(doc, "episodes", 20, 1), seed=_int(doc, "seed", 0, 0),
                policies=tuple(policies), variants=variants, noise=noise, timing=timing, time_limit_s=float(limit),
                start_alt_m=check_start_alt_m("sweep file: 'start_alt_m'", doc.get("start_alt_m", 100.0)),
                world_label=label, extra={"sweep": True},
                vehicle_profile=one_of("sweep file: 'vehicle_profile'",
                                       doc.get("vehicle_profile", default_vehicle_profile(timing)), VEHICLE_PROFILE_NAMES))


def plot_sweep(rows: list[dict], out_png: Path, title: str) -> None:
    """Success rate per cell (policy / perception / prompts) with its Wilson 95 % interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['policy']}\n{r['perception']} / {r['prompts']}" + (f"\nshift {r['shift']}" if r.get("shift") else "")
              for r in rows]
    rates = [100.0 * r["safe"] / r["episodes"] if r["episodes"] else 0.0 for r in rows]
    lo = [rate - 100 * r["success_ci95"][0] for rate, r in zip(rates, rows)]
    hi = [100 * r["success_ci95"][1] - rate for rate, r in zip(rates, rows)]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(rows) + 2), 4.5), dpi=110)
    ax.bar(range(len(rows)), rates, yerr=[lo, hi], capsize=4, color="tab:blue", alpha=0.8)
    ax.set_xticks(range(len(rows)), labels, fontsize=7, rotation=30, ha="right")
    ax.set_ylabel("safe landings (%), Wilson 95 %")
    ax.set_ylim(0, 100)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out_png)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei sweep", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", type=Path, help="the grid, YAML (.yaml/.yml) or JSON")
    p.add_argument("--out", type=Path, default=Path("runs/sweep"), help="output folder (resumes if it exists)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="episodes in parallel")
    p.add_argument("--engine", default="local", choices=("local", "ray"))
    p.add_argument("--address", default=None, help="Ray cluster address (with --engine ray)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--vehicle-profile", choices=VEHICLE_PROFILE_NAMES,
                   help="what the vehicle reports and how it flies (default: the file's vehicle_profile, else as "
                        "`dovesei bench` at the file's timing)")
    return p


def run_sweep(path: Path, *, out: Path, jobs: int, engine: str = "local", address: str | None = None,
              progress: bool = True, vehicle_profile: str | None = None) -> dict:
    if jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, got {jobs}")
    if address and engine != "ray":
        raise ConfigError("--address names a Ray cluster: use it with --engine ray")
    doc = read_sweep_file(path)
    if vehicle_profile is not None:  # the flag wins over the file
        doc = {**doc, "vehicle_profile": vehicle_profile}
    grid = grid_from_doc(doc)
    doc = run_grid(grid, out=out, workers=jobs, engine=engine, address=address, progress=progress,
                   title="dovesei sweep")
    try:
        plot_sweep(doc["per_variant"], out / "sweep.png",
                   f"{grid.world_label}: {grid.episodes} starts per world, timing {grid.timing}")
    except ImportError as exc:  # matplotlib is a dev extra
        log.warning("no sweep.png: %s", exc)
    return doc


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        run_sweep(args.file, out=args.out, jobs=args.jobs, engine=args.engine, address=args.address,
                  progress=not args.no_progress, vehicle_profile=args.vehicle_profile)
    except DoveseiError as exc:
        print(f"dovesei sweep: {exc}", file=sys.stderr)
        return 2
    print((args.out / "summary.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
