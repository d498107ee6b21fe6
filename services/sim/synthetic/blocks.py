"""Block contents of the synthetic city, built-up kinds: houses, apartments, plazas, shops, parking.

Each renderer gets a block and fills its inner rectangle (inside the sidewalk ring) completely.
"""

from __future__ import annotations

import math

import numpy as np

from dovesei.sim.synthetic.canvas import Canvas, jit, mix, pick, scaled, smooth_path, Tree, uni
from dovesei.sim.synthetic.classes import (
    BARE_SOIL, GRASS, PAL_ASPHALT, PAL_GRASS, PAL_LOT_ASPHALT, PAL_PAINT, PAL_ROOF_FLAT, PAL_ROOF_PITCHED,
    PAL_TREE, PAL_WATER_POOL, PARKING_LOT, PLAZA, RGB, ROAD, SIDEWALK, TREE, WATER,
)
from dovesei.sim.synthetic.layout import Block, BlockFrame
from dovesei.sim.synthetic.objects import add_tree, draw_car, draw_person, flat_building, people_in, pitched_roof


def draw_grass(cv: Canvas, rng, x0, y0, x1, y1, stripes: bool | None = None,
               rgb: RGB | None = None) -> RGB:
    rgb = jit(rng, rgb or PAL_GRASS[int(rng.integers(len(PAL_GRASS)))], 0.05)
    cv.rect(x0, y0, x1, y1, rgb, GRASS)
    if stripes is None:
        stripes = rng.random() < 0.5
    if stripes:
        # Mowing stripes: alternate bands a few percent brighter.
        w = uni(rng, 3.5, 7.0)
        light = scaled(rgb, uni(rng, 1.05, 1.1))
        if rng.random() < 0.5:
            for t in np.arange(x0, x1, 2 * w):
                cv.rect(t, y0, min(t + w, x1), y1, light)
        else:
            for t in np.arange(y0, y1, 2 * w):
                cv.rect(x0, t, x1, min(t + w, y1), light)
    return rgb


def scatter_trees(cv: Canvas, rng, x0, y0, x1, y1, n: int, clumps: bool = True) -> None:
    if x1 - x0 < 4 or y1 - y0 < 4:
        return
    while n > 0:
        cx, cy = uni(rng, x0 + 2, x1 - 2), uni(rng, y0 + 2, y1 - 2)
        k = int(rng.integers(3, 12)) if clumps else 1
        spread = uni(rng, 4, 9)
        rgb = PAL_TREE[int(rng.integers(len(PAL_TREE)))]
        for _ in range(min(k, n)):
            x, y = cx + rng.normal(0, spread), cy + rng.normal(0, spread)
            if x0 + 1 < x < x1 - 1 and y0 + 1 < y < y1 - 1:
                add_tree(cv, rng, x, y, rgb=rgb)
            n -= 1


def footpath(cv: Canvas, rng, x0, y0, x1, y1, width_m: float, rgb: RGB,
             cls: int = SIDEWALK) -> np.ndarray:
    """A curving footpath between two random points on opposite edges of the rectangle."""
    if rng.random() < 0.5:
        a, b = (x0, uni(rng, y0, y1)), (x1, uni(rng, y0, y1))
    else:
        a, b = (uni(rng, x0, x1), y0), (uni(rng, x0, x1), y1)
    mid = [(uni(rng, x0 + 0.2 * (x1 - x0), x1 - 0.2 * (x1 - x0)),
            uni(rng, y0 + 0.2 * (y1 - y0), y1 - 0.2 * (y1 - y0)))
           for _ in range(rng.integers(1, 3))]
    pts = smooth_path(np.array([a, *mid, b], float))
    cv.band(pts, width_m, rgb, cls)
    return pts


def draw_residential(cv: Canvas, rng, blk: Block) -> None:
    """Detached houses on lots facing the streets; deep blocks get a middle access lane with
    its own two rows of houses, so gardens stay garden-sized."""
    x0, y0, x1, y1 = blk.inner
    fr = BlockFrame(x0, y0, x1, y1, along_x=(x1 - x0) >= (y1 - y0))
    draw_grass(cv, rng, x0, y0, x1, y1, stripes=False)
    halves = [fr]
    if fr.depth > 84:
        lane_w = uni(rng, 5.0, 6.5)
        mid = fr.depth / 2
        lane = fr.rect(0, mid - lane_w / 2, fr.length, mid + lane_w / 2)
        cv.rect(*lane, jit(rng, PAL_ASPHALT, 0.04), ROAD)
        halves = [BlockFrame(*fr.rect(0, 0, fr.length, mid - lane_w / 2), along_x=fr.along_x),
                  BlockFrame(*fr.rect(0, mid + lane_w / 2, fr.length, fr.depth), along_x=fr.along_x)]
    for half in halves:
        lot_depth = min(half.depth / 2, uni(rng, 21, 31))
        if half.depth > 2 * lot_depth + 6:
            # A shared inner garden behind both rows of lots.
            gx0, gy0, gx1, gy1 = half.rect(0, lot_depth, half.length, half.depth - lot_depth)
            scatter_trees(cv, rng, gx0, gy0, gx1, gy1, int((gx1 - gx0) * (gy1 - gy0) / 70))
        for f in (half, half.flipped()):
            u = 0.0
            while u < f.length - 6:
                w = uni(rng, 11, 18)
                if f.length - (u + w) < 10:
                    w = f.length - u
                _house_lot(cv, rng, f, u, u + w, lot_depth)
                u += w


def _house_lot(cv: Canvas, rng, f: BlockFrame, u0: float, u1: float, depth: float) -> None:
    w = u1 - u0
    draw_grass(cv, rng, *f.rect(u0, 0, u1, depth), stripes=rng.random() < 0.3)
    hedge = (44, 72, 40)
    if rng.random() < 0.7:
        cv.band([f.pt(u0 + 0.4, 0.5), f.pt(u0 + 0.4, depth - 0.3)], uni(rng, 0.8, 1.6), hedge,
                TREE, 1.6)
    if rng.random() < 0.25:
        cv.band([f.pt(u0 + 0.5, 0.4), f.pt(u1 - 0.5, 0.4)], 0.8, hedge, TREE, 1.4)
    setback = uni(rng, 3, 6.5)
    hl = min(w - 3.0, uni(rng, 10, 17))
    hd = min(depth - setback - 4.5, uni(rng, 9, 14))
    if hl < 5 or hd < 5:
        scatter_trees(cv, rng, *f.rect(u0, 0, u1, depth), 2, clumps=False)
        return
    left = uni(rng, 1.0, w - hl - 1.0)
    hu0, hu1, hv0, hv1 = u0 + left, u0 + left + hl, setback, setback + hd
    pave = jit(rng, (176, 170, 160), 0.05)
    ang = f.v_angle()
    # Driveway to the street on whichever side of the house has room, sometimes with a car.
    for (da, db) in ((u0 + 0.6, hu0 - 0.3), (hu1 + 0.3, u1 - 0.6)):
        if db - da >= 3.0:
            dw = min(3.2, db - da)
            dx0 = db - dw if da < hu0 else da
            cv.rect(*f.rect(dx0, 0, dx0 + dw, hv0 + hd * 0.7), pave, SIDEWALK)
            if rng.random() < 0.5:
                cx, cy = f.pt(dx0 + dw / 2, uni(rng, 3.0, max(3.1, hv0 + hd * 0.7 - 2.6)))
                flip = math.pi if rng.random() < 0.5 else 0.0
                draw_car(cv, rng, cx, cy, ang + flip + rng.normal(0, 0.03))
            break
    back = depth - hv1
    if rng.random() < 0.5 and back > 4:
        cv.rect(*f.rect(hu0 + 0.5, hv1, hu1 - 0.5, hv1 + min(3.5, back - 1)), pave, PLAZA)
    if rng.random() < 0.18 and back > 11 and w > 10:
        pl, pw = uni(rng, 6, 10), uni(rng, 3.2, 4.5)
        pu = uni(rng, u0 + 1.5, max(u0 + 1.6, u1 - pl - 1.5))
        pv = uni(rng, hv1 + 4, depth - pw - 2)
        cv.rect(*f.rect(pu - 1, pv - 1, pu + pl + 1, pv + pw + 1), jit(rng, (200, 196, 186)),
                SIDEWALK)
        cv.rect(*f.rect(pu, pv, pu + pl, pv + pw), jit(rng, PAL_WATER_POOL, 0.04), WATER)
    if rng.random() < 0.3 and back > 6:
        su = u0 + 1 if rng.random() < 0.5 else u1 - 4
        sx0, sy0, sx1, sy1 = f.rect(su, depth - 4, su + 3, depth - 1)
        flat_building(cv, rng, sx0, sy0, sx1, sy1, 2.5, commercial=False)
    hx0, hy0, hx1, hy1 = f.rect(hu0, hv0, hu1, hv1)
    rgb = jit(rng, pick(rng, PAL_ROOF_PITCHED), 0.06)
    h = uni(rng, 6.5, 10)
    if rng.random() < 0.25 and back > 8:
        # L-shaped house: a wing towards the back garden, ridge perpendicular to the main one.
        wu = hu0 if rng.random() < 0.5 else hu1 - min(6.0, hl / 2)
        wx0, wy0, wx1, wy1 = f.rect(wu, hv1 - 1, wu + min(6.0, hl / 2), hv1 + min(7.0, back - 2))
        pitched_roof(cv, rng, wx0, wy0, wx1, wy1, h - 0.8, rgb,
                     ridge_along_x=(wx1 - wx0) < (wy1 - wy0))
    pitched_roof(cv, rng, hx0, hy0, hx1, hy1, h, rgb)
    for _ in range(int(rng.integers(1, 6))):
        tu, tv = uni(rng, u0 + 2, u1 - 2), uni(rng, hv1 + 2.5, max(hv1 + 2.6, depth - 2))
        add_tree(cv, rng, *f.pt(tu, tv), r_m=uni(rng, 2.6, 5.5))
    if rng.random() < 0.5:
        add_tree(cv, rng, *f.pt(uni(rng, u0 + 2, u1 - 2), uni(rng, 1.5, max(1.6, setback - 1))),
                 r_m=uni(rng, 1.8, 3.2))
    if rng.random() < 0.12 and back > 5:
        draw_person(cv, rng, *f.pt(uni(rng, u0 + 1, u1 - 1), uni(rng, hv1 + 2, depth - 1)))


def draw_apartments(cv: Canvas, rng, blk: Block) -> None:
    """A perimeter block: flat-roofed wings around a green courtyard (European style)."""
    x0, y0, x1, y1 = blk.inner
    d = uni(rng, 12, 18)
    if min(x1 - x0, y1 - y0) < 2 * d + 12:
        _plaza_ground(cv, rng, x0, y0, x1, y1)
        flat_building(cv, rng, x0 + 3, y0 + 3, x1 - 3, y1 - 3, uni(rng, 10, 25))
        return
    cx0, cy0, cx1, cy1 = x0 + d, y0 + d, x1 - d, y1 - d
    draw_grass(cv, rng, x0, y0, x1, y1)
    pave = jit(rng, (170, 166, 158))
    cv.band([(cx0 + 3, cy0 + 3), (cx1 - 3, cy0 + 3), (cx1 - 3, cy1 - 3), (cx0 + 3, cy1 - 3)],
            2.0, pave, SIDEWALK, closed=True)
    if rng.random() < 0.6:
        sx, sy = uni(rng, cx0 + 5, cx1 - 12), uni(rng, cy0 + 5, cy1 - 12)
        cv.rect(sx, sy, sx + uni(rng, 6, 10), sy + uni(rng, 6, 10), jit(rng, (196, 178, 140)),
                BARE_SOIL)
    if max(cx1 - cx0, cy1 - cy0) > 50:
        # Large courtyards are split by a cross wing (with a passage through it).
        h, rgb = uni(rng, 10, 20), pick(rng, PAL_ROOF_FLAT)
        if cx1 - cx0 > cy1 - cy0:
            m = (cx0 + cx1) / 2 + uni(rng, -8, 8)
            flat_building(cv, rng, m - d / 2, cy0, m + d / 2, (cy0 + cy1) / 2 - 2.5, h, rgb,
                          commercial=False)
            flat_building(cv, rng, m - d / 2, (cy0 + cy1) / 2 + 2.5, m + d / 2, cy1, h, rgb,
                          commercial=False)
        else:
            m = (cy0 + cy1) / 2 + uni(rng, -8, 8)
            flat_building(cv, rng, cx0, m - d / 2, (cx0 + cx1) / 2 - 2.5, m + d / 2, h, rgb,
                          commercial=False)
            flat_building(cv, rng, (cx0 + cx1) / 2 + 2.5, m - d / 2, cx1, m + d / 2, h, rgb,
                          commercial=False)
    scatter_trees(cv, rng, cx0 + 3, cy0 + 3, cx1 - 3, cy1 - 3,
                  int((cx1 - cx0) * (cy1 - cy0) / uni(rng, 60, 160)))
    people_in(cv, rng, cx0, cy0, cx1, cy1, int(rng.integers(0, 8)), {GRASS, SIDEWALK, BARE_SOIL})
    wings = [(x0, y0, x1, cy0), (x0, cy1, x1, y1), (x0, cy0, cx0, cy1), (cx1, cy0, x1, cy1)]
    gap_wing = int(rng.integers(0, 4)) if rng.random() < 0.5 else -1
    base_rgb = pick(rng, PAL_ROOF_FLAT)
    for n, (a0, b0, a1, b1) in enumerate(wings):
        along_x = (a1 - a0) >= (b1 - b0)
        length = (a1 - a0) if along_x else (b1 - b0)
        cuts = np.sort(uni(rng, 0, length, int(rng.integers(0, 3))))
        edges = [0.0, *cuts, length]
        for k in range(len(edges) - 1):
            s, e = edges[k], edges[k + 1]
            if n == gap_wing and k == 0 and e - s > 12:
                # A gateway through the block, paved.
                g = (s + e) / 2
                if along_x:
                    cv.rect(a0 + g - 2.5, b0, a0 + g + 2.5, b1, pave, SIDEWALK)
                    flat_building(cv, rng, a0 + s, b0, a0 + g - 2.5, b1, uni(rng, 12, 22),
                                  jit(rng, base_rgb, 0.04))
                    s = g + 2.5
                else:
                    cv.rect(a0, b0 + g - 2.5, a1, b0 + g + 2.5, pave, SIDEWALK)
                    flat_building(cv, rng, a0, b0 + s, a1, b0 + g - 2.5, uni(rng, 12, 22),
                                  jit(rng, base_rgb, 0.04))
                    s = g + 2.5
            if e - s < 2:
                continue
            h = uni(rng, 12, 24)
            rgb = jit(rng, base_rgb, 0.05)
            if along_x:
                flat_building(cv, rng, a0 + s, b0, a0 + e, b1, h, rgb, commercial=False)
            else:
                flat_building(cv, rng, a0, b0 + s, a1, b0 + e, h, rgb, commercial=False)


def _plaza_ground(cv: Canvas, rng, x0, y0, x1, y1) -> RGB:
    """Paving: a base colour with a grid of joints every few metres and some slab variation."""
    paving = [(186, 176, 160), (170, 168, 164), (196, 186, 170), (160, 150, 140)]
    rgb = jit(rng, paving[int(rng.integers(len(paving)))], 0.04)
    cv.rect(x0, y0, x1, y1, rgb, PLAZA)
    step = uni(rng, 3, 8)
    joint = scaled(rgb, 0.88)
    alt = scaled(rgb, uni(rng, 0.92, 1.06))
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


def draw_plaza(cv: Canvas, rng, blk: Block) -> None:
    x0, y0, x1, y1 = blk.inner
    rgb = _plaza_ground(cv, rng, x0, y0, x1, y1)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    span = min(x1 - x0, y1 - y0)
    if rng.random() < 0.55 and span > 30:
        r = uni(rng, 4, min(10, span / 5))
        cv.disc((cx, cy), r + 1.2, scaled(rgb, 1.08), PLAZA)
        cv.disc((cx, cy), r, jit(rng, (70, 110, 120), 0.05), WATER)
    elif rng.random() < 0.5 and span > 30:
        cv.disc((cx, cy), uni(rng, 6, span / 4), jit(rng, PAL_GRASS[0], 0.05), GRASS)
    # Tree rows in planters along the long edges, a kiosk, many people.
    step = uni(rng, 7, 11)
    along_x = (x1 - x0) >= (y1 - y0)
    for t in np.arange(x0 + 4 if along_x else y0 + 4, (x1 if along_x else y1) - 3, step):
        for off in (4.0, (y1 - y0 if along_x else x1 - x0) - 4.0):
            if rng.random() < 0.8:
                px, py = (t, y0 + off) if along_x else (x0 + off, t)
                cv.disc((px, py), 1.0, (90, 80, 66), BARE_SOIL)
                add_tree(cv, rng, px, py, r_m=uni(rng, 2.5, 4.0))
    if rng.random() < 0.5 and span > 25:
        kx, ky = uni(rng, x0 + 8, x1 - 14), uni(rng, y0 + 8, y1 - 12)
        flat_building(cv, rng, kx, ky, kx + uni(rng, 4, 8), ky + uni(rng, 3, 5), 3.5,
                      commercial=False)
    area = (x1 - x0) * (y1 - y0)
    people_in(cv, rng, x0, y0, x1, y1, int(area / uni(rng, 60, 160)), {PLAZA}, group_max=5)


def draw_commercial(cv: Canvas, rng, blk: Block) -> None:
    x0, y0, x1, y1 = blk.inner
    along_x = (x1 - x0) >= (y1 - y0)
    length = (x1 - x0) if along_x else (y1 - y0)
    parts = [0.0, length] if length < 60 else [0.0, uni(rng, 0.3, 0.7) * length, length]
    for a, b in zip(parts[:-1], parts[1:]):
        rx0, ry0, rx1, ry1 = (x0 + a, y0, x0 + b, y1) if along_x else (x0, y0 + a, x1, y0 + b)
        if rng.random() < 0.3 and len(parts) > 2:
            parking_lot(cv, rng, rx0, ry0, rx1, ry1)
            continue
        if rng.random() < 0.5:
            _plaza_ground(cv, rng, rx0, ry0, rx1, ry1)
            ground = {PLAZA}
        else:
            cv.rect(rx0, ry0, rx1, ry1, jit(rng, PAL_LOT_ASPHALT), PARKING_LOT)
            ground = {PARKING_LOT}
        m = [uni(rng, 2, 7) for _ in range(4)]
        flat_building(cv, rng, rx0 + m[0], ry0 + m[1], rx1 - m[2], ry1 - m[3], uni(rng, 6, 32))
        # Cars parked along the apron, people on the paving.
        if ground == {PARKING_LOT}:
            for _ in range(int(rng.integers(0, 8))):
                cx, cy = uni(rng, rx0 + 3, rx1 - 3), uni(rng, ry0 + 3, ry1 - 3)
                if cv.label_at(cx, cy) == PARKING_LOT:
                    draw_car(cv, rng, cx, cy, rng.choice([0, math.pi / 2]) + rng.normal(0, 0.05))
        people_in(cv, rng, rx0, ry0, rx1, ry1, int(rng.integers(0, 10)), ground)


def parking_lot(cv: Canvas, rng, x0, y0, x1, y1) -> None:
    """Painted double rows of perpendicular bays with aisles, cars in most bays, tree islands."""
    rgb = jit(rng, PAL_LOT_ASPHALT, 0.05)
    cv.rect(x0, y0, x1, y1, rgb, PARKING_LOT)
    fr = BlockFrame(x0, y0, x1, y1, along_x=(x1 - x0) >= (y1 - y0))
    bay_w, bay_d, aisle = uni(rng, 2.4, 2.7), 5.0, uni(rng, 6.0, 7.0)
    island = uni(rng, 2.0, 3.0) if rng.random() < 0.5 else 0.0
    occupancy = uni(rng, 0.5, 0.97)
    v = 1.5
    paint = mix(rgb, PAL_PAINT, 0.85)
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
                    draw_car(cv, rng, cx, cy,
                             ang_v + (0 if rng.random() < 0.7 else math.pi) + rng.normal(0, 0.04))
            if len(us):
                cv.band([fr.pt(us[-1] + bay_w, rv), fr.pt(us[-1] + bay_w, rv + bay_d)], 0.12,
                        paint, under=rgb)
        v += 2 * bay_d + aisle
        if island and v + island + 2 * bay_d + aisle <= fr.depth - 1.0:
            ix0, iy0, ix1, iy1 = fr.rect(1.5, v, fr.length - 1.5, v + island)
            draw_grass(cv, rng, ix0, iy0, ix1, iy1, stripes=False)
            for t in np.arange(5.0, fr.length - 4, uni(rng, 9, 14)):
                add_tree(cv, rng, *fr.pt(t, v + island / 2), r_m=uni(rng, 2.5, 4.0))
            v += island
        else:
            v += 0.6
    people_in(cv, rng, x0, y0, x1, y1, int(rng.integers(0, 5)), {PARKING_LOT}, group_max=2)


def draw_parking(cv: Canvas, rng, blk: Block) -> None:
    x0, y0, x1, y1 = blk.inner
    if rng.random() < 0.6:
        # Planted border around the lot.
        draw_grass(cv, rng, x0, y0, x1, y1, stripes=False)
        m = uni(rng, 2.5, 4.0)
        for t in np.arange(x0 + 3, x1 - 2, uni(rng, 8, 12)):
            for yy in (y0 + m / 2, y1 - m / 2):
                add_tree(cv, rng, t, yy, r_m=uni(rng, 2.2, 3.8))
        parking_lot(cv, rng, x0 + m, y0 + m, x1 - m, y1 - m)
    else:
        parking_lot(cv, rng, x0, y0, x1, y1)
