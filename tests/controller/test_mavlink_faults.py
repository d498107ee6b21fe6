"""The MAVLink adapter against hostile or broken autopilot data (fake autopilot on UDP loopback).

NaN and out-of-range samples, huge commands, a dying I/O thread, spoofed and second autopilots,
signing (unsigned, wrong key, replay), a takeoff that cannot happen, a second ground station.
Where a test asserts that something did NOT happen it waits on a deadline for it first.
"""

from __future__ import annotations

import io
import logging
import math
import socket
import time
from collections.abc import Callable, Iterator

import pytest

from dovesei.controller.mavlink import proto as mv
from dovesei.controller.mavlink.vehicle import MavlinkVehicle, NotSteerableError, VehicleConnectError
from dovesei.controller.mavlink.signing import LinkSigning
from dovesei.controller.mavlink.proto import (
    SpeedLimits,
    clamp_setpoint,
    load_signing_key,
    read_signing_timestamp,
    signing_key_from_passphrase,
    signing_timestamp_now,
)
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.messages import Stamp, VelocityCommand
from dovesei.shared.zconfig import free_port
from dovesei.testing.fake_autopilot import FakeAutopilot

KEY = signing_key_from_passphrase("correct horse battery staple")


def command(fwd: float = 0.0, right: float = 0.0, down: float = 0.0, yaw_rate: float = 0.0) -> VelocityCommand:
    return VelocityCommand(vehicle_id="uav1", seq=0, stamp=Stamp(0.0, "vehicle"),
                           vel_body_frd_m_s=(fwd, right, down), yaw_rate_rad_s=yaw_rate)


def barrier(vehicle: MavlinkVehicle, messages: int = 20) -> None:
    start = vehicle.messages_received
    assert wait_until(lambda: vehicle.messages_received >= start + messages, 5.0), "the fake stopped streaming"


Fly = Callable[..., tuple[FakeAutopilot, MavlinkVehicle]]


@pytest.fixture
def fly() -> Iterator[Fly]:
    opened: list[FakeAutopilot | MavlinkVehicle] = []

    def make(flavour: str = "ardupilot", mode: str = "GUIDED", armed: bool = True, fake_kw: dict | None = None,
             wait_state: bool = True, connect_s: float = 5.0,
             **vehicle_kw: object) -> tuple[FakeAutopilot, MavlinkVehicle]:
        port = free_port(socket.SOCK_DGRAM)
        fake = FakeAutopilot(f"udpin:127.0.0.1:{port}", flavour=flavour, mode=mode, armed=armed, heartbeat_hz=20,
                             **(fake_kw or {}))
        opened.append(fake.start())
        vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", **vehicle_kw)  # type: ignore[arg-type]
        opened.append(vehicle)
        vehicle.connect(connect_s)
        if wait_state:
            assert wait_until(lambda: vehicle.poll_state() is not None, 5.0), "no state from the fake"
        return fake, vehicle

    yield make
    for thing in reversed(opened):
        thing.stop() if isinstance(thing, FakeAutopilot) else thing.close()


# ---------------------------------------------------------------------- bad samples


@pytest.mark.parametrize(("name", "fields", "reason"), [
    ("attitude", {"roll": math.nan}, "bad ATTITUDE"),
    ("attitude", {"yaw": math.inf}, "bad ATTITUDE"),
    ("attitude", {"yawspeed": 1e9}, "bad ATTITUDE"),
    ("local_position_ned", {"z": math.nan}, "bad LOCAL_POSITION_NED"),
    ("local_position_ned", {"z": 50.0}, "bad LOCAL_POSITION_NED"),  # 50 m below the origin
    ("local_position_ned", {"z": -1e6}, "bad LOCAL_POSITION_NED"),  # 1000 km up
    ("local_position_ned", {"vx": 1e4}, "bad LOCAL_POSITION_NED"),
])
def test_a_bad_sample_is_counted_and_dropped_and_the_link_lives_on(fly: Fly, name: str, fields: dict,
                                                                   reason: str) -> None:
    fake, vehicle = fly(fake_kw={"alt_m": 40.0})
    vehicle.send(command(fwd=1.0))
    base = {"attitude": dict(time_boot_ms=1, roll=0.0, pitch=0.0, yaw=0.0, rollspeed=0.0, pitchspeed=0.0,
                             yawspeed=0.0),
            "local_position_ned": dict(time_boot_ms=1, x=0.0, y=0.0, z=-40.0, vx=0.0, vy=0.0, vz=0.0)}[name]
    for _ in range(3):
        fake.inject(name, **{**base, **fields})
    assert wait_until(lambda: vehicle.samples_rejected[reason] >= 3, 5.0), dict(vehicle.samples_rejected)
    # The I/O thread lives: still streaming, still reading, and every state it gave is sane.
    count = len(fake.received()[0])
    barrier(vehicle)
    assert len(fake.received()[0]) > count and vehicle.lost_reason is None
    vehicle.send(command(fwd=1.0))
    state = vehicle.poll_state()
    assert state is not None and 39.0 < state.alt_agl_m < 41.0
    assert all(math.isfinite(v) for v in (state.roll_rad, state.pitch_rad, state.yaw_rad, *state.vel_body_frd_m_s))


@pytest.mark.parametrize("alt_m", [140.0, 19.0])  # a 100 m jump; one forged state under the hand-over altitude
def test_a_local_position_no_multirotor_flew_to_is_dropped(fly: Fly, alt_m: float) -> None:
    fake, vehicle = fly(fake_kw={"alt_m": 40.0})
    barrier(vehicle)
    now_s = vehicle.poll_state().stamp.t_s  # the fake's boot clock: the forgery claims to be current
    for k in range(2):  # fewer than a real step needs to be believed
        fake.inject("local_position_ned", time_boot_ms=int((now_s + 0.01 * (k + 1)) * 1000), x=0.0, y=0.0,
                    z=-alt_m, vx=0.0, vy=0.0, vz=0.0)
    assert wait_until(lambda: vehicle.samples_rejected["LOCAL_POSITION_NED jump"] >= 2, 5.0), \
        dict(vehicle.samples_rejected)
    barrier(vehicle)
    seen = []
    assert wait_until(lambda: (st := vehicle.poll_state()) is not None and seen.append(st.alt_agl_m) is None
                      and len(seen) >= 3, 5.0)
    assert all(39.0 < a < 41.0 for a in seen), seen


def test_huge_commands_are_clamped_not_fatal(fly: Fly) -> None:
    fake, vehicle = fly(limits=SpeedLimits(horizontal_m_s=10.0, up_m_s=2.5, down_m_s=1.5))
    # The message layer refuses 1e299 already; the largest it lets through is still clamped here.
    vehicle.send(command(fwd=250.0, right=250.0, down=250.0, yaw_rate=50.0))
    assert wait_until(lambda: len(fake.received()[0]) >= 3, 5.0)
    sp = fake.received()[0][-1]
    assert math.hypot(sp.vel_m_s[0], sp.vel_m_s[1]) == pytest.approx(10.0, rel=1e-4)
    assert sp.vel_m_s[0] == pytest.approx(sp.vel_m_s[1], rel=1e-4)  # the direction is kept
    assert sp.vel_m_s[2] == pytest.approx(1.5) and sp.yaw_rate_rad_s == pytest.approx(math.radians(30), rel=1e-4)
    vehicle.send(command(down=-250.0))
    assert wait_until(lambda: fake.received()[0][-1].vel_m_s[2] == pytest.approx(-2.5), 5.0)
    assert vehicle.setpoints_clamped >= 2 and vehicle.lost_reason is None


def test_clamped_commands_are_counted_per_command_not_per_repeat(fly: Fly) -> None:
    """The run's stats say how often the controller asked for more than the vehicle flies (issue 26:
    54-74 % of a SITL flight's setpoints were clamped, and nothing said so)."""
    fake, vehicle = fly(limits=SpeedLimits(horizontal_m_s=10.0, up_m_s=2.5, down_m_s=1.5))
    for cmd in (command(fwd=12.0), command(down=4.0), command(fwd=3.0), command(fwd=9.0, down=1.5),
                command(right=-18.0)):
        vehicle.send(cmd)
        barrier(vehicle, 10)  # the stream repeats each one several times
    counters = vehicle.counters()
    assert counters["commands_steered"] == 5 and counters["commands_clamped"] == 3
    assert counters["setpoints_clamped"] > 3  # the repeats are counted there, not here


def test_clamp_keeps_direction_and_refuses_non_finite() -> None:
    limits = SpeedLimits(horizontal_m_s=10.0, up_m_s=2.5, down_m_s=1.5)
    vel, rate, clamped = clamp_setpoint((30.0, -40.0, 0.5), 0.0, limits)
    assert vel == pytest.approx((6.0, -8.0, 0.5)) and rate == 0.0 and clamped
    assert clamp_setpoint((1.0, 1.0, -1.0), 0.1, limits) == ((1.0, 1.0, -1.0), 0.1, False)
    assert clamp_setpoint((1e308, 1e308, 0.0), 0.0, limits)[0][0] == pytest.approx(10 / math.sqrt(2))
    with pytest.raises(ConfigError, match="finite"):
        clamp_setpoint((math.nan, 0.0, 0.0), 0.0, limits)


def test_an_io_thread_failure_is_a_reported_link_loss(fly: Fly, caplog: pytest.LogCaptureFixture) -> None:
    fake, vehicle = fly()
    vehicle.send(command(fwd=2.0))
    assert wait_until(lambda: len(fake.received()[0]) >= 3, 5.0)

    def broken() -> None:
        raise RuntimeError("parser state corrupted")

    vehicle._conn.recv_msg = broken  # the next read in the I/O thread raises
    assert wait_until(lambda: vehicle.lost_reason is not None, 5.0)
    assert "I/O thread failed" in vehicle.lost_reason and "parser state corrupted" in vehicle.lost_reason
    assert wait_until(lambda: any(r.levelno == logging.ERROR and "I/O thread failed" in r.getMessage()
                                  for r in caplog.records), 5.0)  # logged right after the reason is set
    with pytest.raises(NotSteerableError, match="I/O thread failed"):
        vehicle.send(command(fwd=1.0))  # send() says not sent
    assert vehicle.hold() is False and vehicle.poll_state() is None
    count = len(fake.received()[0])
    assert not wait_until(lambda: len(fake.received()[0]) > count, 0.5), "setpoints kept flowing"


# ---------------------------------------------------------------------- who is the autopilot


def test_a_pinned_system_id_never_locks_onto_a_spoofer_heard_first() -> None:
    port = free_port(socket.SOCK_DGRAM)
    vehicle = MavlinkVehicle(f"udpin:127.0.0.1:{port}", system_id=1)
    spoofer = FakeAutopilot(f"udpout:127.0.0.1:{port}", system=42, heartbeat_hz=50, boot_s=0)
    real = FakeAutopilot(f"udpout:127.0.0.1:{port}", system=1, heartbeat_hz=2, boot_s=0)
    spoofer.start()
    try:
        with pytest.raises(VehicleConnectError):
            vehicle.connect(0.5)  # only the spoofer speaks yet: no autopilot
        vehicle = MavlinkVehicle(f"udpin:127.0.0.1:{port}", system_id=1)
        real.start()
        vehicle.connect(5.0)
        assert vehicle._target is not None and vehicle._target.system == 1
        assert wait_until(lambda: vehicle.intruders[42] > 3, 5.0)
    finally:
        vehicle.close()
        real.stop()
        spoofer.stop()


def test_a_second_autopilot_mid_flight_is_refused_and_reported(fly: Fly, caplog: pytest.LogCaptureFixture) -> None:
    fake, vehicle = fly()
    vehicle.send(command(fwd=1.0))
    fake.spoof_heartbeat(system=77, count=5)
    assert wait_until(lambda: vehicle.intruders[77] >= 5, 5.0)
    assert vehicle._target is not None and vehicle._target.system == 1
    assert any("second autopilot (system 77" in r.getMessage() for r in caplog.records)
    vehicle.send(command(fwd=0.5))  # still steering the first one
    assert wait_until(lambda: fake.received()[0][-1].vel_m_s[0] == 0.5, 5.0)


def test_a_second_ground_station_switching_modes_stops_the_stream(fly: Fly) -> None:
    fake, vehicle = fly(allow_mode_switch=True)
    vehicle.send(command(fwd=1.0))
    fake.gcs_set_mode("LOITER")
    assert wait_until(lambda: vehicle.mode == "LOITER", 5.0)
    with pytest.raises(NotSteerableError, match="pilot override"):
        vehicle.send(command(fwd=1.0))
    count = len(fake.received()[0])
    barrier(vehicle)
    assert len(fake.received()[0]) <= count + 1 and fake.mode == "LOITER"


# ---------------------------------------------------------------------- signing


def test_a_signed_link_flies_and_persists_its_timestamp(fly: Fly, tmp_path) -> None:
    stamp_file = tmp_path / "key.timestamp"
    fake, vehicle = fly(signing_key=KEY, signing_timestamp_file=stamp_file, fake_kw={"signing_key": KEY})
    vehicle.send(command(fwd=1.5))
    assert wait_until(lambda: len(fake.received()[0]) >= 3, 5.0)  # the fake accepts only signed frames
    assert fake.signing_counts["goodsig"] > 0 and fake.signing_counts["badsig"] == 0
    assert vehicle.signing_rejected == {}
    vehicle.close()
    saved = read_signing_timestamp(stamp_file)
    assert saved >= signing_timestamp_now() - 100_000 * 60  # within a minute of now, in 10 us units
    # The next session starts after the saved one, even if the clock went back.
    stamp_file.write_text(str(saved + 10**12))
    assert LinkSigning(KEY, stamp_file, warn=lambda *a: None).initial_timestamp() == saved + 10**12 + 1


@pytest.mark.parametrize(("fake_key", "why"), [(None, "unsigned"), (signing_key_from_passphrase("other"), "wrong key")])
def test_unsigned_or_wrong_key_autopilots_are_rejected_and_counted(fly: Fly, fake_key: bytes | None,
                                                                   why: str) -> None:
    with pytest.raises(VehicleConnectError, match="failed signing"):
        fly(signing_key=KEY, fake_kw={"signing_key": fake_key}, connect_s=1.0)


def test_a_replayed_frame_is_rejected_and_counted() -> None:
    mavlink = mv.load_mavutil().mavlink
    warnings: list[str] = []
    signing = LinkSigning(KEY, None, warn=lambda kind, fmt, *args: warnings.append(fmt % args))
    rx = mavlink.MAVLink(io.BytesIO())
    rx.robust_parsing = True  # as on every mavutil link: a bad frame becomes BAD_DATA
    rx.signing.secret_key, rx.signing.timestamp = KEY, signing_timestamp_now()
    signing.attach(rx)
    tx = mavlink.MAVLink(io.BytesIO(), srcSystem=1, srcComponent=1)
    tx.signing.secret_key, tx.signing.sign_outgoing, tx.signing.timestamp = KEY, True, signing_timestamp_now()
    frame = tx.heartbeat_encode(2, 3, 0, 0, 3).pack(tx)
    assert [m.get_type() for m in rx.parse_buffer(frame)] == ["HEARTBEAT"]
    assert [m.get_type() for m in (rx.parse_buffer(frame) or [])] in ([], ["BAD_DATA"])  # the same frame again
    assert signing.rejected == {"replayed": 1} and "replayed" in warnings[0]
    # Signed with another key and a timestamp far ahead: refused as a wrong key...
    forger = mavlink.MAVLink(io.BytesIO(), srcSystem=1, srcComponent=1)
    forger.signing.secret_key, forger.signing.sign_outgoing = signing_key_from_passphrase("guess"), True
    forger.signing.timestamp = tx.signing.timestamp + 10**9
    assert [m.get_type() for m in (rx.parse_buffer(forger.heartbeat_encode(2, 3, 0, 0, 3).pack(forger)) or [])] \
        in ([], ["BAD_DATA"])
    assert signing.rejected["wrong key"] == 1
    # ...and it never advanced the stream's timestamp: the next honest frame still passes.
    assert [m.get_type() for m in rx.parse_buffer(tx.heartbeat_encode(2, 3, 0, 0, 3).pack(tx))] == ["HEARTBEAT"]


def test_signing_key_files(tmp_path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(bytes(range(32)))
    hexed = tmp_path / "hex.key"
    hexed.write_text(bytes(range(32)).hex() + "\n")
    phrase = tmp_path / "phrase.key"
    phrase.write_text("correct horse battery staple\n")
    assert load_signing_key(raw) == load_signing_key(hexed) == bytes(range(32))
    assert load_signing_key(phrase) == KEY and len(KEY) == 32
    with pytest.raises(ConfigError, match="cannot be read"):
        load_signing_key(tmp_path / "missing.key")


# ---------------------------------------------------------------------- takeoff


def test_takeoff_gives_up_naming_the_pre_arm_reasons(fly: Fly) -> None:
    fake, vehicle = fly(mode="LOITER", armed=False, wait_state=False,
                        fake_kw={"alt_m": 0.0, "boot_s": 60.0, "statustext_period_s": 0.2})
    with pytest.raises(NotSteerableError) as info:
        vehicle.arm_and_takeoff(10.0, ready_timeout_s=1.5)
    text = str(info.value)
    assert "not ready to arm within 2 s" in text and "pre-arm checks failing" in text
    assert "PreArm: EKF attitude is bad" in text and "EKF not ready" in text and "no home position" in text
    assert not fake.armed
    assert not [c for c in fake.received()[2] if c.command == mv.MAV_CMD_COMPONENT_ARM_DISARM]


def test_arming_is_retried_with_backoff_until_the_autopilot_accepts(fly: Fly) -> None:
    # Booted and healthy, but the checks ArduPilot runs only at arming refuse the first two ARMs.
    fake, vehicle = fly(mode="LOITER", armed=False, wait_state=False,
                        fake_kw={"alt_m": 0.0, "boot_s": 0.2, "arm_refusals": 2})
    vehicle.arm_and_takeoff(3.0, ready_timeout_s=20.0)
    arms = [c for c in fake.received()[2] if c.command == mv.MAV_CMD_COMPONENT_ARM_DISARM]
    assert len(arms) >= 2 and arms[-1].result == mv.MAV_RESULT_ACCEPTED
    assert all(a.result != mv.MAV_RESULT_ACCEPTED for a in arms[:-1])
    gaps = [b.recv_s - a.recv_s for a, b in zip(arms, arms[1:])]
    assert gaps[0] >= 0.9 and (len(gaps) < 2 or gaps[1] >= 1.9)  # 1 s, then 2 s
    assert fake.armed and -fake.position_ned_m[2] >= 2.8
    assert "Arm: Throttle too high" in vehicle.readiness.reasons()


# ---------------------------------------------------------------------- the personalities' own rules


def test_px4_leaves_offboard_one_second_after_our_stream_stops(fly: Fly) -> None:
    fake, vehicle = fly(flavour="px4", mode="LOITER", allow_mode_switch=True, handover="none")
    with pytest.raises(NotSteerableError, match="switch to OFFBOARD requested"):
        vehicle.send(command(fwd=1.0))
    assert wait_until(lambda: vehicle.mode == "OFFBOARD", 5.0)  # only after the zero pre-stream
    vehicle.send(command(fwd=1.0))
    vehicle.handover()  # 'none': our stream stops, PX4's COM_OF_LOSS_T (1 s) failsafe follows
    stopped_s = fake.received()[0][-1].recv_s
    assert wait_until(lambda: fake.mode == "LOITER", 5.0)
    lost_after_s = fake.received()[0][-1].recv_s - stopped_s
    assert lost_after_s < 0.2  # no setpoint after the hand-over ('none' means none)


def test_ardupilot_stops_a_guided_velocity_after_guid_timeout(fly: Fly) -> None:
    fake, vehicle = fly(mode="GUIDED", handover="none", fake_kw={"alt_m": 50.0})
    vehicle.send(command(fwd=2.0))
    assert wait_until(lambda: fake.position_ned_m[0] > 1.0, 5.0)
    vehicle.handover()
    # A setpoint already on its way when handover() returned still lands: wait until the stream
    # has been quiet for a while, then time GUID_TIMEOUT from the true last one.
    assert wait_until(lambda: time.monotonic() - fake.received()[0][-1].recv_s > 0.3, 3.0)
    last_sp_s = fake.received()[0][-1].recv_s
    # Within GUID_TIMEOUT (3 s) it keeps flying the last velocity, then it stops where it is.
    assert wait_until(lambda: fake.velocity_ned_m_s == (0.0, 0.0, 0.0), 8.0)
    stopped_after_s = time.monotonic() - last_sp_s
    assert 2.9 <= stopped_after_s <= 4.0, stopped_after_s
    assert fake.received()[0][-1].recv_s == last_sp_s  # 'none' sent nothing more
