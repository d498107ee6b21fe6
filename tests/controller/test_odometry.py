"""The velocity estimate integrated between capture stamps: the track alone, then through the core."""

from __future__ import annotations

import dataclasses
import math

import pytest

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.odometry import VelocityTrack
from dovesei.shared.messages import Stamp, VehicleState
from tests.controller.test_core import RecordingPolicy, heatmap


def test_the_track_integrates_the_velocity_between_any_two_stamps() -> None:
    track = VelocityTrack()
    for k in range(41):  # 2 s at 20 Hz: 3 m/s forward heading east, then right (south) from 1 s
        t = 0.05 * k
        track.add(t, (3.0, 0.0, 0.0) if t < 1.0 else (0.0, 2.0, 0.0), math.pi / 2.0)
    dn, de = track.displacement_ne_m(0.0, 0.5)
    assert dn == pytest.approx(0.0, abs=1e-9) and de == pytest.approx(1.5)
    # Between samples the track is linear; across the change of velocity the trapezoid averages it.
    dn, de = track.displacement_ne_m(0.525, 2.0)
    assert de == pytest.approx(3.0 * 0.425 + 1.5 * 0.05, abs=1e-9)
    assert dn == pytest.approx(-(2.0 * 1.0 + 1.0 * 0.05), abs=1e-9)
    # A little past the newest state, the newest velocity carries it; further, nothing is invented.
    dn, _ = track.displacement_ne_m(2.0, 2.2)
    assert dn == pytest.approx(-0.4)
    assert track.displacement_ne_m(2.0, 2.0 + track.extrapolate_s + 0.1) is None
    assert track.displacement_ne_m(-1.0, 1.0) is None  # before the track began


def test_a_gap_or_time_going_back_restarts_the_track() -> None:
    track = VelocityTrack(max_gap_s=1.0)
    track.add(0.0, (1.0, 0.0, 0.0), 0.0)
    track.add(0.5, (1.0, 0.0, 0.0), 0.0)
    track.add(3.0, (1.0, 0.0, 0.0), 0.0)  # 2.5 s without a state: what happened is unknown
    assert track.displacement_ne_m(0.0, 3.0) is None
    track.add(3.5, (1.0, 0.0, 0.0), 0.0)
    assert track.displacement_ne_m(3.0, 3.5) == pytest.approx((0.5, 0.0))
    track.add(1.0, (1.0, 0.0, 0.0), 0.0)  # backwards: a new timeline
    assert track.displacement_ne_m(3.0, 3.5) is None
    track.add(1.0, (5.0, 0.0, 0.0), 0.0)  # the same stamp again changes nothing
    track.add(1.5, (1.0, 0.0, 0.0), 0.0)
    assert track.displacement_ne_m(1.0, 1.5) == pytest.approx((0.5, 0.0))


def test_the_track_forgets_what_is_older_than_it_keeps() -> None:
    track = VelocityTrack(keep_s=2.0)
    for k in range(200):
        track.add(0.05 * k, (1.0, 0.0, 0.0), 0.0)
    assert track.displacement_ne_m(0.0, 9.0) is None
    assert track.displacement_ne_m(8.0, 9.0) == pytest.approx((1.0, 0.0))
    assert len(track._t) <= 2 * 2.0 / 0.05 + 2




def test_the_policy_gets_the_estimate_integrated_between_capture_stamps_not_at_arrival() -> None:
    """Frames every 0.5 s, each due 0.4 s after capture, while the vehicle accelerates north at
    2 m/s^2: the displacement between captures is what the velocity did then, not the
    velocity at arrival x dt."""
    policy = RecordingPolicy()
    core = ControllerCore(ControllerConfig(lockstep=True), policy=policy)
    dt, accel = 0.05, 2.0
    for k in range(61):  # 3 s
        t = round(k * dt, 9)
        if k % 10 == 0:
            core.on_heatmap(heatmap(k // 10, t), 0.0)
        due = (k - 8) // 10 if k >= 8 and (k - 8) % 10 == 0 else -1
        core.tick(VehicleState("uav1", k, Stamp(t, "sim"), 80.0, (accel * t, 0.0, 0.0), yaw_rad=0.0,
                               await_frame_seq=due))
    obs = policy.observations
    assert len(obs) == 6 and obs[0].odom_delta_ne_m is None  # the first has nothing before it
    for i, o in enumerate(obs[1:], start=1):
        t0, t1 = 0.5 * (i - 1), 0.5 * i  # capture stamps
        dn, de = o.odom_delta_ne_m
        assert dn == pytest.approx(0.5 * accel * (t1 ** 2 - t0 ** 2), abs=1e-6) and de == pytest.approx(0.0)
        # What velocity x dt at arrival would have said: the velocity 0.4 s late, not the mean over
        # the interval (0.25 s before its end): 0.65 m too much each time.
        assert o.vel_est_body_frd_m_s[0] * 0.5 - dn == pytest.approx(accel * (0.4 + 0.25) * 0.5, abs=1e-6)


def test_a_decision_refused_after_the_policy_took_its_heatmap_still_moves_the_capture_stamp() -> None:
    """The policy dead-reckoned the interval when it stepped; the next displacement must start
    there even when the core refused the decision (too fast), or it is counted twice."""

    class TooFast(RecordingPolicy):
        def step(self, obs):
            d = super().step(obs)
            return d if len(self.observations) != 2 else dataclasses.replace(d, vel_body_frd_m_s=(500.0, 0.0, 0.0))

    policy = TooFast()
    core = ControllerCore(ControllerConfig(lockstep=True), policy=policy)
    for k in range(31):  # 1.5 s at 1 m/s north; heatmaps every 0.5 s, due at once
        t = round(0.05 * k, 9)
        if k % 10 == 0:
            core.on_heatmap(heatmap(k // 10, t), 0.0)
        core.tick(VehicleState("uav1", k, Stamp(t, "sim"), 80.0, (1.0, 0.0, 0.0), await_frame_seq=k // 10 if k % 10 == 0 else -1))
    assert core.policy_errors == 1  # the second decision was refused
    deltas = [o.odom_delta_ne_m for o in policy.observations]
    assert deltas[0] is None and len(deltas) == 4
    assert all(d == pytest.approx((0.5, 0.0)) for d in deltas[1:])


def test_the_policy_gets_the_attitude_at_capture_not_at_arrival() -> None:
    """A body-fixed camera turns with the vehicle: a frame captured level and handed over 0.4 s
    later, while the vehicle pitches and rolls at 30 deg/s, must reach the policy with the
    attitude it was captured with (the heatmap is placed on the ground with it), not the tick's."""
    policy = RecordingPolicy()
    core = ControllerCore(ControllerConfig(lockstep=True), policy=policy)
    rate = math.radians(30.0)

    def attitude(t: float) -> tuple[float, float, float]:
        return -rate * t, rate * t, 0.2 + 0.1 * t  # roll, pitch, yaw (radians)

    for k in range(61):  # 3 s; heatmaps captured every 0.5 s, each due 0.4 s later
        t = round(k * 0.05, 9)
        if k % 10 == 0:
            core.on_heatmap(heatmap(k // 10, t), 0.0)
        due = (k - 8) // 10 if k >= 8 and (k - 8) % 10 == 0 else -1
        roll, pitch, yaw = attitude(t)
        core.tick(VehicleState("uav1", k, Stamp(t, "sim"), 80.0, (0.0, 0.0, 0.0), yaw_rad=yaw, roll_rad=roll,
                               pitch_rad=pitch, await_frame_seq=due))
    assert len(policy.observations) == 6
    for i, o in enumerate(policy.observations):
        roll, pitch, yaw = attitude(0.5 * i)  # at capture; at arrival each was 12 deg further
        assert (o.roll_rad, o.pitch_rad, o.yaw_rad) == pytest.approx((roll, pitch, yaw), abs=1e-9)


def test_the_attitude_track_interpolates_and_never_invents() -> None:
    track = VelocityTrack(extrapolate_s=0.25)
    track.add(0.0, (0.0, 0.0, 0.0), math.pi - 0.1, 0.0, 0.2)
    track.add(0.1, (0.0, 0.0, 0.0), -math.pi + 0.1, 0.1, 0.0)  # the heading crosses +-pi
    roll, pitch, yaw = track.attitude_at(0.05)
    assert roll == pytest.approx(0.05) and pitch == pytest.approx(0.1)
    assert abs(math.remainder(yaw - math.pi, 2.0 * math.pi)) < 1e-9  # the short way round, not through 0
    assert track.attitude_at(0.3) == pytest.approx((0.1, 0.0, -math.pi + 0.1))  # the newest, a little past it
    assert track.attitude_at(0.4) is None and track.attitude_at(-0.1) is None
