"""The adapter's GNSS-denied messages against the fake autopilot: what goes out for each autopilot."""

from __future__ import annotations

import math
import socket
from collections.abc import Iterator

import pytest

from dovesei.controller.mavlink import proto as mv
from dovesei.controller.mavlink.vehicle import MavlinkVehicle
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.messages import Stamp, VelocityCommand, VisualOdometry
from dovesei.shared.zconfig import free_port
from dovesei.testing.fake_autopilot import FakeAutopilot
from dovesei.testing.fake_ekf import FakeEkf


def odom(seq: int, vel: tuple[float, float, float], vehicle: str = "uav1", quality: float = 0.9,
         var: float = 0.09) -> VisualOdometry:
    return VisualOdometry(vehicle, seq, seq - 1, Stamp(12.5 + 0.1 * seq, "vehicle"), vel, var, quality, True, 0.1,
                          40.0)


@pytest.fixture
def link() -> Iterator:
    opened: list = []

    def make(flavour: str, yaw_rad: float = 0.0, before=None, **kw: object) -> tuple[FakeAutopilot, MavlinkVehicle]:
        port = free_port(socket.SOCK_DGRAM)
        fake = FakeAutopilot(f"udpin:127.0.0.1:{port}", flavour=flavour, mode="GUIDED" if flavour == "ardupilot"
                             else "LOITER", armed=True, heartbeat_hz=20, yaw_rad=yaw_rad,
                             ekf=FakeEkf(coast_s=0.0)).start()
        opened.append(fake)
        if before is not None:
            before(fake)
        vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", **kw)  # type: ignore[arg-type]
        opened.append(vehicle)
        vehicle.connect(5.0)
        assert wait_until(lambda: vehicle.poll_state() is not None, 10.0)
        return fake, vehicle

    yield make
    for thing in reversed(opened):
        thing.stop() if isinstance(thing, FakeAutopilot) else thing.close()


def test_ardupilot_gets_vision_speed_in_ned_with_the_variance_and_the_capture_time(link) -> None:
    fake, vehicle = link("ardupilot", yaw_rad=math.pi / 2, gnss_denied="external-nav")  # both messages
    vehicle.on_visual_odometry(odom(1, (2.0, 0.5, 0.0)))
    vehicle.on_visual_odometry(odom(1, (2.0, 0.5, 0.0)))  # a duplicate: not sent twice
    vehicle.on_visual_odometry(odom(2, (2.0, 0.5, 0.0), vehicle="uav9"))  # another vehicle's: refused
    vehicle.on_visual_odometry(odom(3, (2.0, 0.5, 0.0), quality=0.2))  # too poor to fly on: not sent
    vehicle.on_visual_odometry(odom(4, (2.0, 0.5, 0.0)))
    assert wait_until(lambda: len(fake.vision_speeds) >= 2, 5.0)
    first = [v for v in fake.vision_speeds if v.kind == "VISION_SPEED_ESTIMATE"][0]
    assert first.kind == "VISION_SPEED_ESTIMATE" and first.usec == int((12.5 + 0.1) * 1e6)
    # Heading east: forward 2 m/s is east, right 0.5 m/s is south.
    assert first.vel_m_s == pytest.approx((-0.5, 2.0, 0.0), abs=1e-4)
    assert first.covariance == pytest.approx((0.09, 0, 0, 0, 0.09, 0, 0, 0, 0.09))
    assert wait_until(lambda: vehicle.vision_sent == 2 and len(fake.vision_speeds) == 4, 5.0)
    assert vehicle.samples_rejected["other vehicle's odometry"] == 1
    # With each, the body displacement over the frame pair (dt 0.1 s) and a confidence for which
    # EKF3's velErr (0.1 + 0.8 x (1 - c/100) m/s with its defaults) is the camera's 0.3 m/s.
    delta = [v for v in fake.vision_speeds if v.kind == "VISION_POSITION_DELTA"][0]
    assert delta.usec == first.usec and delta.vel_m_s == pytest.approx((2.0, 0.5, 0.0), abs=1e-4)
    assert delta.covariance == (75.0,)
    # A sample at 0.8 m/s (good enough to fly on) is too noisy for VISION_SPEED_ESTIMATE, which
    # ArduPilot fuses at VISO_VEL_M_NSE whatever the covariance: only the delta carries it, weighted.
    vehicle.on_visual_odometry(odom(5, (1.0, 0.0, 0.0), var=0.64))
    assert wait_until(lambda: vehicle.vision_sent == 3 and len(fake.vision_speeds) == 5, 5.0)
    newest = fake.vision_speeds[-1]
    assert newest.kind == "VISION_POSITION_DELTA" and newest.covariance == (12.0,)
    assert [v.kind for v in fake.vision_speeds].count("VISION_SPEED_ESTIMATE") == 2


def test_the_confidence_sent_makes_ekf3s_error_the_cameras() -> None:
    from dovesei.controller.gnss_denied import body_odom_confidence, speed_message_takes  # noqa: PLC0415

    for sd in (0.1, 0.3, 0.5, 0.9):
        c = body_odom_confidence(sd * sd)
        assert 0.1 + 0.8 * (1.0 - c / 100.0) == pytest.approx(sd, abs=0.005)
    assert body_odom_confidence(0.0) == 100.0 and body_odom_confidence(4.0) == 0.0
    assert speed_message_takes(0.25) and not speed_message_takes(0.26)
    with pytest.raises(ValueError):
        body_odom_confidence(float("nan"))


def test_px4_gets_odometry_with_only_a_body_velocity(link) -> None:
    fake, vehicle = link("px4", gnss_denied="external-nav")
    vehicle.on_visual_odometry(odom(1, (1.5, -0.5, 0.1)))
    assert wait_until(lambda: len(fake.vision_speeds) >= 1, 5.0)
    sample = fake.vision_speeds[0]
    assert sample.kind == "ODOMETRY" and sample.vel_m_s == pytest.approx((1.5, -0.5, 0.1), abs=1e-5)
    cov = sample.covariance
    assert cov[0] == cov[6] == cov[11] == pytest.approx(0.09) and cov[1] == 0.0  # the upper triangle's diagonal
    # PX4 has no source set to switch, and ESTIMATOR_STATUS is asked for (it has no EKF_STATUS_REPORT).
    asked = {int(c.params[0]) for c in fake.received()[2] if c.command == mv.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert mv.MSG_ID_ESTIMATOR_STATUS in asked and mv.MSG_ID_GPS_RAW_INT in asked


def test_off_sends_nothing_and_reports_the_loss(link) -> None:
    fake, vehicle = link("ardupilot")  # gnss_denied off, the default
    vehicle.on_visual_odometry(odom(1, (1.0, 0.0, 0.0)))
    assert vehicle.nav_status().velocity_trusted and not vehicle.nav_status().gnss_lost
    fake.lose_gnss()
    assert wait_until(lambda: vehicle.nav_status().gnss_lost, 5.0)
    status = vehicle.nav_status()
    assert not status.velocity_trusted and "GPS_RAW_INT fix type 1" in status.reason
    assert fake.vision_speeds == [] and not [c for c in fake.received()[2]
                                              if c.command == mv.MAV_CMD_SET_EKF_SOURCE_SET]
    assert vehicle.counters()["gnss_losses"] == 1


def test_attitude_flying_trusts_only_the_camera_even_when_gnss_returns(link) -> None:
    fake, vehicle = link("ardupilot", gnss_denied="attitude")
    vehicle.send(VelocityCommand("uav1", 0, Stamp(0.0, "vehicle"), (0.0, 0.0, 0.0)))  # dovesei flies it in GUIDED
    fake.lose_gnss()
    assert wait_until(lambda: fake.mode == "GUIDED_NOGPS", 10.0)
    fake.restore_gnss()
    assert wait_until(lambda: not vehicle.nav_status().gnss_lost, 5.0)
    status = vehicle.nav_status()  # no odometry at all: flying attitude targets blind is not trusted
    assert not status.velocity_trusted and "flying attitude targets and no visual velocity" in status.reason


def test_a_controller_started_after_the_loss_still_gets_states_from_the_barometer(link) -> None:
    """GNSS gone before we connect: LOCAL_POSITION_NED never comes, so the state is made from
    ATTITUDE and GLOBAL_POSITION_INT's relative altitude, without a position."""
    fake, vehicle = link("ardupilot", before=FakeAutopilot.lose_gnss)
    assert wait_until(lambda: (s := vehicle.poll_state()) is not None and not s.pos_valid, 5.0)
    states = []
    assert wait_until(lambda: (s := vehicle.poll_state()) is not None and states.append(s) is None, 5.0)
    # The barometric height (the EKF failsafe is landing it at 1 m/s meanwhile: compare with the truth now).
    assert states[0].alt_agl_m == pytest.approx(-fake.position_ned_m[2], abs=1.0) and not states[0].pos_valid
    assert states[0].stamp.clock == "vehicle" and fake.mode == "LAND"
    # It never saw a fix, so it cannot tell GNSS went; it sees the position gone and trusts nothing.
    assert vehicle.nav_status().position_lost and not vehicle.nav_status().velocity_trusted
    assert wait_until(lambda: vehicle.counters()["gnss_losses"] == 1, 2.0)  # counted as the loss it is


def test_booting_without_a_fix_is_not_a_loss_until_the_vehicle_is_armed(link) -> None:
    """SITL: a controller started while the autopilot boots (disarmed, no GPS fix yet, EKF without a
    position) took that for a GNSS loss, started flying attitude targets in STABILIZE and refused every
    command once the vehicle had taken off in GUIDED."""
    def booting(fake: FakeAutopilot) -> None:
        fake.set_armed(False)
        fake.lose_gnss()

    fake, vehicle = link("ardupilot", gnss_denied="attitude", before=booting)
    assert wait_until(lambda: vehicle.nav_status().position_lost, 5.0)  # it sees no position...
    assert not wait_until(lambda: vehicle.counters()["gnss_losses"] > 0, 1.5)  # ...and no loss on the ground
    fake.restore_gnss()  # the fix comes; ArduPilot arms only with a position (a pre-arm check)
    assert wait_until(lambda: not vehicle.nav_status().position_lost, 10.0)
    fake.set_armed(True)  # and the vehicle took off in GUIDED
    assert wait_until(lambda: vehicle.armed and vehicle.poll_state() is not None, 10.0)
    vehicle.send(VelocityCommand("uav1", 0, Stamp(0.0, "vehicle"), (1.0, 0.0, 0.0)))  # steered in GUIDED
    assert fake.mode == "GUIDED" and vehicle.counters()["gnss_losses"] == 0
    fake.lose_gnss()  # the real loss, in flight, is acted on
    assert wait_until(lambda: fake.mode == "GUIDED_NOGPS", 10.0)
    assert vehicle.counters()["gnss_losses"] == 1


# ---------------------------------------------------------------------- VISO_TYPE's pre-arm check


@pytest.fixture
def on_the_ground() -> Iterator:
    """A disarmed fake ArduCopter on the ground with VISO_TYPE set and ARMING_CHECK's VISION bit."""
    opened: list = []

    def make(**vehicle_kw: object) -> tuple[FakeAutopilot, MavlinkVehicle]:
        port = free_port(socket.SOCK_DGRAM)
        fake = FakeAutopilot(f"udpin:127.0.0.1:{port}", flavour="ardupilot", mode="LOITER", armed=False, alt_m=0.0,
                             boot_s=0.3, heartbeat_hz=20, statustext_period_s=0.3,
                             ekf=FakeEkf(viso_arming_check=True)).start()
        opened.append(fake)
        vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", **vehicle_kw)  # type: ignore[arg-type]
        opened.append(vehicle)
        vehicle.connect(5.0)
        return fake, vehicle

    yield make
    for thing in reversed(opened):
        thing.stop() if isinstance(thing, FakeAutopilot) else thing.close()


def test_visodom_refuses_to_arm_until_vision_data_streams(on_the_ground) -> None:
    """ArduCopter with VISO_TYPE 1: no vision message within 300 ms, no arming ("VisOdom: not
    healthy"); the camera's odometry cannot help on the ground (it measures from 1 m up)."""
    fake, vehicle = on_the_ground(gnss_denied="off")
    with pytest.raises(mv.NotSteerableError) as info:
        vehicle.arm_and_takeoff(3.0, ready_timeout_s=2.0)
    assert "PreArm: VisOdom: not healthy" in str(info.value)
    assert not fake.armed and not fake.vision_speeds


def test_external_nav_streams_a_zero_velocity_while_disarmed_so_arducopter_arms(on_the_ground) -> None:
    fake, vehicle = on_the_ground(gnss_denied="external-nav")
    vehicle.arm_and_takeoff(3.0, ready_timeout_s=20.0)
    assert fake.armed and -fake.position_ned_m[2] >= 2.9
    arms = [c for c in fake.received()[2] if c.command == mv.MAV_CMD_COMPONENT_ARM_DISARM]
    assert arms[-1].result == mv.MAV_RESULT_ACCEPTED
    armed_s = arms[-1].recv_s
    # Before the ARM: zero velocities (10 Hz asked; the rate is load-dependent), both messages, standing still.
    before = [v for v in fake.vision_speeds if v.recv_s < armed_s]
    assert {v.kind for v in before} == {"VISION_SPEED_ESTIMATE", "VISION_POSITION_DELTA"}
    assert all(v.vel_m_s == pytest.approx((0.0, 0.0, 0.0)) for v in before)
    speeds = [v for v in before if v.kind == "VISION_SPEED_ESTIMATE"]
    assert speeds
    # Once armed (and flying) the zero stops: nothing more while the adapter keeps reading 20 states.
    sent = vehicle.ground_vision_sent
    assert sent >= len(speeds)  # counted per sample sent (both messages of it)
    states = 0

    def twenty_more_states() -> bool:
        nonlocal states
        states += vehicle.poll_state() is not None
        return states >= 20

    assert wait_until(twenty_more_states, 60.0, poll_s=0.01)
    assert vehicle.ground_vision_sent == sent
    # The camera's own samples go out as before, once armed.
    vehicle.on_visual_odometry(odom(1, (1.0, 0.0, 0.0)))
    assert wait_until(lambda: vehicle.vision_sent == 1, 5.0)
