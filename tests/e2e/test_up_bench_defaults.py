"""`bench` and `up` fly the same settings for the same policy, and `up`'s start is the bench's start 0."""

from __future__ import annotations

from pathlib import Path

import pytest

from dovesei.bench import build_parser as bench_parser
from dovesei.bench import make_grid, settings_from_args
from dovesei.bench.run import plan_jobs
from dovesei.controller.policies.registry import policy_names
from dovesei.flight_defaults import default_start_margin_m
from dovesei.sim.estimator import default_vehicle_profile
from dovesei.sim.world import load_world
from dovesei.up.options import build_parser as up_parser
from dovesei.up.options import options_from_args, resolve_start

# Room for clearance's whole search area (its margin, ~330 m) beside the 100 m footprint on each side.
WORLD = "synthetic:size_m=1000,seed=5"


@pytest.fixture(scope="module")
def world():
    return load_world(WORLD)


def _both(policy: str, *flags: str):
    argv = ["--policy", policy, "--world", WORLD, *flags]
    grid = make_grid(**settings_from_args(bench_parser().parse_args(argv)))
    options = options_from_args(up_parser().parse_args(argv))
    return grid, options


@pytest.mark.parametrize("policy", policy_names())
def test_up_flies_the_bench_settings_for_the_same_policy(policy: str) -> None:
    grid, options = _both(policy)
    assert grid.timing == options.timing
    assert grid.time_limit_s == options.time_limit_s
    assert grid.start_alt_m == options.start_alt_m and grid.handover_alt_m == options.handover_alt_m
    up_profile = options.vehicle_profile or default_vehicle_profile(options.timing)
    assert grid.vehicle_profile == up_profile
    # and the clearance policy keeps its true-second timers in both (the reference clock's 78 s cuts it)
    assert (grid.timing == "real") == (policy == "clearance")


@pytest.mark.parametrize("policy", policy_names())
@pytest.mark.parametrize("seed", [0, 3])
def test_up_start_is_the_bench_start_0(policy: str, seed: int, world, tmp_path: Path) -> None:
    grid, options = _both(policy, "--seed", str(seed))
    job0 = plan_jobs(grid, {WORLD: world}, tmp_path)[0]
    x_m, y_m, alt_m = resolve_start(world, options)
    assert job0["index"] == 0 and job0["policy"] == policy
    assert (round(x_m, 3), round(y_m, 3), alt_m) == (job0["start"]["x_m"], job0["start"]["y_m"], job0["start"]["alt_m"])


def test_clearance_starts_keep_its_search_area_on_the_map(world) -> None:
    # The same seed, another policy: the start moves inward by clearance's margin, in up as in the bench.
    _, plain = _both("dovesei", "--seed", "0")
    _, ours = _both("clearance", "--seed", "0")
    margin = default_start_margin_m(["clearance"])
    assert margin > 300.0 > default_start_margin_m(["dovesei"])
    x_m, y_m, _ = resolve_start(world, ours)
    assert min(x_m, y_m, world.width_m - x_m, world.height_m - y_m) >= margin
    assert resolve_start(world, plain) != (x_m, y_m, ours.start_alt_m)
