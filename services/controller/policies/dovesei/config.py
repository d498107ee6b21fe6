"""Every constant of the `dovesei` policy, with units, and its view of the two timing presets.

The values are those in force in the reference's aerial experiments (REFERENCE.md in the project's
shared notes).
Timers are written in the reference's own seconds (5 s, 60 s, 300 s), which were WALL seconds;
`timer_scale` converts them to seconds of the data clock the policy actually runs on:

    data-clock seconds = reference seconds x timer_scale

The presets themselves (`reference`, `real`) are defined once, in `dovesei.shared.timing`, for
the sim, the policies and the CLI alike; this module only copies their `timer_scale` and
`decision_period_s` into a `DoveseiConfig`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from dovesei.shared import timing as shared_timing
from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.shared.mission import SAFETY_RADIUS_M


@dataclass(frozen=True)
class DoveseiConfig:
    """Constants of the reference lander and its segmentation threshold; names carry units."""

    # --- timing (see module docstring) ---
    timing_name: str = "real"
    timer_scale: float = 1.0  # data-clock seconds per reference (wall) second
    decision_period_s: float = 0.5  # nominal time between heatmaps on the data clock
    # The reference measured dt for `est = s * dt` on the wall clock too; with this on, dt is
    # converted like every other timer (data dt / timer_scale). Off = raw data-clock dt.
    est_dt_on_reference_clock: bool = True

    # --- segmentation service: dynamic threshold on P(safe) ---
    seg_threshold_start: float = 0.85
    seg_threshold_steps: int = 100  # threshold = start - (start / steps) * ti, ti = 0..steps
    seg_min_safe_fraction: float = 0.10

    # --- lander post-processing ---
    grid_rows_px: int = 352
    grid_cols_px: int = 353  # width forced odd by the reference
    ema_beta: float = 1.0 / 30.0
    binary_threshold_u8: int = 127  # kept pixels are > this value
    dist_core_threshold: float = 0.6  # normalised distance cores are > this value
    dynamic_focus: bool = True  # False = the paper's no-focus ablation (radius held at diagonal)
    focus_rate: float = 0.1  # r += focus_rate * (target - r) per heatmap
    focus_mult_aiming: float = 6.0  # focus target = mult * half-width px * safety radius / proj
    focus_mult_landing: float = 2.0

    # --- state machine ---
    safe_altitude_m: float = 50.0
    aiming_floor_mult: float = 1.1  # descend while aiming only above 1.1 x safe altitude = 55 m
    safety_radius_m: float = SAFETY_RADIUS_M
    xy_ok_mult: float = 2.0  # xy_ok: err < xy_ok_mult * safety radius / cg
    giveup_after_s: float = 5.0  # reference seconds (x timer_scale on the data clock)
    restart_duration_s: float = 60.0  # reference seconds
    max_landing_time_s: float = 300.0  # reference seconds, horizon of the conservative gain
    min_conservative_gain: float = 0.5
    warm_up_cycles: int = 5
    altitude_landed_m: float = 5.0
    integrator_limit: float = 1.0  # |int| clip per axis (metres of halved error, no dt)

    # --- outputs ---
    gain_searching: float = 0.5
    aiming_gain_mult: float = 0.5  # AIMING gain = 0.25
    z_speed_landing_m_s: float = 3.0  # initial `s`, and the scale of the descent law
    z_gain_landing_per_s: float = 0.02  # LANDING descent = max(0.02 * 3 * alt, 0.5) m/s
    z_min_speed_landing_m_s: float = 0.5
    aiming_descending_mult: float = 0.5  # AIMING descent = 0.5 * 0.02 * 3 * alt = 0.03 * alt
    z_speed_climbing_m_s: float = 6.0  # commanded; the reference sim clips it to 5

    def __post_init__(self) -> None:
        positive = (
            "timer_scale", "decision_period_s", "seg_threshold_start", "seg_min_safe_fraction",
            "ema_beta", "focus_rate", "safe_altitude_m", "safety_radius_m", "giveup_after_s",
            "restart_duration_s", "max_landing_time_s", "min_conservative_gain", "integrator_limit",
            "z_speed_landing_m_s",
        )
        for name in positive:
            validate.positive(f"DoveseiConfig.{name}", getattr(self, name))
        if self.seg_threshold_steps < 1:
            raise ConfigError(f"DoveseiConfig.seg_threshold_steps must be >= 1, got {self.seg_threshold_steps}")
        if self.grid_rows_px < 3 or self.grid_cols_px < 3:
            raise ConfigError(
                f"DoveseiConfig grid must be at least 3x3 px, got {self.grid_rows_px}x{self.grid_cols_px}"
            )
        if not 0.0 < self.ema_beta <= 1.0 or not 0.0 < self.focus_rate <= 1.0:
            raise ConfigError(
                f"DoveseiConfig.ema_beta and focus_rate must be in (0, 1], got {self.ema_beta}, {self.focus_rate}"
            )
        if not 0.0 < self.seg_min_safe_fraction <= 1.0:
            raise ConfigError(f"DoveseiConfig.seg_min_safe_fraction must be in (0, 1], got {self.seg_min_safe_fraction}")
        if self.min_conservative_gain > 1.0:
            raise ConfigError(f"DoveseiConfig.min_conservative_gain must be <= 1, got {self.min_conservative_gain}")

    # Timers on the data clock (what the policy compares elapsed data time against).
    @property
    def giveup_after_data_s(self) -> float:
        return self.giveup_after_s * self.timer_scale

    @property
    def restart_duration_data_s(self) -> float:
        return self.restart_duration_s * self.timer_scale

    @property
    def max_landing_time_data_s(self) -> float:
        return self.max_landing_time_s * self.timer_scale

    @property
    def aiming_floor_m(self) -> float:
        return self.aiming_floor_mult * self.safe_altitude_m

    @property
    def focus_diagonal_px(self) -> float:
        return math.hypot(self.grid_rows_px, self.grid_cols_px)

    def replace(self, **changes: object) -> DoveseiConfig:
        """A copy with some fields changed (validated again)."""
        try:
            return dataclasses.replace(self, **changes)
        except TypeError as exc:  # an unknown field name
            raise ConfigError(f"DoveseiConfig: {exc}") from None


def _from_shared(name: str) -> DoveseiConfig:
    t = shared_timing.timing(name)
    return DoveseiConfig(timing_name=t.name, timer_scale=t.timer_scale, decision_period_s=t.decision_period_s)


def reference_timing() -> DoveseiConfig:
    """Timers and decision rate as the reference's simulated UAV experienced them (shared preset)."""
    return _from_shared("reference")


def real_timing() -> DoveseiConfig:
    """True seconds, and decisions at a real CLIPSeg's rate (shared preset)."""
    return _from_shared("real")


# Name -> builder, for every preset of dovesei.shared.timing (the one owner of the names).
TIMING_PRESETS = {name: (lambda n=name: _from_shared(n)) for name in shared_timing.TIMING_NAMES}


def timing_preset(name: str) -> DoveseiConfig:
    """The preset called `name` ("reference" or "real"), or a ConfigError naming the choices."""
    if name not in TIMING_PRESETS:
        raise ConfigError(f"unknown timing preset {name!r}; known: {', '.join(sorted(TIMING_PRESETS))}")
    return TIMING_PRESETS[name]()
