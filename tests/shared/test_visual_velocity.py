"""Visual velocity (dovesei.shared.visual_velocity): known motions over a textured ground plane.

The views come from `tests.shared.ground`, a ray caster written apart from the estimator, so the
geometry is checked against an independent model.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dovesei.shared.codec import decode, encode
from dovesei.shared.messages import FieldError, Stamp, VisualOdometry
from dovesei.shared.visual_velocity import (
    INVALID_VAR_M2_S2, FrameMeta, VisualVelocity, VisualVelocityConfig, estimate, odometry_message, prepare,
)
from dovesei.shared.errors import ConfigError
from tests.shared.ground import HFOV, ned_to_body, view

DT = 0.1


def pair(alt: float, vel_ned=(0.0, 0.0, 0.0), yaw0: float = 0.4, yaw_rate: float = 0.0,
         att0=(0.0, 0.0), att1=(0.0, 0.0), meta_alt1: float | None = None, **meta1):
    """Frames 0 and 1 (DT apart) of a vehicle flying vel_ned, and their metadata."""
    alt1 = alt + vel_ned[2] * -DT
    yaw1 = yaw0 + yaw_rate * DT
    gsd = alt / 400.0
    a = view(0.0, 0.0, alt, yaw0, *att0, gsd=gsd)
    b = view(vel_ned[0] * DT, vel_ned[1] * DT, alt1, yaw1, *att1, gsd=gsd)
    m0 = FrameMeta(0, 10.0, alt, HFOV, att0[0], att0[1], yaw0)
    fields = dict(seq=1, t_s=10.0 + DT, alt_agl_m=alt1 if meta_alt1 is None else meta_alt1, hfov_rad=HFOV,
                  roll_rad=att1[0], pitch_rad=att1[1], yaw_rad=yaw1)
    fields.update(meta1)
    return a, b, m0, FrameMeta(**fields)


def run_pair(a, b, m0, m1, config: VisualVelocityConfig = VisualVelocityConfig()):
    return estimate(prepare(a, m0, config), prepare(b, m1, config), config)


def assert_close(est, truth_body, rel: float = 0.03, abs_m_s: float = 0.05) -> None:
    err = np.linalg.norm(np.array(est.vel_body_frd_m_s[:2]) - truth_body[:2])
    assert est.valid, est.reason
    assert err <= rel * np.linalg.norm(truth_body[:2]) + abs_m_s, (est.vel_body_frd_m_s, truth_body)


# ---------------------------------------------------------------------------------------- geometry


@pytest.mark.parametrize("alt", [20.0, 50.0, 100.0])
def test_known_translation_gives_the_velocity_at_each_altitude(alt: float) -> None:
    vel_ned = (4.0, -2.5, 0.0)
    est = run_pair(*pair(alt, vel_ned, yaw0=0.4))
    assert_close(est, ned_to_body(vel_ned, 0.0, 0.0, 0.4))
    assert est.quality > 0.6 and est.n_inliers >= 50
    # The variance is honest but not useless: 0.5 mrad of attitude uncertainty per frame alone is
    # 0.7 m/s at 100 m and 10 Hz, and the residual adds little on a clean view.
    sd = math.sqrt(est.vel_var_m2_s2)
    assert 0.1 < sd < 0.2 + 0.008 * alt
    assert (est.prev_seq, est.seq, est.dt_s) == (0, 1, pytest.approx(DT))


def test_hover_reads_zero() -> None:
    est = run_pair(*pair(60.0, (0.0, 0.0, 0.0)))
    assert est.valid and np.linalg.norm(est.vel_body_frd_m_s) < 0.05


def test_altitude_scales_the_velocity() -> None:
    # The same pixels told a wrong altitude give a proportionally wrong speed: the scale is the altitude's.
    a, b, m0, m1 = pair(50.0, (5.0, 0.0, 0.0), yaw0=0.0)
    right = run_pair(a, b, m0, m1)
    doubled = run_pair(a, b, FrameMeta(0, 10.0, 100.0, HFOV), FrameMeta(1, 10.0 + DT, 100.0, HFOV))
    assert right.vel_body_frd_m_s[0] == pytest.approx(5.0, rel=0.03)
    assert doubled.vel_body_frd_m_s[0] == pytest.approx(10.0, rel=0.03)


def test_yaw_between_frames_is_removed() -> None:
    # 0.25 rad of yaw in one frame (2.5 rad/s) shifts the image corners by ~60 px.
    a, b, m0, m1 = pair(40.0, (3.0, 1.0, 0.0), yaw0=1.0, yaw_rate=2.5)
    est = run_pair(a, b, m0, m1)
    assert_close(est, ned_to_body((3.0, 1.0, 0.0), 0.0, 0.0, 1.0 + 2.5 * DT))
    # Spinning in place reads as no motion...
    spin = run_pair(*pair(40.0, (0.0, 0.0, 0.0), yaw0=-2.0, yaw_rate=2.5))
    assert spin.valid and np.linalg.norm(spin.vel_body_frd_m_s[:2]) < 0.1
    # ...and only because of the yaw: told the heading did not change, the same frames do not agree.
    wrong = run_pair(a, b, m0, FrameMeta(1, 10.0 + DT, 40.0, HFOV, yaw_rad=1.0))
    assert not wrong.valid or np.linalg.norm(np.array(wrong.vel_body_frd_m_s[:2]) - est.vel_body_frd_m_s[:2]) > 1.0


def test_roll_and_pitch_are_removed() -> None:
    # Tilting by 0.1 rad moves the image by ~22 work px, the image of a 4 m shift at 40 m: it must
    # not be read as a velocity. The truth is the level velocity seen in the tilted body.
    vel_ned = (5.0, 0.0, 0.0)
    att1 = (0.1, -0.15)
    est = run_pair(*pair(40.0, vel_ned, yaw0=0.0, att0=(-0.05, 0.05), att1=att1))
    truth = ned_to_body(vel_ned, att1[0], att1[1], 0.0)
    assert_close(est, truth, rel=0.04)
    tilt_only = run_pair(*pair(40.0, (0.0, 0.0, 0.0), yaw0=0.0, att0=(0.0, 0.0), att1=att1))
    assert tilt_only.valid and np.linalg.norm(tilt_only.vel_body_frd_m_s) < 0.2


def test_a_wrong_attitude_tag_is_measured_and_removed_and_the_variance_still_says_so() -> None:
    # The newer frame tagged 5 mrad off in roll and pitch at 60 m: taken at its word the velocity
    # would be off by 60 x 7 mrad / 0.1 s = 4.2 m/s. The perspective the tilt leaves far from the
    # axis gives it away: the fit measures it and removes it, and the variance still counts it.
    a, b, m0, m1 = pair(60.0, (3.0, 1.0, 0.0), yaw0=0.5)
    right = run_pair(a, b, m0, m1)
    wrong = run_pair(a, b, m0, FrameMeta(1, m1.t_s, m1.alt_agl_m, HFOV, 0.005, -0.005, m1.yaw_rad))
    truth = ned_to_body((3.0, 1.0, 0.0), 0.0, 0.0, 0.5)
    assert_close(wrong, truth, rel=0.04)
    assert wrong.vel_var_m2_s2 > 4 * right.vel_var_m2_s2 and math.sqrt(wrong.vel_var_m2_s2) > 2.0


@pytest.mark.parametrize("hfov_deg", [10.0, 4.0])
def test_in_a_narrow_view_a_wrong_tag_is_never_a_confident_wrong_velocity(hfov_deg: float) -> None:
    # A narrow view sees little perspective: the tilt is harder to tell from a shift (at 4 deg the
    # tag's 5 mrad is 25 px, seeded so far off that the tracks fail). Whether the fit can remove
    # it or not, an estimate that claims to be valid stays inside what its variance admits.
    hfov = math.radians(hfov_deg)
    gsd = 60.0 * math.tan(hfov / 2) / 320  # the texture at about the view's own pixel size
    a = view(0.0, 0.0, 60.0, 0.5, gsd=gsd, hfov=hfov)
    b = view(0.3, 0.1, 60.0, 0.5, gsd=gsd, hfov=hfov)
    m0 = FrameMeta(0, 10.0, 60.0, hfov, 0.0, 0.0, 0.5)
    right = run_pair(a, b, m0, FrameMeta(1, 10.0 + DT, 60.0, hfov, 0.0, 0.0, 0.5))
    wrong = run_pair(a, b, m0, FrameMeta(1, 10.0 + DT, 60.0, hfov, 0.005, -0.005, 0.5))
    truth = ned_to_body((3.0, 1.0, 0.0), 0.0, 0.0, 0.5)
    assert_close(right, truth, rel=0.04)
    err = np.linalg.norm(np.array(wrong.vel_body_frd_m_s[:2]) - truth[:2])
    assert not wrong.valid or (err <= 2.45 * math.sqrt(wrong.vel_var_m2_s2)
                               and wrong.vel_var_m2_s2 > 4 * right.vel_var_m2_s2)
    assert wrong.valid or wrong.vel_var_m2_s2 == INVALID_VAR_M2_S2


def test_descent_is_measured_from_the_image_scale() -> None:
    # 4 m/s down at 40 m: frame 1 is 0.4 m lower, the image 1 % larger.
    a, b, m0, m1 = pair(40.0, (1.0, 0.0, 4.0), yaw0=0.0)
    est = run_pair(a, b, m0, m1)
    assert est.valid and est.vel_body_frd_m_s[2] == pytest.approx(4.0, abs=0.5)
    assert est.vel_body_frd_m_s[0] == pytest.approx(1.0, abs=0.1)


def test_the_texture_threshold_is_in_grey_levels_per_pixel() -> None:
    # A ramp of g grey levels per pixel: the structure tensor's larger eigenvalue reads (2 g / 255)^2,
    # the scale the config's min_gradient is converted with.
    g = 3.0
    ramp = np.tile((np.arange(64) * g).astype(np.uint8), (64, 1))
    eig = cv2.cornerEigenValsAndVecs(ramp, 5, 3)[..., 0]
    assert float(np.median(eig[16:48, 16:48])) == pytest.approx((2 * g / 255) ** 2, rel=0.01)


# ---------------------------------------------------------------------------------------- failures


def test_a_blank_view_is_invalid() -> None:
    blank = np.full((480, 640, 3), 128, np.uint8)
    m0, m1 = FrameMeta(0, 0.0, 50.0, HFOV), FrameMeta(1, DT, 50.0, HFOV)
    est = run_pair(blank, blank, m0, m1)
    assert not est.valid and est.quality == 0.0 and "texture" in est.reason
    assert est.vel_body_frd_m_s == (0.0, 0.0, 0.0) and est.vel_var_m2_s2 == INVALID_VAR_M2_S2
    # Sensor noise on a blank view is not texture either.
    rng = np.random.default_rng(1)
    noisy = [np.clip(128 + rng.normal(0, 2, (480, 640)), 0, 255).astype(np.uint8) for _ in range(2)]
    assert not run_pair(noisy[0], noisy[1], m0, m1).valid


def test_a_blurred_view_is_invalid() -> None:
    a, b, m0, m1 = pair(50.0, (3.0, 0.0, 0.0))
    sharp = run_pair(a, b, m0, m1)
    blur = [cv2.GaussianBlur(x, (0, 0), 12) for x in (a, b)]
    est = run_pair(blur[0], blur[1], m0, m1)
    assert sharp.valid and not est.valid and est.quality < sharp.quality


def test_unrelated_frames_give_no_velocity() -> None:
    # Two different patches of ground (a failed match): textured, but nothing tracks consistently.
    a = view(0.0, 0.0, 50.0)
    b = view(300.0, -200.0, 50.0, yaw=2.0)
    est = run_pair(a, b, FrameMeta(0, 0.0, 50.0, HFOV), FrameMeta(1, DT, 50.0, HFOV))
    assert not est.valid and est.vel_body_frd_m_s == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("alt1, words", [
    (float("nan"), "altitude"), (float("inf"), "altitude"), (-5.0, "altitude"), (0.2, "altitude"),
    (1e6, "altitude"), (80.0, "jumped"),
])
def test_a_bad_altitude_is_invalid(alt1: float, words: str) -> None:
    a, b, m0, m1 = pair(50.0, (3.0, 0.0, 0.0), meta_alt1=alt1)
    est = run_pair(a, b, m0, m1)
    assert not est.valid and words in est.reason and est.vel_body_frd_m_s == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("meta1, words", [
    ({"t_s": 10.0}, "time"), ({"t_s": 9.0}, "time"), ({"t_s": float("nan")}, "time"), ({"t_s": 15.0}, "time"),
    ({"roll_rad": float("nan")}, "attitude"), ({"pitch_rad": 1.4}, "tilted"), ({"hfov_rad": 0.0}, "field of view"),
])
def test_bad_times_and_attitudes_are_invalid(meta1: dict, words: str) -> None:
    est = run_pair(*pair(50.0, (3.0, 0.0, 0.0), **meta1))
    assert not est.valid and words in est.reason


def test_an_implausible_speed_is_invalid() -> None:
    # A real 6 m shift at 50 m, but stamped 5 ms apart: 1200 m/s is no velocity a multirotor flies.
    est = run_pair(*pair(50.0, (60.0, 0.0, 0.0), t_s=10.005))
    assert not est.valid and "implausible speed" in est.reason


def test_bad_images_and_configs_are_refused_in_one_line() -> None:
    meta = FrameMeta(0, 0.0, 50.0, HFOV)
    for bad in (np.zeros((480, 640), np.float32), np.zeros((10, 10), np.uint8), [[1, 2]],
                np.zeros((48, 64, 4), np.uint8)):
        with pytest.raises(ValueError, match="visual velocity needs") as info:
            prepare(bad, meta)
        assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="min_quality"):
        VisualVelocityConfig(min_quality=1.5)
    with pytest.raises(ConfigError, match="work_width_px"):
        VisualVelocityConfig(work_width_px=True)


# ---------------------------------------------------------------------------------------- stream and message


def _stream(alt: float, frames: int, vel_ne=(2.0, 2.0)):
    vv = VisualVelocity()
    outs = []
    for k in range(frames):
        image = view(vel_ne[0] * DT * k, vel_ne[1] * DT * k, alt, 0.0, gsd=alt / 400.0, rgb=False)
        outs.append(vv.update(image, FrameMeta(k, DT * k, alt, HFOV)))
    return vv, outs


def test_the_stream_compares_each_frame_with_the_one_before_at_20_m() -> None:
    vv, outs = _stream(20.0, 4)
    assert vv.config.baseline_s(20.0) == pytest.approx(DT)
    assert outs[0] is None
    for k, est in enumerate(outs[1:], start=1):
        assert (est.prev_seq, est.seq) == (k - 1, k)
        assert est.dt_s == pytest.approx(DT)
        assert_close(est, np.array([2.0, 2.0, 0.0]))


def test_from_high_up_the_stream_compares_over_half_a_second() -> None:
    # At 100 m each frame's attitude tag error is divided by 0.5 s instead of 0.1 s: the frame
    # five back once there is one (the oldest kept before), the same velocity, dt_s saying so.
    vv, outs = _stream(100.0, 9)
    assert vv.config.baseline_s(100.0) == pytest.approx(0.5) and vv.config.baseline_s(1000.0) == pytest.approx(0.5)
    assert outs[0] is None
    pairs = [(est.prev_seq, est.seq) for est in outs[1:]]
    assert pairs == [(0, 1), (0, 2), (0, 3), (0, 4), (0, 5), (1, 6), (2, 7), (3, 8)]
    for est in outs[1:]:
        assert est.dt_s == pytest.approx(DT * (est.seq - est.prev_seq))
        assert_close(est, np.array([2.0, 2.0, 0.0]))
    # Time running back starts the stream afresh (the estimate says why, nothing older is used).
    back = vv.update(view(0.0, 0.0, 100.0, 0.0, gsd=0.25, rgb=False), FrameMeta(9, 0.3, 100.0, HFOV))
    assert not back.valid and back.prev_seq == 8
    after = vv.update(view(0.2, 0.2, 100.0, 0.0, gsd=0.25, rgb=False), FrameMeta(10, 0.4, 100.0, HFOV))
    assert after.prev_seq == 9


def _tagged_stream(alt: float, frames: int, tag_sd_rad: float, seed: int = 3):
    """A stream flying 2 m/s north-east over level views whose tags are each off by N(0, tag_sd) in
    roll and pitch: (the stream, its estimates, the same pairs estimated one by one)."""
    rng = np.random.default_rng(seed)
    vv = VisualVelocity()
    prepared, outs = [], []
    for k in range(frames):
        image = view(0.2 * k, 0.2 * k, alt, 0.3, gsd=alt / 400.0, rgb=False)
        roll, pitch = rng.normal(0.0, tag_sd_rad, 2) if tag_sd_rad > 0 else (0.0, 0.0)
        meta = FrameMeta(k, DT * k, alt, HFOV, float(roll), float(pitch), 0.3)
        prepared.append(prepare(image, meta, vv.config))
        outs.append(vv.update(image, meta))
    alone = [None if est is None else estimate(prepared[est.prev_seq], prepared[est.seq], vv.config)
             for est in outs]
    return vv, outs, alone


def test_the_stream_measures_tags_worse_than_stated_and_its_variance_counts_them() -> None:
    # Tags off by 2 mrad per frame and axis where 0.5 is stated: two frames differ by 2.8 mrad,
    # 40 m x 2.8 mrad / 0.2 s = 0.57 m/s per axis where the stated error would say 0.14.
    alt, sd = 40.0, 0.002
    vv, outs, alone = _tagged_stream(alt, 60, sd)
    measured = vv.tags.var_rad2
    assert 0.5 * 2 * sd ** 2 <= measured <= 2.0 * 2 * sd ** 2, math.sqrt(measured / 2)
    late = [(est, one) for est, one in zip(outs[-20:], alone[-20:]) if est is not None and est.valid]
    assert len(late) >= 15
    for est, one in late:
        # The velocity is the pair's own; only the variance learned the tags.
        assert est.vel_body_frd_m_s == one.vel_body_frd_m_s
        # (what the meter held when it was made: within the last 20 fits of the final figure)
        assert est.vel_var_m2_s2 >= 0.6 * alt ** 2 * measured / est.dt_s ** 2 >= 4 * alt ** 2 * 2 * 0.0005 ** 2 / est.dt_s ** 2


def test_exact_tags_leave_the_stated_error_in_place() -> None:
    vv, outs, alone = _tagged_stream(40.0, 30, 0.0)
    assert vv.tags.var_rad2 < 2 * 0.0005 ** 2
    for est, one in zip(outs, alone):
        assert (est is None and one is None) or est == one


def test_messages_always_build_and_survive_the_codec() -> None:
    a, b, m0, m1 = pair(50.0, (3.0, 1.0, 0.0))
    good = run_pair(a, b, m0, m1)
    msg = odometry_message(good, m1, vehicle_id="uav1", stamp=Stamp(10.1, "vehicle"))
    back = decode(encode(msg), VisualOdometry)
    assert back.valid and back.vel_body_frd_m_s == good.vel_body_frd_m_s and back.frame_seq == 1
    assert back.yaw_rad == pytest.approx(m1.yaw_rad) and back.alt_agl_m == pytest.approx(m1.alt_agl_m)
    # A NaN altitude: the estimate is invalid and the message carries zeros, never the NaN.
    bad_meta = FrameMeta(1, 10.1, float("nan"), HFOV, yaw_rad=float("inf"))
    bad = run_pair(a, b, m0, bad_meta)
    msg = odometry_message(bad, bad_meta, vehicle_id="uav1", stamp=Stamp(10.1, "vehicle"))
    back = decode(encode(msg), VisualOdometry)
    assert not back.valid and back.alt_agl_m == 0.0 and back.yaw_rad == 0.0 and back.vel_body_frd_m_s == (0, 0, 0)
    # A valid estimate paired with a frame whose attitude is not finite is not let through as valid.
    msg = odometry_message(good, bad_meta, vehicle_id="uav1", stamp=Stamp(10.1, "vehicle"))
    assert not msg.valid and msg.vel_var_m2_s2 == INVALID_VAR_M2_S2


def test_each_frame_says_where_its_texture_lies_on_level_ground() -> None:
    textured = view(0.0, 0.0, 100.0, 0.0, 0.0, 0.0, gsd=0.25)
    grey = cv2.cvtColor(textured, cv2.COLOR_RGB2GRAY) if textured.ndim == 3 else textured
    h, w = grey.shape[:2]
    meta = FrameMeta(0, 0.0, 100.0, HFOV)
    # All over: nearly every cell, centred on the nadir.
    full = prepare(grey, meta)
    assert full.texture_share > 0.9 and math.hypot(*full.texture_offset) < 0.05
    # A coast along the left third of a view over calm water: a third of the cells, to the right of
    # the nadir by minus two thirds of the half view (tan(36.5 deg) = 0.74 per metre of altitude).
    coast = np.full_like(grey, 90)
    coast[:, : w // 3] = grey[:, : w // 3]
    left = prepare(coast, meta)
    half = math.tan(HFOV / 2)
    assert 0.25 < left.texture_share < 0.4
    assert left.texture_offset[1] == pytest.approx(-2 / 3 * half, abs=0.08) and abs(left.texture_offset[0]) < 0.05
    # Rolled 10 deg right, the image's left edge looks further left on the ground: levelled, the
    # texture's centre moves left too (by about tan 10 deg), forward stays put.
    rolled = prepare(coast, FrameMeta(0, 0.0, 100.0, HFOV, roll_rad=math.radians(10.0)))
    assert rolled.texture_offset[1] < left.texture_offset[1] - 0.1 and abs(rolled.texture_offset[0]) < 0.05
    # Nothing: no share, no offset; and the estimate and the message carry the newer frame's.
    blank = prepare(np.full_like(grey, 90), meta)
    assert blank.texture_share == 0.0 and blank.texture_offset == (0.0, 0.0)
    est = estimate(blank, left)
    assert not est.valid and est.texture_share == left.texture_share and est.texture_offset == left.texture_offset
    msg = odometry_message(est, left.meta, vehicle_id="uav1", stamp=Stamp(0.1, "vehicle"))
    back = decode(encode(msg), VisualOdometry)
    assert back.texture_share == pytest.approx(left.texture_share) and back.texture_offset == pytest.approx(left.texture_offset)
    with pytest.raises(FieldError, match="texture_share"):
        VisualOdometry("uav1", 1, 0, Stamp(0.1, "vehicle"), (0.0, 0.0, 0.0), 1.0, 0.0, False, 0.1, 50.0,
                       texture_share=1.5)
