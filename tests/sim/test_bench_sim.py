"""`dovesei bench-sim` end to end on a small world: the JSON line carries every figure, sane values."""

from __future__ import annotations

import json

import pytest

from dovesei.benchmarks import sim as bench
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.starts import Start
from tests.sim.test_sim_core import MID_Y_M, WEST_M, split_world

SMALL_WORLD = "synthetic:size_m=300"  # generated once (~1 s), then read from the disk cache


def test_bench_sim_prints_one_json_line_with_the_figures(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--json", "--world", SMALL_WORLD, "--batches", "2", "--frames", "20", "--episode-s", "2",
            "--zenoh-episode-s", "1"]
    assert bench.main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1  # --json: nothing but the JSON object
    report = json.loads(lines[-1])
    for key in ("render_fps", "render_fps_cpu", "realtime_factor", "realtime_factor_real_timing",
                "zenoh_realtime_factor", "world_load_s", "pyramid_build_s", "steps_per_s"):
        assert isinstance(report[key], (int, float)) and report[key] > 0, key
    assert len(report["render_fps_batches"]) == 2 and report["frame_px"] == [352, 352]
    # 2 s of reference timing: one frame per 0.05 s step, none at the final (judged) step.
    assert report["episode_sim_s"] == pytest.approx(2.0) and report["episode_frames"] == 40
    assert report["world_px"] == [1200, 1200] and report["gsd_m"] == 0.25


def test_bench_sim_human_output_ends_with_the_json_line(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--world", SMALL_WORLD, "--batches", "1", "--frames", "5", "--episode-s", "0.5", "--zenoh-episode-s", "0"]
    assert bench.main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) > 1 and "render" in lines[1]
    assert json.loads(lines[-1])["zenoh_realtime_factor"] is None  # skipped on request


@pytest.mark.parametrize("argv", [["--batches", "0"], ["--episode-s", "-1"], ["--frames", "0"]])
def test_bench_sim_refuses_bad_sizes(argv: list[str]) -> None:
    assert bench.main(argv) == 2


def test_the_trivial_policy_circles_inside_a_small_world() -> None:
    # The episode must last its time limit, not end early by leaving the world or landing.
    world = split_world()
    core = SimCore(world, Start(WEST_M, MID_Y_M, 100.0), SimConfig(timing="real", time_limit_s=60.0))
    out = core.reset()
    while out.result is None:
        out = core.step(bench.trivial_command(out.state))
    assert out.result.outcome == "timeout"
    assert abs(out.result.final_x_m - WEST_M) < 25.0 and abs(out.result.final_y_m - MID_Y_M) < 25.0
