"""The styles of the synthetic world suite, besides the original city (`style=city`).

Three are the city's street grid with another mix of blocks (`CityStyle`): `downtown` (shops,
apartment blocks, plazas and car parks on a tight grid), `villas` (detached houses with gardens
and pools on wide lots) and `parkland` (a campus: parks, sports grounds, ponds, a few halls). Two
add what a grid of blocks cannot draw: `coast` is a city whose one side is the sea, with a beach,
a paved quay and piers with boats; `desert` is open sand with a few long roads, scattered walled
compounds, warehouses, car parks and shrubs.

`crowded` is a city of plazas and parks where crowds gather (groups of 20-80 people, some milling
about) and many more walk and drive than elsewhere (`STYLE_DENSITY`, drawn by `populate`).

Each style is a function of the seed alone. A style draws on the `Canvas` with the same routines
as the city, so its label map is exactly what was drawn and the finishing pass (shadows,
textures) is shared.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from dovesei.sim.populate import Density
from dovesei.sim.synthetic.blocks import parking_lot
from dovesei.sim.synthetic.canvas import Canvas, blob, jit, scaled, smooth_path, uni
from dovesei.sim.synthetic.classes import (
    BARE_SOIL, PAL_ASPHALT, PAL_PAINT, PLAZA, ROAD, ROOF_FLAT, SIDEWALK, WATER,
)
from dovesei.sim.synthetic.layout import CityStyle
from dovesei.sim.synthetic.objects import add_tree, draw_car, draw_person, flat_building, people_in

CITY_STYLES: dict[str, CityStyle] = {
    "downtown": CityStyle(
        kind_weights=(("commercial", 0.44), ("apartments", 0.4), ("plaza", 0.06), ("parking", 0.05),
                      ("park", 0.03), ("construction", 0.02)),
        spacing_long_m=(60, 110), spacing_short_m=(45, 85), no_river_chance=0.8),
    "villas": CityStyle(
        kind_weights=(("residential", 0.74), ("park", 0.08), ("water", 0.03), ("sports", 0.03), ("plaza", 0.03),
                      ("commercial", 0.04), ("parking", 0.03), ("construction", 0.02)),
        spacing_long_m=(90, 170), spacing_short_m=(70, 130), no_river_chance=0.6),
    "parkland": CityStyle(
        kind_weights=(("park", 0.4), ("sports", 0.14), ("water", 0.07), ("apartments", 0.12), ("commercial", 0.1),
                      ("parking", 0.07), ("plaza", 0.07), ("residential", 0.03)),
        spacing_long_m=(120, 220), spacing_short_m=(90, 170), no_river_chance=0.3),
    # A city of squares and parks, where the crowds are (their people: `STYLE_DENSITY`).
    "crowded": CityStyle(
        kind_weights=(("plaza", 0.3), ("park", 0.28), ("commercial", 0.16), ("apartments", 0.14), ("parking", 0.06),
                      ("sports", 0.04), ("water", 0.02)),
        spacing_long_m=(80, 150), spacing_short_m=(60, 120), no_river_chance=0.7),
    # The land side of the coast is an ordinary mixed city; `draw_coast` then floods one side.
    "coast": CityStyle(
        kind_weights=(("residential", 0.3), ("apartments", 0.24), ("commercial", 0.18), ("park", 0.1),
                      ("parking", 0.07), ("plaza", 0.07), ("sports", 0.02), ("construction", 0.02)),
        no_river_chance=1.0),
}

_SAND = (204, 178, 134)
_SEA = (38, 92, 118)
# The sea and the beach are drawn over a finished city: what lay beneath them still has queued
# shadow casters. Giving the flooded surfaces the greatest height (51 m) means no such phantom
# shadow can fall on them (a pixel is shadowed only by something taller than itself).
_OVER_ALL_M = 51.0


def _coastline(rng, size_m: float) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """A wavy shoreline across the world, as points (u along the shore, v towards the sea)."""
    t = np.arange(-40.0, size_m + 40.0, 10.0)
    base = uni(rng, 0.62, 0.72) * size_m
    off = np.zeros_like(t)
    for amp, lam in ((uni(rng, 30, 70), uni(rng, 600, 1400)), (uni(rng, 5, 15), uni(rng, 120, 300))):
        off += amp * np.sin(2 * math.pi * t / lam + uni(rng, 0, 2 * math.pi))
    side = int(rng.integers(4))  # which world edge the sea lies beyond

    def to_xy(uv: np.ndarray) -> np.ndarray:
        u, v = uv[:, 0], uv[:, 1]
        if side == 0:
            return np.stack([v, u], 1)  # sea to the east
        if side == 1:
            return np.stack([size_m - v, u], 1)  # sea to the west
        if side == 2:
            return np.stack([u, v], 1)  # sea to the south (image down)
        return np.stack([u, size_m - v], 1)  # sea to the north

    return np.stack([t, base + off], 1), to_xy


def draw_coast(cv: Canvas, rng) -> None:
    """Flood one side of a finished city: sea, a beach or a paved quay, piers with boats."""
    size_m = cv.side_px * cv.gsd_m
    shore, to_xy = _coastline(rng, size_m)
    far = size_m + 100.0

    def region(shift_m: float) -> np.ndarray:
        # Everything seaward of the shoreline moved `shift_m` towards the land.
        edge = shore - (0.0, shift_m)
        return to_xy(np.vstack([edge, (edge[-1, 0], far), (edge[0, 0], far)]))

    beach_m = uni(rng, 25, 60)
    cv.poly(region(beach_m + 6.0), jit(rng, (176, 172, 162), 0.04), SIDEWALK, _OVER_ALL_M)  # promenade
    cv.poly(region(beach_m), jit(rng, _SAND, 0.04), BARE_SOIL, _OVER_ALL_M)
    # A harbour: along a stretch of the shore the beach is a paved quay with piers into the sea.
    u0 = uni(rng, 0.15, 0.55) * size_m
    u1 = u0 + uni(rng, 250, 450)
    quay = shore[(shore[:, 0] >= u0) & (shore[:, 0] <= u1)]
    if len(quay) >= 2:
        top = quay - (0.0, beach_m)
        cv.poly(to_xy(np.vstack([top, quay[::-1] + (0.0, 4.0)])), jit(rng, (168, 166, 160), 0.04), PLAZA,
                _OVER_ALL_M)
    cv.poly(region(0.0), jit(rng, _SEA, 0.03), WATER, _OVER_ALL_M)
    # Deeper water is darker: image-only bands further out.
    for k, depth_m in enumerate((60.0, 140.0, 260.0)):
        cv.poly(region(-depth_m), scaled(_SEA, 0.92 - 0.07 * k))
    if len(quay) >= 2:
        for u in np.arange(u0 + 25.0, u1 - 10.0, uni(rng, 45, 80)):
            v = float(np.interp(u, shore[:, 0], shore[:, 1]))
            length, width = uni(rng, 60, 150), uni(rng, 4, 8)
            pier = np.array([(u - width / 2, v - 2), (u + width / 2, v - 2), (u + width / 2, v + length),
                             (u - width / 2, v + length)])
            cv.poly(to_xy(pier), jit(rng, (150, 140, 126), 0.05), SIDEWALK, 1.5)
            for side in (-1, 1):
                for w in np.arange(v + 8.0, v + length - 6.0, uni(rng, 9, 16)):
                    if rng.random() < 0.7:
                        bx, by = to_xy(np.array([(u + side * (width / 2 + 2.6), w)]))[0]
                        ang = math.atan2(*(to_xy(np.array([(u, 1.0)])) - to_xy(np.array([(u, 0.0)])))[0][::-1])
                        draw_car(cv, rng, bx, by, ang, rgb=(236, 236, 232), length_m=uni(rng, 6.5, 12))
    # Boats at anchor and people on the sand.
    for _ in range(int(rng.integers(4, 14))):
        u, dv = uni(rng, 0, size_m), uni(rng, 80, 300)
        v = float(np.interp(u, shore[:, 0], shore[:, 1])) + dv
        bx, by = to_xy(np.array([(u, v)]))[0]
        if 0 < bx < size_m and 0 < by < size_m:
            draw_car(cv, rng, bx, by, uni(rng, 0, math.pi), rgb=(230, 230, 226), length_m=uni(rng, 6.5, 15))
    for _ in range(int(size_m / 25)):
        u = uni(rng, 0, size_m)
        v = float(np.interp(u, shore[:, 0], shore[:, 1])) - uni(rng, 3, beach_m - 3)
        x, y = to_xy(np.array([(u, v)]))[0]
        if cv.label_at(x, y) == BARE_SOIL:
            draw_person(cv, rng, x, y)


# Styles drawn on top of a finished city, before its trees.
CITY_EXTRAS: dict[str, Callable[[Canvas, object], None]] = {"coast": draw_coast}


def _compound(cv: Canvas, rng, cx: float, cy: float) -> None:
    """A walled plot: paved or sandy yard, one flat-roofed house, palms, maybe a car or a pool."""
    w, h = uni(rng, 25, 70), uni(rng, 25, 70)
    x0, y0, x1, y1 = cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2
    if not cv.in_world(x0, y0, x1, y1):
        return
    paved = rng.random() < 0.5
    cv.rect(x0, y0, x1, y1, jit(rng, (196, 186, 168) if paved else (210, 186, 146), 0.04),
            PLAZA if paved else BARE_SOIL)
    wall = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    for (ax, ay), (bx, by) in zip(wall, wall[1:] + wall[:1]):
        # One caster per side: the hull of the whole wall would shade the entire yard.
        cv.cast([(ax - 0.25, ay - 0.25), (bx + 0.25, ay - 0.25), (bx + 0.25, by + 0.25), (ax - 0.25, by + 0.25)]
                if ay == by else [(ax - 0.25, ay - 0.25), (ax + 0.25, ay - 0.25), (bx + 0.25, by + 0.25),
                                  (bx - 0.25, by + 0.25)], 2.5)
    cv.band(wall, 0.5, jit(rng, (222, 212, 192), 0.03), ROOF_FLAT, 2.5, closed=True)
    bw, bh = w * uni(rng, 0.35, 0.6), h * uni(rng, 0.35, 0.6)
    bx, by = uni(rng, x0 + 3, x1 - bw - 3), uni(rng, y0 + 3, y1 - bh - 3)
    flat_building(cv, rng, bx, by, bx + bw, by + bh, uni(rng, 4, 10),
                  jit(rng, [(226, 218, 200), (206, 196, 176), (184, 180, 172)][int(rng.integers(3))], 0.04),
                  commercial=False)
    if rng.random() < 0.3 and w > 35:
        px = bx + bw + 2 if bx + bw + 10 < x1 - 2 else x0 + 2
        cv.rect(px, by, px + 6, by + 3.5, jit(rng, (96, 186, 206), 0.04), WATER)
    for _ in range(int(rng.integers(0, 5))):
        add_tree(cv, rng, uni(rng, x0 + 2, x1 - 2), uni(rng, y0 + 2, y1 - 2), r_m=uni(rng, 1.8, 3.5))
    if rng.random() < 0.5:
        draw_car(cv, rng, uni(rng, x0 + 4, x1 - 4), uni(rng, y0 + 3, y1 - 3), uni(rng, 0, math.pi))
    people_in(cv, rng, x0, y0, x1, y1, int(rng.integers(0, 3)), {PLAZA, BARE_SOIL}, group_max=2)


def draw_desert(cv: Canvas, rng_layout, rng) -> None:
    """Open sand with a few long roads, walled compounds near them, warehouses, car parks, shrubs."""
    size_m = cv.side_px * cv.gsd_m
    cv.img[0] = _SAND
    cv.img[1:] = cv.img[0]
    cv.lab[:] = BARE_SOIL
    # Dunes and gravel flats: large image-only patches of slightly other sand tones.
    for _ in range(int(size_m / 40)):
        cx, cy = uni(rng, 0, size_m), uni(rng, 0, size_m)
        a = uni(rng, 20, 120)
        cv.poly(blob(rng, cx, cy, a, a * uni(rng, 0.3, 0.8)),
                jit(rng, [(208, 182, 138), (196, 170, 128), (200, 178, 140)][int(rng.integers(3))], 0.02))
    roads = []
    for _ in range(int(rng_layout.integers(2, 5))):
        vertical = rng_layout.random() < 0.5
        c = uni(rng_layout, 0.1, 0.9) * size_m
        width = uni(rng_layout, 9, 14)
        wobble = uni(rng_layout, -0.08, 0.08) * size_m
        a = np.array([(c, -20.0), (c + wobble, size_m + 20.0)]) if vertical else \
            np.array([(-20.0, c), (size_m + 20.0, c + wobble)])
        cv.band(a, width + 5.0, jit(rng, (186, 168, 136), 0.03), BARE_SOIL)  # graded shoulders
        cv.band(a, width, jit(rng, PAL_ASPHALT, 0.04), ROAD)
        cv.band(a, 0.15, PAL_PAINT)
        roads.append((a, width))
    # Compounds, most of them within a short drive of a road.
    n = int(size_m * size_m / 40_000 * uni(rng_layout, 0.7, 1.2))
    for _ in range(n):
        if roads and rng_layout.random() < 0.75:
            (p0, p1), width = roads[int(rng_layout.integers(len(roads)))]
            t = rng_layout.random()
            px, py = p0 + t * (p1 - p0)
            d = (p1 - p0) / np.linalg.norm(p1 - p0)
            off = (width / 2 + uni(rng_layout, 30, 160)) * (1 if rng_layout.random() < 0.5 else -1)
            cx, cy = px - d[1] * off, py + d[0] * off
        else:
            cx, cy = uni(rng_layout, 0, size_m), uni(rng_layout, 0, size_m)
        if cv.label_at(cx, cy) == BARE_SOIL:
            _compound(cv, rng, cx, cy)
    for _ in range(int(rng_layout.integers(2, 6))):
        x0, y0 = uni(rng_layout, 20, size_m - 160), uni(rng_layout, 20, size_m - 120)
        w, h = uni(rng_layout, 50, 140), uni(rng_layout, 40, 100)
        if rng_layout.random() < 0.5:
            cv.rect(x0 - 8, y0 - 8, x0 + w + 8, y0 + h + 8, jit(rng, PAL_ASPHALT, 0.05), ROAD)
            flat_building(cv, rng, x0, y0, x0 + w, y0 + h, uni(rng, 7, 14))
        else:
            parking_lot(cv, rng, x0, y0, x0 + w, y0 + h)
    # Shrubs and the odd palm grove.
    for _ in range(int(size_m * size_m / 2500)):
        x, y = uni(rng, 0, size_m), uni(rng, 0, size_m)
        if cv.label_at(x, y) == BARE_SOIL:
            add_tree(cv, rng, x, y, r_m=uni(rng, 0.8, 1.8), h_m=uni(rng, 1.0, 2.5),
                     rgb=(96, 102, 62))
    # Tracks across the sand (image only: driven-on sand is still sand).
    for _ in range(int(size_m / 200)):
        pts = smooth_path(np.array([(uni(rng, 0, size_m), uni(rng, 0, size_m)) for _ in range(4)]))
        cv.band(pts, 2.5, scaled(_SAND, 0.9))
    people_in(cv, rng, 0, 0, size_m, size_m, int(size_m / 100), {BARE_SOIL, PLAZA})
    # Cars on the roads.
    for (p0, p1), width in roads:
        d = p1 - p0
        ang = math.atan2(d[1], d[0])
        for t in np.arange(0.0, 1.0, uni(rng, 0.03, 0.08)):
            if rng.random() < 0.5:
                side = 1 if rng.random() < 0.5 else -1
                x, y = p0 + t * d
                nx, ny = -d[1] / np.linalg.norm(d), d[0] / np.linalg.norm(d)
                draw_car(cv, rng, x + nx * side * width / 4, y + ny * side * width / 4,
                         ang + (0 if side > 0 else math.pi))


# How busy each style is beyond what its drawing placed (`populate.Density`; the others: the default).
STYLE_DENSITY: dict[str, Density] = {
    "crowded": Density(walkers_per_ha=8.0, standing_per_ha=3.0, cars_per_ha_road=8.0, crowds_per_km2=25.0),
    "desert": Density(walkers_per_ha=0.4, standing_per_ha=0.2, cars_per_ha_road=3.0),
}

# Styles that replace the street grid altogether: draw(canvas, layout rng, drawing rng).
OPEN_STYLES: dict[str, Callable[[Canvas, object, object], None]] = {"desert": draw_desert}
STYLES = ("city", *CITY_STYLES, *OPEN_STYLES)
