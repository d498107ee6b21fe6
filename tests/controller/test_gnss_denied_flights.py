"""End to end: GNSS lost mid-descent on the fake ArduCopter, with each `--gnss-denied` mode.

`run()` owns the MAVLink link (udpout to the fake); the test plays the camera and the segmenter
from the state key (as the camera service tags frames): a heatmap every 0.25 s and a visual
velocity every 0.05 s measured from the fake's true motion (the camera's job, issue 23 item 3;
its own tests cover the estimator). The policy flies forward 1 m/s and down 1.5 m/s from 40 m;
GNSS is cut below 36 m. Then:

- external-nav: VISION_SPEED_ESTIMATE and VISION_POSITION_DELTA stream at >= 10 Hz, the EKF is
  switched to source set 2 (VELXY ExternalNav) and fuses them, GUIDED never leaves, the hand-over
  comes at 20 m; with VISION_SPEED_ESTIMATE alone EKF3 loses its position after posRetryTimeUseVel
  and the controller holds while the autopilot's failsafe takes over;
- attitude: ArduCopter goes GUIDED -> GUIDED_NOGPS, the controller flies attitude targets on the
  visual velocity (bounded tilt), the hand-over comes at 20 m, the EKF failsafe never lands it;
- off: the loss is reported, the controller holds: no descent, no hand-over (FS_EKF_ACTION 2,
  ALT_HOLD, so the autopilot's failsafe does not descend either; with the default LAND it would).

Every wait has a deadline; nothing asserts a tight timing.
"""

from __future__ import annotations

import logging
import math
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest
import zenoh

from dovesei.controller.mavlink import proto as mv
from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.gnss_denied import quaternion_to_euler
from dovesei.controller.policies.base import Decision, Observation
from dovesei.controller.service import RunStats, run
from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.lifecycle import Inbox, is_alive, wait_until
from dovesei.shared.messages import ControllerStatus, SafetyHeatmap, Stamp, VehicleState, VisualOdometry
from dovesei.shared.zconfig import free_port, loopback_config
from dovesei.testing.fake_autopilot import FakeAutopilot
from dovesei.testing.fake_ekf import FakeEkf

START_ALT_M = 40.0
LOSS_BELOW_M = 36.0
DEADLINE_S = 120.0  # generous: 2 shared cores, the flight itself takes ~20 s


class ForwardAndDown:
    """Forward 1 m/s and down 1.5 m/s, a target at the centre."""

    name = "forward-and-down"

    def __init__(self) -> None:
        self.steps = 0

    def step(self, obs: Observation) -> Decision:
        self.steps += 1
        return Decision((1.0, 0.0, 1.5), 0.0, "LANDING", (32.0, 32.0), 10.0, 0.5, landing=True)

    def reset(self) -> None:
        pass


class Camera(threading.Thread):
    """Camera + segmenter stand-in: heatmaps at 4 Hz, visual velocity at 20 Hz (from the fake's motion)."""

    def __init__(self, session, states: Inbox[VehicleState], fake: FakeAutopilot) -> None:
        super().__init__(name="camera", daemon=True)
        self.session, self.states, self.fake, self.stop = session, states, fake, threading.Event()
        self.newest: VehicleState | None = None
        self.heatmaps = self.odometry = 0
        self.blind = threading.Event()  # set: the camera sees nothing (quality 0)
        self.truth: list[tuple[str, tuple[float, float, float]]] = []  # (fake's mode, body FRD velocity)

    def run(self) -> None:
        prob = np.full((64, 64), 200, np.uint8)
        tick = 0
        while not self.stop.wait(0.05):
            while (s := self.states.poll()) is not None:
                self.newest = s
            if self.newest is None:
                continue
            stamp = self.newest.stamp
            roll, pitch, yaw = self.fake.attitude_rad
            vel = mv.ned_to_frd(self.fake.velocity_ned_m_s, roll, pitch, yaw)
            self.truth.append((self.fake.mode, vel))
            good = not self.blind.is_set()
            odom = VisualOdometry("uav1", self.odometry + 1, self.odometry, stamp,
                                  vel if good else (0.0, 0.0, 0.0), 0.04, 0.9 if good else 0.0, good, 0.05,
                                  self.newest.alt_agl_m)
            self.session.put(keys.odometry("uav1"), encode(odom))
            self.odometry += 1
            if tick % 5 == 0:
                hm = SafetyHeatmap("uav1", self.heatmaps, stamp, prob, self.newest.alt_agl_m, 1.27, "simulated", True,
                                   "p", "f", 0.01)
                self.session.put(keys.heatmap("uav1"), encode(hm))
                self.heatmaps += 1
            tick += 1


@dataclass
class Flight:
    fake: FakeAutopilot
    camera: Camera
    statuses: list[ControllerStatus] = field(default_factory=list)
    loss_s: float | None = None  # time.monotonic when GNSS was cut
    loss_alt_m: float | None = None
    stats: RunStats | None = None


@pytest.fixture
def fly(zenoh_pair) -> Iterator:
    """fly(mode, fake_kw, until) -> Flight: connect, fly, cut GNSS below 36 m, run until `until(flight)`."""
    service_session, test_session = zenoh_pair
    closers: list = []

    def go(mode: str, until, ekf: FakeEkf | None = None, flavour: str = "ardupilot", **config_kw: object) -> Flight:
        port = free_port(socket.SOCK_DGRAM)
        # PX4 starts in LOITER: it enters OFFBOARD only once setpoints stream (the adapter's switch).
        fake = FakeAutopilot(f"udpin:127.0.0.1:{port}", flavour=flavour, mode="GUIDED" if flavour == "ardupilot"
                             else "LOITER", armed=True, alt_m=START_ALT_M, heartbeat_hz=10, ekf=ekf)
        fake.start()
        closers.append(fake.stop)
        config = ControllerConfig(lockstep=False, timing="real", vehicle_url=f"udpout:127.0.0.1:{port}",
                                  vehicle_connect_timeout_s=10.0, state_stale_after_s=1.0, gnss_denied=mode,
                                  handover_action="hold", **config_kw)
        states = Inbox(test_session, keys.state("uav1"), VehicleState, newest_only=True)
        statuses = Inbox(test_session, keys.status("uav1"), ControllerStatus, newest_only=False, depth=4096)
        closers.extend([states.close, statuses.close])
        camera = Camera(test_session, states, fake)
        flight = Flight(fake, camera)
        stop, result = threading.Event(), {}
        policy = ForwardAndDown()

        def serve() -> None:
            try:
                result["stats"] = run(service_session, config=config, stop=stop,
                                      core=ControllerCore(config, policy=policy))
            except BaseException as exc:  # surfaced below
                result["error"] = exc

        thread = threading.Thread(target=serve, name="controller", daemon=True)
        thread.start()

        def progress() -> bool:
            while (st := statuses.poll()) is not None:
                flight.statuses.append(st)
            alt = -fake.position_ned_m[2]
            if flight.loss_s is None and alt < LOSS_BELOW_M:
                fake.lose_gnss()
                flight.loss_s, flight.loss_alt_m = time.monotonic(), alt
            return "error" in result or until(flight)

        try:
            assert wait_until(lambda: is_alive(test_session, "uav1", "controller", 0.5) or "error" in result, 15.0)
            camera.start()
            done = wait_until(progress, DEADLINE_S)
            assert "error" not in result, result.get("error")
            assert done, (f"flight did not end: fake at {fake.position_ned_m}, mode {fake.mode}, last status "
                          f"{flight.statuses[-1].reason if flight.statuses else None}")
        finally:
            stop.set()
            thread.join(15.0)
            camera.stop.set()
            camera.join(5.0)
        assert not thread.is_alive()
        if "error" in result:
            raise result["error"]
        flight.stats = result["stats"]
        while (st := statuses.poll()) is not None:
            flight.statuses.append(st)
        return flight

    yield go
    for close in reversed(closers):
        close()


def handed_over(flight: Flight) -> bool:
    return flight.loss_s is not None and any(st.state == "HANDOVER" for st in flight.statuses)


def after_loss(flight: Flight) -> list[ControllerStatus]:
    return [st for st in flight.statuses if st.gnss_lost]


def test_external_nav_keeps_guided_flying_on_the_visual_velocity_to_the_handover(fly,
                                                                                  caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    flight = fly("external-nav", handed_over)
    fake = flight.fake
    # The EKF was switched to the ExternalNav set and fused the camera's velocity; GUIDED never left.
    switches = [c for c in fake.received()[2] if c.command == mv.MAV_CMD_SET_EKF_SOURCE_SET]
    assert switches and switches[-1].params[0] == 2.0 and switches[-1].result == 0
    assert switches[0].recv_s >= flight.loss_s
    assert fake.ekf.source_set == 2 and not fake.ekf.failsafe_active
    assert fake.mode == "GUIDED" and fake.armed
    # VISION_SPEED_ESTIMATE and VISION_POSITION_DELTA at >= 10 Hz: the variance with the first, NED
    # from the body velocity; the body displacement with the second (its confidence from the variance).
    for kind in ("VISION_SPEED_ESTIMATE", "VISION_POSITION_DELTA"):
        sent = [v for v in fake.vision_speeds if v.kind == kind and v.recv_s >= flight.loss_s]
        span_s = sent[-1].recv_s - sent[0].recv_s
        assert span_s > 3.0 and (len(sent) - 1) / span_s >= 10.0, (kind, len(sent), span_s)
        assert any(abs(v.vel_m_s[0] - 1.0) < 0.3 for v in sent), kind  # heading north at 1 m/s forward
    speeds = [v for v in fake.vision_speeds if v.kind == "VISION_SPEED_ESTIMATE"]
    assert speeds[-1].covariance[0] == pytest.approx(0.04) and speeds[-1].covariance[4] == pytest.approx(0.04)
    # 0.2 m/s: confidence 87.5 (EKF3 velErr 0.1 + 0.8 x 0.125 = 0.2 m/s)
    assert [v for v in fake.vision_speeds if v.kind == "VISION_POSITION_DELTA"][-1].covariance[0] == pytest.approx(87.5, abs=1.0)
    # The status said so: GNSS lost, flying on external nav; and it descended to the hand-over.
    lost = after_loss(flight)
    assert lost and any(st.nav_source == "external-nav" for st in lost)
    assert any("external nav" in st.nav_reason for st in lost)
    assert -fake.position_ned_m[2] <= 20.5
    assert flight.stats.odometry_received > 50 and flight.stats.vehicle_link["gnss_losses"] == 1
    assert any("GNSS lost" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)


def test_attitude_flies_guided_nogps_on_the_visual_velocity_to_the_handover(fly) -> None:
    flight = fly("attitude", handed_over)
    fake = flight.fake
    assert fake.mode == "GUIDED_NOGPS" and fake.armed, fake.mode  # no EKF failsafe LAND
    assert not any(text.startswith("EKF Failsafe") for _, text in fake.statustexts_sent)
    flown = [t for t in fake.attitude_targets if t.accepted]
    assert len(flown) > 50 and all(t.type_mask == mv.ATTITUDE_TYPE_MASK_ANGLES_THRUST for t in flown)
    # Bounded tilt; descending on the climb-rate thrust scale (below 0.5); forward meant nose down.
    angles = [quaternion_to_euler(t.q) for t in flown]
    assert max(math.hypot(r, p) for r, p, _ in angles) <= math.radians(15.0) + 1e-3
    assert any(t.thrust < 0.45 for t in flown)
    assert any(p < -0.005 for _, p, _ in angles)
    # Our velocity loop held the demanded 1 m/s forward and 0 right on the visual velocity.
    nogps = [v for mode, v in flight.camera.truth if mode == "GUIDED_NOGPS"]
    late = nogps[len(nogps) // 2:]
    assert len(late) > 40
    assert float(np.median([v[0] for v in late])) == pytest.approx(1.0, abs=0.25)
    assert float(np.median([abs(v[1]) for v in late])) < 0.25
    lost = after_loss(flight)
    assert any(st.nav_source == "visual" for st in lost)
    assert -fake.position_ned_m[2] <= 20.5
    # At the hand-over it holds: level attitude target, climb rate 0 (thrust 0.5).
    assert flown[-1].thrust == pytest.approx(0.5)


def test_off_reports_the_loss_and_holds_without_descending(fly) -> None:
    def held_long_enough(flight: Flight) -> bool:
        return flight.loss_s is not None and time.monotonic() - flight.loss_s > 10.0

    # FS_EKF_ACTION 2 (ALT_HOLD): the autopilot's own failsafe does not descend blind either.
    flight = fly("off", held_long_enough, ekf=FakeEkf(fs_ekf_action=2))
    fake = flight.fake
    lost = after_loss(flight)
    assert lost, "the loss was never reported"
    assert all(st.nav_source == "none" and st.watchdog == "hold" for st in lost)
    assert all("--gnss-denied off" in st.nav_reason and "no trusted velocity source" in st.reason for st in lost)
    assert not any(st.state == "HANDOVER" for st in flight.statuses)
    # No descent after the loss was noticed (what flew before the first report is at most ~1 s of 1.5 m/s).
    assert -fake.position_ned_m[2] >= flight.loss_alt_m - 2.0 > 20.0
    assert fake.mode == "ALT_HOLD"  # the EKF failsafe fired: GUIDED needs a position
    assert any(st.position_lost for st in lost)


def blind_then_handover(marks: dict[str, float], blind_s: float, ready) -> Callable[[Flight], bool]:
    """`fly`'s end condition: once `ready(flight)` below 33 m, the camera is blind for `blind_s`
    (the times and altitudes in `marks`); the flight ends at the hand-over after it sees again."""

    def until(flight: Flight) -> bool:
        if ready(flight) and "blind_s" not in marks and -flight.fake.position_ned_m[2] < 33.0:
            flight.camera.blind.set()
            marks["blind_s"], marks["blind_alt_m"] = time.monotonic(), -flight.fake.position_ned_m[2]
        if "blind_s" in marks and "seeing_s" not in marks and time.monotonic() - marks["blind_s"] > blind_s:
            marks["blind_end_alt_m"] = -flight.fake.position_ned_m[2]
            flight.camera.blind.clear()
            marks["seeing_s"] = time.monotonic()
        return "seeing_s" in marks and handed_over(flight)

    return until


def test_a_blind_camera_stops_the_descent_until_it_sees_again(fly) -> None:
    """Attitude mode after the loss: the camera goes blind for a while; no descent then, the reason
    says why; when it sees again the descent resumes to the hand-over."""
    marks: dict[str, float] = {}
    flight = fly("attitude", blind_then_handover(marks, 5.0, lambda f: f.fake.mode == "GUIDED_NOGPS"))
    # Blind for 5 s: at most the ~0.5 s of odometry age plus a tick of descent, never the 7.5 m of 5 s.
    assert marks["blind_end_alt_m"] >= marks["blind_alt_m"] - 1.5
    blind = [st for st in flight.statuses if st.gnss_lost and not st.nav_source == "visual" and st.state != "HANDOVER"]
    assert blind and all(st.watchdog == "hold" for st in blind)
    assert any("visual velocity invalid" in st.reason for st in blind), {st.reason for st in blind}
    assert -flight.fake.position_ned_m[2] <= 20.5  # and then it went on to the hand-over


def test_external_nav_flies_back_level_while_the_camera_is_blind(fly) -> None:
    """External nav after the loss: the camera goes blind for 2 s (less than the EKF coasts before
    its failsafe) while the vehicle flies forward: the setpoints sent meanwhile fly it back the
    way it came, level, and once it sees again it descends on to the hand-over."""
    marks: dict[str, float] = {}
    # The EKF coasts as long as SITL's did (~8 s): a loaded machine's late ticks stay inside it.
    flight = fly("external-nav", blind_then_handover(marks, 2.0, lambda f: f.loss_s is not None),
                 ekf=FakeEkf(coast_s=8.0))
    assert marks["blind_end_alt_m"] >= marks["blind_alt_m"] - 1.5
    blind = [st for st in flight.statuses if "flying back over the ground the camera measured" in st.reason]
    assert blind and all(st.watchdog == "hold" and st.vel_body_frd_m_s[2] <= 0.0 for st in blind)
    assert all(st.vel_body_frd_m_s[0] < -1.0 for st in blind)  # forward was +1 m/s: back it goes
    sent = [sp for sp in flight.fake.received()[0] if marks["blind_s"] + 0.7 <= sp.recv_s <= marks["seeing_s"]]
    assert sent and all(sp.vel_m_s[2] <= 0.0 for sp in sent)
    assert any(math.hypot(sp.vel_m_s[0], sp.vel_m_s[1]) > 3.0 for sp in sent)
    assert flight.fake.mode == "GUIDED" and not flight.fake.ekf.failsafe_active
    assert -flight.fake.position_ned_m[2] <= 20.5


def test_the_controller_process_takes_gnss_denied_from_its_command_line() -> None:
    """Tier 3: `dovesei-controller --gnss-denied attitude` as a real process on a fake ArduCopter that
    loses GNSS once the controller flies it: it switches to GUIDED_NOGPS, flies attitude targets on the odometry the test
    publishes over Zenoh, says so in its status, and holds the vehicle on SIGTERM."""
    mav_port, zenoh_port = free_port(socket.SOCK_DGRAM), free_port()
    # The EKF coasts as long as SITL's did (about 8 s to "EKF variance", issue 23), not the 3 s the
    # in-process flights use: a process starved by a loaded machine must still get its chance to
    # switch modes before the failsafe, as it would on the vehicle.
    with FakeAutopilot(f"udpin:127.0.0.1:{mav_port}", flavour="ardupilot", mode="GUIDED", armed=True,
                       alt_m=START_ALT_M, heartbeat_hz=10, ekf=FakeEkf(coast_s=8.0)) as fake:
        proc = subprocess.Popen(
            [sys.executable, "-m", "dovesei.controller.service", "--vehicle-url", f"udpout:127.0.0.1:{mav_port}",
             "--gnss-denied", "attitude", "--max-tilt-deg", "12", "--state-stale-after-s", "1",
             "--listen", f"tcp/127.0.0.1:{zenoh_port}", "--no-multicast-scouting", "--log-level", "WARNING"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            with zenoh.open(loopback_config(connect_ports=[zenoh_port])) as session, \
                    Inbox(session, keys.state("uav1"), VehicleState, newest_only=True) as states, \
                    Inbox(session, keys.status("uav1"), ControllerStatus, newest_only=False, depth=4096) as statuses:
                assert wait_until(lambda: is_alive(session, "uav1", "controller", 0.5), 30.0), "never came up"
                assert wait_until(lambda: states.poll() is not None, 15.0), "no state from the controller"
                assert wait_until(lambda: bool(fake.received()[0]), 30.0), "the controller never flew the vehicle"
                fake.lose_gnss()  # mid-flight, with the controller flying it in GUIDED
                camera = Camera(session, states, fake)
                camera.start()
                seen: list[ControllerStatus] = []

                def flying_on_visual() -> bool:
                    while (st := statuses.poll()) is not None:
                        seen.append(st)
                    return fake.mode == "GUIDED_NOGPS" and any(st.nav_source == "visual" for st in seen) and \
                        sum(t.accepted for t in fake.attitude_targets) > 20
                try:
                    assert wait_until(flying_on_visual, DEADLINE_S), (fake.mode, seen[-1].reason if seen else None)
                finally:
                    camera.stop.set()
                    camera.join(5.0)
                lost = [st for st in seen if st.gnss_lost]
                assert lost and "GPS_RAW_INT fix type 1" in lost[-1].nav_reason
                flown = [t for t in fake.attitude_targets if t.accepted]
                assert max(math.hypot(*quaternion_to_euler(t.q)[:2]) for t in flown) <= math.radians(12.0) + 1e-3
                proc.send_signal(signal.SIGTERM)
                out, _ = proc.communicate(timeout=30.0)
            assert proc.returncode == 0, out
            # Told to hold on the way out: the last target asks for no climb and no descent (thrust 0.5).
            # The fake reads its socket in its own thread: the last datagram may still be on its way.
            def last_thrust() -> float:
                return [t for t in fake.attitude_targets if t.accepted][-1].thrust

            wait_until(lambda: last_thrust() == pytest.approx(0.5), 10.0)
            assert last_thrust() == pytest.approx(0.5)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def test_a_velocity_alone_lets_ekf3_lose_its_position_and_the_controller_holds(fly) -> None:
    """--external-nav-message speed: VISION_SPEED_ESTIMATE alone keeps EKF3's velocity but not its
    position past posRetryTimeUseVel (4 s here, 10 s in EKF3): the controller sees the position go,
    stops descending and says why; the EKF failsafe then takes the vehicle (LAND), which is why the
    default also sends VISION_POSITION_DELTA."""
    def failsafe(flight: Flight) -> bool:
        return any(text.startswith("EKF Failsafe") for _, text in flight.fake.statustexts_sent)

    flight = fly("external-nav", failsafe, ekf=FakeEkf(pos_retry_use_vel_s=4.0), external_nav_message="speed")
    fake = flight.fake
    assert {v.kind for v in fake.vision_speeds} == {"VISION_SPEED_ESTIMATE"} and fake.ekf.source_set == 2
    held = [st for st in flight.statuses if st.position_lost]
    assert held and all(st.watchdog == "hold" and st.nav_source == "none" for st in held if st.state != "HANDOVER")
    assert any("not fusing" in st.nav_reason and "horizontal position" in st.nav_reason for st in held)
    assert fake.mode == "LAND"


def test_px4_flies_offboard_attitude_setpoints_on_the_visual_velocity_to_the_handover(fly) -> None:
    """PX4: no mode to switch to; after the loss OFFBOARD gets attitude setpoints whose thrust is a
    collective thrust closed here around the hover thrust (the fake flies it as one)."""
    flight = fly("attitude", handed_over, flavour="px4", mavlink_allow_mode_switch=True)
    fake = flight.fake
    assert fake.mode == "OFFBOARD" and fake.armed
    flown = [t for t in fake.attitude_targets if t.accepted]
    assert len(flown) > 50 and all(t.type_mask == mv.ATTITUDE_TYPE_MASK_ANGLES_THRUST for t in flown)
    assert any(t.thrust < 0.5 for t in flown)  # less than hover: descending
    assert any(st.nav_source == "visual" for st in after_loss(flight))
    assert -fake.position_ned_m[2] <= 20.5
    nogps = [v for mode, v in flight.camera.truth if mode == "OFFBOARD"]
    late = nogps[-60:-20]
    assert float(np.median([v[0] for v in late])) == pytest.approx(1.0, abs=0.3)
