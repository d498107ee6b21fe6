"""What the `dovesei` policy reports with each decision (`Decision.report`), typed: the state
machine's errors, gains and integrator (`MachineReport`) and the lander image's segmentation and
candidates (`DoveseiReport`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MachineReport:
    """One cycle of the reference's state machine."""

    cg: float  # conservative gain
    err_m: float  # horizontal error to the target (the reference's halved metres)
    x_err_m: float
    y_err_m: float
    est_m: float  # the altitude estimate the machine compares against
    dt_s: float  # data-clock seconds since the previous cycle (the nominal period on the first)
    xy_ok: bool
    is_landing: bool
    is_aiming: bool
    descend_while_aiming: bool
    gain: float
    int_x: float  # integrator
    int_y: float
    s_m_s: float  # descent speed
    cycles: int


@dataclass(frozen=True)
class DoveseiReport:
    """One decision of the `dovesei` policy: the machine's cycle and what the image gave it."""

    machine: MachineReport
    alt_agl_m: float
    proj_m: float  # the heatmap's footprint, metres
    seg_ok: bool  # the dynamic threshold found a mask
    safe_fraction: float
    focus_radius_grid_px: float
    score: float | None = None  # the best candidate's score; None without candidates
    n_candidates: int | None = None
    target_row_grid_px: float | None = None  # the best candidate on the reference's grid
    target_col_grid_px: float | None = None
