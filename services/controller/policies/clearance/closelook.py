"""The close look: `clearance` looks at its spot at full resolution before it commits (issue 24).

At 100 m a person is one pixel of the 352 px view and far under one CLIPSeg token: the ground map
cannot see them. So a descending `clearance` asks for a crop of its spot plus the separation
margin (`LookRequest`: the controller gets it from the camera and has it scored with the "never"
set, `dovesei.shared.crop`, docs/CROP.md) and gates its descent on the verdict:

    DESCEND above look_alt_m + brake_m ------------------------------------- descends as before
    reaching it (~43 m) --no clear look of THIS spot yet--> hold the altitude (stops by ~40 m), ask
        clear_looks clear looks in a row (nothing of the never set within margin_m) --> descend on
        anything inside the margin --> hold, keep looking; found in reject_findings of the last
            reject_window looks of that ground, or not clear after wait_s --> reject the spot
            (blacklisted: the inner policy searches on from where it is)
        no answer / refused / failed --> keep holding, ask again every retry_s (never commits blind)
    the last descent (past the gate) --> a new look every look_period_s while descending
        anything inside the margin --> wait (hold the altitude, keep looking: people walk through)
            resume_looks clear looks in a row --> descend on;  not so within wait_s, or found again
            wait_s after the first finding on that ground --> reject (searches on from there)
    within final_gate_m of the hand-over --> a look every final_look_period_s over a wider square
        (margin + walk_m_s x fresh_limit_s: a walker beyond it cannot reach the margin by the
        hand-over); hold unless a clear
        look was asked within `fresh_limit_s` (walkers: the hand-over needs a look from just now),
        and each decision's landing word ends there (the controller neither hands over nor
        descends past it)
    HANDOVER declared, the controller confirming the altitude --> looks go on every final_look_period_s
        anything inside the margin, or no fresh clear look --> the hand-over is taken back (DESCEND,
            holding over the spot as above) until the looks clear it again

The wrapper is pure like every policy: the answer to a request comes back in a later
`Observation.look`; nothing here talks to a camera. Only `clearance`'s DESCEND is gated (the
paper's policy stays faithful to the reference). The spot and the vehicle are read from the inner
decision's `spot` (its own north/east frame), never from a true position.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.shared.frames import to_body
from dovesei.controller.policies.base import Decision, LookRequest, LookResult, Observation
from dovesei.controller.policies.clearance.ground_map import logit
from dovesei.controller.policies.clearance.scene import sigmoid
from dovesei.shared import validate
from dovesei.shared.mission import HANDOVER_ALT_M, PERSON_SEPARATION_M, VEHICLE_SEPARATION_M

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CloseLookConfig:
    """When to look, how wide, and what a look must show; seconds on the data clock."""

    handover_alt_m: float = HANDOVER_ALT_M
    look_alt_m: float = 40.0  # no descent below this without a clear look at the spot
    brake_m: float = 3.0  # the gate closes this far above look_alt_m: a 2 m/s descent stops in time
    final_gate_m: float = 3.0  # within this of the hand-over, the clear look must be fresh
    # The margin around the spot a look must show clear: the separation from people plus the lateral
    # error of landing where it looked (touchdown error median 0.4 m in issue 23's suite). People set
    # it: at 352 px an 8 m square is 2.3 cm/px and a person ~22 px, more than a CLIPSeg token; a
    # square wide enough for the vehicles' 5 m would shrink them under one. Vehicles (4.5 m) are
    # seen in the 352 px view itself from 40 m, and cut into the map's clearance there.
    margin_m: float = PERSON_SEPARATION_M + 1.0
    out_px: int = 352  # CLIPSeg's own input side
    # A look finds something of the never set in two ways. A person is small: at this scale (2.3
    # cm/px, a CLIPSeg token 0.36 m) someone 0.45-0.6 m across answers as a compact blob about a
    # token wide, however faintly the segmenter reads them against the ground around them. So a
    # blob detector, the scale-normalised Laplacian of Gaussian of logit P(never) at blob_sigma_m
    # (a blob of radius r peaks at sigma r / sqrt(2): 0.16-0.21 m for a person), finds a person by
    # how they stand out of their surroundings, not by an absolute level; broad swells of the map
    # (the segmenter's calibration and context moving over metres) do not answer at that scale.
    # Both thresholds were chosen on simulated crops of seeds 100+ (the bench reports 0-33) over
    # parkland, downtown and crowded: 60 people within 3.5 m of the spot and 60 clear
    # squares, 4 looks each, per profile, missing the fewest people first. Checked on other crops
    # (seeds 200+; villas, coast, desert, downtown), against the rules they replace (P >= 0.3, or a
    # rise of 1.0 log-odds above the square's median): `realistic` missed 6 of 237 looks at people
    # (21 before) and fired on 14 of 240 clear looks (28); `harsh` 12 of 237 (46) and 68 of 240 (118).
    blob_sigma_m: float = 0.15
    blob_min_logit: float = 0.10
    # ... and anything broad near even odds (the never set within 0.4 log-odds of the landing
    # prompts: a car, a crowd, an ambiguous person), `never_p_min`. A broad swell below it is the
    # segmenter's calibration, not an object: at 0.3, in the `realistic` checks above, clear looks
    # fired 36 times instead of 14 and 2 looks at people missed instead of 6.
    never_p_min: float = 0.4
    # ... which the flight calibrates online. CLIPSeg's absolute levels move with the scene and its
    # calibration (issue 25), and P(never) with them: `harsh`'s per-episode offset on the landing
    # prompts lifts P(never) over a whole flight, and there the 0.4 level fired on clear ground look
    # after look (harsh coast start 4 of 12: 64 findings in 205 looks, 62 of them with nobody within
    # 6 m and no vehicle within 8 m; the search ended NO_SPOT). So once baseline_looks looks of
    # OTHER ground (farther than a square's side from the spot judged: its own objects do not set
    # its bar) have been scored, something broad must also stand baseline_k_logit above their
    # median (each look's median log-odds P(never)); the baseline never lifts it above never_p_max
    # (more likely never than a landing prompt always counts). Chosen on crops of seeds 100+ (7
    # worlds, 3 looks of 70 clear, 70 person and 60 car squares per profile, the baseline from 3
    # other clear squares under the same perception seed), `harsh`: clear looks fired 28 % -> 17 %
    # (broad rule 17 % -> 4 %), looks at cars found 99 % -> 99 % (broad rule 98 % -> 96 %), looks at
    # people 96 % -> 96 %; `realistic` unchanged (4 %, 100 %, 100 %). k 2.0 kept fewer cars (broad
    # rule 86 %). Checked on seeds 200+: `harsh` clear 32 % -> 18 %, cars 100 % -> 99 % (broad rule
    # 96 % -> 88 %, the blob finds the rest), people 92 % -> 92 %; `realistic` unchanged (5 %, 100 %,
    # 100 %).
    baseline_k_logit: float = 1.5
    baseline_looks: int = 3
    never_p_max: float = 0.6
    # Something broad (the never_p_min rule: a car, a crowd) counts this far from the spot, as far
    # as the square reaches (its half side is margin_m): the judge keeps vehicles 5 m away, and
    # with the person margin alone harsh downtown start 3 of 6 handed over with a car 3.7 m from
    # the touchdown, seen at 3.6-4.3 m look after look.
    broad_margin_m: float = VEHICLE_SEPARATION_M + 1.0
    never_min_px: int = 6  # this many pixels inside the margin (of either rule) make it a finding
    look_period_s: float = 1.0  # the last descent looks again this often
    # ... and this often within final_gate_m of the hand-over and while a declared hand-over is
    # being confirmed: there the looks are what keeps walkers out of the separation (fresh_s).
    final_look_period_s: float = 0.5
    # Looks miss (a person misread as the ground under them in some squares, flicker): the gate
    # needs this many clear looks in a row, and a descent that found something resumes only after
    # resume_looks.
    clear_looks: int = 2
    resume_looks: int = 4
    # One look is not a verdict on a spot: a noisy segmenter fires on a clear square now and then
    # (`harsh`: 28 % of clear looks in the checks above, coming and going from look to look), while
    # someone standing there is found look after look (missed in 5 %). So before the gate a finding
    # holds the descent, and the spot is rejected once reject_findings of the last reject_window
    # looks at that ground (within margin_m) found something, or it is not clear after wait_s. On the
    # calibration crops (4 looks each) that rejected 13 of 60 clear `harsh` squares instead of 22,
    # and every one of the 60 people as before.
    reject_findings: int = 2
    reject_window: int = 3
    retry_s: float = 1.0  # a failed or refused look is asked again after this
    answer_timeout_s: float = 5.0  # a look with no answer after this is asked again
    # Something inside the margin during the last descent: wait this long, then abort. It counts
    # from the first finding on that ground (within margin_m), not from the last: findings that
    # keep coming back between short clear streaks (a crowd walking past, or a flickering false
    # finding) reject the spot too, where each wait restarting had held harsh crowded start 5 of 6
    # between 30 and 45 m for 600 s.
    wait_s: float = 30.0
    # The hand-over needs a clear look asked (cut from the newest frame then) at most this long
    # ago. Someone just outside the square at that look may have walked into the margin since: at
    # 1.5 m/s (the top of pedestrians' usual 1.2-1.5 m/s, and of the sim's walkers) 1 s takes 1.5 m
    # of its 4 m, leaving 2.5 m from the spot in the worst case. Found in a session experiment
    # (Dubai start 15, the perception reading the world's photo): with 3 s allowed, a walker came
    # from beyond the square to 2.5 m of the touchdown in the 2.3 s between the last clear look and
    # the hand-over. A look cannot be younger than its answer's lag plus the delay until a decision
    # is flown plus the policy's step until the next decision renews the word (the bench: 0.5 +
    # 0.4 + 0.5 s; `fresh_limit_s`), so the limit is that, at least
    # fresh_s and at most fresh_max_s (a slow segmenter's looks leave walkers less of the margin,
    # 4 m - 1.5 m/s x the limit; past fresh_max_s the vehicle holds and never hands over blind).
    fresh_s: float = 1.0
    fresh_max_s: float = 3.0
    # ... and the looks that hand over reach that far beyond the margin: within final_gate_m of the
    # hand-over and while one is confirmed, a look's margin (and its square's half side) is
    # margin_m + walk_m_s x the freshness limit, at most final_margin_max_m. Anyone beyond it at
    # the look cannot be inside margin_m by the hand-over. Found on the final code of 7 Dec (coast,
    # `realistic`, start 22): a walker at 1.07 m/s, 4.7 m from the touchdown 1.5 s before the
    # hand-over, outside the 8 m square, was 3.26 m from it at the hand-over. A wider square sees
    # people worse (`closelook-stats`, `harsh`: 12 of 240 looks at people missed at 8 m, 27 at 10
    # m), so only these looks are wider: standing people were looked at from 40 m down at 8 m.
    # The cap keeps them from growing further: at 5.7 m (an 11.4 m square) a walker at walk_m_s
    # from just beyond it is still 3.4 m from the spot after the bench's 1.525 s limit, outside the
    # judge's 3 m; at 6 m `harsh` missed more people (`closelook-stats --seed-base 100`, 60 person
    # squares, 4 looks: 25 of 240 looks missed, the gate opening on 7 squares, at 5.7 m; 30 and 8 at
    # 6 m), and crowded start 16 under `harsh` handed over 2.0 m from someone standing there that
    # its 12 m looks missed twelve times. (That miss was traced later to the simulated perception
    # reading crops at the vehicle's altitude, not to the square's size: docs/RESULTS.md, 7 Dec.)
    walk_m_s: float = 1.5
    final_margin_max_m: float = 5.7
    spot_slack_m: float = 1.0  # a look covers the spot it was asked for, moved at most this far

    def __post_init__(self) -> None:
        for name in ("handover_alt_m", "look_alt_m", "brake_m", "margin_m", "broad_margin_m", "look_period_s", "retry_s",
                     "answer_timeout_s", "wait_s", "fresh_s", "spot_slack_m", "final_look_period_s", "fresh_max_s"):
            validate.positive(f"close look {name}", getattr(self, name))
        # Looks near the hand-over come at least as often as before it, and often enough for one to be fresh.
        validate.in_range("close look final_look_period_s", self.final_look_period_s, 0.0,
                          min(self.look_period_s, self.fresh_s))
        validate.in_range("close look fresh_max_s", self.fresh_max_s, self.fresh_s, 60.0)
        validate.non_negative("close look final_gate_m", self.final_gate_m)
        validate.in_range("close look never_p_min", self.never_p_min, 0.0, 1.0)
        validate.in_range("close look never_p_max", self.never_p_max, 0.0, 1.0)
        validate.non_negative("close look baseline_k_logit", self.baseline_k_logit)
        validate.in_range("close look baseline_looks", self.baseline_looks, 1, 1000)
        # Something broad is at least as much of a finding as a person: never over less ground.
        validate.in_range("close look broad_margin_m", self.broad_margin_m, self.margin_m, 1e4)
        validate.in_range("close look walk_m_s", self.walk_m_s, 0.0, 10.0)
        validate.in_range("close look final_margin_max_m", self.final_margin_max_m, self.margin_m, 1e4)
        validate.in_range("close look blob_sigma_m", self.blob_sigma_m, 0.01, 5.0)
        validate.positive("close look blob_min_logit", self.blob_min_logit)
        validate.in_range("close look out_px", self.out_px, 32, 1024)
        validate.in_range("close look never_min_px", self.never_min_px, 1, 10_000)
        validate.in_range("close look clear_looks", self.clear_looks, 1, 100)
        validate.in_range("close look resume_looks", self.resume_looks, 1, 100)
        validate.in_range("close look reject_window", self.reject_window, 1, 100)
        validate.in_range("close look reject_findings", self.reject_findings, 1, self.reject_window)
        if self.look_alt_m <= self.handover_alt_m + self.final_gate_m:
            validate.in_range("close look look_alt_m", self.look_alt_m, self.handover_alt_m + self.final_gate_m + 1.0,
                              1e4)

    @property
    def side_m(self) -> float:
        """The square asked for: the margin around the spot on every side."""
        return 2.0 * self.margin_m


def close_look_config(handover_alt_m: float) -> CloseLookConfig:
    """The defaults for a flight handing over at `handover_alt_m` (the first look at least 10 m above it)."""
    base = CloseLookConfig()
    return dataclasses.replace(base, handover_alt_m=handover_alt_m, look_alt_m=max(base.look_alt_m,
                                                                                    handover_alt_m + 10.0))


@dataclass(frozen=True)
class Verdict:
    """One look's finding: is the margin around the spot clear of the never set?"""

    clear: bool
    nearest_m: float | None  # distance from the square's centre to the nearest never pixel inside it
    p_max: float  # the largest P(never) within the margin
    median_logit: float = 0.0  # the square's median log-odds P(never): the flight's baseline
    broad_p: float = 0.0  # the level the broad rule used
    raised: bool = False  # the flight's baseline lifted that level above never_p_min

    def text(self, margin_m: float) -> str:
        level = f", broad from P {self.broad_p:.2f} on this flight" if self.raised else ""
        if self.clear:
            seen = f"nearest at {self.nearest_m:.1f} m" if self.nearest_m is not None else "none seen"
            return f"clear: nothing of the never set within {margin_m:.1f} m ({seen}, P max {self.p_max:.2f}{level})"
        broad = ", something broad" if self.nearest_m is not None and self.nearest_m > margin_m else ""
        return (f"never set {self.nearest_m:.1f} m from the spot (P max {self.p_max:.2f}, margin {margin_m:.1f} m"
                f"{broad}{level})")


def blob_response(logit_never: np.ndarray, side_m: float, sigma_m: float) -> np.ndarray:
    """The scale-normalised Laplacian of Gaussian of logit P(never) (float32) at `sigma_m`
    (positive on blobs that stand out of their surroundings), in log-odds, per pixel of the square."""
    sigma_px = sigma_m * logit_never.shape[0] / side_m
    smooth = cv2.GaussianBlur(logit_never, (0, 0), sigma_px)
    return -cv2.Laplacian(smooth, cv2.CV_32F) * np.float32(sigma_px * sigma_px)


def verdict(prob_never: np.ndarray, side_m: float, cfg: CloseLookConfig,
            baseline_logit: float | None = None, margin_m: float | None = None) -> Verdict:
    """Where the never map holds a person-sized blob (`blob_min_logit`) within the margin
    (`margin_m`, else the config's) of the square's centre (the spot asked for), or crosses the
    broad level within broad_margin_m (at least the margin); the nearest of either counts as found.
    The broad level is `never_p_min`, or with the flight's `baseline_logit`
    (`CloseLookPolicy.baseline_logit`) baseline_k_logit above it, at most `never_p_max`."""
    margin = cfg.margin_m if margin_m is None else margin_m
    broad_margin = max(cfg.broad_margin_m, margin)
    n = prob_never.shape[0]
    m_per_px = side_m / n
    c = (n - 1) / 2.0
    yy, xx = np.mgrid[0:n, 0:n]
    dist_px_m = np.hypot(yy - c, xx - c) * np.float32(m_per_px)
    broad_p = cfg.never_p_min
    if baseline_logit is not None:
        broad_p = max(broad_p, min(sigmoid(baseline_logit + cfg.baseline_k_logit), cfg.never_p_max))
    broad = prob_never >= broad_p
    lg = logit(prob_never, 1e-4)  # once: the blob rule's map and the flight's baseline
    blob = blob_response(lg, side_m, cfg.blob_sigma_m) >= cfg.blob_min_logit
    counted = (broad & (dist_px_m <= broad_margin)) | (blob & (dist_px_m <= margin))
    inside = dist_px_m <= margin
    p_max = float(prob_never[inside].max()) if inside.any() else 0.0
    clear = int(np.count_nonzero(counted)) < cfg.never_min_px
    # The nearest finding: of those that count when it is one, of any in the square (a report) when clear.
    dist_m = dist_px_m[(broad | blob) if clear else counted]
    return Verdict(clear, float(dist_m.min()) if dist_m.size else None, p_max, float(np.median(lg)), broad_p,
                   broad_p > cfg.never_p_min)


@dataclass(frozen=True)
class _Look:
    """A look asked or taken: the spot (policy north/east), the altitude, the time and its margin."""

    north_m: float
    east_m: float
    alt_m: float
    t_s: float
    margin_m: float


class CloseLookPolicy:
    """`clearance` (or any policy reporting a `Decision.spot`) with its descent gated on close looks.

    Its counters (`looks`, `failures`, `findings`) are attributes, read by the status and tests."""

    def __init__(self, inner, config: CloseLookConfig = CloseLookConfig()) -> None:
        self.inner, self.look_config = inner, config
        self.reset()

    @property
    def name(self) -> str:
        return self.inner.name

    @property
    def config(self):
        return self.inner.config

    def map_view(self) -> dict[str, object]:
        return self.inner.map_view()

    def reset(self) -> None:
        self.inner.reset()
        self._asked: _Look | None = None  # the look in flight
        self._last_ask_s = -math.inf
        self._clear: _Look | None = None  # the newest clear look
        self._streak = 0  # clear looks in a row of the spot `_clear` looked at
        self._committed: _Look | None = None  # the spot the gate let the descent past (the last descent's)
        self._never_since_s: float | None = None  # the last descent: something inside the margin since
        self._trouble: tuple[float, float, float] | None = None  # the last descent's first finding: t, north, east
        self._verdict = ""
        self._recent: deque[tuple[float, float, bool]] = deque(maxlen=self.look_config.reject_window)
        self._spot: tuple[float, float] | None = None  # the spot of the last gated decision
        # Every look's spot and median log-odds P(never): the flight's baseline for the broad rule.
        self._medians: deque[tuple[float, float, float]] = deque(maxlen=200)
        self.looks = self.failures = self.findings = 0
        # The recent answers' lags (ask -> answer) and the recent steps, on the policy's clock, and
        # the recent decisions' delays (heatmap capture -> flown, the data clock).
        self._lags: deque[float] = deque(maxlen=5)
        self._steps: deque[float] = deque(maxlen=5)
        self._delays: deque[float] = deque(maxlen=5)
        self._last_t_s: float | None = None
        self._final = False  # in the final band (entered within final_gate_m, left final_gate_m above it)

    # ---- the step ------------------------------------------------------------------------

    def step(self, obs: Observation) -> Decision:
        if self._last_t_s is not None:
            self._steps.append(self._bounded_s(obs.t_s - self._last_t_s))
        self._last_t_s = obs.t_s
        # No number is no delay: never a longer word.
        self._delays.append(self._bounded_s(float(obs.delay_s) if validate.is_number(obs.delay_s) else 0.0))
        if obs.look is not None:
            self._take(obs.look, obs)
        if hasattr(self.inner, "handover_withheld"):
            # The inner policy hands over on its own once low enough: it may only with a fresh clear
            # look of its spot (an altitude hold sags through the hand-over altitude while waiting).
            withheld = self.inner.handover_withheld = self._handover_withheld(obs.t_s)
            if withheld and hasattr(self.inner, "withdraw_handover"):
                # ... and a hand-over declared but not yet completed (the controller confirms the
                # altitude over a few states, seconds on a noisy baro) is taken back: someone walked
                # into the margin meanwhile (harsh Dubai start 8: a walker seen leaving it came back
                # from 6.8 m to 1.8 m in the 4 s a hand-over took to confirm, unlooked at).
                self.inner.withdraw_handover(obs.t_s, obs.alt_agl_m, withheld)
        return self._gate(obs, self.inner.step(obs))

    def _handover_withheld(self, t_s: float) -> str:
        """Why the hand-over must wait ("" when a fresh clear look covers the spot and nothing is pending)."""
        if self._never_since_s is not None:
            return "close look: waiting for the never set to clear the margin"
        if self._spot is None or not self._cleared(self._spot):
            return "close look: no clear look of the spot"
        if not self._fresh(t_s):
            return "close look: no fresh clear look"
        return ""

    def _cleared(self, spot: tuple[float, float]) -> bool:
        """clear_looks clear looks in a row cover `spot`, and nothing is pending since."""
        return (self._covers(self._clear, spot) and self._never_since_s is None
                and self._streak >= self.look_config.clear_looks)

    def _fresh(self, t_s: float) -> bool:
        """The newest clear look is at most `fresh_limit_s` old (call only when it exists)."""
        return t_s - self._clear.t_s <= self.fresh_limit_s

    def _bounded_s(self, seconds: float) -> float:
        """A lag, step or delay as the freshness limit counts it: within [0, fresh_max_s]."""
        return min(max(seconds, 0.0), self.look_config.fresh_max_s)

    @property
    def fresh_limit_s(self) -> float:
        """How old the clear look behind a hand-over may be: the answers' lag, plus the delay until a
        decision is flown, plus a step and a quarter (the next decision renews the word a step
        later, flown that delay after its heatmap's stamp), medians of the last few (one long gap
        moves none of them), within [fresh_s, fresh_max_s] (CloseLookConfig).

        Without the delay the word ran out every step before its renewal was flown: in the bench
        (answers a 0.5 s step after the ask, flown 0.4 s after the heatmap's capture) a limit of
        1.125 s left the word out 0.275 s of every 0.5 s, the descent and the hand-over's
        confirmation stopping each time (harsh villas start 31 under the shift confirmed its
        hand-over for 7 s and touched down 4.3 m from its spot)."""
        cfg = self.look_config
        lag = float(np.median(self._lags)) if self._lags else 0.0
        step = float(np.median(self._steps)) if self._steps else 0.0
        delay = float(np.median(self._delays)) if self._delays else 0.0
        return min(cfg.fresh_max_s, max(cfg.fresh_s, lag + delay + 1.25 * step))

    @property
    def final_margin_m(self) -> float:
        """The margin of the looks that hand over: the person margin plus a walker's reach over the
        freshness limit (CloseLookConfig.walk_m_s), at most final_margin_max_m."""
        cfg = self.look_config
        return min(cfg.final_margin_max_m, cfg.margin_m + cfg.walk_m_s * self.fresh_limit_s)

    def _take(self, look: LookResult, obs: Observation) -> None:
        cfg, asked = self.look_config, self._asked
        self._asked = None
        if asked is None:
            return  # an answer to a look this flight no longer waits for (after a reset)
        if not look.ok:
            self.failures += 1
            self._verdict = f"look failed: {look.refusal}"
            log.warning("close look %d at %.1f m failed: %s (holding, asking again)", look.request_seq, asked.alt_m,
                        look.refusal)
            return
        self.looks += 1
        self._lags.append(self._bounded_s(obs.t_s - asked.t_s))
        _, never = look.heatmap.probabilities()
        v = verdict(never, look.heatmap.side_m, cfg, self.baseline_logit((asked.north_m, asked.east_m)),
                    margin_m=asked.margin_m)
        self._medians.append((asked.north_m, asked.east_m, v.median_logit))
        self._verdict = v.text(asked.margin_m)
        self._recent.append((asked.north_m, asked.east_m, not v.clear))
        if v.clear:
            self._streak = self._streak + 1 if self._covers(self._clear, (asked.north_m, asked.east_m)) else 1
            self._clear = asked  # its age counts from the ask: the crop is cut from the newest frame then
            if self._never_since_s is not None and self._streak >= cfg.resume_looks:
                self._never_since_s = None  # clear long enough: the descent resumes
            log.info("close look %d at %.1f m: %s", look.request_seq, asked.alt_m, self._verdict)
            return
        self.findings += 1
        self._clear, self._streak = None, 0
        first = self._never_since_s is None
        self._never_since_s = obs.t_s if first else self._never_since_s
        if self._trouble is None or math.hypot(self._trouble[1] - asked.north_m,
                                               self._trouble[2] - asked.east_m) > cfg.margin_m:
            self._trouble = (obs.t_s, asked.north_m, asked.east_m)
        waited_s = obs.t_s - self._trouble[0]
        repeated = sum(found for north, east, found in self._recent
                       if math.hypot(north - asked.north_m, east - asked.east_m) <= cfg.margin_m)
        before_gate = not self._covers(self._committed, (asked.north_m, asked.east_m))
        if (before_gate and repeated >= cfg.reject_findings) or waited_s > cfg.wait_s:
            # Found again before the gate let it past (the first looks, or a spot the map moved since),
            # or a wait that did not end: reject the spot.
            why = (f"close look: {self._verdict}" + (f", found in {repeated} of the last {len(self._recent)} looks"
                                                     if before_gate else "")
                   + (f", found again {waited_s:.0f} s after the first finding there" if waited_s else ""))
            self._reject(obs.t_s, obs.alt_agl_m, why)
        elif first:
            log.info("close look %d at %.1f m: %s: waiting", look.request_seq, asked.alt_m, self._verdict)

    def baseline_logit(self, spot: tuple[float, float]) -> float | None:
        """The median of the square medians of this flight's looks at other ground (farther than a
        square's side from `spot`), None before baseline_looks of them."""
        cfg = self.look_config
        other = [m for north, east, m in self._medians
                 if math.hypot(north - spot[0], east - spot[1]) > cfg.side_m]
        return float(np.median(other)) if len(other) >= cfg.baseline_looks else None

    def _reject(self, t_s: float, alt_m: float, why: str) -> None:
        """The spot is rejected (the inner policy blacklists it and searches on); its waits and
        findings end with it."""
        self.inner.reject_target(t_s, alt_m, why)
        self._never_since_s, self._committed, self._trouble = None, None, None

    def _covers(self, look: _Look | None, spot: tuple[float, float]) -> bool:
        """Did `look` look at this spot (moved at most spot_slack_m since)?"""
        return look is not None and math.hypot(look.north_m - spot[0], look.east_m - spot[1]) <= \
            self.look_config.spot_slack_m

    def _gate(self, obs: Observation, d: Decision) -> Decision:
        cfg, t, alt = self.look_config, obs.t_s, obs.alt_agl_m
        chosen = d.spot
        handing = d.state == "HANDOVER"  # declared, the controller confirming it: looks go on
        if d.state not in ("DESCEND", "HANDOVER") or chosen is None or alt > cfg.look_alt_m + cfg.brake_m:
            if d.state not in ("DESCEND", "HANDOVER"):
                self._never_since_s, self._spot, self._trouble = None, None, None
            self._final = False
            return dataclasses.replace(d, look_verdict=self._verdict)
        spot = self._spot = (chosen.north_m, chosen.east_m)
        here = (chosen.est_north_m, chosen.est_east_m)
        if self._never_since_s is not None and t - self._never_since_s > cfg.wait_s:
            # A wait that did not end: the deadline holds whatever the looks since were (clear ones
            # of a spot the map kept moving never make a streak).
            self._reject(t, alt, f"close look: not clear {cfg.resume_looks} looks in a row within {cfg.wait_s:g} s "
                                 f"of a finding ({self._verdict}; {t - self._never_since_s:.0f} s)")
        cleared = self._cleared(spot)
        if cleared:
            self._committed = self._clear  # the gate is open for this spot: findings now mean waiting
        fresh = cleared and self._fresh(t)
        # The final band is entered within final_gate_m of the hand-over and left only final_gate_m
        # above that: a noisy baro crosses its edge both ways, and each crossing had put the looks
        # back on look_period_s, leaving the next word older than its renewal (harsh desert start 11
        # under the shift hovered 22-26 m for 12 s, looking every second, its word running out).
        band_m = cfg.handover_alt_m + cfg.final_gate_m
        self._final = alt <= band_m or (self._final and alt <= band_m + cfg.final_gate_m)
        final = self._final
        hold, why = False, ""
        if handing:
            pass  # allowed at this step's start (`step` takes it back otherwise): the looks go on, no hold
        elif not cleared:
            hold = True
            why = ("close look: waiting for the never set to clear the margin" if self._never_since_s is not None
                   else "close look: holding until a look clears the spot")
        elif final and not fresh:
            hold, why = True, (f"close look: holding for a look from the last {self.fresh_limit_s:.1f} s before "
                               f"the hand-over")
        # Ask: before the first look, while waiting, and again every look_period_s of the last descent.
        if self._asked is not None and t - self._asked.t_s > cfg.answer_timeout_s:
            self.failures += 1
            self._verdict = f"look failed: no answer within {cfg.answer_timeout_s:g} s"
            self._asked = None
        request = None
        period = cfg.look_period_s if cleared or self._streak else cfg.retry_s
        if (final or handing) and (cleared or self._streak):
            period = cfg.final_look_period_s  # the hand-over needs a fresh look: look more often there
        if self._asked is None and t - self._last_ask_s >= period:
            fwd, right = to_body(spot[0] - here[0], spot[1] - here[1], obs.yaw_rad)
            margin = self.final_margin_m if final or handing else cfg.margin_m
            request = LookRequest((float(fwd), float(right)), 2.0 * margin, cfg.out_px)
            self._asked, self._last_ask_s = _Look(spot[0], spot[1], alt, t, margin), t
        if not hold:
            # Near the hand-over the landing word lasts as long as the clear look stays fresh: the
            # controller hands over between this policy's steps, and must not on a look gone stale.
            until = self._clear.t_s + self.fresh_limit_s if (final or handing) and self._clear is not None else None
            return dataclasses.replace(d, look_request=request, look_verdict=self._verdict, landing_until_s=until)
        vf, vr, vz = d.vel_body_frd_m_s
        # Hold the altitude (a descent is positive down); never climb here, the inner policy's abort does.
        return dataclasses.replace(d, vel_body_frd_m_s=(vf, vr, min(vz, 0.0)), landing=False,
                                   reason=f"{why} ({self._verdict or 'no look yet'})", look_request=request,
                                   look_verdict=self._verdict)
