"""What `clearance` reports with each decision (`Decision.report`), typed: the position estimate and
its bias, the map, the search's counters, the probe, the registration and the hold.

The chosen spot itself is `Decision.spot` (a `SpotReport`, shared by every policy with a ground
map: the controller's status carries it).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ProbeReport:
    """The area the search looks closer at (the high map's promise there)."""

    north_m: float
    east_m: float
    p_safe: float


@dataclass(frozen=True)
class RegistrationReport:
    """The last heatmap's registration against the keyframe and the spot's anchor."""

    registered: bool
    response: float
    innovation_m: float
    anchored: bool
    spot_fixed: bool
    spot_response: float
    spot_since_s: float  # capped at 1e6 s (never fixed)


@dataclass(frozen=True)
class SceneReport:
    """The scene's levels read off the high map (log-odds); a threshold nothing meets reports as 99."""

    spot_logit: float
    gate_logit: float
    best_logit: float
    typical_logit: float


@dataclass(frozen=True)
class ClearanceReport:
    """One decision of the `clearance` policy, as it explains it."""

    alt_agl_m: float
    est_north_m: float  # the policy's own position estimate (no true position is ever read)
    est_east_m: float
    bias_north_m_s: float  # the learnt bias of the autopilot's velocity estimate
    bias_east_m_s: float
    cell_m: float  # the ground map's resolution now
    aborts: int
    blacklisted: int  # rejected areas
    required_clearance_m: float
    waypoint: int  # of the search route
    fenced: bool  # the fence cut the command
    fence_m: float
    uncertainty_m: float
    anchors: int
    probes: int  # areas probed so far
    scene: SceneReport | None = None  # None until the high map has levels
    probe: ProbeReport | None = None
    registration: RegistrationReport | None = None
    hold_error_m: float | None = None  # while holding where the search gave up: distance from that point
