"""Pictures of worlds: a synthetic world beside its label map, any world's labels in colour, and
the camera's views of a world at several altitudes (`dovesei preview` draws them).

Reads worlds and renders camera views through `dovesei.sim`; nothing here is used by a service.
"""

from __future__ import annotations

import colorsys
import math
from pathlib import Path

import cv2
import numpy as np

from dovesei.sim.camera import CameraModel, render
from dovesei.sim.synthetic.classes import RGB
from dovesei.sim.synthetic.generate import (
    BARE_SOIL, CAR, GRASS, PARKING_LOT, PERSON, PLAZA, ROAD, ROOF_FLAT, ROOF_PITCHED, SIDEWALK, SPORTS_FIELD,
    SYNTHETIC_CLASSES, TREE, WATER, SyntheticParams, generate_city, safe_fraction,
)
from dovesei.sim.world import World


def synthetic_label_colours() -> dict[int, RGB]:
    """Display colours of the classes (for previews and plots), RGB."""
    return {ROOF_FLAT: (230, 60, 60), ROOF_PITCHED: (170, 20, 70), ROAD: (60, 60, 60),
            SIDEWALK: (150, 150, 150), PLAZA: (240, 220, 140), PARKING_LOT: (120, 160, 220),
            CAR: (255, 140, 0), GRASS: (120, 220, 80), SPORTS_FIELD: (40, 180, 150),
            TREE: (20, 100, 30), WATER: (30, 90, 230), BARE_SOIL: (170, 120, 70),
            PERSON: (255, 0, 255)}


def colourize_synthetic(labels: np.ndarray) -> np.ndarray:
    lut = np.zeros((256, 3), np.uint8)
    for cls, rgb in synthetic_label_colours().items():
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
    ci, cl = image[r0:r0 + crop, c0:c0 + crop], colourize_synthetic(labels[r0:r0 + crop, c0:c0 + crop])
    interp = cv2.INTER_AREA if crop > panel_px else cv2.INTER_NEAREST
    ci = cv2.resize(ci, (panel_px, panel_px), interpolation=interp)
    cl = cv2.resize(cl, (panel_px, panel_px), interpolation=cv2.INTER_NEAREST)
    for panel in (ci, cl):
        scale_bar(panel, crop * params.gsd_m / panel_px)
    legend = np.full((panel_px, 330, 3), 255, np.uint8)
    frac = safe_fraction(labels)
    lines = [f"{params.style}  seed {params.seed}  {params.size_m:g} m  {params.gsd_m:g} m/px",
             f"crop {crop_m:g} m x {crop_m:g} m", f"safe fraction {frac:.3f}", ""]
    for n, text in enumerate(lines):
        cv2.putText(legend, text, (10, 28 + 26 * n), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1,
                    cv2.LINE_AA)
    for n, (cls, (name, safe)) in enumerate(SYNTHETIC_CLASSES.items()):
        y = 28 + 26 * len(lines) + 30 * n
        cv2.rectangle(legend, (10, y - 16), (40, y + 6), synthetic_label_colours()[cls], -1)
        cv2.putText(legend, f"{cls:2d} {name} ({'safe' if safe else 'unsafe'})", (50, y),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    top = np.hstack([ci, cl, legend])
    ov_px = top.shape[1] // 2
    oi = cv2.resize(image, (ov_px, ov_px), interpolation=cv2.INTER_AREA)
    ol = cv2.resize(colourize_synthetic(labels), (ov_px, ov_px), interpolation=cv2.INTER_NEAREST)
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


def colourise_labels(world: World, labels: np.ndarray) -> np.ndarray:
    """An RGB picture of a label map: safe classes in greens, unsafe ones in other hues, outside black."""
    lut = np.zeros((256, 3), dtype=np.uint8)
    for cid, rgb in _class_colours(world).items():
        lut[cid] = rgb
    return lut[labels]


def _class_colours(world: World) -> dict[int, tuple[int, int, int]]:
    # Hues spread evenly within each group, so neighbouring classes stay tellable apart: safe
    # classes share the green band (a glance tells safe from not), unsafe ones get the rest.
    safe = sorted(c for c, info in world.classes.items() if info.safe)
    unsafe = sorted(c for c, info in world.classes.items() if not info.safe)
    colours = {}
    for group, (h0, h1) in ((safe, (0.17, 0.42)), (unsafe, (0.5, 1.08))):
        for i, cid in enumerate(group):
            hue = (h0 + (h1 - h0) * i / max(1, len(group))) % 1.0
            value = 0.95 if i % 2 == 0 else 0.7
            colours[cid] = tuple(int(255 * v) for v in colorsys.hsv_to_rgb(hue, 0.8, value))
    return colours


def render_views(world: World, x_m: float, y_m: float, path: str | Path,
                 alts_m: tuple[float, ...] = (100.0, 50.0, 20.0), yaw_rad: float = 0.0,
                 cam: CameraModel = CameraModel()) -> Path:
    """Write one PNG: the camera image (top row) and its label map (bottom row) per altitude."""
    gap = 8
    cols = []
    for alt_m in alts_m:
        image, labels, _ = render(world, x_m, y_m, alt_m, yaw_rad, cam)
        tile = image.copy()
        _caption(tile, f"{alt_m:.0f} m AGL  {2 * cam.half_width_m(alt_m):.0f} m wide")
        scale_bar(tile, 2 * cam.half_width_m(alt_m) / cam.width_px)
        parts = [tile]
        if labels is not None:
            lab = colourise_labels(world, labels)
            _caption(lab, "labels")
            parts += [np.full((gap, cam.width_px, 3), 255, np.uint8), lab]
        cols.append(np.vstack(parts))
        cols.append(np.full((cols[-1].shape[0], gap, 3), 255, np.uint8))
    body = np.hstack(cols[:-1])
    legend = _legend(world, body.shape[1])
    sheet = np.vstack([body, legend]) if legend is not None else body
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(sheet[:, :, ::-1])):
        raise OSError(f"could not write {path}")
    return path


def world_sheet(world: World, path: str | Path, panel_px: int = 900) -> Path:
    """Write world.png for a world folder: the image beside its colour-coded labels, a scale bar
    on each and the class legend under them (a label picture without its key says nothing)."""
    image = world.image_rgb
    scale = panel_px / max(image.shape[:2])
    size = (max(1, int(image.shape[1] * scale)), max(1, int(image.shape[0] * scale)))
    left = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    parts = [left]
    if world.labels is not None:
        parts += [np.full((size[1], 8, 3), 255, np.uint8),
                  cv2.resize(colourise_labels(world, world.labels), size, interpolation=cv2.INTER_NEAREST)]
    m_per_px = world.gsd_m / scale
    for panel in (parts[0], parts[-1]):
        scale_bar(panel, m_per_px)
    body = np.hstack(parts)
    legend = _legend(world, body.shape[1])
    sheet = np.vstack([body, legend]) if legend is not None else body
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(sheet[:, :, ::-1])):
        raise OSError(f"could not write {path}")
    return path


def scale_bar(img: np.ndarray, m_per_px: float, max_frac: float = 0.3) -> None:
    """A round-length scale bar in the lower left corner (in place; RGB)."""
    target_m = img.shape[1] * max_frac * m_per_px
    if not (target_m > 0 and math.isfinite(target_m)):
        return
    step = 10 ** math.floor(math.log10(target_m))
    length_m = max(m for m in (step, 2 * step, 5 * step) if m <= target_m)
    length_px = int(round(length_m / m_per_px))
    x0, y0 = 12, img.shape[0] - 14
    cv2.rectangle(img, (x0 - 6, y0 - 24), (x0 + length_px + 6, y0 + 8), (255, 255, 255), -1)
    cv2.rectangle(img, (x0, y0 - 3), (x0 + length_px, y0 + 3), (0, 0, 0), -1)
    text = f"{length_m:g} m" if length_m < 1000 else f"{length_m / 1000:g} km"
    cv2.putText(img, text, (x0, y0 - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)


def _caption(img: np.ndarray, text: str) -> None:
    cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)


def _legend(world: World, width_px: int) -> np.ndarray | None:
    if world.labels is None or not world.classes:
        return None
    per_row = max(1, width_px // 260)
    ids = sorted(world.classes)
    colours = _class_colours(world)
    rows = -(-len(ids) // per_row)
    legend = np.full((rows * 22 + 8, width_px, 3), 255, np.uint8)
    for i, cid in enumerate(ids):
        x0, y0 = (i % per_row) * 260 + 6, (i // per_row) * 22 + 6
        cv2.rectangle(legend, (x0, y0), (x0 + 16, y0 + 16), colours[cid], -1)
        info = world.classes[cid]
        text = f"{cid} {info.name[:26]}{'' if info.safe else ' (unsafe)'}"
        cv2.putText(legend, text, (x0 + 22, y0 + 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return legend
