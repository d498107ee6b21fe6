"""`dovesei bench`: the results contract, resuming, refusing mixed settings, jobs do not change
results, clean one-line errors before any work, intervals and limits from the same runs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dovesei.bench import main, run_bench, summarise, wilson_interval
from dovesei.bench.stats import limits_for, success_by_limit
from dovesei.shared.errors import ConfigError

WORLD = "synthetic:size_m=400,seed=1"
EPISODE_KEYS = {"world", "policy", "seed", "start", "outcome", "sim_time_s", "path_length_m", "wall_time_s"}
SUMMARY_KEYS = {"episodes", "safe", "unsafe", "timeout", "out_of_world", "error", "mean_sim_time_s",
                "mean_path_length_m", "success_ci95", "success_by_limit"}


def _bench(out: Path, jobs: int = 1, episodes: int = 1, noise: float = 0.0, **kw) -> dict:
    return run_bench(world_spec=WORLD, episodes=episodes, seed=3, policies=["dovesei", "dovesei-nofocus"],
                     noise=noise, timing="reference", time_limit_s=8.0, start_alt_m=100.0, jobs=jobs, out=out,
                     progress=False, **kw)


def _strip(doc: dict) -> list[dict]:
    return [{k: v for k, v in e.items() if k != "wall_time_s"} for e in doc["episodes"]]


def test_results_contract_and_resume(tmp_path: Path) -> None:
    doc = _bench(tmp_path)
    assert len(doc["episodes"]) == 2
    for e in doc["episodes"]:
        assert EPISODE_KEYS <= set(e)
        assert e["world"] == WORLD
        assert e["outcome"] in {"safe", "unsafe", "timeout", "out_of_world", "error"}
        assert set(e["start"]) == {"x_m", "y_m", "alt_m"} and e["start"]["alt_m"] == 100.0
        # The judge's ceiling: how far the nearest ground judged safe lay from the start (the
        # default synthetic city has lawns and plazas within a few hundred metres of anywhere).
        assert e["nearest_safe_m"] is not None and 0.0 <= e["nearest_safe_m"] <= 500.0
        # The paper's policies confirm no spot: their records say so (null), not 0.
        assert e["touchdown_error_m"] is None and e["confirmed"] is None
    assert doc["episodes"][0]["nearest_safe_m"] == doc["episodes"][1]["nearest_safe_m"]  # the same start
    assert set(doc["summary"]) == {"dovesei", "dovesei-nofocus"}
    assert all(SUMMARY_KEYS <= set(s) and s["episodes"] == 1 for s in doc["summary"].values())
    # The same starts for every policy.
    starts = {p: [e["start"] for e in doc["episodes"] if e["policy"] == p] for p in doc["summary"]}
    assert starts["dovesei"] == starts["dovesei-nofocus"]
    table = (tmp_path / "summary.md").read_text().split("## ")[0]
    assert table.count("| dovesei") == 2 and "95 % CI" in table
    assert table.count("no confirmed spot") == 2
    assert all(s["median_touchdown_error_m"] is None and s["touchdown_error_episodes"] == 0
               for s in doc["summary"].values())
    assert (tmp_path / "paths.png").stat().st_size > 0
    assert len(list((tmp_path / "tracks").glob("*.npy"))) == 2
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
    assert _strip(resumed) == _strip(full)


def test_other_settings_in_the_same_folder_are_refused(tmp_path: Path) -> None:
    _bench(tmp_path, episodes=1)
    with pytest.raises(ConfigError, match="other settings"):
        _bench(tmp_path, episodes=1, noise=0.5)


def test_a_bench_grows_by_its_new_starts_only(tmp_path: Path) -> None:
    small = _bench(tmp_path, episodes=1)
    first = (tmp_path / "episodes.jsonl").read_text()
    grown = _bench(tmp_path, episodes=2)
    journal = (tmp_path / "episodes.jsonl").read_text()
    assert journal.startswith(first) and len(journal.splitlines()) == 4  # two new episodes, two kept
    assert grown["episodes"][0] == small["episodes"][0] and len(grown["episodes"]) == 4
    assert _strip(_bench(tmp_path, episodes=1)) == _strip(small)  # and shrinks back to the first starts


def test_parallel_jobs_give_the_same_episodes(tmp_path: Path) -> None:
    one = _bench(tmp_path / "one", jobs=1, episodes=2)
    two = _bench(tmp_path / "two", jobs=2, episodes=2)
    assert _strip(one) == _strip(two)


def test_several_worlds_give_a_row_per_world_and_the_worlds_own_starts(tmp_path: Path) -> None:
    other = "synthetic:size_m=400,seed=2"
    doc = run_bench(worlds=(WORLD, other), episodes=1, seed=3, policies=["dovesei"], noise=0.0, timing="reference",
                    time_limit_s=4.0, start_alt_m=100.0, jobs=1, out=tmp_path, progress=False, world_label="two")
    assert [e["world"] for e in doc["episodes"]] == [WORLD, other]
    assert [(r["world"], r["policy"], r["episodes"]) for r in doc["per_world"]] == [(WORLD, "dovesei", 1),
                                                                                   (other, "dovesei", 1)]
    assert "## Per world" in (tmp_path / "summary.md").read_text()
    assert {p.parent.name for p in (tmp_path / "tracks").rglob("*.npy")} == {"00-synthetic-size-m-400-seed-1",
                                                                            "01-synthetic-size-m-400-seed-2"}


def test_suite_default_flies_every_world_of_the_suite(tmp_path: Path, capsys) -> None:
    from dovesei.sim.suite import DEFAULT_SUITE

    assert main(["--suite", "default", "--episodes", "1", "--policy", "dovesei", "--time-limit-s", "0.5",
                 "--jobs", "1", "--out", str(tmp_path), "--no-progress"]) == 0
    doc = json.loads((tmp_path / "results.json").read_text())
    assert [e["world"] for e in doc["episodes"]] == list(DEFAULT_SUITE)
    assert doc["config"]["world"] == "suite:default" and len(doc["per_world"]) == len(DEFAULT_SUITE)
    assert "## Per world" in capsys.readouterr().out


def test_real_timing_with_clean_perception_lands_a_pinned_share(tmp_path: Path) -> None:
    # Fixed seeds, true seconds, 2 Hz perception, a 300 s limit, the paper's drone (ideal vehicle:
    # it knew its state): measured 1/3 safe, 2 out of the (small) world, none unsafe (with people
    # and cars in the world; 2/3 before). The range allows one start to change either way; clean
    # perception must never put the vehicle down on unsafe ground. (The realistic vehicle, the
    # default with real timing, measured 0/3 here: a 300 s timeout and 2 out of the world.)
    doc = run_bench(world_spec="synthetic:size_m=600,seed=1", episodes=3, seed=0, policies=["dovesei"], noise=None,
                    timing="real", time_limit_s=300.0, start_alt_m=100.0, jobs=1, out=tmp_path, perception="clean",
                    progress=False, vehicle_profile="ideal")
    s = doc["summary"]["dovesei"]
    assert 1 <= s["safe"] <= 3 and s["unsafe"] == 0 and s["error"] == 0, s
    assert all(e["sim_time_s"] <= 300.0 for e in doc["episodes"])
    assert s["success_by_limit"]["300"]["safe"] == s["safe"] and "600" not in s["success_by_limit"]


def test_summary_means_are_over_successful_episodes() -> None:
    eps = [{"policy": "p", "outcome": "safe", "sim_time_s": 40.0, "path_length_m": 10.0, "wall_time_s": 1.0},
           {"policy": "p", "outcome": "timeout", "sim_time_s": 60.0, "path_length_m": 99.0, "wall_time_s": 1.0}]
    s = summarise(eps, ["p"])["p"]
    assert (s["safe"], s["timeout"], s["mean_sim_time_s"], s["mean_path_length_m"]) == (1, 1, 40.0, 10.0)


def test_wilson_interval_known_values() -> None:
    # Textbook values (Wilson 1927 / Newcombe 1998, z = 1.96).
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    lo, hi = wilson_interval(29, 50)  # symmetric under swapping successes and failures
    assert (lo, hi) == pytest.approx((1 - wilson_interval(21, 50)[1], 1 - wilson_interval(21, 50)[0]))
    assert lo < 29 / 50 < hi
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_success_against_the_limit_counts_landings_by_each_limit() -> None:
    limits = limits_for("real", 1200.0)
    assert [p for p, _ in limits] == [60.0, 300.0, 600.0, 1200.0]
    assert [s for _, s in limits] == [60.0, 300.0, 600.0, 1200.0]
    eps = [{"outcome": "safe", "sim_time_s": t} for t in (50.0, 250.0, 700.0)] + [{"outcome": "timeout",
                                                                                    "sim_time_s": 1200.0}]
    got = success_by_limit(eps, limits)
    assert [got[k]["safe"] for k in ("60", "300", "600", "1200")] == [1, 2, 2, 3]
    # A shorter run only reports the limits it covers, on the preset's own clock.
    ref = limits_for("reference", 20.0)
    assert [p for p, _ in ref] == [60.0, 300.0] and ref[0][1] < ref[1][1] <= 20.0


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dovesei.cli", "bench", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120)


@pytest.mark.parametrize("args, needle", [
    (["--world", "no/such/world"], "no/such/world"),
    (["--episodes", "-1"], "--episodes"),
    (["--jobs", "0"], "--jobs"),
    (["--policy", "dovesei,nope"], "nope"),
    (["--timing", "fast"], "fast"),
    (["--perception", "dreamy"], "--perception"),
    (["--address", "10.0.0.1:6379"], "--engine ray"),
    (["--time-limit-s", "nan"], "--time-limit-s"),
    (["--suite", "nope"], "--suite"),
    (["--episodes", "ten"], "--episodes"),
    (["--suite", "default", "--world", "synthetic"], "not allowed with"),
])
def test_cli_errors_are_one_line_and_leave_no_folder(tmp_path: Path, args: list[str], needle: str) -> None:
    out = tmp_path / "out"
    r = _cli(*args, "--out", str(out), "--no-progress", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("dovesei bench:") and needle in lines[0], r.stderr
    assert "Traceback" not in r.stderr
    assert not out.exists()


def test_engine_ray_without_ray_names_the_install_command(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # what an install without the `scale` extra sees
    assert main(["--engine", "ray", "--world", WORLD, "--episodes", "1", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "pip install" in err and "dovesei[scale]" in err
    assert not (tmp_path / "o").exists()


def test_results_json_round_trips(tmp_path: Path) -> None:
    doc = _bench(tmp_path)
    assert json.loads((tmp_path / "results.json").read_text()) == doc


def test_the_start_margin_shrinks_to_what_a_small_world_leaves_room_for() -> None:
    from dovesei.flight_defaults import fitting_margin_m  # lazy: this test only
    from dovesei.sim.world import load_world

    small = load_world("synthetic:size_m=400,seed=1")
    fitted = fitting_margin_m(small, 40.0, 180.0)
    assert 5.0 <= fitted < 180.0
    assert fitting_margin_m(small, 40.0, 20.0) == 20.0  # a margin that fits is kept
    assert fitting_margin_m(small, 40.0, 180.0, floor_m=fitted + 1.0) == 180.0  # no room even at the floor


def test_records_carry_the_separation_figures_and_the_summary_counts_them(tmp_path: Path) -> None:
    # From 25 m `clearance` reaches the 20 m hand-over within the limit on most starts (measured: 2
    # of these 3); the judge measures the nearest person and vehicle there, and the summary and page
    # count what broke the separation (a 50 m vehicle rule, which any city touchdown breaks).
    # From 25 m the scene is the first views: a top pass over this 400 m world would fly off it.
    settings = tmp_path / "clearance.toml"
    settings.write_text("scene_after_top_pass = false\n", encoding="utf-8")
    doc = run_bench(world_spec=WORLD, episodes=3, seed=0, policies=["clearance"], noise=None, timing="real",
                    time_limit_s=120.0, start_alt_m=25.0, handover_alt_m=20.0, jobs=1, out=tmp_path / "bench",
                    progress=False, perception="clean", separation_m=(3.0, 50.0), policy_config=settings)
    judged = [e for e in doc["episodes"] if e["separation_violated"] is not None]
    assert judged, [e["outcome"] for e in doc["episodes"]]
    for e in doc["episodes"]:
        assert {"nearest_person_m", "nearest_vehicle_m", "separation_violated"} <= set(e)
    for e in judged:  # a vehicle within 50 m of any touchdown in a city: the strict rule catches it
        near_car = e["nearest_vehicle_m"] is not None and e["nearest_vehicle_m"] < 50.0
        assert e["separation_violated"] == (near_car or (e["nearest_person_m"] or 99.0) < 3.0)
        assert e["outcome"] == "unsafe" or not e["separation_violated"]
    s = doc["summary"]["clearance"]
    assert s["separation_judged"] == len(judged)
    assert s["separation_violations"] == sum(e["separation_violated"] for e in judged)
    assert doc["config"]["separation_m"] == [3.0, 50.0]
    md = (tmp_path / "bench" / "summary.md").read_text()
    assert "separation violations" in md and "no vehicle within 50 m of the touchdown" in md
    assert f"| {s['separation_violations']}/{len(judged)} |" in md
    assert "nearest person median / min" in (tmp_path / "bench" / "report.html").read_text()
