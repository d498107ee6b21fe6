"""Finishing a synthetic world: shadows, textures, colour grading and the camera's blur.

Runs once after drawing: queued shadow casters become a shadow map, per-class noise at several
scales and a tint field give surfaces their texture, and one affine map per channel grades the
colours. Only the image changes: labels stay exactly as drawn.
"""

from __future__ import annotations

from dataclasses import field

import cv2
import numpy as np

from dovesei.sim.synthetic.canvas import Canvas, uni
from dovesei.sim.synthetic.classes import SHADOW_RGB, TEX_COARSE, TEX_GRAIN, TEX_MID, TEX_TINT


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


def finish_world(cv: Canvas, rng, gsd_m: float) -> None:
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
    lut_g, lut_m, lut_c = _lut(TEX_GRAIN, k), _lut(TEX_MID, k), _lut(TEX_COARSE, k)
    lut_tint = [_lut(TEX_TINT, 1.0, c) for c in range(3)]
    # Per-world colour grading (white balance, contrast, a touch of haze) folded into one
    # affine map per channel: out = in * scale_c + offset_c.
    gain = uni(rng, 0.95, 1.05, 3)
    haze = np.array([4.0, 6.0, 10.0]) * uni(rng, 0.5, 1.5)
    contrast = uni(rng, 0.95, 1.08)
    scale_c = gain * contrast
    offset_c = gain * 128 * (1 - contrast) + haze
    shade = (1.0 - SHADOW_RGB) / 255.0
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
