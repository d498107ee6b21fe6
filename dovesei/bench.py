"""`dovesei bench`: the paper's experiment, automatically judged and resumable.

N seeded start positions uniform over the world at 100 m, the same starts for every policy, one
episode per (policy, start) run by the in-process runner (`dovesei.episode`, the same service
cores as `dovesei up`), in parallel worker processes. Each finished episode is appended to
`episodes.jsonl` at once, so an interrupted bench continues where it stopped. At the end:

    results.json   {"episodes": [...], "summary": {policy: {...}}, "config": {...}}
    summary.md     a table shaped like the paper's Table I, plus the unsafe count
    paths.png      every policy's path from the same starts over the world image
    tracks/        one .npy path per episode (t_s, x_m, y_m, alt_agl_m)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from dovesei.shared.errors import ConfigError

log = logging.getLogger(__name__)

DEFAULT_POLICIES = "dovesei,dovesei-nofocus"
PAPER_TIME_LIMIT_S = 1200.0
SUMMARY_KEYS = ("episodes", "safe", "unsafe", "timeout", "out_of_world", "error")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dovesei bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", default="synthetic", help="synthetic[:seed=N,...] or a world folder")
    p.add_argument("--episodes", type=int, default=50, help="start positions (each flown by every policy)")
    p.add_argument("--seed", type=int, default=0, help="seed of the start positions and of the perception noise")
    p.add_argument("--policy", default=DEFAULT_POLICIES, help="comma-separated policies")
    p.add_argument("--segmenter", default="sim", choices=("sim",),
                   help="perception backend (the bench flies simulated perception; CLIPSeg runs in `dovesei up`)")
    p.add_argument("--noise", type=float, default=None, help="simulated perception noise scale (default: calibrated)")
    p.add_argument("--timing", default="reference", choices=("reference", "real"), help="policy timing preset")
    p.add_argument("--time-limit-s", type=float, default=None,
                   help="sim-time limit of an episode (default: the paper's 1200 s on the preset's clock: "
                        "1200 s with --timing real, 1200 x 0.05 = 60 s with --timing reference)")
    p.add_argument("--start-alt-m", type=float, default=100.0)
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="episodes in parallel")
    p.add_argument("--out", type=Path, default=Path("runs/bench"), help="output folder (resumes if it exists)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    return p


def parse_policies(text: str) -> list[str]:
    from dovesei.controller.policies import policy_names

    names = [p.strip() for p in text.split(",") if p.strip()]
    known = policy_names()
    unknown = [n for n in names if n not in known]
    if not names or unknown:
        raise ConfigError(f"--policy {text!r}: unknown {unknown or 'empty list'}; known: {', '.join(known)}")
    return list(dict.fromkeys(names))


def paper_time_limit_s(timing: str) -> float:
    """The paper's 1200 s limit on the clock of a timing preset.

    The reference's 1200 s ran on the wall clock, like its other timers, while its simulator ran at
    ~5 % of real time: the UAV had ~60 s of sim time. The `reference` preset scales every timer by
    that factor, and so this limit; under `real` timing the limit is 1200 true seconds.
    """
    from dovesei.controller.policies.config import timing_preset

    return PAPER_TIME_LIMIT_S * timing_preset(timing).timer_scale


# ---- worker side: one world per process, loaded once ----
_WORLD = None


def _init_worker(world_spec: str) -> None:
    global _WORLD
    from dovesei.sim.world import load_world

    logging.getLogger().setLevel(logging.WARNING)  # workers report through results, not logs
    # One thread per worker: --jobs workers already fill the cores, and OpenCV's own thread pool
    # on top of them only adds contention (results do not depend on it).
    import cv2

    cv2.setNumThreads(1)
    _WORLD = load_world(world_spec)


def _use_world(world) -> None:
    global _WORLD
    _WORLD = world


def _run_job(job: dict) -> dict:
    from dovesei.episode import EpisodeSpec, run_episode
    from dovesei.sim.starts import Start

    start = Start(**job["start"])
    spec = EpisodeSpec(policy=job["policy"], start=start, timing=job["timing"], seed=job["seed"],
                       noise=job["noise"], time_limit_s=job["time_limit_s"])
    t0 = time.perf_counter()
    try:
        rec = run_episode(_WORLD, spec)
    except Exception as exc:  # an episode that crashes is recorded as 'error', the bench goes on
        log.exception("episode %s/%d failed", job["policy"], job["index"])
        return {**_record_base(job), "outcome": "error", "sim_time_s": 0.0, "path_length_m": 0.0,
                "wall_time_s": time.perf_counter() - t0, "detail": f"{type(exc).__name__}: {exc}"}
    track_path = Path(job["tracks_dir"]) / f"{job['policy']}-{job['index']:04d}.npy"
    np.save(track_path, rec.track.astype(np.float32))
    r = rec.result
    return {**_record_base(job), "outcome": r.outcome, "sim_time_s": round(r.sim_time_s, 3),
            "path_length_m": round(r.path_length_m, 3), "wall_time_s": round(rec.wall_time_s, 3),
            "final": {"x_m": round(r.final_x_m, 3), "y_m": round(r.final_y_m, 3), "alt_m": round(r.final_alt_m, 3)},
            "classes_found": list(r.classes_found), "detail": r.detail,
            "closest_unsafe_m": round(r.closest_unsafe_m, 3) if r.closest_unsafe_valid else None}


def _record_base(job: dict) -> dict:
    return {"policy": job["policy"], "index": job["index"], "seed": job["seed"],
            "start": {"x_m": job["start"]["x_m"], "y_m": job["start"]["y_m"], "alt_m": job["start"]["alt_m"]}}


# ---- driver side ----
def summarise(episodes: Iterable[dict], policies: Sequence[str]) -> dict[str, dict]:
    """Counts per outcome and the paper's means (time and path over SUCCESSFUL episodes)."""
    summary: dict[str, dict] = {}
    for pol in policies:
        eps = [e for e in episodes if e["policy"] == pol]
        safe = [e for e in eps if e["outcome"] == "safe"]
        s = {k: 0 for k in SUMMARY_KEYS}
        s["episodes"] = len(eps)
        for e in eps:
            s[e["outcome"]] += 1
        s["mean_sim_time_s"] = round(float(np.mean([e["sim_time_s"] for e in safe])), 1) if safe else None
        s["mean_path_length_m"] = round(float(np.mean([e["path_length_m"] for e in safe])), 1) if safe else None
        s["mean_wall_time_s"] = round(float(np.mean([e["wall_time_s"] for e in eps])), 2) if eps else None
        summary[pol] = s
    return summary


def summary_markdown(summary: dict[str, dict], config: dict) -> str:
    lines = [
        "# dovesei bench",
        "",
        f"World `{config['world']}`, {config['episodes']} starts at {config['start_alt_m']:.0f} m (seed {config['seed']}), "
        f"limit {config['time_limit_s']:.0f} s of sim time, timing preset `{config['timing']}`, "
        f"perception `{config['segmenter']}` (simulated, noise {config['noise']}). Success = reaching the "
        "hand-over altitude (20 m) with the 2 m footprint disk on safe classes, judged on the label map.",
        "",
        "| policy | success | unsafe | timeout | out of world | error | avg. time (s) | avg. distance (m) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for pol, s in summary.items():
        n = s["episodes"]
        fmt = (lambda v: "-" if v is None else f"{v:.1f}")
        lines.append(f"| {pol} | {s['safe']}/{n} | {s['unsafe']}/{n} | {s['timeout']}/{n} | {s['out_of_world']}/{n} | "
                     f"{s['error']}/{n} | {fmt(s['mean_sim_time_s'])} | {fmt(s['mean_path_length_m'])} |")
    lines += ["", "Averages are over successful episodes, as in the paper's Table I (time in sim seconds, "
              "distance = horizontal path length).", ""]
    return "\n".join(lines)


def _config_key(config: dict) -> str:
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()[:16]


def _load_done(path: Path, key: str) -> dict[tuple[str, int], dict]:
    done: dict[tuple[str, int], dict] = {}
    if not path.exists():
        return done
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            log.warning("%s line %d is truncated (interrupted write); that episode runs again", path, n)
            continue
        if rec.get("config_key") != key:
            raise ConfigError(f"{path.parent} holds a bench with other settings; use another --out or delete it")
        done[(rec["policy"], rec["index"])] = rec
    return done


class Progress:
    """One stderr line: episodes done and the running success counts per policy."""

    def __init__(self, total: int, policies: Sequence[str], enabled: bool) -> None:
        self.total, self.policies, self.enabled = total, policies, enabled
        self.t0 = time.monotonic()

    def show(self, episodes: list[dict]) -> None:
        if not self.enabled:
            return
        done = len(episodes)
        width = 24
        bar = "#" * int(width * done / max(1, self.total))
        counts = "  ".join(
            f"{p}: {sum(e['outcome'] == 'safe' for e in episodes if e['policy'] == p)} safe"
            f"/{sum(e['policy'] == p for e in episodes)}" for p in self.policies)
        sys.stderr.write(f"\r[{bar:<{width}}] {done}/{self.total}  {counts}  {time.monotonic() - self.t0:.0f}s ")
        sys.stderr.flush()
        if done == self.total:
            sys.stderr.write("\n")


def run_bench(*, world_spec: str, episodes: int, seed: int, policies: Sequence[str], noise: float, timing: str,
              time_limit_s: float, start_alt_m: float, jobs: int, out: Path, segmenter: str = "sim",
              progress: bool = True) -> dict:
    """Run (or resume) a bench into `out`; returns the results.json content."""
    from dovesei.sim.starts import generate_starts
    from dovesei.sim.world import load_world

    if episodes < 1 or jobs < 1:
        raise ConfigError("--episodes and --jobs must be at least 1")
    world = load_world(world_spec)
    starts = generate_starts(world, episodes, seed, alt_m=start_alt_m)
    config = {"world": world_spec, "episodes": episodes, "seed": seed, "policies": list(policies), "noise": noise,
              "timing": timing, "time_limit_s": time_limit_s, "start_alt_m": start_alt_m, "segmenter": segmenter}
    key = _config_key(config)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tracks").mkdir(exist_ok=True)
    journal = out / "episodes.jsonl"
    done = _load_done(journal, key)
    jobs_todo = []
    for i, st in enumerate(starts):
        for pol in policies:
            if (pol, i) in done:
                continue
            jobs_todo.append({"policy": pol, "index": i, "seed": seed * 100003 + i, "noise": noise, "timing": timing,
                              "time_limit_s": time_limit_s, "tracks_dir": str(out / "tracks"),
                              "start": {"x_m": round(st.x_m, 3), "y_m": round(st.y_m, 3), "alt_m": st.alt_m}})
    if done:
        log.info("resuming: %d episodes already done, %d to go", len(done), len(jobs_todo))
    results = list(done.values())
    bar = Progress(len(starts) * len(policies), policies, progress)
    bar.show(results)
    with journal.open("a") as fh:
        def keep(rec: dict) -> None:
            rec["config_key"] = key
            fh.write(json.dumps(rec) + "\n")
            fh.flush()  # a crash loses at most the episode in flight
            results.append(rec)
            bar.show(results)

        if jobs == 1 or len(jobs_todo) == 1:
            _use_world(world)  # in this process: reuse the loaded world, keep the caller's logging
            for job in jobs_todo:
                keep(_run_job(job))
        elif jobs_todo:
            ctx = mp.get_context("spawn")  # no inherited Zenoh/torch state in workers
            with ctx.Pool(jobs, initializer=_init_worker, initargs=(world_spec,)) as pool:
                for rec in pool.imap_unordered(_run_job, jobs_todo):
                    keep(rec)
    results.sort(key=lambda e: (policies.index(e["policy"]), e["index"]))
    episodes_out = [{k: v for k, v in e.items() if k != "config_key"} for e in results]
    doc = {"episodes": episodes_out, "summary": summarise(episodes_out, policies), "config": config}
    (out / "results.json").write_text(json.dumps(doc, indent=1))
    (out / "summary.md").write_text(summary_markdown(doc["summary"], config))
    try:
        from dovesei.pictures.plots import plot_bench_paths

        plot_bench_paths(world, doc, out / "tracks", out / "paths.png")
    except ImportError as exc:  # matplotlib is a dev extra; the numbers matter more than the picture
        log.warning("no paths.png: %s", exc)
    return doc


def main(argv: list[str] | None = None) -> int:
    from dovesei.segmenter.simulated import SimPerceptionParams

    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        policies = parse_policies(args.policy)
        noise = SimPerceptionParams().noise if args.noise is None else args.noise
        limit_s = paper_time_limit_s(args.timing) if args.time_limit_s is None else args.time_limit_s
        doc = run_bench(world_spec=args.world, episodes=args.episodes, seed=args.seed, policies=policies, noise=noise,
                        timing=args.timing, time_limit_s=limit_s, start_alt_m=args.start_alt_m,
                        jobs=args.jobs, out=args.out, segmenter=args.segmenter, progress=not args.no_progress)
    except ConfigError as exc:
        print(f"dovesei bench: {exc}", file=sys.stderr)
        return 2
    print((args.out / "summary.md").read_text())
    print(json.dumps(doc["summary"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
