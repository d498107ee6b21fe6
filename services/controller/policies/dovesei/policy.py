"""The `dovesei` policy: the DOVESEI (2023) lander, faithful to docs/REFERENCE.md.

One decision cycle per heatmap, exactly like the reference (its cycle = one segmentation answer).
Data flows one way through a cycle:

    P(safe) (H, W) float32
      -> dynamic_threshold   0/255 mask of "the best ~10 % of pixels" (the reference's
                             segmentation service), or failure
      -> LanderImage         resize to 352x353, EMA, uint8, border, > 127, dynamic focus circle,
                             distance transform, cores > 0.6, contour candidates sorted by
                             area / perimeter / (distance to centre + 1), dummy "straight ahead"
      -> StateMachine        errors in (halved) metres, transitions, outputs, integrator
      -> Decision            body FRD velocity (+down), state, target, focus radius

State chain, checked in this order every cycle ("timer" = the give-up timer):

    any   --alt - est <= 5 m-->                        LANDED (terminal)
    any   --non-finite input or < 5 cycles so far-->   SENSOR_ERROR (timer cleared)
    no timer:      is_landing                       -> LANDING
                   is_aiming and not LANDING        -> AIMING
                   alt >= 50 and alt + est >= 55    -> SEARCHING
                   otherwise SEARCHING stays, any other state -> WAITING (timer starts)
    timer > 5 s:   alt >= 50 -> RESTARTING (towards the 2nd candidate) --60 s--> SEARCHING
                   alt <  50 -> CLIMBING (+6 m/s)
    timer <= 5 s:  is_landing -> LANDING (timer cleared), otherwise unchanged (WAITING)

A typical flight: SENSOR_ERROR x5 -> SEARCHING -> AIMING (descending to ~55 m) -> LANDING -> LANDED.
Timeouts: WAITING and CLIMBING end through the give-up timer, RESTARTING after its 60 s; SEARCHING,
AIMING and LANDING have none in the reference (the 1200 s episode limit is the bench's). Timers
are in the reference's (wall) seconds and run on the data clock scaled by `timer_scale`; so does
the dt of `est` (config.py says why).
Every behaviour-changing quirk of the reference is reproduced and marked `# quirk:`.
Ticks without a new heatmap (`prob_safe is None`) are not cycles: the previous decision is
returned unchanged, as the reference's vehicle held its last command between answers.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np

from dovesei.controller.policies.base import Decision, Observation, PolicyInputError, checked_prob_safe, resolve_config
from dovesei.controller.policies.dovesei.config import DoveseiConfig, timing_preset
from dovesei.controller.policies.dovesei.report import DoveseiReport, MachineReport
from dovesei.shared import footprint

log = logging.getLogger(__name__)


class DoveseiState(str, Enum):
    SEARCHING = "SEARCHING"
    AIMING = "AIMING"
    LANDING = "LANDING"
    WAITING = "WAITING"
    CLIMBING = "CLIMBING"
    RESTARTING = "RESTARTING"
    LANDED = "LANDED"
    SENSOR_ERROR = "SENSOR_ERROR"


# The failure path's normalised error: x 1000 of the footprint half-width, a saturated move.
_FAILURE_ERR_NORM = (1000.0, 1000.0)
# The dummy candidate: normalised error "straight ahead" with score 0, always in the list.
_DUMMY_ERR_NORM = (1.0, 0.0)


# ---------------------------------------------------------------------------------------------
# Segmentation service: dynamic threshold
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ThresholdResult:
    mask_u8: np.ndarray | None  # 0/255 with the input's shape; None when the service fails
    threshold: float | None  # the threshold that produced the mask; None on failure
    safe_fraction: float  # fraction of pixels in the mask (0 on failure)


def _min_count(n_px: int, fraction: float) -> int:
    """Smallest pixel count k with k / n >= fraction in float arithmetic (the reference's test)."""
    k = math.ceil(fraction * n_px)
    while k > 0 and (k - 1) / n_px >= fraction:
        k -= 1
    while k / n_px < fraction:
        k += 1
    return k


def dynamic_threshold(prob_safe: np.ndarray, config: DoveseiConfig) -> ThresholdResult:
    """The reference service's threshold loop, found by bisection instead of 100 passes.

    Reference loop: thr = 0.85; for ti in 0..100: if frac(P > thr) < 0.10 then thr = 0.85 -
    0.0085 * ti, else success. So the thresholds CHECKED are 0.85, 0.85 (step 0 repeats), 0.8415,
    ..., 0.0085, and 0.0 is set but never checked (failure). frac(P > thr) >= 0.10 holds exactly
    when the k-th largest value is > thr, k the smallest count making the fraction >= 0.10.
    """
    p = np.ascontiguousarray(prob_safe, dtype=np.float32)
    n_px = p.size
    k = _min_count(n_px, config.seg_min_safe_fraction)
    start = config.seg_threshold_start
    step = start / config.seg_threshold_steps
    # quirk: step 0 is checked twice (the loop sets 0.85 - 0 * step after failing at 0.85).
    checked = [start] + [start - step * ti for ti in range(config.seg_threshold_steps)]
    # Comparisons run in float32 like the reference's (float32 array vs Python float).
    checked_f32 = np.asarray(checked, dtype=np.float32)

    def passes(i: int) -> bool:  # the k-th largest P is > checked[i]: at least k pixels above it
        return int(np.count_nonzero(p > checked_f32[i])) >= k

    # `passes` only turns true as the thresholds fall, so the first passing one is found by
    # bisection: a handful of counts instead of a selection over the whole grid (40x cheaper).
    if not passes(len(checked) - 1):
        return ThresholdResult(None, None, 0.0)
    lo, hi = 0, len(checked) - 1  # the first passing index lies in [lo, hi]
    while lo < hi:
        mid = (lo + hi) // 2
        if passes(mid):
            hi = mid
        else:
            lo = mid + 1
    threshold = checked[lo]
    mask = np.greater(p, np.float32(threshold)).view(np.uint8) * np.uint8(255)
    return ThresholdResult(mask, float(threshold), float(np.count_nonzero(mask)) / n_px)


# ---------------------------------------------------------------------------------------------
# Lander post-processing: EMA, focus, distance transform, candidates
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Candidates:
    """Landing candidates best first; the dummy is the entry whose pixel is None."""

    err_norm: np.ndarray  # (n, 2) normalised error (x forward = image up, y right), best first
    scores: np.ndarray  # (n,) area / perimeter / (distance + 1), best first
    pixels_rc: tuple[tuple[int, int] | None, ...]  # grid (row, col) of each, None for the dummy


def focus_target_px(prev_state: DoveseiState, proj_m: float, radius_px: float, config: DoveseiConfig) -> float:
    """Where the focus radius heads this cycle, from the PREVIOUS cycle's state."""
    if not config.dynamic_focus:
        return config.focus_diagonal_px
    half_width_px = config.grid_cols_px / 2.0  # 176.5: the reference uses the odd width
    if prev_state is DoveseiState.AIMING:
        return float(int(config.focus_mult_aiming * half_width_px * config.safety_radius_m / proj_m))
    if prev_state is DoveseiState.LANDING:
        return float(int(config.focus_mult_landing * half_width_px * config.safety_radius_m / proj_m))
    if prev_state is DoveseiState.WAITING:
        return radius_px
    return config.focus_diagonal_px


@functools.lru_cache(maxsize=8)
def _focus_circle(rows: int, cols: int, radius: int) -> np.ndarray:
    """The filled focus circle (255 inside) on a rows x cols grid, centred on the integer pixel
    (int(cols / 2), int(rows / 2)); read-only and kept: a settled focus draws the same circle cycle
    after cycle."""
    circle = np.zeros((rows, cols), np.uint8)
    cv2.circle(circle, (int(cols / 2.0), int(rows / 2.0)), radius, 255, -1)
    circle.flags.writeable = False
    return circle


def find_candidates(binary_u8: np.ndarray, focus_radius_px: float, config: DoveseiConfig) -> Candidates:
    """Cores of the focused binary grid -> sorted candidates (steps 4-6 after the radius update).

    `binary_u8` is the 0/255 grid after EMA, border and > 127; it is modified in place (focus).
    """
    rows, cols = binary_u8.shape
    centre_row, centre_col = rows / 2.0, cols / 2.0  # (176, 176.5): scores measure from here
    radius = int(focus_radius_px)
    # The circle is centred on integer pixels (col 176, row 176); a radius reaching every corner
    # keeps the whole grid, so drawing it is skipped (identical result, cheaper).
    cover_px = math.ceil(math.hypot(max(int(centre_row), rows - 1 - int(centre_row)),
                                    max(int(centre_col), cols - 1 - int(centre_col)))) + 1
    if radius < cover_px:
        # quirk: pixels outside are zeroed BEFORE the distance transform: the edge is an obstacle.
        cv2.bitwise_and(binary_u8, _focus_circle(rows, cols, radius), dst=binary_u8)

    # The distance map is worked out over the rows of the safe pixels and one more above and below
    # (all of them when there are none), whole rows: those rows are 0 (obstacles), so no shorter
    # path to an obstacle leaves them, and OpenCV's float rounding of a value follows its column
    # (a box of columns moved some values by 1 ulp and a candidate by 8 px). The rest is 0.
    _, by, _, bh = cv2.boundingRect(binary_u8)
    r0, r1 = (max(by - 1, 0), min(by + bh + 1, rows)) if bh else (0, rows)
    if (r0, r1) == (0, rows):
        dist = cv2.distanceTransform(binary_u8, cv2.DIST_L2, 3)
    else:
        dist = np.zeros((rows, cols), np.float32)
        dist[r0:r1] = cv2.distanceTransform(binary_u8[r0:r1], cv2.DIST_L2, 3)
    cv2.normalize(dist, dist, 0.0, 1.0, cv2.NORM_MINMAX)
    # quirk: cv2.THRESH_BINARY keeps dist > 0.6 strictly (not >=), as the reference does.
    cores = (dist > np.float32(config.dist_core_threshold)).view(np.uint8)
    contours, _ = cv2.findContours(cores, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)

    errs: list[tuple[float, float]] = [_DUMMY_ERR_NORM]
    scores: list[float] = [0.0]
    pixels: list[tuple[int, int] | None] = [None]
    for contour in contours:
        area = cv2.contourArea(contour)  # of the simplified polygon: a 3x3 core has area 4
        perimeter = cv2.arcLength(contour, True)
        if area == 0 or perimeter == 0:
            continue
        # First row-major maximum of the distance inside the filled contour. Working in the
        # bounding box gives the same pixel: row-major order inside a box is the global order.
        x0, y0, w, h = cv2.boundingRect(contour)
        filled = np.zeros((h, w), np.uint8)
        cv2.drawContours(filled, [contour], -1, 255, cv2.FILLED, offset=(-x0, -y0))
        inside = np.where(filled == 255, dist[y0:y0 + h, x0:x0 + w], np.float32(0.0))
        r_box, c_box = np.unravel_index(int(np.argmax(inside)), inside.shape)
        row, col = int(r_box) + y0, int(c_box) + x0
        dist_to_centre_px = math.sqrt((centre_row - row) ** 2 + (centre_col - col) ** 2)
        # Same operation order as the reference so equal shapes give bit-identical scores.
        scores.append((1.0 / perimeter) * area / (dist_to_centre_px + 1.0))
        errs.append(((centre_row - row) / rows, -(centre_col - col) / cols))
        pixels.append((row, col))

    # quirk: argsort()[::-1] reverses an ascending sort; numpy sorts short lists stably, so among
    # equal scores the LATER contour wins, and the dummy (score 0, index 0) always comes last.
    order = np.argsort(np.asarray(scores))[::-1]
    return Candidates(
        err_norm=np.asarray(errs, dtype=np.float64)[order],
        scores=np.asarray(scores, dtype=np.float64)[order],
        pixels_rc=tuple(pixels[i] for i in order),
    )


class LanderImage:
    """The lander's image-space memory: the EMA heatmap and the focus radius."""

    def __init__(self, config: DoveseiConfig) -> None:
        self._config = config
        self.filtered: np.ndarray | None = None  # EMA grid, float64, None before the first success
        self._delta = np.empty((config.grid_rows_px, config.grid_cols_px), np.float64)  # scratch
        self.radius_px = config.focus_diagonal_px

    def process(self, mask_u8: np.ndarray, prev_state: DoveseiState, proj_m: float) -> Candidates:
        cfg = self._config
        # quirk: the reference passes INTER_AREA in the dst slot, so bilinear runs; its grey edges
        # feed the EMA.
        resized = cv2.resize(mask_u8, (cfg.grid_cols_px, cfg.grid_rows_px))
        if self.filtered is None:
            # The EMA starts at the first SUCCESSFUL heatmap.
            self.filtered = resized.astype(np.float64)
        # F += beta * (H - F), written in place with the same operations and rounding.
        np.subtract(resized, self.filtered, out=self._delta)
        self._delta *= cfg.ema_beta
        self.filtered += self._delta
        # quirk: no compensation for the UAV's own motion (the EMA lives in image space).
        grid = self.filtered.astype(np.uint8)  # truncation: F >= 128 passes, not F >= 127.5
        grid[0, :] = 0
        grid[-1, :] = 0
        grid[:, 0] = 0
        grid[:, -1] = 0
        _, binary = cv2.threshold(grid, cfg.binary_threshold_u8, 255, cv2.THRESH_BINARY)

        target = focus_target_px(prev_state, proj_m, self.radius_px, cfg)
        self.radius_px += cfg.focus_rate * (target - self.radius_px)
        return find_candidates(binary, self.radius_px, cfg)


# ---------------------------------------------------------------------------------------------
# State machine
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MachineOutput:
    state: DoveseiState
    vel_forward_m_s: float
    vel_right_m_s: float
    vel_up_m_s: float
    report: MachineReport


def conservative_gain(elapsed_data_s: float, config: DoveseiConfig) -> float:
    """cg = max(0.5, 1 - exp(1 - 300 / elapsed)), elapsed in reference seconds."""
    elapsed_ref_s = elapsed_data_s / config.timer_scale
    if elapsed_ref_s <= 0.0:
        return 1.0  # the limit as elapsed -> 0+ (the reference never evaluates it at 0)
    cg = 1.0 - math.exp(1.0 - config.max_landing_time_s / elapsed_ref_s)
    return cg if cg > config.min_conservative_gain else config.min_conservative_gain


class StateMachine:
    """The reference lander's state update and velocity law (pure, one call per cycle)."""

    def __init__(self, config: DoveseiConfig) -> None:
        self._config = config
        self.reset()

    def reset(self) -> None:
        cfg = self._config
        self.state = DoveseiState.SEARCHING  # the reference's initial state, before warm-up
        self.cycles = 0  # counts SENSOR_ERROR cycles only, as the reference does
        self.giveup_start_s: float | None = None  # the reference's 0 = "off"
        self.restart_start_s: float | None = None
        self.restart_dir_m = (0.0, 0.0)
        self.s_m_s = cfg.z_speed_landing_m_s
        self.gain = cfg.gain_searching
        self.int_x = 0.0
        self.int_y = 0.0

    def update(
        self,
        *,
        elapsed_s: float,
        dt_s: float,
        alt_agl_m: float,
        err_sorted_m: np.ndarray,
        depth_ok: bool,
    ) -> MachineOutput:
        """One cycle. `err_sorted_m` is (n >= 1, 2): candidates in metres (halved), best first."""
        cfg = self._config
        prev = self.state
        cg = conservative_gain(elapsed_s, cfg)
        dt_est_s = dt_s / cfg.timer_scale if cfg.est_dt_on_reference_clock else dt_s
        # quirk: est = s * dt with dt on the reference's clock: much larger than the real per-cycle
        # descent, the cause of the SEARCHING -> AIMING -> LANDING oscillation around 52-55 m.
        est_m = self.s_m_s * dt_est_s
        landed = alt_agl_m - est_m <= cfg.altitude_landed_m
        x_err_m, y_err_m = float(err_sorted_m[0, 0]), float(err_sorted_m[0, 1])
        err_m = math.sqrt(x_err_m**2 + y_err_m**2)
        xy_ok = err_m < cfg.xy_ok_mult * cfg.safety_radius_m / cg
        is_safe = alt_agl_m >= cfg.safe_altitude_m
        descend_while_aiming = alt_agl_m + est_m >= cfg.aiming_floor_m
        is_landing = err_m < cfg.safety_radius_m and depth_ok and not descend_while_aiming
        is_aiming = is_safe and xy_ok and depth_ok

        # --- transitions, in the reference's order ---
        if landed:
            self.state = DoveseiState.LANDED
        elif not (math.isfinite(x_err_m) and math.isfinite(y_err_m)) or self.cycles < cfg.warm_up_cycles:
            self.state = DoveseiState.SENSOR_ERROR
            self.giveup_start_s = None
            self.cycles += 1
        elif self.giveup_start_s is None:
            if is_landing:
                self.state = DoveseiState.LANDING
            elif is_aiming and self.state is not DoveseiState.LANDING:
                # quirk: LANDING never falls back to AIMING, so it almost never aborts.
                self.state = DoveseiState.AIMING
            elif is_safe and descend_while_aiming:
                self.state = DoveseiState.SEARCHING
            elif self.state is not DoveseiState.SEARCHING:
                self.giveup_start_s = elapsed_s
                self.state = DoveseiState.WAITING
            # quirk: otherwise SEARCHING persists at any altitude (after an abort it searches at
            # ~50 m and never climbs back to 100 m).
        else:
            if elapsed_s - self.giveup_start_s > cfg.giveup_after_data_s:
                if is_safe:
                    self.state = DoveseiState.RESTARTING
                    if self.restart_start_s is None:
                        # quirk: the direction is the SECOND candidate (often the dummy, due
                        # forward), in metres at this cycle's proj, chosen once.
                        row = 1 if err_sorted_m.shape[0] > 1 else 0
                        self.restart_dir_m = (float(err_sorted_m[row, 0]), float(err_sorted_m[row, 1]))
                        self.restart_start_s = elapsed_s
                    if elapsed_s - self.restart_start_s > cfg.restart_duration_data_s:
                        self.giveup_start_s = None
                        self.restart_start_s = None
                        self.state = DoveseiState.SEARCHING
                else:
                    self.state = DoveseiState.CLIMBING
            elif is_landing:
                self.state = DoveseiState.LANDING
                self.giveup_start_s = None

        # --- outputs: lateral terms (x, y) in halved metres, vertical z (+up) ---
        x = y = z_up = 0.0
        if self.state is DoveseiState.SEARCHING:
            self.gain = cfg.gain_searching
            x, y = x_err_m, y_err_m
            # Neutralised so that the integrator is exactly 0 after this cycle's update.
            self.int_x, self.int_y = -x, -y
        elif self.state is DoveseiState.AIMING:
            self.gain = cfg.gain_searching * cfg.aiming_gain_mult
            x, y = x_err_m, y_err_m
            if descend_while_aiming:
                self.s_m_s = cfg.aiming_descending_mult * cfg.z_gain_landing_per_s * cfg.z_speed_landing_m_s * alt_agl_m
                z_up = -self.s_m_s
        elif self.state is DoveseiState.LANDING:
            self.int_x = self.int_y = 0.0
            s = cfg.z_gain_landing_per_s * cfg.z_speed_landing_m_s * alt_agl_m
            self.s_m_s = s if s > cfg.z_min_speed_landing_m_s else cfg.z_min_speed_landing_m_s
            z_up = -self.s_m_s
        elif self.state is DoveseiState.CLIMBING:
            z_up = cfg.z_speed_climbing_m_s
        elif self.state is DoveseiState.RESTARTING:
            # quirk: the gain is whatever the last SEARCHING/AIMING cycle set (0.5 or 0.25).
            x, y = self.restart_dir_m
        # WAITING, SENSOR_ERROR, LANDED: x = y = z = 0.

        # quirk: the integrator has no dt, is clipped to +/-1 and runs in every state, so the
        # "zero" states still move at gain * int; only SEARCHING and LANDING clear it.
        lim = cfg.integrator_limit
        self.int_x = min(max(self.int_x + x, -lim), lim)
        self.int_y = min(max(self.int_y + y, -lim), lim)
        vel_forward = x * self.gain + self.int_x * self.gain
        vel_right = y * self.gain + self.int_y * self.gain

        if self.state is not prev:
            log.info(
                "dovesei: %s -> %s (alt %.2f m, err %.2f m, est %.2f m, cg %.3f)",
                prev.value, self.state.value, alt_agl_m, err_m, est_m, cg,
            )
        report = MachineReport(
            cg=cg, err_m=err_m, x_err_m=x_err_m, y_err_m=y_err_m, est_m=est_m, dt_s=dt_s, xy_ok=bool(xy_ok),
            is_landing=bool(is_landing), is_aiming=bool(is_aiming), descend_while_aiming=bool(descend_while_aiming),
            gain=self.gain, int_x=self.int_x, int_y=self.int_y, s_m_s=self.s_m_s, cycles=int(self.cycles),
        )
        return MachineOutput(self.state, vel_forward, vel_right, z_up, report)


# ---------------------------------------------------------------------------------------------
# The policy
# ---------------------------------------------------------------------------------------------


def _resolve_config(config: DoveseiConfig | str | None) -> DoveseiConfig:
    return resolve_config(config, DoveseiConfig, timing_preset, "dovesei")


class DoveseiPolicy:
    """The reference lander as a pure policy: `step` once per controller tick."""

    def __init__(
        self, config: DoveseiConfig | str | None = None, *, name: str = "dovesei", dynamic_focus: bool = True
    ) -> None:
        cfg = _resolve_config(config)
        if not dynamic_focus:
            cfg = cfg.replace(dynamic_focus=False)  # the paper's ablation
        self.name = name
        self.config = cfg
        self._machine = StateMachine(cfg)
        self.reset()

    def reset(self) -> None:
        self._image = LanderImage(self.config)
        self._machine.reset()
        self._t0_s: float = math.nan  # set by the first step
        self._last_cycle_t_s: float | None = None
        self._landed = False
        self._decision = Decision(
            vel_body_frd_m_s=(0.0, 0.0, 0.0),
            yaw_rate_rad_s=0.0,
            state=DoveseiState.SENSOR_ERROR.value,  # nothing seen yet: the warm-up state
            target_px=None,
            focus_radius_px=self._image.radius_px,
            threshold=None,
        )

    # Read-only views for tests, logs and overlays.
    @property
    def state(self) -> DoveseiState:
        return self._machine.state

    @property
    def focus_radius_px(self) -> float:
        return self._image.radius_px

    @property
    def filtered_heatmap(self) -> np.ndarray | None:
        """A copy of the EMA grid (352x353, values 0..255), None before the first success."""
        return None if self._image.filtered is None else self._image.filtered.copy()

    def step(self, obs: Observation) -> Decision:
        prob = self._validate(obs)
        if math.isnan(self._t0_s):
            self._t0_s = obs.t_s  # elapsed time (cg, timers) counts from the first step
        if prob is None or self._landed:
            # Not a cycle: the reference vehicle held its last command between answers, and
            # the reference process exits once LANDED.
            return self._decision
        if self._last_cycle_t_s is None:
            dt_s = self.config.decision_period_s  # no previous cycle: the nominal period
        else:
            dt_s = obs.t_s - self._last_cycle_t_s
            if dt_s == 0.0:
                return self._decision  # quirk: the reference skips a cycle with dt == 0
        self._last_cycle_t_s = obs.t_s
        return self._cycle(obs, prob, dt_s)

    def _cycle(self, obs: Observation, prob: np.ndarray, dt_s: float) -> Decision:
        cfg = self.config
        prev_state = self._machine.state
        seg = dynamic_threshold(prob, cfg)
        proj_m = footprint.half_width_m(obs.alt_agl_m, obs.hfov_rad)  # footprint HALF-width
        usable_alt = math.isfinite(proj_m) and proj_m > 0.0
        candidates: Candidates | None = None
        if seg.mask_u8 is not None and usable_alt:
            candidates = self._image.process(seg.mask_u8, prev_state, proj_m)
            # quirk: normalised errors span the FULL width but proj is the HALF-width, so every
            # metric error, threshold and gain below acts on half the true offset.
            err_sorted_m = candidates.err_norm * proj_m
            depth_ok = True  # the reference simulator's constant fake depth always passes
        elif not usable_alt:
            # Our guard: the reference crashes on a non-finite or zero altitude; NaN errors send
            # the machine to SENSOR_ERROR (or LANDED first when alt - est <= 5 m).
            err_sorted_m = np.array([[math.nan, math.nan]])
            depth_ok = False
        else:
            # Segmentation failure: steps 1-7 skipped, saturated error, depth checks failing.
            err_sorted_m = np.array([_FAILURE_ERR_NORM]) * proj_m
            depth_ok = False

        out = self._machine.update(
            elapsed_s=obs.t_s - self._t0_s,
            dt_s=dt_s,
            alt_agl_m=obs.alt_agl_m,
            err_sorted_m=err_sorted_m,
            depth_ok=depth_ok,
        )
        self._landed = out.state is DoveseiState.LANDED

        h_px, w_px = prob.shape
        scale_rows, scale_cols = h_px / cfg.grid_rows_px, w_px / cfg.grid_cols_px
        target_px = None
        extra: dict[str, float | int] = {}
        if candidates is not None:
            extra.update(score=float(candidates.scores[0]), n_candidates=len(candidates.scores))
            best = candidates.pixels_rc[0]
            if best is not None:
                # Grid pixel centres mapped back onto the observation's heatmap pixels.
                target_px = ((best[0] + 0.5) * scale_rows - 0.5, (best[1] + 0.5) * scale_cols - 0.5)
                extra.update(target_row_grid_px=float(best[0]), target_col_grid_px=float(best[1]))
        report = DoveseiReport(machine=out.report, alt_agl_m=float(obs.alt_agl_m), proj_m=float(proj_m),
                               seg_ok=seg.mask_u8 is not None, safe_fraction=float(seg.safe_fraction),
                               focus_radius_grid_px=float(self._image.radius_px), **extra)
        log.debug("dovesei cycle t=%.3f state=%s report=%s", obs.t_s, out.state.value, report)
        self._decision = Decision(
            vel_body_frd_m_s=(float(out.vel_forward_m_s), float(out.vel_right_m_s), float(-out.vel_up_m_s)),
            yaw_rate_rad_s=0.0,  # the reference has no yaw control
            state=out.state.value,
            target_px=target_px,
            focus_radius_px=self._image.radius_px * scale_rows,
            threshold=seg.threshold,
            report=report,
            # The paper's success is reaching 20 m while LANDING; any other state there is not a landing.
            landing=out.state in (DoveseiState.LANDING, DoveseiState.LANDED),
        )
        return self._decision

    def _validate(self, obs: Observation) -> np.ndarray | None:
        """Checks an observation; returns P(safe) as float32 (or None when there is none)."""
        if not isinstance(obs.t_s, (int, float)) or not math.isfinite(obs.t_s):
            raise PolicyInputError(f"observation t_s must be a finite number of seconds, got {obs.t_s!r}")
        if self._last_cycle_t_s is not None and obs.t_s < self._last_cycle_t_s:
            raise PolicyInputError(
                f"observation t_s went backwards: {obs.t_s} s after a cycle at {self._last_cycle_t_s} s"
            )
        if not isinstance(obs.alt_agl_m, (int, float)):
            raise PolicyInputError(f"observation alt_agl_m must be a number (NaN allowed), got {obs.alt_agl_m!r}")
        if not (isinstance(obs.hfov_rad, (int, float)) and 0.0 < obs.hfov_rad < math.pi):
            raise PolicyInputError(f"observation hfov_rad must be in (0, pi), got {obs.hfov_rad!r}")
        if obs.prob_safe is None:
            return None
        prob = obs.prob_safe
        return checked_prob_safe(prob, min_side_px=1)
