"""The scene's thresholds (scene): read off the map's own log-odds, they move with any
recalibration logit P' = a logit P + b, a scene of one class is judged by the floor alone, one
material in patches that read a little apart passes all of them, and a scene whose best reads
below even odds has nothing safe in it."""

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


def test_a_scene_of_one_material_in_patches_that_read_apart_passes_its_better_patches() -> None:
    """Sand with a patch of gravel reading 0.3 log-odds lower: the contrast is the patches', and a
    threshold a fifth of it below the best disk would fail half the sand (the best disk is the
    top of the sand's own spread). The threshold admits the sand; the gravel sits at its edge."""
    rng = np.random.default_rng(5)
    sand = rng.normal(2.1, 0.03, (200, 200)).astype(np.float32)
    sand[50:, :] = rng.normal(1.8, 0.03, (150, 200))  # the gravel: three quarters, the median
    known = np.ones(sand.shape, bool)
    lv = levels_from(sand, known, CFG, CELL_M)
    assert lv.contrast_logit > 0.2  # two "classes" by contrast against the per-cell noise
    spot = lv.spot_for(0.03, CFG)
    assert spot == pytest.approx(lv.best_logit * (1.0 - CFG.level_slack_frac), abs=1e-6)
    assert float((sand[:50] >= spot).mean()) > 0.999
    assert lv.gate_logit <= spot
    # A city keeps its contrast's threshold: the sidewalk stays out (see the recalibration test).
    city = levels_from(_city(np.random.default_rng(6)), known, CFG, CELL_M)
    assert city.spot_for(0.15, CFG) > 1.1 + 3 * 0.15


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
