"""The controller's geofence: whatever the policy asks, the dead-reckoned position stays within
the radius of the start (issue 26: the paper's RESTARTING move flew ~600 m blind on ArduCopter
SITL and left the world in 2 of 4 flights)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.controller.core import DEFAULT_VEHICLE_GEOFENCE_M, ControllerConfig, ControllerCore, Mode
from dovesei.controller.geofence import Geofence
from dovesei.controller.policies.base import Decision, Observation
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import SafetyHeatmap, Stamp, VehicleState


class Runaway:
    """The RESTARTING move: one fixed direction at 14 m/s (north-east in the body frame), no end."""

    name = "runaway"

    def step(self, obs: Observation) -> Decision:
        return Decision((10.0, 10.0, 0.0), 0.0, "RESTARTING", None, 10.0, 0.5)

    def reset(self) -> None:
        pass


def _fly(core: ControllerCore, seconds: float, yaw_rad: float = 0.3) -> tuple[list[float], list[str]]:
    """A vehicle that flies exactly what it is told at 20 Hz; a fresh heatmap every 0.25 s."""
    prob = np.full((16, 16), 128, np.uint8)
    n = e = 0.0
    vel = (0.0, 0.0, 0.0)
    ranges, reasons = [], []
    for k in range(int(seconds * 20)):
        t = 0.05 * k
        if k % 5 == 0:
            core.on_heatmap(SafetyHeatmap("uav1", k, Stamp(t, "sim"), prob, 60.0, 1.2, "simulated", True, "p", "f",
                                             0.01), 0.0)
        cmd, status = core.tick(VehicleState("uav1", k, Stamp(t, "sim"), 60.0, vel, yaw_rad=yaw_rad,
                                             await_frame_seq=k if k % 5 == 0 else -1))
        vel = cmd.vel_body_frd_m_s
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        n += (c * vel[0] - s * vel[1]) * 0.05
        e += (s * vel[0] + c * vel[1]) * 0.05
        ranges.append(math.hypot(n, e))
        reasons.append(status.reason)
    return ranges, reasons


def test_no_policy_flies_past_the_fence_and_the_status_says_when_it_capped() -> None:
    core = ControllerCore(ControllerConfig(geofence_radius_m=100.0), policy=Runaway())
    ranges, reasons = _fly(core, 40.0)  # 560 m unfenced
    assert max(ranges) <= 100.5, max(ranges)
    assert ranges[-1] > 95.0  # it got there: only the outward speed was capped, gently
    assert "geofence" not in reasons[20] and "geofence: " in reasons[-1] and "radius 100 m" in reasons[-1]
    assert core.mode is Mode.OK and core.geofence is not None and core.geofence.clipped > 100


def test_beyond_the_fence_ok_pulls_back_a_hold_only_stops() -> None:
    fence = Geofence(50.0, gain_per_s=0.5, max_inward_m_s=2.0)
    fence.add(0.0, (10.0, 0.0, 0.0), 0.0)
    fence.add(6.0, (10.0, 0.0, 0.0), 0.0)  # 60 m north
    vel, why = fence.cap((0.0, 3.0, 1.0), 0.0)  # eastward: tangential, kept; pulled back at 2 m/s
    assert vel == pytest.approx((-2.0, 3.0, 1.0)) and why is not None
    held, why = fence.cap((0.0, 0.0, 0.0), 0.0, pull_back=False)
    assert held == (0.0, 0.0, 0.0) and why is None
    inward, why = fence.cap((-5.0, 0.0, 0.0), 0.0)
    assert inward == (-5.0, 0.0, 0.0) and why is None


def test_off_with_the_sim_on_with_a_real_vehicle_and_checked() -> None:
    assert ControllerConfig().geofence_m is None  # the paper's experiment as published
    real = ControllerConfig(vehicle_url="udpout:127.0.0.1:14550", lockstep=False, timing="real")
    assert real.geofence_m == DEFAULT_VEHICLE_GEOFENCE_M
    assert ControllerConfig(geofence_radius_m=0.0, vehicle_url="udpout:127.0.0.1:14550", lockstep=False,
                            timing="real").geofence_m is None
    with pytest.raises(ConfigError, match="geofence_radius_m"):
        ControllerConfig(geofence_radius_m=-5.0)
