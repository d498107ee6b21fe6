"""Objects of the synthetic worlds: cars, people, trees and buildings (pitched and flat roofs)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from dovesei.sim.synthetic.canvas import Canvas, jit, obb, pick, scaled, SHIFT, Tree, uni
from dovesei.sim.synthetic.classes import (
    CAR, PAL_CAR, PAL_CLOTHES, PAL_ROOF_FLAT, PAL_TREE, PERSON, RGB, ROOF_FLAT, ROOF_PITCHED, TREE,
)
from dovesei.sim.objects import PERSON as OBJ_PERSON, VEHICLE


def _lambert(cv: Canvas, out_xy: tuple[float, float], pitch_rad: float) -> float:
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


def draw_car(cv: Canvas, rng, cx: float, cy: float, ang_rad: float, rgb: RGB | None = None,
             length_m: float | None = None) -> None:
    """A car (or, when `length_m` > 5.5 m, a van / truck) with windows and a shadow."""
    length = length_m or uni(rng, 4.1, 4.9)
    van = length > 5.5
    width = 2.2 if van else uni(rng, 1.72, 1.9)
    rgb = jit(rng, rgb or pick(rng, PAL_CAR), 0.04)
    ca, sa = math.cos(ang_rad), math.sin(ang_rad)
    local = (_VAN_SHAPES if van else _CAR_SHAPES) * (length / 2, width / 2)
    px = cv.px(local @ np.array([[ca, sa], [-sa, ca]]) + (cx, cy))
    body = px[:8]
    cv.cast_px(body, 1.5)
    cv2.fillPoly(cv.img, [body], rgb, cv2.LINE_8, SHIFT)
    cv2.fillPoly(cv.lab, [body], CAR, cv2.LINE_8, SHIFT)
    cv2.fillPoly(cv.height_u, [body], cv._hu(1.5), cv2.LINE_8, SHIFT)
    cv2.fillConvexPoly(cv.img, px[8:12], _GLASS, cv2.LINE_8, SHIFT)
    cv.objects.append((VEHICLE, cx, cy, ang_rad, length, width, rgb))
    if not van:
        cv2.fillConvexPoly(cv.img, px[12:16], _GLASS, cv2.LINE_8, SHIFT)
        cv2.fillConvexPoly(cv.img, px[16:20], scaled(rgb, 1.08), cv2.LINE_8, SHIFT)


def draw_person(cv: Canvas, rng, x: float, y: float) -> None:
    """A person seen from above: ~0.45-0.6 m across, with a long thin shadow."""
    r = uni(rng, 0.22, 0.3)
    cv.cast_disc((x, y), 0.15, 1.7)
    rgb = jit(rng, PAL_CLOTHES[int(rng.integers(len(PAL_CLOTHES)))], 0.08)
    cv.disc((x, y), r, rgb, PERSON, 1.7)
    cv.objects.append((OBJ_PERSON, x, y, 0.0, 2 * r, 2 * r, rgb))


def people_in(cv: Canvas, rng, x0, y0, x1, y1, n: int, allowed: set[int],
              group_max: int = 4) -> None:
    """Scatter `n` people in groups over the rectangle, only where the ground is `allowed`."""
    placed = 0
    tries = 0
    while placed < n and tries < 4 * n + 10:
        tries += 1
        gx, gy = uni(rng, x0, x1), uni(rng, y0, y1)
        for _ in range(int(rng.integers(1, group_max + 1))):
            x, y = gx + rng.normal(0, 0.8), gy + rng.normal(0, 0.8)
            if cv.label_at(x, y) in allowed:
                draw_person(cv, rng, x, y)
                placed += 1


def add_tree(cv: Canvas, rng, x: float, y: float, r_m: float | None = None,
             h_m: float | None = None, rgb: RGB | None = None) -> None:
    r = r_m or uni(rng, 2.2, 5.0)
    h = h_m or float(np.clip(r * uni(rng, 1.6, 2.6), 3.0, 22.0))
    cv.trees.append(Tree(x, y, r, h, jit(rng, rgb or PAL_TREE[int(rng.integers(len(PAL_TREE)))], 0.07)))


def draw_tree(cv: Canvas, rng, t: Tree) -> None:
    """A clumpy crown: a dark core, lobes lit according to the sun side, a highlight."""
    cv.cast_crown((t.x_m, t.y_m), t.r_m, t.h_m)
    cv.disc((t.x_m, t.y_m), t.r_m * 0.8, scaled(t.rgb, 0.75), TREE, t.h_m)
    n = 3 if t.r_m < 3 else 4
    for _ in range(n):
        a = 2 * math.pi * rng.random()
        d = (0.25 + 0.25 * rng.random()) * t.r_m
        lit = math.cos(a) * cv.sun_xy[0] + math.sin(a) * cv.sun_xy[1]
        cv.disc((t.x_m + d * math.cos(a), t.y_m + d * math.sin(a)),
                (0.45 + 0.15 * rng.random()) * t.r_m,
                scaled(t.rgb, 0.85 + 0.22 * lit), TREE, t.h_m)
    hx, hy = t.x_m + cv.sun_xy[0] * 0.35 * t.r_m, t.y_m + cv.sun_xy[1] * 0.35 * t.r_m
    cv.disc((hx, hy), 0.3 * t.r_m, scaled(t.rgb, 1.25))


def pitched_roof(cv: Canvas, rng, x0, y0, x1, y1, h_m: float, rgb: RGB,
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
    pitch = math.radians(uni(rng, 28, 42))
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
        cv.poly([w(a, b) for a, b in pts], scaled(rgb, k))
        lit_faces.append((k, pts, out))
    dark, light = scaled(rgb, 0.7), scaled(rgb, 1.2)
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
        ca, cb = uni(rng, a0 + 1, a1 - 1), uni(rng, b0 + 1, b1 - 1)
        cx, cy = w(ca, cb)
        sq = obb(cx, cy, 0.8, 0.8, 0.0)
        cv.cast(sq, h_m + 1.0, base_m=h_m - 1.5)
        cv.poly(sq, jit(rng, (120, 74, 60)), ROOF_PITCHED, h_m + 1.0)
    for _ in range(int(rng.integers(0, 3))):
        ca, cb = uni(rng, a0 + 1.5, a1 - 1.5), uni(rng, b0 + 1.2, b1 - 1.2)
        cv.poly(obb(*w(ca, cb), 1.0, 0.8, 0.0), (60, 66, 78))


def flat_building(cv: Canvas, rng, x0, y0, x1, y1, h_m: float, rgb: RGB | None = None,
                  commercial: bool = True) -> None:
    """A flat roof with a parapet, roof sections, plant boxes, vents, skylights or panels."""
    if x1 - x0 < 2 or y1 - y0 < 2:
        return
    rgb = jit(rng, rgb or pick(rng, PAL_ROOF_FLAT), 0.05)
    foot = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    cv.cast(foot, h_m)
    cv.poly(foot, rgb, ROOF_FLAT, h_m)
    area = (x1 - x0) * (y1 - y0)
    if rng.random() < 0.35 and min(x1 - x0, y1 - y0) > 10:
        m = uni(rng, 1.5, 4)
        cv.rect(x0 + m, y0 + m, x1 - m, y1 - m, jit(rng, rgb, 0.05))
    if commercial and rng.random() < 0.25 and min(x1 - x0, y1 - y0) > 16:
        # Rows of skylights (pale, bluish) across the long side.
        along_x = (x1 - x0) >= (y1 - y0)
        sky = (176, 190, 200)
        for t in np.arange(4.0, ((x1 - x0) if along_x else (y1 - y0)) - 3, uni(rng, 5, 8)):
            if along_x:
                cv.rect(x0 + t, y0 + 3, x0 + t + 1.2, y1 - 3, sky)
            else:
                cv.rect(x0 + 3, y0 + t, x1 - 3, y0 + t + 1.2, sky)
    elif rng.random() < 0.1 and area > 200:
        # Rows of solar panels over part of the roof.
        pan = (36, 46, 72)
        px1 = x0 + (x1 - x0) * uni(rng, 0.4, 1.0)
        for yy in np.arange(y0 + 2, y0 + (y1 - y0) * uni(rng, 0.5, 1.0) - 3, 2.6):
            cv.rect(x0 + 2, yy, px1 - 2, yy + 1.8, pan)
    cv.band(foot, 0.5, scaled(rgb, 1.18), closed=True)
    if area > 250 and rng.random() < 0.6:
        bw, bh = uni(rng, 3, 7), uni(rng, 3, 5)
        bx = uni(rng, x0 + 2, max(x0 + 2.1, x1 - bw - 2))
        by = uni(rng, y0 + 2, max(y0 + 2.1, y1 - bh - 2))
        box = [(bx, by), (bx + bw, by), (bx + bw, by + bh), (bx, by + bh)]
        cv.cast(box, h_m + 3.0, base_m=h_m)
        cv.poly(box, scaled(rgb, 1.1), ROOF_FLAT, h_m + 3.0)
    n_ac = min(40, int(area / 150 * uni(rng, 0.2, 1.6)))
    for _ in range(n_ac):
        aw, ah = uni(rng, 1.0, 3.0), uni(rng, 1.0, 2.2)
        if x1 - x0 < aw + 2.5 or y1 - y0 < ah + 2.5:
            break
        ax, ay = uni(rng, x0 + 1.2, x1 - aw - 1.2), uni(rng, y0 + 1.2, y1 - ah - 1.2)
        box = [(ax, ay), (ax + aw, ay), (ax + aw, ay + ah), (ax, ay + ah)]
        cv.cast(box, h_m + 1.4, base_m=h_m)
        grey = int(uni(rng, 185, 228))
        cv.poly(box, (grey, grey, grey - 3), ROOF_FLAT, h_m + 1.4)
        if rng.random() < 0.5:
            cv.disc((ax + aw / 2, ay + ah / 2), min(aw, ah) * 0.32, (70, 72, 74))
    for _ in range(int(area / 400 * uni(rng, 0, 2))):
        cv.disc((uni(rng, x0 + 1, x1 - 1), uni(rng, y0 + 1, y1 - 1)), 0.35, (58, 58, 60))
