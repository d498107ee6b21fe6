"""The clearance policy's ego-motion: registration on known shifts, scale, strips, drift."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dovesei.controller.policies.clearance_config import ClearanceConfig
from dovesei.controller.policies.clearance_map import footprint_width_m
from dovesei.controller.policies.clearance_motion import EgoMotion, phase_shift, tilt_offset_ne, to_body, to_ne

HFOV = math.radians(73.0)
GROUND_GSD = 0.1  # metres per cell of the synthetic ground


def _ground(seed: int = 0, side: int = 4000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(rng.random((side // 8, side // 8)).astype(np.float32), (0, 0), 1.5)
    g = cv2.resize(g, (side, side), interpolation=cv2.INTER_LINEAR)
    return (g - g.min()) / (g.max() - g.min())


def _view(ground: np.ndarray, north_m: float, east_m: float, alt_m: float, size: int = 352) -> np.ndarray:
    g = footprint_width_m(alt_m, HFOV) / size
    s = g / GROUND_GSD
    c = (size - 1) / 2.0
    row0 = (ground.shape[0] - 1) / 2.0 - north_m / GROUND_GSD
    col0 = (ground.shape[1] - 1) / 2.0 + east_m / GROUND_GSD
    m = np.array([[s, 0.0, col0 - s * c], [0.0, s, row0 - s * c]])
    return cv2.warpAffine(ground, m, (size, size), flags=cv2.INTER_AREA | cv2.WARP_INVERSE_MAP)


def test_phase_shift_recovers_known_pixel_shifts() -> None:
    rng = np.random.default_rng(0)
    ground = cv2.GaussianBlur(rng.random((300, 300)).astype(np.float32), (0, 0), 2.0)
    window = cv2.createHanningWindow((96, 96), cv2.CV_32F)
    ref = ground[100:196, 100:196].copy()
    for d_row, d_col in ((0, 0), (3, -5), (-7, 2), (10, 10)):
        cur = ground[100 - d_row:196 - d_row, 100 - d_col:196 - d_col].copy()  # content moves by +d
        dx, dy, response = phase_shift(ref, cur, window)
        assert (dx, dy) == pytest.approx((d_col, d_row), abs=0.3)
        assert response > 0.3


def test_frames_convert() -> None:
    assert to_ne(1.0, 0.0, math.pi / 2) == pytest.approx((0.0, 1.0))  # facing east, forward = east
    assert to_body(*to_ne(2.0, -3.0, 0.7), 0.7) == pytest.approx((2.0, -3.0))
    n, e = tilt_offset_ne(100.0, 0.0, math.radians(10.0), 0.0)  # nose up: the camera looks back
    assert n == pytest.approx(-100.0 * math.tan(math.radians(10.0))) and e == pytest.approx(0.0)


@pytest.mark.parametrize("alt_end", [100.0, 80.0])
def test_registration_measures_a_known_ground_shift_without_any_velocity(alt_end: float) -> None:
    ground = _ground(1)
    ego = EgoMotion(ClearanceConfig())
    ego.correct(_view(ground, 0.0, 0.0, 100.0), 0.5, 100.0, HFOV, 0.0)  # the keyframe
    # The vehicle moved 6 m north and 4 m west (and maybe descended); no velocity told it so.
    ego.predict(0.5, (0.0, 0.0, 0.0), 0.0)
    step = None
    for _ in range(6):  # the gain applies a share per frame; repeated frames converge
        step = ego.correct(_view(ground, 6.0, -4.0, alt_end), 0.5, alt_end, HFOV, 0.0)
    assert step is not None and step.registered
    assert (ego.north_m, ego.east_m) == pytest.approx((6.0, -4.0), abs=0.5)


def test_a_strip_constrains_only_the_across_direction() -> None:
    """Along a straight strip a shift is unobservable: the prediction is kept there."""
    img = np.zeros((352, 352), np.float32)
    img[:, 160:192] = 1.0  # a north-south strip
    ego = EgoMotion(ClearanceConfig())
    ego.correct(img, 0.5, 100.0, HFOV, 0.0)
    ego.predict(1.0, (5.0, 0.0, 0.0), 0.0)  # the velocity says 5 m north
    step = ego.correct(img, 1.0, 100.0, HFOV, 0.0)  # the image cannot tell
    assert step.registered
    assert ego.north_m == pytest.approx(5.0, abs=1e-6)


def test_drift_of_a_biased_noisy_velocity_estimate_stays_bounded() -> None:
    ground = _ground(2)
    rng = np.random.default_rng(0)
    cfg = ClearanceConfig()
    with_reg, dead = EgoMotion(cfg), EgoMotion(cfg.replace(reg_min_std=1.0))
    n = e = 0.0
    errs = []
    for k in range(80):  # 40 s at 2 Hz, flying 3 m/s north-east
        vel_true = (3.0, 2.0)
        n, e = n + vel_true[0] * 0.5, e + vel_true[1] * 0.5
        est = (vel_true[0] + 0.8 + rng.normal(0, 0.4), vel_true[1] - 0.6 + rng.normal(0, 0.4), 0.0)
        img = _view(ground, n, e, 90.0)
        for ego in (with_reg, dead):
            ego.predict(0.5, est, 0.0)
            ego.correct(img, 0.5, 90.0, HFOV, 0.0)
        errs.append(math.hypot(with_reg.north_m - n, with_reg.east_m - e))
    dead_err = math.hypot(dead.north_m - n, dead.east_m - e)
    assert dead_err > 30.0  # 40 s of a 1 m/s bias
    assert max(errs) < 5.0
    assert errs[-1] < 3.0
    # The bias was learnt (the truth minus the estimate is about (-0.8, +0.6) m/s).
    assert with_reg.bias_n_m_s < -0.3 and with_reg.bias_e_m_s > 0.2
