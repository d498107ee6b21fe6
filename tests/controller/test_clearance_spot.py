"""The `clearance` policy lands where it checked: the spot's keyframe keeps the target on the
checked ground while dead reckoning drifts, and where vision cannot tell, it re-checks the footprint
below instead of descending on the estimate. The touchdown is measured from the ground of the
policy's own confirming look (Decision.confirmed) placed with that frame's true pose.

The drift is the issue's GNSS-denied estimate: bias (1.0, -0.8) m/s, noise 0.5 m/s, and a wind of
(0.6, 0.4) m/s the estimate cannot see (tests/controller/test_clearance_fence.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from dovesei.controller.policies.clearance.policy import ClearancePolicy
from dovesei.controller.policies.clearance.config import ClearanceConfig
from tests.controller.test_clearance_scenarios import SIDE, Flight, World, fly

DRIFT = dict(bias_m_s=(1.0, -0.8), vel_noise_m_s=0.5, wind_m_s=(0.6, 0.4))


def _sand(seed: int) -> World:
    """Open ground, all safe, with a faint texture fixed on it (ripples, stones): it reads 0.86-0.90,
    under this harness's per-frame noise of 0.1, so every look is alike to a threshold but the
    ground can still be recognised from one look to the next."""
    rng = np.random.default_rng(seed)
    field = cv2.GaussianBlur(rng.random((SIDE, SIDE)).astype(np.float32), (0, 0), 8.0)
    field = (field - field.min()) / (field.max() - field.min())
    return World(0.95 + 0.05 * field)


def _flight(world: World, config: ClearanceConfig, seed: int) -> Flight:
    # These flights are about the spot's keyframe: the scene's levels come from the first views.
    return fly(world, ClearancePolicy(config.replace(scene_after_top_pass=False)), seed=seed, t_max_s=300.0, **DRIFT)


def test_over_faint_texture_the_touchdown_is_the_checked_ground() -> None:
    """Registered against the spot's keyframe, the hand-over lies within ~1 m of the confirmed
    ground, and the confirmation came from a look during the descent, not only the choice."""
    world = _sand(11)
    flight = _flight(world, ClearanceConfig(), seed=11)
    assert flight.alt_m <= 20.0 and flight.decision.state in ("DESCEND", "HANDOVER"), flight.decision.reason
    error = flight.touchdown_error_m()
    assert error is not None and error < 1.5, error
    confirmed_alt = flight.frame_poses[flight.decision.confirmed.frame_seq][2]
    assert confirmed_alt < 25.0  # confirmed again on the way down, close to the hand-over


def test_trusting_the_estimate_lands_far_from_the_checked_ground() -> None:
    """The control: the same flight with the vision fix and the re-check turned off (no peak is
    ever clear enough, the spot counts as known forever) hands over where dead reckoning took it,
    metres from the ground it checked: the test above passes because of the keyframe."""
    world = _sand(11)
    blind = ClearanceConfig(spot_min_response=1.0, spot_trust_s=1e6)
    flight = _flight(world, blind, seed=11)
    assert flight.alt_m <= 20.0
    error = flight.touchdown_error_m()
    assert error is not None and error > 4.0, error


def test_where_vision_cannot_tell_it_rechecks_below_and_never_descends_on_the_estimate() -> None:
    """Featureless ground (only per-frame noise): no look registers, so the descent goes in
    steps, each after the footprint below was re-checked; every descending command follows a
    recent confirmation, and the hand-over lies near the last one despite the drift."""
    world = World(np.ones((SIDE, SIDE), bool))
    policy = ClearancePolicy(ClearanceConfig(scene_after_top_pass=False))
    flight = fly(world, policy, seed=3, t_max_s=300.0, **DRIFT)
    assert flight.alt_m <= 20.0
    assert any("re-checked the footprint below" in r for r in _reasons(policy, flight))
    held = [down for _, _, alt, state, down in flight.track if state == "DESCEND" and 22.0 < alt < 90.0]
    assert held and min(held) == 0.0 and max(held) > 0.0  # it descended, and it held in between
    error = flight.touchdown_error_m()
    assert error is not None and error < 2.5, error


def _reasons(policy: ClearancePolicy, flight: Flight) -> list[str]:
    return [flight.decision.reason, policy.memory.reason]
