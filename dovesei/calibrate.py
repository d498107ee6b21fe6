"""`dovesei calibrate`: success rates of the policies against the simulated perception's noise.

For each timing preset and noise level, a full `dovesei bench` (resumable, in its own folder
under --out) with the same starts for every policy; then one table and one plot:

    calibration.json   {"cells": [{timing, noise, policy, episodes, safe, unsafe, timeout, ...}]}
    calibration.md     success counts per policy x preset x noise
    calibration.png    success rate vs noise, one line per policy and preset

The default noise of the simulated perception is chosen from this sweep: the level at which
`dovesei` vs `dovesei-nofocus` under the reference-timing preset come closest to the paper's
29/50 and 3/50 (see `paper_distance`).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from dovesei.bench import DEFAULT_POLICIES, paper_time_limit_s, parse_policies, run_bench
from dovesei.shared.errors import ConfigError

log = logging.getLogger(__name__)

PAPER_SUCCESS = {"dovesei": 29 / 50, "dovesei-nofocus": 3 / 50}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dovesei calibrate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", default="synthetic")
    p.add_argument("--noise", default="0,0.5,1,1.5,2", help="comma-separated noise levels")
    p.add_argument("--noise-real", default=None,
                   help="noise levels under real timing (default: --noise); its episodes cost ~20x more")
    p.add_argument("--timing", default="reference,real", help="comma-separated timing presets")
    p.add_argument("--episodes", type=int, default=50, help="starts per cell (reference timing)")
    p.add_argument("--episodes-real", type=int, default=None,
                   help="starts per cell under real timing (its 1200 s episodes cost 20x more; default: --episodes)")
    p.add_argument("--policy", default=DEFAULT_POLICIES)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    p.add_argument("--out", type=Path, default=Path("runs/calibration"))
    return p


def paper_distance(cells: list[dict], timing: str, noise: float) -> float | None:
    """Sum of |success rate - paper's| over the paper's two policies for one cell (None if missing)."""
    total = 0.0
    for pol, paper in PAPER_SUCCESS.items():
        cell = next((c for c in cells if c["timing"] == timing and c["noise"] == noise and c["policy"] == pol), None)
        if cell is None or not cell["episodes"]:
            return None
        total += abs(cell["safe"] / cell["episodes"] - paper)
    return total


def table_markdown(cells: list[dict], noises: list[float], timings: list[str], policies: list[str]) -> str:
    lines = ["| timing | policy | " + " | ".join(f"noise {n:g}" for n in noises) + " |",
             "|---|---|" + "---|" * len(noises)]
    for t in timings:
        for pol in policies:
            row = []
            for n in noises:
                c = next((c for c in cells if c["timing"] == t and c["noise"] == n and c["policy"] == pol), None)
                row.append("-" if c is None else f"{c['safe']}/{c['episodes']} (unsafe {c['unsafe']})")
            lines.append(f"| {t} | {pol} | " + " | ".join(row) + " |")
    return "\n".join(lines)


def plot(cells: list[dict], noises: list[float], timings: list[str], policies: list[str], out_png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for t, style in zip(timings, ("-", "--", ":")):
        for pol, colour in zip(policies, ("tab:blue", "tab:orange", "tab:green", "tab:red")):
            xs, ys = [], []
            for n in noises:
                c = next((c for c in cells if c["timing"] == t and c["noise"] == n and c["policy"] == pol), None)
                if c and c["episodes"]:
                    xs.append(n)
                    ys.append(100.0 * c["safe"] / c["episodes"])
            ax.plot(xs, ys, style, marker="o", color=colour, label=f"{pol} ({t} timing)")
    for pol, colour in zip(PAPER_SUCCESS, ("tab:blue", "tab:orange")):
        ax.axhline(100 * PAPER_SUCCESS[pol], color=colour, alpha=0.3, lw=4, label=f"paper: {pol}")
    ax.set_xlabel("simulated perception noise scale")
    ax.set_ylabel("safe landings (%)")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title("Success vs perception noise (simulated perception, automatic judge)")
    fig.tight_layout()
    fig.savefig(out_png)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        policies = parse_policies(args.policy)
        noises = [float(n) for n in args.noise.split(",") if n.strip()]
        noises_real = [float(n) for n in (args.noise_real or args.noise).split(",") if n.strip()]
        timings = [t.strip() for t in args.timing.split(",") if t.strip()]
        for t in timings:
            paper_time_limit_s(t)  # validates the preset name
        if not noises or not noises_real or any(n < 0 for n in noises + noises_real):
            raise ConfigError(f"--noise {args.noise!r}: give non-negative levels")
    except (ConfigError, ValueError) as exc:
        print(f"dovesei calibrate: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    cells: list[dict] = []
    for t in timings:
        episodes = args.episodes_real if (t == "real" and args.episodes_real) else args.episodes
        for n in (noises_real if t == "real" else noises):
            log.info("calibration cell: timing %s, noise %g, %d starts", t, n, episodes)
            doc = run_bench(world_spec=args.world, episodes=episodes, seed=args.seed, policies=policies, noise=n,
                            timing=t, time_limit_s=paper_time_limit_s(t), start_alt_m=100.0, jobs=args.jobs,
                            out=args.out / f"{t}-noise{n:g}", progress=sys.stderr.isatty())
            for pol, s in doc["summary"].items():
                cells.append({"timing": t, "noise": n, "policy": pol, **s})
            (args.out / "calibration.json").write_text(json.dumps({"cells": cells}, indent=1))
    ranked = sorted((d, n) for n in noises if (d := paper_distance(cells, "reference", n)) is not None)
    best = {"noise": ranked[0][1], "distance": round(ranked[0][0], 3)} if ranked else None
    all_noises = sorted(set(noises) | (set(noises_real) if "real" in timings else set()))
    table = table_markdown(cells, all_noises, timings, policies)
    text = ["# Calibration of the simulated perception", "",
            f"World `{args.world}`, start seed {args.seed}, limit = the paper's 1200 s on each preset's clock "
            f"(60 s of sim time under reference timing, 1200 s under real timing); {args.episodes} starts per cell"
            + (f" ({args.episodes_real} under real timing)" if args.episodes_real and "real" in timings else "")
            + "; each cell flies both policies from the same starts.", "",
            table, ""]
    if best:
        text.append(f"Closest to the paper's 29/50 vs 3/50 under reference timing: noise {best['noise']:g} "
                    f"(sum of success-rate differences {best['distance']}).")
    (args.out / "calibration.md").write_text("\n".join(text) + "\n")
    (args.out / "calibration.json").write_text(json.dumps({"cells": cells, "closest_to_paper": best}, indent=1))
    try:
        plot(cells, all_noises, timings, policies, args.out / "calibration.png")
    except ImportError as exc:
        log.warning("no calibration.png: %s", exc)
    print("\n".join(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
