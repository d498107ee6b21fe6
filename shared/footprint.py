"""What a nadir pinhole camera sees of flat ground: the one formula every service and tool uses.

A square-pixel camera `width_px` wide with horizontal field of view `hfov_rad`, level at
`alt_agl_m` above flat ground, sees a footprint tan(hfov / 2) x alt metres either side of its
optical axis; its focal length is (width_px / 2) / tan(hfov / 2) pixels, so one pixel near the
centre covers 2 alt tan(hfov / 2) / width_px metres. Tilted views (ray by ray) build on the focal
length, and `tilt_rotation` turns body rays into the heading-level frame. The expressions keep one evaluation order so every caller gets the same bits it got
before they were gathered here (bench records depend on it).
"""

from __future__ import annotations

import math

import numpy as np

# The reference camera's horizontal field of view: the paper's 73 deg, which its code renders and
# this project's sim, camera service and controller take by default. A real camera says its own.
REFERENCE_HFOV_DEG = 73.0
REFERENCE_HFOV_RAD = math.radians(REFERENCE_HFOV_DEG)


def focal_px(width_px: float, hfov_rad: float) -> float:
    """Focal length in pixels of a camera `width_px` wide with horizontal field of view `hfov_rad`."""
    return (width_px / 2.0) / math.tan(hfov_rad / 2.0)


def half_width_m(alt_agl_m: float, hfov_rad: float) -> float:
    """Half the ground footprint's width (across the image's columns) at an altitude."""
    return math.tan(hfov_rad / 2.0) * alt_agl_m


def width_m(alt_agl_m: float, hfov_rad: float) -> float:
    """The ground footprint's full width at an altitude."""
    return 2.0 * half_width_m(alt_agl_m, hfov_rad)


def metres_per_px(alt_agl_m: float, hfov_rad: float, width_px: float) -> float:
    """Ground size of one pixel of an image `width_px` wide at an altitude (square pixels)."""
    return width_m(alt_agl_m, hfov_rad) / width_px


def tilt_rotation(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """Body (forward, right, down) -> heading-level (forward, right, down): R_y(pitch) @ R_x(roll)."""
    cr, sr, cp, sp = math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    return np.array([[cp, sp * sr, sp * cr],
                     [0.0, cr, -sr],
                     [-sp, cp * sr, cp * cr]], dtype=np.float64)
