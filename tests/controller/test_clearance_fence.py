"""The `clearance` search never runs away: a fence on every command bounds the dead-reckoned
position to search radius + fence margin, and in closed loop (biased, noisy velocity estimate and
a wind it cannot see) the true track stays inside that too."""

from __future__ import annotations

import math

import numpy as np

from dovesei.controller.policies.base import Decision, Observation
from dovesei.controller.policies.clearance.policy import ClearancePolicy, fence
from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.clearance.motion import to_body, to_ne
from tests.controller.test_clearance_scenarios import World, _textured, fly

# The closed-loop flights search a 150 m radius: the whole route fits their 900 s (the default
# radius is larger), and the fence works the same at any radius.
CFG = ClearanceConfig(search_radius_m=150.0)
FENCE_M = CFG.fence_m


def test_bench_starts_keep_the_whole_fenced_search_area_on_every_suite_world() -> None:
    # A bench that flies `clearance` draws its starts so that the fence plus a drift allowance
    # lies on the map, around every start, on every world of the suite.
    from dovesei.flight_defaults import default_start_margin_m  # lazy: the CLI layer, only for this check
    from dovesei.sim.starts import generate_starts
    from dovesei.sim.suite import DEFAULT_SUITE
    from dovesei.sim.world import load_world

    radius_m = ClearanceConfig().search_radius_m
    margin = default_start_margin_m(("dovesei", "clearance"))
    assert margin >= radius_m + 20.0
    assert default_start_margin_m(("dovesei",)) < margin  # the paper's runs keep their starts
    for spec in DEFAULT_SUITE[:2]:
        world = load_world(spec)
        for st in generate_starts(world, 50, 0, margin_m=margin):
            edge = min(st.x_m, st.y_m, world.width_m - st.x_m, world.height_m - st.y_m)
            assert edge >= radius_m + 20.0


def test_fence_caps_outward_speed_and_leaves_inward_alone() -> None:
    yaw = 0.7
    at_edge = (FENCE_M - 0.5) / math.sqrt(2.0)  # north-east of the start, half a metre from the fence
    out = (*to_body(6.0 / math.sqrt(2.0), 6.0 / math.sqrt(2.0), yaw), 1.0)  # 6 m/s straight out, descending
    vel, fenced = fence(out, at_edge, at_edge, yaw, CFG)
    vn, ve = to_ne(vel[0], vel[1], yaw)
    assert fenced and (vn + ve) / math.sqrt(2.0) <= CFG.fence_gain_per_s * 0.5 + 1e-9
    assert vel[2] == 1.0  # vertical untouched
    inward = (*to_body(-3.0, -3.0, yaw), 0.0)
    assert fence(inward, at_edge, at_edge, yaw, CFG) == (inward, False)
    # Beyond the fence even a hover command pulls back in.
    vel, fenced = fence((0.0, 0.0, 0.0), 0.0, FENCE_M + 4.0, 0.0, CFG)
    assert fenced and to_ne(vel[0], vel[1], 0.0)[1] < 0.0


class _Recording(ClearancePolicy):
    """The policy, keeping its own position estimate after every step (for the assertions)."""

    def reset(self) -> None:
        super().reset()
        self.estimates: list[tuple[float, float]] = []
        self.decision_fenced: list[bool] = []

    def step(self, obs: Observation) -> Decision:
        d = super().step(obs)
        self.estimates.append((self.motion.north_m, self.motion.east_m))
        self.decision_fenced.append(d.report is not None and d.report.fenced)
        return d


def _nowhere_to_land(config: ClearanceConfig, seed: int = 5):
    rng = np.random.default_rng(seed)
    world = World(_textured(rng, 4000))  # dense yards between roads and buildings, none wide enough
    policy = _Recording(config)
    # The estimate reads (1.0, -0.8) m/s too much and is noisy; a wind it cannot see blows too.
    flight = fly(world, policy, t_max_s=900.0, bias_m_s=(1.0, -0.8), vel_noise_m_s=0.5, wind_m_s=(0.6, 0.4),
                 seed=seed)
    return policy, flight


def test_biased_odometry_search_stays_inside_radius_plus_margin() -> None:
    policy, flight = _nowhere_to_land(CFG)
    assert flight.decision.state == "NO_SPOT", flight.decision.reason
    assert flight.alt_m > 20.0
    est = max(math.hypot(n, e) for n, e in policy.estimates)
    assert est <= FENCE_M + 0.5, est
    # It did search out to its radius (the pattern's corners sit at ~71 m) ...
    assert flight.max_range_m > 0.8 * CFG.search_radius_m
    # ... and the true track, drift and vehicle lag included, never left the search radius.
    assert flight.max_range_m < CFG.search_radius_m, flight.max_range_m


def test_fence_bounds_the_estimate_even_when_registration_is_off() -> None:
    """Without registration nothing can see the drift (the truth wanders with wind - bias), but
    no command takes the dead-reckoned position past the fence."""
    cfg = CFG.replace(reg_min_std=1.0)
    policy, flight = _nowhere_to_land(cfg, seed=6)
    est = max(math.hypot(n, e) for n, e in policy.estimates)
    assert est <= FENCE_M + 0.5, est
    assert flight.decision.state == "NO_SPOT"


def test_no_spot_holds_its_point_by_vision_against_wind_and_a_biased_estimate() -> None:
    """A zero-velocity command is no hold without GNSS: here the wind alone would carry the vehicle
    0.72 m/s x 300 s = 216 m. The registered position holds it where the search gave up."""
    rng = np.random.default_rng(5)
    world = World(_textured(rng, 4000))
    policy = _Recording(CFG)
    flight = fly(world, policy, t_max_s=1500.0, bias_m_s=(1.0, -0.8), vel_noise_m_s=0.5, wind_m_s=(0.6, 0.4),
                 seed=5, hold_s=300.0)
    assert flight.decision.state == "NO_SPOT"
    held = [(n, e) for n, e, _, state, _ in flight.track if state == "NO_SPOT"]
    assert len(held) >= 500  # 300 s of holding at 2 Hz
    n0, e0 = held[0]
    drift = max(math.hypot(n - n0, e - e0) for n, e in held)
    assert drift < 15.0, drift
    assert flight.max_range_m < CFG.search_radius_m
    assert flight.decision.report.hold_error_m < 10.0


def test_the_fence_shrinks_while_the_estimate_is_uncertain() -> None:
    policy = ClearancePolicy(CFG)
    assert policy.fence_m() == FENCE_M  # a fresh estimate: the fence margin covers it
    policy.motion.uncertainty_m = 40.0
    assert policy.fence_m() == CFG.search_radius_m - 40.0
    # The same outward command at 115 m from the start: free under the full fence, pulled back
    # under the shrunk one.
    out = (6.0, 0.0, 0.0)
    assert fence(out, 115.0, 0.0, 0.0, CFG, FENCE_M)[1] is False
    vel, fenced = fence(out, 115.0, 0.0, 0.0, CFG, policy.fence_m())
    assert fenced and vel[0] < 0.0


def test_a_waypoint_beyond_a_shrunk_fence_is_flown_to_its_edge_and_passed() -> None:
    import dataclasses  # lazy: only here

    from dovesei.controller.policies.clearance.machine import Inputs, Memory, Phase, search_route, step

    route = search_route(((100.0, 100.0, 140.0),))  # its first point: 100 m north
    mem = dataclasses.replace(Memory(), phase=Phase.SEARCH)
    base = dict(t_s=1.0, alt_agl_m=100.0, yaw_rad=0.0, fresh=True, gap=False, search_alt_m=100.0, route=route,
                best=None, check=None, hfov_rad=math.radians(73.0))
    # Under the full fence the vehicle at 55 m north still has 45 m to go ...
    mem1, vel = step(mem, Inputs(north_m=55.0, east_m=0.0, **base), CFG)
    assert mem1.waypoint == 0 and vel[0] > 0.0
    # ... under a 60 m fence the point is pulled to 55 m: it has arrived and flies on.
    mem2, _ = step(mem, Inputs(north_m=55.0, east_m=0.0, fence_m=60.0, **base), CFG)
    assert mem2.waypoint == 1
