"""Where bench episodes run: a local process pool (the default) or Ray tasks.

An episode is a pure function of its job (a plain dict: world spec, policy, start, seeds,
perception, prompts, timing, limit), so either engine gives the same records for the same jobs
(wall times aside). Each worker process keeps the worlds it has loaded (`_world`), so a world is
built once per worker, not once per episode. Records, tracks included, travel back to the driver,
which alone writes files: a Ray worker on another machine never needs the output folder.

    driver: jobs --> engine.run(jobs, on_record) --> on_record(record) per finished episode
    worker: _run_job(job) --> dovesei.episode.run_episode --> record (+ track array)
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import time
from collections.abc import Callable, Sequence

import numpy as np

from dovesei.episode import EpisodeSpec, run_episode, separation_fields
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import EpisodeResult
from dovesei.shared.mission import HANDOVER_ALT_M
from dovesei.sim.judge import canopy_figures, disk_safe_map, nearest_safe_m
from dovesei.sim.starts import Start
from dovesei.sim.world import load_world

log = logging.getLogger(__name__)

RAY_INSTALL = 'pip install "dovesei[scale]"  (or: pip install ray)'
OnRecord = Callable[[dict], None]

# ---- worker side: worlds loaded once per process ----
_WORLDS: dict = {}
_WORKER_READY = False


def _prepare_worker() -> None:
    global _WORKER_READY
    if _WORKER_READY:
        return
    # One OpenCV thread per worker: the engine already fills the cores with workers, and OpenCV's
    # own pool on top of them only adds contention (results do not depend on it).
    import cv2

    cv2.setNumThreads(1)
    _WORKER_READY = True


def _init_pool_worker() -> None:
    logging.getLogger().setLevel(logging.WARNING)  # workers report through records, not logs
    _prepare_worker()


def use_world(spec: str, world) -> None:
    """Hand an already loaded world to this process's cache (the in-process path)."""
    _WORLDS[spec] = world


def _world(spec: str):
    if spec not in _WORLDS:
        _WORLDS[spec] = load_world(spec)
    return _WORLDS[spec]


_SAFE_MAPS: dict = {}  # world spec -> the judge's disk-safe map
_NEAREST: dict = {}  # (world spec, start) -> nearest_safe_m: every policy flies the same start
NEAREST_SAFE_WITHIN_M = 500.0  # how far a record's nearest_safe_m looks


def _nearest_safe_m(spec: str, start: Start) -> float | None:
    """The judge's side: how far from the start the nearest ground a landing there would be
    judged safe on lies (None: none within NEAREST_SAFE_WITHIN_M, or a world without labels)."""
    key = (spec, start)
    if key not in _NEAREST:
        world = _world(spec)
        if world.labels is None:
            return None
        if spec not in _SAFE_MAPS:
            _SAFE_MAPS[spec] = disk_safe_map(world)
        d = nearest_safe_m(world, _SAFE_MAPS[spec], start.x_m, start.y_m, NEAREST_SAFE_WITHIN_M)
        _NEAREST[key] = None if d is None else round(d, 1)
    return _NEAREST[key]


def run_job(job: dict) -> dict:
    """Fly one job; always returns a record (a crashing episode becomes outcome 'error')."""
    _prepare_worker()
    t0 = time.perf_counter()
    try:
        spec = EpisodeSpec.from_job(job, Start(**job["start"]))
        rec = run_episode(_world(job["world"]), spec)
    except Exception as exc:  # one broken episode is recorded, the bench goes on
        log.exception("episode %s/%s/%d failed", job["world"], job["policy"], job["index"])
        return {**record_base(job), "outcome": "error", "sim_time_s": 0.0, "path_length_m": 0.0,
                "wall_time_s": round(time.perf_counter() - t0, 3), "detail": f"{type(exc).__name__}: {exc}"}
    try:
        nearest = _nearest_safe_m(job["world"], spec.start)
    except Exception:  # noqa: BLE001 - a figure for the report: the episode's record stands without it
        log.exception("nearest safe ground for %s/%d not measured", job["world"], job["index"])
        nearest = None
    r = rec.result
    track = rec.track
    # How far the vehicle truly got from its start (the judge's view; the policy never sees it).
    max_range_m = float(np.max(np.hypot(track[:, 1] - spec.start.x_m, track[:, 2] - spec.start.y_m))) \
        if len(track) else 0.0
    return {**record_base(job), "outcome": r.outcome, "max_range_m": round(max_range_m, 1),
            "nearest_safe_m": nearest,
            # The controller's own last word: a timeout that is a deliberate hold reads NO_SPOT here.
            "final_state": rec.states[-1] if rec.states else "", "sim_time_s": round(r.sim_time_s, 3),
            "path_length_m": round(r.path_length_m, 3), "wall_time_s": round(rec.wall_time_s, 3),
            "final": {"x_m": round(r.final_x_m, 3), "y_m": round(r.final_y_m, 3), "alt_m": round(r.final_alt_m, 3)},
            "classes_found": list(r.classes_found), "detail": r.detail,
            "closest_unsafe_m": round(r.closest_unsafe_m, 3) if r.closest_unsafe_valid else None,
            # The ground the policy last confirmed (the judge's placing of its confirming look) and
            # how far from it the hand-over was: null for a policy that confirms no spot, not 0.
            "confirmed": ({"x_m": round(r.confirmed_x_m, 3), "y_m": round(r.confirmed_y_m, 3)}
                          if r.confirmed_valid else None),
            "touchdown_error_m": round(r.touchdown_error_m, 3) if r.touchdown_error_valid else None,
            **separation_fields(r),
            **_canopy_field(job["world"], r),
            "_track": rec.track.astype(np.float32)}


def _canopy_field(spec: str, r: EpisodeResult) -> dict:
    """{"canopy": figures} for a judged landing on a world whose labels lump lawn with tree canopy
    (`judge.canopy_figures`); nothing on other worlds, whose records stay as they were."""
    if not r.classes_found:  # no landing judged
        return {}
    try:
        figures = canopy_figures(_world(spec), r.final_x_m, r.final_y_m)
    except Exception:  # noqa: BLE001 - a figure for the report: the episode's record stands without it
        log.exception("canopy figures for %s not measured", spec)
        return {}
    return {} if figures is None else {"canopy": figures}


def record_base(job: dict) -> dict:
    """The fields that identify an episode in results.json."""
    base = {"world": job["world"], "policy": job["policy"], "index": job["index"], "seed": job["seed"],
            "start": {"x_m": job["start"]["x_m"], "y_m": job["start"]["y_m"], "alt_m": job["start"]["alt_m"]}}
    # Only a sweep varies these within one run; a plain bench keeps its records as they were.
    for key in ("perception", "prompts", "shift"):
        if job.get(f"{key}_label") is not None:
            base[key] = job[f"{key}_label"]
    if job.get("perception_shift") is not None:  # the (a, b) this episode's heatmaps were shifted by
        base["perception_shift"] = dict(job["perception_shift"])
    # The vehicle profile is recorded when it is not `ideal`, whose records stay those of the sim
    # before profiles existed.
    if job.get("vehicle_profile") not in (None, "ideal"):
        base["vehicle_profile"] = job["vehicle_profile"]
    if job.get("gnss_denied") not in (None, "off"):
        base["gnss_denied"] = job["gnss_denied"]
    # Likewise the hand-over altitude when it is not the mission's default.
    if job.get("handover_alt_m", HANDOVER_ALT_M) != HANDOVER_ALT_M:
        base["handover_alt_m"] = job["handover_alt_m"]
    return base


# ---- engines ----
def run_local(jobs: Sequence[dict], *, workers: int, on_record: OnRecord, preloaded: dict | None = None) -> None:
    """In this process for one worker (reusing `preloaded` worlds, keeping the caller's logging),
    else a spawn pool: no inherited Zenoh or torch state in the workers."""
    if workers == 1 or len(jobs) == 1:
        for spec, world in (preloaded or {}).items():
            use_world(spec, world)
        for job in jobs:
            on_record(run_job(job))
        return
    ctx = mp.get_context("spawn")
    with ctx.Pool(workers, initializer=_init_pool_worker) as pool:
        for rec in pool.imap_unordered(run_job, jobs):
            on_record(rec)


def ray_module():
    """The `ray` module, or a ConfigError with the install command (checked before any work)."""
    try:
        import ray
    except ImportError:
        raise ConfigError(f"--engine ray needs Ray, which is not installed: {RAY_INSTALL}") from None
    return ray


def _ray_task(job: dict) -> dict:
    logging.getLogger().setLevel(logging.WARNING)
    return run_job(job)


def run_ray(jobs: Sequence[dict], *, workers: int, address: str | None, on_record: OnRecord) -> None:
    """Episodes as Ray tasks, one CPU each, results handed on as they finish.

    Without `address` a private local Ray instance with `workers` CPUs is started
    (`address="local"`: never a silent join of a cluster that happens to be running); with one,
    the bench joins that cluster and uses all of it. At most 2 tasks per CPU are in flight, so an
    interrupted bench loses little and the journal stays close to the work done.
    """
    ray = ray_module()
    if address:
        ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
    else:
        ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.WARNING)
    try:
        remote = ray.remote(num_cpus=1, max_retries=1)(_ray_task)
        window = max(1, 2 * int(ray.cluster_resources().get("CPU", workers)))
        todo = list(jobs)
        inflight: dict = {}
        while todo or inflight:
            while todo and len(inflight) < window:
                job = todo.pop(0)
                inflight[remote.remote(job)] = job
            ready, _ = ray.wait(list(inflight), num_returns=1)
            for ref in ready:
                job = inflight.pop(ref)
                try:
                    rec = ray.get(ref)
                except Exception as exc:  # a worker that died twice: that episode is an error record
                    rec = {**record_base(job), "outcome": "error", "sim_time_s": 0.0, "path_length_m": 0.0,
                           "wall_time_s": 0.0, "detail": f"ray: {type(exc).__name__}: {exc}"}
                on_record(rec)
    finally:
        ray.shutdown()


ENGINES = ("local", "ray")
