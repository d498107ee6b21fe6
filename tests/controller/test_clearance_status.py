"""The controller's status explains the `clearance` policy: the reason of its last transition and
the spot it chose, with clearance and confidence, on the wire like every other field."""

from __future__ import annotations

import numpy as np
import pytest

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.clearance.policy import ClearancePolicy
from dovesei.shared.codec import decode, encode
from dovesei.shared.messages import ControllerStatus, FieldError, SafetyHeatmap, Stamp, VehicleState


def _open_ground(seq: int, t_s: float, rng: np.random.Generator) -> SafetyHeatmap:
    prob = np.clip(0.92 + rng.normal(0.0, 0.03, (64, 64)), 0.0, 1.0).astype(np.float16)
    return SafetyHeatmap("uav1", seq, Stamp(t_s, "sim"), prob, 100.0, 1.274, "simulated", True, "p", "f", inference_s=0.1)


def test_status_carries_the_transition_reason_and_the_chosen_spot() -> None:
    # Open ground from the first views (the scene's levels without waiting for the top pass).
    core = ControllerCore(ControllerConfig(lockstep=True, policy="clearance"),
                          policy=ClearancePolicy(ClearanceConfig(scene_after_top_pass=False)))
    rng = np.random.default_rng(0)
    seen: list[ControllerStatus] = []
    for seq in range(30):  # the levels are read every 2 s: a few frames before the first spot
        t = 0.5 * seq
        core.on_heatmap(_open_ground(seq, t, rng), t)
        _, status = core.tick(VehicleState("uav1", seq, Stamp(t, "sim"), 100.0, (0.0, 0.0, 0.0), await_frame_seq=seq))
        seen.append(status)
        if status.state in ("APPROACH", "DESCEND"):
            break
    states = [s.state for s in seen]
    assert "SEARCH" in states and states[-1] in ("APPROACH", "DESCEND"), states
    searching = seen[states.index("SEARCH")]
    assert "warm-up" in searching.policy_reason and not searching.spot_valid
    approach = seen[-1]
    # Open ground under the vehicle: the spot is found and locked in one step (SEARCH -> APPROACH
    # -> DESCEND); the status says the last transition's reason.
    expected = "spot " if approach.state == "APPROACH" else "locked within"
    assert approach.policy_reason.startswith(expected), approach.policy_reason
    assert approach.policy_reason == core.decision.reason
    assert approach.spot_valid and approach.spot_clearance_m >= core.policy.config.required_clearance_m
    assert 0.0 < approach.spot_confidence <= 1.0
    assert approach.spot_north_m == pytest.approx(core.decision.spot.north_m)
    assert approach.reason  # the watchdog's own reason is still there, separately
    back = decode(encode(approach), ControllerStatus)
    assert back.policy_reason == approach.policy_reason and back.spot_clearance_m == approach.spot_clearance_m


def test_status_spot_fields_are_range_checked() -> None:
    with pytest.raises(FieldError, match="spot_confidence"):
        ControllerStatus("uav1", 1, Stamp(0.0, "sim"), "clearance", "APPROACH", "ok", "", 0, 0.0, 1.0,
                         spot_valid=True, spot_confidence=1.5)
    with pytest.raises(FieldError, match="spot_clearance_m"):
        ControllerStatus("uav1", 1, Stamp(0.0, "sim"), "clearance", "APPROACH", "ok", "", 0, 0.0, 1.0,
                         spot_clearance_m=-1.0)
