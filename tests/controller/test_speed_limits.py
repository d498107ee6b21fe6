"""The vehicle's speed limits reach the policy that is ours to bound.

ArduCopter flies guided velocities within WPNAV_SPEED / WPNAV_SPEED_UP / WPNAV_SPEED_DN (10, 2.5
and 1.5 m/s by default); on SITL 54-74 % of the setpoints were clamped to them (issue 26). The
`clearance` policy now asks only what is flown when the controller drives a MAVLink vehicle; the
`dovesei` policy stays faithful to the reference and is clamped by the adapter (counted there).
"""

from __future__ import annotations

import math

import numpy as np

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.policies.clearance.policy import ClearancePolicy
from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.dovesei.policy import DoveseiPolicy
from tests.controller.test_clearance_scenarios import SIDE, World, fly

MAVLINK = dict(vehicle_url="udpout:127.0.0.1:14550", lockstep=False, timing="real")


def _max_speeds(flight) -> tuple[float, float]:
    downs = [row[4] for row in flight.track]
    return max(downs), -min(downs)


def test_clearance_on_a_mavlink_vehicle_never_asks_more_than_the_vehicle_flies() -> None:
    world = World(np.ones((SIDE, SIDE), bool))
    core = ControllerCore(ControllerConfig(policy="clearance", mavlink_max_horizontal_m_s=5.0, mavlink_max_up_m_s=2.0,
                                           mavlink_max_down_m_s=1.5, **MAVLINK))
    assert isinstance(core.policy, ClearancePolicy)
    cfg = core.policy.config
    assert (cfg.descent_max_m_s, cfg.descent_min_m_s, cfg.climb_speed_m_s) == (1.5, 1.0, 2.0)
    assert cfg.search_speed_m_s == 5.0 and cfg.max_speed_m_s == 5.0
    # The limits, not the scene's levels, are the point: the spot from the first views (the default
    # top pass over the 300 m search area takes minutes before the first descent).
    flight = fly(world, ClearancePolicy(cfg.replace(scene_after_top_pass=False)), t_max_s=200.0)
    assert flight.alt_m <= 20.0  # it still lands, only slower
    down, up = _max_speeds(flight)
    assert down <= 1.5 + 1e-9 and up <= 2.0 + 1e-9, (down, up)


def test_clearance_with_the_sim_keeps_its_own_speeds_and_dovesei_stays_faithful() -> None:
    world = World(np.ones((SIDE, SIDE), bool))
    sim = ControllerCore(ControllerConfig(policy="clearance", timing="real"))
    assert sim.policy.config == ClearanceConfig()  # the sim has no MAVLink limits: bench unchanged
    down, _ = _max_speeds(fly(world, ClearancePolicy(sim.policy.config.replace(scene_after_top_pass=False)),
                              t_max_s=200.0))
    assert down > 1.5  # what the limits above cut
    paper = ControllerCore(ControllerConfig(policy="dovesei", **MAVLINK))
    faithful = ControllerCore(ControllerConfig(policy="dovesei", vehicle_url="zenoh", lockstep=False, timing="real"))
    assert isinstance(paper.policy, DoveseiPolicy) and paper.policy.config == faithful.policy.config
    assert math.isclose(ControllerConfig(**MAVLINK).mavlink_max_down_m_s, 1.5)
