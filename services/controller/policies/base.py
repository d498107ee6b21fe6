"""What every landing policy takes and returns (the contract; `registry` builds one by name).

Data flow: the controller loop turns the newest heatmap and vehicle state into an `Observation`,
calls `Policy.step` once per loop tick and sends the `Decision`'s body-frame FRD velocity. A
policy is pure: no Zenoh, MAVLink or wall clock inside, every time comes from `Observation.t_s`
(the data clock), so the same observations give the same decisions on any host.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from dovesei.shared import footprint
from dovesei.shared.errors import DoveseiError


class PolicyInputError(DoveseiError, ValueError):
    """An observation a policy cannot use (wrong shape, NaN heatmap, time running backwards...)."""


@dataclass(frozen=True)
class LookRequest:
    """A close look a policy asks for: a square of ground around a spot (dovesei.shared.crop),
    centred `centre_frd_m` (forward, right metres from the point below the vehicle, heading-level
    body frame, as the policy believes it now), `side_m` wide, at `out_px`."""

    centre_frd_m: tuple[float, float]
    side_m: float
    out_px: int


@dataclass(frozen=True)
class LookResult:
    """What came of a close look: the scored crop (`heatmap`, a CropHeatmap: probabilities and the
    square's geometry, nothing of the sim's truth), or why there is none (`refusal`: the camera
    refused, the segmenter failed, nobody answered). `request_seq` is the CropRequest's."""

    request_seq: int
    heatmap: Any = None  # dovesei.shared.messages.CropHeatmap
    refusal: str = ""

    @property
    def ok(self) -> bool:
        return self.heatmap is not None


@dataclass(frozen=True)
class Observation:
    """One look at the world, on the data clock: what a real vehicle without GNSS has.

    The camera model is the heatmap's size (pixels, square) and `hfov_rad`; altitude and attitude
    are those at capture; the velocity is the autopilot's own estimate (body FRD, no GNSS: it does
    not see wind or estimator drift). There is deliberately no position field: policies never read
    the sim's true pose (a test asserts this field set).
    """

    t_s: float  # data clock (sim or vehicle), seconds
    # Altitude when the heatmap's frame was captured (the reference samples it at request time).
    alt_agl_m: float
    prob_safe: np.ndarray | None  # (H, W) float32 P(safe) in [0, 1]; None = no new heatmap this tick
    hfov_rad: float = footprint.REFERENCE_HFOV_RAD
    roll_rad: float = 0.0  # attitude at capture (FRD body, radians)
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    vel_est_body_frd_m_s: tuple[float, float, float] | None = None  # autopilot estimate; None = none
    cmd_vel_body_frd_m_s: tuple[float, float, float] | None = None  # last command sent; None = unknown
    # The velocity estimate integrated from the previous observation's capture to this one's (level
    # north/east metres, the autopilot's heading); None = unknown (the policy falls back on
    # velocity x dt, which lags by the perception latency whenever the vehicle accelerates).
    odom_delta_ne_m: tuple[float, float] | None = None
    # The camera frame the heatmap came from (-1: unknown): a policy names it when it reports
    # which heatmap confirmed its spot (`Confirmation`), so a judge can map that look to the ground.
    frame_seq: int = -1
    # The answer to the policy's last `Decision.look_request` (once, on the first observation after
    # it came back); None: nothing new.
    look: LookResult | None = None
    # False while the controller trusts no horizontal velocity (GNSS lost and the camera's velocity
    # lost too: over calm water, say): the policy's commands are not flown meanwhile, and the
    # ground ahead gave the camera nothing to measure.
    velocity_trusted: bool = True
    # How long after the heatmap's capture the decision taken on it starts being flown (data clock:
    # the state the controller adopts it at, less the heatmap's stamp): the pipeline's latency. A
    # word that must outlast it until the next decision (the close look's landing word) counts it.
    delay_s: float = 0.0


@dataclass(frozen=True)
class Confirmation:
    """The heatmap that last confirmed the chosen spot and where the spot lay in it.

    The pixel is in that heatmap's own pixels (row down, col right; the heatmap has its camera
    frame's size and field of view), measured in that look, not projected from a later position
    estimate: mapped with the frame's pose it is the ground whose clearance was checked.
    """

    frame_seq: int
    row_px: float
    col_px: float


@dataclass(frozen=True)
class SpotReport:
    """The spot a policy with a ground map has chosen, where it lies and how good it is."""

    north_m: float  # local north/east of the policy's own position estimate's frame
    east_m: float
    clearance_m: float  # metres of checked safe ground around it (now, on the map)
    confidence: float  # [0, 1]
    p_safe: float  # fused P(safe) at the spot
    distance_m: float  # from the estimated position
    est_north_m: float = 0.0  # the position estimate the spot is seen from (same frame)
    est_east_m: float = 0.0


@dataclass(frozen=True)
class Decision:
    """What to do until the next decision, and why (for logs and the status key)."""

    vel_body_frd_m_s: tuple[float, float, float]  # forward, right, down (+down)
    yaw_rate_rad_s: float
    state: str
    target_px: tuple[float, float] | None  # (row, col) in the observation's heatmap pixels
    focus_radius_px: float
    threshold: float | None  # dynamic segmentation threshold used (None when it failed)
    reason: str = ""  # why the policy is in `state` (the last transition's reason)
    # The policy is committed to landing where it is (descending onto a checked spot, or done):
    # only then may the controller hand over at the hand-over altitude. A descent the policy has
    # aborted that sinks through that altitude (inertia, a baro step) is not a landing.
    landing: bool = False
    # ... and until when that word holds (data clock; None: until the next decision). A policy whose
    # clearance of the ground ages (the close look: walkers) says when it runs out; past it the
    # controller neither hands over nor lets the descent go on until a newer decision renews it.
    landing_until_s: float | None = None
    confirmed: Confirmation | None = None  # policies with a checked spot: the look that confirmed it last
    spot: SpotReport | None = None  # policies with a ground map: the chosen spot (the status carries it)
    # The policy's own typed report of this decision, for logs, tests and overlays: a
    # `ClearanceReport` or a `DoveseiReport` (None before the first one).
    report: Any = None
    # A close look to take now (the controller asks the camera and the segmenter; the answer comes
    # back in a later `Observation.look`), and the last close look's verdict for status and video.
    look_request: LookRequest | None = None
    look_verdict: str = ""


def checked_prob_safe(prob: Any, min_side_px: int) -> np.ndarray:
    """The observation's P(safe) as contiguous float32, or PolicyInputError saying what is wrong."""
    if not isinstance(prob, np.ndarray) or prob.ndim != 2 or min(prob.shape) < min_side_px:
        shape = getattr(prob, "shape", None)
        kind = "a non-empty 2-D numpy array" if min_side_px <= 1 else \
            f"a 2-D numpy array at least {min_side_px} px a side"
        raise PolicyInputError(f"prob_safe must be {kind}, got shape {shape}")
    if not np.issubdtype(prob.dtype, np.floating):
        raise PolicyInputError(f"prob_safe must hold floats in [0, 1], got dtype {prob.dtype}")
    prob = np.ascontiguousarray(prob, dtype=np.float32)
    lo, hi = float(prob.min()), float(prob.max())
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0.0 or hi > 1.0:
        raise PolicyInputError(f"prob_safe must be finite and within [0, 1], got range [{lo}, {hi}]")
    return prob


def resolve_config(config: Any, config_type: type, preset: Callable[[str], Any], what: str) -> Any:
    """A policy's config from a config object, a preset name, or None (the `real` preset)."""
    if config is None:
        return preset("real")
    if isinstance(config, str):
        return preset(config)
    if isinstance(config, config_type):
        return config
    raise TypeError(f"{what} config must be a {config_type.__name__}, a preset name or None, got {type(config).__name__}")


class Policy(Protocol):
    """A landing policy: one `step` per controller tick."""

    name: str

    def step(self, obs: Observation) -> Decision: ...

    def reset(self) -> None: ...
