"""Ego-motion for the `clearance` policy: where the vehicle is in its own local frame, without GNSS.

Two sources, fused every heatmap:

- prediction: the autopilot's velocity estimate integrated between the two frames' capture
  stamps (the controller's track of every vehicle state), or, without it, the estimate blended
  with the commanded velocity, rotated by yaw into north/east, times dt (capped); plus an
  estimated bias x dt. On its own this drifts: a real estimator without GNSS misses wind and its
  own errors.
- registration: phase correlation of the heatmap against a keyframe, both resampled to the same
  ground scale (metres per pixel from altitude and field of view), gives the camera's ground
  displacement since the keyframe. A keyframe (not the previous frame) keeps the error from
  piling up per frame; it is renewed once the view moved a share of the image or the altitude
  changed by a ratio. A shift is used only when the correlation peak is clear, the heatmap has
  texture and the innovation is inside a gate; then it corrects the position and, slowly, the
  velocity bias (so a biased estimator is learnt, not just patched). Anchors (below) give
  absolute fixes; the keyframe moves with the estimate a fix moves.
- the spot's keyframe (`set_spot`): the look that chose the landing target, against which every
  later heatmap is registered too. A fix from it puts the estimate back where it was relative
  to the checked ground (so the target, in the estimate's frame, is that ground again), and
  `spot_since_s` says how long ago the last one was: the policy descends only on a recent one.

Pure and deterministic: arrays in, numbers out, no clock but the observation's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.shared.frames import to_body, to_ne
from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.clearance.ground_map import footprint_width_m


def phase_shift(ref: np.ndarray, cur: np.ndarray, window: np.ndarray) -> tuple[float, float, float]:
    """(dx, dy, response): `cur` is `ref` with its content moved by (+dx right, +dy down) px."""
    a = ref - np.float32(ref.mean())
    b = cur - np.float32(cur.mean())
    (dx, dy), response = cv2.phaseCorrelate(a, b, window)
    return float(dx), float(dy), float(response)


def tilt_offset_ne(alt_agl_m: float, roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float]:
    """Where the image centre looks relative to the point below the vehicle (flat ground).

    The camera looks along body down; with the ZYX attitude (MAVLink ATTITUDE) that axis is
    (cos r sin p, -sin r, cos r cos p) in the heading-level frame (forward, right, down). So nose up
    (pitch > 0) turns it forwards (the belly faces ahead: a braking vehicle sees where it goes) and
    right wing down (roll > 0) turns it left.
    """
    forward = alt_agl_m * math.tan(pitch_rad)
    right = -alt_agl_m * math.tan(roll_rad) / math.cos(pitch_rad)
    return to_ne(forward, right, yaw_rad)


def _constrained(img: np.ndarray, inn_n: float, inn_e: float, yaw_rad: float, min_ratio: float) -> tuple[float, float]:
    """The innovation with its components along weakly textured directions removed."""
    out_n, out_e, _ = _constrained_dirs(img, inn_n, inn_e, yaw_rad, min_ratio)
    return out_n, out_e


def _constrained_dirs(img: np.ndarray, inn_n: float, inn_e: float, yaw_rad: float,
                      min_ratio: float) -> tuple[float, float, int]:
    """The innovation with its components along weakly textured directions removed, and how
    many directions (0-2) the texture constrains.

    The structure tensor of the image (sums of gradient products) has one large eigenvalue per
    direction that edges constrain; a strip or a single edge leaves the other one near zero.
    """
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    jxx, jyy, jxy = float((gx * gx).sum()), float((gy * gy).sum()), float((gx * gy).sum())
    evals, evecs = np.linalg.eigh(np.array([[jxx, jxy], [jxy, jyy]]))
    top = float(evals[-1])
    if top <= 0.0:
        return 0.0, 0.0, 0
    out_n = out_e = 0.0
    dirs = 0
    for lam, (ux, uy) in zip(evals, evecs.T):
        if lam < min_ratio * top:
            continue
        dirs += 1
        # Image direction (x right, y down) -> body (forward = -y, right = x) -> north/east.
        vn, ve = to_ne(-float(uy), float(ux), yaw_rad)
        along = inn_n * vn + inn_e * ve
        out_n += along * vn
        out_e += along * ve
    return out_n, out_e, dirs


@dataclass(frozen=True)
class MotionStep:
    """What the ego-motion did with one heatmap (for the status and tests)."""

    north_m: float
    east_m: float
    registered: bool  # a registration shift was accepted
    response: float
    innovation_m: float  # |measured - predicted| when a shift was measured, else 0
    new_keyframe: bool
    anchored: bool = False  # an anchor (a view registered when the estimate was good) was matched
    uncertainty_m: float = 0.0  # the position error the estimate allows itself (see EgoMotion)
    spot_fixed: bool = False  # registered against the spot's keyframe (the estimate is on the checked ground)
    spot_response: float = 0.0


@dataclass
class _View:
    """A registration image and where it was taken: its ground scale, heading and the ground
    point its centre looked at (in the estimate's frame), plus, for anchors, the estimate's own
    uncertainty when it was taken."""

    img: np.ndarray
    gsd_m: float
    yaw_rad: float
    cc: tuple[float, float]
    uncertainty_m: float = 0.0


class EgoMotion:
    """Dead reckoning corrected by keyframe registration and anchored to views of the start
    area; north/east metres from the start.

    Registering each frame against a keyframe, and each keyframe against the one before, is a
    chain: whatever a link measures wrong stays in the estimate for good. Under the simulated
    CLIPSeg that error is systematic (about 2 % of the distance flown, mostly across the track on
    the suite's Dubai world), so a 600 s search drifted 70 m. Anchors close the loop: a keyframe
    taken while the estimate's uncertainty is small is kept, and whenever a later view falls on
    it again (the search returns over the same ground, each pass to the start) the frame is also
    registered against the anchor, and that absolute fix pulls the estimate back.

    The uncertainty is a bound the estimate keeps on itself: it grows by `drift_frac` of every
    metre dead-reckoned or chained (the error measured above, with margin) and is reset to an
    anchor's own after an anchor fix. The fence shrinks by what it exceeds the fence margin.
    """

    def __init__(self, config: ClearanceConfig) -> None:
        self.cfg = config
        n = config.reg_size_px
        self._window = cv2.createHanningWindow((n, n), cv2.CV_32F)
        self.reset()

    def reset(self) -> None:
        self.north_m = 0.0
        self.east_m = 0.0
        self.bias_n_m_s = 0.0
        self.bias_e_m_s = 0.0
        self.uncertainty_m = 0.0
        self._key: _View | None = None
        self._anchors: list[_View] = []
        self._fails = 0
        self._unregistered_s = 0.0
        self._static: np.ndarray | None = None  # image-fixed pattern of the registration images
        self._last_pred_m = (0.0, 0.0)  # the last prediction's displacement (north, east)
        self._last_view: _View | None = None  # the newest look, for `set_spot`
        self._spot: _View | None = None  # the spot's keyframe
        self.spot_since_s = math.inf  # data seconds since the spot's keyframe was taken or last fixed

    def set_spot(self) -> bool:
        """Take the newest look as the spot's keyframe (the look that chose or re-checked the
        target); False when there was none."""
        if self._last_view is None:
            return False
        self._spot = self._last_view
        self.spot_since_s = 0.0
        return True

    def clear_spot(self) -> None:
        self._spot = None
        self.spot_since_s = math.inf

    @property
    def anchors(self) -> int:
        return len(self._anchors)

    def predict(self, dt_s: float, vel_body_frd_m_s: tuple[float, float, float], yaw_rad: float,
                displacement_ne_m: tuple[float, float] | None = None) -> None:
        """Dead-reckon one step: the estimate's own displacement over the step when the
        controller integrated it between the capture stamps, else velocity x dt (capped); plus
        the learnt bias x dt. The displacement covers the whole interval, a perception gap
        included (it is what the autopilot measured); the bias and the uncertainty's per-second
        term use the capped dt."""
        dt = min(max(dt_s, 0.0), self.cfg.dt_cap_s)
        if displacement_ne_m is not None:
            dn, de = displacement_ne_m
        else:
            vn, ve = to_ne(vel_body_frd_m_s[0], vel_body_frd_m_s[1], yaw_rad)
            dn, de = vn * dt, ve * dt
        self._last_pred_m = (dn + self.bias_n_m_s * dt, de + self.bias_e_m_s * dt)
        self.north_m += self._last_pred_m[0]
        self.east_m += self._last_pred_m[1]
        self.uncertainty_m += self.cfg.drift_frac * math.hypot(*self._last_pred_m) + self.cfg.drift_m_s * dt

    def _measure(self, ref: _View, img: np.ndarray, gsd: float, yaw_rad: float, tn: float,
                 te: float) -> tuple[float, float, float, bool, float]:
        """Register `img` against `ref`: (measured north, east, response, static, scale)."""
        n = self.cfg.reg_size_px
        scale = ref.gsd_m / gsd  # the reference's pixels cover more ground when it was higher
        angle = math.degrees(yaw_rad - ref.yaw_rad)
        m = cv2.getRotationMatrix2D(((n - 1) / 2.0, (n - 1) / 2.0), angle, scale)
        # The reference is moved by the PREDICTED motion too, so the correlation measures the
        # residual. A pattern fixed in the image (perception artefacts over water or bare
        # ground, which move with the camera) then peaks at minus the prediction, not at zero,
        # and is recognised and refused instead of reading as "no motion".
        f_pred, r_pred = to_body(self.north_m + tn - ref.cc[0], self.east_m + te - ref.cc[1], yaw_rad)
        pdx, pdy = -r_pred / gsd, f_pred / gsd
        m[0, 2] += pdx
        m[1, 2] += pdy
        assert self._static is not None
        warped = cv2.warpAffine(ref.img - self._static, m, (n, n), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_REFLECT)
        rdx, rdy, response = phase_shift(warped, img - self._static, self._window)
        static = math.hypot(pdx, pdy) > 1.5 and math.hypot(rdx + pdx, rdy + pdy) < 1.0
        dx, dy = pdx + rdx, pdy + rdy
        # Content moving down the image = the camera moved forward.
        dn, de = to_ne(dy * gsd, -dx * gsd, yaw_rad)
        return ref.cc[0] + dn - tn, ref.cc[1] + de - te, response, static, scale

    def _trust(self, response: float) -> float:
        """A mediocre peak moves the estimate a little; only a clear one fully (phase correlation
        over weak texture is pulled towards whatever moves with the camera)."""
        cfg = self.cfg
        return min(1.0, (response - cfg.reg_min_response) / max(cfg.reg_full_response - cfg.reg_min_response, 1e-6))

    def _nearest_anchor(self, cn: float, ce: float, gsd: float, reach_m: float) -> _View | None:
        """The best-known anchor (least uncertainty) of about this scale within reach."""
        best = None
        for a in self._anchors:
            ratio = max(a.gsd_m / gsd, gsd / a.gsd_m)
            if (ratio <= self.cfg.anchor_scale_ratio and math.hypot(a.cc[0] - cn, a.cc[1] - ce) < reach_m
                    and (best is None or a.uncertainty_m < best.uncertainty_m)):
                best = a
        return best

    def _anchor_fix(self, img: np.ndarray, gsd: float, width_m: float, yaw_rad: float, tn: float,
                    te: float) -> tuple[float, float] | None:
        """Register against the best anchor in view; an accepted match corrects the position.
        Returns the correction applied (north, east metres), None when there was none."""
        cfg = self.cfg
        a = self._nearest_anchor(self.north_m + tn, self.east_m + te, gsd, cfg.anchor_reach_frac * width_m)
        if a is None or a.uncertainty_m >= self.uncertainty_m:
            return None  # the estimate is already as good as the anchor would make it
        meas_n, meas_e, response, static, _ = self._measure(a, img, gsd, yaw_rad, tn, te)
        inn_n, inn_e = meas_n - self.north_m, meas_e - self.east_m
        # An absolute fix: the gate is wide (the uncertainty bound is a model and the chain's
        # error can outgrow it while the vehicle slows down and descends).
        gate = cfg.reg_gate_m + cfg.anchor_gate_frac * width_m + 2.0 * self.uncertainty_m
        if static or response < cfg.anchor_min_response or math.hypot(inn_n, inn_e) > gate:
            return None
        k = self._trust(response)
        inn_n, inn_e = _constrained(img, inn_n, inn_e, yaw_rad, cfg.reg_min_eigen_ratio)
        self.north_m += k * inn_n
        self.east_m += k * inn_e
        # The fix is as good as the anchor plus the match (a share of the gate); a weak one keeps
        # part of the old uncertainty.
        self.uncertainty_m = min(self.uncertainty_m, a.uncertainty_m + cfg.reg_gate_m
                                 + (1.0 - k) * (self.uncertainty_m - a.uncertainty_m))
        return k * inn_n, k * inn_e

    def correct(self, prob: np.ndarray, dt_s: float, alt_agl_m: float, hfov_rad: float, yaw_rad: float,
                roll_rad: float = 0.0, pitch_rad: float = 0.0) -> MotionStep:
        """Register `prob` (taken at the predicted position) against the keyframe, then an anchor."""
        cfg = self.cfg
        n = cfg.reg_size_px
        img = cv2.resize(prob, (n, n), interpolation=cv2.INTER_AREA).astype(np.float32, copy=False)
        width_m = footprint_width_m(alt_agl_m, hfov_rad)
        gsd = width_m / n
        tn, te = tilt_offset_ne(alt_agl_m, roll_rad, pitch_rad, yaw_rad)
        textured = float(img.std()) >= cfg.reg_min_std
        registered, anchored, response, innovation, new_key = False, False, 0.0, 0.0, False
        # The image-fixed part of the heatmaps (artefacts that move with the camera) is learnt
        # as a slow average while the ground moves through the view, and removed before
        # correlating; while hovering it is frozen (the ground would be learnt instead).
        moving_px = math.hypot(*self._last_pred_m) / gsd
        if self._static is None:
            self._static = np.zeros_like(img)
        elif moving_px > 1.0 and dt_s > 0.0:
            alpha = np.float32(min(1.0, min(dt_s, cfg.dt_cap_s) / cfg.static_tau_s))
            self._static += alpha * (img - self._static)
        key = self._key
        if key is not None and textured:
            meas_n, meas_e, response, static, scale = self._measure(key, img, gsd, yaw_rad, tn, te)
            inn_n, inn_e = meas_n - self.north_m, meas_e - self.east_m
            innovation = math.hypot(inn_n, inn_e)
            # The prediction's own uncertainty grows with the time since the last accepted shift.
            self._unregistered_s += dt_s
            since_s = self._unregistered_s  # what the innovation accrued over
            gate = cfg.reg_gate_m + cfg.reg_gate_frac * width_m + cfg.reg_gate_m_s * since_s
            if response >= cfg.reg_min_response and innovation <= gate and not static:
                registered = True
                self._fails = 0
                self._unregistered_s = 0.0
                k = cfg.reg_pos_gain * self._trust(response)
                # Aperture problem: along a straight edge or strip a shift is unobservable, and
                # phase correlation then says "no motion". Only directions the texture constrains
                # are corrected; the others keep the prediction.
                inn_n, inn_e = _constrained(img, inn_n, inn_e, yaw_rad, cfg.reg_min_eigen_ratio)
                self.north_m += k * inn_n
                self.east_m += k * inn_e
                # The innovation accrued since the last accepted shift: a velocity error (it over
                # that time), learnt over bias_tau. One larger than any bias the estimator may
                # have is a jump, not a velocity error.
                if (since_s > 0.0 and response >= cfg.reg_full_response
                        and math.hypot(inn_n, inn_e) <= cfg.bias_max_m_s * since_s):
                    rate = min(1.0, since_s / cfg.bias_tau_s) / max(since_s, 1e-3)
                    self.bias_n_m_s += rate * inn_n * (1.0 - k)
                    self.bias_e_m_s += rate * inn_e * (1.0 - k)
                    b = math.hypot(self.bias_n_m_s, self.bias_e_m_s)
                    if b > cfg.bias_max_m_s:
                        self.bias_n_m_s *= cfg.bias_max_m_s / b
                        self.bias_e_m_s *= cfg.bias_max_m_s / b
            else:
                self._fails += 1
            # Motion since the keyframe by the estimate (a measured shift can be blind along a strip).
            moved_px = math.hypot(self.north_m + tn - key.cc[0], self.east_m + te - key.cc[1]) / gsd
            ratio = max(scale, 1.0 / scale)
            if moved_px > cfg.key_shift_frac * n or ratio > cfg.key_scale_ratio or self._fails >= 3:
                new_key = True
        elif key is None or (not textured and self._fails >= 3):
            new_key = True
        if textured and self._anchors:
            fix = self._anchor_fix(img, gsd, width_m, yaw_rad, tn, te)
            anchored = fix is not None
            if fix is not None and self._key is not None:
                # The fix moved the estimate, not the vehicle, and the keyframe was placed with
                # (nearly) the same error: it moves with it. Left where it was, the next
                # registration read the fix as motion and the bias learner as a velocity error
                # (a 5 m fix learnt 2.6 m/s in 4 s while hovering, and the hold ran away).
                self._key.cc = (self._key.cc[0] + fix[0], self._key.cc[1] + fix[1])
        spot_fixed, spot_response = self._spot_fix(img, gsd, width_m, yaw_rad, tn, te, dt_s)
        self._last_view = _View(img.copy(), gsd, yaw_rad, (self.north_m + tn, self.east_m + te))
        if spot_fixed and self._spot is not None and max(self._spot.gsd_m / gsd, gsd / self._spot.gsd_m) > \
                self.cfg.spot_renew_ratio:
            # Lower (or higher) by a ratio: a fixed look of the same ground at this scale
            # registers better from here on; the chain adds one fix's error.
            self._spot = self._last_view
        if new_key or self._key is None:
            self._key = _View(img.copy(), gsd, yaw_rad, (self.north_m + tn, self.east_m + te))
            self._fails = 0
            new_key = True
            self._maybe_anchor(self._key, textured)
        return MotionStep(self.north_m, self.east_m, registered, response, innovation, new_key, anchored,
                          self.uncertainty_m, spot_fixed, spot_response)

    def _spot_fix(self, img: np.ndarray, gsd: float, width_m: float, yaw_rad: float, tn: float, te: float,
                  dt_s: float) -> tuple[bool, float]:
        """Register against the spot's keyframe; an accepted match puts the estimate where that
        look says it is (relative to the checked ground). Returns (fixed, response)."""
        if self._spot is None:
            return False, 0.0
        cfg = self.cfg
        self.spot_since_s += max(dt_s, 0.0)
        if float(img.std()) < 1e-4:
            return False, 0.0  # a flat image has no phase to correlate
        meas_n, meas_e, response, static, _ = self._measure(self._spot, img, gsd, yaw_rad, tn, te)
        inn_n, inn_e = meas_n - self.north_m, meas_e - self.east_m
        gate = cfg.reg_gate_m + cfg.reg_gate_frac * width_m + cfg.spot_drift_m_s * self.spot_since_s
        if static or response < cfg.spot_min_response or math.hypot(inn_n, inn_e) > gate:
            return False, response
        # Along a strip or an edge the shift is unobservable: only the directions the texture
        # constrains are corrected, and only both make a fix (the spot is pinned, not slid along).
        inn_n, inn_e, dirs = _constrained_dirs(img, inn_n, inn_e, yaw_rad, cfg.reg_min_eigen_ratio)
        # A share of it, as for the keyframe: a fix's own error (a fraction of a registration
        # pixel, ~0.3 m at 90 m) applied whole every frame jittered the fused map by a cell and
        # cost a 12 m lawn its clearance; the share leaves a lag of drift x (1 - k) / k per look.
        k = cfg.reg_pos_gain * self._trust(response)
        inn_n, inn_e = k * inn_n, k * inn_e
        self.north_m += inn_n
        self.east_m += inn_e
        if self._key is not None:
            self._key.cc = (self._key.cc[0] + inn_n, self._key.cc[1] + inn_e)  # it moved with the estimate
        if dirs < 2:
            return False, response
        self.spot_since_s = 0.0
        return True, response

    def _maybe_anchor(self, key: _View, textured: bool) -> None:
        """Keep a new keyframe as an anchor unless an anchor of about its scale, known at least
        as well, lies near; a worse-known one there is replaced (the anchors tile the ground
        seen, each with the best estimate it was ever seen with)."""
        cfg = self.cfg
        if not textured:
            return
        reach = cfg.anchor_spacing_frac * key.gsd_m * cfg.reg_size_px
        for i, a in enumerate(self._anchors):
            if (max(a.gsd_m / key.gsd_m, key.gsd_m / a.gsd_m) < cfg.key_scale_ratio
                    and math.hypot(a.cc[0] - key.cc[0], a.cc[1] - key.cc[1]) < reach):
                if a.uncertainty_m > self.uncertainty_m + cfg.anchor_gain_m:
                    self._anchors[i] = _View(key.img, key.gsd_m, key.yaw_rad, key.cc, self.uncertainty_m)
                return
        if len(self._anchors) < cfg.anchor_max:
            self._anchors.append(_View(key.img, key.gsd_m, key.yaw_rad, key.cc, self.uncertainty_m))
