"""The sim's SITL truth reader against a fake SITL output: real UDP, real MAVLink 2 packets.

`FakeSitlOutput` plays one ArduPilot SITL output (`--serial2 udpclient:127.0.0.1:PORT`): it sends
the autopilot's HEARTBEAT, answers MAV_CMD_REQUEST_MESSAGE for GPS_GLOBAL_ORIGIN once its EKF has
an origin, and streams SIM_STATE at ~50 Hz only once asked with MAV_CMD_SET_MESSAGE_INTERVAL, as
ArduPilot does (SIM_STATE is in no stream). Its pose is set in metres about CMAC, the harness's
home, and converted with ArduPilot's own scaling.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import pytest

from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.zconfig import free_port
from dovesei.sim.sitl_truth import LATLON_TO_M, MSG_ID_GPS_GLOBAL_ORIGIN, MSG_ID_SIM_STATE, Origin, SitlTruth, parse_truth_url, sample_problem, \
    true_pose

HOME_LAT_E7, HOME_LON_E7, HOME_ALT_M = -353632610, 1491652299, 584.09  # CMAC, as SITL reports it on the ground
DEADLINE_S = 10.0


def _mavlink2():
    from pymavlink.dialects.v20 import ardupilotmega  # noqa: PLC0415 (the fake needs the dialect only here)

    return ardupilotmega


def sim_state(north_m: float = 0.0, east_m: float = 0.0, alt_agl_m: float = 0.0, *, roll: float = 0.0,
              pitch: float = 0.0, yaw: float = 0.0, vel=(0.0, 0.0, 0.0), lat_e7: int | None = None):
    """A SIM_STATE message at a pose about CMAC (ArduPilot 4.6 puts 1e-7 deg in the float lat/lon too)."""
    lat = HOME_LAT_E7 + round(north_m / LATLON_TO_M) if lat_e7 is None else lat_e7
    lon = HOME_LON_E7 + round(east_m / (LATLON_TO_M * math.cos(math.radians(HOME_LAT_E7 * 1e-7))))
    return _mavlink2().MAVLink_sim_state_message(
        1.0, 0.0, 0.0, 0.0, roll, pitch, yaw, 0.0, 0.0, -9.8, 0.0, 0.0, 0.0, float(lat), float(lon),
        HOME_ALT_M + alt_agl_m, 0.0, 0.0, vel[0], vel[1], vel[2], lat, lon)


class FakeSitlOutput:
    """One SITL output sending to `udpin:127.0.0.1:port`; streams SIM_STATE once asked."""

    def __init__(self, port: int, *, system: int = 1, has_origin: bool = True) -> None:
        self.port, self.has_origin = port, has_origin
        self._mav = _mavlink2().MAVLink(None, srcSystem=system, srcComponent=1)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.02)
        self._lock = threading.Lock()
        self._state = sim_state()
        self.motion = None  # or a function of the boot clock (s) giving the SIM_STATE to send then
        self._boot0 = time.monotonic()
        self.requests: list = []  # COMMAND_LONGs received
        self.sent_states = 0
        self.streaming = True  # False: stop sending SIM_STATE (SITL gone)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fake-sitl", daemon=True)

    def set(self, msg) -> None:
        with self._lock:
            self._state = msg

    def send(self, msg) -> None:
        self._sock.sendto(msg.pack(self._mav), ("127.0.0.1", self.port))

    def _run(self) -> None:
        parser = _mavlink2().MAVLink(None)
        last_hb = 0.0
        while not self._stop.is_set():
            if time.monotonic() - last_hb > 0.5:
                self.send(_mavlink2().MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3))  # a quadrotor, ArduPilot
                last_hb = time.monotonic()
            try:
                data, _ = self._sock.recvfrom(65536)
                asks = [m for m in parser.parse_buffer(data) or () if m.get_type() == "COMMAND_LONG"]
                self.requests += asks
                if self.has_origin and any(a.command == 512 and a.param1 == 49 for a in asks):
                    self.send(_mavlink2().MAVLink_gps_global_origin_message(
                        HOME_LAT_E7, HOME_LON_E7, round(HOME_ALT_M * 1000), 0))
            except TimeoutError:
                pass
            asked = {int(r.param1) for r in self.requests if r.command == 511}
            if MSG_ID_SIM_STATE in asked and self.streaming:
                boot_s = time.monotonic() - self._boot0
                with self._lock:
                    msg = self._state if self.motion is None else self.motion(boot_s)
                if 30 in asked:  # ATTITUDE, from the same pass: what dates the SIM_STATE beside it
                    self.send(_mavlink2().MAVLink_attitude_message(int(boot_s * 1000), msg.roll, msg.pitch, msg.yaw,
                                                                   0.0, 0.0, 0.0))
                self.send(msg)
                self.sent_states += 1

    def __enter__(self) -> FakeSitlOutput:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(DEADLINE_S)
        self._sock.close()


def test_the_url_must_be_a_udp_listener() -> None:
    assert parse_truth_url("udpin:127.0.0.1:14552") == ("127.0.0.1", 14552)
    for bad in ("udpout:127.0.0.1:14552", "tcp:127.0.0.1:5762", "udpin:127.0.0.1", "udpin::14552",
                "udpin:127.0.0.1:0", "/dev/ttyACM0", "", None):
        with pytest.raises(ConfigError, match="--sitl-truth .*udpin:HOST:PORT"):
            parse_truth_url(bad)


def test_positions_are_metres_from_the_origin_with_ardupilots_scaling() -> None:
    origin = Origin(HOME_LAT_E7, HOME_LON_E7, HOME_ALT_M)
    pose = true_pose(sim_state(120.0, -45.0, 37.5, roll=0.1, pitch=-0.2, yaw=3.5, vel=(1.0, 2.0, -0.5)), origin, 7.0)
    # 1e-7 degree steps: the round trip is good to about a centimetre.
    assert (pose.north_m, pose.east_m) == pytest.approx((120.0, -45.0), abs=0.02)
    assert pose.alt_agl_m == pytest.approx(37.5, abs=1e-3)
    assert (pose.roll_rad, pose.pitch_rad) == pytest.approx((0.1, -0.2))
    assert pose.yaw_rad == pytest.approx(3.5 - 2 * math.pi)  # wrapped into (-pi, pi]
    assert pose.vel_ned_m_s == pytest.approx((1.0, 2.0, -0.5)) and pose.recv_monotonic_s == 7.0
    # The same distance with a spherical-earth formula: within 0.1 % at 130 m.
    assert math.hypot(pose.north_m, pose.east_m) == pytest.approx(math.hypot(120.0, 45.0), rel=1e-3)


@pytest.mark.parametrize("fields, problem", [
    (dict(lat_e7=0), "lat_int"), (dict(lat_e7=950_000_000), "out of range"), (dict(roll=math.nan), "non-finite"),
    (dict(alt_agl_m=math.inf), "non-finite"), (dict(alt_agl_m=50_000.0), "altitude"), (dict(yaw=9.0), "attitude"),
    (dict(vel=(500.0, 0.0, 0.0)), "speed"),
])
def test_a_broken_sample_is_named(fields: dict, problem: str) -> None:
    msg = sim_state(**fields)
    if fields.get("lat_e7") == 0:
        msg.lon_int = 0
    assert problem in sample_problem(msg)
    assert sample_problem(sim_state(10.0, 10.0, 10.0)) == ""


def test_the_reader_asks_for_sim_state_and_follows_it() -> None:
    port = free_port()
    with SitlTruth(f"udpin:127.0.0.1:{port}", rate_hz=50.0) as truth, FakeSitlOutput(port) as sitl:
        # Nothing flows until asked: the reader asks the heartbeat's system for message 108 at 50 Hz.
        assert wait_until(lambda: truth.newest() is not None, DEADLINE_S)
        asks = {(a.command, a.param1): a for a in sitl.requests}
        assert asks[(511, MSG_ID_SIM_STATE)].param2 == pytest.approx(20_000.0)
        assert (512, MSG_ID_GPS_GLOBAL_ORIGIN) in asks and truth.requests_sent >= 2
        assert all((a.target_system, a.target_component) == (1, 1) for a in sitl.requests)
        assert truth.origin == Origin(HOME_LAT_E7, HOME_LON_E7, pytest.approx(HOME_ALT_M))
        sitl.set(sim_state(30.0, 40.0, 80.0, yaw=0.5))
        assert wait_until(lambda: truth.newest().alt_agl_m > 79.0, DEADLINE_S)
        pose = truth.newest()
        assert (pose.north_m, pose.east_m, pose.yaw_rad) == pytest.approx((30.0, 40.0, 0.5), abs=0.02)
        sitl.set(sim_state(30.0, 40.0, 80.0, roll=math.nan))  # refused: the last good pose stays
        assert wait_until(lambda: truth.rejected > 3, DEADLINE_S)
        assert truth.newest().north_m == pytest.approx(30.0, abs=0.02)
    assert truth.samples > 0 and truth.error is None


def test_the_truth_is_dated_on_the_autopilots_clock_and_read_at_a_states_instant() -> None:
    # The fake flies north at 10 m/s on its boot clock; SIM_STATE has no time, the ATTITUDE sent
    # with it does. `at(t)` gives the pose of that instant, between samples by interpolation.
    port = free_port()
    with SitlTruth(f"udpin:127.0.0.1:{port}") as truth, FakeSitlOutput(port) as sitl:
        sitl.motion = lambda boot_s: sim_state(10.0 * boot_s, 0.0, 50.0, pitch=0.1 * math.sin(boot_s))
        assert wait_until(lambda: truth.newest() is not None and truth.newest().boot_s is not None, DEADLINE_S)
        assert any(a.command == 511 and a.param1 == 30 for a in sitl.requests)
        assert wait_until(lambda: truth.newest().boot_s > 1.5, DEADLINE_S)
        now_s = truth.newest().boot_s
        for back_s in (0.05, 0.333, 1.0):
            pose = truth.at(now_s - back_s)
            # 1e-7 deg steps and the ATTITUDE-to-SIM_STATE gap on loopback: well within 0.3 m (30 ms).
            assert pose.north_m == pytest.approx(10.0 * (now_s - back_s), abs=0.3), back_s
            assert pose.pitch_rad == pytest.approx(0.1 * math.sin(now_s - back_s), abs=0.01)
        # Outside what is kept: the nearest end, never an extrapolation.
        assert truth.at(now_s + 5.0).north_m == pytest.approx(truth.newest().north_m, abs=0.5)
        assert truth.at(-100.0).boot_s >= 0.0


def test_without_the_ekf_origin_no_pose_is_made_up() -> None:
    # `dovesei up --takeoff` starts the sim after the climb: the first sample is no origin.
    port = free_port()
    with SitlTruth(f"udpin:127.0.0.1:{port}") as truth, FakeSitlOutput(port, has_origin=False) as sitl:
        sitl.set(sim_state(5.0, 5.0, 100.0))
        assert wait_until(lambda: sitl.sent_states > 20, DEADLINE_S)
        assert truth.newest() is None and truth.origin is None
        origin_asks = [a for a in sitl.requests if a.command == 512 and a.param1 == MSG_ID_GPS_GLOBAL_ORIGIN]
        assert origin_asks
        sitl.has_origin = True  # the EKF got its first fix: the next ask is answered
        assert wait_until(lambda: truth.newest() is not None, DEADLINE_S)
        assert truth.newest().alt_agl_m == pytest.approx(100.0, abs=1e-3)
        assert truth.newest().north_m == pytest.approx(5.0, abs=0.02)


def test_another_systems_sim_state_is_ignored() -> None:
    port = free_port()
    with SitlTruth(f"udpin:127.0.0.1:{port}") as truth, FakeSitlOutput(port) as ours:
        assert wait_until(lambda: truth.newest() is not None, DEADLINE_S)
        other = FakeSitlOutput(port, system=7)
        other.requests = list(ours.requests)  # stream without being asked
        other.set(sim_state(500.0, 0.0, 90.0))
        with other:
            assert wait_until(lambda: other.sent_states > 20, DEADLINE_S)
        assert truth.newest().north_m == pytest.approx(0.0, abs=0.02)


def test_a_taken_port_is_one_line_naming_the_flag() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 0))
        port = holder.getsockname()[1]
        with pytest.raises(ConfigError, match=f"--sitl-truth .*cannot bind 127.0.0.1:{port}"):
            SitlTruth(f"udpin:127.0.0.1:{port}").start()
