"""Vehicle dynamics: limits hold, commands are tracked, stale commands brake, wind drifts, seeds repeat."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.sim.dynamics import (
    GRAVITY_M_S2,
    DynamicsError,
    Vehicle,
    VehicleParams,
    Pose,
    body_frd_to_ned,
)

DT_S = 0.05


def fly(vehicle: Vehicle, seconds: float, cmd, yaw_rate: float = 0.0) -> Pose:
    """Step with a command re-sent every step (always fresh)."""
    for _ in range(round(seconds / DT_S)):
        vehicle.step(DT_S, cmd, yaw_rate, vehicle.state.t_s)
    return vehicle.state


def test_body_to_ned_by_heading() -> None:
    np.testing.assert_allclose(body_frd_to_ned((1, 0, 0), 0.0), [1, 0, 0], atol=1e-12)  # forward = north
    np.testing.assert_allclose(body_frd_to_ned((1, 0, 0), math.pi / 2), [0, 1, 0], atol=1e-12)  # east
    np.testing.assert_allclose(body_frd_to_ned((0, 1, 0), math.pi / 2), [-1, 0, 0], atol=1e-12)  # right = south
    np.testing.assert_allclose(body_frd_to_ned((0, 0, 2), 1.0), [0, 0, 2], atol=1e-12)


def test_step_response_reaches_commanded_speed_and_moves_the_right_way() -> None:
    v = Vehicle(Pose(100.0, 100.0, 50.0, yaw_rad=math.pi / 2))  # facing east
    st = fly(v, 6.0, (5.0, 0.0, 1.0))  # forward 5 m/s, descend 1 m/s
    assert st.vel_ned_m_s[1] == pytest.approx(5.0, abs=0.01) and abs(st.vel_ned_m_s[0]) < 1e-9
    assert st.vel_ned_m_s[2] == pytest.approx(1.0, abs=0.01)
    assert st.x_m > 100.0 + 20.0 and st.y_m == pytest.approx(100.0)  # went east
    assert st.alt_agl_m < 50.0 - 4.0
    assert st.vel_body_frd_m_s() == pytest.approx((5.0, 0.0, 1.0), abs=0.01)


def test_limits_are_never_exceeded() -> None:
    params = VehicleParams(max_tilt_deg=20.0)  # g*tan(20 deg) = 3.57 < 4: the tilt limit binds
    v = Vehicle(Pose(0.0, 0.0, 500.0), params, seed=1)
    rng = np.random.default_rng(0)
    a_h_max = GRAVITY_M_S2 * math.tan(math.radians(20.0))
    prev = np.array(v.vel_own_ned_m_s)
    prev_yaw = v.state.yaw_rad
    peak = np.zeros(4)  # horizontal speed, vertical speed, horizontal accel, vertical accel
    for i in range(3000):
        if i % 120 == 0:  # a new wild command every 6 s (long enough to reach the speed limit)
            cmd = tuple(rng.uniform(-40, 40, 3))
            # Turning chases a rotating target (speed capped by accel / yaw rate): every other segment only.
            yaw_rate = float(rng.uniform(-5, 5)) if i % 240 else 0.0
        v.step(DT_S, cmd, yaw_rate, v.state.t_s)
        vel = np.array(v.vel_own_ned_m_s)
        assert math.hypot(vel[0], vel[1]) <= 15.0 + 1e-9
        assert abs(vel[2]) <= 5.0 + 1e-9
        acc = (vel - prev) / DT_S
        assert math.hypot(acc[0], acc[1]) <= a_h_max + 1e-6
        assert abs(acc[2]) <= 3.0 + 1e-6
        dyaw = math.remainder(v.state.yaw_rad - prev_yaw, 2 * math.pi)
        assert abs(dyaw) <= params.max_yaw_rate_rad_s * DT_S + 1e-9
        assert -math.pi < v.state.yaw_rad <= math.pi
        prev, prev_yaw = vel, v.state.yaw_rad
        peak = np.maximum(peak, [math.hypot(vel[0], vel[1]), abs(vel[2]), math.hypot(acc[0], acc[1]), abs(acc[2])])
    # The limits are reached, not merely respected by a sluggish model.
    np.testing.assert_allclose(peak, [15.0, 5.0, a_h_max, 3.0], rtol=1e-3)  # speed approaches exponentially


def test_saturated_command_reaches_max_speed() -> None:
    v = Vehicle(Pose(0.0, 0.0, 100.0))
    st = fly(v, 10.0, (30.0, 30.0, -20.0))
    assert math.hypot(st.vel_ned_m_s[0], st.vel_ned_m_s[1]) == pytest.approx(15.0, abs=1e-6)
    assert st.vel_ned_m_s[2] == pytest.approx(-5.0, abs=1e-6)  # climbing at 5 m/s


def test_stale_command_brakes_to_hover() -> None:
    v = Vehicle(Pose(0.0, 0.0, 50.0))
    fly(v, 5.0, (10.0, 0.0, 0.0))
    assert v.state.vel_ned_m_s[0] == pytest.approx(10.0, abs=0.01)
    cmd_t_s = v.state.t_s
    # Keep handing over the same old command: held for 0.5 s, then dropped.
    for _ in range(round(0.5 / DT_S)):
        v.step(DT_S, (10.0, 0.0, 0.0), 0.0, cmd_t_s)
        assert not v.last_command_stale
    assert v.state.vel_ned_m_s[0] == pytest.approx(10.0, abs=0.01)
    v.step(DT_S, (10.0, 0.0, 0.0), 0.0, cmd_t_s)  # exactly 0.5 s old: the boundary, either way
    for _ in range(round(5.0 / DT_S)):
        v.step(DT_S, (10.0, 0.0, 0.0), 0.0, cmd_t_s)
        assert v.last_command_stale
    assert max(abs(c) for c in v.state.vel_ned_m_s) < 1e-3
    # No command at all is the same as a stale one.
    v2 = Vehicle(Pose(0.0, 0.0, 50.0, vel_ned_m_s=(3.0, 0.0, 0.0)))
    for _ in range(80):
        v2.step(DT_S, None)
    assert abs(v2.state.vel_ned_m_s[0]) < 1e-3


def test_wind_drifts_a_hovering_vehicle() -> None:
    # Hovering in the wind: the ground velocity already equals the wind, the own velocity is 0.
    start = Pose(50.0, 50.0, 30.0, vel_ned_m_s=(1.0, -2.0, 0.0))
    v = Vehicle(start, VehicleParams(wind_ned_m_s=(1.0, -2.0, 0.0)))
    st = fly(v, 10.0, (0.0, 0.0, 0.0))
    assert st.y_m == pytest.approx(60.0, abs=1e-6)  # north 1 m/s
    assert st.x_m == pytest.approx(30.0, abs=1e-6)  # west 2 m/s
    assert st.vel_ned_m_s == pytest.approx((1.0, -2.0, 0.0))
    assert v.vel_own_ned_m_s == pytest.approx((0.0, 0.0, 0.0))


def test_drift_and_gusts_are_seeded() -> None:
    params = VehicleParams(drift_sigma_m_s_sqrt_s=0.1, gust_sigma_m_s=1.0)

    def run(seed: int) -> list[Pose]:
        v = Vehicle(Pose(0.0, 0.0, 40.0), params, seed=seed)
        return [v.step(DT_S, (1.0, 0.5, 0.2), 0.1, v.state.t_s) for _ in range(400)]

    a, b, c = run(7), run(7), run(8)
    assert a == b
    assert a != c
    # The disturbance actually moves the vehicle off the undisturbed path.
    calm = Vehicle(Pose(0.0, 0.0, 40.0))
    for _ in range(400):
        calm.step(DT_S, (1.0, 0.5, 0.2), 0.1, calm.state.t_s)
    assert math.hypot(a[-1].x_m - calm.state.x_m, a[-1].y_m - calm.state.y_m) > 0.5


def test_ground_stops_descent() -> None:
    v = Vehicle(Pose(0.0, 0.0, 2.0))
    st = fly(v, 5.0, (2.0, 0.0, 5.0))
    assert st.alt_agl_m == 0.0 and st.vel_ned_m_s == (0.0, 0.0, 0.0)
    st = fly(v, 3.0, (0.0, 0.0, -2.0))  # a climb command lifts it off again
    assert st.alt_agl_m > 1.0


@pytest.mark.parametrize("kwargs", [{"max_speed_h_m_s": 0.0}, {"max_tilt_deg": 95.0},
                                    {"drift_sigma_m_s_sqrt_s": -1.0}, {"wind_ned_m_s": (1.0, float("nan"), 0.0)}])
def test_bad_params(kwargs: dict) -> None:
    with pytest.raises(DynamicsError):
        VehicleParams(**kwargs)


def test_bad_steps() -> None:
    v = Vehicle(Pose(0.0, 0.0, 10.0))
    with pytest.raises(DynamicsError, match="dt_s"):
        v.step(0.0, (1.0, 0.0, 0.0), 0.0, 0.0)
    with pytest.raises(DynamicsError, match="finite"):
        v.step(0.1, (float("inf"), 0.0, 0.0), 0.0, 0.0)
    with pytest.raises(DynamicsError, match="alt_agl_m"):
        Vehicle(Pose(0.0, 0.0, -1.0))
