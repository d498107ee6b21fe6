"""The drawing surface of the synthetic worlds and its geometry helpers.

`Canvas` writes image, labels and heights with the same polygon, so the label map is exactly what
was drawn; shadow casters are queued and rasterised at the end by `render`. `FastRng` serves
the ~10^5 scalar draws of a world from pre-drawn blocks; the small colour helpers (`uni`, `jit`,
`pick`, ...) are shared by every drawing module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.sim.synthetic.classes import RGB


SHIFT = 3  # OpenCV sub-pixel bits: polygons are placed to 1/8 px
_HEIGHT_UNIT_M = 0.2  # the height map is uint8 in these units (0..51 m)


class FastRng:
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


def uni(rng: np.random.Generator, lo, hi, size=None):
    """rng.uniform that tolerates an empty range (hi < lo: returns lo), which odd block sizes
    produce; it always consumes the same draws, so determinism does not depend on it."""
    return rng.uniform(lo, hi if hi > lo else lo, size)


def _u8(v: float) -> int:
    return 0 if v < 0 else 255 if v > 255 else int(v)


def pick(rng: np.random.Generator, weighted: list[tuple[RGB, float]]) -> RGB:
    # Plain Python on purpose: called per object, where numpy's per-call overhead dominates.
    x = rng.random() * sum(p for _, p in weighted)
    for rgb, p in weighted:
        x -= p
        if x <= 0:
            return rgb
    return weighted[-1][0]


def jit(rng: np.random.Generator, rgb: RGB, rel: float = 0.06) -> RGB:
    """Object-to-object colour variation: a common brightness factor plus a little hue noise."""
    k = 1.0 + rel * rng.normal()
    return (_u8(rgb[0] * k + 3 * rng.normal()), _u8(rgb[1] * k + 3 * rng.normal()),
            _u8(rgb[2] * k + 3 * rng.normal()))


def scaled(rgb: RGB, k: float) -> RGB:
    return (_u8(rgb[0] * k), _u8(rgb[1] * k), _u8(rgb[2] * k))


def mix(a: RGB, b: RGB, t: float) -> RGB:
    return (_u8(a[0] + (b[0] - a[0]) * t + 0.5), _u8(a[1] + (b[1] - a[1]) * t + 0.5),
            _u8(a[2] + (b[2] - a[2]) * t + 0.5))


# ----------------------------------------------------------------------------------------------
# Canvas: every drawing primitive writes image, labels and heights with the same polygon, so the
# label map is exactly what was drawn.


@dataclass
class Tree:
    x_m: float
    y_m: float
    r_m: float
    h_m: float
    rgb: RGB


class Canvas:
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
        self.trees: list[Tree] = []
        # People and cars as drawn, canvas metres (x right, y down): (kind, x, y, angle from +x
        # towards +y, length, width, rgb). They become the world's baked objects (`objects.py`).
        self.objects: list[tuple] = []
        self._k = (1 << SHIFT) / gsd_m
        self._half = 0.5 * (1 << SHIFT)

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
        cv2.fillPoly(self.img, p, rgb, cv2.LINE_8, SHIFT)
        if cls is not None:
            cv2.fillPoly(self.lab, p, cls, cv2.LINE_8, SHIFT)
            cv2.fillPoly(self.height_u, p, self._hu(h_m), cv2.LINE_8, SHIFT)

    def rect(self, x0, y0, x1, y1, rgb: RGB, cls: int | None = None, h_m: float = 0.0) -> None:
        self.poly([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], rgb, cls, h_m)

    def disc(self, c, r_m: float, rgb: RGB, cls: int | None = None, h_m: float = 0.0) -> None:
        cp, rp = self._pt(c), max(1, int(r_m * self._k + 0.5))
        cv2.circle(self.img, cp, rp, rgb, -1, cv2.LINE_8, SHIFT)
        if cls is not None:
            cv2.circle(self.lab, cp, rp, cls, -1, cv2.LINE_8, SHIFT)
            cv2.circle(self.height_u, cp, rp, self._hu(h_m), -1, cv2.LINE_8, SHIFT)

    def band(self, pts_m, width_m: float, rgb: RGB, cls: int | None = None, h_m: float = 0.0,
             closed: bool = False, under: RGB | None = None) -> None:
        """A polyline `width_m` wide. Lines thinner than a pixel are drawn 1 px wide with their
        colour blended towards `under` in proportion, so thin paint does not look too bold."""
        if under is not None and width_m < self.gsd_m:
            rgb = mix(under, rgb, width_m / self.gsd_m)
        p, t = [self.px(pts_m)], self._thick(width_m)
        cv2.polylines(self.img, p, closed, rgb, t, cv2.LINE_8, SHIFT)
        if cls is not None:
            cv2.polylines(self.lab, p, closed, cls, t, cv2.LINE_8, SHIFT)
            cv2.polylines(self.height_u, p, closed, self._hu(h_m), t, cv2.LINE_8, SHIFT)

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

    def label_near(self, x_m: float, y_m: float, r_m: float, label: int) -> bool:
        """Whether any label pixel within `r_m` (plus a pixel) of the point, inside the world, is `label`."""
        r_px = r_m / self.gsd_m + 1.0
        c, r = x_m / self.gsd_m, y_m / self.gsd_m
        r0, r1 = max(0, int(r - r_px)), min(self.side_px, int(r + r_px) + 1)
        c0, c1 = max(0, int(c - r_px)), min(self.side_px, int(c + r_px) + 1)
        return bool((self.lab[r0:r1, c0:c1] == label).any())


_UNIT_CIRCLES = {n: np.stack([np.cos(a), np.sin(a)], axis=1)
                 for n in (6, 10, 12, 40) for a in [np.linspace(0, 2 * math.pi, n, endpoint=False)]}


def _fill_hull(img: np.ndarray, value: int, hull: np.ndarray) -> None:
    cv2.fillConvexPoly(img, hull, value, cv2.LINE_8, SHIFT)


def _thick_line(img: np.ndarray, value: int, p0, p1, thick_px: int) -> None:
    cv2.line(img, p0, p1, value, thick_px, cv2.LINE_8, SHIFT)


def _fill_ellipse(img: np.ndarray, value: int, centre, axes, angle_deg: float) -> None:
    cv2.ellipse(img, centre, axes, angle_deg, 0, 360, value, -1, cv2.LINE_8, SHIFT)


def circle_pts(c, r_m: float, n: int = 12) -> np.ndarray:
    unit = _UNIT_CIRCLES.get(n)
    if unit is None:
        a = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
        unit = np.stack([np.cos(a), np.sin(a)], axis=1)
    return unit * r_m + (c[0], c[1])


_OBB_UNIT = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], np.float64)


def obb(cx: float, cy: float, length_m: float, width_m: float, ang_rad: float,
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


def rounded_rect(x0, y0, x1, y1, r_m: float, n: int = 5) -> np.ndarray:
    r = max(0.0, min(r_m, (x1 - x0) / 2, (y1 - y0) / 2))
    pts = []
    for cx, cy, a0 in ((x1 - r, y0 + r, -90), (x1 - r, y1 - r, 0), (x0 + r, y1 - r, 90),
                       (x0 + r, y0 + r, 180)):
        for a in np.radians(np.linspace(a0, a0 + 90, n)):
            pts.append((cx + r * math.cos(a), cy + r * math.sin(a)))
    return np.array(pts)


def blob(rng, cx, cy, ax_m, ay_m, n: int = 40) -> np.ndarray:
    """An irregular closed outline (pond, soil heap): an ellipse with low-order radial noise."""
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    k = np.ones(n)
    for h in range(2, 5):
        k += rng.normal(0, 0.12 / (h - 1)) * np.cos(h * a + uni(rng, 0, 2 * math.pi))
    return np.stack([cx + ax_m * k * np.cos(a), cy + ay_m * k * np.sin(a)], axis=1)


def smooth_path(pts: np.ndarray, iters: int = 3) -> np.ndarray:
    """Chaikin corner cutting: turns a few waypoints into a gently curving path."""
    for _ in range(iters):
        q = 0.75 * pts[:-1] + 0.25 * pts[1:]
        r = 0.25 * pts[:-1] + 0.75 * pts[1:]
        pts = np.vstack([pts[:1], np.stack([q, r], axis=1).reshape(-1, 2), pts[-1:]])
    return pts
