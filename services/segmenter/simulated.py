"""The simulated perception's public face: profiles, defaults and the frame adapter's helpers.

The simulated perception is a TEST INSTRUMENT, never a perception system: it turns the sim's
ground-truth label image into CLIPSeg-like prompt logits (`sim_backend.py`, with the class-name
appearances of `appearance.py` and the prompt response table of `responses.py`), and the
segmenter's own fusion makes P(safe) from them, as after CLIPSeg. It never reads which classes
the judge counts safe. Frames without truth labels (a real camera) are refused with
`MissingTruthError`.

What other modules use (one owner of the perception defaults):

- `PROFILES` (`clean`, `realistic`, `harsh`), `DEFAULT_PROFILE` (`realistic`) and
  `profile_params(name, noise)` -> `PerceptionParams`;
- `DEFAULT_NOISE` (1.0: each profile is calibrated at noise 1; ``noise`` scales its errors);
- `SimulatedBackend` (= `SimPerception`) and `view_of(frame)`, the `View` of a camera frame.

Pictures of it live in `dovesei.pictures.perception`; its statistics against real CLIPSeg's in
`dovesei perception-stats`.
"""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np

from dovesei.shared import footprint
from dovesei.shared.errors import DoveseiError
from dovesei.shared.messages import CameraFrame, CropFrame

from .prompts import REFERENCE_PROMPTS
from .sim_backend import DEFAULT_PROFILE, PROFILES, PerceptionParams, SimPerception, View, profile_params

DEFAULT_NOISE = 1.0
# The noise at which the profiles are calibrated; kept under this name for callers of release 1.
CALIBRATED_NOISE = DEFAULT_NOISE
PROFILE_NAMES: tuple[str, ...] = tuple(PROFILES)
SimulatedBackend = SimPerception
SimPerceptionParams = PerceptionParams


class MissingTruthError(DoveseiError, ValueError):
    """A frame without the sim's ground-truth labels reached the simulated backend."""

    def __init__(self) -> None:
        super().__init__(
            "simulated perception needs the sim's ground-truth labels; this frame has none (a real camera?)"
        )


def view_of(frame: CameraFrame) -> View:
    """Where a frame's camera looked (the ground point comes with the sim's truth, if any)."""
    centre = frame.truth.centre_world_m if frame.truth is not None else None
    world = frame.truth.world if frame.truth is not None else ""
    return View(centre, float(frame.alt_agl_m), float(frame.hfov_rad), float(frame.yaw_rad), world,
                float(frame.stamp.t_s))


# A crop is read as the frame of a nadir camera with the frames' field of view (the sim camera's
# 73 deg) that sees just its square, not as seen from the vehicle's altitude: the misreadings
# that follow the scale of the view (the confusion fields over log-altitude) follow the square's
# size. The same square cut at 22 m or at 40 m is the same 352 px image (both oversampled from a
# full-resolution frame), so CLIPSeg reads it alike; read at the vehicle's altitude, looks at one
# square from two heights had missed someone independently, which flattered every descent's
# repeated looks.
CROP_VIEW_HFOV_RAD = footprint.REFERENCE_HFOV_RAD


def crop_view_of(crop: CropFrame) -> View:
    """The `View` a crop is read with: its square's centre and heading, at the altitude whose
    footprint under CROP_VIEW_HFOV_RAD is the square."""
    alt_m = float(crop.side_m) / footprint.width_m(1.0, CROP_VIEW_HFOV_RAD)
    return dataclasses.replace(view_of(crop), alt_agl_m=alt_m, hfov_rad=CROP_VIEW_HFOV_RAD)


def demo_labels(size_px: int = 352) -> tuple[np.ndarray, dict[int, str]]:
    """A small hand-drawn block at ~100 m (lawn, road, roofs, cars, a pond) and its class names."""
    names = {1: "roof_flat", 2: "roof_pitched", 3: "road", 4: "sidewalk", 6: "parking_lot", 7: "car", 8: "grass",
             10: "tree", 11: "water", 12: "bare_soil"}
    lab = np.full((352, 352), 4, np.uint8)
    cv2.rectangle(lab, (0, 150), (351, 174), 3, -1)
    cv2.rectangle(lab, (6, 6), (192, 142), 8, -1)
    cv2.ellipse(lab, (70, 60), (34, 22), 15, 0, 360, 11, -1)
    cv2.circle(lab, (150, 45), 12, 10, -1)
    cv2.rectangle(lab, (232, 6), (345, 142), 1, -1)
    cv2.rectangle(lab, (6, 182), (192, 345), 6, -1)
    for col in range(12, 180, 14):
        cv2.rectangle(lab, (col, 200), (col + 5, 210), 7, -1)
    cv2.rectangle(lab, (232, 182), (345, 345), 2, -1)
    cv2.rectangle(lab, (100, 280), (180, 340), 12, -1)
    if size_px != 352:
        lab = cv2.resize(lab, (size_px, size_px), interpolation=cv2.INTER_NEAREST)
    return lab, names


def bench_hz(n: int = 100, profile: str = DEFAULT_PROFILE) -> float:
    """Heatmaps per wall-clock second at 352x352 (reference prompts, grouped fusion) on one OpenCV thread."""
    return bench_rates(n, profile)["wall_hz"]


def bench_rates(n: int = 100, profile: str = DEFAULT_PROFILE) -> dict[str, float]:
    """Heatmaps per second at 352x352 on one OpenCV thread: per wall-clock second (`wall_hz`) and
    per CPU second of this process (`cpu_hz`, what one core does however busy the machine is)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    labels, names = demo_labels()
    perception = SimPerception(profile_params(profile), seed=0)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # per core: the controller and the sim share the machine
    try:
        view = View((500.0, 500.0), 100.0, footprint.REFERENCE_HFOV_RAD)
        perception.safe_probability(labels, names, view, 0, REFERENCE_PROMPTS)  # warm the caches
        t0, c0 = time.perf_counter(), time.process_time()
        for seq in range(n):
            perception.safe_probability(labels, names, view, 1 + seq, REFERENCE_PROMPTS)
        elapsed_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    finally:
        cv2.setNumThreads(threads)
    return {"wall_hz": n / elapsed_s, "cpu_hz": n / max(cpu_s, 1e-9)}


__all__ = [
    "CALIBRATED_NOISE", "DEFAULT_NOISE", "DEFAULT_PROFILE", "MissingTruthError", "PROFILES", "PROFILE_NAMES",
    "PerceptionParams", "SimPerception", "SimPerceptionParams", "SimulatedBackend", "View", "bench_hz", "bench_rates",
    "demo_labels", "profile_params", "view_of",
]
