"""The clearance policy's ground map: fusion, decay, confidence, resolution, spots by clearance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.clearance.ground_map import (GroundMap, clearance_at, emphasise_dips, find_candidate,
                                                      find_spot, footprint_width_m, logit, look_weight, promise)

HFOV = math.radians(73.0)
CFG = ClearanceConfig()
# The map's tests are about geometry: the thresholds a scene would give (scene) are
# handed in as the policy hands them, in log-odds.
SPOT_P, PROBE_P = 0.84, 0.78
SPOT, PROBE = math.log(SPOT_P / (1 - SPOT_P)), math.log(PROBE_P / (1 - PROBE_P))


def _fuse(gmap: GroundMap, prob: np.ndarray, alt: float = 50.0, at: tuple[float, float] = (0.0, 0.0),
          times: int = 1, weight: float = 1.0) -> None:
    for _ in range(times):
        gmap.fuse(prob, alt, HFOV, 0.0, at[0], at[1], weight)


def test_fused_probability_is_the_log_odds_mean_not_a_certainty() -> None:
    gmap = GroundMap(CFG)
    gmap.follow(50.0, 0.0, 0.0)
    _fuse(gmap, np.full((352, 352), 0.7, np.float32), times=20)
    p, looks = gmap.at(0.0, 0.0)
    # Twenty looks of 0.7 stay 0.7: errors of one ground patch are not independent.
    assert p == pytest.approx(0.7, abs=1e-3)
    assert looks == pytest.approx(20.0)
    _fuse(gmap, np.full((352, 352), 0.3, np.float32), times=20)
    assert gmap.at(0.0, 0.0)[0] == pytest.approx(0.5, abs=1e-3)  # logit(0.7) = -logit(0.3)
    assert gmap.confidence()[gmap.n // 2, gmap.n // 2] == pytest.approx(1.0 - math.exp(-40.0 / CFG.looks_full))


def test_decay_fades_confidence_but_keeps_the_mean_and_unseen_cells_are_unknown() -> None:
    gmap = GroundMap(CFG)
    gmap.follow(50.0, 0.0, 0.0)
    _fuse(gmap, np.full((352, 352), 0.8, np.float32), times=4)
    gmap.decay(CFG.decay_tau_s)
    p, looks = gmap.at(0.0, 0.0)
    assert p == pytest.approx(0.8, abs=1e-3)
    assert looks == pytest.approx(4.0 * math.exp(-1.0), rel=1e-4)
    half_width = footprint_width_m(50.0, HFOV) / 2.0
    assert gmap.at(half_width + 10.0, 0.0) == (0.5, 0.0)  # never seen
    assert gmap.at(1e6, 0.0) == (0.5, 0.0)  # off the map


def test_a_shifted_view_lands_in_the_right_cells() -> None:
    gmap = GroundMap(CFG)
    gmap.follow(50.0, 0.0, 0.0)
    prob = np.full((352, 352), 0.1, np.float32)
    prob[:176, :] = 0.9  # the northern half of the image is safe
    _fuse(gmap, prob, at=(10.0, -5.0))  # the camera looks at 10 m north, 5 m west
    assert gmap.at(20.0, -5.0)[0] > 0.85  # north of the image centre
    assert gmap.at(0.0, -5.0)[0] < 0.15  # south of it


def test_resolution_follows_altitude_and_resampling_keeps_the_evidence() -> None:
    gmap = GroundMap(CFG)
    assert gmap.desired_cell_m(100.0) == 1.0
    assert gmap.desired_cell_m(40.0) == 0.5
    assert gmap.desired_cell_m(20.0) == 0.25
    gmap.follow(100.0, 0.0, 0.0)
    prob = np.full((352, 352), 0.1, np.float32)
    prob[:, 200:] = 0.9  # east is safe
    _fuse(gmap, prob, alt=100.0, times=3)
    assert gmap.follow(20.0, 0.0, 0.0) and gmap.cell_m == 0.25
    assert gmap.at(15.0, 15.0)[0] > 0.85 and gmap.at(0.0, -15.0)[0] < 0.15
    assert gmap.at(15.0, 15.0)[1] == pytest.approx(3.0, rel=1e-3)
    # Moving far re-centres the map on the vehicle (whole cells, evidence carried along).
    assert gmap.follow(20.0, 0.0, 30.0)
    row, col = gmap.cell_of(0.0, 30.0)
    assert abs(row - gmap.n / 2) < 2 and abs(col - gmap.n / 2) < 2
    assert gmap.at(15.0, 15.0)[0] > 0.85


def _built_mask_map(safe_width_m: float, alt: float = 30.0) -> GroundMap:
    """The map after several looks at a safe north-south band `safe_width_m` wide on unsafe ground."""
    gmap = GroundMap(CFG)
    gmap.follow(alt, 0.0, 0.0)
    width_m = footprint_width_m(alt, HFOV)
    cols = (np.arange(352) - 175.5) * width_m / 352
    prob = np.where(np.abs(cols) <= safe_width_m / 2.0, 0.9, 0.1).astype(np.float32)
    _fuse(gmap, np.tile(prob, (352, 1)), alt=alt, times=4)
    return gmap


def test_a_3_m_strip_is_rejected_and_a_12_m_lawn_accepted() -> None:
    strip = _built_mask_map(3.0)
    clear = strip.clearance_m(SPOT)
    assert clearance_at(strip, clear, 0.0, 0.0) <= 1.6
    assert find_spot(strip, clear, CFG, north_m=0.0, east_m=0.0, blacklist=()) is None
    lawn = _built_mask_map(12.0)
    clear = lawn.clearance_m(SPOT)
    spot = find_spot(lawn, clear, CFG, north_m=0.0, east_m=0.0, blacklist=())
    assert spot is not None
    assert spot.clearance_m >= CFG.required_clearance_m
    assert abs(spot.east_m) <= 6.0 - CFG.required_clearance_m + 0.3  # its whole disk is on the lawn
    assert 5.4 <= clearance_at(lawn, clear, 0.0, 0.0) <= 6.3  # the lawn's half-width
    assert spot.p_safe > 0.85 and 0.0 < spot.confidence < 1.0


def test_spots_respect_the_blacklist_and_the_search_radius() -> None:
    lawn = _built_mask_map(12.0)
    clear = lawn.clearance_m(SPOT)
    spot = find_spot(lawn, clear, CFG, north_m=0.0, east_m=0.0, blacklist=())
    assert spot is not None
    again = find_spot(lawn, clear, CFG, north_m=0.0, east_m=0.0, blacklist=((spot.north_m, spot.east_m),))
    assert again is None or math.hypot(again.north_m - spot.north_m, again.east_m - spot.east_m) > (
        CFG.required_clearance_m + CFG.refine_radius_m)
    tight = CFG.replace(search_radius_m=6.0, fence_margin_m=1.0)
    near = find_spot(lawn, clear, tight, north_m=0.0, east_m=0.0, blacklist=())
    assert near is None or math.hypot(near.north_m, near.east_m) <= tight.fence_m - tight.lock_out_m


def test_unknown_ground_is_never_a_spot() -> None:
    gmap = GroundMap(CFG)
    gmap.follow(30.0, 0.0, 0.0)
    _fuse(gmap, np.full((352, 352), 0.95, np.float32), alt=30.0, weight=0.5)  # half a look only
    assert find_spot(gmap, gmap.clearance_m(SPOT), CFG, north_m=0.0, east_m=0.0, blacklist=()) is None
    _fuse(gmap, np.full((352, 352), 0.95, np.float32), alt=30.0, times=3)
    assert find_spot(gmap, gmap.clearance_m(SPOT), CFG, north_m=0.0, east_m=0.0, blacklist=()) is not None


def test_a_promising_area_is_a_candidate_until_probed_and_a_poor_one_never() -> None:
    # From 100 m: a band reading 0.82 (a lawn smeared by the token grid: below the spot test,
    # above the probe threshold) 40 m east, and a 0.7 band 40 m west.
    gmap = GroundMap(CFG)
    gmap.follow(100.0, 0.0, 0.0)
    width_m = footprint_width_m(100.0, HFOV)
    cols = (np.arange(352) - 175.5) * width_m / 352
    prob = np.full(352, 0.1, np.float32)
    prob[np.abs(cols - 40.0) <= 8.0] = 0.82
    prob[np.abs(cols + 40.0) <= 8.0] = 0.7
    _fuse(gmap, np.tile(prob, (352, 1)), alt=100.0, times=3)
    clear = gmap.clearance_m(SPOT)
    assert find_spot(gmap, clear, CFG, north_m=0.0, east_m=0.0, blacklist=()) is None
    around = promise(gmap, CFG, 0.0, 0.0, 150.0)

    def candidate(skip=(), fence_m=CFG.fence_m, within_m=200.0, p=around):
        return find_candidate(gmap, p, CFG, north_m=0.0, east_m=0.0, skip=skip, fence_m=fence_m, within_m=within_m,
                              min_logit=PROBE)

    cand = candidate()
    assert cand is not None and abs(cand.east_m - 40.0) <= 4.0
    assert PROBE_P <= cand.p_safe <= 0.82 + 1e-6 and cand.distance_m == pytest.approx(math.hypot(cand.north_m, cand.east_m))
    # The nearest part of the band is preferred (the band runs north-south through the view).
    assert abs(cand.north_m) <= 2.0
    # Once probed, the band near that point is skipped; far along it, it is a candidate again.
    again = candidate(skip=((cand.north_m, cand.east_m),))
    assert again is not None and math.hypot(again.north_m - cand.north_m, again.east_m - cand.east_m) > CFG.probe_skip_m
    assert abs(again.east_m - 40.0) <= 4.0  # never the 0.7 band
    # Out of reach, beyond the fence, or outside the window the promise was read over: none.
    assert candidate(within_m=20.0) is None
    assert candidate(fence_m=30.0) is None
    assert candidate(p=promise(gmap, CFG, 0.0, -40.0, 20.0)) is None
    # The window's edge does not lower the promise: read over a small window round the band, a
    # cell reads as it does over a wide one.
    small = promise(gmap, CFG, 0.0, 40.0, 6.0)
    r, c = (int(round(v)) for v in gmap.cell_of(0.0, 40.0))
    assert small.disk[r - small.r0, c - small.c0] == pytest.approx(around.disk[r - around.r0, c - around.c0])


LAWN = SPOT_P + 0.05


def _blob_view(size: int = 352, blob_px: int = 6, depth: float = 0.045, seed: int = 0) -> np.ndarray:
    """A lawn a little above the safe threshold with a person-sized shallow dip (after CLIPSeg's
    smear, still above the threshold) and mild pixel noise."""
    rng = np.random.default_rng(seed)
    p = np.full((size, size), LAWN, np.float32) + rng.normal(0.0, 0.005, (size, size)).astype(np.float32)
    yy, xx = np.mgrid[:size, :size]
    p -= (depth * np.exp(-((yy - 150) ** 2 + (xx - 170) ** 2) / (2.0 * blob_px ** 2))).astype(np.float32)
    p[:, 300:] = 0.3  # a wide dark area (a road) at the side
    return np.clip(p, 0.0, 1.0)


def test_a_shallow_small_dip_is_deepened_below_the_safe_threshold_and_wide_areas_are_left() -> None:
    p = _blob_view()
    kernel = int(round(CFG.dip_kernel_frac * 352))
    out = emphasise_dips(p, kernel, CFG.dip_gain, 0.02)
    assert p[150, 170] >= SPOT_P  # as seen: the threshold misses the person
    assert out[150, 170] < SPOT_P  # deepened: now it is an obstacle
    # Flat lawn away from the dip and the edge keeps its reading (pixel noise is no dip) ...
    assert abs(float(np.median(out[20:100, 20:100])) - LAWN) < 0.01
    assert float(out[20:100, 20:100].min()) >= SPOT_P
    # ... and the wide dark road is not made darker than it is.
    assert abs(float(out[100:250, 320:340].mean()) - 0.3) < 0.02
    # Off: gain 0 returns the map as it was.
    assert emphasise_dips(p, kernel, 0.0) is p


@pytest.mark.parametrize("a,b", [(0.6, -0.8), (1.0, 0.0), (1.6, 0.8)])
def test_dips_in_log_odds_move_with_a_recalibration(a: float, b: float) -> None:
    """On log-odds, with the floor scaled as the scene's contrast scales, a recalibrated view is
    deepened into the recalibrated result: the person stays an obstacle under every calibration."""
    lg = logit(_blob_view(), CFG.p_clip)
    kernel = int(round(CFG.dip_kernel_frac * 352))
    base = emphasise_dips(lg, kernel, CFG.dip_gain, 0.1, clip=None)
    shifted = emphasise_dips(a * lg + b, kernel, CFG.dip_gain, 0.1 * a, clip=None)
    np.testing.assert_allclose(shifted, a * base + b, atol=2e-3 * a + 1e-4)
    assert shifted[150, 170] < a * SPOT + b <= float(shifted[20:100, 20:100].min())


def test_low_looks_outweigh_high_ones_by_the_token_area() -> None:
    assert look_weight(100.0, CFG) == pytest.approx(1.0)
    assert look_weight(20.0, CFG) == pytest.approx(25.0)
    assert look_weight(5.0, CFG) == CFG.look_weight_max
    gmap = GroundMap(CFG)
    gmap.follow(25.0, 0.0, 0.0)
    # Ten smeared looks from 100 m say 0.85; three sharp ones from 25 m say 0.3: the sharp ones win.
    _fuse(gmap, np.full((352, 352), 0.85, np.float32), alt=100.0, times=10, weight=look_weight(100.0, CFG))
    _fuse(gmap, np.full((352, 352), 0.3, np.float32), alt=25.0, times=3, weight=look_weight(25.0, CFG))
    assert gmap.at(0.0, 0.0)[0] < 0.45


def test_a_mask_lands_on_another_grid_where_its_ground_is() -> None:
    # A coarse map (1 m cells) and a fine one (0.25 m) centred elsewhere: a 10 x 10 cell square
    # marked on the coarse grid covers the same ground on the fine one.
    coarse, fine = GroundMap(CFG), GroundMap(CFG)
    coarse.follow(100.0, 0.0, 0.0)
    fine.follow(20.0, 12.0, -7.0)
    assert (coarse.cell_m, fine.cell_m) == (1.0, 0.25)
    mask = np.zeros((coarse.n, coarse.n), np.uint8)
    r0, c0 = (int(round(v)) for v in coarse.cell_of(20.0, -10.0))
    mask[r0:r0 + 10, c0:c0 + 10] = 1
    # The square's ground: from the north-west cell's outer edges to the south-east cell's.
    north_max, west = (v + d for v, d in zip(coarse.point_of(r0, c0), (0.5, -0.5)))
    north_min, east_max = (v + d for v, d in zip(coarse.point_of(r0 + 9, c0 + 9), (-0.5, 0.5)))
    onto = coarse.mask_onto(mask, fine)
    rows, cols = np.nonzero(onto)
    north, east = fine.point_of(rows, cols)
    # Fine cells whose centres lie inside it: 0.125 m within its edges.
    assert north.max() == pytest.approx(north_max - 0.125) and north.min() == pytest.approx(north_min + 0.125)
    assert east.min() == pytest.approx(west + 0.125) and east.max() == pytest.approx(east_max - 0.125)
    assert rows.size == 40 * 40
    # The same mask given as a window of the map (its cell (0, 0) at the map's (r0, c0)) lands alike.
    assert np.array_equal(coarse.mask_onto(mask[r0:r0 + 10, c0:c0 + 10].copy(), fine, r0, c0), onto)


def test_a_rechecked_target_stays_put_while_it_has_its_clearance_and_moves_when_it_lacks_it() -> None:
    lawn = _built_mask_map(16.0)
    clear = lawn.clearance_m(SPOT)
    need = CFG.required_clearance_m
    hyst = need * CFG.recheck_hysteresis

    def recheck(east_m: float, vehicle_east_m: float = 0.0):
        return find_spot(lawn, clear, CFG, north_m=0.0, east_m=vehicle_east_m, blacklist=(), near=(0.0, east_m),
                         within_m=CFG.refine_radius_m, need_m=hyst)

    # 2 m east of the lawn's centre line has 6 m of clearance: the target stays there, even with
    # the vehicle 3 m off to the west (the nearest qualifying cell would be west of it).
    kept = recheck(2.0, vehicle_east_m=-3.0)
    assert kept is not None and abs(kept.east_m - 2.0) <= lawn.cell_m and abs(kept.north_m) <= lawn.cell_m
    # 5 m east has ~3 m: enough to pass the re-check (hysteresis), not enough to stay: it moves in.
    inner = recheck(5.0)
    assert inner is not None and inner.east_m < 5.0 - 0.4 and inner.clearance_m >= need
    # 6.5 m east has only ~1.5 m: it moves inwards, to a cell with the clearance needed.
    moved = recheck(6.5)
    assert moved is not None and moved.east_m < 6.5 - 1.0 and moved.clearance_m >= need
