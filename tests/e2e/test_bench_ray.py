"""`dovesei bench --engine ray`: episodes are pure functions of their parameters, so a 2-worker
local Ray bench gives the process pool's records (wall times aside), into the same resumable
results.json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dovesei.bench import main, run_bench

WORLD = "synthetic:size_m=400,seed=1"
LIMIT_S = 3.0  # 60 decisions per episode: enough for paths to differ, cheap enough for a loaded CI


STARTS = 4  # x 2 policies = 8 episodes: twice the 4 tasks Ray keeps in flight on 2 CPUs


def _bench(out: Path, engine: str, episodes: int = STARTS) -> dict:
    # STARTS starts x 2 policies, on a small world with a short limit.
    return run_bench(world_spec=WORLD, episodes=episodes, seed=5, policies=["dovesei", "dovesei-nofocus"], noise=None,
                     timing="reference", time_limit_s=LIMIT_S, start_alt_m=100.0, jobs=2, out=out, engine=engine,
                     progress=False)


def _strip(doc: dict) -> list[dict]:
    return [{k: v for k, v in e.items() if k != "wall_time_s"} for e in doc["episodes"]]


@pytest.mark.timeout(900)  # two engines x 8 episodes plus Ray's start on 2 shared cores
def test_ray_bench_matches_the_process_pool_record_for_record(tmp_path: Path) -> None:
    pool = _bench(tmp_path / "pool", "local")
    ray = _bench(tmp_path / "ray", "ray")
    assert len(ray["episodes"]) == 2 * STARTS
    assert _strip(ray) == _strip(pool)
    strip_wall = lambda s: {p: {k: v for k, v in d.items() if k != "mean_wall_time_s"} for p, d in s.items()}  # noqa: E731
    assert strip_wall(ray["summary"]) == strip_wall(pool["summary"])
    # Tracks come back from the workers and are written by the driver, one per episode.
    assert len(list((tmp_path / "ray" / "tracks").glob("*.npy"))) == 2 * STARTS
    # The journal is the same resumable one: a second run finds everything done and changes nothing.
    journal = (tmp_path / "ray" / "episodes.jsonl").read_text()
    assert main(["--engine", "ray", "--jobs", "2", "--world", WORLD, "--episodes", str(STARTS), "--seed", "5",
                 "--time-limit-s", str(LIMIT_S), "--out", str(tmp_path / "ray"), "--no-progress"]) == 0
    assert (tmp_path / "ray" / "episodes.jsonl").read_text() == journal
    assert json.loads((tmp_path / "ray" / "results.json").read_text())["episodes"] == ray["episodes"]
