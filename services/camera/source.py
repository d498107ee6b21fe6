"""Frames from an onboard camera: OpenCV capture of a device, a file, a stream or a GStreamer pipeline.

`Grabber` reads continuously in a thread and keeps only the newest frame (BGR, capture time on a
monotonic clock, running index), so the publisher never works through a backlog; `crop_resize`
turns a captured frame into the published RGB image and `output_hfov_rad` gives the field of view
that is left after the crop. No Zenoh and no vehicle state here: `dovesei.camera.service` tags and
publishes.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from dovesei.shared import footprint
from dovesei.shared.errors import ConfigError

log = logging.getLogger(__name__)

ROTATIONS = {0: None, 90: cv2.ROTATE_90_CLOCKWISE, 180: cv2.ROTATE_180, 270: cv2.ROTATE_90_COUNTERCLOCKWISE}
REOPEN_PERIOD_S = 1.0  # a lost device or stream is reopened this often


def source_kind(source: str) -> str:
    """'device', 'gstreamer', 'stream' or 'file', from the shape of the source string."""
    if source.isdigit():
        return "device"
    if "!" in source:
        return "gstreamer"
    if "://" in source:
        return "stream"
    return "file"


def output_hfov_rad(hfov_deg: float, src_w: int, src_h: int, out_w: int, out_h: int, rotate_deg: int) -> float:
    """Horizontal FOV of the published image after rotation and centre crop to out_w:out_h."""
    half_tan_w = footprint.half_width_m(1.0, math.radians(hfov_deg))  # per metre of altitude: tan(hfov / 2)
    if rotate_deg in (90, 270):
        # The old vertical axis becomes horizontal: its FOV follows from square pixels.
        half_tan_w, src_w, src_h = half_tan_w * src_h / src_w, src_h, src_w
    crop_w = min(src_w, src_h * out_w / out_h)
    return 2.0 * math.atan(half_tan_w * crop_w / src_w)


def crop_resize(bgr: np.ndarray, out_w: int, out_h: int, rotate_deg: int) -> np.ndarray:
    """Rotate, centre-crop to the output aspect and resize; returns RGB uint8 (out_h, out_w, 3)."""
    if ROTATIONS[rotate_deg] is not None:
        bgr = cv2.rotate(bgr, ROTATIONS[rotate_deg])
    h, w = bgr.shape[:2]
    crop_w, crop_h = min(w, round(h * out_w / out_h)), min(h, round(w * out_h / out_w))
    x0, y0 = (w - crop_w) // 2, (h - crop_h) // 2
    crop = bgr[y0:y0 + crop_h, x0:x0 + crop_w]
    # INTER_AREA averages when shrinking (no aliasing of fine ground texture), LINEAR when growing.
    interp = cv2.INTER_AREA if crop_w >= out_w else cv2.INTER_LINEAR
    return cv2.cvtColor(cv2.resize(crop, (out_w, out_h), interpolation=interp), cv2.COLOR_BGR2RGB)


def open_capture(source: str) -> cv2.VideoCapture:
    """An opened cv2.VideoCapture for any supported source, or ConfigError saying what failed."""
    kind = source_kind(source)
    if kind == "file" and not Path(source).is_file():
        raise ConfigError(f"camera source {source!r}: no such video file")
    if kind == "gstreamer" and "GStreamer:                   YES" not in cv2.getBuildInformation():
        raise ConfigError("camera source is a GStreamer pipeline but this OpenCV build has no GStreamer "
                          "support (opencv-python-headless ships without it; use a system OpenCV)")
    if kind == "device":
        cap = cv2.VideoCapture(int(source))
    elif kind == "gstreamer":
        cap = cv2.VideoCapture(source, cv2.CAP_GSTREAMER)
    else:
        cap = cv2.VideoCapture(source)
    if not cap.isOpened():
        cap.release()
        raise ConfigError(f"camera source {source!r} ({kind}) could not be opened")
    return cap


class Grabber:
    """Reads frames continuously in a thread and keeps only the newest (BGR, capture time, index).

    A file is paced at its own frame rate (it would otherwise be read in a blink); a device or a
    stream is read as fast as it delivers, and reopened every REOPEN_PERIOD_S while it fails.
    """

    def __init__(self, source: str, *, loop_file: bool, clock: Callable[[], float] = time.monotonic) -> None:
        self.source, self.kind, self.loop_file, self._clock = source, source_kind(source), loop_file, clock
        self._cap = open_capture(source)
        fps = self._cap.get(cv2.CAP_PROP_FPS) if self.kind == "file" else 0.0
        self._file_period_s = 1.0 / fps if fps and math.isfinite(fps) and fps > 0 else 1.0 / 30.0
        self._lock = threading.Lock()
        self._slot: tuple[np.ndarray, float, int] | None = None
        self._count = 0
        self.ended = threading.Event()  # a file reached its end and does not loop
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="camera-grab", daemon=True)

    def start(self) -> Grabber:
        self._thread.start()
        return self

    def newest(self) -> tuple[np.ndarray, float, int] | None:
        """(BGR frame, capture time on the clock, running index) of the newest frame, if any."""
        with self._lock:
            return self._slot

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def _run(self) -> None:
        next_read_s = self._clock()
        while not self._stop.is_set():
            if self.kind == "file":
                # Pace the file at its own frame rate (never faster), as if a camera produced it.
                delay = next_read_s - self._clock()
                if delay > 0 and self._stop.wait(delay):
                    return
                next_read_s = max(next_read_s + self._file_period_s, self._clock())
            ok, bgr = self._cap.read() if self._cap is not None else (False, None)
            if ok and bgr is not None and bgr.ndim == 3 and bgr.shape[2] == 3:
                with self._lock:
                    self._count += 1
                    self._slot = (bgr, self._clock(), self._count)
                continue
            if self.kind == "file":
                if not self.loop_file:
                    self.ended.set()
                    return
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                continue
            # A device unplugged or a stream dropped: wait, reopen, and go on if it is back.
            if self._stop.wait(REOPEN_PERIOD_S):
                return
            self._reopen()

    def _reopen(self) -> None:
        if self._cap is not None:
            self._cap.release()
        try:
            self._cap = open_capture(self.source)
        except ConfigError as exc:
            self._cap = None
            log.debug("camera reopen failed: %s", exc)
