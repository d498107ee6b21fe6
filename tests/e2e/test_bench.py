"""`dovesei bench`: the results contract, resuming, refusing mixed settings, jobs do not change results."""

from __future__ import annotations

from pathlib import Path

import pytest

from dovesei.bench import main, run_bench, summarise
from dovesei.shared.errors import ConfigError

WORLD = "synthetic:size_m=400,seed=1"
EPISODE_KEYS = {"policy", "seed", "start", "outcome", "sim_time_s", "path_length_m", "wall_time_s"}
SUMMARY_KEYS = {"episodes", "safe", "unsafe", "timeout", "mean_sim_time_s", "mean_path_length_m"}


def _bench(out: Path, jobs: int = 1, episodes: int = 1, noise: float = 0.0) -> dict:
    return run_bench(world_spec=WORLD, episodes=episodes, seed=3, policies=["dovesei", "dovesei-nofocus"],
                     noise=noise, timing="reference", time_limit_s=8.0, start_alt_m=100.0, jobs=jobs, out=out,
                     progress=False)


def test_results_contract_and_resume(tmp_path: Path) -> None:
    doc = _bench(tmp_path)
    assert len(doc["episodes"]) == 2
    for e in doc["episodes"]:
        assert EPISODE_KEYS <= set(e)
        assert e["outcome"] in {"safe", "unsafe", "timeout", "out_of_world", "error"}
        assert set(e["start"]) == {"x_m", "y_m", "alt_m"} and e["start"]["alt_m"] == 100.0
    assert set(doc["summary"]) == {"dovesei", "dovesei-nofocus"}
    assert all(SUMMARY_KEYS <= set(s) and s["episodes"] == 1 for s in doc["summary"].values())
    # The same starts for every policy.
    starts = {p: [e["start"] for e in doc["episodes"] if e["policy"] == p] for p in doc["summary"]}
    assert starts["dovesei"] == starts["dovesei-nofocus"]
    assert (tmp_path / "summary.md").read_text().count("| dovesei") == 2
    assert (tmp_path / "paths.png").stat().st_size > 0
    journal = (tmp_path / "episodes.jsonl").read_text()
    # Resuming: nothing runs again and the results are the same.
    again = _bench(tmp_path)
    assert (tmp_path / "episodes.jsonl").read_text() == journal
    assert again["summary"] == doc["summary"]


def test_an_interrupted_bench_continues_where_it_stopped(tmp_path: Path) -> None:
    full = _bench(tmp_path / "full")
    part = tmp_path / "part"
    _bench(part)
    lines = (part / "episodes.jsonl").read_text().splitlines()
    # Keep one finished episode and a torn last line, as a killed bench leaves them.
    (part / "episodes.jsonl").write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])
    resumed = _bench(part)
    strip = lambda d: [{k: v for k, v in e.items() if k != "wall_time_s"} for e in d["episodes"]]  # noqa: E731
    assert strip(resumed) == strip(full)


def test_other_settings_in_the_same_folder_are_refused(tmp_path: Path) -> None:
    _bench(tmp_path, episodes=1)
    with pytest.raises(ConfigError, match="other settings"):
        _bench(tmp_path, episodes=1, noise=0.5)


def test_parallel_jobs_give_the_same_episodes(tmp_path: Path) -> None:
    one = _bench(tmp_path / "one", jobs=1)
    two = _bench(tmp_path / "two", jobs=2)
    strip = lambda d: [{k: v for k, v in e.items() if k != "wall_time_s"} for e in d["episodes"]]  # noqa: E731
    assert strip(one) == strip(two)


def test_summary_means_are_over_successful_episodes() -> None:
    eps = [{"policy": "p", "outcome": "safe", "sim_time_s": 40.0, "path_length_m": 10.0, "wall_time_s": 1.0},
           {"policy": "p", "outcome": "timeout", "sim_time_s": 60.0, "path_length_m": 99.0, "wall_time_s": 1.0}]
    s = summarise(eps, ["p"])["p"]
    assert (s["safe"], s["timeout"], s["mean_sim_time_s"], s["mean_path_length_m"]) == (1, 1, 40.0, 10.0)


def test_cli_rejects_unknown_policy(capsys) -> None:
    assert main(["--policy", "dovesei,nope", "--episodes", "1"]) == 2
    assert "nope" in capsys.readouterr().err
