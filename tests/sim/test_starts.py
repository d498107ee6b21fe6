"""Start positions: seeded, identical across calls, footprint inside the world, prefix-stable."""

from __future__ import annotations

import numpy as np
import pytest

from dovesei.sim.camera import CameraModel
from dovesei.sim.starts import Start, generate_starts
from dovesei.sim.world import World, WorldError


def world_m(width_m: float, height_m: float, gsd_m: float = 1.0) -> World:
    h, w = round(height_m / gsd_m), round(width_m / gsd_m)
    return World(np.zeros((h, w, 3), np.uint8), None, gsd_m, {}, "plain")


def test_footprint_and_margin_inside_and_uniform_spread() -> None:
    world = world_m(1600.0, 1200.0)
    cam = CameraModel()
    starts = generate_starts(world, 500, seed=3)
    half_m = cam.half_width_m(100.0) + 5.0
    xs = np.array([s.x_m for s in starts])
    ys = np.array([s.y_m for s in starts])
    assert xs.min() >= half_m and xs.max() <= 1600.0 - half_m
    assert ys.min() >= half_m and ys.max() <= 1200.0 - half_m
    assert all(s.alt_m == 100.0 and s.yaw_rad == 0.0 for s in starts)
    # Uniform: each half of the usable range holds about half of the starts.
    assert 200 < (xs < 800.0).sum() < 300 and 200 < (ys < 600.0).sum() < 300


def test_same_seed_same_starts_and_prefix_stable() -> None:
    world = world_m(800.0, 800.0)
    a = generate_starts(world, 50, seed=11)
    assert a == generate_starts(world, 50, seed=11)
    assert generate_starts(world, 10, seed=11) == a[:10]
    assert generate_starts(world, 50, seed=12) != a
    assert isinstance(a[0], Start) and generate_starts(world, 0, seed=1) == []


def test_world_too_small() -> None:
    # 100 m altitude needs a 148 m footprint plus margins: 150 m is not enough.
    with pytest.raises(WorldError, match="too small"):
        generate_starts(world_m(150.0, 1000.0), 5, seed=0)
    # At 50 m the same world fits.
    assert len(generate_starts(world_m(150.0, 1000.0), 5, seed=0, alt_m=50.0)) == 5


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        generate_starts(world_m(500.0, 500.0), -1, seed=0)
    with pytest.raises(ValueError):
        generate_starts(world_m(500.0, 500.0), 3, seed=0, alt_m=0.0)
