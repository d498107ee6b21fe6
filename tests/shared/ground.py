"""A flat textured ground seen by a pinhole camera with any attitude, for the visual-velocity tests.

Written apart from `dovesei.shared.visual_velocity` (a per-pixel ray cast onto the plane and
`cv2.remap`), so the estimator's geometry is checked against an independent model: a camera at
(north, east, altitude) with roll, pitch and yaw (ZYX, body to NED), image up = body forward,
image right = body right.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

HFOV = math.radians(73.0)


def make_texture(size: int = 2048, seed: int = 0) -> np.ndarray:
    """Grey ground with detail at three scales (2, 8, 32 texels), contrast like aerial imagery."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.float32)
    for s in (2, 8, 32):
        n = rng.normal(0, 1, (size // s + 1, size // s + 1)).astype(np.float32)
        img += cv2.resize(n, (size, size), interpolation=cv2.INTER_CUBIC)[:size, :size] * math.sqrt(s)
    img = (img - img.mean()) / img.std() * 40 + 128
    return np.clip(img, 0, 255).astype(np.uint8)


TEXTURE = make_texture()


def ned_to_body(vel_ned, roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    r = np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                  [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                  [-sp, sr * cp, cr * cp]])
    return r.T @ np.asarray(vel_ned, float)


def view(north: float, east: float, alt: float, yaw: float = 0.0, roll: float = 0.0, pitch: float = 0.0,
         w: int = 640, h: int = 480, gsd: float | None = None, rgb: bool = True, hfov: float = HFOV) -> np.ndarray:
    """What the camera sees of TEXTURE (centred on the origin) from that pose."""
    gsd = gsd if gsd is not None else alt / 400.0  # about 1.5 texels per image pixel at any altitude
    f = (w / 2) / math.tan(hfov / 2)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    body = np.stack([-(v - (h - 1) / 2) / f, (u - (w - 1) / 2) / f, np.ones_like(u)], axis=-1)
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    r = np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                  [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                  [-sp, sr * cp, cr * cp]])
    ned = body @ r.T
    gn = north + alt * ned[..., 0] / ned[..., 2]
    ge = east + alt * ned[..., 1] / ned[..., 2]
    size = TEXTURE.shape[0]
    col = (ge / gsd + size / 2).astype(np.float32)
    row = (size / 2 - gn / gsd).astype(np.float32)
    grey = cv2.remap(TEXTURE, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB) if rgb else grey
