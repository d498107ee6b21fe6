"""The sim service over in-process Zenoh: a test session plays the controller.

`run()` flies in a thread on one loopback peer; the test reads frames, states and the result from
the other (one subscriber on `dovesei/<vehicle>/*`, so the arrival order across keys is visible)
and answers with commands. Also: the external-pose mode, with the test session publishing the
vehicle states a controller of a MAVLink vehicle would, and the flags. Every wait has a deadline.
"""

from __future__ import annotations

import ast
import json
import logging
import math
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import zenoh

import dovesei.sim
from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.lifecycle import is_alive, wait_until
from dovesei.shared.messages import CameraFrame, ControllerStatus, EpisodeResult, Message, Stamp, VehicleState, replace
from dovesei.sim.camera import optical_axis_ground_m, render
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.service import SimServiceConfig, SimStats, build_parser, config_from_args, main, run
from dovesei.sim.starts import Start
from dovesei.sim.world import World
from dovesei.shared.zconfig import free_port
from dovesei.shared.errors import ConfigError
from tests.sim.test_sim_core import WEST_M, MID_Y_M, command, split_world
from tests.sim.test_sitl_truth import FakeSitlOutput, sim_state

VID = "uav1"
DEADLINE_S = 10.0


@pytest.fixture(scope="module")
def world() -> World:
    return split_world()


@dataclass
class Recorder:
    """Everything published under the vehicle's keys, in arrival order, decoded (own cmds excluded)."""

    session: zenoh.Session
    seen: list[tuple[str, Message]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._sub = self.session.declare_subscriber(f"dovesei/{VID}/*", zenoh.handlers.FifoChannel(100_000))
        self._cmd = self.session.declare_publisher(keys.cmd(VID))
        self._token: zenoh.LivelinessToken | None = None

    def announce(self) -> None:
        """The controller's liveliness token: the sim (--wait-for controller) starts once it sees it."""
        self._token = self.session.liveliness().declare_token(keys.alive(VID, "controller"))

    def next(self, deadline_s: float = DEADLINE_S) -> tuple[str, Message]:
        got: list[tuple[str, Message]] = []

        def arrived() -> bool:
            while (sample := self._sub.try_recv()) is not None:
                topic = str(sample.key_expr).rsplit("/", 1)[-1]
                if topic != "cmd":
                    got.append((topic, decode(sample.payload.to_bytes(), key=str(sample.key_expr))))
                    return True
            return False

        assert wait_until(arrived, deadline_s, poll_s=0.001), f"nothing published within {deadline_s} s"
        self.seen.append(got[0])
        return got[0]

    def until_result(self, on_state=None) -> EpisodeResult:
        """Read until the episode result, calling `on_state(state)` for each state."""
        while True:
            topic, msg = self.next()
            if topic == "episode":
                return msg
            if topic == "state" and on_state is not None:
                on_state(msg)

    def send(self, payload: Message | bytes) -> None:
        self._cmd.put(payload if isinstance(payload, bytes) else encode(payload))

    def of(self, topic: str) -> list:
        return [m for t, m in self.seen if t == topic]

    def close(self) -> None:
        if self._token is not None:
            self._token.undeclare()
        self._cmd.undeclare()
        self._sub.undeclare()


class SimThread:
    """The service's `run` in a thread, stopped and joined on exit."""

    def __init__(self, session: zenoh.Session, config: SimServiceConfig, world: World) -> None:
        self.stop, self.stats = threading.Event(), SimStats()
        self.result: EpisodeResult | None = None
        self.error: BaseException | None = None
        self.wall_s = 0.0

        def body() -> None:
            t0 = time.monotonic()
            try:
                self.result = run(session, config=config, stop=self.stop, world=world, stats=self.stats)
            except BaseException as exc:  # handed to the test thread by join()
                self.error = exc
            self.wall_s = time.monotonic() - t0

        self._thread = threading.Thread(target=body, name="sim-run", daemon=True)

    def __enter__(self) -> SimThread:
        self._thread.start()
        return self

    def join(self) -> EpisodeResult | None:
        self._thread.join(DEADLINE_S)
        assert not self._thread.is_alive(), "run() did not return"
        if self.error is not None:
            raise self.error
        return self.result

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self._thread.join(DEADLINE_S)


@pytest.fixture
def pair(zenoh_pair) -> Iterator[tuple[zenoh.Session, Recorder]]:
    sim_session, ctrl_session = zenoh_pair
    rec = Recorder(ctrl_session)
    try:
        yield sim_session, rec
    finally:
        rec.close()


def lockstep_config(**overrides) -> SimServiceConfig:
    base = dict(sim=SimConfig(vehicle_id=VID, time_limit_s=30.0), start_xy_alt_m=(WEST_M, MID_Y_M, 30.0),
                wait_for=("controller",), wait_timeout_s=DEADLINE_S, cmd_timeout_s=DEADLINE_S)
    base.update(overrides)
    return SimServiceConfig(**base)


DESCEND = (0.5, 0.0, 4.0)  # forward 0.5 m/s, down 4 m/s: 30 m -> 20 m in about 3 s of sim time


def in_process(world: World, config: SimServiceConfig) -> tuple[list[VehicleState], EpisodeResult]:
    """The same episode driven by direct calls: what the service must reproduce over Zenoh."""
    x_m, y_m, alt_m = config.start_xy_alt_m
    core = SimCore(world, Start(x_m, y_m, alt_m), config.sim)
    out, states = core.reset(), []
    while True:
        states.append(out.state)
        if out.result is not None:
            return states, out.result
        out = core.step(command(out.state, DESCEND))


def same_states(a: list[VehicleState], b: list[VehicleState]) -> bool:
    strip = lambda s: replace(s, sent_wall_s=0.0)  # noqa: E731 - the wall time of sending differs, nothing else
    return [strip(s) for s in a] == [strip(s) for s in b]


def test_lockstep_frames_before_states_result_published_same_as_in_process(pair, world: World) -> None:
    sim_session, rec = pair
    config = lockstep_config()

    def answer(state: VehicleState) -> None:
        # Stamped like a real controller's: the sim measures the command hop from sent_wall_s.
        rec.send(replace(command(state, DESCEND), frame_seq=state.await_frame_seq, sent_wall_s=time.time()))

    with SimThread(sim_session, config, world) as sim:
        rec.announce()
        published = rec.until_result(answer)
        returned = sim.join()
    states, frames = rec.of("state"), rec.of("camera")
    assert [s.seq for s in states] == list(range(len(states)))
    assert [f.seq for f in frames] == list(range(len(frames))) and len(frames) == len(states) - 1
    # Reference timing: step k publishes frame k, then state k (awaiting frame k - 1); the last
    # step is judged and has no frame; the result comes after it.
    topics = [t for t, _ in rec.seen]
    assert topics == ["camera", "state"] * len(frames) + ["state", "episode"]
    for k, (f, s) in enumerate(zip(frames, states)):
        assert f.stamp == s.stamp and s.await_frame_seq == k - 1 and f.truth is not None
    expected_states, expected_result = in_process(world, config)
    assert same_states(states, expected_states)
    assert published == returned == expected_result and published.outcome == "safe"
    assert sim.stats.commands_used == len(states) - 1 and sim.stats.commands_stale == 0
    hops = sim.stats.command_to_sim_s
    assert len(hops) == sim.stats.commands_used and all(0.0 <= h < DEADLINE_S for h in hops)
    assert sorted(sim.stats.command_to_sim_s_by_frame) == list(range(len(frames) - 1))


def test_a_controller_that_stops_answering_ends_the_episode_as_error(pair, world: World) -> None:
    sim_session, rec = pair
    config = lockstep_config(cmd_timeout_s=0.3)

    def answer_first_five(state: VehicleState) -> None:
        if state.seq < 5:
            rec.send(command(state, DESCEND))

    with SimThread(sim_session, config, world) as sim:
        rec.announce()
        published = rec.until_result(answer_first_five)
        returned = sim.join()
    assert published == returned and returned.outcome == "error"
    assert "controller" in returned.detail and "state 5" in returned.detail and keys.cmd(VID) in returned.detail
    assert [s.seq for s in rec.of("state")] == [0, 1, 2, 3, 4, 5]
    assert returned.sim_time_s == pytest.approx(0.25)


def test_bad_stale_and_foreign_commands_are_counted_and_ignored(pair, world: World) -> None:
    sim_session, rec = pair
    config = lockstep_config()

    def answer_amid_noise(state: VehicleState) -> None:
        rec.send(b"\x93not a message")  # not msgpack of a map
        rec.send(state)  # a valid message of the wrong schema
        if state.seq > 0:
            rec.send(command(replace(state, seq=state.seq - 1), DESCEND))  # a late answer to the previous state
        rec.send(replace(command(state, (9.0, 9.0, -5.0)), vehicle_id="uav2"))  # someone else's
        rec.send(command(state, DESCEND))

    with SimThread(sim_session, config, world) as sim:
        rec.announce()
        published = rec.until_result(answer_amid_noise)
        sim.join()
    answered = len(rec.of("state")) - 1
    assert sim.stats.commands_rejected == 2 * answered
    assert sim.stats.commands_stale == answered - 1 and sim.stats.commands_foreign == answered
    # The noise changed nothing: same episode as with a clean controller.
    assert published == in_process(world, config)[1]


def test_realtime_runs_on_the_wall_clock_and_brakes_when_commands_stop(pair, world: World) -> None:
    sim_session, rec = pair
    speed = 5.0
    config = lockstep_config(lockstep=False, speed=speed, sim=SimConfig(vehicle_id=VID, time_limit_s=4.0),
                             start_xy_alt_m=(WEST_M, MID_Y_M, 60.0))

    def descend_for_one_second(state: VehicleState) -> None:
        if state.stamp.t_s < 1.0:
            rec.send(command(state, (0.0, 0.0, 3.0)))

    with SimThread(sim_session, config, world) as sim:
        rec.announce()
        result = rec.until_result(descend_for_one_second)
        sim.join()
    assert result.outcome == "timeout" and result.sim_time_s == pytest.approx(4.0)
    assert sim.stats.steps == 80
    # The schedule, not the host, sets the pace: 4 s of sim time at x5 take at least ~0.8 s.
    assert sim.wall_s >= 0.9 * 4.0 / speed
    states = rec.of("state")
    assert len(states) >= 72  # real time may drop under congestion; loopback should not
    assert max(s.vel_body_frd_m_s[2] for s in states if 0.5 <= s.stamp.t_s <= 1.2) > 2.0
    late = [s for s in states if s.stamp.t_s >= 3.2]  # last command ~0.95 s + 0.5 s timeout + ~1.5 s to stop
    assert late and all(abs(s.vel_body_frd_m_s[2]) < 0.05 for s in late)
    assert max(s.alt_agl_m for s in late) - min(s.alt_agl_m for s in late) < 0.05
    assert result.final_alt_m < 58.0  # it did descend before braking


def test_waiting_for_a_missing_service_ends_as_error_before_any_state(pair, world: World) -> None:
    sim_session, rec = pair
    config = lockstep_config(wait_for=("segmenter", "controller"), wait_timeout_s=0.3)
    with SimThread(sim_session, config, world) as sim:
        rec.announce()  # the controller is up, the segmenter never comes
        published = rec.until_result()
        returned = sim.join()
    assert published == returned and returned.outcome == "error" and "segmenter" in returned.detail
    assert "controller" not in returned.detail.split(" of ")[0]
    assert rec.of("state") == [] and rec.of("camera") == []


def test_stop_ends_a_lockstep_run_cleanly_without_a_result(pair, world: World) -> None:
    sim_session, rec = pair
    with SimThread(sim_session, lockstep_config(), world) as sim:
        rec.announce()
        assert rec.next()[0] == "camera" and rec.next()[0] == "state"  # waiting for our answer now
        assert is_alive(rec.session, VID, "sim")
        sim.stop.set()
        assert sim.join() is None
    # The token went with the run (its withdrawal reaches the other session asynchronously).
    assert wait_until(lambda: not is_alive(rec.session, VID, "sim", timeout_s=0.3), 5.0)


def test_jpeg_frames_on_the_wire_keep_exact_truth(pair, world: World) -> None:
    sim_session, rec = pair
    config = lockstep_config(jpeg_quality=90, sim=SimConfig(vehicle_id=VID, time_limit_s=0.2))
    with SimThread(sim_session, config, world) as sim:
        rec.announce()
        rec.until_result(lambda s: rec.send(command(s, DESCEND)))
        sim.join()
    x_m, y_m, alt_m = config.start_xy_alt_m
    raw = SimCore(world, Start(x_m, y_m, alt_m), config.sim).reset().frame
    sent = rec.of("camera")[0]
    assert sent.image_rgb.shape == raw.image_rgb.shape and not np.array_equal(sent.image_rgb, raw.image_rgb)
    # A noise texture is JPEG's worst case; the error stays that of lossy compression, not garbage.
    assert np.abs(sent.image_rgb.astype(int) - raw.image_rgb).mean() < 40
    assert np.array_equal(sent.truth.labels, raw.truth.labels)  # labels always travel raw




class StatePublisher:
    """Plays the controller of a MAVLink vehicle: publishes its state on the state key at ~50 Hz.

    `move` changes the pose published from then on (local NED about the take-off point).
    """

    def __init__(self, session: zenoh.Session, vehicle_id: str = VID, *, alt_m: float = 60.0, yaw_rad: float = 0.3,
                 pos_valid: bool = True, t0: float | None = None) -> None:
        self._pub = session.declare_publisher(keys.state(VID))
        self._status_pub = session.declare_publisher(keys.status(VID))
        self.handover: bool | None = None  # the controller's status: None publishes none
        self.vehicle_id, self.pos_valid = vehicle_id, pos_valid
        self._ned_m = (0.0, 0.0, -alt_m)
        self._yaw_rad = yaw_rad
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.sent = 0
        self._t0 = t0  # the vehicle clock's zero (time.monotonic); None: when the thread starts
        self._thread = threading.Thread(target=self._run, name="states", daemon=True)

    def move(self, north_m: float, east_m: float, alt_m: float) -> None:
        with self._lock:
            self._ned_m = (north_m, east_m, -alt_m)

    def _run(self) -> None:
        t0 = time.monotonic() if self._t0 is None else self._t0
        while not self._stop.wait(0.02):
            with self._lock:
                ned, yaw = self._ned_m, self._yaw_rad
            st = VehicleState(self.vehicle_id, self.sent, Stamp(time.monotonic() - t0, "vehicle"), -ned[2],
                              (0.0, 0.0, 0.0), yaw_rad=yaw, mode="GUIDED", pos_valid=self.pos_valid,
                              pos_local_ned_m=ned)
            self._pub.put(encode(st))
            if self.handover is not None:
                self._status_pub.put(encode(ControllerStatus(
                    VID, self.sent, st.stamp, "double", "HANDOVER" if self.handover else "WAITING", "ok", "", -1, -1.0,
                    0.0, alt_agl_m=st.alt_agl_m, handover=self.handover)))
            self.sent += 1

    def __enter__(self) -> StatePublisher:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(DEADLINE_S)
        self._pub.undeclare()
        self._status_pub.undeclare()


def external_config(**overrides) -> SimServiceConfig:
    base = dict(sim=SimConfig(vehicle_id=VID), start_xy_alt_m=(WEST_M, MID_Y_M, 100.0), external_pose=True,
                wait_timeout_s=5.0, cmd_timeout_s=5.0)
    base.update(overrides)
    return SimServiceConfig(**base)


def test_external_pose_frames_follow_the_received_states_and_the_judge_ends_it(pair, world: World) -> None:
    sim_session, rec = pair

    def shows(frame: CameraFrame, x_m: float, y_m: float) -> bool:
        expected = render(world, x_m, y_m, frame.alt_agl_m, frame.yaw_rad)[0]
        return np.array_equal(frame.image_rgb, expected)

    def frame_at(x_m: float, y_m: float) -> CameraFrame:
        t_end = time.monotonic() + DEADLINE_S
        while time.monotonic() < t_end:
            topic, msg = rec.next()
            if topic == "camera" and shows(msg, x_m, y_m):
                return msg
        raise AssertionError(f"no frame rendered at ({x_m}, {y_m})")

    with StatePublisher(rec.session) as states, SimThread(sim_session, external_config(), world) as sim:
        first = frame_at(WEST_M, MID_Y_M)  # the local origin sits at the start
        assert first.alt_agl_m == pytest.approx(60.0) and first.yaw_rad == pytest.approx(0.3, abs=1e-6)
        assert first.stamp.clock == "vehicle" and first.truth is not None
        states.move(north_m=12.0, east_m=-7.0, alt_m=60.0)
        moved = frame_at(WEST_M - 7.0, MID_Y_M + 12.0)  # north = +y, east = +x
        assert moved.seq > first.seq
        states.move(north_m=12.0, east_m=-7.0, alt_m=15.0)  # below the hand-over altitude
        result = rec.until_result()
        assert sim.join() == result
    assert result.outcome == "safe" and result.stamp.clock == "vehicle"
    assert (result.final_x_m, result.final_y_m) == pytest.approx((WEST_M - 7.0, MID_Y_M + 12.0))
    # The sim only listens on the state key in this mode: every state seen there is the controller's.
    seen_states = rec.of("state")
    assert seen_states and all(st.mode == "GUIDED" for st in seen_states)
    assert sim.stats.poses_received > 0 and sim.stats.states_sent == 0


def test_external_pose_lands_on_the_controllers_handover_not_on_the_altitude(pair, world: World) -> None:
    sim_session, rec = pair
    with StatePublisher(rec.session) as states, SimThread(sim_session, external_config(), world) as sim:
        states.handover = False  # the controller speaks, and its policy has aborted the descent
        states.move(north_m=0.0, east_m=0.0, alt_m=15.0)  # sank through 20 m anyway
        low_frames = 0
        while low_frames < 4:  # frames rendered at 15 m: the episode goes on
            topic, msg = rec.next()
            assert topic != "episode", f"an uncommanded sink below 20 m was scored: {msg}"
            low_frames += topic == "camera" and msg.alt_agl_m == pytest.approx(15.0)
        states.handover = True
        result = rec.until_result()
        assert sim.join() == result
    assert result.outcome == "safe" and result.final_alt_m == pytest.approx(15.0)


def test_external_pose_without_states_is_an_error_naming_the_key(pair, world: World) -> None:
    sim_session, _rec = pair
    with SimThread(sim_session, external_config(wait_timeout_s=0.5), world) as sim:
        result = sim.join()
    assert result.outcome == "error" and keys.state(VID) in result.detail
    assert sim.stats.frames_sent == 0


def test_external_pose_ignores_foreign_and_positionless_states(pair, world: World) -> None:
    sim_session, rec = pair
    with StatePublisher(rec.session, vehicle_id="uav9") as foreign, \
            StatePublisher(rec.session, pos_valid=False) as positionless, \
            SimThread(sim_session, external_config(wait_timeout_s=1.0), world) as sim:
        result = sim.join()
        assert foreign.sent > 0 and positionless.sent > 0
    assert result.outcome == "error" and sim.stats.frames_sent == 0 and sim.stats.states_foreign > 0


def test_external_pose_ends_in_error_when_the_states_stop(pair, world: World) -> None:
    sim_session, rec = pair
    with SimThread(sim_session, external_config(cmd_timeout_s=0.5), world) as sim:
        with StatePublisher(rec.session):
            assert wait_until(lambda: sim.stats.frames_sent > 0, DEADLINE_S)
        result = sim.join()
    assert result.outcome == "error" and "no vehicle state" in result.detail


def test_sitl_truth_renders_and_judges_at_the_true_pose_while_frames_carry_the_estimate(pair, world: World) -> None:
    # The controller's states (the EKF) say 55 m, yaw 0.3, no local position (a GNSS-free EKF);
    # SITL's physics says 12 m north, 7 m west, 60 m, yaw 0.1. The image follows the truth, the
    # frame's altitude and attitude (what a policy reads) the estimate.
    sim_session, rec = pair
    port = free_port()
    config = external_config(sitl_truth=f"udpin:127.0.0.1:{port}")
    true_x_m, true_y_m = WEST_M - 7.0, MID_Y_M + 12.0
    sitl = FakeSitlOutput(port)
    sitl.set(sim_state(12.0, -7.0, 60.0, roll=0.05, pitch=-0.04, yaw=0.1))  # metres from the EKF origin
    with sitl, StatePublisher(rec.session, alt_m=55.0, pos_valid=False), SimThread(sim_session, config, world) as sim:
        t_end = time.monotonic() + DEADLINE_S
        frame = None
        while frame is None and time.monotonic() < t_end:
            topic, msg = rec.next()
            frame = msg if topic == "camera" else None
        assert frame is not None, "no frame"
        # Rendered where SITL is (lat/lon steps of 1e-7 deg: a millimetre off), at its altitude,
        # heading and tilt: the optical axis meets the ground where SITL's attitude points it.
        axis = optical_axis_ground_m(true_x_m, true_y_m, 60.0, 0.1, 0.05, -0.04)
        assert frame.truth.centre_world_m == pytest.approx(axis, abs=0.01)
        assert math.dist(axis, (true_x_m, true_y_m)) > 3.0  # the tilt is seen, not the estimate's level attitude

        def differs(x_m: float, y_m: float, alt_m: float, yaw_rad: float, roll_rad: float = 0.05,
                    pitch_rad: float = -0.04) -> float:
            view = render(world, x_m, y_m, alt_m, yaw_rad, roll_rad=roll_rad, pitch_rad=pitch_rad)[0]
            return float(np.abs(frame.image_rgb.astype(int) - view).mean())

        # SIM_STATE carries float32 angles and altitudes: equal to the truth within a last bit, not bytes.
        at_truth = differs(true_x_m, true_y_m, 60.0, 0.1)
        assert at_truth < 0.1 * differs(true_x_m, true_y_m, 60.0, 0.1, 0.0, 0.0)  # not level
        assert at_truth < 0.1 * differs(WEST_M, MID_Y_M, 55.0, 0.3, 0.0, 0.0)  # not at the estimate
        # What a policy reads is the estimate's: altitude, heading, attitude, the vehicle's clock.
        assert frame.alt_agl_m == pytest.approx(55.0) and frame.yaw_rad == pytest.approx(0.3)
        assert (frame.roll_rad, frame.pitch_rad) == (0.0, 0.0) and frame.stamp.clock == "vehicle"
        # The truth sinks below the hand-over altitude while the estimate still says 55 m: the
        # judge follows the truth.
        sitl.set(sim_state(12.0, -7.0, 15.0, yaw=0.1))
        result = rec.until_result()
        assert sim.join() == result
    assert result.outcome == "safe" and (result.final_x_m, result.final_y_m) == pytest.approx((true_x_m, true_y_m),
                                                                                               abs=0.05)
    # The truth is interpolated at each state's autopilot time: the first state judged below the
    # hand-over altitude may fall between the last 60 m sample and the first 15 m one (a loaded
    # machine spaces them out: 15.68 m once), never above the hand-over altitude nor below 15 m.
    assert 15.0 - 0.01 <= result.final_alt_m <= 20.0
    assert sim.stats.truth_samples > 0 and sim.stats.truth_rejected == 0 and sim.stats.states_sent == 0


def test_external_pose_builds_the_camera_pyramid_before_the_first_frame(pair, caplog) -> None:
    # Built lazily in flight, each level stalled the real-time loop 1-3 s and the first frame went
    # out 5 s late (issue 26). Every level a view up to 1.5 x the start altitude needs is built
    # before any state is awaited: rendering at 140 m afterwards builds nothing.
    sim_session, _rec = pair
    fresh = split_world()
    with caplog.at_level(logging.INFO, logger="dovesei.sim.camera"):
        with SimThread(sim_session, external_config(wait_timeout_s=0.3), fresh) as sim:
            assert sim.join().outcome == "error"
        assert any("camera pyramid level" in r.getMessage() for r in caplog.records)
        caplog.clear()
        render(fresh, WEST_M, MID_Y_M, 140.0, 0.0, roll_rad=0.3, pitch_rad=0.2)
    assert not [r.getMessage() for r in caplog.records if "camera pyramid level" in r.getMessage()]


def test_sitl_truth_is_rendered_at_the_instant_of_the_labelling_state(pair, world: World) -> None:
    # SITL flies north at 4 m/s on its boot clock; the controller's states, on the same clock, run
    # 2 s behind it. Each frame shows where SITL was at its state's stamp (8 m short of its newest
    # position), so image and label describe one moment.
    sim_session, rec = pair
    port = free_port()
    sitl = FakeSitlOutput(port)
    sitl.motion = lambda boot_s: sim_state(4.0 * boot_s, 0.0, 60.0)
    with sitl:
        time.sleep(max(0.0, sitl._boot0 + 2.2 - time.monotonic()))  # the states' clock starts at SITL's 2 s
        with StatePublisher(rec.session, pos_valid=False, t0=sitl._boot0 + 2.0), \
                SimThread(sim_session, external_config(sitl_truth=f"udpin:127.0.0.1:{port}"), world):
            seen = []
            t_end = time.monotonic() + DEADLINE_S
            while len(seen) < 4 and time.monotonic() < t_end:
                topic, msg = rec.next()
                # Kept truth begins when the sim starts (SITL's ~2.3 s): stamps from 3 s lie inside it.
                if topic == "camera" and msg.stamp.t_s > 3.0:
                    seen.append(msg)
    assert len(seen) == 4
    for frame in seen:
        north_m = frame.truth.centre_world_m[1] - MID_Y_M
        assert north_m == pytest.approx(4.0 * frame.stamp.t_s, abs=1.0), (frame.stamp.t_s, north_m)


def test_sitl_truth_that_never_comes_or_stops_is_an_error_naming_it(pair, world: World) -> None:
    sim_session, rec = pair
    port = free_port()
    url = f"udpin:127.0.0.1:{port}"
    with StatePublisher(rec.session), SimThread(sim_session, external_config(sitl_truth=url, wait_timeout_s=0.5),
                                                  world) as sim:
        result = sim.join()
    assert result.outcome == "error" and f"no SIM_STATE from SITL on {url}" in result.detail
    assert sim.stats.frames_sent == 0
    sitl = FakeSitlOutput(port)
    sitl.set(sim_state(0.0, 0.0, 60.0))
    with sitl, StatePublisher(rec.session), \
            SimThread(sim_session, external_config(sitl_truth=url, cmd_timeout_s=0.5), world) as sim:
        assert wait_until(lambda: sim.stats.frames_sent > 0, DEADLINE_S)
        sitl.streaming = False  # SITL stopped; the controller's states go on
        result = sim.join()
    assert result.outcome == "error" and f"no SIM_STATE from SITL on {url} for 0.5 s" in result.detail


def test_sitl_truth_needs_the_camera_mode_and_a_udp_listener() -> None:
    c = config_from_args(build_parser().parse_args(["--external-pose", "--sitl-truth", "udpin:127.0.0.1:14552"]))
    assert c.sitl_truth == "udpin:127.0.0.1:14552"
    with pytest.raises(ConfigError, match="--sitl-truth applies to the camera mode only"):
        SimServiceConfig(sitl_truth="udpin:127.0.0.1:14552")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--external-pose", "--sitl-truth", "udpout:127.0.0.1:14552"])


def test_odometry_after_the_result_needs_the_camera_mode_with_odometry() -> None:
    c = config_from_args(build_parser().parse_args(["--external-pose", "--odometry-rate-hz", "10",
                                                    "--odometry-after-result-s", "110"]))
    assert c.odometry_after_result_s == 110.0
    with pytest.raises(ConfigError, match="--odometry-after-result-s applies to the camera mode with odometry"):
        config_from_args(build_parser().parse_args(["--external-pose", "--odometry-after-result-s", "110"]))
    with pytest.raises(ConfigError, match="--odometry-after-result-s"):
        SimServiceConfig(external_pose=True, odometry_after_result_s=-1.0)


def test_external_pose_flag_takes_no_url() -> None:
    assert config_from_args(build_parser().parse_args(["--external-pose"])).external_pose is True
    assert config_from_args(build_parser().parse_args([])).external_pose is False
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--external-pose", "udpin:0.0.0.0:14551"])


def test_flags_build_the_config() -> None:
    args = build_parser().parse_args([
        "--vehicle-id", "uav7", "--world", "synthetic:seed=3", "--start", "120,80.5", "--timing", "real",
        "--realtime", "--speed", "4", "--frame-period-s", "1.0", "--latency-s", "0.2", "--jpeg-quality", "80",
        "--no-truth", "--wait-for", "segmenter,controller", "--cmd-timeout-s", "2", "--handover-alt-m", "15"])
    c = config_from_args(args)
    assert c.sim.vehicle_id == "uav7" and c.world == "synthetic:seed=3" and c.start_xy_alt_m == (120.0, 80.5, 100.0)
    assert not c.lockstep and c.speed == 4.0 and c.jpeg_quality == 80 and not c.sim.attach_truth
    assert (c.sim.period_s, c.sim.delay_s, c.sim.handover_alt_m) == (1.0, 0.2, 15.0)
    assert c.wait_for == ("segmenter", "controller") and c.cmd_timeout_s == 2.0
    default = config_from_args(build_parser().parse_args([]))
    assert default.lockstep and default.start_xy_alt_m is None and default.sim.timing == "reference"


@pytest.mark.parametrize("argv", [["--start", "1"], ["--start", "a,b"], ["--wait-for", "camera"],
                                  ["--speed", "0"], ["--start", "1,2", "--start-seed", "3"]])
def test_bad_flags_are_refused(argv: list[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(argv)


def test_main_exits_1_when_the_episode_ends_in_error(tmp_path: Path) -> None:
    # A real world (the Dubai tile shipped in the package, by its alias) and a controller that
    # never comes: error, exit status 1.
    argv = ["--world", "dubai", "--wait-for", "controller", "--wait-timeout-s", "0.3", "--no-multicast-scouting",
            "--listen", f"tcp/127.0.0.1:{free_port()}", "--log-level", "WARNING",
            "--stats-out", str(tmp_path / "stats" / "sim.json")]
    # main installs SIGINT/SIGTERM handlers: put pytest's back afterwards.
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert main(argv) == 1
        stats = json.loads((tmp_path / "stats" / "sim.json").read_text())
        assert stats["steps"] == 0 and stats["states_sent"] == 0 and stats["command_to_sim_s"] == []
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


def test_no_sim_module_talks_mavlink() -> None:
    # Only the controller opens the autopilot's link (issue 9): the sim never imports the controller,
    # and pymavlink only in the SITL truth reader, which binds its own SITL output (udpin only,
    # tested above) and parses with the dialect module, never mavutil's connections.
    for path in Path(dovesei.sim.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n.startswith("dovesei.controller") for n in names), f"{path.name}: {names}"
            if path.name == "sitl_truth.py":
                assert not any(n.startswith("pymavlink") and "dialects.v20" not in n for n in names), names
            else:
                assert not any(n.startswith("pymavlink") for n in names), f"{path.name}: {names}"


def test_the_controllers_status_gives_the_judge_its_confirmed_ground(pair, world: World) -> None:
    """Over Zenoh the sim takes the controller's status (its confirming look: frame 0, 40 px above
    the centre) and its result carries the touchdown error measured from that frame's own pose,
    as the in-process runner measures it."""
    from dovesei.shared.messages import ControllerStatus  # lazy: only this test sends one

    sim_session, rec = pair
    config = lockstep_config()
    status_pub = rec.session.declare_publisher(keys.status(VID))
    look = dict(confirmed_valid=True, confirmed_frame_seq=0, confirmed_row_px=175.5 - 40.0, confirmed_col_px=175.5)

    def answer(state: VehicleState) -> None:
        status_pub.put(encode(ControllerStatus(VID, state.seq, state.stamp, "clearance", "DESCEND", "ok", "", 0, 0.0,
                                               1.0, **look)))
        rec.send(replace(command(state, DESCEND), frame_seq=state.await_frame_seq, sent_wall_s=time.time()))

    try:
        with SimThread(sim_session, config, world) as sim:
            rec.announce()
            published = rec.until_result(answer)
            sim.join()
    finally:
        status_pub.undeclare()
    x_m, y_m, alt_m = config.start_xy_alt_m
    core = SimCore(world, Start(x_m, y_m, alt_m), config.sim)
    out = core.reset()
    while out.result is None:
        core.note_status(ControllerStatus(VID, 0, out.state.stamp, "clearance", "DESCEND", "ok", "", 0, 0.0, 1.0,
                                          **look))
        out = core.step(command(out.state, DESCEND))
    expected = out.result
    assert expected.touchdown_error_valid and expected.touchdown_error_m > 3.0
    assert published.confirmed_valid and published.touchdown_error_valid
    assert (published.confirmed_x_m, published.confirmed_y_m) == pytest.approx((expected.confirmed_x_m,
                                                                                expected.confirmed_y_m))
    assert published.touchdown_error_m == pytest.approx(expected.touchdown_error_m)
