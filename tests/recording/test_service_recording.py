"""`--record` on the services that fly a real drone: the controller and the camera service write an
MCAP file while they run over in-process Zenoh, and the recording's own reader reads it back.

Each service's `run()` runs in a thread on one loopback peer (multicast scouting off, a free port:
the `zenoh_pair` fixture); the test plays the other processes from the second peer.
"""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh

from dovesei.camera import service as camera_service
from dovesei.camera.service import CameraConfig, CameraStats
from dovesei.controller import service as controller_service
from dovesei.controller.core import ControllerConfig
from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import Inbox, is_alive, wait_until
from dovesei.shared.messages import (
    CameraFrame, ControllerStatus, SafetyHeatmap, Stamp, VehicleState, VelocityCommand, VisualOdometry,
)
from dovesei.shared.recording import FlightRecording

DEADLINE_S = 10.0
BLOCK = zenoh.CongestionControl.BLOCK  # as the lockstep sim and segmenter publish: nothing lost


def heatmap(seq: int, t_s: float, vehicle_id: str = "uav1") -> SafetyHeatmap:
    prob = (np.random.default_rng(seq).random((48, 48)) * 255).astype(np.uint8)
    return SafetyHeatmap(vehicle_id, seq, Stamp(t_s, "sim"), prob, 90.0, 1.27, "simulated", True, "p", "f", 0.01)


def state(seq: int, t_s: float, await_seq: int = -1, alt_m: float = 90.0, clock: str = "sim") -> VehicleState:
    return VehicleState("uav1", seq, Stamp(t_s, clock), alt_m, (0.0, 0.0, 0.0), await_frame_seq=await_seq)


class Service:
    """A service's `run` in a thread; `stop()` ends it and re-raises what it raised."""

    def __init__(self, target, session, **kwargs: object) -> None:
        self.halt, self.result = threading.Event(), {}

        def serve() -> None:
            try:
                self.result["stats"] = target(session, stop=self.halt, **kwargs)
            except BaseException as exc:  # surfaced in the test thread by stop()
                self.result["error"] = exc

        self.thread = threading.Thread(target=serve, daemon=True)
        self.thread.start()

    def stop(self):
        self.halt.set()
        self.thread.join(DEADLINE_S)
        assert not self.thread.is_alive(), "run() did not return after stop"
        if "error" in self.result:
            raise self.result["error"]
        return self.result["stats"]


def test_controller_records_states_adopted_heatmaps_commands_and_statuses(zenoh_pair, tmp_path: Path) -> None:
    a, b = zenoh_pair
    path = tmp_path / "flight" / "controller.mcap"
    config = ControllerConfig(lockstep=True, lockstep_heatmap_wait_s=5.0, record_path=str(path))
    with Inbox(b, keys.cmd("uav1"), VelocityCommand, newest_only=False) as cmds:
        service = Service(controller_service.run, a, config=config)
        try:
            assert wait_until(lambda: is_alive(b, "uav1", "controller", 0.5), DEADLINE_S, stop=None)
            sent = [heatmap(0, 0.0), heatmap(1, 0.10)]
            b.put(keys.heatmap("uav1"), encode(heatmap(7, 0.05, vehicle_id="uav2")),
                  congestion_control=BLOCK)  # refused: never recorded
            b.put(keys.heatmap("uav1"), encode(sent[0]), congestion_control=BLOCK)
            b.put(keys.state("uav1"), encode(state(0, 0.05, await_seq=0)), congestion_control=BLOCK)
            assert cmds.recv(DEADLINE_S) is not None
            b.put(keys.state("uav1"), encode(state(1, 0.10)), congestion_control=BLOCK)
            assert cmds.recv(DEADLINE_S) is not None
            b.put(keys.heatmap("uav1"), encode(sent[1]), congestion_control=BLOCK)
            b.put(keys.state("uav1"), encode(state(2, 0.15, await_seq=1)), congestion_control=BLOCK)
            assert cmds.recv(DEADLINE_S) is not None
        finally:
            stats = service.stop()
    assert stats.ticks == 3

    rec = FlightRecording(path)
    assert rec.profile == "dovesei"
    assert rec.meta("run") == {"policy": "dovesei", "timing": config.timing, "lockstep": True, "vehicle_id": "uav1",
                               "vehicle_url": "zenoh"}
    msgs = [m for _, m in rec.messages()]
    by_type = {t: [m for m in msgs if isinstance(m, t)] for t in (VehicleState, SafetyHeatmap, VelocityCommand,
                                                                  ControllerStatus)}
    assert len(msgs) == sum(len(v) for v in by_type.values())  # nothing else was recorded
    assert [s.seq for s in by_type[VehicleState]] == [0, 1, 2]
    assert [h.seq for h in by_type[SafetyHeatmap]] == [0, 1]  # adopted ones only, each once
    for got, want in zip(by_type[SafetyHeatmap], sent):
        assert got.vehicle_id == "uav1" and np.array_equal(got.prob_safe, want.prob_safe)  # PNG is lossless
    assert [c.state_seq for c in by_type[VelocityCommand]] == [0, 1, 2]
    assert all(c.sent_wall_s > 0 for c in by_type[VelocityCommand])  # what went out, stamped when sent
    assert [s.frame_seq for s in by_type[ControllerStatus]] == [0, 0, 1]
    # File order is the controller's: the state, the heatmap the tick adopted, its command, its status.
    kinds = [type(m).__name__ for m in msgs]
    assert kinds == ["VehicleState", "SafetyHeatmap", "VelocityCommand", "ControllerStatus",
                     "VehicleState", "VelocityCommand", "ControllerStatus",
                     "VehicleState", "SafetyHeatmap", "VelocityCommand", "ControllerStatus"]


def test_controller_without_record_writes_nothing_and_a_bad_path_is_one_error(zenoh_pair, tmp_path: Path) -> None:
    a, _b = zenoh_pair
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where a folder should be")
    config = ControllerConfig(record_path=str(blocker / "x.mcap"))
    with pytest.raises(ConfigError, match=r"--record .*not-a-dir/x\.mcap: cannot write the recording"):
        controller_service.run(a, config=config, stop=threading.Event())
    assert controller_service.config_from_args(
        controller_service.build_parser().parse_args(["--record", "f.mcap"])).record_path == "f.mcap"
    assert controller_service.config_from_args(controller_service.build_parser().parse_args([])).record_path is None


def write_video(path: Path, frames: int, size: tuple[int, int] = (160, 120)) -> Path:
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (w, h))
    assert writer.isOpened(), "this OpenCV cannot write MJPG"
    for i in range(frames):
        bgr = np.zeros((h, w, 3), np.uint8)
        bgr[:, : w // 2] = (200, 0, 0)  # BGR blue left, red right
        bgr[:, w // 2:] = (0, 0, 200)
        bgr[: h // 4] += np.uint8(i)
        writer.write(bgr)
    writer.release()
    return path


def test_camera_records_published_frames_with_their_states(zenoh_pair, tmp_path: Path) -> None:
    a, b = zenoh_pair
    video = write_video(tmp_path / "flight.avi", frames=20)
    path = tmp_path / "camera.mcap"
    config = CameraConfig(source=str(video), width_px=96, height_px=96, rate_hz=10.0, record_path=str(path))
    pub = b.declare_publisher(keys.state("uav1"))
    halt = threading.Event()

    def publish_states() -> None:  # what the controller of a MAVLink vehicle does, at 50 Hz
        seq = 0
        while not halt.wait(0.02):
            pub.put(encode(state(seq, 10.0 + seq * 0.02, alt_m=40.0 + seq * 0.1, clock="vehicle")))
            seq += 1

    states_thread = threading.Thread(target=publish_states, daemon=True)
    states_thread.start()
    stats = CameraStats()
    try:
        with Inbox(b, keys.camera("uav1"), CameraFrame, newest_only=False) as inbox:
            service = Service(camera_service.run, a, config=config, stats=stats)
            live: list[CameraFrame] = []

            def ended() -> bool:
                while (f := inbox.poll()) is not None:
                    live.append(f)
                return stats.ended and len(live) == stats.published

            try:
                assert wait_until(ended, DEADLINE_S), f"ended={stats.ended} published={stats.published}"
            finally:
                service.stop()
    finally:
        halt.set()
        states_thread.join()
        pub.undeclare()

    rec = FlightRecording(path)
    assert rec.meta("camera_service")["width_px"] == 96 and rec.meta("camera_service")["source"] == str(video)
    every = [m for _, m in rec.messages()]
    # The visual odometry is recorded as published (its altitude interpolated between states).
    odometry = [m for m in every if isinstance(m, VisualOdometry)]
    assert len(odometry) == stats.odometry_published >= 3
    assert [m.frame_seq for m in odometry] == sorted(m.frame_seq for m in odometry)
    msgs = [m for m in every if not isinstance(m, VisualOdometry)]
    frames = [m for m in msgs if isinstance(m, CameraFrame)]
    states = [m for m in msgs if isinstance(m, VehicleState)]
    assert len(frames) == stats.published == len(live) >= 3
    assert 1 <= len(states) <= len(frames) and len(msgs) == len(frames) + len(states)
    assert [f.seq for f in frames] == [f.seq for f in live]
    last_state = None
    for m in msgs:
        if isinstance(m, VehicleState):
            last_state = m
            continue
        # Each frame follows the state that tagged it: its altitude, its clock.
        assert last_state is not None and m.alt_agl_m == last_state.alt_agl_m
        assert m.stamp.clock == "vehicle" and m.stamp.t_s >= last_state.stamp.t_s
    for got, want in zip(frames, live):
        assert got.image_rgb.shape == (96, 96, 3)
        # JPEG in the file: close to the published pixels, not equal.
        assert np.abs(got.image_rgb.astype(int) - want.image_rgb.astype(int)).mean() < 4.0
        left, right = got.image_rgb[60, 10].astype(int), got.image_rgb[60, 85].astype(int)
        assert left[2] > 150 > left[0] and right[0] > 150 > right[2]


def test_camera_record_flag_and_bad_path(zenoh_pair, tmp_path: Path) -> None:
    a, _b = zenoh_pair
    args = camera_service.build_parser().parse_args(["--source", "0", "--record", "cam.mcap"])
    assert camera_service.config_from_args(args).record_path == "cam.mcap"
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match="--record .*cannot write the recording"):
        camera_service.run(a, config=CameraConfig(source="0", record_path=str(blocker / "c.mcap")),
                           stop=threading.Event())
