"""The scene's thresholds (scene): read off the map's own log-odds, they move with any
recalibration logit P' = a logit P + b, a scene of one class is judged by the floor alone, and a
scene whose best reads below even odds has nothing safe in it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.clearance.scene import levels_from

CFG = ClearanceConfig()
SHIFTS = [(0.6, -0.8), (0.6, 0.8), (1.0, 0.0), (1.6, -0.8), (1.6, 0.8)]
CELL_M = 2.0


def _city(rng: np.random.Generator) -> np.ndarray:
    """A 200 x 200 map (2 m cells) from high up: roads and roofs, a 12 m band of sidewalk and a 20 m lawn."""
    m = rng.normal(-1.0, 0.3, (200, 200)).astype(np.float32)
    m[:, 100:106] = rng.normal(1.1, 0.15, (200, 6))
    m[40:50, 40:50] = rng.normal(2.2, 0.15, (10, 10))
    return m


@pytest.mark.parametrize("a,b", SHIFTS)
def test_every_threshold_moves_with_a_recalibration(a: float, b: float) -> None:
    mean = _city(np.random.default_rng(1))
    known = np.ones(mean.shape, bool)
    base = levels_from(mean, known, CFG, CELL_M)
    shifted = levels_from(a * mean + b, known, CFG, CELL_M)
    assert base.contrast_logit > 0.0 and shifted.contrast_logit > 0.0  # a lawn among roads: contrast
    for name in ("best_logit", "typical_logit"):
        assert getattr(shifted, name) == pytest.approx(a * getattr(base, name) + b, abs=1e-4), name
    # Every threshold moves with the map, held only by the floor (even odds) where it reaches it.
    for name in ("gate_logit", "probe_logit", "probe_now_logit"):
        assert getattr(shifted, name) == pytest.approx(max(0.0, a * getattr(base, name) + b), abs=1e-4), name
    assert shifted.dip_floor_logit == pytest.approx(a * base.dip_floor_logit, rel=1e-4)
    for noise in (0.0, 0.1, 0.5):
        assert shifted.spot_for(a * noise, CFG) == pytest.approx(max(0.0, a * base.spot_for(noise, CFG) + b), abs=1e-4)
    # The lawn passes the spot test, the sidewalk does not.
    spot = shifted.spot_for(0.15 * a, CFG)
    assert a * 1.1 + b + 3 * 0.15 * a < spot < a * 2.2 + b - 3 * 0.15 * a


def test_a_scene_of_one_class_is_judged_by_the_floor_alone() -> None:
    rng = np.random.default_rng(2)
    desert = rng.normal(1.0, 0.2, (200, 200)).astype(np.float32)
    known = np.ones(desert.shape, bool)
    lv = levels_from(desert, known, CFG, CELL_M)
    assert lv.contrast_logit == 0.0 and not lv.nothing_safe
    assert lv.spot_for(0.2, CFG) == lv.gate_logit == CFG.scene_floor_logit == 0.0
    # The same scene read pessimistically (below even odds): nothing here is safe.
    roofs = levels_from(desert - 1.8, known, CFG, CELL_M)
    assert roofs.nothing_safe and math.isinf(roofs.spot_for(0.2, CFG)) and math.isinf(roofs.probe_logit)


def test_a_scene_whose_best_reads_below_even_odds_has_nothing_safe() -> None:
    rng = np.random.default_rng(3)
    town = rng.normal(-2.0, 0.3, (200, 200)).astype(np.float32)
    town[:, 80:120] = rng.normal(-0.6, 0.2, (200, 40))  # the best it has: roofs at P 0.35
    lv = levels_from(town, np.ones(town.shape, bool), CFG, CELL_M)
    assert lv.nothing_safe and lv.best_logit < 0.0


def test_unknown_cells_never_count_and_too_little_seen_is_nothing_safe_yet() -> None:
    mean = _city(np.random.default_rng(4))
    known = np.zeros(mean.shape, bool)
    known[100:103, 100:103] = True  # less than one clearance disk
    assert levels_from(mean, known, CFG, CELL_M).nothing_safe
    # The lawn unknown: the best known ground is the sidewalk, and the lawn's cells do not count.
    known = np.ones(mean.shape, bool)
    known[30:60, 30:60] = False
    lv = levels_from(mean, known, CFG, CELL_M)
    assert 0.9 < lv.best_logit < 1.4
