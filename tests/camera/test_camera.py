"""The onboard camera service: pure geometry, the publish loop with a fake grabber and clock, and the
whole service on a video file it writes itself over in-process Zenoh, tagged with the states a test
session publishes on the state key (as the controller of a MAVLink vehicle does).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from dovesei.camera import service as cs
from dovesei.camera import source as src
from dovesei.camera.service import CameraConfig, CameraPublisher, CameraStats
from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import Inbox, wait_until
from dovesei.shared.messages import CameraFrame, Stamp, VehicleState, VisualOdometry, replace
from tests.shared.ground import ned_to_body, view


def write_video(path: Path, frames: int, fps: float = 20.0, size: tuple[int, int] = (160, 120)) -> Path:
    """An MJPG .avi whose frames are a blue left half, a red right half and a brightness ramp by index."""
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened(), "this OpenCV cannot write MJPG"
    for i in range(frames):
        bgr = np.zeros((h, w, 3), np.uint8)
        bgr[:, : w // 2] = (200, 0, 0)  # BGR blue
        bgr[:, w // 2:] = (0, 0, 200)  # BGR red
        bgr[: h // 4] += np.uint8(min(50, i))  # a top band that brightens with the index
        writer.write(bgr)
    writer.release()
    return path


def state(alt_m: float, t_s: float = 10.0, seq: int = 0) -> VehicleState:
    return VehicleState(vehicle_id="uav1", seq=seq, stamp=Stamp(t_s, "vehicle"), alt_agl_m=alt_m,
                        vel_body_frd_m_s=(0.0, 0.0, 0.0), roll_rad=0.01, pitch_rad=-0.02, yaw_rad=1.5, mode="GUIDED")


# ---------------------------------------------------------------------- pure pieces


def test_crop_keeps_orientation_and_colour_order() -> None:
    bgr = np.zeros((120, 160, 3), np.uint8)
    bgr[:, :80] = (255, 0, 0)  # blue on the left
    bgr[:60, 80:] = (0, 0, 255)  # red top-right
    rgb = src.crop_resize(bgr, 64, 64, 0)
    assert rgb.shape == (64, 64, 3) and rgb.dtype == np.uint8
    assert tuple(rgb[32, 5]) == (0, 0, 255) and tuple(rgb[5, 60]) == (255, 0, 0)
    # Rotated 90 deg clockwise: the old left edge (blue) is the top, the old top edge the right side,
    # so red (old top-right) ends bottom-right and the black old bottom-right ends bottom-left.
    rot = src.crop_resize(bgr, 64, 64, 90)
    assert tuple(rot[5, 32]) == (0, 0, 255) and tuple(rot[60, 60]) == (255, 0, 0) and tuple(rot[60, 5]) == (0, 0, 0)


def test_cropping_narrows_the_published_field_of_view() -> None:
    # 4:3 to square keeps 3/4 of the width: tan(hfov'/2) = 0.75 tan(hfov/2).
    hfov = src.output_hfov_rad(73.0, 160, 120, 352, 352, 0)
    assert math.tan(hfov / 2) == pytest.approx(0.75 * math.tan(math.radians(36.5)))
    assert src.output_hfov_rad(73.0, 120, 120, 352, 352, 0) == pytest.approx(math.radians(73.0))
    # Rotated: the old vertical FOV becomes horizontal, and nothing is cropped to a portrait 3:4.
    vfov_half_tan = math.tan(math.radians(36.5)) * 120 / 160
    assert math.tan(src.output_hfov_rad(73.0, 160, 120, 120, 160, 90) / 2) == pytest.approx(vfov_half_tan)


def test_config_and_sources_are_checked() -> None:
    with pytest.raises(ConfigError, match="width_px"):
        CameraConfig(source="0", width_px=8)
    with pytest.raises(ConfigError, match="rate_hz"):
        CameraConfig(source="0", rate_hz=True)  # a bool is not a rate
    with pytest.raises(ConfigError, match="rotate_deg"):
        CameraConfig(source="0", rotate_deg=45)
    with pytest.raises(ConfigError, match="no such video file"):
        src.open_capture("/nonexistent/flight.avi")
    assert [src.source_kind(s) for s in ("0", "a.avi", "rtsp://cam/1", "v4l2src ! appsink")] == \
        ["device", "file", "stream", "gstreamer"]


# ---------------------------------------------------------------------- publish loop, fake grabber and clock


class FakeGrabber:
    def __init__(self) -> None:
        self.slot: tuple[np.ndarray, float, int] | None = None
        self.ended = threading.Event()

    def push(self, t_s: float) -> None:
        index = self.slot[2] + 1 if self.slot else 1
        self.slot = (np.full((120, 160, 3), 100, np.uint8), t_s, index)

    def newest(self) -> tuple[np.ndarray, float, int] | None:
        return self.slot


class ListStates:
    def __init__(self) -> None:
        self.queue: list[VehicleState] = []

    def poll(self) -> VehicleState | None:
        return self.queue.pop(0) if self.queue else None

    def age_s(self) -> float:
        return 0.0  # each state arrives when the test polls it

    def close(self) -> None:
        pass


def test_stall_is_reported_once_and_publishing_recovers(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    grabber, states, sent = FakeGrabber(), ListStates(), []
    loop = CameraPublisher(CameraConfig(source="0", width_px=32, height_px=32, stall_timeout_s=2.0), grabber,
                           states, sent.append, clock=lambda: now[0])
    states.queue.append(state(30.0, t_s=100.0))
    loop.poll_state()  # the state arrives at t = 0
    grabber.push(0.5)
    now[0] = 0.6
    assert loop.tick() and len(sent) == 1
    frame = decode(sent[0], CameraFrame)
    assert frame.alt_agl_m == 30.0 and frame.stamp.clock == "vehicle"
    assert frame.stamp.t_s == pytest.approx(100.5)  # the state arrived at 0.0, the frame was captured at 0.5
    assert (frame.roll_rad, frame.pitch_rad, frame.yaw_rad) == (0.01, -0.02, 1.5)
    caplog.set_level(logging.WARNING, logger=cs.__name__)
    for t in (1.0, 2.0, 2.7, 3.5, 5.0):  # no new frame from 0.6 on
        now[0] = t
        assert not loop.tick()
    assert loop.stats.stalled
    assert sum("no new frame" in r.getMessage() for r in caplog.records) == 1
    states.queue.append(state(30.0, t_s=105.0))
    loop.poll_state()  # a fresh state (t = 5.0) before the camera returns
    grabber.push(5.1)
    now[0] = 5.2
    assert loop.tick() and not loop.stats.stalled and len(sent) == 2
    assert decode(sent[1], CameraFrame).seq == 1


def test_frames_without_a_recent_state_are_withheld() -> None:
    now = [0.0]
    grabber, states, sent = FakeGrabber(), ListStates(), []
    loop = CameraPublisher(CameraConfig(source="0", width_px=32, height_px=32, state_timeout_s=1.0), grabber,
                           states, sent.append, clock=lambda: now[0])
    grabber.push(0.0)
    assert not loop.tick() and loop.stats.withheld_no_state == 1  # no state at all
    states.queue.append(state(30.0))
    loop.poll_state()  # arrives at t = 0
    now[0] = 3.0
    grabber.push(3.0)
    assert not loop.tick()  # the only state is 3 s older than the capture
    states.queue.append(state(31.0, t_s=13.0))
    grabber.push(3.0)
    assert loop.tick() and decode(sent[0], CameraFrame).alt_agl_m == 31.0


# ---------------------------------------------------------------------- the service over in-process Zenoh


class StatePublisher:
    """Publishes a VehicleState at 50 Hz from a thread until closed (what the controller of a MAVLink vehicle does)."""

    def __init__(self, session: object, alt_m: float) -> None:
        self._pub = session.declare_publisher(keys.state("uav1"))
        self._stop = threading.Event()
        self.alt_m = alt_m
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        seq = 0
        while not self._stop.wait(0.02):
            self._pub.put(encode(state(self.alt_m, t_s=10.0 + seq * 0.02, seq=seq)))
            seq += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._pub.undeclare()


@pytest.fixture
def service(zenoh_pair: tuple[object, object]) -> Iterator:
    """Run the camera source on session a in a thread; the test talks from session b."""
    a, b = zenoh_pair
    threads: list[tuple[threading.Thread, threading.Event]] = []

    def start(config: CameraConfig, stats: CameraStats, **kw: object) -> None:
        stop = threading.Event()
        t = threading.Thread(target=cs.run, args=(a,), kwargs={"config": config, "stop": stop, "stats": stats, **kw},
                             daemon=True)
        t.start()
        threads.append((t, stop))

    yield b, start
    for t, stop in threads:
        stop.set()
        t.join(timeout=10.0)
        assert not t.is_alive(), "camera source did not stop"


def test_video_file_frames_arrive_tagged_then_end_of_file_stops_publishing(
        service: tuple, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    b, start = service
    video = write_video(tmp_path / "flight.avi", frames=20, fps=20.0)
    states = StatePublisher(b, alt_m=42.5)
    try:
        with Inbox(b, keys.camera("uav1"), CameraFrame, newest_only=False) as inbox:
            stats = CameraStats()
            caplog.set_level(logging.WARNING, logger=cs.__name__)
            start(CameraConfig(source=str(video), width_px=96, height_px=96, rate_hz=10.0), stats)
            frames: list[CameraFrame] = []

            def collect() -> bool:
                while (f := inbox.poll()) is not None:
                    frames.append(f)
                return stats.ended and len(frames) == stats.published

            assert wait_until(collect, 10.0), f"ended={stats.ended} published={stats.published} got={len(frames)}"
    finally:
        states.close()
    assert len(frames) >= 3  # a 1 s file at 10 Hz, minus the frames withheld before the first state
    assert [f.seq for f in frames] == list(range(len(frames)))
    for f in frames:
        assert f.image_rgb.shape == (96, 96, 3) and f.alt_agl_m == 42.5 and f.vehicle_id == "uav1"
        assert f.stamp.clock == "vehicle" and f.stamp.t_s >= 10.0
        # Blue left half, red right half survived the crop, the resize and the BGR -> RGB swap.
        left, right = f.image_rgb[60, 10].astype(int), f.image_rgb[60, 85].astype(int)
        assert left[2] > 150 > left[0] and right[0] > 150 > right[2]
    assert frames[0].hfov_rad == pytest.approx(2 * math.atan(0.75 * math.tan(math.radians(36.5))))
    assert [f.stamp.t_s for f in frames] == sorted(f.stamp.t_s for f in frames)
    ends = [r for r in caplog.records if "reached its end" in r.getMessage()]
    assert len(ends) == 1 and ends[0].levelno == logging.WARNING


def test_jpeg_on_the_wire_and_a_looping_file(service: tuple, tmp_path: Path) -> None:
    b, start = service
    video = write_video(tmp_path / "short.avi", frames=6, fps=20.0)  # 0.3 s of video
    states = StatePublisher(b, alt_m=80.0)
    raw_sizes: list[int] = []
    sub = b.declare_subscriber(keys.camera("uav1"), lambda s: raw_sizes.append(len(s.payload.to_bytes())))
    try:
        with Inbox(b, keys.camera("uav1"), CameraFrame, newest_only=False) as inbox:
            stats = CameraStats()
            start(CameraConfig(source=str(video), width_px=128, height_px=128, rate_hz=20.0, jpeg_quality=80,
                               loop_file=True), stats)
            frames: list[CameraFrame] = []

            def enough() -> bool:
                while (f := inbox.poll()) is not None:
                    frames.append(f)
                return len(frames) >= 12  # twice the file's length: it looped

            assert wait_until(enough, 10.0), f"got {len(frames)} frames, stats {stats}"
    finally:
        sub.undeclare()
        states.close()
    assert not stats.ended
    assert frames[-1].image_rgb.shape == (128, 128, 3)
    assert max(raw_sizes) < 128 * 128 * 3 / 4  # JPEG, not raw RGB


def test_frames_carry_the_newest_state_received(service: tuple, tmp_path: Path) -> None:
    # The state changes while the camera runs: later frames carry the new altitude, none a mix.
    b, start = service
    video = write_video(tmp_path / "flight.avi", frames=40, fps=20.0)
    states = StatePublisher(b, alt_m=50.0)
    try:
        with Inbox(b, keys.camera("uav1"), CameraFrame, newest_only=False) as inbox:
            start(CameraConfig(source=str(video), width_px=64, height_px=64, rate_hz=20.0, loop_file=True),
                  CameraStats())
            first = inbox.recv(10.0)
            assert first is not None and first.alt_agl_m == 50.0
            states.alt_m = 20.0  # read by the publishing thread on its next tick

            def lower() -> bool:
                f = inbox.poll()
                return f is not None and f.alt_agl_m == 20.0

            assert wait_until(lower, 10.0)
    finally:
        states.close()


def test_the_camera_service_has_no_autopilot_link() -> None:
    # Only the controller opens MAVLink: no flag, no config field, no import of it here.
    assert "mavlink" not in cs.build_parser().format_help().lower()
    assert "pymavlink" not in Path(cs.__file__).read_text() and "pymavlink" not in Path(src.__file__).read_text()


# ---------------------------------------------------------------------- visual odometry on the odometry key

# The vehicle flies north at 8 m/s, 42.5 m up, heading 1.5 rad, tilted as `state()` says: in the
# body frame that is mostly to the left (heading east of north), forward slightly negative.
ODO_ALT_M, ODO_VEL_NED = 42.5, (8.0, 0.0, 0.0)


def ground_frames(n: int, dt_s: float, size: tuple[int, int] = (320, 240)) -> list[np.ndarray]:
    """BGR views of the textured ground along the flight (one every dt_s), at the attitude of `state()`."""
    w, h = size
    return [cv2.cvtColor(view(ODO_VEL_NED[0] * dt_s * k, ODO_VEL_NED[1] * dt_s * k, ODO_ALT_M, 1.5, 0.01, -0.02,
                              w=w, h=h, gsd=0.1, rgb=False), cv2.COLOR_GRAY2BGR) for k in range(n)]


def odo_truth() -> np.ndarray:
    return ned_to_body(ODO_VEL_NED, 0.01, -0.02, 1.5)


def test_odometry_follows_the_grabbed_frames_and_blank_ones_are_invalid() -> None:
    now = [0.0]
    grabber, states, sent, odo = FakeGrabber(), ListStates(), [], []
    loop = CameraPublisher(CameraConfig(source="0", width_px=96, height_px=96), grabber, states, sent.append,
                           clock=lambda: now[0], put_odometry=odo.append)
    states.queue.append(state(ODO_ALT_M, t_s=100.0))
    loop.poll_state()
    views = ground_frames(4, 0.1)
    for k, bgr in enumerate(views):
        grabber.slot = (bgr, 0.1 * k, k + 1)
        now[0] = 0.1 * k
        assert not loop.odometry_tick()  # no state after the capture yet: wait for it to interpolate
        now[0] = 0.1 * k + cs.ATTITUDE_WAIT_S + 0.01  # none came: the state before it is used
        assert loop.odometry_tick() == (k > 0)  # the first frame has nothing to compare with
        assert not loop.odometry_tick()  # the same frame is never compared twice
    msgs = [decode(b, VisualOdometry) for b in odo]
    # At 42.5 m a frame is compared with the newest at least 0.21 s older (VisualVelocityConfig's
    # baseline): the first frame until the fourth, whose interval then spans 0.3 s.
    assert [(m.prev_frame_seq, m.frame_seq) for m in msgs] == [(1, 2), (1, 3), (1, 4)]
    for m in msgs:
        assert m.valid and m.dt_s == pytest.approx(0.1 * (m.frame_seq - m.prev_frame_seq)) and m.stamp.clock == "vehicle"
        assert np.linalg.norm(np.array(m.vel_body_frd_m_s[:2]) - odo_truth()[:2]) < 0.05 * 8.0
        assert (m.alt_agl_m, m.yaw_rad) == (ODO_ALT_M, 1.5)
    assert sent == []  # odometry never publishes camera frames
    grabber.push(0.5)  # a uniform grey frame: nothing to track
    now[0] = 0.6
    assert loop.odometry_tick()
    blank = decode(odo[-1], VisualOdometry)
    assert not blank.valid and blank.vel_body_frd_m_s == (0.0, 0.0, 0.0) and blank.quality == 0.0
    assert loop.stats.odometry_published == 4 and loop.stats.odometry_valid == 3


def test_odometry_interpolates_the_attitude_at_the_capture() -> None:
    now = [0.0]
    grabber, states, odo = FakeGrabber(), ListStates(), []
    loop = CameraPublisher(CameraConfig(source="0", width_px=96, height_px=96), grabber, states, [].append,
                           clock=lambda: now[0], put_odometry=odo.append)
    views = ground_frames(2, 0.1)
    yaws = []
    for k, bgr in enumerate(views):
        t0 = 0.1 * k
        # States at t0 - 0.01 (yaw 3.1) and t0 + 0.01 (yaw -3.1, across the +-pi seam); the capture
        # sits halfway, so its yaw is pi, not 0.
        for dt, yaw in ((-0.01, 3.1), (0.01, -3.1)):
            now[0] = t0 + dt
            states.queue.append(replace(state(ODO_ALT_M + 10 * dt, t_s=100.0 + t0 + dt), yaw_rad=yaw, roll_rad=0.0,
                                        pitch_rad=0.0))
            loop.poll_state()
            if dt < 0:
                grabber.slot = (bgr, t0, k + 1)
                assert not loop.odometry_tick()  # waits for the state after the capture
        assert loop.odometry_tick() == (k > 0)
    msg = decode(odo[-1], VisualOdometry)
    assert abs(abs(msg.yaw_rad) - math.pi) < 1e-6 and msg.alt_agl_m == pytest.approx(ODO_ALT_M)


def test_the_camera_service_publishes_visual_odometry(service: tuple, tmp_path: Path) -> None:
    b, start = service
    fps, n = 20.0, 60
    video = tmp_path / "ground.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), fps, (320, 240))
    for bgr in ground_frames(n, 1.0 / fps):
        writer.write(bgr)
    writer.release()
    states = StatePublisher(b, alt_m=ODO_ALT_M)
    msgs: list[VisualOdometry] = []
    try:
        with Inbox(b, keys.odometry("uav1"), VisualOdometry, newest_only=False) as inbox:
            stats = CameraStats()
            start(CameraConfig(source=str(video), width_px=128, height_px=128, rate_hz=2.0, odometry_rate_hz=10.0),
                  stats)

            def collect() -> bool:
                while (m := inbox.poll()) is not None:
                    msgs.append(m)
                return stats.ended and len(msgs) == stats.odometry_published

            assert wait_until(collect, 20.0), f"ended={stats.ended} odometry={stats.odometry_published} got={len(msgs)}"
    finally:
        states.close()
    assert len(msgs) >= 5, f"only {len(msgs)} odometry messages from a 3 s file"
    valid = [m for m in msgs if m.valid]
    assert len(valid) >= 0.8 * len(msgs)
    # Frames are paced by the grabber thread: on a loaded host dt jitters, so the median is judged.
    vel = np.median([m.vel_body_frd_m_s for m in valid], axis=0)
    assert np.linalg.norm(vel[:2] - odo_truth()[:2]) < 0.15 * 8.0, (vel, odo_truth())
    assert all(m.vehicle_id == "uav1" and m.alt_agl_m == ODO_ALT_M and 0 < m.dt_s < 1.0 for m in valid)
    assert [m.frame_seq for m in msgs] == sorted(m.frame_seq for m in msgs)
    assert all(m.prev_frame_seq < m.frame_seq for m in msgs)


# ---------------------------------------------------------------------- close-look crops


@pytest.mark.parametrize("rotate_deg", [0, 90])
def test_a_crop_of_the_newest_full_resolution_frame_lands_on_the_known_ground(rotate_deg: int) -> None:
    from dovesei.shared.crop import CropRefused
    from dovesei.shared.messages import CropRequest
    from dovesei.sim.camera import CameraModel, render
    from tests.sim.test_crop import MARKER_FRD_M, START, marker_world

    world, (roll, pitch) = marker_world(), (0.01, -0.02)  # the tags of `state()`
    full_rgb, _, _ = render(world, START.x_m, START.y_m, START.alt_m, START.yaw_rad, CameraModel(1600, 1200, 73.0),
                            roll_rad=roll, pitch_rad=pitch, with_labels=False, interpolation="linear")
    bgr = cv2.cvtColor(full_rgb, cv2.COLOR_RGB2BGR)
    hfov_deg = 73.0
    if rotate_deg == 90:
        # A sensor mounted sideways: it delivers the view turned back, and `--rotate 90` undoes it.
        bgr = cv2.rotate(bgr, cv2.ROTATE_90_COUNTERCLOCKWISE)
        hfov_deg = math.degrees(2 * math.atan(math.tan(math.radians(36.5)) * 1200 / 1600))
    now = [0.0]
    grabber, states = FakeGrabber(), ListStates()
    loop = CameraPublisher(CameraConfig(source="0", width_px=96, height_px=96, hfov_deg=hfov_deg,
                                        rotate_deg=rotate_deg), grabber, states, [].append, clock=lambda: now[0])
    states.queue.append(state(START.alt_m, t_s=50.0))
    loop.poll_state()
    grabber.slot = (bgr, 0.1, 1)
    now[0] = 0.2
    assert loop.tick()
    crop = loop.crop(CropRequest("uav1", 1, Stamp(50.0, "vehicle"), MARKER_FRD_M, 4.0, 128))
    rows, cols = np.nonzero(crop.image_rgb.max(axis=2) > 150)
    assert rows.size and crop.frame_seq == 0 and crop.stamp.t_s == pytest.approx(50.1)
    assert math.hypot(rows.mean() - 63.5, cols.mean() - 63.5) * crop.m_per_px < 0.1
    assert crop.source_m_per_px == pytest.approx(2 * 40.0 * math.tan(math.radians(36.5)) / 1600, rel=0.05)
    with pytest.raises(CropRefused, match="outside the camera's view"):
        loop.crop(CropRequest("uav1", 2, Stamp(50.0, "vehicle"), (35.0, 0.0), 4.0, 128))
