"""`dovesei bench-odometry` end to end on a small world: the figures are there and sane, and the
error table measures something (a wrong altitude tag shows up as the matching error)."""

from __future__ import annotations

import json

import pytest

from dovesei.benchmarks import odometry as bench
from dovesei.cli import COMMANDS
from dovesei.sim.world import load_world

SMALL_WORLD = "synthetic:size_m=300"  # generated once (~1 s), then read from the disk cache


def test_bench_odometry_prints_speed_and_error_figures(capsys: pytest.CaptureFixture[str]) -> None:
    assert COMMANDS["bench-odometry"][0] == bench.__name__
    argv = ["--json", "--world", SMALL_WORLD, "--pairs", "1", "--frames", "12", "--tilt", "on", "--noise", "ideal",
            "--flight-s", "4"]
    assert bench.main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    report = json.loads(lines[0])
    speed = report["speed"]
    assert speed["size"] == "640x480" and speed["frames"] == 12
    assert 0 < speed["cpu_ms_median"] <= speed["cpu_ms_p95"] and speed["valid_fraction"] > 0.5
    table = report["error"]["per_world"]["tilted camera, ideal"]
    assert set(table) == {SMALL_WORLD, "all"}
    everything = table["all"]
    # 4 speeds x 4 altitudes, one pair each: at 100 m a tilted footprint and its margin (170 m
    # each side) do not fit in this 300 m world, so that altitude has no pairs.
    assert everything["pairs"] == 16 and 0.0 <= everything["invalid_fraction"] < 0.5
    assert everything["err_pct_median"] < 10.0 and everything["err_m_s_at_rest_p95"] < 0.5
    assert len(report["error"]["per_cell"]["tilted camera, ideal"]) == 16
    # The scripted flights: 4 s at 10 Hz is ~39 compared pairs per profile; the ideal profile's
    # tags are the truth, so its error is the estimator's own.
    flights = report["flights"]["per_profile"]
    assert set(flights) == {"ideal", "realistic", "harsh"}
    ideal = flights["ideal"]["all"]
    assert 30 <= ideal["samples"] <= 40 and ideal["invalid_fraction"] < 0.2 and ideal["err_pct_median"] < 5.0
    # The gate's share: at least the invalid samples, never more than all of them.
    for profile in flights.values():
        assert profile["all"]["invalid_fraction"] <= profile["all"]["refused_fraction"] <= 1.0


def test_the_error_figure_sees_a_wrong_altitude(monkeypatch: pytest.MonkeyPatch) -> None:
    # Realistic tags with only their altitude error left: at 0 the error is the estimator's own
    # (small); at 30 % sigma the median error must follow it.
    world = {SMALL_WORLD: load_world(SMALL_WORLD)}
    for name in ("NOISE_GREY", "ROLL_PITCH_SIGMA_RAD", "YAW_SIGMA_RAD", "ALT_REL_SIGMA"):
        monkeypatch.setattr(bench, name, 0.0)
    monkeypatch.setattr(bench, "ALTITUDES_M", (40.0,))
    monkeypatch.setattr(bench, "SPEEDS_M_S", (5.0,))
    clean = bench.bench_error(world, 6, 0, (False,), ("realistic",))["per_world"]["level camera, realistic"]["all"]
    monkeypatch.setattr(bench, "ALT_REL_SIGMA", 0.30)
    off = bench.bench_error(world, 6, 0, (False,), ("realistic",))["per_world"]["level camera, realistic"]["all"]
    assert clean["err_pct_median"] < 3.0 and off["err_pct_median"] > 10.0, (clean, off)


def test_bad_arguments_are_one_line_errors(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        bench.main(["--pairs", "0", "--world", SMALL_WORLD])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "--pairs" in err and len(err.splitlines()) == 1
