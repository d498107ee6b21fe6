"""The pure GNSS-denied pieces: estimator flags, the odometry gate, the judgement per mode, the attitude loop."""

from __future__ import annotations

import dataclasses
import math

import pytest

from dovesei.controller.mavlink import proto as mv
from dovesei.controller.core import ControllerConfig, ControllerCore, Mode
from dovesei.controller.gnss_denied import (
    AttitudeGains,
    AttitudeLoop,
    NavJudge,
    NavRetreat,
    NavStatus,
    OdometryGate,
    OdometryLimits,
    ekf_health,
    euler_to_quaternion,
    quaternion_to_euler,
    vision_speed_covariance,
)
from dovesei.controller.policies.base import Decision, Observation
from dovesei.shared.errors import ConfigError
from dovesei.shared.frames import to_ne
from dovesei.shared.messages import SafetyHeatmap, Stamp, VehicleState, VisualOdometry

import numpy as np

GOOD_FLAGS = (mv.EKF_ATTITUDE | mv.EKF_VELOCITY_HORIZ | mv.EKF_VELOCITY_VERT | mv.EKF_POS_HORIZ_REL
              | mv.EKF_POS_HORIZ_ABS | mv.EKF_POS_VERT_ABS)
DEAD_RECKONING_FLAGS = GOOD_FLAGS & ~mv.EKF_POS_HORIZ_ABS  # external-nav fused: relative position only
CONST_POS_FLAGS = mv.EKF_ATTITUDE | mv.EKF_VELOCITY_VERT | mv.EKF_POS_VERT_ABS | mv.EKF_CONST_POS_MODE


def odom(seq: int, quality: float = 0.9, valid: bool = True, var: float = 0.04,
         vel: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> VisualOdometry:
    return VisualOdometry("uav1", seq, seq - 1, Stamp(0.1 * seq, "vehicle"), vel if valid else (0.0, 0.0, 0.0), var,
                          quality if valid else 0.0, valid, 0.1, 50.0)


def test_constants_match_pymavlink() -> None:
    mavlink = mv.load_mavutil().mavlink
    assert mv.MAV_CMD_SET_EKF_SOURCE_SET == mavlink.MAV_CMD_SET_EKF_SOURCE_SET == 42007
    for ours, theirs in ((mv.MSG_ID_GPS_RAW_INT, "GPS_RAW_INT"), (mv.MSG_ID_VISION_SPEED_ESTIMATE,
                         "VISION_SPEED_ESTIMATE"), (mv.MSG_ID_ESTIMATOR_STATUS, "ESTIMATOR_STATUS"),
                         (mv.MSG_ID_ODOMETRY, "ODOMETRY"), (mv.MSG_ID_GLOBAL_POSITION_INT, "GLOBAL_POSITION_INT")):
        assert ours == getattr(mavlink, f"MAVLINK_MSG_ID_{theirs}"), theirs
    assert (mv.EKF_POS_HORIZ_ABS, mv.EKF_CONST_POS_MODE, mv.EKF_PRED_POS_HORIZ_REL) == (
        mavlink.EKF_POS_HORIZ_ABS, mavlink.EKF_CONST_POS_MODE, mavlink.EKF_PRED_POS_HORIZ_REL)
    # PX4's ESTIMATOR_STATUS flags share the bits we read.
    assert (mavlink.ESTIMATOR_VELOCITY_HORIZ, mavlink.ESTIMATOR_POS_HORIZ_REL, mavlink.ESTIMATOR_POS_HORIZ_ABS,
            mavlink.ESTIMATOR_CONST_POS_MODE) == (mv.EKF_VELOCITY_HORIZ, mv.EKF_POS_HORIZ_REL, mv.EKF_POS_HORIZ_ABS,
                                                 mv.EKF_CONST_POS_MODE)
    assert mv.ATTITUDE_TYPE_MASK_ANGLES_THRUST == (mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_ROLL_RATE_IGNORE
                                                   | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_PITCH_RATE_IGNORE
                                                   | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE)
    assert mv.encode_mode("ardupilot", "GUIDED_NOGPS")[0] == 20
    assert mv.load_mavutil().mode_mapping_acm[20] == "GUIDED_NOGPS"


def test_ekf_flags_read_as_arducopter_position_ok() -> None:
    assert ekf_health(GOOD_FLAGS).position
    assert ekf_health(DEAD_RECKONING_FLAGS).position  # relative position is enough for GUIDED
    lost = ekf_health(CONST_POS_FLAGS)
    assert not lost.position and not lost.velocity_horizontal
    assert "constant-position mode" in lost.missing() and "horizontal velocity" in lost.missing()
    # Constant-position mode overrides a position flag (ArduCopter's ekf_has_relative_position).
    assert not ekf_health(GOOD_FLAGS | mv.EKF_CONST_POS_MODE).position
    with pytest.raises(ConfigError, match="16-bit"):
        ekf_health(-1)


def test_frd_to_ned_inverts_ned_to_frd() -> None:
    for roll, pitch, yaw in ((0.0, 0.0, 0.0), (0.1, -0.2, 2.5), (-0.3, 0.25, -1.2)):
        frd = mv.ned_to_frd((1.5, -2.0, 0.3), roll, pitch, yaw)
        assert mv.frd_to_ned(frd, roll, pitch, yaw) == pytest.approx((1.5, -2.0, 0.3), abs=1e-9)
    # Level, heading east: forward is east.
    assert mv.frd_to_ned((2.0, 0.0, 0.0), 0.0, 0.0, math.pi / 2) == pytest.approx((0.0, 2.0, 0.0), abs=1e-9)


def test_odometry_gate_refuses_stale_invalid_poor_and_noisy_samples() -> None:
    gate = OdometryGate(OdometryLimits(max_age_s=0.5, min_quality=0.5, max_var_m2_s2=1.0))
    assert gate.judge(0.0) == (False, "no visual velocity received")
    assert gate.add(odom(1), 10.0)
    assert gate.judge(10.2) == (True, "")
    assert gate.velocity(10.2) == (1.0, 0.0, 0.0)
    good, why = gate.judge(10.6)
    assert not good and "old" in why and gate.velocity(10.6) is None
    assert not gate.add(odom(1), 11.0), "a duplicate is not newer"
    assert gate.add(odom(2, valid=False), 11.0)
    assert gate.judge(11.0) == (False, "visual velocity invalid (quality 0.00) (no good sample for 0.5 s)")
    assert gate.add(odom(3, quality=0.3), 11.1)
    assert "quality 0.30 below 0.5" in gate.judge(11.1)[1]
    assert gate.add(odom(4, var=2.0), 11.2)
    assert "variance" in gate.judge(11.2)[1]
    assert not gate.sample_good(odom(5, var=2.0)) and gate.sample_good(odom(5))


def test_one_noisy_pair_among_good_ones_keeps_the_source_trusted() -> None:
    # SITL, GPS cut at 80 m: a pair over the variance limit every few frames flipped the trust off
    # (no descent) again and again for ten minutes, though the EKF only received the good ones.
    gate = OdometryGate(OdometryLimits(max_age_s=0.5, min_quality=0.5, max_var_m2_s2=1.0))
    for k in range(30):
        gate.add(odom(k, var=2.9 if k % 3 == 2 else 0.3), 10.0 + 0.1 * k)
        assert gate.judge(10.0 + 0.1 * k + 0.05) == (True, ""), k
        assert gate.velocity(10.0 + 0.1 * k + 0.05) == (1.0, 0.0, 0.0)
    for k in range(30, 36):  # then only noisy ones: trusted for 0.5 s after the last good one, no longer
        gate.add(odom(k, var=2.9), 10.0 + 0.1 * k)
    good, why = gate.judge(13.55)
    assert not good and "variance 2.90" in why and gate.velocity(13.55) is None


def test_judge_per_mode_after_a_gnss_loss() -> None:
    gate = OdometryGate()
    for mode in ("off", "external-nav", "attitude"):
        judge = NavJudge(mode)
        judge.on_gps_fix(3)
        judge.on_ekf_flags(GOOD_FLAGS)
        judge.on_local_position(0.0)
        healthy = judge.status(0.1, gate)
        assert healthy == NavStatus(False, False, True, "autopilot", "the autopilot's estimate is healthy")
    # GNSS gone, the EKF still coasting: lost, and only a good visual velocity makes a source.
    gate.add(odom(1), 1.0)
    judge = NavJudge("off")
    judge.on_gps_fix(3)
    judge.on_gps_fix(1)
    off = judge.status(1.0, gate)
    assert off.gnss_lost and not off.velocity_trusted and "--gnss-denied off" in off.reason
    judge = NavJudge("attitude")
    judge.on_gps_fix(3)
    judge.on_gps_fix(1)
    attitude = judge.status(1.0, gate)
    assert attitude.velocity_trusted and attitude.source == "visual"
    stale = judge.status(2.0, gate)
    assert not stale.velocity_trusted and "old" in stale.reason and "no descent" in stale.reason
    # external-nav: trusted only when the EKF has horizontal velocity and a (relative) position.
    judge = NavJudge("external-nav")
    judge.on_gps_fix(3)
    judge.on_gps_fix(1)
    judge.on_ekf_flags(CONST_POS_FLAGS)
    pending = judge.status(1.0, gate)
    assert pending.position_lost and not pending.velocity_trusted and "not fusing" in pending.reason
    judge.on_ekf_flags(DEAD_RECKONING_FLAGS)
    fused = judge.status(1.0, gate)
    assert fused.velocity_trusted and fused.source == "external-nav" and fused.gnss_lost and not fused.position_lost


def test_judge_sees_the_loss_in_the_flags_and_in_a_stopped_local_position() -> None:
    gate = OdometryGate()
    judge = NavJudge("off", local_stale_s=1.0)
    judge.on_ekf_flags(GOOD_FLAGS)
    judge.on_ekf_flags(DEAD_RECKONING_FLAGS)  # the absolute position went away: GNSS lost
    assert judge.gnss_lost()[0]
    px4 = NavJudge("off", local_stale_s=1.0)  # PX4 stops LOCAL_POSITION_NED when it has no position
    px4.on_local_position(5.0)
    assert not px4.position_lost(5.5)[0]
    lost, why = px4.position_lost(6.5)
    assert lost and "LOCAL_POSITION_NED" in why
    assert not px4.status(6.5, gate).velocity_trusted
    # Nothing reported at all (the sim, a flow-only setup): nothing is judged lost.
    assert NavJudge("off").status(0.0, gate).velocity_trusted


def test_quaternion_round_trip_and_vision_covariance() -> None:
    for angles in ((0.1, -0.2, 2.0), (0.0, 0.0, -3.0), (-0.25, 0.2, 0.5)):
        q = euler_to_quaternion(*angles)
        assert math.isclose(sum(c * c for c in q), 1.0, rel_tol=1e-12)
        assert quaternion_to_euler(q) == pytest.approx(angles, abs=1e-9)
    assert vision_speed_covariance(0.04) == [0.04, 0, 0, 0, 0.04, 0, 0, 0, 0.04]


def test_attitude_loop_tilts_towards_the_error_bounded_and_encodes_the_climb() -> None:
    loop = AttitudeLoop(AttitudeGains(max_tilt_rad=math.radians(15.0)))
    # Want 3 m/s forward, measure 0: nose down (negative pitch), bounded by the tilt / acceleration limit.
    out = loop.step((3.0, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0), 0.0, 0.5, 0.05)
    assert out.pitch_rad < 0 and abs(out.roll_rad) < 1e-9
    assert abs(out.pitch_rad) <= math.radians(15.0) + 1e-9
    assert quaternion_to_euler(out.q)[2] == pytest.approx(0.5)  # the heading held in the quaternion
    # Moving right too fast: roll left (negative).
    out = loop.step((0.0, 0.0, 0.0), 0.0, (0.0, 2.0, 0.0), 0.0, 0.5, 0.05)
    assert out.roll_rad < 0
    # Huge demand: never beyond the bound.
    out = loop.step((50.0, 50.0, 0.0), 0.0, (0.0, 0.0, 0.0), 0.0, 0.5, 0.05)
    assert math.hypot(out.roll_rad, out.pitch_rad) <= math.radians(15.0) * 1.001
    # ArduCopter's climb-rate thrust: 0.5 holds, descent 0.75 m/s of 1.5 is 0.25, climb 2.5 of 2.5 is 1.
    assert loop.step((0.0, 0.0, 0.0), 0.0, None, None, 0.5, 0.05).thrust == 0.5
    assert loop.step((0.0, 0.0, 0.75), 0.0, None, None, 0.5, 0.05).thrust == pytest.approx(0.25)
    assert loop.step((0.0, 0.0, -2.5), 0.0, None, None, 0.5, 0.05).thrust == pytest.approx(1.0)
    # No measured velocity: level, whatever the demand.
    level = loop.step((3.0, 3.0, 0.0), 0.0, None, None, 0.5, 0.05)
    assert level.roll_rad == 0.0 and level.pitch_rad == 0.0
    # PX4 thrust: around the hover thrust, more when sinking below the demanded climb.
    px4 = AttitudeLoop(thrust_mode="thrust")
    assert px4.step((0.0, 0.0, 0.0), 0.0, None, 0.0, 0.0, 0.05).thrust == pytest.approx(0.5)
    assert px4.step((0.0, 0.0, 0.0), 0.0, None, -1.0, 0.0, 0.05).thrust > 0.5
    assert 0.1 <= px4.step((0.0, 0.0, 5.0), 0.0, None, 3.0, 0.0, 0.05).thrust < 0.5


def test_attitude_loop_drives_a_point_mass_to_the_demanded_velocity() -> None:
    """Closed loop on a drag-damped point mass (what a multirotor under attitude control is, to first order)."""
    loop = AttitudeLoop()
    vel = [0.0, 0.0]
    dt = 0.05
    for _ in range(int(20.0 / dt)):
        out = loop.step((2.0, -1.0, 0.0), 0.0, (vel[0], vel[1], 0.0), 0.0, 0.0, dt)
        acc = (-9.80665 * math.tan(out.pitch_rad), 9.80665 * math.tan(out.roll_rad))
        vel = [v + (a - 0.3 * v) * dt for v, a in zip(vel, acc)]
    assert vel == pytest.approx([2.0, -1.0], abs=0.1)


class Descend:
    name = "descend"

    def step(self, obs: Observation) -> Decision:
        return Decision((1.0, 0.0, 1.0), 0.0, "LANDING", None, 10.0, 0.5, landing=True)

    def reset(self) -> None:
        pass


def test_core_stops_descending_without_a_trusted_velocity_and_says_why() -> None:
    config = ControllerConfig(lockstep=False, timing="real", vehicle_url="udpout:127.0.0.1:14550",
                              gnss_denied="attitude", state_stale_after_s=5.0)
    core = ControllerCore(config, policy=Descend(), mono=lambda: 0.0)
    hm = SafetyHeatmap("uav1", 0, Stamp(0.0, "vehicle"), np.full((8, 8), 200, np.uint8), 50.0, 1.27, "simulated",
                       True, "p", "f", 0.01)
    core.on_heatmap(hm, 0.0)
    state = VehicleState("uav1", 0, Stamp(0.0, "vehicle"), 50.0, (0.0, 0.0, 0.0))
    trusted = NavStatus(True, False, True, "visual", "GNSS lost; flying attitude targets on the visual velocity")
    cmd, status = core.tick(state, 0.0, trusted)
    assert core.mode is Mode.OK and cmd.vel_body_frd_m_s == (1.0, 0.0, 1.0)
    assert status.nav_source == "visual" and status.gnss_lost and not status.position_lost
    blind = NavStatus(True, True, False, "none", "GNSS lost; visual velocity 0.8 s old (limit 0.5 s): no descent")
    cmd, status = core.tick(VehicleState("uav1", 1, Stamp(0.05, "vehicle"), 50.0, (0.0, 0.0, 0.0)), 0.05, blind)
    assert core.mode is Mode.NO_VELOCITY and cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0)
    assert status.watchdog == "hold" and "no trusted velocity source" in status.reason and "0.8 s old" in status.reason
    assert status.nav_source == "none" and status.position_lost and status.nav_reason == blind.reason


class Observed:
    """Flies north at 4 m/s (never landing) and keeps every observation it was given."""

    name = "observed"

    def __init__(self) -> None:
        self.seen: list[Observation] = []

    def step(self, obs: Observation) -> Decision:
        self.seen.append(obs)
        return Decision((4.0, 0.0, 0.5), 0.0, "SEARCH", None, 10.0, 0.5)

    def reset(self) -> None:
        pass


def test_a_velocity_lost_in_flight_flies_back_the_way_it_came_without_descending_then_holds() -> None:
    # Over calm water the camera measures nothing, and a hold there drifts with the wind for as
    # long as it waits: the vehicle that flew onto it flies back, level, for nav_retreat_max_s.
    config = ControllerConfig(lockstep=False, timing="real", vehicle_url="udpout:127.0.0.1:14550",
                              gnss_denied="external-nav", state_stale_after_s=100.0, nav_retreat_max_s=10.0)
    policy = Observed()
    now = [0.0]  # the controller's own clock, kept with the states'
    core = ControllerCore(config, policy=policy, mono=lambda: now[0])
    trusted = NavStatus(True, False, True, "external-nav", "GNSS lost; the EKF fuses the visual velocity")
    blind = NavStatus(True, False, False, "none", "GNSS lost; visual velocity invalid (quality 0.00)")
    yaw = math.radians(30.0)
    # Flying north-east (heading 30 deg, 4 m/s forward) on a trusted velocity for 5 s ...
    k = 0
    for k in range(100):
        t = now[0] = 0.05 * k
        if k % 5 == 0:
            core.on_heatmap(SafetyHeatmap("uav1", k, Stamp(t, "vehicle"), np.full((8, 8), 200, np.uint8), 50.0, 1.27,
                                          "simulated", True, "p", "f", 0.01), t)
        cmd, _ = core.tick(VehicleState("uav1", k, Stamp(t, "vehicle"), 50.0, (4.0, 0.0, 0.0), yaw_rad=yaw), t, trusted)
    assert core.mode is Mode.OK and policy.seen[-1].velocity_trusted
    # ... then the velocity is lost: back the way it came (south-west), level, at the retreat speed,
    # whatever the policy commands; the policy is told.
    modes = []
    for j in range(1, 260):
        t = now[0] = 0.05 * (k + j)
        if j % 5 == 0:
            core.on_heatmap(SafetyHeatmap("uav1", k + j, Stamp(t, "vehicle"), np.full((8, 8), 200, np.uint8), 50.0,
                                          1.27, "simulated", True, "p", "f", 0.01), t)
        cmd, status = core.tick(VehicleState("uav1", k + j, Stamp(t, "vehicle"), 50.0, (0.0, 0.0, 0.0), yaw_rad=yaw),
                                t, blind)
        modes.append((0.05 * j, cmd.vel_body_frd_m_s, status.reason))
    assert not policy.seen[-1].velocity_trusted
    early = [m for m in modes if m[0] < 9.9]
    late = [m for m in modes if m[0] > 10.1]
    for _, vel, reason in early:
        # Body frame, heading kept: straight backwards.
        assert vel == pytest.approx((-config.nav_retreat_speed_m_s, 0.0, 0.0), abs=1e-9)
        assert "flying back over the ground the camera measured" in reason and "no trusted velocity source" in reason
    for _, vel, reason in late:
        assert vel == (0.0, 0.0, 0.0) and "flying back" not in reason
    # Trusted again: the policy is followed (and told); lost again after that flicker of trust, it
    # is the same loss, whose time is spent: a hold.
    t = now[0] = 0.05 * (k + 260)
    core.on_heatmap(SafetyHeatmap("uav1", k + 260, Stamp(t, "vehicle"), np.full((8, 8), 200, np.uint8), 50.0, 1.27,
                                  "simulated", True, "p", "f", 0.01), t)
    cmd, _ = core.tick(VehicleState("uav1", k + 260, Stamp(t, "vehicle"), 50.0, (0.0, 0.0, 0.0), yaw_rad=yaw), t,
                       trusted)
    assert core.mode is Mode.OK and cmd.vel_body_frd_m_s == (4.0, 0.0, 0.5) and policy.seen[-1].velocity_trusted
    now[0] = t + 0.05
    cmd, _ = core.tick(VehicleState("uav1", k + 261, Stamp(t + 0.05, "vehicle"), 50.0, (0.0, 0.0, 0.0), yaw_rad=yaw),
                       t + 0.05, blind)
    assert core.mode is Mode.NO_VELOCITY and cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0)


def test_the_retreat_goes_back_to_where_a_steady_stretch_was_trusted_and_past_it() -> None:
    r = NavRetreat(speed_m_s=2.0, max_s=12.0, solid_s=3.0, back_s=3.0)
    t = 0.0
    for vel in [(0.0, 3.0)] * 60 + [(5.0, 0.0)] * 60:  # east at 3 m/s for 6 s, then north at 5 m/s for 6 s
        assert r.update(t, vel, True) is None
        t += 0.1
    # Lost: back to where it was 3 s before, 15 m south, and on south once past it.
    way = r.update(t, (5.0, 0.0), False)
    assert way == pytest.approx((-2.0, 0.0), abs=0.05)
    for _ in range(100):  # flying it: 10 s at 2 m/s, 5 m past the point
        t += 0.1
        way = r.update(t, (-2.0, 0.0), False)
        assert way is not None and way == pytest.approx((-2.0, 0.0), abs=0.05)
    assert r.lost_for_s(t) == pytest.approx(10.0, abs=0.01)
    while r.lost_for_s(t) < 12.0 - 1e-9:
        t += 0.1
        r.update(t, (-2.0, 0.0), False)
    assert r.update(t, (0.0, 0.0), False) is None  # max_s spent: hold
    # A flicker of trust (1 s) neither ends that loss nor gives it more time; a steady stretch does.
    for _ in range(10):
        t += 0.1
        r.update(t, (2.0, 0.0), True)
    assert r.update(t + 0.1, (0.0, 0.0), False) is None and r.lost_for_s(t + 0.1) > 12.0
    t += 0.1
    for _ in range(40):  # 4 s west at 2 m/s, trusted: a new point to go back to
        t += 0.1
        r.update(t, (0.0, -2.0), True)
    assert r.lost_for_s(t) == 0.0
    assert r.update(t + 0.1, (0.0, -2.0), False) == pytest.approx((0.0, 2.0), abs=0.05)
    hover = NavRetreat(speed_m_s=2.0, max_s=12.0)
    for k in range(60):
        hover.update(0.1 * k, (0.1, 0.0), True)
    assert hover.update(6.0, (0.0, 0.0), False) is None  # lost where it hovered: nowhere to go back to
    off = NavRetreat(speed_m_s=2.0, max_s=0.0)
    for k in range(60):
        off.update(0.1 * k, (5.0, 0.0), True)
    assert off.update(6.0, (5.0, 0.0), False) is None
    with pytest.raises(ConfigError, match="speed_m_s"):
        NavRetreat(speed_m_s=0.0, max_s=5.0)
    with pytest.raises(ConfigError, match="nav_retreat_max_s"):
        ControllerConfig(nav_retreat_max_s=-1.0)


def test_config_checks_the_gnss_denied_flags() -> None:
    with pytest.raises(ConfigError, match="gnss_denied 'gps'"):
        ControllerConfig(lockstep=False, timing="real", vehicle_url="udpout:127.0.0.1:1", gnss_denied="gps")
    with pytest.raises(ConfigError, match="needs a MAVLink vehicle"):
        ControllerConfig(gnss_denied="attitude")
    with pytest.raises(ConfigError, match="ekf_source_set"):
        ControllerConfig(lockstep=False, timing="real", vehicle_url="udpout:127.0.0.1:1", ekf_source_set=4)
    from dovesei.controller.service import build_parser, config_from_args, to_argv
    config = ControllerConfig(lockstep=False, timing="real", vehicle_url="udpout:127.0.0.1:1",
                              gnss_denied="external-nav", ekf_source_set=3, attitude_max_tilt_deg=12.0)
    argv = to_argv(config)
    assert "--gnss-denied" in argv and "external-nav" in argv
    assert config_from_args(build_parser().parse_args(argv)) == config


def test_the_up_report_summarises_the_navigation_from_the_statuses() -> None:
    from dovesei.shared.messages import ControllerStatus
    from dovesei.up.report import Navigation

    def status(t_s: float, alt_m: float, source: str, lost: bool, reason: str = "") -> ControllerStatus:
        return ControllerStatus("uav1", int(t_s * 10), Stamp(t_s, "vehicle"), "p", "LANDING", "ok" if source != "none"
                                else "hold", reason, 0, 0.0, 0.0, alt_agl_m=alt_m, nav_source=source, gnss_lost=lost,
                                nav_reason=f"nav {t_s}")

    assert Navigation.of({0.0: status(0.0, 50.0, "", False)}) is None  # the sim
    statuses = {0.0: status(0.0, 50.0, "autopilot", False), 1.0: status(1.0, 40.0, "none", True,
                                                                      "no trusted velocity source: x"),
                2.0: status(2.0, 40.0, "visual", True), 3.0: status(3.0, 30.0, "visual", True)}
    nav = Navigation.of(statuses)
    assert nav is not None and nav.gnss_lost and nav.gnss_lost_t_s == 1.0 and nav.gnss_lost_alt_m == 40.0
    assert nav.sources == ("autopilot", "none", "visual") and nav.no_velocity_holds == 1
    assert (nav.first_reason, nav.last_reason) == ("nav 1.0", "nav 3.0")



def test_a_vehicle_that_never_had_gnss_is_judged_by_its_flags_alone() -> None:
    """A flow-only setup reports GPS_RAW_INT without a fix from boot: that is no loss, and with
    --gnss-denied off it must not hold; its EKF's flags decide."""
    gate = OdometryGate()
    judge = NavJudge("off")
    judge.on_gps_fix(0)
    judge.on_ekf_flags(DEAD_RECKONING_FLAGS)  # flying on flow: relative position, velocity
    status = judge.status(0.0, gate)
    assert not status.gnss_lost and status.velocity_trusted and status.source == "autopilot"
    judge.on_ekf_flags(CONST_POS_FLAGS)  # the flow gave out: that is a position loss
    status = judge.status(0.0, gate)
    assert status.position_lost and not status.velocity_trusted
    # Booting: no fix yet, then a fix, then none: only the last is a loss.
    judge = NavJudge("off")
    for fix in (1, 3):
        judge.on_gps_fix(fix)
        assert not judge.gnss_lost()[0]
    judge.on_gps_fix(1)
    assert judge.gnss_lost()[0]


def test_the_gate_says_where_the_newest_frame_sees_measurable_ground_in_north_and_east() -> None:
    gate = OdometryGate()
    blind = dict(valid=False)
    # Heading east (yaw 90 deg): texture to the right of the view is ground to the south.
    gate.add(dataclasses.replace(odom(1, **blind), yaw_rad=math.pi / 2, texture_share=0.2,
                                 texture_offset=(0.0, 0.5)), 0.1)
    assert gate.ground_seen(0.1) == pytest.approx((-0.5, 0.0), abs=1e-12)
    assert gate.ground_seen(0.1 + gate.limits.max_age_s + 0.01) is None  # a stale frame sees nothing now
    # Too little of it (a wave's glint), or straight below (a view textured all over): nothing aside.
    gate.add(dataclasses.replace(odom(2, **blind), texture_share=0.01, texture_offset=(0.5, 0.0)), 0.2)
    assert gate.ground_seen(0.2) is None
    gate.add(dataclasses.replace(odom(3, **blind), texture_share=0.9, texture_offset=(0.05, -0.02)), 0.3)
    assert gate.ground_seen(0.3) is None


def test_the_nav_status_carries_the_ground_seen_only_while_the_velocity_is_not_trusted() -> None:
    judge = NavJudge("external-nav")
    judge.on_gps_fix(mv.GPS_FIX_TYPE_3D)
    judge.on_ekf_flags(GOOD_FLAGS)
    judge.on_gps_fix(0)
    judge.on_ekf_flags(DEAD_RECKONING_FLAGS)
    gate = OdometryGate()
    gate.add(dataclasses.replace(odom(1, valid=False), texture_share=0.2, texture_offset=(0.6, 0.0)), 0.1)
    status = judge.status(0.1, gate)
    assert not status.velocity_trusted and status.ground_seen_ne == pytest.approx((0.6, 0.0))
    gate.add(dataclasses.replace(odom(2), texture_share=0.2, texture_offset=(0.6, 0.0)), 0.2)
    status = judge.status(0.2, gate)
    assert status.velocity_trusted and status.ground_seen_ne is None
    # --gnss-denied off flies nothing on the camera: it holds.
    off = NavJudge("off")
    off.on_gps_fix(mv.GPS_FIX_TYPE_3D)
    off.on_gps_fix(0)
    gate.add(dataclasses.replace(odom(3, valid=False), texture_share=0.2, texture_offset=(0.6, 0.0)), 0.3)
    assert off.status(0.3, gate).ground_seen_ne is None


def test_a_velocity_lost_over_water_flies_towards_the_coast_the_camera_sees_before_the_way_back() -> None:
    # Blind over the sea with the coast in the view: the coast is flown to (a measurement, every
    # frame), not the remembered way back; with nothing seen, the way back as before.
    config = ControllerConfig(lockstep=False, timing="real", vehicle_url="udpout:127.0.0.1:14550",
                              gnss_denied="external-nav", state_stale_after_s=100.0, nav_retreat_max_s=10.0)
    now = [0.0]
    core = ControllerCore(config, policy=Observed(), mono=lambda: now[0])
    trusted = NavStatus(True, False, True, "external-nav", "GNSS lost; the EKF fuses the visual velocity")
    blind = NavStatus(True, False, False, "none", "GNSS lost; visual velocity invalid (quality 0.00)")
    yaw = math.radians(30.0)
    west = dataclasses.replace(blind, ground_seen_ne=(0.0, -0.4))  # 40 m west at 100 m

    def tick(k: int, nav: NavStatus):
        t = now[0] = 0.05 * k
        if k % 5 == 0:
            core.on_heatmap(SafetyHeatmap("uav1", k, Stamp(t, "vehicle"), np.full((8, 8), 200, np.uint8), 100.0,
                                          1.27, "simulated", True, "p", "f", 0.01), t)
        return core.tick(VehicleState("uav1", k, Stamp(t, "vehicle"), 100.0, (4.0, 0.0, 0.0), yaw_rad=yaw), t, nav)

    for k in range(100):
        tick(k, trusted)
    for k in range(100, 400):  # 15 s: past the way back's 10 s, the coast is still flown to
        cmd, status = tick(k, west)
        fwd, right, down = cmd.vel_body_frd_m_s
        north, east = to_ne(fwd, right, yaw)
        assert (north, east, down) == pytest.approx((0.0, -config.nav_retreat_speed_m_s, 0.0), abs=1e-9)
        assert core.mode is Mode.NO_VELOCITY and "towards the ground the camera can measure, 40 m away at 270 deg" \
            in status.reason
    # The coast out of view (the wind the blind estimate does not know of carries the vehicle
    # off): on west the way it was last seen for 10 s (nav_retreat_max_s), then a hold.
    for k in range(400, 600):
        cmd, status = tick(k, blind)
        fwd, right, down = cmd.vel_body_frd_m_s
        north, east = to_ne(fwd, right, yaw)
        assert (north, east, down) == pytest.approx((0.0, -config.nav_retreat_speed_m_s, 0.0), abs=1e-9)
        assert f"flying on towards the ground the camera measured {0.05 * (k - 399):.0f} s ago (of 10 s), " \
               "at 270 deg" in status.reason
    cmd, status = tick(601, blind)  # 10.1 s since it was seen: the way back's time is spent too, a hold
    assert cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0) and "towards" not in status.reason


def test_ground_seen_then_lost_is_flown_on_for_max_s_and_forgotten_after_a_steady_stretch() -> None:
    r = NavRetreat(speed_m_s=4.0, max_s=20.0)
    t = 0.0
    for _ in range(50):  # 5 s trusted, flying east at 4 m/s: the way back is west
        r.update(t, (0.0, 4.0), True)
        t += 0.1
    assert r.update(t, (0.0, 4.0), False) == pytest.approx((0.0, -4.0))  # lost, nothing seen: the way back
    t += 0.1
    assert r.update(t, (0.0, 0.0), False, seen_ne=(0.3, 0.4)) == pytest.approx((2.4, 3.2))  # seen: towards it
    seen_t = t
    t += 0.1
    assert r.update(t, (0.0, 0.0), False) == pytest.approx((2.4, 3.2))  # out of view: on the same way
    assert r.seen_ne is None and r.seen_ago_s == pytest.approx(0.1)
    for k in range(2, 200):  # for max_s after it was last seen, past the way back's own 20 s
        t = seen_t + 0.1 * k
        assert r.update(t, (0.0, 0.0), False) == pytest.approx((2.4, 3.2))
    t = seen_t + 20.1
    assert r.update(t, (0.0, 0.0), False) is None and r.seen_ago_s is None  # spent: a hold
    assert r.update(t + 0.1, (0.0, 0.0), False, seen_ne=(0.0, -0.5)) == pytest.approx((0.0, -4.0))  # seen again
    t += 0.2
    for _ in range(10):  # a flicker of trust (1 s) keeps the memory
        t += 0.1
        r.update(t, (0.0, 1.0), True)
    assert r.update(t + 0.1, (0.0, 0.0), False) == pytest.approx((0.0, -4.0))
    for _ in range(40):  # a steady stretch (4 s) ends the loss and forgets the ground seen in it
        t += 0.1
        r.update(t, (4.0, 0.0), True)
    assert r.update(t + 0.1, (0.0, 0.0), False) == pytest.approx((-4.0, 0.0)) and r.seen_ago_s is None
    off = NavRetreat(speed_m_s=4.0, max_s=0.0)  # 0: neither the seen ground nor its memory is flown
    assert off.update(0.0, (0.0, 0.0), False, seen_ne=(0.3, 0.4)) is None
    assert off.update(0.1, (0.0, 0.0), False) is None


def test_ground_seen_straight_below_gives_no_direction_and_the_way_back_stands() -> None:
    retreat = NavRetreat(4.0, 30.0)
    for k in range(80):  # 4 s trusted, flying north at 4 m/s
        retreat.update(0.05 * k, (4.0, 0.0), True)
    way = retreat.update(4.0, (4.0, 0.0), False, seen_ne=(0.0, 0.0))
    assert way == pytest.approx((-4.0, 0.0)) and retreat.seen_ne is None
    assert retreat.update(4.05, (0.0, 0.0), False, seen_ne=(0.0, 0.3)) == pytest.approx((0.0, 4.0))
    assert retreat.seen_ne == (0.0, 0.3)
