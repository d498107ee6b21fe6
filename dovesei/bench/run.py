"""Running a bench grid: worlds x starts x policies (x perception profiles x prompt sets for a
sweep), journalled so an interrupted run continues where it stopped.

`run_grid` is the one driver: `dovesei bench` calls it with one perception profile and the
default prompts, `dovesei sweep` with several. Every finished episode is appended to
`episodes.jsonl` at once (tagged with the hash of the settings, so a folder never mixes two
benches), its track saved under `tracks/`, and the progress bar redrawn. At the end
`results.json`, `summary.md` and the path pictures are written from the whole journal.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dovesei.bench import engines, shift, stats
from dovesei.flight_defaults import starts as bench_starts
from dovesei.pictures.html import write_bench_page
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.mission import HANDOVER_ALT_M, PERSON_SEPARATION_M, SAFETY_RADIUS_M, VEHICLE_SEPARATION_M
from dovesei.sim.judge import CANOPY_NEAR_M
from dovesei.sim.world import load_world, require_judged

log = logging.getLogger(__name__)

EPISODE_SEED_STRIDE = 100003  # episode seed = seed * stride + start index: disjoint across bench seeds


def episode_seed(seed: int, index: int) -> int:
    return seed * EPISODE_SEED_STRIDE + index


@dataclass(frozen=True)
class Variant:
    """One perception profile and prompt set an episode is flown with (a sweep has several).

    `label` is None for the bench's single variant: its records keep the release's fields.
    """

    perception: str
    prompts_name: str = "reference"
    prompts: dict | None = None  # {"positive": [...], "negative": [...], "template": "..."}; None = the reference
    labelled: bool = False
    shift: tuple[float, float, float] | None = None  # --perception-shift (A_LO, A_HI, B); None = plain


@dataclass(frozen=True)
class Grid:
    """Everything that decides the episodes of one run (and so its settings hash)."""

    worlds: tuple[str, ...]
    episodes: int
    seed: int
    policies: tuple[str, ...]
    variants: tuple[Variant, ...]
    noise: float | None
    timing: str
    time_limit_s: float
    start_alt_m: float
    world_label: str = ""  # what --world/--suite said, for the summary
    start_margin_m: float = 5.0  # starts lie this far inside the footprint-on-the-map area
    segmenter: str = "sim"
    extra: dict = field(default_factory=dict)  # more settings that belong in the hash (e.g. the sweep file's)
    vehicle_profile: str = "ideal"  # dovesei.sim.estimator: what the vehicle reports and how it flies
    handover_alt_m: float = HANDOVER_ALT_M  # where every episode ends and is judged (controller, policy, judge)
    # --policy-config: the constants a file changed from the preset's ({} = none), for its one policy.
    policy_config: dict = field(default_factory=dict)
    # The judge's separations from people and vehicles (0: that rule off).
    separation_m: tuple[float, float] = (PERSON_SEPARATION_M, VEHICLE_SEPARATION_M)
    close_look: bool = True  # clearance looks at its spot at full resolution before committing (issue 24)
    gnss_denied: str = "off"  # "external-nav": the autopilot fuses the camera's visual velocity (SimConfig.external_nav)

    @property
    def shifted(self) -> bool:
        """Whether any variant flies a perception shift (then every record names its shift)."""
        return any(v.shift is not None for v in self.variants)

    def config(self) -> dict:
        return {"world": self.world_label or self.worlds[0], "worlds": list(self.worlds), "episodes": self.episodes,
                "seed": self.seed, "policies": list(self.policies), "noise": self.noise, "timing": self.timing,
                "time_limit_s": self.time_limit_s, "start_alt_m": self.start_alt_m, "segmenter": self.segmenter,
                # Only a non-default margin enters the settings (and their hash): older benches resume.
                **({"start_margin_m": self.start_margin_m} if self.start_margin_m != 5.0 else {}),
                # Likewise `ideal` (the sim before profiles) stays out: its benches resume and hash as before.
                **({"vehicle_profile": self.vehicle_profile} if self.vehicle_profile != "ideal" else {}),
                # And the default hand-over: benches flown before it was a setting resume and hash as before.
                **({"handover_alt_m": self.handover_alt_m} if self.handover_alt_m != HANDOVER_ALT_M else {}),
                **({"policy_config": self.policy_config} if self.policy_config else {}),
                "separation_m": list(self.separation_m),
                # clearance with and without close looks flies differently: such benches never resume
                # one from the other (benches without the key predate the close look).
                **({"close_look": self.close_look} if "clearance" in self.policies else {}),
                # Only a vehicle on the camera's velocity enters the settings: benches before it resume.
                **({"gnss_denied": self.gnss_denied} if self.gnss_denied != "off" else {}),
                # Likewise a run without a perception shift hashes as before.
                **({"perception_shift": [shift.label(v.shift) for v in self.variants]} if self.shifted else {}),
                "perception": [v.perception for v in self.variants] if len(self.variants) > 1 else self.variants[0].perception,
                "prompts": {v.prompts_name: v.prompts for v in self.variants}, **self.extra}


def _config_key(config: dict) -> str:
    # The episode count is left out: start i does not depend on how many starts are drawn, so a
    # bench grown from 10 to 50 starts keeps its first 10 episodes and flies only the new ones.
    kept = {k: v for k, v in config.items() if k != "episodes"}
    return hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()[:16]


def _record_key(rec: dict) -> tuple:
    return (rec.get("world"), rec["policy"], rec.get("perception"), rec.get("prompts"), rec.get("shift"), rec["index"])


def load_journal(path: Path, key: str) -> dict[tuple, dict]:
    done: dict[tuple, dict] = {}
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
        done[_record_key(rec)] = rec
    return done


def world_slug(i: int, spec: str) -> str:
    return f"{i:02d}-" + re.sub(r"[^A-Za-z0-9]+", "-", Path(spec).name if "/" in spec else spec).strip("-")[:40]


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


def load_worlds(specs: Sequence[str]) -> dict:
    """Every world of the run, loaded before anything is written (a bad one fails the run early)."""
    for spec in specs:
        require_judged(spec)  # before any download: a label-less world is never judged
    return {spec: load_world(spec) for spec in specs}


def plan_jobs(grid: Grid, worlds: dict, out: Path) -> list[dict]:
    """Every episode of the grid as a job dict, in a fixed order (world, start, variant, policy)."""
    jobs = []
    for wi, spec in enumerate(grid.worlds):
        for i, st in enumerate(bench_starts(worlds[spec], grid.episodes, grid.seed, alt_m=grid.start_alt_m,
                                            margin_m=grid.start_margin_m)):
            for var in grid.variants:
                for pol in grid.policies:
                    jobs.append({
                        "world": spec, "world_index": wi, "policy": pol, "index": i, "seed": episode_seed(grid.seed, i),
                        "noise": grid.noise, "timing": grid.timing, "time_limit_s": grid.time_limit_s,
                        "perception": var.perception, "prompts": var.prompts,
                        "vehicle_profile": grid.vehicle_profile, "handover_alt_m": grid.handover_alt_m,
                        "policy_config": grid.policy_config or None, "separation_m": list(grid.separation_m),
                        "close_look": grid.close_look,
                        "gnss_denied": grid.gnss_denied,
                        "perception_label": var.perception if var.labelled else None,
                        "prompts_label": var.prompts_name if var.labelled else None,
                        "shift_label": shift.label(var.shift) if grid.shifted else None,
                        "perception_shift": None if var.shift is None else dict(zip(
                            ("a", "b"), shift.draw(var.shift, grid.seed, wi, i))),
                        "start": {"x_m": round(st.x_m, 3), "y_m": round(st.y_m, 3), "alt_m": st.alt_m}})
    return jobs


def _track_path(out: Path, grid: Grid, rec: dict) -> Path:
    parts = [] if len(grid.worlds) == 1 else [world_slug(grid.worlds.index(rec["world"]), rec["world"])]
    if rec.get("perception") is not None or rec.get("prompts") is not None:
        parts.append(f"{rec.get('perception')}-{rec.get('prompts')}")
    if rec.get("shift") not in (None, shift.PLAIN_LABEL):  # the plain runs keep the plain folder
        parts.append("shift-" + re.sub(r"[^0-9.]+", "-", rec["shift"]))
    folder = out.joinpath("tracks", *parts)
    folder.mkdir(parents=True, exist_ok=True)
    return folder / f"{rec['policy']}-{rec['index']:04d}.npy"


def run_grid(grid: Grid, *, out: Path, workers: int, engine: str = "local", address: str | None = None,
             progress: bool = True, title: str = "dovesei bench") -> dict:
    """Run (or resume) every episode of `grid` into `out`; returns the results.json content.

    All checks (worlds load, starts fit, Ray importable, the folder holds no other bench) happen
    before the output folder is created, so a failed start leaves nothing behind.
    """
    if engine not in engines.ENGINES:
        raise ConfigError(f"--engine {engine!r}: choose one of {', '.join(engines.ENGINES)}")
    if engine == "ray":
        engines.ray_module()
    worlds = load_worlds(grid.worlds)
    jobs = plan_jobs(grid, worlds, out)
    config = grid.config()
    key = _config_key(config)
    journal = out / "episodes.jsonl"
    done = load_journal(journal, key)
    planned = {_record_key(engines.record_base(j)) for j in jobs}
    done = {k: rec for k, rec in done.items() if k in planned}  # a grown or shrunk bench keeps what fits
    todo = [j for j in jobs if _record_key(engines.record_base(j)) not in done]
    created = not out.exists()
    try:
        return _run(grid, jobs, todo, done, worlds, config, key, out=out, workers=workers, engine=engine,
                    address=address, progress=progress, title=title)
    except BaseException:
        # A run that failed (or was interrupted) before its first episode leaves no empty folder.
        if created and out.is_dir() and not (journal.exists() and journal.stat().st_size):
            shutil.rmtree(out, ignore_errors=True)
        raise


def _run(grid: Grid, jobs: list[dict], todo: list[dict], done: dict, worlds: dict, config: dict, key: str, *,
         out: Path, workers: int, engine: str, address: str | None, progress: bool, title: str) -> dict:
    journal = out / "episodes.jsonl"
    out.mkdir(parents=True, exist_ok=True)
    if done:
        log.info("resuming: %d episodes already done, %d to go", len(done), len(todo))
    results = list(done.values())
    bar = Progress(len(jobs), grid.policies, progress)
    bar.show(results)
    with journal.open("a") as fh:
        def keep(rec: dict) -> None:
            track = rec.pop("_track", None)
            if track is not None:
                np.save(_track_path(out, grid, rec), track)
            rec["config_key"] = key
            fh.write(json.dumps(rec) + "\n")
            fh.flush()  # a crash loses at most the episodes in flight
            results.append(rec)
            bar.show(results)

        if todo and engine == "ray":
            engines.run_ray(todo, workers=workers, address=address, on_record=keep)
        elif todo:
            engines.run_local(todo, workers=workers, on_record=keep, preloaded=worlds)
    order = {_record_key(engines.record_base(j)): n for n, j in enumerate(jobs)}
    results.sort(key=lambda e: order.get(_record_key(e), len(order)))
    episodes_out = [{k: v for k, v in e.items() if k != "config_key"} for e in results]
    limits = stats.limits_for(grid.timing, grid.time_limit_s)
    # With a perception shift the headline figures stay the plain runs'; the shift sits beside them
    # (a bench of shifted runs only has its shifted runs as headline).
    plain = [e for e in episodes_out if e.get("shift") in (None, shift.PLAIN_LABEL)] or episodes_out
    doc = {"episodes": episodes_out, "summary": stats.summarise(plain, grid.policies, limits=limits),
           "config": config}
    if len(grid.worlds) > 1:
        doc["per_world"] = stats.summarise_by(episodes_out, ("world", "policy", "shift") if grid.shifted
                                              else ("world", "policy"))
    if any(v.labelled for v in grid.variants):
        doc["per_variant"] = stats.summarise_by(episodes_out, ("policy", "perception", "prompts", "shift")
                                                if grid.shifted else ("policy", "perception", "prompts"))
    if grid.shifted:
        doc["per_shift"] = stats.summarise_by(episodes_out, ("policy", "shift"))
    (out / "results.json").write_text(json.dumps(doc, indent=1))
    (out / "summary.md").write_text(summary_markdown(doc, title=title))
    _plot_paths(grid, worlds, doc, out)
    write_bench_page(out, doc, title=title)  # after the pictures: the page embeds them
    return doc


def summary_markdown(doc: dict, *, title: str = "dovesei bench") -> str:
    config = doc["config"]
    worlds = config["worlds"]
    where = f"World `{worlds[0]}`" if len(worlds) == 1 else f"{len(worlds)} worlds (`{config['world']}`)"
    noise = "noise 1, as calibrated" if config["noise"] is None else f"noise x{config['noise']:g}"
    lines = [
        f"# {title}", "",
        f"{where}, {config['episodes']} starts{' per world' if len(worlds) > 1 else ''} at "
        f"{config['start_alt_m']:.0f} m (seed {config['seed']}"
        f"{', at least %g m inside the edge beyond the footprint' % config['start_margin_m'] if 'start_margin_m' in config else ''}"
        f"), limit {config['time_limit_s']:g} s of sim time, "
        f"timing preset `{config['timing']}`, simulated perception `{config['perception']}` ({noise}), "
        f"vehicle profile `{config.get('vehicle_profile', 'ideal')}`"
        f"{' on the camera' + chr(39) + 's visual velocity (`--gnss-denied external-nav`)' if config.get('gnss_denied') == 'external-nav' else ''}. "
        f"Success = reaching the hand-over altitude ({config.get('handover_alt_m', HANDOVER_ALT_M):g} m) with the "
        f"{SAFETY_RADIUS_M:g} m footprint disk on safe classes, judged on "
        f"the label map, {stats.separation_text(config)}. Intervals are Wilson 95 %.", "",
        *stats.policy_table(doc["summary"]), "",
        "Averages are over successful episodes, as in the paper's Table I (time in sim seconds, distance = "
        "horizontal path length).", ""]
    limit_lines = stats.limit_table(doc["summary"])
    if limit_lines:
        lines += ["## Success against the time limit (the same runs, cut at each limit)", "",
                  "The paper's limits on its own clock and, in brackets, on this preset's sim clock.", "",
                  *limit_lines, ""]
    if doc.get("per_shift"):
        lines += ["## Plain and with the perception shift", "",
                  "The same starts, every heatmap P turned into sigmoid(a logit(P) + b) with a and b drawn per "
                  f"start from `{'`, `'.join(s for s in config['perception_shift'] if s != shift.PLAIN_LABEL)}` "
                  "(A_LO,A_HI,B); " + ("`none` = the plain runs (the table above). " if shift.PLAIN_LABEL in
                                       config["perception_shift"] else "shifted runs only (`--shift-only`): the "
                                       "table above is theirs, their plain twins another bench's. ")
                  + "Each episode's a and b are in results.json.", "",
                  *stats.rows_table(doc["per_shift"], ("policy", "shift")), ""]
    canopy_lines = stats.canopy_table(doc["summary"])
    if canopy_lines:
        lines += ["## Unsafe landings on ground the labels do not separate from tree canopy", "",
                  "A class marked `canopy_from_image` lumps open ground with trees (e.g. Dubai's \"vegetation\"); "
                  "the judge keeps it as labelled. Beside each such unsafe landing, the canopy the world's image "
                  f"shows: in the {SAFETY_RADIUS_M:g} m disk, within {CANOPY_NEAR_M:g} m, and the nearest crown "
                  "(the first column counts them among the hand-overs judged on such a world).", "",
                  *canopy_lines, ""]
    if doc.get("per_world"):
        keys = ("world", "policy", "shift") if "shift" in doc["per_world"][0] else ("world", "policy")
        lines += ["## Per world", "", *stats.rows_table(doc["per_world"], keys), ""]
    if doc.get("per_variant"):
        keys = ("policy", "perception", "prompts", "shift") if "shift" in doc["per_variant"][0] \
            else ("policy", "perception", "prompts")
        lines += ["## Per perception profile and prompt set", "", *stats.rows_table(doc["per_variant"], keys), ""]
    return "\n".join(lines)


def _plot_paths(grid: Grid, worlds: dict, doc: dict, out: Path) -> None:
    try:
        from dovesei.pictures.plots import plot_bench_paths  # lazy: needs matplotlib (dev extra)
    except ImportError as exc:  # matplotlib is a dev extra; the numbers matter more than the picture
        log.warning("no paths.png: %s", exc)
        return
    if any(v.labelled for v in grid.variants):
        return  # a sweep's picture is its results plot; per-variant path panels would be unreadable
    for wi, spec in enumerate(grid.worlds):
        # The plain runs' paths (a shifted run's tracks lie in their own folder).
        sub = {**doc, "episodes": [e for e in doc["episodes"] if e.get("world") == spec
                                   and e.get("shift") in (None, shift.PLAIN_LABEL)]}
        if len(grid.worlds) == 1:
            plot_bench_paths(worlds[spec], sub, out / "tracks", out / "paths.png")
        else:
            slug = world_slug(wi, spec)
            try:
                plot_bench_paths(worlds[spec], sub, out / "tracks" / slug, out / f"paths-{slug}.png")
            except DoveseiError as exc:
                log.warning("no paths picture for %s: %s", spec, exc)
