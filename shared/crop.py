"""Close-look crops: the geometry of a ground square in a camera frame, and what a camera refuses.

A `CropRequest` names a square of flat ground by its centre (forward, right metres from the point
straight below the vehicle, in the heading-level body frame at the capture) and its side, and asks
for it `out_px` pixels a side. Image up = body forward, image right = body right, as every frame.

    crop pixel (u, v) --square--> ground point (forward, right, alt) in the heading-level frame
      --tilt (roll, pitch; body = R^T level)--> body ray --pinhole (focal f, centre cu, cv)--> source
      pixel (col, row)

is one 3x3 homography (`crop_homography`), so a camera cuts the crop with one `cv2.warpPerspective`
from its newest full-resolution frame, whatever the tilt (`cut_crop`). The sim renders the same
square from its world instead (`dovesei.sim.camera.render_ground_square`).

A camera answers only what it can answer well (`CropLimits.refusal`): a side and an output size
within bounds, a square whose four corners lie inside the frame, no more than `max_upsample` times
finer than the detail the frame has there, and at most `rate_hz` crops a second (`RateLimit`). A
refusal is one line naming what was wrong; the service replies it as an error and keeps serving.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.shared import footprint, validate
from dovesei.shared.footprint import tilt_rotation
from dovesei.shared.errors import DoveseiError
from dovesei.shared.messages import CropRequest

# The steepest ray a crop may use: 80 deg from straight down (a square near the horizon is a smear).
_MIN_RAY_DOWN = math.cos(math.radians(80.0))


class CropRefused(DoveseiError, ValueError):
    """A crop request a camera will not answer; the text says why in one line."""


@dataclass(frozen=True)
class CropLimits:
    """What a camera (or the sim in its place) agrees to cut; every refusal names the bound."""

    min_side_m: float = 0.5
    max_side_m: float = 200.0
    min_out_px: int = 32
    max_out_px: int = 1024
    max_upsample: float = 8.0  # crop pixels per source pixel at the centre: beyond it the detail is made up
    rate_hz: float = 5.0  # crops a second, sustained
    burst: int = 5  # crops at once after a quiet spell

    def __post_init__(self) -> None:
        validate.positive("crop min_side_m", self.min_side_m)
        validate.in_range("crop max_side_m", self.max_side_m, self.min_side_m, 1e4)
        validate.in_range("crop min_out_px", self.min_out_px, 1, 8192)
        validate.in_range("crop max_out_px", self.max_out_px, self.min_out_px, 8192)
        validate.in_range("crop max_upsample", self.max_upsample, 1.0, 1000.0)
        validate.positive("crop rate_hz", self.rate_hz)
        validate.in_range("crop burst", self.burst, 1, 1000)

    def size_refusal(self, req: CropRequest) -> str | None:
        """Why the request's sizes are refused (None: they are fine)."""
        if not self.min_side_m <= req.side_m <= self.max_side_m:
            return f"side {req.side_m:g} m outside {self.min_side_m:g}..{self.max_side_m:g} m"
        if not self.min_out_px <= req.out_px <= self.max_out_px:
            return f"output {req.out_px} px outside {self.min_out_px}..{self.max_out_px} px"
        return None

    def detail_refusal(self, req: CropRequest, source_m_per_px: float) -> str | None:
        """Why the crop would invent detail the source does not have (None: it would not)."""
        upsample = source_m_per_px / (req.side_m / req.out_px)
        if upsample > self.max_upsample:
            return (f"{req.out_px} px over {req.side_m:g} m is {upsample:.1f}x finer than the frame's "
                    f"{source_m_per_px * 100:.1f} cm/px there (at most {self.max_upsample:g}x)")
        return None


class RateLimit:
    """A token bucket on the caller's clock: `allow(now_s)` is False when asked too often."""

    def __init__(self, rate_hz: float, burst: int) -> None:
        self.rate_hz, self.burst = float(rate_hz), int(burst)
        self._tokens = float(burst)
        self._last_s: float | None = None

    def allow(self, now_s: float) -> bool:
        if self._last_s is not None:
            self._tokens = min(float(self.burst), self._tokens + max(0.0, now_s - self._last_s) * self.rate_hz)
        self._last_s = now_s
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False

    def refusal(self) -> str:
        return f"too frequent: at most {self.rate_hz:g} crops/s (burst {self.burst})"


def square_to_level(centre_frd_m: tuple[float, float], side_m: float, out_px: int, alt_agl_m: float) -> np.ndarray:
    """3x3: crop pixel (u right, v down, 1) -> ground point (forward, right, alt) in the heading-level frame."""
    s = side_m / out_px
    c = (out_px - 1) / 2.0
    fwd, right = centre_frd_m
    return np.array([[0.0, -s, fwd + s * c],
                     [s, 0.0, right - s * c],
                     [0.0, 0.0, alt_agl_m]], dtype=np.float64)


def crop_homography(req_centre_frd_m: tuple[float, float], side_m: float, out_px: int, *, alt_agl_m: float,
                    roll_rad: float, pitch_rad: float, width_px: int, height_px: int, hfov_rad: float) -> np.ndarray:
    """3x3: crop pixel (u, v, 1) -> source pixel (col, row) in homogeneous form, for a square-pixel
    pinhole `width_px` x `height_px` with horizontal field of view `hfov_rad`, tilted by roll/pitch."""
    f_px = footprint.focal_px(width_px, hfov_rad)
    cu, cv_ = (width_px - 1) / 2.0, (height_px - 1) / 2.0
    # Body ray (forward, right, down) -> pixel: col = cu + f right / down, row = cv - f forward / down.
    k = np.array([[0.0, f_px, cu],
                  [-f_px, 0.0, cv_],
                  [0.0, 0.0, 1.0]], dtype=np.float64)
    return k @ tilt_rotation(roll_rad, pitch_rad).T @ square_to_level(req_centre_frd_m, side_m, out_px, alt_agl_m)


def view_refusal(h: np.ndarray, out_px: int, width_px: int, height_px: int) -> str | None:
    """Why the square does not lie inside the frame (None: all four corners map inside it)."""
    corners = np.array([[0, out_px - 1, 0, out_px - 1], [0, 0, out_px - 1, out_px - 1], [1, 1, 1, 1]], float)
    mapped = h @ corners
    if np.any(mapped[2] <= 0.0):
        return "the square lies behind the camera (at or above the horizon)"
    col, row = mapped[0] / mapped[2], mapped[1] / mapped[2]
    if col.min() < -0.5 or row.min() < -0.5 or col.max() > width_px - 0.5 or row.max() > height_px - 0.5:
        return (f"the square reaches outside the camera's view (corners at columns {col.min():.0f}..{col.max():.0f}, "
                f"rows {row.min():.0f}..{row.max():.0f} of a {width_px}x{height_px} frame)")
    return None


def source_m_per_px(alt_agl_m: float, roll_rad: float, pitch_rad: float, width_px: int, hfov_rad: float,
                    centre_frd_m: tuple[float, float]) -> float:
    """Ground size of one source pixel at the square's centre (slant range / focal length)."""
    fwd, right = centre_frd_m
    slant_m = math.sqrt(fwd * fwd + right * right + alt_agl_m * alt_agl_m)
    # The ray to the centre meets the ground obliquely: the footprint of a pixel grows by 1/cos.
    down = (tilt_rotation(roll_rad, pitch_rad).T @ np.array([fwd, right, alt_agl_m]))[2] / slant_m
    return slant_m / footprint.focal_px(width_px, hfov_rad) / max(down, _MIN_RAY_DOWN)


def _translate(h: np.ndarray, col0: float, row0: float, scale_x: float = 1.0, scale_y: float = 1.0) -> np.ndarray:
    """`h` followed by: shift the source by (-col0, -row0), then scale it (pixel centres kept)."""
    shift = np.array([[1.0, 0.0, -col0], [0.0, 1.0, -row0], [0.0, 0.0, 1.0]])
    scale = np.array([[scale_x, 0.0, 0.5 * scale_x - 0.5], [0.0, scale_y, 0.5 * scale_y - 0.5], [0.0, 0.0, 1.0]])
    return scale @ shift @ h


def cut_crop(image: np.ndarray, h: np.ndarray, out_px: int) -> np.ndarray:
    """The square cut from a full-resolution frame (bilinear; area-averaged first when it shrinks).

    Only the source region under the square is touched (a 12 MP frame is never copied whole)."""
    corners = h @ np.array([[0, out_px - 1, 0, out_px - 1], [0, 0, out_px - 1, out_px - 1], [1, 1, 1, 1]], float)
    cols, rows = corners[0] / corners[2], corners[1] / corners[2]
    src_h, src_w = image.shape[:2]
    col0, row0 = max(0, int(math.floor(cols.min())) - 2), max(0, int(math.floor(rows.min())) - 2)
    col1, row1 = min(src_w, int(math.ceil(cols.max())) + 3), min(src_h, int(math.ceil(rows.max())) + 3)
    src, m = image[row0:row1, col0:col1], _translate(h, col0, row0)
    # Source pixels per crop pixel: the square's extent in the source over its extent in the crop.
    shrink = max(cols.max() - cols.min(), rows.max() - rows.min()) / max(out_px - 1, 1)
    if shrink > 1.5:
        # Average the region down first, so a bilinear lookup does not alias its fine detail away.
        small = cv2.resize(src, None, fx=1.0 / shrink, fy=1.0 / shrink, interpolation=cv2.INTER_AREA)
        m = _translate(m, 0.0, 0.0, small.shape[1] / src.shape[1], small.shape[0] / src.shape[0])
        src = small
    return cv2.warpPerspective(src, m, (out_px, out_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)


@dataclass(frozen=True)
class CropPlan:
    """An accepted request: the homography into the source frame and the detail the source has."""

    homography: np.ndarray
    source_m_per_px: float


def plan_crop(req: CropRequest, limits: CropLimits, rate: RateLimit, now_s: float, *, vehicle_id: str,
              newest_seq: int | None, alt_agl_m: float, roll_rad: float, pitch_rad: float, width_px: int,
              height_px: int, hfov_rad: float) -> CropPlan:
    """Check a request against the newest capture (seq, tags, the full-resolution camera model) and
    the limits; CropRefused names the first thing wrong. Only a request that passes every other check
    spends a token of the rate limit (a burst of garbage cannot lock out the honest asker)."""
    if req.vehicle_id != vehicle_id:
        raise CropRefused(f"request for vehicle {req.vehicle_id!r}, this camera is {vehicle_id!r}")
    if newest_seq is None:
        raise CropRefused("no frame captured yet")
    if req.frame_seq not in (-1, newest_seq):
        raise CropRefused(f"frame {req.frame_seq} is not kept (only the newest, {newest_seq}; ask -1 for it)")
    problem = limits.size_refusal(req)
    if problem is None and not alt_agl_m > 0.0:
        problem = f"the capture's altitude {alt_agl_m:g} m gives no ground to cut"
    h = None
    if problem is None:
        h = crop_homography(req.centre_frd_m, req.side_m, req.out_px, alt_agl_m=alt_agl_m, roll_rad=roll_rad,
                            pitch_rad=pitch_rad, width_px=width_px, height_px=height_px, hfov_rad=hfov_rad)
        problem = view_refusal(h, req.out_px, width_px, height_px)
    src_m = 0.0
    if problem is None:
        src_m = source_m_per_px(alt_agl_m, roll_rad, pitch_rad, width_px, hfov_rad, req.centre_frd_m)
        problem = limits.detail_refusal(req, src_m)
    if problem is None and not rate.allow(now_s):
        problem = rate.refusal()
    if problem is not None:
        raise CropRefused(f"crop {req.request_seq} refused: {problem}")
    return CropPlan(h, src_m)
