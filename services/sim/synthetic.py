"""Procedural aerial "city" world: an orthophoto-like RGB image and its per-pixel class map.

This is the simulator's embedded default world (DESIGN.md section 7a). Everything is derived
from `SyntheticParams` (seed, size, ground sample distance), so the same params always give the
same bytes, and `load_or_generate` caches the result on disk.

Data flow of `generate_city`:

    seed -> layout (road grid, blocks of one kind each, optional river, sun direction)
         -> drawing pass on a `_Canvas` (flat colours into RGB, class ids into labels and object
            heights into a height map, all with the SAME polygons; shadow casters are queued)
         -> trees last (their canopy covers, and relabels, whatever is under them)
         -> shadow pass (queued casters rasterised into a "shadow height" map; a pixel is in
            shadow where something taller stands between it and the sun)
         -> texture pass (per-class noise at several scales, tints, shadows, colour grading)
         -> slight camera blur of the image (labels stay crisp)

World frame: x to the right (image columns), y down (image rows), metres from the top-left
corner; pixel (r, c) covers [c, c+1) x [r, r+1) times `gsd_m`. Shadows are not a class: they
only darken what they fall on. Class ids and which are safe: `SYNTHETIC_CLASSES`.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from dovesei.shared.errors import ConfigError

log = logging.getLogger(__name__)

# Bump whenever the look or the layout changes: it is part of the cache file name.
GENERATOR_VERSION = 2

ROOF_FLAT, ROOF_PITCHED, ROAD, SIDEWALK, PLAZA, PARKING_LOT, CAR = 1, 2, 3, 4, 5, 6, 7
GRASS, SPORTS_FIELD, TREE, WATER, BARE_SOIL, PERSON = 8, 9, 10, 11, 12, 13

# id -> (name, safe to land on). Fixed: other tools and stored results refer to these ids.
SYNTHETIC_CLASSES: dict[int, tuple[str, bool]] = {
    ROOF_FLAT: ("roof_flat", False),
    ROOF_PITCHED: ("roof_pitched", False),
    ROAD: ("road", False),
    SIDEWALK: ("sidewalk", False),
    PLAZA: ("plaza", True),
    PARKING_LOT: ("parking_lot", True),
    CAR: ("car", False),
    GRASS: ("grass", True),
    SPORTS_FIELD: ("sports_field", True),
    TREE: ("tree", False),
    WATER: ("water", False),
    BARE_SOIL: ("bare_soil", True),
    PERSON: ("person", False),
}

SIZE_RANGE_M = (200.0, 5000.0)
GSD_RANGE_M = (0.05, 1.0)
# 16384^2 px is ~1 GB of RGB + labels; beyond that the world does not fit "reasonable memory".
MAX_SIDE_PX = 16384

_SHIFT = 3  # OpenCV sub-pixel bits: polygons are placed to 1/8 px
_HEIGHT_UNIT_M = 0.2  # the height map is uint8 in these units (0..51 m)
RGB = tuple[int, int, int]


class SyntheticWorldError(ConfigError):
    """Bad synthetic-world parameters or spec string."""


@dataclass(frozen=True)
class SyntheticParams:
    """What a synthetic world is a function of; equal params give byte-identical worlds."""

    seed: int = 0
    size_m: float = 1600.0
    gsd_m: float = 0.25

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise SyntheticWorldError(f"seed must be an integer, got {self.seed!r}")
        if not 0 <= int(self.seed) < 2**63:
            raise SyntheticWorldError(f"seed must be in [0, 2**63), got {self.seed}")
        for name, value, (lo, hi) in (
            ("size_m", self.size_m, SIZE_RANGE_M),
            ("gsd_m", self.gsd_m, GSD_RANGE_M),
        ):
            number = isinstance(value, (int, float, np.floating, np.integer))
            if isinstance(value, bool) or not number:
                raise SyntheticWorldError(f"{name} must be a number, got {value!r}")
            if not (math.isfinite(value) and lo <= value <= hi):
                raise SyntheticWorldError(f"{name} must be in [{lo:g}, {hi:g}], got {value!r}")
        if self.side_px > MAX_SIDE_PX:
            raise SyntheticWorldError(
                f"size_m / gsd_m = {self.side_px} px per side exceeds {MAX_SIDE_PX} px; "
                "use a coarser gsd_m or a smaller size_m"
            )

    @property
    def side_px(self) -> int:
        return int(round(self.size_m / self.gsd_m))


def parse_spec(spec: str) -> SyntheticParams:
    """Parse the CLI form `synthetic[:seed=N,size_m=X,gsd_m=Y]` (any subset, any order)."""
    if not isinstance(spec, str):
        raise SyntheticWorldError(f"world spec must be a string, got {type(spec).__name__}")
    head, sep, tail = spec.strip().partition(":")
    if head != "synthetic":
        raise SyntheticWorldError(f"world spec {spec!r} does not start with 'synthetic'")
    if sep and not tail.strip():
        raise SyntheticWorldError(f"world spec {spec!r}: nothing after ':'")
    kinds = {"seed": int, "size_m": float, "gsd_m": float}
    values: dict[str, float | int] = {}
    for item in tail.split(",") if tail.strip() else []:
        key, eq, raw = (s.strip() for s in item.partition("="))
        if not eq or not key or not raw:
            raise SyntheticWorldError(f"world spec {spec!r}: expected key=value, got {item!r}")
        if key not in kinds:
            raise SyntheticWorldError(
                f"world spec {spec!r}: unknown key {key!r} (known: {', '.join(kinds)})"
            )
        if key in values:
            raise SyntheticWorldError(f"world spec {spec!r}: key {key!r} given twice")
        try:
            values[key] = kinds[key](raw)
        except ValueError:
            raise SyntheticWorldError(
                f"world spec {spec!r}: {key}={raw!r} is not a valid {kinds[key].__name__}"
            ) from None
    return SyntheticParams(**values)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------------
# Palettes (RGB). Base colours are flat; the texture pass adds grain, patches and shadows.

_ASPHALT = (82, 84, 86)
_LOT_ASPHALT = (96, 96, 95)
_PAINT = (228, 228, 222)
_SIDEWALK = (168, 164, 156)
_GRASS = [(98, 128, 62), (88, 122, 58), (106, 130, 66), (84, 116, 56), (112, 128, 70)]
_TREE = [(50, 76, 40), (58, 86, 44), (45, 68, 42), (66, 92, 48), (40, 60, 46), (72, 90, 52)]
_ROOF_PITCHED = [  # (colour, weight): clay tiles dominate, then slate, metal, concrete tiles
    ((176, 88, 62), 4.0), ((158, 76, 56), 3.0), ((128, 78, 60), 2.0), ((74, 76, 82), 2.5),
    ((138, 142, 146), 1.2), ((140, 58, 52), 0.7), ((78, 104, 90), 0.5), ((110, 104, 98), 1.5),
]
_ROOF_FLAT = [
    ((168, 166, 160), 3.0), ((184, 178, 166), 2.0), ((92, 92, 95), 2.0), ((214, 214, 210), 1.5),
    ((132, 132, 134), 2.0), ((150, 140, 126), 1.0),
]
_CAR = [
    ((232, 232, 230), 24), ((30, 30, 34), 18), ((118, 120, 124), 16), ((176, 178, 182), 13),
    ((40, 64, 120), 9), ((150, 30, 30), 7), ((44, 80, 52), 3), ((196, 180, 150), 4),
    ((220, 180, 40), 2), ((90, 50, 40), 4),
]
_CLOTHES = [(30, 30, 35), (200, 40, 40), (40, 70, 160), (235, 235, 235), (230, 200, 40),
            (90, 90, 95), (150, 110, 80), (40, 140, 70)]
_WATER_POND = (52, 74, 72)
_WATER_RIVER = (58, 82, 92)
_WATER_POOL = (96, 186, 206)
_SOIL = (150, 122, 92)

# Texture amplitudes per class: grain (per pixel), mid (~0.75 m), coarse (~5-15 m) relative
# luminance modulation, and an RGB tint driven by a ~30-60 m patch field (dry grass, stains).
_TEX_GRAIN = {ROOF_FLAT: .035, ROOF_PITCHED: .05, ROAD: .05, SIDEWALK: .04, PLAZA: .04,
              PARKING_LOT: .05, CAR: .015, GRASS: .06, SPORTS_FIELD: .04, TREE: .08,
              WATER: .015, BARE_SOIL: .08, PERSON: 0.0}
_TEX_MID = {ROOF_FLAT: .03, ROOF_PITCHED: .06, ROAD: .03, SIDEWALK: .03, PLAZA: .03,
            PARKING_LOT: .03, CAR: 0.0, GRASS: .09, SPORTS_FIELD: .03, TREE: .26,
            WATER: .02, BARE_SOIL: .09, PERSON: 0.0}
_TEX_COARSE = {ROOF_FLAT: .06, ROOF_PITCHED: .04, ROAD: .07, SIDEWALK: .05, PLAZA: .05,
               PARKING_LOT: .07, CAR: 0.0, GRASS: .12, SPORTS_FIELD: .04, TREE: .10,
               WATER: .06, BARE_SOIL: .14, PERSON: 0.0}
_TEX_TINT = {GRASS: (34, 18, 4), BARE_SOIL: (18, 12, 6), TREE: (10, 8, 0), ROAD: (6, 6, 6),
             ROOF_FLAT: (-8, -8, -6), WATER: (-6, 4, 0), PARKING_LOT: (6, 6, 6)}
# Shadowed surfaces get the bluish sky light only: per-channel factor.
_SHADOW_RGB = np.array([0.42, 0.46, 0.56], np.float32)


class _FastRng:
    """A numpy Generator whose scalar `random`, `uniform` and `normal` are served from
    pre-drawn blocks: the drawing pass makes ~10^5 scalar draws, and numpy's per-call overhead
    was a sizeable part of generation time. Everything else is delegated. Deterministic."""

    _BLOCK = 8192

    def __init__(self, seed: np.random.SeedSequence) -> None:
        self.gen = np.random.default_rng(seed)
        self._u: list[float] = []
        self._n: list[float] = []

    def __getattr__(self, name: str):
        return getattr(self.gen, name)

    def random(self, size=None, dtype=np.float64):
        if size is not None:
            return self.gen.random(size, dtype=dtype)
        if not self._u:
            self._u = self.gen.random(self._BLOCK).tolist()
        return self._u.pop()

    def uniform(self, low=0.0, high=1.0, size=None):
        if size is not None:
            return self.gen.uniform(low, high, size)
        return low + (high - low) * self.random()

    def normal(self, loc=0.0, scale=1.0, size=None):
        if size is not None:
            return self.gen.normal(loc, scale, size)
        if not self._n:
            self._n = self.gen.standard_normal(self._BLOCK).tolist()
        return loc + scale * self._n.pop()


def _uni(rng: np.random.Generator, lo, hi, size=None):
    """rng.uniform that tolerates an empty range (hi < lo: returns lo), which odd block sizes
    produce; it always consumes the same draws, so determinism does not depend on it."""
    return rng.uniform(lo, hi if hi > lo else lo, size)


def _u8(v: float) -> int:
    return 0 if v < 0 else 255 if v > 255 else int(v)


def _pick(rng: np.random.Generator, weighted: list[tuple[RGB, float]]) -> RGB:
    # Plain Python on purpose: called per object, where numpy's per-call overhead dominates.
    x = rng.random() * sum(p for _, p in weighted)
    for rgb, p in weighted:
        x -= p
        if x <= 0:
            return rgb
    return weighted[-1][0]


def _jit(rng: np.random.Generator, rgb: RGB, rel: float = 0.06) -> RGB:
    """Object-to-object colour variation: a common brightness factor plus a little hue noise."""
    k = 1.0 + rel * rng.normal()
    return (_u8(rgb[0] * k + 3 * rng.normal()), _u8(rgb[1] * k + 3 * rng.normal()),
            _u8(rgb[2] * k + 3 * rng.normal()))


def _scale(rgb: RGB, k: float) -> RGB:
    return (_u8(rgb[0] * k), _u8(rgb[1] * k), _u8(rgb[2] * k))


def _mix(a: RGB, b: RGB, t: float) -> RGB:
    return (_u8(a[0] + (b[0] - a[0]) * t + 0.5), _u8(a[1] + (b[1] - a[1]) * t + 0.5),
            _u8(a[2] + (b[2] - a[2]) * t + 0.5))


# ----------------------------------------------------------------------------------------------
# Canvas: every drawing primitive writes image, labels and heights with the same polygon, so the
# label map is exactly what was drawn.


@dataclass
class _Tree:
    x_m: float
    y_m: float
    r_m: float
    h_m: float
    rgb: RGB


class _Canvas:
    def __init__(self, side_px: int, gsd_m: float, sun_az_rad: float, sun_el_rad: float) -> None:
        self.side_px = side_px
        self.gsd_m = gsd_m
        self.img = np.empty((side_px, side_px, 3), np.uint8)
        self.lab = np.zeros((side_px, side_px), np.uint8)
        self.height_u = np.zeros((side_px, side_px), np.uint8)
        # Unit vector towards the sun in the image plane, and ground shadow offset per metre of
        # height (pointing away from the sun).
        self.sun_xy = np.array([math.cos(sun_az_rad), math.sin(sun_az_rad)])
        self.sun_el_rad = sun_el_rad
        self.shadow_per_m = -self.sun_xy / math.tan(sun_el_rad)
        # Queued shadow casters: (height units, draw function, its arguments after the image).
        # Opaque casters darken fully; foliage (`soft_casts`) lets some light through.
        self.casts: list[tuple] = []
        self.soft_casts: list[tuple] = []
        self.trees: list[_Tree] = []
        self._k = (1 << _SHIFT) / gsd_m
        self._half = 0.5 * (1 << _SHIFT)

    # -- coordinates
    def px(self, pts_m) -> np.ndarray:
        a = np.asarray(pts_m, np.float64) * self._k
        a -= self._half
        return a.round().astype(np.int32)

    def _pt(self, p) -> tuple[int, int]:
        # floor(x + 0.5): round half up, cheaper than round() in this hot path
        return (math.floor(p[0] * self._k - self._half + 0.5),
                math.floor(p[1] * self._k - self._half + 0.5))

    def _thick(self, width_m: float) -> int:
        return max(1, int(round(width_m / self.gsd_m)))

    @staticmethod
    def _hu(h_m: float) -> int:
        u = int(h_m * (1 / _HEIGHT_UNIT_M) + 0.5)
        return 0 if u < 0 else 255 if u > 255 else u

    def in_world(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        size = self.side_px * self.gsd_m
        return x1 > 0 and y1 > 0 and x0 < size and y0 < size

    # -- primitives; cls=None paints the image only (markings, details on a labelled surface)
    def poly(self, pts_m, rgb: RGB, cls: int | None = None, h_m: float = 0.0) -> None:
        p = [self.px(pts_m)]
        cv2.fillPoly(self.img, p, rgb, cv2.LINE_8, _SHIFT)
        if cls is not None:
            cv2.fillPoly(self.lab, p, cls, cv2.LINE_8, _SHIFT)
            cv2.fillPoly(self.height_u, p, self._hu(h_m), cv2.LINE_8, _SHIFT)

    def rect(self, x0, y0, x1, y1, rgb: RGB, cls: int | None = None, h_m: float = 0.0) -> None:
        self.poly([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], rgb, cls, h_m)

    def disc(self, c, r_m: float, rgb: RGB, cls: int | None = None, h_m: float = 0.0) -> None:
        cp, rp = self._pt(c), max(1, int(r_m * self._k + 0.5))
        cv2.circle(self.img, cp, rp, rgb, -1, cv2.LINE_8, _SHIFT)
        if cls is not None:
            cv2.circle(self.lab, cp, rp, cls, -1, cv2.LINE_8, _SHIFT)
            cv2.circle(self.height_u, cp, rp, self._hu(h_m), -1, cv2.LINE_8, _SHIFT)

    def band(self, pts_m, width_m: float, rgb: RGB, cls: int | None = None, h_m: float = 0.0,
             closed: bool = False, under: RGB | None = None) -> None:
        """A polyline `width_m` wide. Lines thinner than a pixel are drawn 1 px wide with their
        colour blended towards `under` in proportion, so thin paint does not look too bold."""
        if under is not None and width_m < self.gsd_m:
            rgb = _mix(under, rgb, width_m / self.gsd_m)
        p, t = [self.px(pts_m)], self._thick(width_m)
        cv2.polylines(self.img, p, closed, rgb, t, cv2.LINE_8, _SHIFT)
        if cls is not None:
            cv2.polylines(self.lab, p, closed, cls, t, cv2.LINE_8, _SHIFT)
            cv2.polylines(self.height_u, p, closed, self._hu(h_m), t, cv2.LINE_8, _SHIFT)

    # -- shadows are queued and rasterised once at the end (tallest last, so the map holds max)
    def cast(self, pts_m, h_m: float, h_lo_m: float = 0.0, base_m: float = 0.0) -> None:
        """Queue the shadow of a prism (footprint `pts_m`, from h_lo_m up to h_m) standing on a
        surface at base_m (a roof for a roof-top plant box): its shadow is laid out for a
        receiver at base_m, and darkens everything lower than h_m under it."""
        p = np.asarray(pts_m, np.float64)
        swept = np.vstack([p + self.shadow_per_m * max(0.0, h_lo_m - base_m),
                           p + self.shadow_per_m * (h_m - base_m)])
        self.casts.append((self._hu(h_m), _fill_hull, cv2.convexHull(self.px(swept))))

    def cast_px(self, pts_px: np.ndarray, h_m: float) -> None:
        """`cast` for a footprint already in canvas units (saves a conversion for small objects)."""
        off = np.round(self.shadow_per_m * (h_m * self._k)).astype(np.int32)
        hull = cv2.convexHull(np.vstack([pts_px, pts_px + off]))
        self.casts.append((self._hu(h_m), _fill_hull, hull))

    def cast_disc(self, c, r_m: float, h_m: float, h_lo_m: float = 0.0) -> None:
        """Shadow of a disc raised between h_lo_m and h_m (a crown, a person): a round-capped
        thick line, which is exactly the swept disc and far cheaper than a polygon hull."""
        d = self.shadow_per_m
        p0 = self._pt((c[0] + d[0] * h_lo_m, c[1] + d[1] * h_lo_m))
        p1 = self._pt((c[0] + d[0] * h_m, c[1] + d[1] * h_m))
        thick_px = max(1, int(round(2 * r_m / self.gsd_m)))
        self.casts.append((self._hu(h_m), _thick_line, p0, p1, thick_px))

    def cast_crown(self, c, r_m: float, h_m: float) -> None:
        """Shadow of a tree: the crown's shadow is an ellipse stretched along the sun's azimuth
        by 1/sin(elevation), detached from the trunk, which casts a thin line up to it."""
        d = self.shadow_per_m
        centre = self._pt((c[0] + d[0] * h_m * 0.62, c[1] + d[1] * h_m * 0.62))
        along = r_m * 0.9 / math.sin(self.sun_el_rad)
        axes = (max(1, int(along * self._k)), max(1, int(r_m * 0.9 * self._k)))
        angle = math.degrees(math.atan2(d[1], d[0]))
        self.soft_casts.append((self._hu(h_m), _fill_ellipse, centre, axes, angle))
        trunk = self._pt((c[0] + d[0] * h_m * 0.45, c[1] + d[1] * h_m * 0.45))
        self.casts.append((self._hu(h_m * 0.45), _thick_line, self._pt(c), trunk,
                           max(1, int(round(0.3 / self.gsd_m)))))

    def label_at(self, x_m: float, y_m: float) -> int:
        c, r = int(x_m / self.gsd_m), int(y_m / self.gsd_m)
        if 0 <= r < self.side_px and 0 <= c < self.side_px:
            return int(self.lab[r, c])
        return 0


_UNIT_CIRCLES = {n: np.stack([np.cos(a), np.sin(a)], axis=1)
                 for n in (6, 10, 12, 40) for a in [np.linspace(0, 2 * math.pi, n, endpoint=False)]}


def _fill_hull(img: np.ndarray, value: int, hull: np.ndarray) -> None:
    cv2.fillConvexPoly(img, hull, value, cv2.LINE_8, _SHIFT)


def _thick_line(img: np.ndarray, value: int, p0, p1, thick_px: int) -> None:
    cv2.line(img, p0, p1, value, thick_px, cv2.LINE_8, _SHIFT)


def _fill_ellipse(img: np.ndarray, value: int, centre, axes, angle_deg: float) -> None:
    cv2.ellipse(img, centre, axes, angle_deg, 0, 360, value, -1, cv2.LINE_8, _SHIFT)


def _circle_pts(c, r_m: float, n: int = 12) -> np.ndarray:
    unit = _UNIT_CIRCLES.get(n)
    if unit is None:
        a = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
        unit = np.stack([np.cos(a), np.sin(a)], axis=1)
    return unit * r_m + (c[0], c[1])


_OBB_UNIT = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], np.float64)


def _obb(cx: float, cy: float, length_m: float, width_m: float, ang_rad: float,
         chamfer_m: float = 0.0) -> np.ndarray:
    """Corners of a rotated rectangle (optionally with chamfered corners), length along ang."""
    hl, hw = length_m / 2, width_m / 2
    if chamfer_m > 0:
        c = chamfer_m
        local = np.array([(-hl + c, -hw), (hl - c, -hw), (hl, -hw + c), (hl, hw - c), (hl - c, hw),
                          (-hl + c, hw), (-hl, hw - c), (-hl, -hw + c)])
    else:
        local = _OBB_UNIT * (hl, hw)
    ca, sa = math.cos(ang_rad), math.sin(ang_rad)
    return local @ np.array([[ca, sa], [-sa, ca]]) + (cx, cy)


def _rounded_rect(x0, y0, x1, y1, r_m: float, n: int = 5) -> np.ndarray:
    r = max(0.0, min(r_m, (x1 - x0) / 2, (y1 - y0) / 2))
    pts = []
    for cx, cy, a0 in ((x1 - r, y0 + r, -90), (x1 - r, y1 - r, 0), (x0 + r, y1 - r, 90),
                       (x0 + r, y0 + r, 180)):
        for a in np.radians(np.linspace(a0, a0 + 90, n)):
            pts.append((cx + r * math.cos(a), cy + r * math.sin(a)))
    return np.array(pts)


def _blob(rng, cx, cy, ax_m, ay_m, n: int = 40) -> np.ndarray:
    """An irregular closed outline (pond, soil heap): an ellipse with low-order radial noise."""
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    k = np.ones(n)
    for h in range(2, 5):
        k += rng.normal(0, 0.12 / (h - 1)) * np.cos(h * a + _uni(rng, 0, 2 * math.pi))
    return np.stack([cx + ax_m * k * np.cos(a), cy + ay_m * k * np.sin(a)], axis=1)


def _smooth_path(pts: np.ndarray, iters: int = 3) -> np.ndarray:
    """Chaikin corner cutting: turns a few waypoints into a gently curving path."""
    for _ in range(iters):
        q = 0.75 * pts[:-1] + 0.25 * pts[1:]
        r = 0.25 * pts[:-1] + 0.75 * pts[1:]
        pts = np.vstack([pts[:1], np.stack([q, r], axis=1).reshape(-1, 2), pts[-1:]])
    return pts


# ----------------------------------------------------------------------------------------------
# Objects


def _lambert(cv: _Canvas, out_xy: tuple[float, float], pitch_rad: float) -> float:
    """Brightness of a roof face relative to a flat roof under the same sun."""
    ca = math.cos(cv.sun_el_rad)
    s = (cv.sun_xy[0] * ca, cv.sun_xy[1] * ca, math.sin(cv.sun_el_rad))
    n = (out_xy[0] * math.sin(pitch_rad), out_xy[1] * math.sin(pitch_rad), math.cos(pitch_rad))
    amb = 0.35
    lit = amb + (1 - amb) * max(0.0, s[0] * n[0] + s[1] * n[1] + s[2] * n[2])
    return float(np.clip(lit / (amb + (1 - amb) * s[2]), 0.5, 1.4))


# A car in its own frame (x forward, y right, units of length/2 and width/2): chamfered body,
# windscreen, rear window and a lighter roof panel. Rotated and placed in one matrix product.
_CAR_SHAPES = np.array([
    (-0.85, -1), (0.85, -1), (1, -0.62), (1, 0.62), (0.85, 1), (-0.85, 1), (-1, 0.62), (-1, -0.62),
    (0.18, -0.82), (0.5, -0.82), (0.5, 0.82), (0.18, 0.82),
    (-0.7, -0.76), (-0.5, -0.76), (-0.5, 0.76), (-0.7, 0.76),
    (-0.42, -0.7), (0.18, -0.7), (0.18, 0.7), (-0.42, 0.7)])
_VAN_SHAPES = np.array([
    (-0.94, -1), (0.94, -1), (1, -0.8), (1, 0.8), (0.94, 1), (-0.94, 1), (-1, 0.8), (-1, -0.8),
    (0.66, -0.85), (0.79, -0.85), (0.79, 0.85), (0.66, 0.85)])
_GLASS = (38, 42, 48)


def _car(cv: _Canvas, rng, cx: float, cy: float, ang_rad: float, rgb: RGB | None = None,
         length_m: float | None = None) -> None:
    """A car (or, when `length_m` > 5.5 m, a van / truck) with windows and a shadow."""
    length = length_m or _uni(rng, 4.1, 4.9)
    van = length > 5.5
    width = 2.2 if van else _uni(rng, 1.72, 1.9)
    rgb = _jit(rng, rgb or _pick(rng, _CAR), 0.04)
    ca, sa = math.cos(ang_rad), math.sin(ang_rad)
    local = (_VAN_SHAPES if van else _CAR_SHAPES) * (length / 2, width / 2)
    px = cv.px(local @ np.array([[ca, sa], [-sa, ca]]) + (cx, cy))
    body = px[:8]
    cv.cast_px(body, 1.5)
    cv2.fillPoly(cv.img, [body], rgb, cv2.LINE_8, _SHIFT)
    cv2.fillPoly(cv.lab, [body], CAR, cv2.LINE_8, _SHIFT)
    cv2.fillPoly(cv.height_u, [body], cv._hu(1.5), cv2.LINE_8, _SHIFT)
    cv2.fillConvexPoly(cv.img, px[8:12], _GLASS, cv2.LINE_8, _SHIFT)
    if not van:
        cv2.fillConvexPoly(cv.img, px[12:16], _GLASS, cv2.LINE_8, _SHIFT)
        cv2.fillConvexPoly(cv.img, px[16:20], _scale(rgb, 1.08), cv2.LINE_8, _SHIFT)


def _person(cv: _Canvas, rng, x: float, y: float) -> None:
    """A person seen from above: ~0.45-0.6 m across, with a long thin shadow."""
    r = _uni(rng, 0.22, 0.3)
    cv.cast_disc((x, y), 0.15, 1.7)
    cv.disc((x, y), r, _jit(rng, _CLOTHES[int(rng.integers(len(_CLOTHES)))], 0.08), PERSON, 1.7)


def _people_in(cv: _Canvas, rng, x0, y0, x1, y1, n: int, allowed: set[int],
               group_max: int = 4) -> None:
    """Scatter `n` people in groups over the rectangle, only where the ground is `allowed`."""
    placed = 0
    tries = 0
    while placed < n and tries < 4 * n + 10:
        tries += 1
        gx, gy = _uni(rng, x0, x1), _uni(rng, y0, y1)
        for _ in range(int(rng.integers(1, group_max + 1))):
            x, y = gx + rng.normal(0, 0.8), gy + rng.normal(0, 0.8)
            if cv.label_at(x, y) in allowed:
                _person(cv, rng, x, y)
                placed += 1


def _tree(cv: _Canvas, rng, x: float, y: float, r_m: float | None = None,
          h_m: float | None = None, rgb: RGB | None = None) -> None:
    r = r_m or _uni(rng, 2.2, 5.0)
    h = h_m or float(np.clip(r * _uni(rng, 1.6, 2.6), 3.0, 22.0))
    cv.trees.append(_Tree(x, y, r, h, _jit(rng, rgb or _TREE[int(rng.integers(len(_TREE)))], 0.07)))


def _draw_tree(cv: _Canvas, rng, t: _Tree) -> None:
    """A clumpy crown: a dark core, lobes lit according to the sun side, a highlight."""
    cv.cast_crown((t.x_m, t.y_m), t.r_m, t.h_m)
    cv.disc((t.x_m, t.y_m), t.r_m * 0.8, _scale(t.rgb, 0.75), TREE, t.h_m)
    n = 3 if t.r_m < 3 else 4
    for _ in range(n):
        a = 2 * math.pi * rng.random()
        d = (0.25 + 0.25 * rng.random()) * t.r_m
        lit = math.cos(a) * cv.sun_xy[0] + math.sin(a) * cv.sun_xy[1]
        cv.disc((t.x_m + d * math.cos(a), t.y_m + d * math.sin(a)),
                (0.45 + 0.15 * rng.random()) * t.r_m,
                _scale(t.rgb, 0.85 + 0.22 * lit), TREE, t.h_m)
    hx, hy = t.x_m + cv.sun_xy[0] * 0.35 * t.r_m, t.y_m + cv.sun_xy[1] * 0.35 * t.r_m
    cv.disc((hx, hy), 0.3 * t.r_m, _scale(t.rgb, 1.25))


def _pitched_roof(cv: _Canvas, rng, x0, y0, x1, y1, h_m: float, rgb: RGB,
                  ridge_along_x: bool | None = None, hip: bool | None = None) -> None:
    """A gable or hip roof on an axis-aligned footprint: faces shaded by the sun, ridge lines."""
    if ridge_along_x is None:
        ridge_along_x = (x1 - x0) >= (y1 - y0)
    if hip is None:
        hip = rng.random() < 0.45
    # Local frame: a along the ridge, b across it.
    if ridge_along_x:
        a0, a1, b0, b1 = x0, x1, y0, y1
        def w(a, b): return (a, b)
    else:
        a0, a1, b0, b1 = y0, y1, x0, x1
        def w(a, b): return (b, a)
    bm, half = (b0 + b1) / 2, (b1 - b0) / 2
    inset = min(half, (a1 - a0) / 2) if hip else 0.0
    pitch = math.radians(_uni(rng, 28, 42))
    foot = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    cv.cast(foot, h_m)
    cv.poly(foot, rgb, ROOF_PITCHED, h_m)
    faces = [([(a0, b0), (a1, b0), (a1 - inset, bm), (a0 + inset, bm)], (0, -1)),
             ([(a0, b1), (a1, b1), (a1 - inset, bm), (a0 + inset, bm)], (0, 1))]
    if hip:
        faces += [([(a0, b0), (a0 + inset, bm), (a0, b1)], (-1, 0)),
                  ([(a1, b0), (a1 - inset, bm), (a1, b1)], (1, 0))]
    lit_faces = []
    for pts, out in faces:
        k = _lambert(cv, w(*out), pitch)
        cv.poly([w(a, b) for a, b in pts], _scale(rgb, k))
        lit_faces.append((k, pts, out))
    dark, light = _scale(rgb, 0.7), _scale(rgb, 1.2)
    cv.band([w(a0 + inset, bm), w(a1 - inset, bm)], 0.3, light)
    if hip:
        for ca, cb, ra in ((a0, b0, a0 + inset), (a0, b1, a0 + inset), (a1, b0, a1 - inset),
                           (a1, b1, a1 - inset)):
            cv.band([w(ca, cb), w(ra, bm)], 0.2, light, under=rgb)
    cv.band(foot, 0.2, dark, closed=True, under=rgb)
    # Roof furniture: solar panels on the sunniest long face, a chimney, skylights.
    k, pts, out = max(lit_faces[:2], key=lambda f: f[0])
    if rng.random() < 0.18 and half > 3 and (a1 - a0 - 2 * inset) > 4:
        bo, bi = (b0 + 0.7, bm - 0.6) if out[1] < 0 else (bm + 0.6, b1 - 0.7)
        ao, ai = a0 + inset + 1.0, a1 - inset - 1.0
        pan = (34, 42, 66)
        cv.poly([w(ao, bo), w(ai, bo), w(ai, bi), w(ao, bi)], pan)
        for a in np.arange(ao + 1.0, ai, 1.0):
            cv.band([w(a, bo), w(a, bi)], 0.05, (120, 130, 150), under=pan)
    if rng.random() < 0.4:
        ca, cb = _uni(rng, a0 + 1, a1 - 1), _uni(rng, b0 + 1, b1 - 1)
        cx, cy = w(ca, cb)
        sq = _obb(cx, cy, 0.8, 0.8, 0.0)
        cv.cast(sq, h_m + 1.0, base_m=h_m - 1.5)
        cv.poly(sq, _jit(rng, (120, 74, 60)), ROOF_PITCHED, h_m + 1.0)
    for _ in range(int(rng.integers(0, 3))):
        ca, cb = _uni(rng, a0 + 1.5, a1 - 1.5), _uni(rng, b0 + 1.2, b1 - 1.2)
        cv.poly(_obb(*w(ca, cb), 1.0, 0.8, 0.0), (60, 66, 78))


def _flat_building(cv: _Canvas, rng, x0, y0, x1, y1, h_m: float, rgb: RGB | None = None,
                   commercial: bool = True) -> None:
    """A flat roof with a parapet, roof sections, plant boxes, vents, skylights or panels."""
    if x1 - x0 < 2 or y1 - y0 < 2:
        return
    rgb = _jit(rng, rgb or _pick(rng, _ROOF_FLAT), 0.05)
    foot = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    cv.cast(foot, h_m)
    cv.poly(foot, rgb, ROOF_FLAT, h_m)
    area = (x1 - x0) * (y1 - y0)
    if rng.random() < 0.35 and min(x1 - x0, y1 - y0) > 10:
        m = _uni(rng, 1.5, 4)
        cv.rect(x0 + m, y0 + m, x1 - m, y1 - m, _jit(rng, rgb, 0.05))
    if commercial and rng.random() < 0.25 and min(x1 - x0, y1 - y0) > 16:
        # Rows of skylights (pale, bluish) across the long side.
        along_x = (x1 - x0) >= (y1 - y0)
        sky = (176, 190, 200)
        for t in np.arange(4.0, ((x1 - x0) if along_x else (y1 - y0)) - 3, _uni(rng, 5, 8)):
            if along_x:
                cv.rect(x0 + t, y0 + 3, x0 + t + 1.2, y1 - 3, sky)
            else:
                cv.rect(x0 + 3, y0 + t, x1 - 3, y0 + t + 1.2, sky)
    elif rng.random() < 0.1 and area > 200:
        # Rows of solar panels over part of the roof.
        pan = (36, 46, 72)
        px1 = x0 + (x1 - x0) * _uni(rng, 0.4, 1.0)
        for yy in np.arange(y0 + 2, y0 + (y1 - y0) * _uni(rng, 0.5, 1.0) - 3, 2.6):
            cv.rect(x0 + 2, yy, px1 - 2, yy + 1.8, pan)
    cv.band(foot, 0.5, _scale(rgb, 1.18), closed=True)
    if area > 250 and rng.random() < 0.6:
        bw, bh = _uni(rng, 3, 7), _uni(rng, 3, 5)
        bx = _uni(rng, x0 + 2, max(x0 + 2.1, x1 - bw - 2))
        by = _uni(rng, y0 + 2, max(y0 + 2.1, y1 - bh - 2))
        box = [(bx, by), (bx + bw, by), (bx + bw, by + bh), (bx, by + bh)]
        cv.cast(box, h_m + 3.0, base_m=h_m)
        cv.poly(box, _scale(rgb, 1.1), ROOF_FLAT, h_m + 3.0)
    n_ac = min(40, int(area / 150 * _uni(rng, 0.2, 1.6)))
    for _ in range(n_ac):
        aw, ah = _uni(rng, 1.0, 3.0), _uni(rng, 1.0, 2.2)
        if x1 - x0 < aw + 2.5 or y1 - y0 < ah + 2.5:
            break
        ax, ay = _uni(rng, x0 + 1.2, x1 - aw - 1.2), _uni(rng, y0 + 1.2, y1 - ah - 1.2)
        box = [(ax, ay), (ax + aw, ay), (ax + aw, ay + ah), (ax, ay + ah)]
        cv.cast(box, h_m + 1.4, base_m=h_m)
        grey = int(_uni(rng, 185, 228))
        cv.poly(box, (grey, grey, grey - 3), ROOF_FLAT, h_m + 1.4)
        if rng.random() < 0.5:
            cv.disc((ax + aw / 2, ay + ah / 2), min(aw, ah) * 0.32, (70, 72, 74))
    for _ in range(int(area / 400 * _uni(rng, 0, 2))):
        cv.disc((_uni(rng, x0 + 1, x1 - 1), _uni(rng, y0 + 1, y1 - 1)), 0.35, (58, 58, 60))


# ----------------------------------------------------------------------------------------------
# Layout


@dataclass
class _Road:
    centre_m: float
    width_m: float
    avenue: bool
    parking_lanes: bool


@dataclass
class _Block:
    x0: float  # outer edge of the sidewalk ring (= kerb line), metres
    y0: float
    x1: float
    y1: float
    sidewalk_m: float
    kind: str = ""
    cells: list[tuple[int, int]] = field(default_factory=list)

    @property
    def inner(self) -> tuple[float, float, float, float]:
        s = self.sidewalk_m
        return self.x0 + s, self.y0 + s, self.x1 - s, self.y1 - s


@dataclass(frozen=True)
class _Frame:
    """Block-local axes: u along the block's long side, v across it from one street front."""

    x0: float
    y0: float
    x1: float
    y1: float
    along_x: bool
    flip_v: bool = False

    @property
    def length(self) -> float:
        return (self.x1 - self.x0) if self.along_x else (self.y1 - self.y0)

    @property
    def depth(self) -> float:
        return (self.y1 - self.y0) if self.along_x else (self.x1 - self.x0)

    def pt(self, u: float, v: float) -> tuple[float, float]:
        if self.flip_v:
            v = self.depth - v
        return (self.x0 + u, self.y0 + v) if self.along_x else (self.x0 + v, self.y0 + u)

    def rect(self, u0, v0, u1, v1) -> tuple[float, float, float, float]:
        (ax, ay), (bx, by) = self.pt(u0, v0), self.pt(u1, v1)
        return min(ax, bx), min(ay, by), max(ax, bx), max(ay, by)

    def v_angle(self) -> float:
        """World angle of the +v direction (away from this frame's street front)."""
        (ax, ay), (bx, by) = self.pt(0, 0), self.pt(0, 1)
        return math.atan2(by - ay, bx - ax)

    def flipped(self) -> "_Frame":
        return _Frame(self.x0, self.y0, self.x1, self.y1, self.along_x, not self.flip_v)


_KIND_WEIGHTS = {"residential": 0.27, "apartments": 0.22, "commercial": 0.21, "park": 0.055,
                 "sports": 0.025, "parking": 0.06, "plaza": 0.045, "water": 0.025,
                 "construction": 0.03}
# Trees scattered at random are dropped where their trunk would stand in these.
_NO_TREES = {WATER, ROOF_FLAT, ROOF_PITCHED, 0}
_REQUIRED_KINDS = ["residential", "apartments", "commercial", "park", "sports", "parking",
                   "plaza", "water", "construction"]


def _road_lines(rng, size_m: float, spacing_m: tuple[float, float]) -> list[_Road]:
    def new_road() -> _Road:
        avenue = rng.random() < 0.2
        parking = (not avenue) and rng.random() < 0.5
        width = _uni(rng, 17, 21) if avenue else 2 * _uni(rng, 3.0, 3.4) + (4.4 if parking else 0)
        return _Road(0.0, width, avenue, parking)

    roads = []
    road = new_road()
    road.centre_m = -_uni(rng, 5, 40)
    while True:
        roads.append(road)
        if road.centre_m > size_m + 5:
            return roads
        nxt = new_road()
        nxt.centre_m = road.centre_m + road.width_m / 2 + _uni(rng, *spacing_m) + nxt.width_m / 2
        road = nxt


@dataclass
class _River:
    pts_m: np.ndarray  # centreline
    width_m: float
    bank_m: float


def _make_river(rng, size_m: float) -> _River | None:
    if size_m < 700 or rng.random() < 0.45:
        return None
    t = np.arange(-60.0, size_m + 60.0, 8.0)
    base = _uni(rng, 0.3, 0.7) * size_m
    off = np.zeros_like(t)
    for amp, lam in ((_uni(rng, 40, 110), _uni(rng, 700, 1600)),
                     (_uni(rng, 10, 30), _uni(rng, 200, 400))):
        off += amp * np.sin(2 * math.pi * t / lam + _uni(rng, 0, 2 * math.pi))
    pts = np.stack([t, base + off], 1) if rng.random() < 0.5 else np.stack([base + off, t], 1)
    return _River(pts, _uni(rng, 24, 42), _uni(rng, 5, 9))


def _layout(rng, size_m: float, river: _River | None
            ) -> tuple[list[_Road], list[_Road], list[_Block], dict[tuple[int, int], int]]:
    """Road grid lines along x and y, the blocks between them, and which block owns each grid
    cell (a merged block owns two, and the street between them is not drawn)."""
    if rng.random() < 0.5:
        sx, sy = (75, 150), (55, 110)
    else:
        sx, sy = (55, 110), (75, 150)
    xr, yr = _road_lines(rng, size_m, sx), _road_lines(rng, size_m, sy)
    nx, ny = len(xr) - 1, len(yr) - 1

    def cell_rect(i0, j0, i1, j1):
        return (xr[i0].centre_m + xr[i0].width_m / 2, yr[j0].centre_m + yr[j0].width_m / 2,
                xr[i1 + 1].centre_m - xr[i1 + 1].width_m / 2,
                yr[j1 + 1].centre_m - yr[j1 + 1].width_m / 2)

    riverside: set[tuple[int, int]] = set()
    if river is not None:
        reach = river.width_m / 2 + river.bank_m + 2
        for i in range(nx):
            for j in range(ny):
                x0, y0, x1, y1 = cell_rect(i, j, i, j)
                dx = np.maximum(np.maximum(x0 - river.pts_m[:, 0], river.pts_m[:, 0] - x1), 0)
                dy = np.maximum(np.maximum(y0 - river.pts_m[:, 1], river.pts_m[:, 1] - y1), 0)
                if np.min(np.hypot(dx, dy)) < reach:
                    riverside.add((i, j))

    owner: dict[tuple[int, int], int] = {}
    blocks: list[_Block] = []

    def add(i0, j0, i1, j1, kind):
        x0, y0, x1, y1 = cell_rect(i0, j0, i1, j1)
        b = _Block(x0, y0, x1, y1, _uni(rng, 2.2, 4.0), kind,
                   [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)])
        for c in b.cells:
            owner[c] = len(blocks)
        blocks.append(b)

    order = [(i, j) for i in range(nx) for j in range(ny)]
    rng.shuffle(order)
    # Big blocks first: two cells merged (the street between them disappears) make room for a
    # running track, a large park or a mall.
    for i, j in order:
        if (i, j) in owner or (i, j) in riverside or rng.random() > 0.05:
            continue
        di, dj = (1, 0) if rng.random() < 0.5 else (0, 1)
        other = (i + di, j + dj)
        if other[0] >= nx or other[1] >= ny or other in owner or other in riverside:
            continue
        kind = str(rng.choice(["sports", "park", "commercial", "apartments", "parking"],
                              p=[0.15, 0.2, 0.3, 0.25, 0.1]))
        add(i, j, other[0], other[1], kind)
    singles = [c for c in order if c not in owner]
    kinds = list(_KIND_WEIGHTS)
    p = np.array([_KIND_WEIGHTS[k] for k in kinds])
    assigned = [str(k) for k in rng.choice(kinds, size=len(singles), p=p / p.sum())]
    # Make sure every kind (hence every class) exists: overwrite the first few draws.
    inner = [n for n, c in enumerate(singles) if c not in riverside]
    if len(inner) >= 2 * len(_REQUIRED_KINDS):
        for n, kind in zip(inner, _REQUIRED_KINDS):
            assigned[n] = kind
    for (i, j), kind in zip(singles, assigned):
        add(i, j, i, j, "riverside" if (i, j) in riverside else kind)
    return xr, yr, blocks, owner


# ----------------------------------------------------------------------------------------------
# Block contents. Each gets the inner rectangle (inside the sidewalk ring) to fill completely.


def _grass(cv: _Canvas, rng, x0, y0, x1, y1, stripes: bool | None = None,
           rgb: RGB | None = None) -> RGB:
    rgb = _jit(rng, rgb or _GRASS[int(rng.integers(len(_GRASS)))], 0.05)
    cv.rect(x0, y0, x1, y1, rgb, GRASS)
    if stripes is None:
        stripes = rng.random() < 0.5
    if stripes:
        # Mowing stripes: alternate bands a few percent brighter.
        w = _uni(rng, 3.5, 7.0)
        light = _scale(rgb, _uni(rng, 1.05, 1.1))
        if rng.random() < 0.5:
            for t in np.arange(x0, x1, 2 * w):
                cv.rect(t, y0, min(t + w, x1), y1, light)
        else:
            for t in np.arange(y0, y1, 2 * w):
                cv.rect(x0, t, x1, min(t + w, y1), light)
    return rgb


def _scatter_trees(cv: _Canvas, rng, x0, y0, x1, y1, n: int, clumps: bool = True) -> None:
    if x1 - x0 < 4 or y1 - y0 < 4:
        return
    while n > 0:
        cx, cy = _uni(rng, x0 + 2, x1 - 2), _uni(rng, y0 + 2, y1 - 2)
        k = int(rng.integers(3, 12)) if clumps else 1
        spread = _uni(rng, 4, 9)
        rgb = _TREE[int(rng.integers(len(_TREE)))]
        for _ in range(min(k, n)):
            x, y = cx + rng.normal(0, spread), cy + rng.normal(0, spread)
            if x0 + 1 < x < x1 - 1 and y0 + 1 < y < y1 - 1:
                _tree(cv, rng, x, y, rgb=rgb)
            n -= 1


def _path(cv: _Canvas, rng, x0, y0, x1, y1, width_m: float, rgb: RGB,
          cls: int = SIDEWALK) -> np.ndarray:
    """A curving footpath between two random points on opposite edges of the rectangle."""
    if rng.random() < 0.5:
        a, b = (x0, _uni(rng, y0, y1)), (x1, _uni(rng, y0, y1))
    else:
        a, b = (_uni(rng, x0, x1), y0), (_uni(rng, x0, x1), y1)
    mid = [(_uni(rng, x0 + 0.2 * (x1 - x0), x1 - 0.2 * (x1 - x0)),
            _uni(rng, y0 + 0.2 * (y1 - y0), y1 - 0.2 * (y1 - y0)))
           for _ in range(rng.integers(1, 3))]
    pts = _smooth_path(np.array([a, *mid, b], float))
    cv.band(pts, width_m, rgb, cls)
    return pts


def _residential(cv: _Canvas, rng, blk: _Block) -> None:
    """Detached houses on lots facing the streets; deep blocks get a middle access lane with
    its own two rows of houses, so gardens stay garden-sized."""
    x0, y0, x1, y1 = blk.inner
    fr = _Frame(x0, y0, x1, y1, along_x=(x1 - x0) >= (y1 - y0))
    _grass(cv, rng, x0, y0, x1, y1, stripes=False)
    halves = [fr]
    if fr.depth > 84:
        lane_w = _uni(rng, 5.0, 6.5)
        mid = fr.depth / 2
        lane = fr.rect(0, mid - lane_w / 2, fr.length, mid + lane_w / 2)
        cv.rect(*lane, _jit(rng, _ASPHALT, 0.04), ROAD)
        halves = [_Frame(*fr.rect(0, 0, fr.length, mid - lane_w / 2), along_x=fr.along_x),
                  _Frame(*fr.rect(0, mid + lane_w / 2, fr.length, fr.depth), along_x=fr.along_x)]
    for half in halves:
        lot_depth = min(half.depth / 2, _uni(rng, 21, 31))
        if half.depth > 2 * lot_depth + 6:
            # A shared inner garden behind both rows of lots.
            gx0, gy0, gx1, gy1 = half.rect(0, lot_depth, half.length, half.depth - lot_depth)
            _scatter_trees(cv, rng, gx0, gy0, gx1, gy1, int((gx1 - gx0) * (gy1 - gy0) / 70))
        for f in (half, half.flipped()):
            u = 0.0
            while u < f.length - 6:
                w = _uni(rng, 11, 18)
                if f.length - (u + w) < 10:
                    w = f.length - u
                _house_lot(cv, rng, f, u, u + w, lot_depth)
                u += w


def _house_lot(cv: _Canvas, rng, f: _Frame, u0: float, u1: float, depth: float) -> None:
    w = u1 - u0
    _grass(cv, rng, *f.rect(u0, 0, u1, depth), stripes=rng.random() < 0.3)
    hedge = (44, 72, 40)
    if rng.random() < 0.7:
        cv.band([f.pt(u0 + 0.4, 0.5), f.pt(u0 + 0.4, depth - 0.3)], _uni(rng, 0.8, 1.6), hedge,
                TREE, 1.6)
    if rng.random() < 0.25:
        cv.band([f.pt(u0 + 0.5, 0.4), f.pt(u1 - 0.5, 0.4)], 0.8, hedge, TREE, 1.4)
    setback = _uni(rng, 3, 6.5)
    hl = min(w - 3.0, _uni(rng, 10, 17))
    hd = min(depth - setback - 4.5, _uni(rng, 9, 14))
    if hl < 5 or hd < 5:
        _scatter_trees(cv, rng, *f.rect(u0, 0, u1, depth), 2, clumps=False)
        return
    left = _uni(rng, 1.0, w - hl - 1.0)
    hu0, hu1, hv0, hv1 = u0 + left, u0 + left + hl, setback, setback + hd
    pave = _jit(rng, (176, 170, 160), 0.05)
    ang = f.v_angle()
    # Driveway to the street on whichever side of the house has room, sometimes with a car.
    for (da, db) in ((u0 + 0.6, hu0 - 0.3), (hu1 + 0.3, u1 - 0.6)):
        if db - da >= 3.0:
            dw = min(3.2, db - da)
            dx0 = db - dw if da < hu0 else da
            cv.rect(*f.rect(dx0, 0, dx0 + dw, hv0 + hd * 0.7), pave, SIDEWALK)
            if rng.random() < 0.5:
                cx, cy = f.pt(dx0 + dw / 2, _uni(rng, 3.0, max(3.1, hv0 + hd * 0.7 - 2.6)))
                flip = math.pi if rng.random() < 0.5 else 0.0
                _car(cv, rng, cx, cy, ang + flip + rng.normal(0, 0.03))
            break
    back = depth - hv1
    if rng.random() < 0.5 and back > 4:
        cv.rect(*f.rect(hu0 + 0.5, hv1, hu1 - 0.5, hv1 + min(3.5, back - 1)), pave, PLAZA)
    if rng.random() < 0.18 and back > 11 and w > 10:
        pl, pw = _uni(rng, 6, 10), _uni(rng, 3.2, 4.5)
        pu = _uni(rng, u0 + 1.5, max(u0 + 1.6, u1 - pl - 1.5))
        pv = _uni(rng, hv1 + 4, depth - pw - 2)
        cv.rect(*f.rect(pu - 1, pv - 1, pu + pl + 1, pv + pw + 1), _jit(rng, (200, 196, 186)),
                SIDEWALK)
        cv.rect(*f.rect(pu, pv, pu + pl, pv + pw), _jit(rng, _WATER_POOL, 0.04), WATER)
    if rng.random() < 0.3 and back > 6:
        su = u0 + 1 if rng.random() < 0.5 else u1 - 4
        sx0, sy0, sx1, sy1 = f.rect(su, depth - 4, su + 3, depth - 1)
        _flat_building(cv, rng, sx0, sy0, sx1, sy1, 2.5, commercial=False)
    hx0, hy0, hx1, hy1 = f.rect(hu0, hv0, hu1, hv1)
    rgb = _jit(rng, _pick(rng, _ROOF_PITCHED), 0.06)
    h = _uni(rng, 6.5, 10)
    if rng.random() < 0.25 and back > 8:
        # L-shaped house: a wing towards the back garden, ridge perpendicular to the main one.
        wu = hu0 if rng.random() < 0.5 else hu1 - min(6.0, hl / 2)
        wx0, wy0, wx1, wy1 = f.rect(wu, hv1 - 1, wu + min(6.0, hl / 2), hv1 + min(7.0, back - 2))
        _pitched_roof(cv, rng, wx0, wy0, wx1, wy1, h - 0.8, rgb,
                      ridge_along_x=(wx1 - wx0) < (wy1 - wy0))
    _pitched_roof(cv, rng, hx0, hy0, hx1, hy1, h, rgb)
    for _ in range(int(rng.integers(1, 6))):
        tu, tv = _uni(rng, u0 + 2, u1 - 2), _uni(rng, hv1 + 2.5, max(hv1 + 2.6, depth - 2))
        _tree(cv, rng, *f.pt(tu, tv), r_m=_uni(rng, 2.6, 5.5))
    if rng.random() < 0.5:
        _tree(cv, rng, *f.pt(_uni(rng, u0 + 2, u1 - 2), _uni(rng, 1.5, max(1.6, setback - 1))),
              r_m=_uni(rng, 1.8, 3.2))
    if rng.random() < 0.12 and back > 5:
        _person(cv, rng, *f.pt(_uni(rng, u0 + 1, u1 - 1), _uni(rng, hv1 + 2, depth - 1)))


def _apartments(cv: _Canvas, rng, blk: _Block) -> None:
    """A perimeter block: flat-roofed wings around a green courtyard (European style)."""
    x0, y0, x1, y1 = blk.inner
    d = _uni(rng, 12, 18)
    if min(x1 - x0, y1 - y0) < 2 * d + 12:
        _plaza_ground(cv, rng, x0, y0, x1, y1)
        _flat_building(cv, rng, x0 + 3, y0 + 3, x1 - 3, y1 - 3, _uni(rng, 10, 25))
        return
    cx0, cy0, cx1, cy1 = x0 + d, y0 + d, x1 - d, y1 - d
    _grass(cv, rng, x0, y0, x1, y1)
    pave = _jit(rng, (170, 166, 158))
    cv.band([(cx0 + 3, cy0 + 3), (cx1 - 3, cy0 + 3), (cx1 - 3, cy1 - 3), (cx0 + 3, cy1 - 3)],
            2.0, pave, SIDEWALK, closed=True)
    if rng.random() < 0.6:
        sx, sy = _uni(rng, cx0 + 5, cx1 - 12), _uni(rng, cy0 + 5, cy1 - 12)
        cv.rect(sx, sy, sx + _uni(rng, 6, 10), sy + _uni(rng, 6, 10), _jit(rng, (196, 178, 140)),
                BARE_SOIL)
    if max(cx1 - cx0, cy1 - cy0) > 50:
        # Large courtyards are split by a cross wing (with a passage through it).
        h, rgb = _uni(rng, 10, 20), _pick(rng, _ROOF_FLAT)
        if cx1 - cx0 > cy1 - cy0:
            m = (cx0 + cx1) / 2 + _uni(rng, -8, 8)
            _flat_building(cv, rng, m - d / 2, cy0, m + d / 2, (cy0 + cy1) / 2 - 2.5, h, rgb,
                           commercial=False)
            _flat_building(cv, rng, m - d / 2, (cy0 + cy1) / 2 + 2.5, m + d / 2, cy1, h, rgb,
                           commercial=False)
        else:
            m = (cy0 + cy1) / 2 + _uni(rng, -8, 8)
            _flat_building(cv, rng, cx0, m - d / 2, (cx0 + cx1) / 2 - 2.5, m + d / 2, h, rgb,
                           commercial=False)
            _flat_building(cv, rng, (cx0 + cx1) / 2 + 2.5, m - d / 2, cx1, m + d / 2, h, rgb,
                           commercial=False)
    _scatter_trees(cv, rng, cx0 + 3, cy0 + 3, cx1 - 3, cy1 - 3,
                   int((cx1 - cx0) * (cy1 - cy0) / _uni(rng, 60, 160)))
    _people_in(cv, rng, cx0, cy0, cx1, cy1, int(rng.integers(0, 8)), {GRASS, SIDEWALK, BARE_SOIL})
    wings = [(x0, y0, x1, cy0), (x0, cy1, x1, y1), (x0, cy0, cx0, cy1), (cx1, cy0, x1, cy1)]
    gap_wing = int(rng.integers(0, 4)) if rng.random() < 0.5 else -1
    base_rgb = _pick(rng, _ROOF_FLAT)
    for n, (a0, b0, a1, b1) in enumerate(wings):
        along_x = (a1 - a0) >= (b1 - b0)
        length = (a1 - a0) if along_x else (b1 - b0)
        cuts = np.sort(_uni(rng, 0, length, int(rng.integers(0, 3))))
        edges = [0.0, *cuts, length]
        for k in range(len(edges) - 1):
            s, e = edges[k], edges[k + 1]
            if n == gap_wing and k == 0 and e - s > 12:
                # A gateway through the block, paved.
                g = (s + e) / 2
                if along_x:
                    cv.rect(a0 + g - 2.5, b0, a0 + g + 2.5, b1, pave, SIDEWALK)
                    _flat_building(cv, rng, a0 + s, b0, a0 + g - 2.5, b1, _uni(rng, 12, 22),
                                   _jit(rng, base_rgb, 0.04))
                    s = g + 2.5
                else:
                    cv.rect(a0, b0 + g - 2.5, a1, b0 + g + 2.5, pave, SIDEWALK)
                    _flat_building(cv, rng, a0, b0 + s, a1, b0 + g - 2.5, _uni(rng, 12, 22),
                                   _jit(rng, base_rgb, 0.04))
                    s = g + 2.5
            if e - s < 2:
                continue
            h = _uni(rng, 12, 24)
            rgb = _jit(rng, base_rgb, 0.05)
            if along_x:
                _flat_building(cv, rng, a0 + s, b0, a0 + e, b1, h, rgb, commercial=False)
            else:
                _flat_building(cv, rng, a0, b0 + s, a1, b0 + e, h, rgb, commercial=False)


def _plaza_ground(cv: _Canvas, rng, x0, y0, x1, y1) -> RGB:
    """Paving: a base colour with a grid of joints every few metres and some slab variation."""
    paving = [(186, 176, 160), (170, 168, 164), (196, 186, 170), (160, 150, 140)]
    rgb = _jit(rng, paving[int(rng.integers(len(paving)))], 0.04)
    cv.rect(x0, y0, x1, y1, rgb, PLAZA)
    step = _uni(rng, 3, 8)
    joint = _scale(rgb, 0.88)
    alt = _scale(rgb, _uni(rng, 0.92, 1.06))
    if rng.random() < 0.5:
        # Chequer of alternately toned large slabs.
        for i, xx in enumerate(np.arange(x0, x1, step)):
            for yy in np.arange(y0 + (i % 2) * step, y1, 2 * step):
                cv.rect(xx, yy, min(xx + step, x1), min(yy + step, y1), alt)
    for xx in np.arange(x0 + step, x1, step):
        cv.band([(xx, y0), (xx, y1)], 0.1, joint, under=rgb)
    for yy in np.arange(y0 + step, y1, step):
        cv.band([(x0, yy), (x1, yy)], 0.1, joint, under=rgb)
    return rgb


def _plaza(cv: _Canvas, rng, blk: _Block) -> None:
    x0, y0, x1, y1 = blk.inner
    rgb = _plaza_ground(cv, rng, x0, y0, x1, y1)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    span = min(x1 - x0, y1 - y0)
    if rng.random() < 0.55 and span > 30:
        r = _uni(rng, 4, min(10, span / 5))
        cv.disc((cx, cy), r + 1.2, _scale(rgb, 1.08), PLAZA)
        cv.disc((cx, cy), r, _jit(rng, (70, 110, 120), 0.05), WATER)
    elif rng.random() < 0.5 and span > 30:
        cv.disc((cx, cy), _uni(rng, 6, span / 4), _jit(rng, _GRASS[0], 0.05), GRASS)
    # Tree rows in planters along the long edges, a kiosk, many people.
    step = _uni(rng, 7, 11)
    along_x = (x1 - x0) >= (y1 - y0)
    for t in np.arange(x0 + 4 if along_x else y0 + 4, (x1 if along_x else y1) - 3, step):
        for off in (4.0, (y1 - y0 if along_x else x1 - x0) - 4.0):
            if rng.random() < 0.8:
                px, py = (t, y0 + off) if along_x else (x0 + off, t)
                cv.disc((px, py), 1.0, (90, 80, 66), BARE_SOIL)
                _tree(cv, rng, px, py, r_m=_uni(rng, 2.5, 4.0))
    if rng.random() < 0.5 and span > 25:
        kx, ky = _uni(rng, x0 + 8, x1 - 14), _uni(rng, y0 + 8, y1 - 12)
        _flat_building(cv, rng, kx, ky, kx + _uni(rng, 4, 8), ky + _uni(rng, 3, 5), 3.5,
                       commercial=False)
    area = (x1 - x0) * (y1 - y0)
    _people_in(cv, rng, x0, y0, x1, y1, int(area / _uni(rng, 60, 160)), {PLAZA}, group_max=5)


def _commercial(cv: _Canvas, rng, blk: _Block) -> None:
    x0, y0, x1, y1 = blk.inner
    along_x = (x1 - x0) >= (y1 - y0)
    length = (x1 - x0) if along_x else (y1 - y0)
    parts = [0.0, length] if length < 60 else [0.0, _uni(rng, 0.3, 0.7) * length, length]
    for a, b in zip(parts[:-1], parts[1:]):
        rx0, ry0, rx1, ry1 = (x0 + a, y0, x0 + b, y1) if along_x else (x0, y0 + a, x1, y0 + b)
        if rng.random() < 0.3 and len(parts) > 2:
            _parking_lot(cv, rng, rx0, ry0, rx1, ry1)
            continue
        if rng.random() < 0.5:
            _plaza_ground(cv, rng, rx0, ry0, rx1, ry1)
            ground = {PLAZA}
        else:
            cv.rect(rx0, ry0, rx1, ry1, _jit(rng, _LOT_ASPHALT), PARKING_LOT)
            ground = {PARKING_LOT}
        m = [_uni(rng, 2, 7) for _ in range(4)]
        _flat_building(cv, rng, rx0 + m[0], ry0 + m[1], rx1 - m[2], ry1 - m[3], _uni(rng, 6, 32))
        # Cars parked along the apron, people on the paving.
        if ground == {PARKING_LOT}:
            for _ in range(int(rng.integers(0, 8))):
                cx, cy = _uni(rng, rx0 + 3, rx1 - 3), _uni(rng, ry0 + 3, ry1 - 3)
                if cv.label_at(cx, cy) == PARKING_LOT:
                    _car(cv, rng, cx, cy, rng.choice([0, math.pi / 2]) + rng.normal(0, 0.05))
        _people_in(cv, rng, rx0, ry0, rx1, ry1, int(rng.integers(0, 10)), ground)


def _parking_lot(cv: _Canvas, rng, x0, y0, x1, y1) -> None:
    """Painted double rows of perpendicular bays with aisles, cars in most bays, tree islands."""
    rgb = _jit(rng, _LOT_ASPHALT, 0.05)
    cv.rect(x0, y0, x1, y1, rgb, PARKING_LOT)
    fr = _Frame(x0, y0, x1, y1, along_x=(x1 - x0) >= (y1 - y0))
    bay_w, bay_d, aisle = _uni(rng, 2.4, 2.7), 5.0, _uni(rng, 6.0, 7.0)
    island = _uni(rng, 2.0, 3.0) if rng.random() < 0.5 else 0.0
    occupancy = _uni(rng, 0.5, 0.97)
    v = 1.5
    paint = _mix(rgb, _PAINT, 0.85)
    ang_v = fr.v_angle()
    while v + 2 * bay_d + aisle <= fr.depth - 1.0:
        rows = [(v, 1.0), (v + bay_d + aisle, -1.0)]
        for rv, facing in rows:
            us = np.arange(1.5, fr.length - 1.5 - bay_w, bay_w)
            for u in us:
                cv.band([fr.pt(u, rv), fr.pt(u, rv + bay_d)], 0.12, paint, under=rgb)
                if rng.random() < occupancy:
                    cx, cy = fr.pt(u + bay_w / 2 + rng.normal(0, 0.1),
                                   rv + bay_d / 2 + rng.normal(0, 0.15))
                    _car(cv, rng, cx, cy,
                         ang_v + (0 if rng.random() < 0.7 else math.pi) + rng.normal(0, 0.04))
            if len(us):
                cv.band([fr.pt(us[-1] + bay_w, rv), fr.pt(us[-1] + bay_w, rv + bay_d)], 0.12,
                        paint, under=rgb)
        v += 2 * bay_d + aisle
        if island and v + island + 2 * bay_d + aisle <= fr.depth - 1.0:
            ix0, iy0, ix1, iy1 = fr.rect(1.5, v, fr.length - 1.5, v + island)
            _grass(cv, rng, ix0, iy0, ix1, iy1, stripes=False)
            for t in np.arange(5.0, fr.length - 4, _uni(rng, 9, 14)):
                _tree(cv, rng, *fr.pt(t, v + island / 2), r_m=_uni(rng, 2.5, 4.0))
            v += island
        else:
            v += 0.6
    _people_in(cv, rng, x0, y0, x1, y1, int(rng.integers(0, 5)), {PARKING_LOT}, group_max=2)


def _parking(cv: _Canvas, rng, blk: _Block) -> None:
    x0, y0, x1, y1 = blk.inner
    if rng.random() < 0.6:
        # Planted border around the lot.
        _grass(cv, rng, x0, y0, x1, y1, stripes=False)
        m = _uni(rng, 2.5, 4.0)
        for t in np.arange(x0 + 3, x1 - 2, _uni(rng, 8, 12)):
            for yy in (y0 + m / 2, y1 - m / 2):
                _tree(cv, rng, t, yy, r_m=_uni(rng, 2.2, 3.8))
        _parking_lot(cv, rng, x0 + m, y0 + m, x1 - m, y1 - m)
    else:
        _parking_lot(cv, rng, x0, y0, x1, y1)


def _park(cv: _Canvas, rng, blk: _Block, riverside: bool = False) -> None:
    x0, y0, x1, y1 = blk.inner
    _grass(cv, rng, x0, y0, x1, y1, stripes=rng.random() < 0.4)
    area = (x1 - x0) * (y1 - y0)
    gravel = _jit(rng, [(196, 186, 164), (150, 148, 144), (178, 164, 140)][int(rng.integers(3))],
                  0.04)
    if not riverside and area > 5000 and rng.random() < 0.3:
        cx = _uni(rng, x0 + 0.35 * (x1 - x0), x1 - 0.35 * (x1 - x0))
        cy = _uni(rng, y0 + 0.35 * (y1 - y0), y1 - 0.35 * (y1 - y0))
        ax, ay = 0.18 * (x1 - x0), 0.18 * (y1 - y0)
        cv.poly(_blob(rng, cx, cy, ax + 2, ay + 2), _jit(rng, (120, 112, 90)), BARE_SOIL)
        cv.poly(_blob(rng, cx, cy, ax, ay), _jit(rng, _WATER_POND, 0.06), WATER)
    for _ in range(int(rng.integers(1, 4))):
        _path(cv, rng, x0, y0, x1, y1, _uni(rng, 2.5, 4.5), gravel)
    if rng.random() < 0.35:
        px, py = _uni(rng, x0 + 5, x1 - 15), _uni(rng, y0 + 5, y1 - 15)
        cv.poly(_blob(rng, px + 5, py + 5, 5, 4, 16), _jit(rng, (198, 180, 142)), BARE_SOIL)
    density = _uni(rng, 50, 130)
    _scatter_trees(cv, rng, x0, y0, x1, y1, int(area / density))
    _people_in(cv, rng, x0, y0, x1, y1, int(area / _uni(rng, 300, 1200)),
               {GRASS, SIDEWALK, BARE_SOIL})


def _water(cv: _Canvas, rng, blk: _Block) -> None:
    """A lake block: an irregular pond with a soil bank, a path around, trees on the shore."""
    x0, y0, x1, y1 = blk.inner
    _grass(cv, rng, x0, y0, x1, y1, stripes=False)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    ax, ay = _uni(rng, 0.3, 0.4) * (x1 - x0), _uni(rng, 0.3, 0.4) * (y1 - y0)
    # One shape at three sizes (path, bank, water): the same seed for each outline.
    shape_seed = int(rng.integers(2**31))

    def outline(grow_m: float) -> np.ndarray:
        return _blob(np.random.default_rng(shape_seed), cx, cy, ax + grow_m, ay + grow_m)

    cv.band(outline(6.0), 3.0, _jit(rng, (184, 172, 150)), SIDEWALK, closed=True)
    cv.poly(outline(1.5), _jit(rng, (116, 106, 84)), BARE_SOIL)
    cv.poly(outline(0.0), _jit(rng, _WATER_POND, 0.08), WATER)
    for t in np.linspace(0, 2 * math.pi, int(rng.integers(6, 16)), endpoint=False):
        k = _uni(rng, 1.25, 1.45)
        x, y = cx + (ax + 6) * k * math.cos(t), cy + (ay + 6) * k * math.sin(t)
        if x0 + 2 < x < x1 - 2 and y0 + 2 < y < y1 - 2:
            _tree(cv, rng, x, y)
    _people_in(cv, rng, x0, y0, x1, y1, int(rng.integers(2, 12)), {SIDEWALK, GRASS})


def _pitch(cv: _Canvas, rng, cx: float, cy: float, length: float, width: float,
           along_x: bool) -> None:
    """A football pitch with mowing stripes and its line markings."""
    def w(a, b):
        return (cx + a, cy + b) if along_x else (cx + b, cy + a)

    hl, hw = length / 2, width / 2
    green = _jit(rng, (72, 132, 62), 0.04)
    cv.poly([w(-hl - 3, -hw - 3), w(hl + 3, -hw - 3), w(hl + 3, hw + 3), w(-hl - 3, hw + 3)],
            green, SPORTS_FIELD)
    n = 12
    for k in range(0, n, 2):
        a = -hl + k * length / n
        b = a + length / n
        cv.poly([w(a, -hw), w(b, -hw), w(b, hw), w(a, hw)], _scale(green, 1.1))
    s = length / 105.0
    lw, paint = 0.12, (236, 238, 232)

    def line(pts, closed=False):
        cv.band([w(a, b) for a, b in pts], lw, paint, closed=closed, under=green)

    line([(-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw)], closed=True)
    line([(0, -hw), (0, hw)])
    cv.band(_circle_pts(w(0, 0), 9.15 * s, 40), lw, paint, closed=True, under=green)
    for sgn in (-1, 1):
        e = sgn * hl
        for depth, half in ((16.5 * s, 20.15 * s), (5.5 * s, 9.16 * s)):
            line([(e, -half), (e - sgn * depth, -half), (e - sgn * depth, half), (e, half)])
        cv.disc(w(e - sgn * 11 * s, 0), 0.2, paint)
        # Goals: a small white frame just behind the line.
        gx0, gx1 = sorted((e, e + sgn * 1.5))
        line([(gx0, -3.66 * s), (gx1, -3.66 * s), (gx1, 3.66 * s), (gx0, 3.66 * s)], closed=True)


def _stadium_pts(cx, cy, straight, radius, along_x, n=24) -> np.ndarray:
    pts = []
    for sgn in (1, -1):
        for t in np.linspace(-math.pi / 2, math.pi / 2, n):
            a = sgn * (straight / 2 + radius * math.cos(t))
            b = sgn * radius * math.sin(t)
            pts.append((cx + a, cy + b) if along_x else (cx + b, cy + a))
    return np.array(pts)


def _sports(cv: _Canvas, rng, blk: _Block) -> None:
    x0, y0, x1, y1 = blk.inner
    _grass(cv, rng, x0, y0, x1, y1, stripes=False)
    along_x = (x1 - x0) >= (y1 - y0)
    L, D = ((x1 - x0), (y1 - y0)) if along_x else ((y1 - y0), (x1 - x0))
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    s_track = min((L - 8) / 176.0, (D - 8) / 92.0, 1.0)
    players = rng.random() < 0.4
    if s_track >= 0.65:
        # 400 m track (scaled to fit): red-brown stadium, six lanes, a pitch inside.
        s = s_track
        straight, r_in, lanes = 84.39 * s, 36.5 * s, 6
        lane_w = 1.22
        track = (172, 82, 62)
        cv.poly(_stadium_pts(cx, cy, straight, r_in + lanes * lane_w, along_x),
                _jit(rng, track, 0.05), SPORTS_FIELD)
        for k in range(lanes + 1):
            cv.band(_stadium_pts(cx, cy, straight, r_in + k * lane_w, along_x), 0.06,
                    (235, 232, 228), closed=True, under=track)
        cv.poly(_stadium_pts(cx, cy, straight, r_in - 0.2, along_x),
                _jit(rng, (80, 128, 60), 0.04), SPORTS_FIELD)
        _pitch(cv, rng, cx, cy, min(100 * s, straight + 2 * r_in - 6), min(64 * s, 2 * r_in - 6),
               along_x)
        pl, pw = 100 * s, 64 * s
        # A grandstand along one straight, where the block leaves room for it.
        room = (D - 2 * (r_in + lanes * lane_w)) / 2 - 3
        if room > 6:
            depth = min(room, _uni(rng, 8, 14))
            b0 = r_in + lanes * lane_w + 2
            a0, a1 = -straight / 2, straight / 2
            sgn = 1 if rng.random() < 0.5 else -1
            bb0, bb1 = sorted((sgn * b0, sgn * (b0 + depth)))
            if along_x:
                gx0, gy0, gx1, gy1 = cx + a0, cy + bb0, cx + a1, cy + bb1
            else:
                gx0, gy0, gx1, gy1 = cx + bb0, cy + a0, cx + bb1, cy + a1
            _flat_building(cv, rng, gx0, gy0, gx1, gy1, _uni(rng, 8, 14), commercial=False)
    else:
        pl = min(105.0, L - 12)
        pw = min(68.0, D - 10, pl * 0.65)
        if pl >= 40 and pw >= 25:
            _pitch(cv, rng, cx, cy, pl, pw, along_x)
        else:
            pl = pw = 0.0
        # Tennis courts in the remaining strip (or in place of the pitch).
        court = [(70, 110, 150), (86, 130, 84), (188, 104, 66)][int(rng.integers(3))]
        tx = x0 + 3
        ty = y0 + 3 if pl == 0 else None
        if ty is not None:
            while tx + 18 <= x1 - 3:
                cw, chh = 18.0, 36.0
                if ty + chh > y1 - 3:
                    break
                cv.rect(tx, ty, tx + cw, ty + chh, _jit(rng, court, 0.04), SPORTS_FIELD)
                cv.band([(tx + 3.5, ty + 6.1), (tx + 14.5, ty + 6.1), (tx + 14.5, ty + 29.9),
                         (tx + 3.5, ty + 29.9)], 0.08, (235, 235, 235), closed=True, under=court)
                cv.band([(tx + 2, ty + 18), (tx + 16, ty + 18)], 0.1, (40, 40, 40))
                tx += cw + 1
    if players and pl > 0:
        for _ in range(int(rng.integers(8, 23))):
            a, b = _uni(rng, -pl / 2, pl / 2), _uni(rng, -pw / 2, pw / 2)
            _person(cv, rng, *((cx + a, cy + b) if along_x else (cx + b, cy + a)))
    # Trees on the margins, a clubhouse in a corner.
    step = _uni(rng, 6, 10)
    for t in np.arange(x0 + 3, x1 - 3, step):
        for yy in (y0 + 3, y1 - 3):
            if rng.random() < 0.85 and cv.label_at(t, yy) == GRASS:
                _tree(cv, rng, t, yy)
    for t in np.arange(y0 + 3, y1 - 3, step):
        for xx in (x0 + 3, x1 - 3):
            if rng.random() < 0.85 and cv.label_at(xx, t) == GRASS:
                _tree(cv, rng, xx, t)
    if rng.random() < 0.5:
        _flat_building(cv, rng, x1 - 16, y1 - 12, x1 - 3, y1 - 4, 4.0, commercial=False)


def _construction(cv: _Canvas, rng, blk: _Block) -> None:
    x0, y0, x1, y1 = blk.inner
    soil = _jit(rng, [_SOIL, (170, 146, 110), (128, 104, 82)][int(rng.integers(3))], 0.04)
    cv.rect(x0, y0, x1, y1, soil, BARE_SOIL)
    # Tyre tracks (darker arcs), heaps, an excavation, site cabins, yellow machines, a slab.
    for _ in range(int(rng.integers(4, 10))):
        pts = _smooth_path(np.array([(_uni(rng, x0, x1), _uni(rng, y0, y1)) for _ in range(3)]))
        cv.band(pts, 2.2, _scale(soil, 0.86))
        cv.band(pts, 0.6, _scale(soil, 1.08))
    for _ in range(int(rng.integers(1, 5))):
        hx, hy = _uni(rng, x0 + 8, x1 - 8), _uni(rng, y0 + 8, y1 - 8)
        r = _uni(rng, 3, 7)
        cv.poly(_blob(rng, hx, hy, r, r * 0.8, 20), _scale(soil, _uni(rng, 0.8, 1.15)), BARE_SOIL)
        cv.poly(_blob(rng, hx + cv.sun_xy[0] * r * 0.3, hy + cv.sun_xy[1] * r * 0.3, r * 0.5,
                      r * 0.4, 16),
                _scale(soil, 1.12))
    if rng.random() < 0.5 and min(x1 - x0, y1 - y0) > 40:
        ex0, ey0 = x0 + _uni(rng, 8, 15), y0 + _uni(rng, 8, 15)
        ex1, ey1 = x1 - _uni(rng, 8, 15), y1 - _uni(rng, 8, 15)
        cv.rect(ex0, ey0, ex1, ey1, _scale(soil, 0.75), BARE_SOIL)
        if rng.random() < 0.6:
            # A concrete base slab already poured in the pit: counted as a (flat) roof.
            _flat_building(cv, rng, ex0 + 4, ey0 + 4, ex1 - 4, ey1 - 4, 1.0, (150, 150, 146),
                           commercial=False)
    for k in range(int(rng.integers(1, 4))):
        cx0, cy0 = x0 + 2 + k * 3.2, y0 + 2
        _flat_building(cv, rng, cx0, cy0, cx0 + 2.8, cy0 + 6, 2.6, _jit(rng, (214, 214, 208)),
                       commercial=False)
    for _ in range(int(rng.integers(1, 4))):
        _car(cv, rng, _uni(rng, x0 + 6, x1 - 6), _uni(rng, y0 + 6, y1 - 6), _uni(rng, 0, math.pi),
             rgb=(222, 170, 30), length_m=_uni(rng, 6, 8))
    _people_in(cv, rng, x0, y0, x1, y1, int(rng.integers(1, 8)), {BARE_SOIL})


_BLOCK_RENDERERS = {"residential": _residential, "apartments": _apartments,
                    "commercial": _commercial, "parking": _parking, "plaza": _plaza,
                    "sports": _sports, "water": _water, "construction": _construction,
                    "park": _park,
                    "riverside": lambda cv, rng, b: _park(cv, rng, b, riverside=True)}


# ----------------------------------------------------------------------------------------------
# Streets: sidewalks are drawn with each block, the carriageway is the background; markings,
# crossings, kerbside parking, traffic and street trees are drawn per road segment.


def _sidewalk(cv: _Canvas, rng, blk: _Block) -> None:
    ring = _rounded_rect(blk.x0, blk.y0, blk.x1, blk.y1, _uni(rng, 2, 6))
    rgb = _jit(rng, _SIDEWALK, 0.05)
    cv.poly(ring, rgb, SIDEWALK)
    # Kerb stone: a light line at the road edge.
    cv.band(ring, 0.2, _scale(rgb, 1.15), closed=True, under=rgb)


def _segment(cv: _Canvas, rng, road: _Road, a0: float, a1: float, vertical: bool) -> None:
    """Markings and traffic of one road between two junctions; a runs along the road."""
    c, w = road.centre_m, road.width_m

    def p(a, b):  # b across the road, from its centre
        return (c + b, a) if vertical else (a, c + b)

    base = _ASPHALT
    paint = _PAINT
    length = a1 - a0
    if length < 8:
        return
    dash, gap = 3.0, 6.0
    if road.avenue:
        med = _uni(rng, 2.5, 4.0)
        mx0, my0 = p(a0 + 5, -med / 2)
        mx1, my1 = p(a1 - 5, med / 2)
        _grass(cv, rng, min(mx0, mx1), min(my0, my1), max(mx0, mx1), max(my0, my1), stripes=False)
        cv.band([p(a0 + 5, -med / 2), p(a1 - 5, -med / 2), p(a1 - 5, med / 2), p(a0 + 5, med / 2)],
                0.25, (190, 188, 182), closed=True)
        if rng.random() < 0.7:
            for t in np.arange(a0 + 9, a1 - 6, _uni(rng, 8, 12)):
                _tree(cv, rng, *p(t, 0), r_m=_uni(rng, 2.5, 4.0))
        lane = (w - med) / 4
        for sgn in (-1, 1):
            b = sgn * (med / 2 + lane)
            for t in np.arange(a0 + 5, a1 - 5 - dash, dash + gap):
                cv.band([p(t, b), p(t + dash, b)], 0.15, paint, under=base)
            cv.band([p(a0 + 5, sgn * (med / 2 + 0.4)), p(a1 - 5, sgn * (med / 2 + 0.4))], 0.15,
                    paint, under=base)
        lanes_b = [sgn * (med / 2 + lane * (k + 0.5)) for sgn in (-1, 1) for k in (0, 1)]
    else:
        for t in np.arange(a0 + 5, a1 - 5 - dash, dash + gap):
            cv.band([p(t, 0), p(t + dash, 0)], 0.15, paint, under=base)
        lane = (w - (4.4 if road.parking_lanes else 0)) / 2
        lanes_b = [-lane / 2, lane / 2]
        if road.parking_lanes:
            occupancy = _uni(rng, 0.3, 0.9)
            for sgn in (-1, 1):
                b = sgn * (w / 2 - 1.1)
                for t in np.arange(a0 + 6, a1 - 8, _uni(rng, 5.8, 6.6)):
                    if rng.random() < occupancy:
                        ang = (math.pi / 2 if vertical else 0.0) + (math.pi if sgn < 0 else 0)
                        ang += rng.normal(0, 0.02)
                        _car(cv, rng, *p(t + 2.5, b + rng.normal(0, 0.1)), ang)
    # Zebra crossings at the junction ends, stripes parallel to the road.
    for end, sgn in ((a0, 1), (a1, -1)):
        if rng.random() < 0.55:
            for b in np.arange(-w / 2 + 0.6, w / 2 - 0.6, 1.0):
                cv.poly([p(end + sgn * 1.0, b), p(end + sgn * 4.0, b), p(end + sgn * 4.0, b + 0.5),
                         p(end + sgn * 1.0, b + 0.5)], paint)
    # Moving traffic: right-hand driving, heading set by the lane side.
    for b in lanes_b:
        for t in np.arange(a0 + 10, a1 - 10, _uni(rng, 25, 90)):
            if rng.random() < 0.35:
                # +a is +y on a vertical road (its right-hand side is -x) and +x on a
                # horizontal one (right-hand side +y).
                forward = (b < 0) if vertical else (b > 0)
                ang = (math.pi / 2 if vertical else 0.0) + (0.0 if forward else math.pi)
                truck = rng.random() < 0.08
                _car(cv, rng, *p(t, b + rng.normal(0, 0.15)), ang + rng.normal(0, 0.01),
                     rgb=(236, 236, 232) if truck else None,
                     length_m=_uni(rng, 6.5, 9) if truck else None)


def _street_life(cv: _Canvas, rng, blk: _Block) -> None:
    """Street trees and pedestrians on a block's sidewalk ring."""
    s = blk.sidewalk_m
    h = s / 2  # walk along the middle of the sidewalk
    x0, y0, x1, y1 = blk.x0, blk.y0, blk.x1, blk.y1
    sides = [((x0, y0 + h), (x1, y0 + h)), ((x0, y1 - h), (x1, y1 - h)),
             ((x0 + h, y0), (x0 + h, y1)), ((x1 - h, y0), (x1 - h, y1))]
    trees = rng.random() < 0.55
    rgb = _TREE[int(rng.integers(len(_TREE)))]
    r = _uni(rng, 2.5, 4.5)
    for (ax, ay), (bx, by) in sides:
        length = math.hypot(bx - ax, by - ay)
        ux, uy = (bx - ax) / length, (by - ay) / length
        if trees and s >= 2.5:
            for t in np.arange(8.0, length - 7, _uni(rng, 8, 12)):
                _tree(cv, rng, ax + ux * t, ay + uy * t, r_m=r * _uni(rng, 0.85, 1.15), rgb=rgb)
        for t in _uni(rng, 3, length - 3, int(rng.poisson(length / 45))):
            x, y = ax + ux * t, ay + uy * t
            if cv.label_at(x, y) == SIDEWALK:
                _person(cv, rng, x + rng.normal(0, s / 6), y + rng.normal(0, s / 6))


def _draw_river(cv: _Canvas, rng, river: _River, xr: list[_Road], yr: list[_Road]) -> None:
    pts = river.pts_m
    outer = river.width_m + 2 * river.bank_m
    cv.band(pts, outer, _jit(rng, _GRASS[0]), GRASS)
    cv.band(pts, river.width_m + 3.0, _jit(rng, (124, 112, 88)), BARE_SOIL)
    cv.band(pts, river.width_m, _jit(rng, _WATER_RIVER, 0.04), WATER)
    # Bridges: every road whose centreline crosses the river band gets a deck over it.
    mask = np.zeros((cv.side_px, cv.side_px), np.uint8)
    cv2.polylines(mask, [cv.px(pts)], False, 1, cv._thick(outer + 2), cv2.LINE_8, _SHIFT)
    size = cv.side_px * cv.gsd_m
    for roads, vertical in ((xr, True), (yr, False)):
        for road in roads:
            k = int(road.centre_m / cv.gsd_m)
            if not 0 <= k < cv.side_px:
                continue
            line = mask[:, k] if vertical else mask[k, :]
            idx = np.flatnonzero(line)
            if idx.size == 0:
                continue
            # Split into contiguous runs (a meander may cross the same road twice).
            for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                a0, a1 = max(0.0, run[0] * cv.gsd_m - 2), min(size, (run[-1] + 1) * cv.gsd_m + 2)
                c, hw = road.centre_m, road.width_m / 2 + 2.5
                rect = (c - hw, a0, c + hw, a1) if vertical else (a0, c - hw, a1, c + hw)
                deck = [(rect[0], rect[1]), (rect[2], rect[1]), (rect[2], rect[3]),
                        (rect[0], rect[3])]
                cv.cast(deck, 6.0, h_lo_m=5.0)
                cv.poly(deck, _SIDEWALK, SIDEWALK, 6.0)
                if vertical:
                    inner = (c - hw + 2.5, a0, c + hw - 2.5, a1)
                else:
                    inner = (a0, c - hw + 2.5, a1, c + hw - 2.5)
                cv.rect(*inner, _ASPHALT, ROAD, 6.0)
                cv.band(deck, 0.4, (200, 198, 192), closed=True)


# ----------------------------------------------------------------------------------------------
# Finishing: shadows, textures, colour grading, camera blur.


def _noise_field(rng, side_px: int, cell_px: float, octaves: int = 1) -> np.ndarray:
    """Smooth value noise at full resolution, int8 (about -127..127): built at low resolution and
    upsampled, octaves summed at the low resolution (cheap)."""
    n = max(4, int(side_px / cell_px) + 2)
    acc = np.zeros((n, n), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        m = max(3, n >> o)
        layer = rng.random((m, m), dtype=np.float32) - 0.5
        acc += amp * cv2.resize(layer, (n, n), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.6
    # Scaled so the field spans roughly the unit range (value noise concentrates near 0).
    low = np.clip(acc * (2.2 * 127 / total) + 128, 1, 255).astype(np.uint8)
    full = cv2.resize(low, (side_px, side_px), interpolation=cv2.INTER_CUBIC)
    # (resize has no int8 path: flipping the top bit maps uint8 v to int8 v - 128, in place)
    np.bitwise_xor(full, 0x80, out=full)
    return full.view(np.int8)


def _lut(table: dict, scale: float, channel: int | None = None) -> np.ndarray:
    lut = np.zeros((1, 256), np.int8)
    for k, v in table.items():
        lut[0, k] = int(round((v if channel is None else v[channel]) * scale))
    return lut


def _finish(cv: _Canvas, rng, gsd_m: float) -> None:
    side = cv.side_px
    # Shadows: rasterise queued casters lowest first, so each pixel holds the tallest caster
    # whose shadow reaches it; it is shadowed if that caster is above the pixel's own height.
    shadow = np.zeros((side, side), np.uint8)
    # Foliage lets some light through (value 185 of 255); opaque casters darken fully.
    for casts, strength in ((cv.soft_casts, 185), (cv.casts, 255)):
        cover = np.zeros((side, side), np.uint8)
        casts.sort(key=lambda c: c[0])
        for hu, draw, *args in casts:
            draw(cover, hu, *args)
        # (saturating subtraction; more than 1 unit = 0.2 m above avoids self-shadowing acne)
        _, hit = cv2.threshold(cv2.subtract(cover, cv.height_u), 1, strength, cv2.THRESH_BINARY)
        cv2.max(shadow, hit, dst=shadow)
        del cover, hit
    shadow = cv2.GaussianBlur(shadow, (0, 0), 0.6)

    # Texture fields; cell sizes are in metres so the look does not depend on gsd.
    def cells(m: float) -> float:
        return max(1.5, m / gsd_m)

    mid = _noise_field(rng, side, cells(0.8))
    coarse = _noise_field(rng, side, cells(4.0), octaves=3)
    patch = _noise_field(rng, side, cells(20.0), octaves=3)
    rows = 256
    # Per-pixel grain: a 2-chunk tile of normal noise, shifted sideways for every chunk, so no
    # full-size noise array is ever drawn (numpy's normal generator is the slow part).
    grain_tile = rng.standard_normal((2 * rows, side), dtype=np.float32)
    k = 127.0 / 0.3  # amplitudes are stored in int8 LUTs, 0.3 = full scale
    lut_g, lut_m, lut_c = _lut(_TEX_GRAIN, k), _lut(_TEX_MID, k), _lut(_TEX_COARSE, k)
    lut_tint = [_lut(_TEX_TINT, 1.0, c) for c in range(3)]
    # Per-world colour grading (white balance, contrast, a touch of haze) folded into one
    # affine map per channel: out = in * scale_c + offset_c.
    gain = _uni(rng, 0.95, 1.05, 3)
    haze = np.array([4.0, 6.0, 10.0]) * _uni(rng, 0.5, 1.5)
    contrast = _uni(rng, 0.95, 1.08)
    scale_c = gain * contrast
    offset_c = gain * 128 * (1 - contrast) + haze
    shade = (1.0 - _SHADOW_RGB) / 255.0
    # All per-pixel arithmetic below is fused OpenCV calls on single-channel planes: numpy's
    # broadcasting of a per-pixel factor over 3 channels was several times slower.
    for r0 in range(0, side, rows):
        r1 = min(side, r0 + rows)
        lab = cv.lab[r0:r1]
        g = np.roll(grain_tile[(r0 // rows) % 2 * rows:][:r1 - r0], -((r0 // rows) * 89 % side),
                    axis=1)
        # Luminance modulation: 1 + sum(amplitude[class] * noise).
        mod = cv2.multiply(cv2.LUT(lab, lut_g), g, dtype=cv2.CV_32F, scale=1 / k)
        mod = cv2.add(mod, cv2.multiply(cv2.LUT(lab, lut_m), mid[r0:r1], dtype=cv2.CV_32F,
                                        scale=1 / (127 * k)))
        mod = cv2.add(mod, cv2.multiply(cv2.LUT(lab, lut_c), coarse[r0:r1], dtype=cv2.CV_32F,
                                        scale=1 / (127 * k)))
        mod = cv2.add(mod, 1.0)
        sh = shadow[r0:r1]
        planes = cv2.split(cv.img[r0:r1])
        out = []
        for c in range(3):
            f = cv2.multiply(planes[c], mod, dtype=cv2.CV_32F)
            lit = cv2.addWeighted(sh, -float(shade[c]), sh, 0.0, 1.0, dtype=cv2.CV_32F)
            f = cv2.multiply(f, lit, scale=float(scale_c[c]))
            f = cv2.add(f, cv2.multiply(cv2.LUT(lab, lut_tint[c]), patch[r0:r1], dtype=cv2.CV_32F,
                                        scale=float(scale_c[c]) / 127))
            # Values are >= 0 up to a tint of a few units on near-black pixels, so the absolute
            # value taken by convertScaleAbs is harmless; it rounds and saturates to uint8.
            out.append(cv2.convertScaleAbs(f, alpha=1.0, beta=float(offset_c[c])))
        cv.img[r0:r1] = cv2.merge(out)
    # The camera's optics: a slight blur softens the rasterised edges (labels are left crisp).
    cv2.GaussianBlur(cv.img, (0, 0), 0.55, dst=cv.img)


# ----------------------------------------------------------------------------------------------
# Entry points


def generate_city(params: SyntheticParams) -> tuple[np.ndarray, np.ndarray]:
    """Build the world: RGB image (H, W, 3) uint8 and labels (H, W) uint8, class ids of
    `SYNTHETIC_CLASSES`. Pure: no I/O, same params -> same bytes."""
    if not isinstance(params, SyntheticParams):
        raise SyntheticWorldError(f"expected SyntheticParams, got {type(params).__name__}")
    t0, c0 = time.perf_counter(), time.process_time()
    # Independent streams: layout, per-object details, textures. Changing one stage's number of
    # draws does not reshuffle the others.
    ss_layout, ss_draw, ss_tex = np.random.SeedSequence([int(params.seed), 0xD0E5E1]).spawn(3)
    rng_layout, rng, rng_tex = (np.random.default_rng(ss_layout), _FastRng(ss_draw),
                                np.random.default_rng(ss_tex))
    size_m = params.side_px * params.gsd_m
    sun_az = rng_layout.uniform(0, 2 * math.pi)
    sun_el = math.radians(rng_layout.uniform(35, 65))
    cv = _Canvas(params.side_px, params.gsd_m, sun_az, sun_el)
    # Everything starts as carriageway; blocks are drawn over it. (Row-wise fill: broadcasting
    # a 3-tuple over the whole image is several times slower.)
    cv.img[0] = _ASPHALT
    cv.img[1:] = cv.img[0]
    cv.lab[:] = ROAD
    river = _make_river(rng_layout, size_m)
    xr, yr, blocks, owner = _layout(rng_layout, size_m, river)
    for blk in blocks:
        if not cv.in_world(blk.x0, blk.y0, blk.x1, blk.y1):
            continue
        _sidewalk(cv, rng, blk)
        _BLOCK_RENDERERS[blk.kind](cv, rng, blk)
    if river is not None:
        _draw_river(cv, rng, river, xr, yr)
    # Road segments between junctions; a street swallowed by a merged block has none.
    for i, road in enumerate(xr):
        for j in range(len(yr) - 1):
            if owner.get((i - 1, j), -1) == owner.get((i, j), -2):
                continue
            a0, a1 = yr[j].centre_m + yr[j].width_m / 2, yr[j + 1].centre_m - yr[j + 1].width_m / 2
            if cv.in_world(road.centre_m - 20, a0, road.centre_m + 20, a1):
                _segment(cv, rng, road, a0, a1, vertical=True)
    for j, road in enumerate(yr):
        for i in range(len(xr) - 1):
            if owner.get((i, j - 1), -1) == owner.get((i, j), -2):
                continue
            a0, a1 = xr[i].centre_m + xr[i].width_m / 2, xr[i + 1].centre_m - xr[i + 1].width_m / 2
            if cv.in_world(a0, road.centre_m - 20, a1, road.centre_m + 20):
                _segment(cv, rng, road, a0, a1, vertical=False)
    for blk in blocks:
        if cv.in_world(blk.x0, blk.y0, blk.x1, blk.y1):
            _street_life(cv, rng, blk)
    # Trees last, so their canopy covers what is under it; none grow in the water.
    for t in cv.trees:
        inside = cv.in_world(t.x_m - t.r_m, t.y_m - t.r_m, t.x_m + t.r_m, t.y_m + t.r_m)
        if inside and cv.label_at(t.x_m, t.y_m) not in _NO_TREES:
            _draw_tree(cv, rng, t)
    t1, c1 = time.perf_counter(), time.process_time()
    _finish(cv, rng_tex, params.gsd_m)
    log.debug("synthetic world %s: drawing %.2f s (cpu %.2f s), finishing %.2f s (cpu %.2f s), "
              "%d casters, %d trees", params, t1 - t0, c1 - c0, time.perf_counter() - t1,
              time.process_time() - c1, len(cv.casts), len(cv.trees))
    return cv.img, cv.lab


def safe_fraction(labels: np.ndarray) -> float:
    """Fraction of pixels whose class is safe in SYNTHETIC_CLASSES."""
    safe = np.zeros(256, bool)
    for cls, (_, ok) in SYNTHETIC_CLASSES.items():
        safe[cls] = ok
    return float(safe[labels].mean())


# ----------------------------------------------------------------------------------------------
# Disk cache


def default_cache_dir() -> Path:
    """`$DOVESEI_CACHE/worlds`, else `$XDG_CACHE_HOME/dovesei/worlds`, else
    `~/.cache/dovesei/worlds`."""
    if os.environ.get("DOVESEI_CACHE"):
        return Path(os.environ["DOVESEI_CACHE"]) / "worlds"
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]) / "dovesei" / "worlds"
    return Path.home() / ".cache" / "dovesei" / "worlds"


def cache_path(params: SyntheticParams, cache_dir: Path | None = None) -> Path:
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return root / (f"synthetic-v{GENERATOR_VERSION}-seed{int(params.seed)}"
                   f"-size{params.size_m:g}m-gsd{params.gsd_m:g}m.npz")


def _load_cached(path: Path, params: SyntheticParams) -> tuple[np.ndarray, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        image, labels = z["image"], z["labels"]
    side = params.side_px
    if image.shape != (side, side, 3) or image.dtype != np.uint8:
        raise ValueError(f"image has shape {image.shape} {image.dtype}, "
                         f"expected ({side}, {side}, 3) uint8")
    if labels.shape != (side, side) or labels.dtype != np.uint8:
        raise ValueError(f"labels have shape {labels.shape} {labels.dtype}, "
                         f"expected ({side}, {side}) uint8")
    return image, labels


def load_or_generate(params: SyntheticParams, cache_dir: Path | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The world for `params`, from the disk cache when present, else generated and cached.

    A cache file that cannot be read is regenerated (with a warning). Writes are atomic: a
    temporary file in the same folder, then `os.replace`, so concurrent users never see half
    a file."""
    path = cache_path(params, cache_dir)
    if path.exists():
        try:
            world = _load_cached(path, params)
            log.info("synthetic world %s loaded from %s", params, path)
            return world
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("synthetic world cache %s is unreadable (%s); regenerating", path, exc)
    t0 = time.perf_counter()
    image, labels = generate_city(params)
    log.info("synthetic world %s generated in %.1f s (safe fraction %.2f)",
             params, time.perf_counter() - t0, safe_fraction(labels))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as fh:
                np.savez(fh, image=image, labels=labels)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
    except OSError as exc:
        # A read-only or full disk costs speed next time, not correctness now.
        log.warning("could not cache synthetic world at %s: %s", path, exc)
    return image, labels


# ----------------------------------------------------------------------------------------------
# Preview picture


def label_colours() -> dict[int, RGB]:
    """Display colours of the classes (for previews and plots), RGB."""
    return {ROOF_FLAT: (230, 60, 60), ROOF_PITCHED: (170, 20, 70), ROAD: (60, 60, 60),
            SIDEWALK: (150, 150, 150), PLAZA: (240, 220, 140), PARKING_LOT: (120, 160, 220),
            CAR: (255, 140, 0), GRASS: (120, 220, 80), SPORTS_FIELD: (40, 180, 150),
            TREE: (20, 100, 30), WATER: (30, 90, 230), BARE_SOIL: (170, 120, 70),
            PERSON: (255, 0, 255)}


def colourize(labels: np.ndarray) -> np.ndarray:
    lut = np.zeros((256, 3), np.uint8)
    for cls, rgb in label_colours().items():
        lut[cls] = rgb
    return lut[labels]


def render_preview(params: SyntheticParams, path: Path | str, crop_m: float = 300.0,
                   panel_px: int = 900) -> Path:
    """Write a PNG: a `crop_m` crop of the world beside its label map and a legend, and a
    downscaled overview of the whole world (image and labels) with the crop outlined."""
    image, labels = generate_city(params)
    side = image.shape[0]
    crop = min(side, int(round(crop_m / params.gsd_m)))
    r0 = c0 = (side - crop) // 2
    ci, cl = image[r0:r0 + crop, c0:c0 + crop], colourize(labels[r0:r0 + crop, c0:c0 + crop])
    interp = cv2.INTER_AREA if crop > panel_px else cv2.INTER_NEAREST
    ci = cv2.resize(ci, (panel_px, panel_px), interpolation=interp)
    cl = cv2.resize(cl, (panel_px, panel_px), interpolation=cv2.INTER_NEAREST)
    legend = np.full((panel_px, 330, 3), 255, np.uint8)
    frac = safe_fraction(labels)
    lines = [f"seed {params.seed}  {params.size_m:g} m  {params.gsd_m:g} m/px",
             f"crop {crop_m:g} m x {crop_m:g} m", f"safe fraction {frac:.3f}", ""]
    for n, text in enumerate(lines):
        cv2.putText(legend, text, (10, 28 + 26 * n), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1,
                    cv2.LINE_AA)
    for n, (cls, (name, safe)) in enumerate(SYNTHETIC_CLASSES.items()):
        y = 28 + 26 * len(lines) + 30 * n
        cv2.rectangle(legend, (10, y - 16), (40, y + 6), label_colours()[cls], -1)
        cv2.putText(legend, f"{cls:2d} {name} ({'safe' if safe else 'unsafe'})", (50, y),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    top = np.hstack([ci, cl, legend])
    ov_px = top.shape[1] // 2
    oi = cv2.resize(image, (ov_px, ov_px), interpolation=cv2.INTER_AREA)
    ol = cv2.resize(colourize(labels), (ov_px, ov_px), interpolation=cv2.INTER_NEAREST)
    k = ov_px / side
    for o in (oi, ol):
        cv2.rectangle(o, (int(c0 * k), int(r0 * k)), (int((c0 + crop) * k), int((r0 + crop) * k)),
                      (255, 255, 0), 2)
    bottom = np.hstack([oi, ol])
    bottom = np.pad(bottom, ((0, 0), (0, top.shape[1] - bottom.shape[1]), (0, 0)),
                    constant_values=255)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), cv2.cvtColor(np.vstack([top, bottom]), cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write preview PNG {out}")
    return out


def main(argv: list[str] | None = None) -> int:
    """`python -m dovesei.sim.synthetic [SPEC] --preview out.png`: time a world, write a preview."""
    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("spec", nargs="?", default="synthetic",
                    help="synthetic[:seed=N,size_m=X,gsd_m=Y]")
    ap.add_argument("--preview", type=Path, help="write a preview PNG here")
    ap.add_argument("--crop-m", type=float, default=300.0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        params = parse_spec(args.spec)
    except SyntheticWorldError as exc:
        log.error("%s", exc)
        return 2
    if args.preview:
        render_preview(params, args.preview, args.crop_m)
        log.info("preview written to %s", args.preview)
    else:
        t0 = time.perf_counter()
        _, labels = generate_city(params)
        print(f"generated {params} in {time.perf_counter() - t0:.2f} s, "
              f"safe fraction {safe_fraction(labels):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
