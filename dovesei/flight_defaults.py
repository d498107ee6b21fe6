"""What `bench` and `up` fly when a setting is left out: one owner, so the same policy flies the same
settings in both, and `up`'s start is the start 0 of `bench --policy P` for the same seed.

    policies (+ a real vehicle?) --default_timing-->          "real" with `clearance` or a real
                                                                vehicle, else the simulation's default
    policies                     --default_start_margin_m-->  clearance's search radius + a drift
                                                                allowance with `clearance`, else 5 m
    world, n, seed, start altitude, margin --starts-->        the margin fitted to the world, then
                                                                `generate_starts` (start i never
                                                                depends on n: up's start = bench's 0)
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.shared.timing import DEFAULT_TIMING
from dovesei.sim.camera import CameraModel
from dovesei.sim.starts import Start, generate_starts

log = logging.getLogger(__name__)

# The true track should stay inside the search radius (the fence inside it allows for drift); the
# starts allow as much again beyond it, so a broken promise is measured, not cut off by the edge.
DRIFT_ALLOWANCE_M = 30.0
PLAIN_START_MARGIN_M = 5.0


def default_timing(policies: Iterable[str], *, real_vehicle: bool = False) -> str:
    """The timing preset flown without `--timing`.

    `clearance` keeps its own true-second timers: the reference preset's 78 sim s limit (the
    paper's 1200 s scaled to its compressed clock) would cut its search short, so it flies real;
    so does every real vehicle. The paper's policies keep the simulation's default.
    """
    return "real" if real_vehicle or "clearance" in policies else DEFAULT_TIMING


def default_start_margin_m(policies: Iterable[str]) -> float:
    """Where starts must lie so every bounded search flown keeps its search area on the map."""
    if "clearance" in policies:
        return ClearanceConfig().search_radius_m + DRIFT_ALLOWANCE_M
    return PLAIN_START_MARGIN_M


def fitting_margin_m(world, alt_m: float, margin_m: float, floor_m: float = PLAIN_START_MARGIN_M) -> float:
    """The start margin, shrunk (with a warning) to what the world leaves room for, never below
    `floor_m`: a small test world still gets starts, and the log says a bounded search may reach
    its edge there."""
    cam = CameraModel()
    room = min(world.width_m / 2.0 - cam.half_width_m(alt_m), world.height_m / 2.0 - cam.half_height_m(alt_m)) - 1.0
    if margin_m <= room or room < floor_m:
        return margin_m  # fits, or does not fit even at the floor (generate_starts names the problem)
    log.warning("world %s (%.0f x %.0f m) has room for a %.0f m start margin, not %.0f m: starts there lie "
                "closer to the edge than a bounded search may fly", world.name, world.width_m, world.height_m, room,
                margin_m)
    return room


def starts(world, n: int, seed: int, *, alt_m: float, margin_m: float) -> list[Start]:
    """The first `n` starts the bench flies on `world` (the margin fitted to the world first)."""
    return generate_starts(world, n, seed, alt_m=alt_m, margin_m=fitting_margin_m(world, alt_m, margin_m))
