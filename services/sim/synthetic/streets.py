"""Streets of the synthetic city: sidewalk rings, carriageway markings, traffic, street life, the river.

Sidewalks are drawn with each block; the carriageway is the background. Markings, crossings,
kerbside parking, traffic and street trees are drawn per road segment between two junctions.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from dovesei.sim.synthetic.blocks import draw_grass
from dovesei.sim.synthetic.canvas import Canvas, jit, rounded_rect, scaled, SHIFT, uni
from dovesei.sim.synthetic.classes import (
    BARE_SOIL, GRASS, PAL_ASPHALT, PAL_GRASS, PAL_PAINT, PAL_SIDEWALK, PAL_TREE, PAL_WATER_RIVER, ROAD,
    SIDEWALK, WATER,
)
from dovesei.sim.synthetic.layout import Block, River, Road
from dovesei.sim.synthetic.objects import add_tree, draw_car, draw_person


def draw_sidewalk(cv: Canvas, rng, blk: Block) -> None:
    ring = rounded_rect(blk.x0, blk.y0, blk.x1, blk.y1, uni(rng, 2, 6))
    rgb = jit(rng, PAL_SIDEWALK, 0.05)
    cv.poly(ring, rgb, SIDEWALK)
    # Kerb stone: a light line at the road edge.
    cv.band(ring, 0.2, scaled(rgb, 1.15), closed=True, under=rgb)


def draw_segment(cv: Canvas, rng, road: Road, a0: float, a1: float, vertical: bool) -> None:
    """Markings and traffic of one road between two junctions; a runs along the road."""
    c, w = road.centre_m, road.width_m

    def p(a, b):  # b across the road, from its centre
        return (c + b, a) if vertical else (a, c + b)

    base = PAL_ASPHALT
    paint = PAL_PAINT
    length = a1 - a0
    if length < 8:
        return
    dash, gap = 3.0, 6.0
    if road.avenue:
        med = uni(rng, 2.5, 4.0)
        mx0, my0 = p(a0 + 5, -med / 2)
        mx1, my1 = p(a1 - 5, med / 2)
        draw_grass(cv, rng, min(mx0, mx1), min(my0, my1), max(mx0, mx1), max(my0, my1), stripes=False)
        cv.band([p(a0 + 5, -med / 2), p(a1 - 5, -med / 2), p(a1 - 5, med / 2), p(a0 + 5, med / 2)],
                0.25, (190, 188, 182), closed=True)
        if rng.random() < 0.7:
            for t in np.arange(a0 + 9, a1 - 6, uni(rng, 8, 12)):
                add_tree(cv, rng, *p(t, 0), r_m=uni(rng, 2.5, 4.0))
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
            occupancy = uni(rng, 0.3, 0.9)
            for sgn in (-1, 1):
                b = sgn * (w / 2 - 1.1)
                for t in np.arange(a0 + 6, a1 - 8, uni(rng, 5.8, 6.6)):
                    if rng.random() < occupancy:
                        ang = (math.pi / 2 if vertical else 0.0) + (math.pi if sgn < 0 else 0)
                        ang += rng.normal(0, 0.02)
                        draw_car(cv, rng, *p(t + 2.5, b + rng.normal(0, 0.1)), ang)
    # Zebra crossings at the junction ends, stripes parallel to the road.
    for end, sgn in ((a0, 1), (a1, -1)):
        if rng.random() < 0.55:
            for b in np.arange(-w / 2 + 0.6, w / 2 - 0.6, 1.0):
                cv.poly([p(end + sgn * 1.0, b), p(end + sgn * 4.0, b), p(end + sgn * 4.0, b + 0.5),
                         p(end + sgn * 1.0, b + 0.5)], paint)
    # Moving traffic: right-hand driving, heading set by the lane side.
    for b in lanes_b:
        for t in np.arange(a0 + 10, a1 - 10, uni(rng, 25, 90)):
            if rng.random() < 0.35:
                # +a is +y on a vertical road (its right-hand side is -x) and +x on a
                # horizontal one (right-hand side +y).
                forward = (b < 0) if vertical else (b > 0)
                ang = (math.pi / 2 if vertical else 0.0) + (0.0 if forward else math.pi)
                truck = rng.random() < 0.08
                draw_car(cv, rng, *p(t, b + rng.normal(0, 0.15)), ang + rng.normal(0, 0.01),
                         rgb=(236, 236, 232) if truck else None,
                         length_m=uni(rng, 6.5, 9) if truck else None)


def draw_street_life(cv: Canvas, rng, blk: Block) -> None:
    """Street trees and pedestrians on a block's sidewalk ring."""
    s = blk.sidewalk_m
    h = s / 2  # walk along the middle of the sidewalk
    x0, y0, x1, y1 = blk.x0, blk.y0, blk.x1, blk.y1
    sides = [((x0, y0 + h), (x1, y0 + h)), ((x0, y1 - h), (x1, y1 - h)),
             ((x0 + h, y0), (x0 + h, y1)), ((x1 - h, y0), (x1 - h, y1))]
    trees = rng.random() < 0.55
    rgb = PAL_TREE[int(rng.integers(len(PAL_TREE)))]
    r = uni(rng, 2.5, 4.5)
    for (ax, ay), (bx, by) in sides:
        length = math.hypot(bx - ax, by - ay)
        ux, uy = (bx - ax) / length, (by - ay) / length
        if trees and s >= 2.5:
            for t in np.arange(8.0, length - 7, uni(rng, 8, 12)):
                add_tree(cv, rng, ax + ux * t, ay + uy * t, r_m=r * uni(rng, 0.85, 1.15), rgb=rgb)
        for t in uni(rng, 3, length - 3, int(rng.poisson(length / 45))):
            x, y = ax + ux * t, ay + uy * t
            if cv.label_at(x, y) == SIDEWALK:
                draw_person(cv, rng, x + rng.normal(0, s / 6), y + rng.normal(0, s / 6))


def draw_river(cv: Canvas, rng, river: River, xr: list[Road], yr: list[Road]) -> None:
    pts = river.pts_m
    outer = river.width_m + 2 * river.bank_m
    cv.band(pts, outer, jit(rng, PAL_GRASS[0]), GRASS)
    cv.band(pts, river.width_m + 3.0, jit(rng, (124, 112, 88)), BARE_SOIL)
    cv.band(pts, river.width_m, jit(rng, PAL_WATER_RIVER, 0.04), WATER)
    # Bridges: every road whose centreline crosses the river band gets a deck over it.
    mask = np.zeros((cv.side_px, cv.side_px), np.uint8)
    cv2.polylines(mask, [cv.px(pts)], False, 1, cv._thick(outer + 2), cv2.LINE_8, SHIFT)
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
                cv.poly(deck, PAL_SIDEWALK, SIDEWALK, 6.0)
                if vertical:
                    inner = (c - hw + 2.5, a0, c + hw - 2.5, a1)
                else:
                    inner = (a0, c - hw + 2.5, a1, c + hw - 2.5)
                cv.rect(*inner, PAL_ASPHALT, ROAD, 6.0)
                cv.band(deck, 0.4, (200, 198, 192), closed=True)
