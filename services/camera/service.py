"""The onboard camera service (`dovesei-camera`): OpenCV capture -> CameraFrame on `dovesei/<vehicle>/camera`.

Data flow:

    capture thread (`dovesei.camera.source.Grabber`): cv2.VideoCapture (device index, video file,
        RTSP/HTTP URL or GStreamer pipeline) -> newest frame slot (BGR, capture time); older
        frames are overwritten unread
    state inbox:   VehicleState from Zenoh (`dovesei/<vehicle>/state`, newest wins), published
        by the controller, the one process that talks to the autopilot -> short history
    publish loop:  at `rate_hz`, the newest unpublished frame -> rotate, centre-crop to the output
        aspect, resize -> tagged with the state received just before capture (altitude, attitude,
        a stamp on the vehicle's clock extrapolated to the capture instant) -> encode (JPEG when
        `jpeg_quality` is set, for a radio link to a ground-station segmenter) -> Zenoh put
    odometry:      at up to `odometry_rate_hz` (10 Hz by default; 0 = off), every new grabbed frame
        -> the same rotation and crop at the estimator's work width, tagged the same way ->
        `dovesei.shared.visual_velocity` against the previous one -> VisualOdometry on
        `dovesei/<vehicle>/odometry` (valid or not, with its reason logged at DEBUG); time between
        frames from their capture instants. frame_seq counts grabbed frames, not published ones.
    crops:         the crop key's queries (`dovesei.shared.crop_server`, own thread) -> a square of
        ground cut from the newest PUBLISHED frame at the device's full resolution, tagged like
        that frame (`CameraPublisher.crop`; only crops cross the link, never the full frame)

Newest frame wins: grabbing runs continuously so the published frame is never older than one
capture period; a segmenter slower than the camera sees fresh frames, not a backlog. Cropping
narrows the field of view, so the published `hfov_rad` is the cropped one (pixels stay square).

Failures: a camera that delivers no new frame for `stall_timeout_s`, or a file that ends, is
reported once at WARNING and nothing is published until frames return: the controller's heatmap
watchdog then holds the vehicle, which is the safe reaction to blindness. Devices and streams are
reopened while they are down; a file can loop. Frames are also withheld (reported once) while no
vehicle state newer than `state_timeout_s` is known, since an untagged altitude would mislead the
policy.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import zenoh

import cv2
import numpy as np

from dovesei.camera.source import ROTATIONS, Grabber, crop_resize, output_hfov_rad
from dovesei.shared import footprint, keys, validate
from dovesei.shared.crop import CropLimits, RateLimit, cut_crop, plan_crop
from dovesei.shared.crop_server import CropServer
from dovesei.shared.cliconfig import CommandLine, Flag, integer_in, non_blank
from dovesei.shared.codec import encode
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import Inbox, declare_alive, install_stop_handlers
from dovesei.shared.messages import CameraFrame, CropFrame, CropRequest, Stamp, VehicleState
from dovesei.shared.recording import FlightRecorder
from dovesei.shared.visual_velocity import FrameMeta, VisualVelocity, odometry_message
from dovesei.shared.zconfig import SessionError, open_session

log = logging.getLogger(__name__)

STATE_HISTORY_S = 3.0  # how far back states are kept to find the one at a frame's capture time
# Odometry waits this long after a capture for the next state, to interpolate the attitude at the
# capture instant: the velocity depends on the attitude CHANGE between frames, so tagging each
# frame with whichever state came last (0..1 state period early, at random) would turn a turn rate
# of 0.5 rad/s and 50 Hz states into ~3 mrad of noise per frame, 2 m/s at 50 m and 10 Hz.
ATTITUDE_WAIT_S = 0.05


@dataclass(frozen=True)
class CameraConfig:
    """Everything the camera source needs; validated when built (ConfigError names the field)."""

    source: str  # "0" (device index), a file path, rtsp://..., or a GStreamer pipeline ("... ! appsink")
    vehicle_id: str = "uav1"
    width_px: int = 352
    height_px: int = 352
    hfov_deg: float = footprint.REFERENCE_HFOV_DEG  # the camera's horizontal field of view before cropping
    rotate_deg: int = 0  # clockwise rotation that puts body-forward at the top of the image
    rate_hz: float = 2.0
    jpeg_quality: int | None = None  # None: raw RGB on the wire
    stall_timeout_s: float = 2.0
    state_timeout_s: float = 1.0
    loop_file: bool = False
    record_path: str | None = None  # write the published frames, their states and the odometry to this MCAP file
    odometry_rate_hz: float = 10.0  # visual velocity from consecutive grabbed frames; 0 = off
    odometry_width_px: int = 320  # frames are cropped like the published ones and shrunk to this width
    # Close looks: the newest published frame is kept at the device's full resolution (whatever it
    # delivers: set the size on the device or the pipeline, e.g. 4000x3000) and squares of it are
    # cut on the crop key, at most this often.
    crop_rate_hz: float = 5.0

    def __post_init__(self) -> None:
        if not isinstance(self.source, str) or not self.source.strip():
            raise ConfigError("camera source must be a device index, a file, a URL or a GStreamer pipeline")
        keys.check_vehicle_id(self.vehicle_id)
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 16 <= value <= 4096:
                raise ConfigError(f"camera {name} must be an integer in 16..4096, got {value!r}")
        if not (validate.is_number(self.hfov_deg) and 0.0 < self.hfov_deg < 180.0):
            raise ConfigError(f"camera hfov_deg must be in (0, 180), got {self.hfov_deg!r}")
        if self.rotate_deg not in ROTATIONS:
            raise ConfigError(f"camera rotate_deg must be one of {sorted(ROTATIONS)}, got {self.rotate_deg!r}")
        for name in ("rate_hz", "stall_timeout_s", "state_timeout_s"):
            validate.positive(f"camera {name}", getattr(self, name))
        validate.in_range("camera odometry_rate_hz", self.odometry_rate_hz, 0.0, 200.0)
        validate.in_range("camera crop_rate_hz", self.crop_rate_hz, 0.01, 100.0)
        if isinstance(self.odometry_width_px, bool) or not isinstance(self.odometry_width_px, int) \
                or not 64 <= self.odometry_width_px <= 1280:
            raise ConfigError(f"camera odometry_width_px must be an integer in 64..1280, got {self.odometry_width_px!r}")
        if self.jpeg_quality is not None:
            validate.in_range("camera jpeg_quality", self.jpeg_quality, 1, 100)


@dataclass
class CameraStats:
    """What the source did; tests and operators read it (the loop is its only writer)."""

    grabbed: int = 0
    published: int = 0
    withheld_no_state: int = 0
    odometry_published: int = 0
    odometry_valid: int = 0
    crops_answered: int = 0
    crops_refused: int = 0
    stalled: bool = False
    ended: bool = False
    warnings: list[str] = field(default_factory=list)


class StateSource(Protocol):
    def poll(self) -> VehicleState | None: ...

    def age_s(self) -> float:
        """Seconds since the state the last poll returned arrived (0 when it is not known)."""
        ...

    def close(self) -> None: ...


class ZenohStateSource:
    """The vehicle state published on Zenoh (by the controller of a MAVLink vehicle, or the sim), newest wins."""

    def __init__(self, session: zenoh.Session, vehicle_id: str) -> None:
        self._inbox = Inbox(session, keys.state(vehicle_id), VehicleState, newest_only=True)

    def poll(self) -> VehicleState | None:
        return self._inbox.poll()

    def age_s(self) -> float:
        # The inbox stamps each sample's arrival: a loop that drains it late (a loaded host, an
        # odometry computation) still dates the state by when it came, not by when it was read.
        return min(max(0.0, time.time() - self._inbox.last_recv_wall_s), STATE_HISTORY_S)

    def close(self) -> None:
        self._inbox.close()


class CameraPublisher:
    """The publish loop's logic, one `tick()` at a time (run() drives it; tests may too)."""

    def __init__(self, config: CameraConfig, grabber: Grabber, state_source: StateSource,
                 put: Callable[[bytes], None], *, clock: Callable[[], float] = time.monotonic,
                 stats: CameraStats | None = None, recorder: FlightRecorder | None = None,
                 put_odometry: Callable[[bytes], None] | None = None) -> None:
        self.config, self.grabber, self.state_source, self.put = config, grabber, state_source, put
        self.put_odometry = put_odometry
        self._odometry = VisualVelocity()
        self._odometry_index = 0
        self.recorder = recorder
        self._recorded_state: VehicleState | None = None
        self.stats = stats if stats is not None else CameraStats()
        self._clock = clock
        self._states: deque[tuple[float, VehicleState]] = deque()
        self._seq = 0
        self._last_index = 0
        self._last_new_frame_s = clock()
        self._no_state_reported = False
        self._hfov_cache: tuple[tuple[int, int], float] | None = None
        # The newest published frame at full resolution and its tags, replaced whole (the crop
        # thread reads it without a lock): (frame, BGR as captured).
        self._newest_full: tuple[CameraFrame, np.ndarray] | None = None
        self.crop_limits = CropLimits(rate_hz=config.crop_rate_hz, burst=max(1, round(config.crop_rate_hz)))
        self._crop_rate = RateLimit(self.crop_limits.rate_hz, self.crop_limits.burst)

    def poll_state(self) -> None:
        """Drain the state source into the history (call often: receive times date the states)."""
        now = self._clock()
        while (state := self.state_source.poll()) is not None:
            self._states.append((now - self.state_source.age_s(), state))
        while self._states and now - self._states[0][0] > STATE_HISTORY_S and len(self._states) > 1:
            self._states.popleft()

    def tick(self) -> bool:
        """Publish the newest frame if it is new and tagged; True when a frame went out."""
        self.poll_state()
        now = self._clock()
        newest = self.grabber.newest()
        if newest is None or newest[2] == self._last_index:
            self._check_stall(now)
            return False
        bgr, capture_s, index = newest
        self.stats.grabbed = index
        self._last_index, self._last_new_frame_s = index, now
        if self.stats.stalled:
            self.stats.stalled = False
            log.info("camera delivering again: publishing resumes")
        tagged = self._state_at(capture_s)
        if tagged is None or capture_s - tagged[0] > self.config.state_timeout_s:
            self.stats.withheld_no_state += 1
            if not self._no_state_reported:
                self._warn(f"no vehicle state newer than {self.config.state_timeout_s:.1f} s at capture: "
                           "frames withheld until the state arrives")
                self._no_state_reported = True
            return False
        if self._no_state_reported:
            log.info("vehicle state available: publishing frames")
            self._no_state_reported = False
        recv_s, state = tagged
        frame = CameraFrame(
            vehicle_id=self.config.vehicle_id, seq=self._seq, stamp=_capture_stamp(state, recv_s, capture_s),
            image_rgb=crop_resize(bgr, self.config.width_px, self.config.height_px, self.config.rotate_deg),
            hfov_rad=self._hfov(bgr.shape[1], bgr.shape[0]), alt_agl_m=state.alt_agl_m,
            roll_rad=state.roll_rad, pitch_rad=state.pitch_rad, yaw_rad=state.yaw_rad, sent_wall_s=time.time())
        self.put(encode(frame, jpeg_quality=self.config.jpeg_quality))
        self._newest_full = (frame, bgr)
        if self.recorder is not None:
            # The state that tagged the frame goes first (once, however many frames it tags).
            if state is not self._recorded_state:
                self.recorder.write(state)
                self._recorded_state = state
            self.recorder.write(frame)
        self._seq += 1
        self.stats.published += 1
        log.debug("frame %d published (alt %.1f m)", frame.seq, frame.alt_agl_m)
        return True

    def odometry_tick(self) -> bool:
        """Compare the newest grabbed frame with the one before and publish the velocity; True if sent.

        A frame without a recent state is skipped and forgotten (the next one starts afresh): a
        velocity scaled by an unknown altitude would be made up.
        """
        if self.put_odometry is None:
            return False
        newest = self.grabber.newest()
        if newest is None or newest[2] == self._odometry_index:
            return False
        bgr, capture_s, index = newest
        after = self._state_after(capture_s)
        if after is None and self._clock() - capture_s < ATTITUDE_WAIT_S:
            return False  # the state after the capture is due shortly: interpolate with it then
        self._odometry_index = index
        tagged = self._state_at(capture_s)
        if tagged is None or capture_s - tagged[0] > self.config.state_timeout_s:
            self._odometry.reset()
            return False
        recv_s, state = tagged
        c = self.config
        # The published frame's crop and field of view, at the estimator's width (never enlarged).
        src_h, src_w = bgr.shape[:2]
        width = min(c.odometry_width_px, src_w if c.rotate_deg in (0, 180) else src_h)
        height = max(32, round(width * c.height_px / c.width_px))
        alt_m, roll, pitch, yaw = _interpolate(tagged, after, capture_s)
        meta = FrameMeta(index, capture_s, alt_m, self._hfov(src_w, src_h), roll, pitch, yaw)
        est = self._odometry.update(crop_resize(bgr, width, height, c.rotate_deg), meta)
        if est is None:
            return False
        msg = odometry_message(est, meta, vehicle_id=c.vehicle_id, stamp=_capture_stamp(state, recv_s, capture_s),
                               sent_wall_s=time.time())
        self.put_odometry(encode(msg))
        if self.recorder is not None:
            self.recorder.write(msg)
        self.stats.odometry_published += 1
        self.stats.odometry_valid += int(msg.valid)
        if msg.valid:
            log.debug("odometry %d: (%.2f, %.2f, %.2f) m/s, quality %.2f", msg.frame_seq, *msg.vel_body_frd_m_s,
                      msg.quality)
        else:
            log.debug("odometry %d invalid: %s", msg.frame_seq, est.reason)
        return True

    def crop(self, req: CropRequest) -> CropFrame:
        """A square of ground cut from the newest published frame at the device's full resolution
        (rotated like the published frames), tagged like that frame; CropRefused says why not.
        Called from the crop server's thread: it reads one snapshot and never the loop's state."""
        c, newest = self.config, self._newest_full
        frame, bgr = newest if newest is not None else (None, None)
        src_h, src_w = bgr.shape[:2] if bgr is not None else (1, 1)
        width, height = (src_w, src_h) if c.rotate_deg in (0, 180) else (src_h, src_w)
        hfov = output_hfov_rad(c.hfov_deg, src_w, src_h, width, height, c.rotate_deg)
        plan = plan_crop(req, self.crop_limits, self._crop_rate, self._clock(), vehicle_id=c.vehicle_id,
                         newest_seq=None if frame is None else frame.seq,
                         alt_agl_m=frame.alt_agl_m if frame else 0.0, roll_rad=frame.roll_rad if frame else 0.0,
                         pitch_rad=frame.pitch_rad if frame else 0.0, width_px=width, height_px=height, hfov_rad=hfov)
        if ROTATIONS[c.rotate_deg] is not None:
            bgr = cv2.rotate(bgr, ROTATIONS[c.rotate_deg])
        rgb = cv2.cvtColor(cut_crop(bgr, plan.homography, req.out_px), cv2.COLOR_BGR2RGB)
        return CropFrame(c.vehicle_id, req.request_seq, frame.seq, frame.stamp, rgb, req.centre_frd_m, req.side_m,
                         frame.alt_agl_m, plan.source_m_per_px, roll_rad=frame.roll_rad, pitch_rad=frame.pitch_rad,
                         yaw_rad=frame.yaw_rad, sent_wall_s=time.time())

    def _check_stall(self, now: float) -> None:
        if self.grabber.ended.is_set() and not self.stats.ended:
            # Warn first: `ended` is what a watcher waits on, and the warning is part of ending.
            self._warn(f"camera source {self.config.source!r} reached its end: publishing stopped "
                       "(the controller's watchdog holds the vehicle)")
            self.stats.ended = True
            return
        silent_s = now - self._last_new_frame_s
        if not self.stats.stalled and not self.stats.ended and silent_s > self.config.stall_timeout_s:
            self.stats.stalled = True
            self._warn(f"camera delivered no new frame for {silent_s:.1f} s: publishing "
                       "stopped until frames return (the controller's watchdog holds the vehicle)")

    def _state_at(self, capture_s: float) -> tuple[float, VehicleState] | None:
        """The last state received at or before the capture (the first one if all came later)."""
        best = None
        for recv_s, state in self._states:
            if recv_s > capture_s:
                break
            best = (recv_s, state)
        if best is None and self._states:
            best = self._states[0]
        return best

    def _state_after(self, capture_s: float) -> tuple[float, VehicleState] | None:
        """The first state received after the capture, if one has arrived."""
        return next(((recv_s, state) for recv_s, state in self._states if recv_s > capture_s), None)

    def _hfov(self, src_w: int, src_h: int) -> float:
        if self._hfov_cache is None or self._hfov_cache[0] != (src_w, src_h):
            c = self.config
            self._hfov_cache = ((src_w, src_h), output_hfov_rad(c.hfov_deg, src_w, src_h, c.width_px, c.height_px,
                                                                c.rotate_deg))
        return self._hfov_cache[1]

    def _warn(self, text: str) -> None:
        self.stats.warnings.append(text)
        log.warning("%s", text)


def _interpolate(before: tuple[float, VehicleState], after: tuple[float, VehicleState] | None,
                 capture_s: float) -> tuple[float, float, float, float]:
    """(alt, roll, pitch, yaw) at the capture, linear between the states received around it (by
    their arrival times; the yaw the short way round); the state before alone when none came after."""
    (t0, s0) = before
    values0 = (s0.alt_agl_m, s0.roll_rad, s0.pitch_rad, s0.yaw_rad)
    if after is None or after[0] <= t0:
        return values0
    (t1, s1) = after
    w = min(1.0, max(0.0, (capture_s - t0) / (t1 - t0)))
    alt, roll, pitch = (a + w * (b - a) for a, b in zip(values0[:3], (s1.alt_agl_m, s1.roll_rad, s1.pitch_rad)))
    yaw = math.remainder(s0.yaw_rad + w * math.remainder(s1.yaw_rad - s0.yaw_rad, math.tau), math.tau)
    return alt, roll, pitch, yaw


def _capture_stamp(state: VehicleState, recv_s: float, capture_s: float) -> Stamp:
    """The state's clock, moved on by the time between the state's arrival and the capture."""
    return Stamp(state.stamp.t_s + max(0.0, capture_s - recv_s), state.stamp.clock)


def run(session: zenoh.Session, *, config: CameraConfig, stop: threading.Event,
        state_source: StateSource | None = None, stats: CameraStats | None = None) -> CameraStats:
    """Capture and publish until `stop` is set; returns what happened (recording to `config.record_path`)."""
    with open_recorder(config) as recorder:
        return _serve(session, config, stop, state_source, stats, recorder)


def open_recorder(config: CameraConfig) -> FlightRecorder | contextlib.nullcontext[None]:
    """The MCAP recorder `config.record_path` asks for (a do-nothing context without one)."""
    if config.record_path is None:
        return contextlib.nullcontext()
    meta = {"camera_service": {"source": config.source, "vehicle_id": config.vehicle_id, "width_px": config.width_px,
                               "height_px": config.height_px, "hfov_deg": config.hfov_deg,
                               "rotate_deg": config.rotate_deg, "rate_hz": config.rate_hz}}
    try:
        return FlightRecorder(config.record_path, metadata=meta)
    except OSError as exc:
        raise ConfigError(f"--record {config.record_path}: cannot write the recording "
                          f"({exc.strerror or exc})") from None


def _serve(session: zenoh.Session, config: CameraConfig, stop: threading.Event, state_source: StateSource | None,
           stats: CameraStats | None, recorder: FlightRecorder | None) -> CameraStats:
    own_source = state_source is None
    if state_source is None:
        state_source = ZenohStateSource(session, config.vehicle_id)
    grabber = Grabber(config.source, loop_file=config.loop_file).start()
    publisher = session.declare_publisher(keys.camera(config.vehicle_id))
    odometry = session.declare_publisher(keys.odometry(config.vehicle_id)) if config.odometry_rate_hz > 0 else None
    loop = CameraPublisher(config, grabber, state_source, publisher.put, stats=stats, recorder=recorder,
                           put_odometry=odometry.put if odometry is not None else None)
    crops = CropServer(session, config.vehicle_id, loop.crop)
    log.info("camera %s (%s) -> %s at %.1f Hz, %dx%d, %s, state from %s; odometry %s", config.source, grabber.kind,
             keys.camera(config.vehicle_id), config.rate_hz, config.width_px, config.height_px,
             f"JPEG q{config.jpeg_quality}" if config.jpeg_quality else "raw RGB", keys.state(config.vehicle_id),
             f"-> {keys.odometry(config.vehicle_id)} at up to {config.odometry_rate_hz:g} Hz" if odometry else "off")
    period_s, poll_s = 1.0 / config.rate_hz, 0.01
    odo_period_s = 1.0 / config.odometry_rate_hz if odometry is not None else math.inf
    try:
        next_pub_s = next_odo_s = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            loop.poll_state()  # keep state receive times accurate between publications
            if now >= next_odo_s:
                # A new frame is compared as soon as it is grabbed; without one, look again next poll.
                if loop.odometry_tick():
                    next_odo_s = max(next_odo_s + odo_period_s, now)
            if now >= next_pub_s:
                loop.tick()
                next_pub_s = max(next_pub_s + period_s, now)
            # At most one poll period: odometry waiting for its next frame looks again then.
            stop.wait(min(poll_s, max(0.0, next_pub_s - time.monotonic())))
    finally:
        crops.close()
        loop.stats.crops_answered, loop.stats.crops_refused = crops.answered, sum(crops.refused.values())
        grabber.close()
        if odometry is not None:
            odometry.undeclare()
        publisher.undeclare()
        if own_source:
            state_source.close()
    return loop.stats


# The one table of the camera's flags: `build_parser`, `config_from_args` and `to_argv` read it.
CLI = CommandLine(CameraConfig, {
    "source": Flag("--source", "device index (0), video file, rtsp:// URL or GStreamer pipeline", check=non_blank),
    "vehicle_id": Flag("--vehicle-id", "vehicle id in the Zenoh keys", check=lambda _w, v: keys.check_vehicle_id(v)),
    "width_px": Flag("--width", "published width, pixels", check=integer_in(16, 4096)),
    "height_px": Flag("--height", "published height, pixels", check=integer_in(16, 4096)),
    "hfov_deg": Flag("--hfov-deg", "camera horizontal field of view before cropping", check=validate.positive),
    "rotate_deg": Flag("--rotate", "clockwise rotation, degrees", choices=tuple(sorted(ROTATIONS))),
    "rate_hz": Flag("--rate-hz", "publication rate", check=validate.positive),
    "jpeg_quality": Flag("--jpeg-quality", "JPEG on the wire at quality Q (for a remote segmenter; default raw)",
                         check=integer_in(1, 100), metavar="Q"),
    "stall_timeout_s": Flag("--stall-timeout", "seconds without a frame before reporting", check=validate.positive),
    "state_timeout_s": Flag("--state-timeout", "max age of the state used to tag a frame, seconds",
                            check=validate.positive),
    "loop_file": Flag("--loop", "loop a video file"),
    "odometry_rate_hz": Flag("--odometry-rate-hz", "visual velocity on the odometry key from consecutive frames, "
                             "at most this often (0 = off)", check=lambda w, v: validate.in_range(w, v, 0.0, 200.0)),
    "odometry_width_px": Flag("--odometry-width", "frames shrunk to this width for the visual velocity, pixels",
                              check=integer_in(64, 1280)),
    "crop_rate_hz": Flag("--crop-rate-hz", "answer at most this many close-look crops a second on the crop key",
                         check=lambda w, v: validate.in_range(w, v, 0.01, 100.0)),
    "record_path": Flag("--record", "write the published frames and their states as an MCAP recording to PATH",
                        check=non_blank, metavar="PATH"),
}, prog="dovesei-camera", description="Publish an onboard camera as dovesei frames.")


build_parser = CLI.build_parser
config_from_args = CLI.from_args
to_argv = CLI.to_argv  # what `dovesei up` passes to a child process; parses back to the same config


def main(argv: list[str] | None = None) -> int:
    config, _process, zconf = CLI.start(argv)  # a bad flag exits 2 with the usage line
    stop = install_stop_handlers()
    try:
        with open_session(zconf) as session:
            token = declare_alive(session, config.vehicle_id, "camera")
            try:
                run(session, config=config, stop=stop)
            finally:
                token.undeclare()
    except ConfigError as exc:
        log.error("%s", exc)
        return 2
    except SessionError as exc:  # a taken listen port, an unreachable router: one line, not a traceback
        log.error("camera not started: %s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
