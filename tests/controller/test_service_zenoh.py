"""The controller service over in-process Zenoh: a test session plays sim and segmenter.

The service runs `run()` in a thread on one loopback peer; the test publishes states and heatmaps
from the other and reads commands and status back. Every wait has a deadline.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest
import zenoh

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.policies.base import Decision, Observation
from dovesei.controller.service import RunStats, build_parser, config_from_args, open_vehicle, run
from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import Inbox, is_alive, wait_until
from dovesei.shared.messages import ControllerStatus, SafetyHeatmap, Stamp, VehicleState, VelocityCommand, replace
from dovesei.shared.zconfig import loopback_config

DEADLINE_S = 10.0
BLOCK = zenoh.CongestionControl.BLOCK


def heatmap(seq: int, t_s: float, alt_m: float = 90.0) -> SafetyHeatmap:
    rng = np.random.default_rng(seq)
    prob = (rng.random((48, 48)) * 255).astype(np.uint8)
    return SafetyHeatmap("uav1", seq, Stamp(t_s, "sim"), prob, alt_m, 1.27, "simulated", True, "p", "f", 0.01)


def state(seq: int, t_s: float, await_seq: int = -1, alt_m: float = 90.0) -> VehicleState:
    return VehicleState("uav1", seq, Stamp(t_s, "sim"), alt_m, (0.0, 0.0, 0.0), await_frame_seq=await_seq)


@dataclass
class Harness:
    """The test's side: publishers for state and heatmap, inboxes for cmd and status."""

    session: zenoh.Session
    cmds: Inbox[VelocityCommand]
    statuses: Inbox[ControllerStatus]
    stop: threading.Event
    result: dict

    # Blocking under congestion, as the lockstep sim and segmenter publish: Zenoh's data queue holds
    # two 64 KB batches, so a dropping put right after a 352 px heatmap is lost whenever the
    # transmit task waits more than 1 ms for the CPU (it did in CI, and no command ever came).
    def put_state(self, msg: VehicleState | bytes) -> None:
        self.session.put(keys.state("uav1"), msg if isinstance(msg, bytes) else encode(msg), congestion_control=BLOCK)

    def put_heatmap(self, msg: SafetyHeatmap | bytes) -> None:
        self.session.put(keys.heatmap("uav1"), msg if isinstance(msg, bytes) else encode(msg), congestion_control=BLOCK)

    def next_cmd(self) -> VelocityCommand:
        cmd = self.cmds.recv(DEADLINE_S)
        assert cmd is not None, "no command from the controller before the deadline"
        return cmd

    def finish(self, thread: threading.Thread) -> RunStats:
        self.stop.set()
        thread.join(DEADLINE_S)
        assert not thread.is_alive(), "run() did not return after stop"
        if "error" in self.result:
            raise self.result["error"]
        return self.result["stats"]


def start_service(zenoh_pair, config: ControllerConfig,
                  **run_kwargs: object) -> Iterator[tuple[Harness, threading.Thread]]:
    """Start `run` in a thread and yield once its liveliness token is visible; stop it after."""
    service_session, test_session = zenoh_pair
    stop, result = threading.Event(), {}
    cmds = Inbox(test_session, keys.cmd("uav1"), VelocityCommand, newest_only=False)
    statuses = Inbox(test_session, keys.status("uav1"), ControllerStatus, newest_only=False)

    def serve() -> None:
        try:
            result["stats"] = run(service_session, config=config, stop=stop, **run_kwargs)
        except BaseException as exc:  # surfaced in the test thread by Harness.finish
            result["error"] = exc

    thread = threading.Thread(target=serve, name="controller", daemon=True)
    thread.start()
    harness = Harness(test_session, cmds, statuses, stop, result)
    try:
        # The token is declared after the service's subscribers: once seen, publishing is safe.
        assert wait_until(lambda: is_alive(test_session, "uav1", "controller", 0.5), DEADLINE_S, stop=None)
        yield harness, thread
    finally:
        stop.set()
        thread.join(DEADLINE_S)
        cmds.close()
        statuses.close()


@pytest.fixture
def lockstep_service(zenoh_pair):
    yield from start_service(zenoh_pair, ControllerConfig(lockstep=True, lockstep_heatmap_wait_s=5.0))


def test_lockstep_answers_every_state_with_the_awaited_heatmap(lockstep_service) -> None:
    h, thread = lockstep_service
    h.put_heatmap(heatmap(0, 0.0))
    h.put_state(state(0, 0.05, await_seq=0))
    cmd = h.next_cmd()
    assert (cmd.state_seq, cmd.frame_seq) == (0, 0) and cmd.sent_wall_s > 0 and cmd.latency is not None

    h.put_state(state(1, 0.10))  # nothing awaited: answered at once with the last decision
    assert (h.next_cmd().state_seq, ) == (1, )

    # The state arrives BEFORE the heatmap it awaits: the controller waits for it, then decides.
    h.put_state(state(2, 0.15, await_seq=1))
    h.put_heatmap(heatmap(1, 0.10))
    cmd = h.next_cmd()
    assert (cmd.state_seq, cmd.frame_seq) == (2, 1)

    status = h.statuses.recv(DEADLINE_S)
    assert status is not None and status.policy == "dovesei" and status.frame_seq == 0
    stats = h.finish(thread)
    assert stats.ticks == 3 and stats.commands_sent == 3 and stats.heatmaps_missed == 0
    # On stop the vehicle is told to hold: a zero command that answers no lockstep tick.
    hold = h.next_cmd()
    assert hold.vel_body_frd_m_s == (0.0, 0.0, 0.0) and hold.state_seq == -1


def test_bad_heatmap_payloads_are_counted_and_the_service_keeps_serving(lockstep_service) -> None:
    h, thread = lockstep_service
    h.put_heatmap(b"\x00not msgpack")
    h.put_heatmap(encode(state(99, 0.0)))  # a valid message of the wrong type on the heatmap key
    h.put_heatmap(heatmap(0, 0.0))
    h.put_state(state(0, 0.05, await_seq=0))
    cmd = h.next_cmd()
    assert (cmd.state_seq, cmd.frame_seq) == (0, 0)
    h.put_state(b"\x93garbage")
    h.put_state(state(1, 0.10))
    assert h.next_cmd().state_seq == 1
    stats = h.finish(thread)
    assert stats.heatmap_payloads_rejected == 2 and stats.heatmaps_received == 1
    assert stats.state_payloads_rejected == 1 and stats.ticks == 2


def test_lockstep_proceeds_blind_after_the_deadline(zenoh_pair) -> None:
    config = ControllerConfig(lockstep=True, lockstep_heatmap_wait_s=0.2, lockstep_heatmap_retry_s=0.05)
    gen = start_service(zenoh_pair, config)
    h, thread = next(gen)
    try:
        h.put_state(state(0, 0.05, await_seq=0))  # the segmenter never answers
        cmd = h.next_cmd()
        assert cmd.frame_seq == -1 and cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0)
        status = h.statuses.recv(DEADLINE_S)
        assert status is not None and status.watchdog == "hold"
        stats = h.finish(thread)
        assert stats.heatmaps_missed == 1
    finally:
        gen.close()


def test_real_time_loop_runs_on_its_own_and_flags_a_stale_state(zenoh_pair) -> None:
    config = ControllerConfig(lockstep=False, rate_hz=20.0, state_stale_after_s=0.3)
    gen = start_service(zenoh_pair, config)
    h, thread = next(gen)
    try:
        h.put_heatmap(heatmap(0, 0.0))
        h.put_state(state(5, 0.05))
        # One state, yet commands keep coming at the loop's rate, each answering state 5.
        seen = [h.next_cmd() for _ in range(3)]
        assert {c.state_seq for c in seen} == {5} and [c.seq for c in seen] == sorted({c.seq for c in seen})
        # The state never advances: within the limit plus a tick the watchdog zeroes the command.
        statuses: list[ControllerStatus] = []
        assert wait_until(lambda: (s := h.statuses.poll()) is not None and statuses.append(s) is None
                          and s.watchdog == "state_stale", DEADLINE_S)
        assert any(s.frame_seq == 0 and s.watchdog == "ok" for s in statuses)
        assert statuses[-1].vel_body_frd_m_s == (0.0, 0.0, 0.0)
        stats = h.finish(thread)
        assert stats.ticks >= 6 and len(stats.wake_lateness_s) == stats.ticks
    finally:
        gen.close()


class FakeMavlink:
    """Records what the loop asks of a flight controller (stands in for MavlinkVehicle)."""

    wakeup = None
    is_link_owner = False  # this double publishes no states of its own
    commands_during_handover = False
    rejected = 0

    def __init__(self, states: list[VehicleState]) -> None:
        self.states, self.sent, self.calls = list(states), [], []
        self.lock = threading.Lock()

    def poll_state(self) -> VehicleState | None:
        with self.lock:
            return self.states.pop(0) if self.states else None

    def send(self, cmd: VelocityCommand) -> None:
        with self.lock:
            self.sent.append(cmd)

    def connect(self, timeout_s: float) -> None:
        self.calls.append("connect")

    def hold(self) -> bool:
        self.calls.append("hold")
        return True

    def handover(self) -> bool:
        self.calls.append("handover")
        return True

    def set_landing_target(self, angle_x_rad: float, angle_y_rad: float, distance_m: float) -> None:
        self.calls.append("landing_target")

    def counters(self) -> dict:
        return {}

    def close(self) -> None:
        self.calls.append("close")

    def nav_status(self) -> None:
        return None  # no estimator to judge: trusted, as the sim

    def on_visual_odometry(self, odom: object) -> None:
        self.calls.append("odometry")


class Descend:
    name = "descend"

    def step(self, obs: Observation) -> Decision:
        return Decision((0.0, 0.0, 1.0), 0.0, "LANDING", None, 10.0, 0.5, landing=True)

    def reset(self) -> None:
        pass


def test_a_flight_controller_gets_setpoints_then_handover_then_hold_on_stop(zenoh_pair) -> None:
    states = [state(k, 0.05 * k, alt_m=22.0 - 0.5 * k) for k in range(12)]  # descends through 20 m
    vehicle = FakeMavlink(states)
    config = ControllerConfig(lockstep=False, rate_hz=50.0, state_stale_after_s=5.0)
    core = ControllerCore(config, policy=Descend())
    gen = start_service(zenoh_pair, config, vehicle=vehicle, core=core)
    h, thread = next(gen)
    try:
        h.put_heatmap(heatmap(0, 0.0, alt_m=22.0))
        assert wait_until(lambda: not vehicle.states and "handover" in vehicle.calls, DEADLINE_S)
        stats = h.finish(thread)
    finally:
        gen.close()
    assert vehicle.calls.count("handover") == 1
    assert vehicle.calls[-1] == "hold", "told to hold on stop; run() does not close a vehicle it was handed"
    # No setpoint once handed over (the 3rd state at/below 20 m, seq 6): the adapter's hand-over
    # action owns the vehicle.
    assert vehicle.sent and all(c.state_seq <= 5 for c in vehicle.sent)
    assert stats.commands_sent == len(vehicle.sent)


def test_a_missing_mavlink_adapter_is_a_clear_error(zenoh_pair, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "dovesei.controller.mavlink.vehicle", None)  # import now fails
    config = ControllerConfig(lockstep=False, timing="real", vehicle_url="udpin:127.0.0.1:14550")
    with pytest.raises(ConfigError, match="MAVLink adapter"):
        open_vehicle(zenoh_pair[0], config)


def test_the_entry_point_holds_the_vehicle_on_sigterm_and_exits_cleanly() -> None:
    """Tier 3: `dovesei-controller` as a real process (lockstep, the default with the sim);
    SIGTERM must end with a hold command."""
    with socket.socket() as probe:  # a free loopback port for the service to listen on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "dovesei.controller.service", "--listen", f"tcp/127.0.0.1:{port}",
         "--no-multicast-scouting", "--log-level", "WARNING"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        with zenoh.open(loopback_config(connect_ports=[port])) as session, \
                Inbox(session, keys.cmd("uav1"), VelocityCommand, newest_only=False) as cmds:
            assert wait_until(lambda: is_alive(session, "uav1", "controller", 0.5), 30.0), "service never came up"
            session.put(keys.state("uav1"), encode(state(0, 0.05)), congestion_control=BLOCK)
            first = cmds.recv(DEADLINE_S)
            assert first is not None and first.state_seq == 0
            proc.send_signal(signal.SIGTERM)
            hold = cmds.recv(DEADLINE_S)
            assert hold is not None and hold.state_seq == -1 and hold.vel_body_frd_m_s == (0.0, 0.0, 0.0)
            out, _ = proc.communicate(timeout=DEADLINE_S)
        assert proc.returncode == 0, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_service_steers_a_fake_autopilot_through_the_mavlink_adapter(zenoh_pair) -> None:
    """`--vehicle <pymavlink URL>`: the real adapter against the fake ArduCopter on UDP loopback."""
    from dovesei.testing.fake_autopilot import FakeAutopilot

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        udp_port = probe.getsockname()[1]
    config = ControllerConfig(lockstep=False, timing="real", vehicle_url=f"udpout:127.0.0.1:{udp_port}", vehicle_connect_timeout_s=5.0)
    with FakeAutopilot(f"udpin:127.0.0.1:{udp_port}", mode="GUIDED", armed=True, alt_m=50.0, heartbeat_hz=20) as fake:
        gen = start_service(zenoh_pair, config, core=ControllerCore(config, policy=Descend()))
        h, thread = next(gen)
        try:
            # Heatmaps must be on the vehicle's clock: take it from the status the controller publishes.
            first = h.statuses.recv(DEADLINE_S)
            assert first is not None and first.watchdog == "hold" and first.stamp.clock == "vehicle"
            h.put_heatmap(replace(heatmap(0, 0.0, alt_m=50.0), stamp=first.stamp))
            assert wait_until(lambda: any(sp.vel_m_s == (0.0, 0.0, 1.0) for sp in fake.received()[0]), DEADLINE_S)
            stats = h.finish(thread)
        finally:
            gen.close()
        assert stats.commands_sent > 0 and stats.send_errors == 0
        setpoints = fake.received()[0]
        assert setpoints[-1].vel_m_s == (0.0, 0.0, 0.0), "stop must leave the vehicle holding"
        assert {sp.frame for sp in setpoints} == {9}  # ArduPilot's MAV_FRAME_BODY_OFFSET_NED


def test_cli_flags_reach_the_config_and_pick_the_loop_for_the_vehicle() -> None:
    parser = build_parser()
    assert config_from_args(parser.parse_args([])).lockstep is True  # the sim's default mode
    assert config_from_args(parser.parse_args(["--realtime"])).lockstep is False
    assert config_from_args(parser.parse_args(["--vehicle-url", "udpin:0.0.0.0:14550"])).lockstep is False
    cfg = config_from_args(parser.parse_args([
        "--vehicle-id", "uav7", "--policy", "dovesei-nofocus", "--timing", "reference", "--rate-hz", "10",
        "--heatmap-hold-after-s", "2", "--heatmap-climb-after-s", "12", "--search-alt-m", "80",
        "--handover-action", "land", "--alt-source", "rangefinder"]))
    assert (cfg.vehicle_id, cfg.policy, cfg.timing, cfg.rate_hz) == ("uav7", "dovesei-nofocus", "reference", 10.0)
    assert (cfg.heatmap_hold_after_s, cfg.heatmap_climb_after_s, cfg.search_alt_m) == (2.0, 12.0, 80.0)
    assert (cfg.handover_action, cfg.mavlink_alt_source) == ("land", "rangefinder")
