"""The episode video: camera | heatmap side by side, with the controller's focus circle, target,
state and altitude (mp4v, MJPG .avi fallback). Needs only OpenCV.

    [VideoFrame] --write_video--> episode.mp4
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dovesei.pictures.common import ReportError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoFrame:
    """One video frame's data: the camera image, its heatmap and what the controller did with it.

    `target_px` and `focus_radius_px` are in the heatmap's pixels (the controller status' units);
    the focus circle is centred on the image centre, as the dynamic-focus mask is.
    """

    t_s: float
    image_rgb: np.ndarray  # (H, W, 3) uint8
    prob_safe: np.ndarray | None  # (h, w) float in [0, 1]; None when no heatmap was recorded
    alt_agl_m: float
    state: str = ""
    watchdog: str = "ok"
    focus_radius_px: float = 0.0
    target_px: tuple[float, float] | None = None
    perception: str = ""  # e.g. "simulated perception (noise 0)": a simulated run says so on screen


def _safety_lut() -> np.ndarray:
    """256 BGR colours from red (P = 0, unsafe) through yellow to green (P = 1, safe)."""
    p = np.linspace(0.0, 1.0, 256)
    red = np.clip(2.0 - 2.0 * p, 0.0, 1.0)
    green = np.clip(2.0 * p, 0.0, 1.0)
    return (np.stack([np.zeros_like(p), green, red], axis=1) * 255.0).astype(np.uint8)


_LUT_BGR = _safety_lut()


def _compose(frame: VideoFrame, side_px: int) -> np.ndarray:
    """camera | heatmap side by side (BGR), with focus circle, target and a text bar."""
    cam = cv2.resize(cv2.cvtColor(np.ascontiguousarray(frame.image_rgb), cv2.COLOR_RGB2BGR), (side_px, side_px),
                     interpolation=cv2.INTER_AREA)
    if frame.prob_safe is not None:
        prob = np.asarray(frame.prob_safe, dtype=np.float32)
        hm_h, hm_w = prob.shape
        idx = np.clip(prob * 255.0 + 0.5, 0, 255).astype(np.uint8)
        heat = cv2.resize(_LUT_BGR[idx], (side_px, side_px), interpolation=cv2.INTER_NEAREST)
    else:
        hm_h, hm_w = frame.image_rgb.shape[:2]
        heat = np.full((side_px, side_px, 3), 40, np.uint8)
        cv2.putText(heat, "no heatmap", (side_px // 4, side_px // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                    (200, 200, 200), 1, cv2.LINE_AA)
    sy, sx = side_px / hm_h, side_px / hm_w
    for panel in (cam, heat):
        if frame.focus_radius_px > 0:
            # The dynamic-focus circle; when it covers the whole image it is clipped to the frame.
            radius = int(round(frame.focus_radius_px * sx))
            cv2.circle(panel, (side_px // 2, side_px // 2), radius, (255, 255, 0), 2, cv2.LINE_AA)
        if frame.target_px is not None:
            row, col = frame.target_px
            centre = (int(round((col + 0.5) * sx)), int(round((row + 0.5) * sy)))
            cv2.drawMarker(panel, centre, (255, 0, 255), cv2.MARKER_TILTED_CROSS, 18, 3, cv2.LINE_AA)
    bar = np.zeros((34, 2 * side_px, 3), np.uint8)
    text = f"t {frame.t_s:7.2f} s   alt {frame.alt_agl_m:6.1f} m   {frame.state or '-'}"
    if frame.watchdog and frame.watchdog != "ok":
        text += f"   WATCHDOG {frame.watchdog.upper()}"
    cv2.putText(bar, text, (8, 23), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    if frame.perception:
        cv2.putText(heat, frame.perception, (8, side_px - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                    cv2.LINE_AA)
    cv2.putText(heat, "P(safe): red 0 .. green 1", (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                cv2.LINE_AA)
    return np.vstack([np.hstack([cam, heat]), bar])


def write_video(frames: Sequence[VideoFrame], out: Path | str, fps: float = 10.0, side_px: int = 352) -> Path:
    """Write camera | heatmap frames as mp4 ('mp4v'); falls back to MJPG .avi. Returns the file written."""
    if not frames:
        raise ReportError("no frames to write: the video needs at least one camera frame")
    if not (math.isfinite(fps) and fps > 0):
        raise ReportError(f"fps must be > 0, got {fps!r}")
    out = Path(out)
    first = _compose(frames[0], side_px)
    size = (first.shape[1], first.shape[0])
    writer = None
    for path, fourcc in ((out.with_suffix(".mp4"), "mp4v"), (out.with_suffix(".avi"), "MJPG")):
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), float(fps), size)
        if writer.isOpened():
            out = path
            break
        log.warning("video codec %s unavailable for %s, trying the next one", fourcc, path)
        writer.release()
        writer = None
    if writer is None:
        raise ReportError(f"OpenCV can write neither mp4v nor MJPG video next to {out}")
    try:
        writer.write(first)
        for frame in frames[1:]:
            writer.write(_compose(frame, side_px))
    finally:
        writer.release()
    return out
