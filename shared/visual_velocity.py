"""Visual velocity: the vehicle's ground velocity from two downward camera frames.

Pure computation (OpenCV and numpy, no torch, no transport), shared by the onboard camera service
and the simulator so that a real flight and a simulated one produce the same odometry stream.

Data flow, once per frame:

    image (RGB or grey, any size) + FrameMeta (stamp, altitude, attitude, field of view)
      -> prepare(): grey, area-downsampled to `work_width_px`, Lucas-Kanade pyramid, corners
         picked one per grid cell where the weaker gradient direction is strong enough
      -> estimate(prev, new):
           track prev's corners into new (pyramidal Lucas-Kanade), each seeded where the attitude
           change alone would move it, and back again (forward-backward check)
           each tracked pair -> two rays (pinhole, image up = body forward, image right = body
           right) -> the level frame of the newer frame's heading (each frame's own roll/pitch,
           the yaw change) -> onto the ground plane at the newer frame's altitude
           robust fit  g_new + T(w) = rho * g_prev - D : D the horizontal displacement,
             rho = h_prev/h_new, T(w) what a small error w of the attitude change would add
      -> VelocityEstimate: (D / dt, (rho - 1) h_new / dt) rotated into body FRD at the newer
         frame, a variance per horizontal axis, a quality in [0, 1], valid or not and why

Geometry (Hartley & Zisserman, "Multiple View Geometry", ch. 8: a camera rotation alone maps
image points by K R K^-1; a plane at depth h projects with a scale of f / h): a pixel (u, v) of an
image W px wide, optical axis at ((W-1)/2, (H-1)/2), focal length f = (W/2) / tan(hfov/2) px,
looks along body (forward, right, down) = (-(v - cy)/f, (u - cx)/f, 1), so one pixel at the
centre covers 2 alt tan(hfov/2) / W metres of flat ground. Rotations are ZYX Euler (yaw, pitch,
roll), body to NED, as MAVLink's ATTITUDE gives them. Ground assumed flat and static; moving
objects and relief are outliers to the robust fit.

The attitude tags' error. A tag error that differs between the two frames tilts every ray of the
newer one alike, h x angle on the ground: alone it reads as a velocity (5 mrad at 100 m over
0.5 s is 1 m/s). But a rotation w = (w_n, w_e) of the newer rays (level, normalised to down = 1,
x forward, y right) also moves each point by a term that grows with its distance from the axis:
    (x, y) -> (x, y) + w_n (-x y, -(1 + y^2)) + w_e (1 + x^2, x y)   (first order)
which no translation or scale has. With a 73 deg view the corners far out see it, so the fit
solves for w beside rho and D (five unknowns, one linear least squares; w has a prior of the
tags' own error) and, when w stands out of its own noise and beyond the tags' stated error, the
velocity comes from the corrected D; otherwise the tags stand (w = 0 in D). Measured (session of 6 Dec 2026): exact views tagged 5 mrad
off in roll or pitch give w within 0.1 mrad and the velocity within 0.02 m/s; in a `harsh` sim
flight over desert at 100 m (relative tag errors median 2.0 mrad, q90 3.5) the fitted w follows
the tags' true error with slope 0.8 (correlation 0.7-0.9) and the horizontal error in the camera's
heading frame fell from median 0.47 to 0.32 m/s (q90 0.84 -> 0.72). The variance still counts the
whole fitted w: the part of the tag error the fit misses is not known.

Failures never produce a confident wrong number: too little texture (a blank, uniform or blurred
frame has few corners), a failed track (few pairs pass the forward-backward check, or they
disagree), an altitude that is not finite or not plausible, a time step that is not positive or
too long, or a speed beyond `max_speed_m_s` all give `valid=False`, a zero velocity, a huge
variance and a `reason`. Every number that leaves here is finite and inside the bounds of the
`VisualOdometry` message.

Where the texture is. Each prepared frame also says which share of its grid cells held a corner
and where their centre lies on the ground, level, per metre of altitude (forward, right of the
heading). A vehicle over calm water has no velocity, but a coast in a corner of its view still
shows which way the measurable ground is: the controller flies there when its velocity is lost.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import cv2
import numpy as np

from dovesei.shared.errors import ConfigError
from dovesei.shared.footprint import focal_px
from dovesei.shared.messages import Stamp, VisualOdometry, field_range
from dovesei.shared.validate import in_range, is_number, positive

# What an invalid estimate reports as its variance per axis (m^2/s^2): (100 m/s)^2, "know nothing".
INVALID_VAR_M2_S2 = 1.0e4
# Ground metres per metre of altitude, as the message bounds it (rays within max_tilt_deg reach tan(85 deg)).
TEXTURE_OFFSET_MIN, TEXTURE_OFFSET_MAX = field_range(VisualOdometry, "texture_offset")
# The fitted tilt corrects the velocity only when it stands out of its own noise: chi-square with
# 2 degrees of freedom at 99 %. Below it the correction would add the fit's noise (h x its sd: at
# 40 m on a 2.5 rad/s turn in the tests, ~0.9 mrad, 0.35 m/s over 0.1 s) for an error the tags'
# prior says is smaller.
TILT_SIGNIFICANT_CHI2 = 9.21
# ...and only when it is beyond the tags' own error (this many of its sd): within it a correction
# trades the tags' error for the fit's, which on noisy views is not smaller. `dovesei
# bench-odometry --pairs 6 --flight-s 0 --noise realistic --tilt on` (tags drawn within their
# stated 0.5 mrad) read median 4.07 % / p95 16.8 % without the correction and 4.69 % / 20.9 %
# correcting every significant tilt (6 Dec 2026).
TILT_CORRECT_PRIORS = 3.0


@dataclass(frozen=True)
class VisualVelocityConfig:
    """Tuning of the estimator; every field is checked when built (ConfigError names it)."""

    work_width_px: int = 320  # frames wider than this are area-averaged down to it (speed, less noise)
    grid_cell_px: int = 16  # one corner candidate per cell of the work image (spread over the view)
    max_features: int = 160
    # Weakest-direction gradient (grey levels per work pixel) a corner needs. Sensor noise of
    # sigma 2 grey levels gives Sobel gradients of ~0.9; a blank or blurred view has far less.
    min_gradient: float = 2.0
    lk_window_px: int = 15
    lk_levels: int = 3  # pyramid levels above the base: tracks shifts up to ~60 work px
    fb_max_px: float = 0.7  # forward-backward disagreement that rejects a track
    min_inliers: int = 15
    min_quality: float = 0.3  # below it the estimate is not valid
    full_texture_features: int = 60  # this many corners (or more) count as a fully textured view
    fit_sigma_px: float = 0.5  # residual (work px) at which the fit quality halves
    # The baseline: each frame is compared with the newest earlier frame at least altitude x
    # `baseline_s_per_m` older (at most `max_baseline_s`; the previous frame at 20 m and 10 Hz).
    # Each frame's attitude tag moves every ray alike, h x angle on the ground whatever the
    # interval, so the velocity's error from it falls as 1 / interval: at 100 m, 0.5 mrad tags
    # give 0.7 m/s over 0.1 s. With the tags and sensor noise of `dovesei bench-odometry --noise
    # realistic` on four suite worlds at 100 m (320 px camera, tilted), the median error was
    # 1.21 m/s over 0.1 s and 0.23 m/s over 0.5 s; at 20 m 0.24 and 0.05 m/s (session
    # measurement, docs/RESULTS.md). The velocity is then the mean over the interval (the
    # message's dt_s says how long), a lag of half of it.
    baseline_s_per_m: float = 0.005
    max_baseline_s: float = 0.5
    min_alt_m: float = 1.0
    max_alt_m: float = 1000.0
    max_climb_m_s: float = 20.0  # altitudes of two frames may differ by at most this x dt (+ 2 m)
    max_speed_m_s: float = 40.0
    max_dt_s: float = 1.0
    max_tilt_deg: float = 60.0  # rays further than this from vertical are not intersected with the ground
    # Error sources the residual cannot see, each given as one standard deviation: each frame's
    # attitude tag (the estimate's short-term error plus the time-tag mismatch: ~1 ms of camera
    # timing jitter at 0.5 rad/s), which moves every ray alike, so two frames' errors give
    # h x sqrt(2) x sigma / dt (0.7 m/s at 100 m and 10 Hz); the altitude's relative error (it
    # scales the whole velocity); and a floor. `dovesei bench-odometry --noise realistic` draws the
    # same per-frame attitude error and checks the variance against the errors it gets.
    attitude_sigma_rad: float = 0.0005
    alt_rel_sigma: float = 0.03
    var_floor_m2_s2: float = 0.01

    def __post_init__(self) -> None:
        for name, lo, hi in (("work_width_px", 32, 4096), ("grid_cell_px", 4, 256), ("max_features", 8, 4096),
                             ("lk_window_px", 5, 61), ("lk_levels", 0, 6), ("min_inliers", 4, 4096),
                             ("full_texture_features", 1, 4096)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise ConfigError(f"visual velocity {name} must be an integer in {lo}..{hi}, got {value!r}")
        for name in ("min_gradient", "fb_max_px", "fit_sigma_px", "min_alt_m", "max_alt_m", "max_climb_m_s",
                     "max_speed_m_s", "max_dt_s", "var_floor_m2_s2"):
            positive(f"visual velocity {name}", getattr(self, name))
        in_range("visual velocity baseline_s_per_m", self.baseline_s_per_m, 0.0, 1.0)
        in_range("visual velocity max_baseline_s", self.max_baseline_s, 0.0, self.max_dt_s)
        in_range("visual velocity min_quality", self.min_quality, 0.0, 1.0)
        in_range("visual velocity max_tilt_deg", self.max_tilt_deg, 1.0, 85.0)
        in_range("visual velocity attitude_sigma_rad", self.attitude_sigma_rad, 0.0, 1.0)
        in_range("visual velocity alt_rel_sigma", self.alt_rel_sigma, 0.0, 1.0)
        if self.min_alt_m >= self.max_alt_m:
            raise ConfigError(f"visual velocity min_alt_m {self.min_alt_m} must be below max_alt_m {self.max_alt_m}")

    def baseline_s(self, alt_agl_m: float) -> float:
        """The interval a frame at this altitude is compared over (0: the previous frame)."""
        if not is_number(alt_agl_m):
            return 0.0
        return min(max(alt_agl_m, 0.0) * self.baseline_s_per_m, self.max_baseline_s)


@dataclass(frozen=True)
class FrameMeta:
    """What is known about a frame besides its pixels: its stamp, the altitude and attitude it was taken at.

    Not checked here: a frame with a NaN altitude is still tracked from, and the estimate that
    uses it says why it is invalid.
    """

    seq: int
    t_s: float
    alt_agl_m: float
    hfov_rad: float
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0


@dataclass(frozen=True)
class PreparedFrame:
    """A frame ready to be tracked from or to: its work image, its corners and its geometry."""

    meta: FrameMeta
    grey: np.ndarray  # the work image (OpenCV's Python binding takes no prebuilt pyramid)
    corners_px: np.ndarray  # (N, 1, 2) float32, work pixels
    width_px: int
    height_px: int
    # Grid cells that held a corner (all of them, before `max_features`): their share of the cells,
    # and their centre on level ground per metre of altitude, (forward, right) of the heading.
    texture_share: float = 0.0
    texture_offset: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class VelocityEstimate:
    """The velocity between two frames, in body FRD at the newer one, with its uncertainty.

    Invalid estimates carry a zero velocity, INVALID_VAR_M2_S2 and the `reason`; quality may be
    above 0 when the failure was soft (a poor but not empty track).
    """

    valid: bool
    vel_body_frd_m_s: tuple[float, float, float]
    vel_var_m2_s2: float
    quality: float
    dt_s: float
    reason: str
    prev_seq: int
    seq: int
    n_features: int = 0
    n_tracked: int = 0
    n_inliers: int = 0
    residual_px: float = 0.0
    # The fitted error of the attitude change (rad, about north and east of the heading frame) and
    # its variance per axis from the fit (prior included): what `VisualVelocity` learns the tags'
    # real error from. Zero for an invalid estimate.
    tilt_rad: tuple[float, float] = (0.0, 0.0)
    tilt_var_rad2: float = 0.0
    # The newer frame's texture (`PreparedFrame`), valid estimate or not.
    texture_share: float = 0.0
    texture_offset: tuple[float, float] = (0.0, 0.0)


def rotation_body_to_level(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll): body FRD vectors -> NED (or a heading frame for a relative yaw)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([
        [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
        [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
        [-sp, sr * cp, cr * cp],
    ])


def _rays_body(points_px: np.ndarray, width_px: int, height_px: int, f_px: float) -> np.ndarray:
    """(N, 2) pixels (u right, v down) -> (N, 3) body FRD rays with down = 1."""
    cx, cy = (width_px - 1) / 2.0, (height_px - 1) / 2.0
    rays = np.empty((len(points_px), 3))
    rays[:, 0] = -(points_px[:, 1] - cy) / f_px
    rays[:, 1] = (points_px[:, 0] - cx) / f_px
    rays[:, 2] = 1.0
    return rays


def _to_pixels(rays_body: np.ndarray, width_px: int, height_px: int, f_px: float) -> np.ndarray:
    cx, cy = (width_px - 1) / 2.0, (height_px - 1) / 2.0
    down = np.maximum(rays_body[:, 2], 1e-3)  # rays that turned upward are clamped; LK then fails them
    return np.stack([cx + f_px * rays_body[:, 1] / down, cy - f_px * rays_body[:, 0] / down], axis=1)


def _grey_work(image: np.ndarray, work_width_px: int) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3) \
            or (image.ndim == 3 and image.shape[2] not in (1, 3)):
        raise ValueError("visual velocity needs a uint8 image, grey (H, W) or RGB (H, W, 3), got "
                         f"{getattr(image, 'dtype', type(image).__name__)} {getattr(image, 'shape', '')}")
    if min(image.shape[:2]) < 32:
        raise ValueError(f"visual velocity needs an image of at least 32x32 px, got {image.shape[1]}x{image.shape[0]}")
    grey = image if image.ndim == 2 else (image[:, :, 0] if image.shape[2] == 1 else
                                          cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    h, w = grey.shape
    if w > work_width_px:
        # Area averaging keeps the optical axis at the centre ((W-1)/2 maps to (w-1)/2) and the
        # ground size per pixel exact, so the pinhole model holds at the work scale.
        grey = cv2.resize(grey, (work_width_px, max(8, round(h * work_width_px / w))), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(grey)


def _corners(grey: np.ndarray, config: VisualVelocityConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """The strongest corner of each grid cell whose weaker gradient direction exceeds min_gradient
    (at most `max_features`, strongest first), every such cell's corner, and the number of cells."""
    block = 5
    # cornerMinEigenVal scales Sobel(3) by 1/(4 block 255) and sums over the block, so a ramp of g
    # grey levels per pixel in the weaker direction reads (2 g / 255)^2 (checked in the tests).
    eig = cv2.cornerMinEigenVal(grey, block, ksize=3)
    threshold = (2.0 * config.min_gradient / 255.0) ** 2
    cell, margin = config.grid_cell_px, config.lk_window_px // 2 + 2
    h, w = eig.shape
    rows, cols = (h - 2 * margin) // cell, (w - 2 * margin) // cell
    if rows < 1 or cols < 1:
        return np.empty((0, 1, 2), np.float32), np.empty((0, 2)), 0
    y0, x0 = margin + (h - 2 * margin - rows * cell) // 2, margin + (w - 2 * margin - cols * cell) // 2
    tiles = eig[y0:y0 + rows * cell, x0:x0 + cols * cell].reshape(rows, cell, cols, cell).transpose(0, 2, 1, 3)
    tiles = tiles.reshape(rows, cols, cell * cell)
    best = tiles.argmax(axis=2)
    strength = np.take_along_axis(tiles, best[..., None], axis=2)[..., 0]
    keep = strength > threshold
    if not keep.any():
        return np.empty((0, 1, 2), np.float32), np.empty((0, 2)), rows * cols
    r_idx, c_idx = np.nonzero(keep)
    order = np.argsort(-strength[r_idx, c_idx])
    r_idx, c_idx = r_idx[order], c_idx[order]
    b = best[r_idx, c_idx]
    xy = np.stack([x0 + c_idx * cell + b % cell, y0 + r_idx * cell + b // cell], axis=1)
    return xy[: config.max_features].astype(np.float32).reshape(-1, 1, 2), xy.astype(np.float64), rows * cols


def _looks_down(rays_level: np.ndarray, config: VisualVelocityConfig) -> np.ndarray:
    """Which level rays look down within max_tilt_deg of vertical: normalised (unit length), a ray
    looks down by its z; shallower ones meet the ground far away."""
    return rays_level[:, 2] / np.linalg.norm(rays_level, axis=1) > math.cos(math.radians(config.max_tilt_deg))


def _texture(cells_px: np.ndarray, n_cells: int, width_px: int, height_px: int, meta: FrameMeta,
             config: VisualVelocityConfig) -> tuple[float, tuple[float, float]]:
    """(share of cells with a corner, their centre on level ground per metre of altitude)."""
    if n_cells < 1 or len(cells_px) == 0 or not all(is_number(v) for v in (meta.hfov_rad, meta.roll_rad,
                                                                            meta.pitch_rad)):
        return 0.0, (0.0, 0.0)
    if not 0.0 < meta.hfov_rad < math.pi:
        return 0.0, (0.0, 0.0)
    rays = _rays_body(cells_px, width_px, height_px, focal_px(width_px, meta.hfov_rad))
    rays = rays @ rotation_body_to_level(meta.roll_rad, meta.pitch_rad, 0.0).T
    down = _looks_down(rays, config)
    if not down.any():
        return 0.0, (0.0, 0.0)
    ground = rays[down, :2] / rays[down, 2:3]
    fwd, right = (float(v) for v in ground.mean(axis=0))
    return min(1.0, len(cells_px) / n_cells), (fwd, right)


def prepare(image: np.ndarray, meta: FrameMeta, config: VisualVelocityConfig = VisualVelocityConfig()) -> PreparedFrame:
    """Grey work image and its corners (ValueError for an image that is not one)."""
    grey = _grey_work(image, config.work_width_px)
    corners, cells, n_cells = _corners(grey, config)
    share, offset = _texture(cells, n_cells, grey.shape[1], grey.shape[0], meta, config)
    return PreparedFrame(meta, grey, corners, grey.shape[1], grey.shape[0], share, offset)


def _invalid(prev: PreparedFrame, new: PreparedFrame, dt_s: float, reason: str, quality: float = 0.0,
             **counts: float) -> VelocityEstimate:
    return VelocityEstimate(False, (0.0, 0.0, 0.0), INVALID_VAR_M2_S2, float(min(max(quality, 0.0), 1.0)),
                            dt_s if is_number(dt_s) else 0.0, reason, prev.meta.seq, new.meta.seq, **counts)


def _plausibility(prev: FrameMeta, new: FrameMeta, dt_s: float, config: VisualVelocityConfig) -> str:
    """Why two frames' metadata cannot give a velocity, or '' when they can."""
    if not (is_number(dt_s) and 0.0 < dt_s <= config.max_dt_s):
        return f"time between frames {dt_s!r} s outside (0, {config.max_dt_s:g}] s"
    for which, m in (("previous", prev), ("newer", new)):
        if not (is_number(m.alt_agl_m) and config.min_alt_m <= m.alt_agl_m <= config.max_alt_m):
            return f"{which} frame's altitude {m.alt_agl_m!r} m outside [{config.min_alt_m:g}, {config.max_alt_m:g}] m"
        if not all(is_number(a) for a in (m.roll_rad, m.pitch_rad, m.yaw_rad)):
            return f"{which} frame's attitude is not finite"
        if not (is_number(m.hfov_rad) and 0.0 < m.hfov_rad < math.pi):
            return f"{which} frame's field of view {m.hfov_rad!r} rad outside (0, pi)"
        if math.degrees(math.acos(min(1.0, math.cos(m.roll_rad) * math.cos(m.pitch_rad)))) > config.max_tilt_deg:
            return f"{which} frame tilted beyond {config.max_tilt_deg:g} deg"
    if abs(new.alt_agl_m - prev.alt_agl_m) > config.max_climb_m_s * dt_s + 2.0:
        return (f"altitude jumped {prev.alt_agl_m:.1f} -> {new.alt_agl_m:.1f} m in {dt_s:.3f} s "
                f"(more than {config.max_climb_m_s:g} m/s)")
    return ""


def estimate(prev: PreparedFrame, new: PreparedFrame, config: VisualVelocityConfig = VisualVelocityConfig(),
             *, tag_change_var_rad2: float = 0.0) -> VelocityEstimate:
    """The velocity that moved the camera from `prev` to `new` (see the module docstring).

    `tag_change_var_rad2`: the variance per axis of the two tags' difference as measured over the
    flight (`VisualVelocity`); the variance counts it when it exceeds the stated one
    (2 x attitude_sigma_rad^2). It never changes the velocity.
    """
    est = _estimate(prev, new, config, tag_change_var_rad2)
    return replace(est, texture_share=new.texture_share, texture_offset=new.texture_offset)


def _estimate(prev: PreparedFrame, new: PreparedFrame, config: VisualVelocityConfig,
              tag_change_var_rad2: float) -> VelocityEstimate:
    dt_s = new.meta.t_s - prev.meta.t_s if is_number(new.meta.t_s) and is_number(prev.meta.t_s) else float("nan")
    why = _plausibility(prev.meta, new.meta, dt_s, config)
    if why:
        return _invalid(prev, new, dt_s, why)
    if (prev.width_px, prev.height_px) != (new.width_px, new.height_px):
        return _invalid(prev, new, dt_s, "the two frames differ in size")
    n_features = len(prev.corners_px)
    if n_features < config.min_inliers:
        return _invalid(prev, new, dt_s, f"too little texture: {n_features} corners", n_features=n_features)
    w, h = new.width_px, new.height_px
    f_prev, f_new = focal_px(w, prev.meta.hfov_rad), focal_px(w, new.meta.hfov_rad)
    # Heading frame of the newer frame: its yaw is 0, the previous frame's is the yaw change.
    dyaw = math.remainder(prev.meta.yaw_rad - new.meta.yaw_rad, math.tau)
    r_prev = rotation_body_to_level(prev.meta.roll_rad, prev.meta.pitch_rad, dyaw)
    r_new = rotation_body_to_level(new.meta.roll_rad, new.meta.pitch_rad, 0.0)
    p0 = prev.corners_px.reshape(-1, 2).astype(np.float64)
    rays_prev = _rays_body(p0, w, h, f_prev) @ r_prev.T  # level frame
    # Seed each track where the attitude change alone would move it: LK then searches only the
    # translation's shift, however fast the vehicle rotates.
    seed = _to_pixels(rays_prev @ r_new, w, h, f_new).astype(np.float32).reshape(-1, 1, 2)
    win = (config.lk_window_px, config.lk_window_px)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev.grey, new.grey, prev.corners_px, seed.copy(),
                                          winSize=win, maxLevel=config.lk_levels, criteria=criteria,
                                          flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(new.grey, prev.grey, p1, prev.corners_px.copy(),
                                            winSize=win, maxLevel=config.lk_levels, criteria=criteria,
                                            flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1.reshape(-1, 2).astype(np.float64)
    fb = np.linalg.norm(back.reshape(-1, 2) - p0, axis=1)
    inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < config.fb_max_px) & inside & np.isfinite(p1).all(axis=1)
    n_tracked = int(ok.sum())
    counts = {"n_features": n_features, "n_tracked": n_tracked}
    if n_tracked < config.min_inliers:
        return _invalid(prev, new, dt_s, f"tracking failed: {n_tracked} of {n_features} corners followed",
                        quality=0.0, **counts)
    rays_prev = rays_prev[ok]
    rays_new = _rays_body(p1[ok], w, h, f_new) @ r_new.T
    down_ok = _looks_down(rays_prev, config) & _looks_down(rays_new, config)
    rays_prev, rays_new = rays_prev[down_ok], rays_new[down_ok]
    if len(rays_prev) < config.min_inliers:
        return _invalid(prev, new, dt_s, "too few tracked corners look down at the ground", **counts)
    h_new = new.meta.alt_agl_m
    # Both frames projected at the newer altitude: the fit's scale then measures the altitude
    # change visually, and the noise of the previous altitude reading never enters the velocity.
    g_prev = h_new * rays_prev[:, :2] / rays_prev[:, 2:3]
    g_new = h_new * rays_new[:, :2] / rays_new[:, 2:3]
    m_per_px = h_new / f_new  # ground size of a work pixel at the centre of the newer frame
    fit = _robust_fit(g_prev, g_new, h_new, prev.meta.alt_agl_m / h_new, prior_m=0.05 * h_new,
                      tilt_prior_rad=math.sqrt(2.0) * config.attitude_sigma_rad)
    if fit is None:
        return _invalid(prev, new, dt_s, "the tracked corners disagree (no consistent motion)", **counts)
    resid_px = fit.resid_m / m_per_px
    n_in = int(fit.inliers.sum())
    counts.update(n_inliers=n_in, residual_px=float(resid_px))
    q_texture = min(1.0, n_features / config.full_texture_features)
    q_track = n_in / n_features
    q_fit = 1.0 / (1.0 + (resid_px / config.fit_sigma_px) ** 2)
    quality = q_texture * q_track * q_fit
    vel_level = np.array([fit.disp_m[0] / dt_s, fit.disp_m[1] / dt_s, (fit.rho - 1.0) * h_new / dt_s])
    vel_body = r_new.T @ vel_level
    speed = float(np.linalg.norm(vel_level))
    if n_in < config.min_inliers:
        return _invalid(prev, new, dt_s, f"only {n_in} corners agree on one motion", quality, **counts)
    if quality < config.min_quality:
        return _invalid(prev, new, dt_s, f"quality {quality:.2f} below {config.min_quality:g} "
                        f"(texture {q_texture:.2f}, tracked {q_track:.2f}, fit {q_fit:.2f})", quality, **counts)
    if not (np.isfinite(vel_body).all() and speed <= config.max_speed_m_s):
        return _invalid(prev, new, dt_s, f"implausible speed {speed:.1f} m/s (limit {config.max_speed_m_s:g})",
                        quality, **counts)
    # Per horizontal axis: the displacement's own spread from the fit, plus the attitude change's
    # error, h x angle: the tags' own, or the fitted tilt and its sd when larger (what the tags
    # were off by, corrected or not: a tag off by 5 mrad at 100 m is 5 m/s over 0.1 s, never
    # passed as a confident 0.7 m/s), plus the altitude's relative error (it scales the whole
    # velocity).
    tilt_var = float(np.trace(fit.tilt_cov)) / 2.0  # per axis
    tilt_ms = tilt_var + float(fit.tilt_rad @ fit.tilt_rad) / 2.0
    att_change_var = max(2.0 * config.attitude_sigma_rad ** 2, tag_change_var_rad2, tilt_ms)
    var = (float(np.trace(fit.disp_cov)) / 2.0 + h_new ** 2 * att_change_var) / dt_s ** 2 \
        + (config.alt_rel_sigma * speed) ** 2 + config.var_floor_m2_s2
    var = min(var, INVALID_VAR_M2_S2)
    return VelocityEstimate(True, tuple(float(v) for v in vel_body), float(var), float(quality), float(dt_s), "",
                            prev.meta.seq, new.meta.seq, **counts,
                            tilt_rad=(float(fit.tilt_rad[0]), float(fit.tilt_rad[1])),
                            tilt_var_rad2=tilt_var)


@dataclass(frozen=True)
class _Fit:
    rho: float
    disp_m: np.ndarray  # D (north, east of the heading frame), metres
    tilt_rad: np.ndarray  # w: the rotation (about north, east) the newer frame's rays needed (D holds
    # its correction only when it was significant and beyond the tags' error; see _robust_fit)
    disp_cov: np.ndarray  # 2 x 2, m^2
    tilt_cov: np.ndarray  # 2 x 2, rad^2
    inliers: np.ndarray
    resid_m: float  # residual sd per axis


def _robust_fit(g_prev: np.ndarray, g_new: np.ndarray, h_m: float, rho0: float, *, prior_m: float,
                tilt_prior_rad: float) -> _Fit | None:
    """Least squares  rho g_prev - D - T(w) = g_new  (module docstring), in up to three rounds, each
    on the pairs near the previous round's fit.

    The scale has a prior rho0 (the altitude readings' ratio) worth `prior_m` of spread per pair,
    so a cluster of corners in one corner of the view cannot make it up; the tilt w a prior of 0
    with sd `tilt_prior_rad` (the tags' own error), weighed against the residual of the round's fit
    without it. Returns None when too few pairs agree.
    """
    n_all = len(g_prev)
    x, y = g_new[:, 0] / h_m, g_new[:, 1] / h_m
    # Two rows per pair (north, east); columns rho, D_n, D_e, w_n, w_e.
    a = np.zeros((n_all, 2, 5))
    a[:, 0, 0], a[:, 1, 0] = g_prev[:, 0], g_prev[:, 1]
    a[:, 0, 1] = a[:, 1, 2] = -1.0
    a[:, 0, 3], a[:, 1, 3] = h_m * x * y, h_m * (1.0 + y * y)
    a[:, 0, 4], a[:, 1, 4] = -h_m * (1.0 + x * x), -h_m * x * y
    inliers = np.ones(n_all, bool)
    for _round in range(3):
        n = int(inliers.sum())
        if n < 4:
            return None
        rows, obs = a[inliers].reshape(-1, 5), g_new[inliers].reshape(-1)
        normal = rows.T @ rows
        rhs = rows.T @ obs
        lam = n * prior_m ** 2
        normal[0, 0] += lam
        rhs[0] += lam * rho0
        # First the data alone on the tilt (a trace-relative nudge keeps a degenerate view
        # solvable), to learn the residual the tilt's prior is weighed against; then with it.
        nudge = 1e-12 * float(np.trace(normal))
        try:
            sol = np.linalg.solve(normal + np.diag([0.0, 0.0, 0.0, nudge, nudge]), rhs)
            resid2 = ((rows @ sol - obs) ** 2).sum()
            sd = max(float(np.sqrt(resid2 / max(1, 2 * n - 5))), 1e-6)
            w_tilt = (sd / tilt_prior_rad) ** 2 if tilt_prior_rad > 0.0 else nudge
            normal[3, 3] += w_tilt
            normal[4, 4] += w_tilt
            sol = np.linalg.solve(normal, rhs)
        except np.linalg.LinAlgError:
            return None
        resid = np.linalg.norm(np.einsum("nij,j->ni", a, sol) - g_new, axis=1)
        sd = max(float(np.sqrt((resid[inliers] ** 2).sum() / max(1, 2 * n - 5))), 1e-6)
        scale = 1.4826 * float(np.median(resid[inliers]))
        # Never tighter than 5 cm plus 0.2 % of the distance to the optical axis (pixel noise).
        limit = np.maximum(3.0 * scale, 0.05 + 0.002 * np.linalg.norm(g_prev, axis=1))
        new_inliers = resid <= limit
        if np.array_equal(new_inliers, inliers):
            break
        inliers = new_inliers
    if int(inliers.sum()) < 4:
        return None
    cov = sd ** 2 * np.linalg.inv(normal)
    tilt, tilt_cov = sol[3:5].copy(), cov[3:5, 3:5].copy()
    if float(tilt @ np.linalg.solve(tilt_cov, tilt)) >= TILT_SIGNIFICANT_CHI2 \
            and math.hypot(*tilt) >= TILT_CORRECT_PRIORS * tilt_prior_rad:
        return _Fit(float(sol[0]), sol[1:3].copy(), tilt, cov[1:3, 1:3].copy(), tilt_cov, inliers, sd)
    # No tilt the data can tell from their noise (a narrow or sparse view, tracking noise on a
    # fast turn), or none beyond the tags' own error: the tags stand, and the fit is the
    # three-unknown one on the same pairs.
    keep = [0, 1, 2]
    normal3, rhs3 = normal[np.ix_(keep, keep)], rhs[keep]
    sol3 = np.linalg.solve(normal3, rhs3)
    cov3 = sd ** 2 * np.linalg.inv(normal3)
    return _Fit(float(sol3[0]), sol3[1:3].copy(), tilt, cov3[1:3, 1:3].copy(), tilt_cov, inliers, sd)


class TagErrorMeter:
    """The attitude tags' real error, measured over the flight from the fits' own tilts.

    `attitude_sigma_rad` is what the autopilot is believed to deliver; a `harsh` vehicle's tags are
    several times worse (relative errors median 2.0 mrad over 0.5 s against the 0.7 stated), and
    where a view tells a tilt poorly the fit falls back on the stated prior, so its variance was
    under the error (`dovesei bench-odometry`, `harsh` flights: 88 % of the errors inside the 95 %
    circle). Where a fit does tell the tilt (its variance under `INFORMED_FRAC` of the prior's),
    its w, undone from the prior's pull, measures the two tags' difference plus the fit's noise:
    for a 2-D Gaussian the median squared norm is 2 ln 2 x the variance per axis, so over the last
    `WINDOW` such fits the tags' variance per axis is median |w|^2 / (2 ln 2) less the median of the
    fits' own. Reported once `MIN_SAMPLES` fits have been seen; 0 before (the stated one stands).
    """

    WINDOW = 100  # 10 s at 10 Hz
    MIN_SAMPLES = 20
    INFORMED_FRAC = 0.25

    def __init__(self, config: VisualVelocityConfig) -> None:
        self._prior_var = 2.0 * config.attitude_sigma_rad ** 2  # per axis, the fit's prior on w
        self._w2: deque[float] = deque(maxlen=self.WINDOW)
        self._noise: deque[float] = deque(maxlen=self.WINDOW)

    def add(self, est: VelocityEstimate) -> None:
        if not est.valid or self._prior_var <= 0.0 or not est.tilt_var_rad2 < self.INFORMED_FRAC * self._prior_var:
            return
        keep = 1.0 - est.tilt_var_rad2 / self._prior_var  # the share of the data's w the prior let through
        w_n, w_e = est.tilt_rad
        if not (is_number(w_n) and is_number(w_e)):
            return
        self._w2.append((w_n * w_n + w_e * w_e) / keep ** 2)
        self._noise.append(est.tilt_var_rad2 / keep)

    @property
    def var_rad2(self) -> float:
        """Variance per axis of the two tags' difference (0: not measured yet)."""
        if len(self._w2) < self.MIN_SAMPLES:
            return 0.0
        return max(0.0, float(np.median(self._w2)) / (2.0 * math.log(2.0)) - float(np.median(self._noise)))


class VisualVelocity:
    """Frame by frame: each `update` compares the frame with an earlier one, the newest at least
    the altitude's baseline older (`VisualVelocityConfig.baseline_s_per_m`), or the oldest kept
    while none is that old yet; None for the first frame. Its variances count the tags' error as
    measured over the flight (`TagErrorMeter`) where that exceeds the stated one."""

    def __init__(self, config: VisualVelocityConfig = VisualVelocityConfig()) -> None:
        self.config = config
        self._frames: list[PreparedFrame] = []  # oldest first, within max_baseline_s of the newest
        self.tags = TagErrorMeter(config)  # kept across resets: the tags' error is the autopilot's

    def update(self, image: np.ndarray, meta: FrameMeta) -> VelocityEstimate | None:
        new = prepare(image, meta, self.config)
        frames = self._frames
        newest = frames[-1] if frames else None
        moving_on = (newest is not None and is_number(meta.t_s) and is_number(newest.meta.t_s)
                     and meta.t_s > newest.meta.t_s)
        if moving_on:
            # The newest frame at least the baseline older (stamps carry rounding), else the oldest kept.
            target_s = self.config.baseline_s(meta.alt_agl_m) - 1e-6
            ref = next((f for f in reversed(frames) if meta.t_s - f.meta.t_s >= target_s), frames[0])
            keep_s = self.config.max_baseline_s + 1e-6
            self._frames = [f for f in frames if meta.t_s - f.meta.t_s <= keep_s] + [new]
        else:
            # The first frame, or time stood still or ran back (`estimate` says so): start afresh.
            ref, self._frames = newest, [new]
        if ref is None:
            return None
        est = estimate(ref, new, self.config, tag_change_var_rad2=self.tags.var_rad2)
        self.tags.add(est)
        return est

    def reset(self) -> None:
        """Forget the earlier frames (after a gap the next update starts afresh)."""
        self._frames = []


def odometry_message(est: VelocityEstimate, newer: FrameMeta, *, vehicle_id: str, stamp: Stamp,
                     sent_wall_s: float = 0.0) -> VisualOdometry:
    """The wire message of an estimate; `newer` is the newer frame's meta (altitude and attitude).

    Numbers are clamped into the message's bounds one last time, so a message always builds: the
    estimator's own checks make this a no-op for every valid estimate. A frame whose altitude or
    attitude is not finite gives an invalid message with zeros in their place.
    """
    def bounded(value: float, lo: float, hi: float) -> float | None:
        return float(value) if is_number(value) and lo <= value <= hi else None

    alt = bounded(newer.alt_agl_m, -1000.0, 100_000.0)
    roll, pitch = bounded(newer.roll_rad, -math.pi, math.pi), bounded(newer.pitch_rad, -math.pi, math.pi)
    yaw = math.remainder(newer.yaw_rad, math.tau) if is_number(newer.yaw_rad) else None
    valid = bool(est.valid) and None not in (alt, roll, pitch, yaw)
    vel = tuple(float(np.clip(v, -300.0, 300.0)) if valid and is_number(v) else 0.0 for v in est.vel_body_frd_m_s)
    var = float(min(max(est.vel_var_m2_s2, 0.0), 1e6)) if valid and is_number(est.vel_var_m2_s2) else INVALID_VAR_M2_S2
    quality = float(min(max(est.quality, 0.0), 1.0)) if is_number(est.quality) else 0.0
    dt_s = float(min(max(est.dt_s, 0.0), 10.0)) if is_number(est.dt_s) else 0.0
    share = float(min(max(est.texture_share, 0.0), 1.0)) if is_number(est.texture_share) else 0.0
    offset = tuple(float(np.clip(v, TEXTURE_OFFSET_MIN, TEXTURE_OFFSET_MAX)) if is_number(v) else 0.0
                   for v in est.texture_offset)
    return VisualOdometry(vehicle_id=vehicle_id, frame_seq=int(est.seq), prev_frame_seq=int(est.prev_seq), stamp=stamp,
                          vel_body_frd_m_s=vel, vel_var_m2_s2=var, quality=quality, valid=valid, dt_s=dt_s,
                          alt_agl_m=alt or 0.0, sent_wall_s=sent_wall_s, roll_rad=roll or 0.0, pitch_rad=pitch or 0.0,
                          yaw_rad=yaw or 0.0, texture_share=share, texture_offset=offset)
