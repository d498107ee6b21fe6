"""Block contents of the synthetic city, open kinds: parks, lakes, sports grounds, construction sites."""

from __future__ import annotations

import math

import numpy as np

from dovesei.sim.synthetic.blocks import draw_grass, footpath, scatter_trees
from dovesei.sim.synthetic.canvas import blob, Canvas, circle_pts, jit, scaled, smooth_path, uni
from dovesei.sim.synthetic.classes import BARE_SOIL, GRASS, PAL_SOIL, PAL_WATER_POND, SIDEWALK, SPORTS_FIELD, WATER
from dovesei.sim.synthetic.layout import Block
from dovesei.sim.synthetic.objects import add_tree, draw_car, draw_person, flat_building, people_in


def draw_park(cv: Canvas, rng, blk: Block, riverside: bool = False) -> None:
    x0, y0, x1, y1 = blk.inner
    draw_grass(cv, rng, x0, y0, x1, y1, stripes=rng.random() < 0.4)
    area = (x1 - x0) * (y1 - y0)
    gravel = jit(rng, [(196, 186, 164), (150, 148, 144), (178, 164, 140)][int(rng.integers(3))],
                 0.04)
    if not riverside and area > 5000 and rng.random() < 0.3:
        cx = uni(rng, x0 + 0.35 * (x1 - x0), x1 - 0.35 * (x1 - x0))
        cy = uni(rng, y0 + 0.35 * (y1 - y0), y1 - 0.35 * (y1 - y0))
        ax, ay = 0.18 * (x1 - x0), 0.18 * (y1 - y0)
        cv.poly(blob(rng, cx, cy, ax + 2, ay + 2), jit(rng, (120, 112, 90)), BARE_SOIL)
        cv.poly(blob(rng, cx, cy, ax, ay), jit(rng, PAL_WATER_POND, 0.06), WATER)
    for _ in range(int(rng.integers(1, 4))):
        footpath(cv, rng, x0, y0, x1, y1, uni(rng, 2.5, 4.5), gravel)
    if rng.random() < 0.35:
        px, py = uni(rng, x0 + 5, x1 - 15), uni(rng, y0 + 5, y1 - 15)
        cv.poly(blob(rng, px + 5, py + 5, 5, 4, 16), jit(rng, (198, 180, 142)), BARE_SOIL)
    density = uni(rng, 50, 130)
    scatter_trees(cv, rng, x0, y0, x1, y1, int(area / density))
    people_in(cv, rng, x0, y0, x1, y1, int(area / uni(rng, 300, 1200)),
              {GRASS, SIDEWALK, BARE_SOIL})


def draw_water(cv: Canvas, rng, blk: Block) -> None:
    """A lake block: an irregular pond with a soil bank, a path around, trees on the shore."""
    x0, y0, x1, y1 = blk.inner
    draw_grass(cv, rng, x0, y0, x1, y1, stripes=False)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    ax, ay = uni(rng, 0.3, 0.4) * (x1 - x0), uni(rng, 0.3, 0.4) * (y1 - y0)
    # One shape at three sizes (path, bank, water): the same seed for each outline.
    shape_seed = int(rng.integers(2**31))

    def outline(grow_m: float) -> np.ndarray:
        return blob(np.random.default_rng(shape_seed), cx, cy, ax + grow_m, ay + grow_m)

    cv.band(outline(6.0), 3.0, jit(rng, (184, 172, 150)), SIDEWALK, closed=True)
    cv.poly(outline(1.5), jit(rng, (116, 106, 84)), BARE_SOIL)
    cv.poly(outline(0.0), jit(rng, PAL_WATER_POND, 0.08), WATER)
    for t in np.linspace(0, 2 * math.pi, int(rng.integers(6, 16)), endpoint=False):
        k = uni(rng, 1.25, 1.45)
        x, y = cx + (ax + 6) * k * math.cos(t), cy + (ay + 6) * k * math.sin(t)
        if x0 + 2 < x < x1 - 2 and y0 + 2 < y < y1 - 2:
            add_tree(cv, rng, x, y)
    people_in(cv, rng, x0, y0, x1, y1, int(rng.integers(2, 12)), {SIDEWALK, GRASS})


def _pitch(cv: Canvas, rng, cx: float, cy: float, length: float, width: float,
           along_x: bool) -> None:
    """A football pitch with mowing stripes and its line markings."""
    def w(a, b):
        return (cx + a, cy + b) if along_x else (cx + b, cy + a)

    hl, hw = length / 2, width / 2
    green = jit(rng, (72, 132, 62), 0.04)
    cv.poly([w(-hl - 3, -hw - 3), w(hl + 3, -hw - 3), w(hl + 3, hw + 3), w(-hl - 3, hw + 3)],
            green, SPORTS_FIELD)
    n = 12
    for k in range(0, n, 2):
        a = -hl + k * length / n
        b = a + length / n
        cv.poly([w(a, -hw), w(b, -hw), w(b, hw), w(a, hw)], scaled(green, 1.1))
    s = length / 105.0
    lw, paint = 0.12, (236, 238, 232)

    def line(pts, closed=False):
        cv.band([w(a, b) for a, b in pts], lw, paint, closed=closed, under=green)

    line([(-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw)], closed=True)
    line([(0, -hw), (0, hw)])
    cv.band(circle_pts(w(0, 0), 9.15 * s, 40), lw, paint, closed=True, under=green)
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


def draw_sports(cv: Canvas, rng, blk: Block) -> None:
    x0, y0, x1, y1 = blk.inner
    draw_grass(cv, rng, x0, y0, x1, y1, stripes=False)
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
                jit(rng, track, 0.05), SPORTS_FIELD)
        for k in range(lanes + 1):
            cv.band(_stadium_pts(cx, cy, straight, r_in + k * lane_w, along_x), 0.06,
                    (235, 232, 228), closed=True, under=track)
        cv.poly(_stadium_pts(cx, cy, straight, r_in - 0.2, along_x),
                jit(rng, (80, 128, 60), 0.04), SPORTS_FIELD)
        _pitch(cv, rng, cx, cy, min(100 * s, straight + 2 * r_in - 6), min(64 * s, 2 * r_in - 6),
               along_x)
        pl, pw = 100 * s, 64 * s
        # A grandstand along one straight, where the block leaves room for it.
        room = (D - 2 * (r_in + lanes * lane_w)) / 2 - 3
        if room > 6:
            depth = min(room, uni(rng, 8, 14))
            b0 = r_in + lanes * lane_w + 2
            a0, a1 = -straight / 2, straight / 2
            sgn = 1 if rng.random() < 0.5 else -1
            bb0, bb1 = sorted((sgn * b0, sgn * (b0 + depth)))
            if along_x:
                gx0, gy0, gx1, gy1 = cx + a0, cy + bb0, cx + a1, cy + bb1
            else:
                gx0, gy0, gx1, gy1 = cx + bb0, cy + a0, cx + bb1, cy + a1
            flat_building(cv, rng, gx0, gy0, gx1, gy1, uni(rng, 8, 14), commercial=False)
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
                cv.rect(tx, ty, tx + cw, ty + chh, jit(rng, court, 0.04), SPORTS_FIELD)
                cv.band([(tx + 3.5, ty + 6.1), (tx + 14.5, ty + 6.1), (tx + 14.5, ty + 29.9),
                         (tx + 3.5, ty + 29.9)], 0.08, (235, 235, 235), closed=True, under=court)
                cv.band([(tx + 2, ty + 18), (tx + 16, ty + 18)], 0.1, (40, 40, 40))
                tx += cw + 1
    if players and pl > 0:
        for _ in range(int(rng.integers(8, 23))):
            a, b = uni(rng, -pl / 2, pl / 2), uni(rng, -pw / 2, pw / 2)
            draw_person(cv, rng, *((cx + a, cy + b) if along_x else (cx + b, cy + a)))
    # Trees on the margins, a clubhouse in a corner.
    step = uni(rng, 6, 10)
    for t in np.arange(x0 + 3, x1 - 3, step):
        for yy in (y0 + 3, y1 - 3):
            if rng.random() < 0.85 and cv.label_at(t, yy) == GRASS:
                add_tree(cv, rng, t, yy)
    for t in np.arange(y0 + 3, y1 - 3, step):
        for xx in (x0 + 3, x1 - 3):
            if rng.random() < 0.85 and cv.label_at(xx, t) == GRASS:
                add_tree(cv, rng, xx, t)
    if rng.random() < 0.5:
        flat_building(cv, rng, x1 - 16, y1 - 12, x1 - 3, y1 - 4, 4.0, commercial=False)


def draw_construction(cv: Canvas, rng, blk: Block) -> None:
    x0, y0, x1, y1 = blk.inner
    soil = jit(rng, [PAL_SOIL, (170, 146, 110), (128, 104, 82)][int(rng.integers(3))], 0.04)
    cv.rect(x0, y0, x1, y1, soil, BARE_SOIL)
    # Tyre tracks (darker arcs), heaps, an excavation, site cabins, yellow machines, a slab.
    for _ in range(int(rng.integers(4, 10))):
        pts = smooth_path(np.array([(uni(rng, x0, x1), uni(rng, y0, y1)) for _ in range(3)]))
        cv.band(pts, 2.2, scaled(soil, 0.86))
        cv.band(pts, 0.6, scaled(soil, 1.08))
    for _ in range(int(rng.integers(1, 5))):
        hx, hy = uni(rng, x0 + 8, x1 - 8), uni(rng, y0 + 8, y1 - 8)
        r = uni(rng, 3, 7)
        cv.poly(blob(rng, hx, hy, r, r * 0.8, 20), scaled(soil, uni(rng, 0.8, 1.15)), BARE_SOIL)
        cv.poly(blob(rng, hx + cv.sun_xy[0] * r * 0.3, hy + cv.sun_xy[1] * r * 0.3, r * 0.5,
                     r * 0.4, 16),
                scaled(soil, 1.12))
    if rng.random() < 0.5 and min(x1 - x0, y1 - y0) > 40:
        ex0, ey0 = x0 + uni(rng, 8, 15), y0 + uni(rng, 8, 15)
        ex1, ey1 = x1 - uni(rng, 8, 15), y1 - uni(rng, 8, 15)
        cv.rect(ex0, ey0, ex1, ey1, scaled(soil, 0.75), BARE_SOIL)
        if rng.random() < 0.6:
            # A concrete base slab already poured in the pit: counted as a (flat) roof.
            flat_building(cv, rng, ex0 + 4, ey0 + 4, ex1 - 4, ey1 - 4, 1.0, (150, 150, 146),
                          commercial=False)
    for k in range(int(rng.integers(1, 4))):
        cx0, cy0 = x0 + 2 + k * 3.2, y0 + 2
        flat_building(cv, rng, cx0, cy0, cx0 + 2.8, cy0 + 6, 2.6, jit(rng, (214, 214, 208)),
                      commercial=False)
    for _ in range(int(rng.integers(1, 4))):
        draw_car(cv, rng, uni(rng, x0 + 6, x1 - 6), uni(rng, y0 + 6, y1 - 6), uni(rng, 0, math.pi),
                 rgb=(222, 170, 30), length_m=uni(rng, 6, 8))
    people_in(cv, rng, x0, y0, x1, y1, int(rng.integers(1, 8)), {BARE_SOIL})
