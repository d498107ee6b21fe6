"""The `dovesei` image pipeline and policy on hand-made heatmaps (REFERENCE.md steps 1-8).

Dynamic threshold and candidate extraction are also checked against literal, slow transcriptions
of the reference's loops (`_literal_*` below), so the faster implementations cannot drift.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from dovesei.benchmarks import policy as bench
from dovesei.controller.policies.base import Observation, PolicyInputError
from dovesei.controller.policies.registry import make_policy, policy_names
from dovesei.controller.policies.dovesei.config import DoveseiConfig, real_timing
from dovesei.controller.policies.dovesei.policy import (
    DoveseiPolicy,
    DoveseiState,
    LanderImage,
    dynamic_threshold,
    find_candidates,
    focus_target_px,
)
from dovesei.shared.errors import ConfigError

CFG = real_timing()
ROWS, COLS = CFG.grid_rows_px, CFG.grid_cols_px  # 352 x 353
DIAG = math.hypot(ROWS, COLS)
PROJ_100 = math.tan(math.radians(36.5)) * 100.0


# --- literal transcriptions of the reference (slow, obviously right) -------------------------


def _literal_threshold(prob: np.ndarray) -> tuple[np.ndarray | None, float | None]:
    start, steps, fraction = 0.85, 100, 0.10
    step = start / steps
    mask, thr, ok = prob > start, start, False
    for ti in range(steps + 1):
        if mask.sum() / mask.size < fraction:
            thr = start - step * ti
            mask = prob > thr
        else:
            ok = True
            break
    return ((mask * 255).astype(np.uint8), thr) if ok else (None, None)


def _literal_candidates(binary: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray, list]:
    binary = binary.copy()
    centre = np.asarray([ROWS / 2, COLS / 2])
    circle = np.zeros_like(binary)
    cv2.circle(circle, (int(centre[1]), int(centre[0])), int(radius_px), 255, -1)
    binary[circle != 255] = 0
    dist = cv2.distanceTransform(binary, cv2.DIST_L2, maskSize=3)
    cv2.normalize(dist, dist, 0, 1.0, cv2.NORM_MINMAX)
    _, cores = cv2.threshold(dist, 0.6, 1.0, cv2.THRESH_BINARY)
    contours, _ = cv2.findContours(cores.astype("uint8"), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    errs, scores, pixels = [[1.0, 0]], [0.0], [None]
    for cnt in contours:
        area, perimeter = cv2.contourArea(cnt), cv2.arcLength(cnt, True)
        if area == 0 or perimeter == 0:
            continue
        filled = np.zeros_like(dist)
        cv2.drawContours(filled, [cnt], contourIdx=-1, color=255, thickness=cv2.FILLED)
        inside = dist.copy()
        inside[filled != 255] = 0.0
        r, c = np.unravel_index(inside.argmax(), inside.shape)
        d = np.sqrt(((centre - [r, c]) ** 2).sum())
        scores.append((1 / perimeter) * area / (d + 1))
        errs.append([(centre[0] - r) / ROWS, -(centre[1] - c) / COLS])
        pixels.append((int(r), int(c)))
    order = np.argsort(scores)[::-1]
    return np.asarray(errs)[order], np.asarray(scores)[order], [pixels[i] for i in order]


def _grid(*disks: tuple[int, int, int]) -> np.ndarray:
    """A 0/255 352x353 grid with filled disks (row, col, radius)."""
    grid = np.zeros((ROWS, COLS), np.uint8)
    for row, col, radius in disks:
        cv2.circle(grid, (col, row), radius, 255, -1)
    return grid


def _random_binary(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    field = cv2.GaussianBlur(rng.random((ROWS, COLS)).astype(np.float32), (0, 0), 6.0)
    return np.where(field > np.quantile(field, 0.7), 255, 0).astype(np.uint8)


# --- dynamic threshold ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (0.9, 0.85),  # passes at once
        (0.5, 0.85 - 0.0085 * 42),  # first checked threshold strictly below 0.5
        (0.85, 0.85 - 0.0085),  # strict '>': 0.85 fails twice (step 0 repeats), 0.8415 passes
        (0.009, 0.85 - 0.0085 * 99),  # the last value checked
    ],
)
def test_dynamic_threshold_on_uniform_maps(value: float, expected: float) -> None:
    res = dynamic_threshold(np.full((64, 80), value, np.float32), CFG)
    assert res.threshold == pytest.approx(expected, abs=1e-12)
    assert res.mask_u8 is not None and res.mask_u8.dtype == np.uint8
    assert set(np.unique(res.mask_u8)) == {255}
    assert res.safe_fraction == 1.0


@pytest.mark.parametrize("value", [0.0, 0.0084])
def test_dynamic_threshold_fails_when_even_0_0085_leaves_too_few(value: float) -> None:
    res = dynamic_threshold(np.full((50, 50), value, np.float32), CFG)
    assert (res.mask_u8, res.threshold, res.safe_fraction) == (None, None, 0.0)


def test_dynamic_threshold_ten_percent_is_enough_one_pixel_less_fails() -> None:
    prob = np.zeros((100, 100), np.float32)
    prob.flat[:1000] = 0.9  # exactly 10 %: 'fraction < 0.10' is false, so 0.85 passes
    res = dynamic_threshold(prob, CFG)
    assert res.threshold == 0.85 and int(np.count_nonzero(res.mask_u8)) == 1000
    prob.flat[999] = 0.0  # 9.99 %, and every other pixel is 0: failure
    assert dynamic_threshold(prob, CFG).threshold is None


def test_dynamic_threshold_on_a_gradient_keeps_the_best_ten_percent() -> None:
    prob = np.tile(np.linspace(0.0, 0.5, 200, dtype=np.float32), (40, 1))  # P rises to the right
    res = dynamic_threshold(prob, CFG)
    # 10 % = the top 20 columns, P >= 180 * 0.5 / 199 = 0.4523: first checked value below is 0.4505.
    assert res.threshold == pytest.approx(0.85 - 0.0085 * 47)
    assert res.mask_u8 is not None
    assert 0.10 <= res.safe_fraction < 0.13
    assert not res.mask_u8[:, :170].any() and res.mask_u8[:, -20:].all()  # only the right edge


@pytest.mark.parametrize("seed", range(12))
def test_dynamic_threshold_matches_the_literal_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = [(352, 352), (48, 64), (7, 3)][seed % 3]
    kind = seed % 4
    if kind == 0:
        prob = rng.random(shape, dtype=np.float32) * rng.uniform(0.01, 1.0)
    elif kind == 1:
        prob = (rng.random(shape) ** 6).astype(np.float32)  # few high values
    elif kind == 2:
        prob = np.round(rng.random(shape) * 20).astype(np.float32) / 20  # many exact ties
    else:
        prob = np.float32(0.85) - np.float32(0.0085) * rng.integers(0, 101, shape).astype(np.float32)
    mask, thr = _literal_threshold(prob)
    res = dynamic_threshold(prob, CFG)
    assert res.threshold == thr
    if mask is None:
        assert res.mask_u8 is None
    else:
        np.testing.assert_array_equal(res.mask_u8, mask)


# --- candidates -------------------------------------------------------------------------------


def test_empty_map_gives_only_the_dummy_straight_ahead() -> None:
    cands = find_candidates(np.zeros((ROWS, COLS), np.uint8), DIAG, CFG)
    np.testing.assert_array_equal(cands.err_norm, [[1.0, 0.0]])
    np.testing.assert_array_equal(cands.scores, [0.0])
    assert cands.pixels_rc == (None,)


def test_single_disk_candidate_is_its_centre_with_the_expected_score() -> None:
    cands = find_candidates(_grid((100, 250, 30)), DIAG, CFG)
    assert cands.pixels_rc == ((100, 250), None)  # the disk, then the dummy
    np.testing.assert_allclose(cands.err_norm[0], [(176 - 100) / 352, (250 - 176.5) / 353])
    # Core = distance > 0.6 x max: a disk of radius ~30 - 18 = 12 px; area / perimeter = r / 2.
    dist_px = math.hypot(176 - 100, 176.5 - 250)
    assert cands.scores[0] == pytest.approx(6.0 / (dist_px + 1.0), rel=0.15)
    assert cands.scores[1] == 0.0


def test_closer_of_two_equal_blobs_wins_and_the_other_is_second() -> None:
    cands = find_candidates(_grid((176, 300, 30), (176, 100, 30)), DIAG, CFG)
    assert cands.pixels_rc == ((176, 100), (176, 300), None)
    assert cands.scores[0] > cands.scores[1] > cands.scores[2] == 0.0


def test_larger_of_two_equidistant_blobs_wins() -> None:
    cands = find_candidates(_grid((276, 176, 30), (76, 176, 40)), DIAG, CFG)
    assert cands.pixels_rc[0] == (76, 176)
    assert cands.pixels_rc[1] == (276, 176)


def test_a_blob_too_thin_for_the_global_cores_is_not_a_candidate() -> None:
    # Min-max normalisation is global: a 10 px disk next to a 40 px one has no core > 0.6.
    cands = find_candidates(_grid((176, 60, 10), (176, 260, 40)), DIAG, CFG)
    assert cands.pixels_rc == ((176, 260), None)


def test_equal_scores_go_to_the_later_contour() -> None:
    # Two mirror-image squares at the same distance: integer polygons give bit-equal scores, and
    # argsort()[::-1] of a short (stably sorted) list puts the later contour first.
    grid = np.zeros((ROWS, COLS), np.uint8)
    grid[66:127, 146:207] = 255
    grid[226:287, 146:207] = 255
    cands = find_candidates(grid.copy(), DIAG, CFG)
    assert cands.scores[0] == cands.scores[1] > 0.0
    dist = cv2.distanceTransform(grid, cv2.DIST_L2, 3)
    cv2.normalize(dist, dist, 0, 1.0, cv2.NORM_MINMAX)
    contours, _ = cv2.findContours((dist > 0.6).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    later_row = int(contours[-1][:, 0, 1].mean())
    assert abs(cands.pixels_rc[0][0] - later_row) < 3
    assert {cands.pixels_rc[0][0], cands.pixels_rc[1][0]} == {96, 256}


def test_focus_circle_edge_is_an_obstacle_and_hides_what_is_outside() -> None:
    full = np.full((ROWS, COLS), 255, np.uint8)
    cands = find_candidates(full, 50.0, CFG)  # all safe: the circle alone shapes the distance map
    assert cands.pixels_rc[0] == (176, 176)
    cands = find_candidates(_grid((40, 40, 20)), 60.0, CFG)  # the only blob lies outside
    assert cands.pixels_rc == (None,)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("radius_px", [DIAG, 120.7, 45.2])
def test_candidates_match_the_literal_reference(seed: int, radius_px: float) -> None:
    binary = _random_binary(seed)
    errs, scores, pixels = _literal_candidates(binary, radius_px)
    cands = find_candidates(binary.copy(), radius_px, CFG)
    assert len(scores) > (2 if radius_px == DIAG else 1)  # the maps have several cores
    np.testing.assert_array_equal(cands.scores, scores)
    np.testing.assert_array_equal(cands.err_norm, errs)
    assert list(cands.pixels_rc) == pixels


def _edge_cases() -> dict[str, np.ndarray]:
    """Grids whose safe pixels lie in a small box, touch the grid's edges, fill it, or are absent:
    the distance map is worked out over the box of the safe pixels, which these move about."""
    small = _grid((60, 290, 9), (75, 300, 5))  # one small corner of the grid
    edges = _random_binary(7)
    edges[:, :40] = 255  # touching the left, top and bottom edges
    corner = np.zeros((ROWS, COLS), np.uint8)
    corner[ROWS - 30:, COLS - 25:] = 255  # the bottom-right corner, edges included
    single = np.zeros((ROWS, COLS), np.uint8)
    single[200, 100] = 255
    return {"small": small, "edges": edges, "corner": corner, "single": single,
            "full": np.full((ROWS, COLS), 255, np.uint8), "empty": np.zeros((ROWS, COLS), np.uint8)}


@pytest.mark.parametrize("case", sorted(_edge_cases()))
@pytest.mark.parametrize("radius_px", [DIAG, 150.3])
def test_candidates_over_a_box_of_the_grid_match_the_literal_reference(case: str, radius_px: float) -> None:
    binary = _edge_cases()[case]
    errs, scores, pixels = _literal_candidates(binary, radius_px)
    cands = find_candidates(binary.copy(), radius_px, CFG)
    # Which of them hold a candidate besides the dummy (the small blob and the corner lie outside
    # the narrower circle; a grid with no obstacle at all, or a lone pixel, has no core).
    found = {"small": radius_px == DIAG, "edges": True, "corner": radius_px == DIAG, "single": False,
             "full": radius_px != DIAG, "empty": False}[case]
    assert (len(scores) >= 2) == found
    np.testing.assert_array_equal(cands.scores, scores)
    np.testing.assert_array_equal(cands.err_norm, errs)
    assert list(cands.pixels_rc) == pixels


# The EMA grid of a paper-experiment flight (dovesei, start 4) that a distance map worked out over
# the box's columns alone got wrong: rows 136-216, each safe from LEFT to RIGHT (exclusive).
_FLIGHT_LEFT = (176, 168, 164, 161, 159, 157, 155, 154, 152, 151, 150, 149, 148, 147, 146, 145, 145, 145, 145,
                145, 145, 144, 144, 144, 144, 144, 144, 144, 144, 144, 143, 143, 143, 143, 143, 143, 143, 143,
                143, 143, 143, 142, 142, 142, 142, 142, 142, 142, 142, 142, 143, 143, 143, 143, 143, 143, 144,
                144, 144, 144, 144, 144, 145, 145, 145, 145, 146, 147, 148, 149, 150, 151, 152, 154, 155, 157,
                159, 161, 164, 168, 176)
_FLIGHT_RIGHT = (177, 185, 189, 192, 194, 196, 198, 199, 201, 202, 203, 204, 205, 206, 207, 208, 209, 209, 210,
                 211, 211, 211, 211, 211, 211, 211, 211, 211, 211, 212, 212, 212, 212, 212, 212, 212, 212, 212,
                 212, 212, 212, 212, 211, 211, 211, 211, 211, 211, 211, 211, 211, 211, 211, 211, 211, 211, 210,
                 210, 210, 210, 210, 210, 210, 209, 209, 208, 207, 206, 205, 204, 203, 202, 201, 199, 198, 196,
                 194, 192, 189, 185, 177)


def _flight_grid() -> np.ndarray:
    grid = np.zeros((ROWS, COLS), np.uint8)
    for row, (left, right) in enumerate(zip(_FLIGHT_LEFT, _FLIGHT_RIGHT), start=136):
        grid[row, left:right] = 255
    return grid


@pytest.mark.parametrize("seed", range(8))
def test_candidates_in_a_narrow_focus_match_the_literal_reference(seed: int) -> None:
    # A narrow focus leaves the safe pixels in a small box of the grid, anywhere along its rows:
    # OpenCV's distance map rounds some values 1 ulp apart at another column offset, which moved
    # a candidate by 8 px (the flight's grid, seed 0) when only the box's columns were worked out.
    rng = np.random.default_rng(100 + seed)
    binary = _flight_grid() if seed == 0 else _random_binary(200 + seed)
    for radius_px in (rng.uniform(25.0, 90.0, 6) if seed else np.arange(38.0, 62.0, 2.0)):
        errs, scores, pixels = _literal_candidates(binary, float(radius_px))
        cands = find_candidates(binary.copy(), float(radius_px), CFG)
        np.testing.assert_array_equal(cands.scores, scores)
        np.testing.assert_array_equal(cands.err_norm, errs)
        assert list(cands.pixels_rc) == pixels


# --- focus radius -----------------------------------------------------------------------------


def _centre_disk_map() -> np.ndarray:
    prob = np.zeros((352, 352), np.float32)
    cv2.circle(prob, (176, 176), 80, 1.0, -1)
    return prob


def _run(policy: DoveseiPolicy, alt_m: float, cycles: int, prob: np.ndarray | None = None, t0: float = 0.0):
    prob = _centre_disk_map() if prob is None else prob
    return [policy.step(Observation(t0 + 0.5 * i, alt_m, prob)) for i in range(cycles)]


@pytest.mark.parametrize(
    ("alt_m", "state", "mult"),
    [(100.0, DoveseiState.AIMING, 6.0), (52.0, DoveseiState.LANDING, 2.0)],
)
def test_focus_radius_follows_the_closed_form(alt_m: float, state: DoveseiState, mult: float) -> None:
    policy = DoveseiPolicy(CFG)
    decisions = _run(policy, alt_m, 6 + 25)
    assert [d.state for d in decisions[:5]] == ["SENSOR_ERROR"] * 5
    assert all(d.state == state.value for d in decisions[5:])
    # Cycles 1-6 follow SEARCHING/SENSOR_ERROR: the target is the diagonal, r stays there.
    assert all(d.focus_radius_px == pytest.approx(DIAG) for d in decisions[:6])
    proj_m = math.tan(math.radians(36.5)) * alt_m
    target = int(mult * 176.5 * 2.0 / proj_m)
    for k, d in enumerate(decisions[6:], start=1):
        assert d.focus_radius_px == pytest.approx(target + (DIAG - target) * 0.9**k, rel=1e-12)


def test_focus_target_laws() -> None:
    proj_m = PROJ_100
    assert focus_target_px(DoveseiState.AIMING, proj_m, 300.0, CFG) == int(6 * 176.5 * 2 / proj_m) == 28
    assert focus_target_px(DoveseiState.LANDING, proj_m, 300.0, CFG) == int(2 * 176.5 * 2 / proj_m) == 9
    assert focus_target_px(DoveseiState.WAITING, proj_m, 123.4, CFG) == 123.4  # keeps the radius
    for other in (DoveseiState.SEARCHING, DoveseiState.RESTARTING, DoveseiState.CLIMBING,
                  DoveseiState.SENSOR_ERROR):
        assert focus_target_px(other, proj_m, 123.4, CFG) == pytest.approx(DIAG)


def test_nofocus_variant_keeps_the_diagonal() -> None:
    policy = make_policy("dovesei-nofocus")
    assert policy.name == "dovesei-nofocus"
    decisions = _run(policy, 100.0, 30)
    assert decisions[-1].state == "AIMING"
    assert all(d.focus_radius_px == pytest.approx(DIAG, abs=1e-12) for d in decisions)


# --- EMA --------------------------------------------------------------------------------------


def test_ema_starts_at_the_first_successful_heatmap() -> None:
    policy = DoveseiPolicy(CFG)
    _run(policy, 100.0, 3, prob=np.zeros((352, 352), np.float32))  # failures: no EMA yet
    assert policy.filtered_heatmap is None
    first = _centre_disk_map()
    policy.step(Observation(10.0, 100.0, first))
    h1 = cv2.resize(dynamic_threshold(first, CFG).mask_u8, (COLS, ROWS)).astype(np.float64)
    np.testing.assert_array_equal(policy.filtered_heatmap, h1)
    assert set(np.unique(h1)) > {0.0, 255.0}  # bilinear leaves grey edges that feed the EMA
    second = np.zeros((352, 352), np.float32)
    second[:, :120] = 1.0
    policy.step(Observation(10.5, 100.0, second))
    h2 = cv2.resize(dynamic_threshold(second, CFG).mask_u8, (COLS, ROWS)).astype(np.float64)
    np.testing.assert_allclose(policy.filtered_heatmap, h1 + (h2 - h1) / 30.0, rtol=0, atol=1e-9)


def test_ema_truncation_needs_128_and_the_border_is_cleared() -> None:
    image = LanderImage(CFG)
    image.filtered = np.full((ROWS, COLS), 127.9)  # truncates to 127: not > 127
    cands = image.process(np.zeros((ROWS, COLS), np.uint8) + 127, DoveseiState.SEARCHING, PROJ_100)
    assert cands.pixels_rc == (None,)
    image.filtered = np.full((ROWS, COLS), 128.0)
    cands = image.process(np.full((ROWS, COLS), 128, np.uint8), DoveseiState.SEARCHING, PROJ_100)
    assert cands.pixels_rc[0] is not None  # all safe but the 1-px border: a core in the middle


# --- the policy end to end --------------------------------------------------------------------


def test_policy_targets_a_disk_and_reports_heatmap_pixels() -> None:
    prob = np.zeros((352, 352), np.float32)
    cv2.circle(prob, (260, 120), 70, 1.0, -1)  # 12 % of the pixels: 0.85 passes
    policy = DoveseiPolicy(CFG)
    d = _run(policy, 100.0, 1, prob=prob)[0]
    assert d.threshold == 0.85
    row, col = d.target_px
    assert abs(row - 120) <= 1 and abs(col - 260) <= 1
    assert d.report.machine.err_m == pytest.approx(math.hypot(56 / 352, 83.5 / 353) * PROJ_100, rel=0.02)


def test_policy_failure_path_commands_a_saturated_searching_move() -> None:
    policy = DoveseiPolicy(CFG)
    decisions = _run(policy, 100.0, 6, prob=np.zeros((352, 352), np.float32))
    d = decisions[-1]
    assert d.state == "SEARCHING"
    assert d.threshold is None and d.target_px is None
    fwd, right, down = d.vel_body_frd_m_s
    assert fwd == pytest.approx(0.5 * 1000 * PROJ_100) and right == pytest.approx(0.5 * 1000 * PROJ_100)
    assert down == 0.0


def test_policy_converts_up_to_frd_down() -> None:
    policy = DoveseiPolicy(CFG)
    d_aiming = _run(policy, 100.0, 6)[-1]
    assert d_aiming.state == "AIMING"
    assert d_aiming.vel_body_frd_m_s[2] == pytest.approx(+0.03 * 100.0)  # descending: +down
    assert d_aiming.yaw_rate_rad_s == 0.0
    policy.reset()
    d_landing = _run(policy, 52.0, 6)[-1]
    assert d_landing.state == "LANDING"
    assert d_landing.vel_body_frd_m_s[2] == pytest.approx(0.06 * 52.0)


def test_ticks_without_a_heatmap_hold_the_last_decision() -> None:
    policy = DoveseiPolicy(CFG)
    first = policy.step(Observation(0.0, 100.0, None))
    assert first.state == "SENSOR_ERROR" and first.vel_body_frd_m_s == (0.0, 0.0, 0.0)
    d = policy.step(Observation(0.05, 100.0, _centre_disk_map()))
    assert d.report.machine.dt_s == CFG.decision_period_s  # no previous cycle: the nominal period
    for i in range(10):
        assert policy.step(Observation(0.1 + 0.05 * i, 100.0, None)) is d
    d2 = policy.step(Observation(1.3, 100.0, _centre_disk_map()))
    assert d2.report.machine.dt_s == pytest.approx(1.25)  # measured between cycles, on the data clock
    assert d2.report.machine.cycles == 2
    assert policy.step(Observation(1.3, 100.0, _centre_disk_map())) is d2  # dt == 0: skipped


def test_non_finite_altitude_is_a_sensor_error_and_leaves_the_ema_alone() -> None:
    policy = DoveseiPolicy(CFG)
    _run(policy, 100.0, 6)
    ema = policy.filtered_heatmap
    d = policy.step(Observation(10.0, math.nan, np.zeros((352, 352), np.float32) + 1.0))
    assert d.state == "SENSOR_ERROR"
    np.testing.assert_array_equal(policy.filtered_heatmap, ema)


def test_landed_is_terminal() -> None:
    policy = DoveseiPolicy(CFG)
    d = _run(policy, 4.0, 1)[0]
    assert d.state == "LANDED"
    assert _run(policy, 100.0, 3, t0=5.0)[-1] is d


def test_reset_restarts_from_scratch() -> None:
    policy = DoveseiPolicy(CFG)
    _run(policy, 100.0, 10)
    policy.reset()
    assert policy.state is DoveseiState.SEARCHING and policy.filtered_heatmap is None
    assert _run(policy, 100.0, 1)[0].state == "SENSOR_ERROR"


@pytest.mark.parametrize(
    ("obs", "match"),
    [
        (Observation(0.0, 100.0, np.zeros((3, 4, 2), np.float32)), "2-D"),
        (Observation(0.0, 100.0, np.full((4, 4), np.nan, np.float32)), "finite"),
        (Observation(0.0, 100.0, np.full((4, 4), 1.5, np.float32)), r"\[0, 1\]"),
        (Observation(0.0, 100.0, np.zeros((4, 4), np.uint8)), "floats"),
        (Observation(math.inf, 100.0, None), "t_s"),
        (Observation(0.0, 100.0, None, hfov_rad=0.0), "hfov_rad"),
    ],
)
def test_bad_observations_raise_a_clear_policy_input_error(obs: Observation, match: str) -> None:
    with pytest.raises(PolicyInputError, match=match):
        DoveseiPolicy(CFG).step(obs)


def test_time_running_backwards_is_rejected() -> None:
    policy = DoveseiPolicy(CFG)
    _run(policy, 100.0, 2, t0=10.0)
    with pytest.raises(PolicyInputError, match="backwards"):
        policy.step(Observation(9.0, 100.0, None))


def test_make_policy_names_presets_and_errors() -> None:
    assert policy_names() == ["clearance", "dovesei", "dovesei-nofocus"]
    assert make_policy("dovesei", "reference").config.timer_scale == pytest.approx(0.065)
    assert make_policy("dovesei").config.timing_name == "real"
    with pytest.raises(ValueError, match="dovesei-nofocus"):
        make_policy("nope")
    with pytest.raises(ConfigError, match="reference"):
        make_policy("dovesei", "bogus")
    with pytest.raises(ConfigError, match="ema_beta"):
        DoveseiConfig(ema_beta=0.0)
    with pytest.raises(ConfigError, match="unexpected"):
        CFG.replace(no_such_field=1)


def test_bench_prints_json_figures(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["--cycles", "5", "--warmup", "1", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["size_px"] == 352 and result["opencv_threads"] == 1
    assert 0.0 < result["median_ms"] <= result["p99_ms"] <= result["max_ms"]


def test_bench_search_scene_times_clearance_searching(capsys: pytest.CaptureFixture[str]) -> None:
    # Nothing in the search scene is safe enough for a spot: every timed cycle is a search or a
    # probe, the states the landing scene never reaches.
    assert bench.main(["--policy", "clearance", "--scene", "search", "--cycles", "30", "--warmup", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["scene"] == "search"
    assert set(result["states"]) <= {"SEARCH", "PROBE"} and sum(result["states"].values()) == 30
    assert set(result["state_median_ms"]) == set(result["states"])
    with pytest.raises(SystemExit):
        bench.main(["--scene", "nowhere"])
