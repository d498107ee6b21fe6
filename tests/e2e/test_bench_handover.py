"""`dovesei bench --handover-alt-m`: every episode hands over and is judged there, the records and
the summary say so, and a bench at the default keeps its records (and settings hash) as before."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from dovesei.bench import run_bench

WORLD = "synthetic:size_m=400,seed=1"
# A 400 m world: clearance takes its scene from the first views, as the other small-world tests do
# (the default top pass over a 300 m search radius flies off it).
SMALL_WORLD = "scene_after_top_pass = false\n"


def test_a_bench_hands_over_where_it_is_told_and_records_it(tmp_path: Path) -> None:
    path = tmp_path / "small.toml"
    path.write_text(SMALL_WORLD)
    doc = run_bench(world_spec=WORLD, episodes=1, seed=0, policies=["clearance"], noise=0.0, timing="real",
                    time_limit_s=600.0, start_alt_m=100.0, jobs=1, out=tmp_path / "b", progress=False,
                    handover_alt_m=35.0, policy_config=path)
    (ep,) = doc["episodes"]
    print(f"bench --handover-alt-m 35: {ep['outcome']} at {ep['final']['alt_m']} m after {ep['sim_time_s']} s")
    assert ep["handover_alt_m"] == 35.0 and doc["config"]["handover_alt_m"] == 35.0
    # Judged where the controller handed over on the vehicle's measured altitude: the true one within its error.
    assert ep["outcome"] in ("safe", "unsafe") and abs(ep["final"]["alt_m"] - 35.0) < 1.0
    assert "hand-over altitude (35 m)" in (tmp_path / "b" / "summary.md").read_text()


def test_at_the_default_the_records_and_settings_keep_their_fields(tmp_path: Path) -> None:
    doc = run_bench(world_spec=WORLD, episodes=1, seed=3, policies=["dovesei"], noise=0.0, timing="reference",
                    time_limit_s=8.0, start_alt_m=100.0, jobs=1, out=tmp_path / "b", progress=False)
    assert "handover_alt_m" not in doc["config"] and "handover_alt_m" not in doc["episodes"][0]
    assert "hand-over altitude (20 m)" in (tmp_path / "b" / "summary.md").read_text()


def test_a_handover_above_the_start_is_one_line_before_any_work(tmp_path: Path) -> None:
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "dovesei.cli", "bench", "--world", WORLD, "--start-alt-m", "40",
                        "--handover-alt-m", "38", "--out", str(out), "--no-progress"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("dovesei bench: --handover-alt-m 38 m"), r.stderr
    assert "start altitude 40 m" in lines[0] and not out.exists()


def test_a_policy_file_is_flown_and_recorded_and_refused_with_two_policies(tmp_path: Path) -> None:
    path = tmp_path / "mine.toml"
    path.write_text(SMALL_WORLD + "scene_floor_p = 0.9\nmargin_m = 1.5\n")  # margin_m is the default: not a change
    doc = run_bench(world_spec=WORLD, episodes=1, seed=0, policies=["clearance"], noise=0.0, timing="real",
                    time_limit_s=600.0, start_alt_m=100.0, jobs=1, out=tmp_path / "b", progress=False,
                    policy_config=path)
    assert doc["config"]["policy_config"] == {"scene_after_top_pass": False, "scene_floor_p": 0.9}
    assert doc["episodes"][0]["outcome"] in ("safe", "unsafe", "timeout")
    r = subprocess.run([sys.executable, "-m", "dovesei.cli", "bench", "--world", WORLD, "--policy", "dovesei,clearance",
                        "--policy-config", str(path), "--out", str(tmp_path / "o"), "--no-progress"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "one --policy" in lines[0], r.stderr
    path.write_text("scene_floor_p = 'x'\n")
    r = subprocess.run([sys.executable, "-m", "dovesei.cli", "bench", "--world", WORLD, "--policy", "clearance",
                        "--policy-config", str(path), "--out", str(tmp_path / "o"), "--no-progress"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "mine.toml: scene_floor_p must be a finite number" in lines[0]
    assert not (tmp_path / "o").exists()


def test_an_episode_builds_its_policy_from_the_jobs_constants() -> None:
    from dovesei.episode import EpisodeSpec, build_cores
    from dovesei.sim.starts import Start
    from dovesei.sim.world import load_world

    job = {"policy": "clearance", "timing": "real", "seed": 0, "time_limit_s": 60.0, "handover_alt_m": 12.0,
           "policy_config": {"scene_floor_p": 0.9, "lower_search_fracs": [0.5]}}
    spec = EpisodeSpec.from_job(job, Start(200.0, 200.0, 100.0))
    _, _, ctrl = build_cores(load_world(WORLD), spec)
    cfg = ctrl.policy.config
    assert (cfg.scene_floor_p, cfg.lower_search_fracs, cfg.handover_alt_m) == (0.9, (0.5,), 12.0)
    assert ctrl.config.handover_alt_m == 12.0
