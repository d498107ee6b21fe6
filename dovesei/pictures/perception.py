"""Pictures of the simulated perception: a camera frame beside its heatmaps per profile.

`render_noise_preview(path, ...)` writes one PNG sheet: the frame (or its labels in stand-in
colours), P(safe) under `clean`, `realistic` and `harsh` (reference prompts and fusion), and two
consecutive `realistic` frames with the target mask of the reference's dynamic threshold, so a
reader sees what persists (misreadings anchored to the ground) and what flickers.

    labels + view --SimPerception (each profile)--> P(safe) --colour map--> panels --> PNG
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from dovesei.segmenter.appearance import appearance_mix
from dovesei.segmenter.fusion import FusionConfig
from dovesei.segmenter.prompts import REFERENCE_PROMPTS
from dovesei.segmenter.simulated import PROFILE_NAMES, SimPerception, View, demo_labels, profile_params
from dovesei.shared import footprint

# Stand-in colours (RGB) of the appearances, for a frame panel without a camera image.
_APPEARANCE_RGB = {
    "lawn": (110, 150, 70), "sports_field": (90, 165, 80), "bare_ground": (170, 140, 95), "paved": (185, 180, 170),
    "parking": (105, 105, 110), "road": (70, 70, 75), "flat_roof": (150, 150, 145), "pitched_roof": (160, 80, 60),
    "tree": (40, 90, 40), "water": (40, 70, 90), "vehicle": (200, 200, 40), "person": (220, 40, 40),
    "shadow": (30, 30, 30), "clutter": (128, 0, 128), "off_world": (0, 0, 0),
}
_REFERENCE_FUSION = FusionConfig(mode="dovesei")


def _names(classes: Mapping[int, object]) -> dict[int, str]:
    return {int(k): (v if isinstance(v, str) else v[0]) for k, v in classes.items()}  # type: ignore[index]


def stand_in_rgb(labels: np.ndarray, classes: Mapping[int, object]) -> np.ndarray:
    """Labels coloured by appearance (the dominant one of each class)."""
    lut = np.zeros((256, 3), np.uint8)
    lut[:] = _APPEARANCE_RGB["clutter"]
    for cid, name in _names(classes).items():
        mix = appearance_mix(name)
        lut[cid] = _APPEARANCE_RGB[max(mix, key=mix.get)]
    lut[255] = _APPEARANCE_RGB["off_world"]
    return lut[labels]


def heat_rgb(prob: np.ndarray) -> np.ndarray:
    """P(safe) as RGB: red 0, yellow 0.5, green 1."""
    t = np.linspace(0.0, 1.0, 256)
    lut = np.stack([np.clip(2.0 - 2.0 * t, 0, 1), np.clip(2.0 * t, 0, 1), np.zeros_like(t)], axis=1)
    return (lut[np.round(np.clip(prob, 0, 1) * 255).astype(np.uint8)] * 230).astype(np.uint8)


def _titled(rgb: np.ndarray, title: str) -> np.ndarray:
    bar = np.full((24, rgb.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(bar, title, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, rgb])


def _threshold_mask(prob: np.ndarray) -> np.ndarray:
    """The reference's dynamic threshold (best ~10 % of pixels), as in perception-stats."""
    from dovesei.controller.policies.dovesei.policy import DoveseiConfig, dynamic_threshold

    res = dynamic_threshold(prob, DoveseiConfig())
    return np.zeros(prob.shape, bool) if res.mask_u8 is None else res.mask_u8 > 0


def render_noise_preview(path: str | Path, labels: np.ndarray | None = None,
                         classes: Mapping[int, object] | None = None, seed: int = 0,
                         image_rgb: np.ndarray | None = None, view: View | None = None) -> Path:
    """Write the PNG sheet (see the module docstring); default scene: a hand-drawn block.

    ``classes`` maps id -> name or (name, safe); only names are used. ``view`` defaults to a
    nadir view at 100 m over the world origin with the 73 deg camera.
    """
    if labels is None:
        labels, classes = demo_labels()
    elif classes is None:
        raise ValueError("render_noise_preview: labels given without their classes")
    names = _names(classes)
    view = view or View((0.0, 0.0), 100.0, footprint.REFERENCE_HFOV_RAD)
    if image_rgb is None:
        frame, frame_title = stand_in_rgb(labels, names), "labels (stand-in colours)"
    else:
        if image_rgb.shape != labels.shape + (3,):
            raise ValueError(f"image_rgb shape {image_rgb.shape} does not match labels {labels.shape}")
        frame, frame_title = image_rgb, f"camera frame, {view.alt_agl_m:.0f} m"
    panels = [_titled(frame, frame_title)]
    for profile in PROFILE_NAMES:
        prob = SimPerception(profile_params(profile), seed=seed).safe_probability(
            labels, names, view, 0, REFERENCE_PROMPTS, _REFERENCE_FUSION)
        panels.append(_titled(heat_rgb(prob), f"{profile}: P(safe), softmax (red 0 .. green 1)"))
    realistic = SimPerception(profile_params("realistic"), seed=seed)
    for seq in (1, 2):
        prob = realistic.safe_probability(labels, names, view, seq, REFERENCE_PROMPTS, _REFERENCE_FUSION)
        rgb = heat_rgb(prob)
        rgb[_threshold_mask(prob)] = (40, 90, 255)
        panels.append(_titled(rgb, f"realistic frame {seq}: blue = best 10 % (dyn. threshold)"))
    gap = np.full((panels[0].shape[0], 6, 3), 255, dtype=np.uint8)
    rows = [np.hstack([panels[i], gap, panels[i + 1], gap, panels[i + 2]]) for i in (0, 3)]
    sheet = np.vstack([rows[0], np.full((6, rows[0].shape[1], 3), 255, np.uint8), rows[1]])
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write preview PNG {out}")
    return out


__all__ = ["heat_rgb", "render_noise_preview", "stand_in_rgb"]
