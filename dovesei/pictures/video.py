"""The episode video: camera | heatmap | the policy's view, a text bar and a legend on every frame.

    [VideoFrame] --write_video--> episode.mp4 (H.264, yuv420p, faststart: plays in browsers and IDE
                                  previews; PyAV's libx264, extra 'video'), else OpenCV mp4v / MJPG

The policy's view is what the decision was made on: the heatmap thresholded at the policy's
threshold (when it had one), dimmed outside the dynamic-focus circle, with the chosen spot. A
policy that picks a spot on a ground map (`clearance`) has no focus circle: its panel shows the
spot as a circle of the spot's clearance radius where the spot lies relative to the vehicle (the
status' target pixel; metres -> pixels with the camera footprint at the frame's altitude), and
the policy's reason for its state (in a row under the panels, not over the view). Frames
before the first heatmap are not shown at the start (the controller is blind then and says
SENSOR_ERROR, which is not what the flight was about); the focus circle is never drawn where
there is no heatmap.
"""

from __future__ import annotations

import itertools
import logging
import math
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from dovesei.pictures.common import ReportError
from dovesei.shared import footprint

try:  # optional extra 'video': without it the video is MPEG-4 Part 2, which browsers do not play
    import av
except ImportError:  # pragma: no cover - depends on the install
    av = None

log = logging.getLogger(__name__)

BAR_PX = 34  # the text bar under the panels
LEGEND_PX = 30  # the legend row under the text bar
# The policy's own words (a map policy's spot figures and reason) in a row under the panels: written
# over the policy view they hid the below-threshold ground that the spot circle reaches near 20 m.
POLICY_TEXT_PX = 48
PANELS = 3  # camera | heatmap | policy view
STATE_WINDOW_S = 1.0  # sim seconds: the window of the state-change count on each frame
BLIND_STATES = ("", "INIT", "SENSOR_ERROR")  # the controller has not used a heatmap yet
MAP_POLICIES = ("clearance",)  # policies that choose a spot on a ground map (no focus circle)
SPOT_BGR = (255, 0, 255)  # the chosen spot: magenta
CONFIRMED_BGR = (80, 255, 80)  # the pixel of the look that confirmed the spot: green
ENDING_HOLD_S = 2.5  # wall seconds the outcome frame stays on screen at the end of the video
# The episode's outcome on the last frame, in the colours of the trajectory plot's end marker (BGR).
OUTCOME_BGR = {"safe": (44, 160, 44), "unsafe": (40, 39, 214), "timeout": (14, 127, 255),
               "out_of_world": (127, 127, 127)}


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
    threshold: float | None = None  # the policy's segmentation threshold on P(safe), when it had one
    recent_changes: int = 0  # controller state changes in the STATE_WINDOW_S before this frame
    policy: str = ""  # the controller status' policy name
    hfov_rad: float | None = None  # the camera's horizontal field of view (sizes the spot circle)
    spot_clearance_m: float | None = None  # a map policy's chosen spot: its clearance radius (None: no spot)
    policy_reason: str = ""  # why the policy is in its state (its last transition)
    # The look that last confirmed the spot: how many frames before this one (0: this frame, whose
    # spot pixel is then `confirmed_px`); None when the policy confirmed none.
    confirmed_frames_ago: int | None = None
    confirmed_px: tuple[float, float] | None = None
    look_verdict: str = ""  # the policy's last close look (issue 24): "clear: ...", "never set 2.1 m ...", ...
    # That look's crop (RGB, square, image up = body forward) and its P(never) at the crop's size.
    look_rgb: np.ndarray | None = None
    look_never: np.ndarray | None = None

    @property
    def map_policy(self) -> bool:
        return self.policy in MAP_POLICIES

    def metres_to_heatmap_px(self, metres: float, width_px: int) -> float | None:
        """A ground distance in heatmap pixels at this frame's altitude (flat ground, nadir camera)."""
        if self.hfov_rad is None or not (self.alt_agl_m > 0 and 0 < self.hfov_rad < math.pi):
            return None
        footprint_m = footprint.width_m(self.alt_agl_m, self.hfov_rad)
        return metres * width_px / footprint_m


def _safety_lut() -> np.ndarray:
    """256 BGR colours from red (P = 0, unsafe) through yellow to green (P = 1, safe)."""
    p = np.linspace(0.0, 1.0, 256)
    red = np.clip(2.0 - 2.0 * p, 0.0, 1.0)
    green = np.clip(2.0 * p, 0.0, 1.0)
    return (np.stack([np.zeros_like(p), green, red], axis=1) * 255.0).astype(np.uint8)


_LUT_BGR = _safety_lut()


def _caption(panel: np.ndarray, text: str) -> None:
    cv2.rectangle(panel, (0, 0), (panel.shape[1], 22), (0, 0, 0), -1)
    cv2.putText(panel, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)


def _legend(width_px: int, map_policy: bool = False) -> np.ndarray:
    """P(safe) colour bar and the marks' meanings (drawn once, the same on every frame)."""
    row = np.full((LEGEND_PX, width_px, 3), 24, np.uint8)
    bar_w = 160
    ramp = np.repeat(_LUT_BGR[np.linspace(0, 255, bar_w).astype(np.uint8)][None], 12, axis=0)
    row[9:21, 60:60 + bar_w] = ramp
    font, white = cv2.FONT_HERSHEY_SIMPLEX, (255, 255, 255)
    cv2.putText(row, "P(safe) 0", (4, 20), font, 0.4, white, 1, cv2.LINE_AA)
    cv2.putText(row, "1", (64 + bar_w, 20), font, 0.4, white, 1, cv2.LINE_AA)
    x = 90 + bar_w
    if map_policy:
        cv2.drawMarker(row, (x + 8, 15), SPOT_BGR, cv2.MARKER_TILTED_CROSS, 14, 2, cv2.LINE_AA)
        cv2.circle(row, (x + 8, 15), 10, SPOT_BGR, 2, cv2.LINE_AA)
        cv2.putText(row, "chosen spot and its clearance", (x + 24, 20), font, 0.4, white, 1, cv2.LINE_AA)
        x += 235
        dimmed = "policy view: below threshold"
    else:
        cv2.circle(row, (x + 8, 15), 8, (255, 255, 0), 2, cv2.LINE_AA)
        cv2.putText(row, "focus circle", (x + 22, 20), font, 0.4, white, 1, cv2.LINE_AA)
        x += 120
        cv2.drawMarker(row, (x + 8, 15), SPOT_BGR, cv2.MARKER_TILTED_CROSS, 14, 2, cv2.LINE_AA)
        cv2.putText(row, "chosen spot", (x + 22, 20), font, 0.4, white, 1, cv2.LINE_AA)
        x += 115
        dimmed = "policy view: below threshold / outside focus"
    cv2.rectangle(row, (x, 8), (x + 14, 22), (60, 60, 60), -1)
    cv2.putText(row, dimmed, (x + 20, 20), font, 0.4, white, 1, cv2.LINE_AA)
    return row


def _spot(panel: np.ndarray, frame: VideoFrame, hm_w: int, sx: float, sy: float) -> list[str]:
    """A map policy's chosen spot: its clearance circle at its place in the view; returns its figures."""
    side_px = panel.shape[0]
    if frame.target_px is None or frame.spot_clearance_m is None:
        return []
    row, col = frame.target_px
    centre = (int(round((col + 0.5) * sx)), int(round((row + 0.5) * sy)))
    radius_hm = frame.metres_to_heatmap_px(frame.spot_clearance_m, hm_w)
    if radius_hm is not None:
        # Clipped by the panel when the spot lies near or beyond the edge of the view. An outline on a
        # dark casing: readable over bright and dimmed (below threshold) ground, hiding neither.
        radius = max(2, int(round(radius_hm * sx)))
        cv2.circle(panel, centre, radius, (0, 0, 0), 4, cv2.LINE_AA)
        cv2.circle(panel, centre, radius, SPOT_BGR, 2, cv2.LINE_AA)
    inside = 0 <= centre[0] < side_px and 0 <= centre[1] < side_px
    text = f"spot: clearance {frame.spot_clearance_m:.1f} m" + ("" if inside else " (outside the view)")
    lines = [text]
    if frame.confirmed_px is not None:
        # This very look confirmed the spot: where, in its own pixels (what the judge maps).
        row_c, col_c = frame.confirmed_px
        cv2.drawMarker(panel, (int(round((col_c + 0.5) * sx)), int(round((row_c + 0.5) * sy))), CONFIRMED_BGR,
                       cv2.MARKER_CROSS, 14, 2, cv2.LINE_AA)
        lines.append("confirmed in this look")
    elif frame.confirmed_frames_ago is not None:
        lines.append(f"confirmed {frame.confirmed_frames_ago} frames ago")
    return lines


def _policy_text(width_px: int, spot: Sequence[str], reason: str, look: str = "") -> np.ndarray:
    """The row under the panels: the spot's figures on the first line, the close look's verdict
    (green clear, red something of the never set, orange a failed look), the policy's reason
    (wrapped) under them; three lines at most."""
    row = np.zeros((POLICY_TEXT_PX, width_px, 3), np.uint8)
    lines = [("policy: " + ", ".join(spot), (255, 255, 255))] if spot else []
    if look:
        colour = (80, 220, 80) if look.startswith("clear") else (60, 60, 255) if look.startswith("never") \
            else (0, 165, 255)
        lines.append(("close look: " + look, colour))
    if reason:
        lines += [(t, (255, 255, 255)) for t in textwrap.wrap("reason: " + reason, max(20, width_px // 7),
                                                             max_lines=3 - len(lines), placeholder=" ...")]
    font = cv2.FONT_HERSHEY_SIMPLEX
    for i, (line, colour) in enumerate(lines[:3]):
        cv2.putText(row, line, (8, 14 + 14 * i), font, 0.4, colour, 1, cv2.LINE_AA)
    return row


LOOK_NEVER_P = 0.3  # the close look's own threshold (policies/clearance/closelook.py): tinted red above it


def _look_inset(panel: np.ndarray, frame: VideoFrame) -> None:
    """The last close look in the camera panel's lower right corner: the crop, red where P(never)
    passes the look's threshold, its margin (the square's inscribed circle) and the verdict's colour."""
    side = panel.shape[0] * 3 // 8
    crop = cv2.resize(cv2.cvtColor(np.ascontiguousarray(frame.look_rgb), cv2.COLOR_RGB2BGR), (side, side),
                      interpolation=cv2.INTER_AREA)
    if frame.look_never is not None:
        never = cv2.resize(np.asarray(frame.look_never, np.float32), (side, side), interpolation=cv2.INTER_LINEAR)
        hot = never >= LOOK_NEVER_P
        crop[hot] = (0.4 * crop[hot] + 0.6 * np.array([0, 0, 255])).astype(np.uint8)
    colour = (80, 220, 80) if frame.look_verdict.startswith("clear") else (60, 60, 255)
    cv2.circle(crop, (side // 2, side // 2), side // 2 - 1, colour, 1, cv2.LINE_AA)
    cv2.drawMarker(crop, (side // 2, side // 2), SPOT_BGR, cv2.MARKER_TILTED_CROSS, 10, 1, cv2.LINE_AA)
    y0, x0 = panel.shape[0] - side - 4, panel.shape[1] - side - 4
    panel[y0:y0 + side, x0:x0 + side] = crop
    cv2.rectangle(panel, (x0 - 1, y0 - 1), (x0 + side, y0 + side), colour, 2)
    cv2.putText(panel, "close look", (x0 + 3, y0 + 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


def _ending(panels: np.ndarray, outcome: str, detail: str) -> None:
    """The episode's outcome across the panels: a band in the outcome's colour, the judge's detail under it."""
    colour = OUTCOME_BGR.get(outcome, (0, 0, 0))
    font = cv2.FONT_HERSHEY_SIMPLEX
    width = panels.shape[1]
    lines = textwrap.wrap(detail, max(30, width // 11), max_lines=3, placeholder=" ...") if detail else []
    top = panels.shape[0] // 2 - 40
    bottom = top + 56 + 24 * len(lines)
    cv2.rectangle(panels, (0, top), (width, bottom), colour, -1)
    cv2.rectangle(panels, (0, top), (width, bottom), (255, 255, 255), 2)
    title = f"END: {outcome.upper().replace('_', ' ')}"
    (w, _), _ = cv2.getTextSize(title, font, 1.2, 2)
    cv2.putText(panels, title, ((width - w) // 2, top + 40), font, 1.2, (255, 255, 255), 2, cv2.LINE_AA)
    for i, line in enumerate(lines):
        (w, _), _ = cv2.getTextSize(line, font, 0.6, 1)
        cv2.putText(panels, line, ((width - w) // 2, top + 70 + 24 * i), font, 0.6, (255, 255, 255), 1, cv2.LINE_AA)


def _compose(frame: VideoFrame, side_px: int, legend: np.ndarray | None = None, outcome: str = "",
             detail: str = "") -> np.ndarray:
    """camera | heatmap | policy view (BGR), with focus circle (or a map policy's spot), target, a text
    bar and the legend; with an `outcome`, the episode's end written across the panels."""
    cam = cv2.resize(cv2.cvtColor(np.ascontiguousarray(frame.image_rgb), cv2.COLOR_RGB2BGR), (side_px, side_px),
                     interpolation=cv2.INTER_AREA)
    has_heatmap = frame.prob_safe is not None
    spot_lines: list[str] = []
    if has_heatmap:
        prob = np.asarray(frame.prob_safe, dtype=np.float32)
        hm_h, hm_w = prob.shape
        prob_big = cv2.resize(prob, (side_px, side_px), interpolation=cv2.INTER_NEAREST)
        heat = _LUT_BGR[np.clip(prob_big * 255.0 + 0.5, 0, 255).astype(np.uint8)]
        policy = heat.copy()
        keep = np.ones((side_px, side_px), bool)
        if frame.threshold is not None:
            keep &= prob_big >= frame.threshold
        sy, sx = side_px / hm_h, side_px / hm_w
        if frame.focus_radius_px > 0 and not frame.map_policy:
            yy, xx = np.mgrid[0:side_px, 0:side_px]
            keep &= (yy - side_px / 2) ** 2 + (xx - side_px / 2) ** 2 <= (frame.focus_radius_px * sx) ** 2
        policy[~keep] = (policy[~keep] * 0.25).astype(np.uint8)
    else:
        heat = np.full((side_px, side_px, 3), 40, np.uint8)
        policy = heat.copy()
        for panel in (heat, policy):
            cv2.putText(panel, "no heatmap kept", (side_px // 4, side_px // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                        (200, 200, 200), 1, cv2.LINE_AA)
    if has_heatmap:  # marks belong to a heatmap: none over "no heatmap"
        for panel in (cam, heat, policy):
            if frame.focus_radius_px > 0 and not frame.map_policy:
                # The dynamic-focus circle; when it covers the whole image it is clipped to the frame.
                radius = int(round(frame.focus_radius_px * sx))
                cv2.circle(panel, (side_px // 2, side_px // 2), radius, (255, 255, 0), 2, cv2.LINE_AA)
            if frame.target_px is not None:
                row, col = frame.target_px
                centre = (int(round((col + 0.5) * sx)), int(round((row + 0.5) * sy)))
                cv2.drawMarker(panel, centre, SPOT_BGR, cv2.MARKER_TILTED_CROSS, 18, 3, cv2.LINE_AA)
        if frame.map_policy:
            spot_lines = _spot(policy, frame, hm_w, sx, sy)
    if frame.look_rgb is not None:
        _look_inset(cam, frame)
    _caption(cam, "camera")
    _caption(heat, "heatmap P(safe)")
    thr = f" >= {frame.threshold:.2f}" if frame.threshold is not None else ""
    _caption(policy, f"policy view: P{thr}, chosen spot" if frame.map_policy else f"policy view: P{thr}, in focus")
    if frame.perception:
        cv2.putText(heat, frame.perception, (8, side_px - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                    cv2.LINE_AA)
    width = PANELS * side_px
    bar = np.zeros((BAR_PX, width, 3), np.uint8)
    text = f"t {frame.t_s:7.2f} s   alt {frame.alt_agl_m:6.1f} m AGL   state {frame.state or '-'}"
    if outcome:
        text += f"   episode: {outcome}"
    if frame.recent_changes > 1:
        # Frames are a sample; a policy that flips state between them would look erratic unexplained.
        text += f" ({frame.recent_changes} state changes in the last {STATE_WINDOW_S:g} s)"
    if frame.watchdog and frame.watchdog != "ok":
        text += f"   WATCHDOG {frame.watchdog.upper()}"
    cv2.putText(bar, text, (8, 23), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    if legend is None:
        legend = _legend(width, frame.map_policy)
    panels = np.hstack([cam, heat, policy])
    if outcome:
        _ending(panels, outcome, detail)
    words = _policy_text(width, spot_lines, frame.policy_reason if frame.map_policy else "",
                         frame.look_verdict if frame.map_policy else "")
    return np.vstack([panels, words, bar, legend])


def _fill_status(frames: Sequence[VideoFrame], policy: str) -> list[VideoFrame]:
    """Frames recorded without a controller status (the last ones, after the controller stopped)
    keep the policy flown, its threshold and its last state, marked as the last one: a blank status
    drew the `dovesei` panel and `state -`."""
    flown = policy or next((f.policy for f in reversed(frames) if f.policy), "")
    out: list[VideoFrame] = []
    last: VideoFrame | None = None
    for f in frames:
        if f.state:
            last = f
        elif last is not None:
            state = last.state if last.state.endswith("(last status)") else f"{last.state} (last status)"
            f = replace(f, state=state, threshold=f.threshold if f.threshold is not None else last.threshold)
        if not f.policy:
            f = replace(f, policy=flown)
        out.append(f)
    return out


def state_change_times(states_by_t: Mapping[float, str]) -> np.ndarray:
    """Sorted sim times at which the state differs from the one before (from {t_s: state})."""
    times = sorted(states_by_t)
    return np.asarray([t for prev, t in zip(times, times[1:]) if states_by_t[t] != states_by_t[prev]],
                      dtype=np.float64)


def changes_before(change_times_s: np.ndarray, t_s: float, window_s: float = STATE_WINDOW_S) -> int:
    """How many state changes fall in (t_s - window_s, t_s]."""
    return int(np.searchsorted(change_times_s, t_s, "right") - np.searchsorted(change_times_s, t_s - window_s, "right"))


def _opening(frames: Sequence[VideoFrame]) -> int:
    """Index of the first frame worth opening on: the first with a heatmap that the controller has
    acted on (not blind: SENSOR_ERROR, INIT or no status); else the first with a heatmap; else 0."""
    for i, frame in enumerate(frames):
        if frame.prob_safe is not None and frame.state not in BLIND_STATES:
            return i
    for i, frame in enumerate(frames):
        if frame.prob_safe is not None:
            return i
    return 0


def write_video(frames: Sequence[VideoFrame], out: Path | str, fps: float = 10.0, side_px: int = 352,
                outcome: str = "", detail: str = "", policy: str = "") -> Path:
    """Write the frames as H.264 MP4 (PyAV), else OpenCV mp4v or MJPG .avi. Returns the file written.

    `outcome` and `detail` (the judge's) are written on the last frame, held ENDING_HOLD_S; `policy`
    names the policy flown for frames recorded without a controller status.
    """
    if not frames:
        raise ReportError("no frames to write: the video needs at least one camera frame")
    if not (math.isfinite(fps) and fps > 0):
        raise ReportError(f"fps must be > 0, got {fps!r}")
    side_px += side_px % 2  # H.264 in yuv420p needs even sides
    frames = _fill_status(frames[_opening(frames):], policy)
    legend = _legend(PANELS * side_px, map_policy=any(f.map_policy for f in frames))
    images = (_compose(f, side_px, legend) for f in frames)
    if outcome:
        ending = _compose(frames[-1], side_px, legend, outcome, detail)
        images = itertools.chain(images, itertools.repeat(ending, max(1, round(ENDING_HOLD_S * fps))))
    out = Path(out)
    if av is not None:
        return _write_h264(images, out.with_suffix(".mp4"), fps)
    log.warning("PyAV is not installed (extra 'video'): writing MPEG-4 Part 2, which browsers do not play")
    return _write_opencv(images, out, fps)


def _write_h264(images, path: Path, fps: float) -> Path:
    # faststart puts the index first: a browser plays the file while it loads.
    with av.open(str(path), mode="w", options={"movflags": "faststart"}) as container:
        stream = None
        for bgr in images:
            if stream is None:
                stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
                stream.width, stream.height = bgr.shape[1], bgr.shape[0]
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "23", "preset": "veryfast"}
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(bgr), format="bgr24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    return path


def _write_opencv(images, out: Path, fps: float) -> Path:
    images = iter(images)
    first = next(images)
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
        for image in images:
            writer.write(image)
    finally:
        writer.release()
    return out
