"""Every constant of the `clearance` policy, with units, validated once.

The policy runs on true data-clock seconds under both timing presets: its timers are its own, not
the reference's, so a preset name only changes nothing but the name kept for reports.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from dovesei.shared import timing as shared_timing
from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.shared.mission import HANDOVER_ALT_M, SAFETY_RADIUS_M


@dataclass(frozen=True)
class Altitudes:
    """The altitudes one flight of the policy uses, from its start altitude (`ClearanceConfig.altitudes`)."""

    search_m: float  # the top search pass (where an abort climbs back to)
    lower_m: tuple[float, ...]  # the lower search passes, in order
    confirm_m: float  # looks at or above this feed the confirmation map
    probe_m: float  # a probe looks from here


@dataclass(frozen=True)
class ClearanceConfig:
    timing_name: str = "real"
    decision_period_s: float = 0.5  # nominal heatmap period (first cycle, bench stepping)

    # --- landing goal ---
    safety_radius_m: float = SAFETY_RADIUS_M  # the disk that must be safe at touchdown (the judge's)
    margin_m: float = 1.5  # added to the radius: position error and the map's blur
    # HANDOVER only at/below this measured altitude; the controller hands its own down (make_policy).
    handover_alt_m: float = HANDOVER_ALT_M
    search_alt_m: float | None = None  # None: the altitude of the first heatmap
    # Every altitude below (search passes, confirmation looks, probes) is written for a start at
    # ref_start_alt_m and scales with the altitude the policy starts at (observed, `altitudes`),
    # never below its floor above the hand-over. A vehicle navigating on optical flow may not
    # reach 100 m: ArduCopter's EKF3 caps the height at 0.7 x the rangefinder's range - 1 m
    # (NavEKF3_core::getHeightControlLimit: 48-69 m for common 70-100 m sensors).
    ref_start_alt_m: float = 100.0

    # --- safety map ---
    map_cells: int = 320  # map side in cells (square, centred near the vehicle)
    cell_per_alt: float = 0.01  # desired cell size = alt x this (1 m at 100 m) ...
    cell_min_m: float = 0.25  # ... within these bounds, in power-of-two steps
    cell_max_m: float = 1.0
    # P clipped to [p_clip, 1 - p_clip] before the logit: one step of the uint8 heatmap the wire may
    # carry (P x 255), so no reading is trusted beyond what the format resolves. A wider clip
    # (0.02 before) flattened the top of a recalibrated map: a lawn at logit 4 and a person on it
    # at 3 both read 3.9.
    p_clip: float = 1.0 / 255.0
    look_period_s: float = 0.5  # frames closer than this count as one look (errors correlate)
    decay_tau_s: float = 30.0  # evidence fades with this time constant
    # --- thresholds from the scene (scene) ---
    # No threshold is a fixed P: each is read off the distribution of fused log-odds over the map
    # of the search area, so a recalibrated segmenter (logit P' = a logit P + b) moves them with it.
    # The one absolute level: a scene whose best class reads below even odds (P 0.5, what the
    # segmenter itself calls "more likely unsafe") has nothing safe in it.
    scene_floor_p: float = 0.5
    # A cell counts as safe within spot_frac of the scene's contrast (its best disk less its
    # median) below the best disk, or spot_z of the map's own per-cell noise, whichever is wider (a
    # scene of one class has no contrast). CLIPSeg's tokens mix a cell's reading with its
    # neighbours' (its output is upsampled from a 22 x 22 grid): a cell taking a fifth of its
    # reading from darker ground reads a fifth of the contrast low, so this admits the ground of
    # the best class and its mixed edges up to a fifth, and nothing a fifth darker on its own.
    spot_frac: float = 0.2
    # A clearance disk holds ~600 cells (3.5 m at 0.25 m): at 4 sigma a Gaussian class loses 3e-5
    # of its cells, so 2 % of its disks lose one to noise (at 3 sigma, 55 %).
    spot_z: float = 4.0
    # However small the contrast, a cell within this share of the best disk's margin over even odds
    # counts as reading like the best: its odds of safe are at least the best's to the power 0.85
    # (best P 0.90 -> 0.87, 0.95 -> 0.92). Why a share and not the contrast: one material reads
    # a few tenths of log-odds apart from patch to patch (wet and dry sand, gravel on sand), and a
    # scene made of it has a "contrast" of that size; spot_frac of it put the threshold inside the
    # better patches' own spread, so every spot failed its re-checks lower down. Why 0.15 (0.3
    # log-odds at P 0.9): the authors' logs of the reference pipeline put the threshold that passes
    # a frame's best tenth at P 0.51 +- 0.1 over their frames, +-0.4 log-odds: CLIPSeg's reading of
    # the best ground moves by more than this share between frames, so a difference this small is
    # no evidence of a different class. Judgement on their statistic, not a fit. Measured from the
    # floor, so an offset b of the perception moves it (see scene.py).
    level_slack_frac: float = 0.15
    # From high up the tokens smear a patch into its surroundings, so a disk's promise (its mean)
    # is a mix: the gate admits disks that read within gate_frac of the contrast below the best
    # (at least 70 % of the reading from ground like the best); during the top pass a probe
    # goes only to disks within probe_now_frac (likely: 75 %).
    gate_frac: float = 0.3
    probe_now_frac: float = 0.25
    # Dips shallower than this share of the contrast between the top class and the one below are
    # the map's own ripple: a person on a lawn is a dip of a good part of that contrast.
    dip_floor_frac: float = 0.1
    # Spots and probes only once the top pass has shown the whole search area, so the levels are
    # the search area's and not the first views': in the first bench of the scene levels (seed 0,
    # realistic), 3 of 8 Dubai starts landed on its "vegetation" (lawns and trees) read as the best
    # class around the start, with open land 116-260 m away, beyond the views seen so far.
    scene_after_top_pass: bool = True
    # The levels are read again at most this often (a few ms over the whole search area): at the
    # search speed a view moves 16 m in 2 s, a fifth of its footprint.
    levels_period_s: float = 2.0
    # A look from altitude h weighs (look_ref_alt_m / h)^2 (at most look_weight_max): sharp low looks
    # outvote the smeared high ones.
    look_ref_alt_m: float = 100.0
    look_weight_max: float = 30.0
    # Small dark features (people, cars under one CLIPSeg token) deepened before fusion: closing
    # disk = dip_kernel_frac x heatmap width (about two of CLIPSeg's 22 tokens), the depth beyond
    # the scene's dip floor (dip_floor_frac of its contrast: the map's own ripple) x dip_gain, in log-odds.
    dip_kernel_frac: float = 2.0 / 22.0
    dip_gain: float = 2.0
    looks_min: float = 2.0  # evidence (looks) a cell needs to count as known
    looks_full: float = 6.0  # confidence = 1 - exp(-looks / looks_full)

    # --- ego-motion ---
    reg_size_px: int = 128  # registration image side
    reg_min_response: float = 0.3  # phase-correlation peak quality to accept a shift ...
    reg_full_response: float = 0.7  # ... to trust it fully and learn the velocity bias from it
    reg_min_std: float = 0.03  # minimum heatmap texture (std of P) to try registering
    reg_min_eigen_ratio: float = 0.2  # a direction is constrained when its texture is this share of the best
    reg_gate_m: float = 2.0  # innovation gate: base, plus reg_gate_frac x footprint width, plus
    reg_gate_frac: float = 0.05  # reg_gate_m_s x the time since the last accepted shift
    reg_gate_m_s: float = 1.0
    reg_pos_gain: float = 0.6  # share of an accepted innovation applied to the position
    static_tau_s: float = 10.0  # learning time of the image-fixed pattern (while moving)
    bias_tau_s: float = 6.0  # velocity-bias estimator time constant
    bias_max_m_s: float = 3.0
    cmd_weight: float = 0.2  # blend of the commanded velocity into the prediction
    key_shift_frac: float = 0.2  # new keyframe beyond this share of the image, or ...
    key_scale_ratio: float = 1.25  # ... this altitude ratio
    dt_cap_s: float = 2.0  # no single step integrates more than this
    # The estimate's own error bound grows by drift_frac of every metre it dead-reckons or chains
    # through keyframes (the chain's error measured under the simulated CLIPSeg on the suite's
    # Dubai world: ~2 % of the distance flown) plus drift_m_s per second (a velocity estimate's
    # bias the registration has not learnt yet).
    drift_frac: float = 0.02
    drift_m_s: float = 0.02
    # Anchors: keyframes kept with the uncertainty they were taken with; a view within
    # anchor_reach_frac x its footprint of one, at a scale ratio up to anchor_scale_ratio, is
    # registered against it when that cuts the uncertainty by anchor_gain_m or more.
    anchor_reach_frac: float = 0.25
    anchor_spacing_frac: float = 0.15
    anchor_scale_ratio: float = 1.8
    anchor_min_response: float = 0.4
    anchor_gate_frac: float = 0.2  # an anchor's innovation gate: reg_gate_m + this x footprint + 2 x uncertainty
    anchor_gain_m: float = 2.0
    anchor_max: int = 600
    # The spot's own keyframe: from the look that chose (or re-checked) the target, every heatmap
    # is registered against it, so the target stays on the ground that was checked while dead
    # reckoning drifts. Phase correlation normalises the spectrum, so low-contrast ground that
    # is consistent from frame to frame still gives a clear peak: the peak (>= spot_min_response)
    # and an innovation gate (reg_gate_m + reg_gate_frac x footprint + spot_drift_m_s x the time
    # since the last fix) decide, not the texture's absolute contrast. spot_drift_m_s is what an
    # estimate without GNSS may be off by per second (a flow EKF's velocity bias plus the wind it
    # cannot see: ~1-2 m/s, the measured drift). The keyframe is renewed from a fixed
    # look once the altitude changed by spot_renew_ratio.
    spot_min_response: float = 0.4
    spot_drift_m_s: float = 2.0
    spot_renew_ratio: float = 1.3
    # Descent only while the spot was fixed (or re-checked) within spot_trust_s; past it, the
    # vehicle holds its altitude and, after recheck_frames fresh looks, re-checks the footprint
    # below (the full clearance, at the vehicle's estimated position, within refine_radius_m of
    # the target) and takes that as the new spot with a new keyframe: it never descends on a
    # dead-reckoned guess of where the checked ground went.
    spot_trust_s: float = 0.75
    recheck_frames: int = 1

    # --- search ---
    # The search stays within this of the start. On the suite's tuning starts (seed 1000, 50 per
    # world) ground with 3.5 m of true clearance lay within 140 m of 278 of 300, within 240 m of
    # 292 and within 290 m of 297 (the misses are Dubai's, where 6 % of the map is safe). Bench
    # starts for it need `--start-margin-m` >= radius + drift (the bench's default with clearance).
    search_radius_m: float = 300.0
    # A fence on every command keeps the dead-reckoned position inside search radius - fence margin:
    # the margin is what drift of the estimate (and the lagging vehicle's overshoot) may add, so the
    # TRUE track stays inside the radius. fence_gain_per_s is the largest outward speed per metre
    # left to the fence (inside, the speed falls to zero at it; beyond, it pulls back in).
    fence_margin_m: float = 10.0
    fence_gain_per_s: float = 0.5
    # Pattern spacing = this x footprint width at search altitude, at most search_spacing_radius_frac
    # x the radius (so a small radius still flies a pattern, not just a hover over the start).
    search_spacing_frac: float = 0.6
    search_spacing_radius_frac: float = 0.67
    search_speed_m_s: float = 8.0
    # The controller trusting no velocity this long (the camera over calm water, GNSS lost) marks
    # where it happened: search waypoints past that point, the way the vehicle was going, less
    # blind_margin_m, are skipped (the loss is noticed some way out over the featureless ground).
    blind_after_s: float = 2.0
    blind_steady_s: float = 5.0  # ... when it ended a trusted stretch this long (not a flicker at the edge)
    blind_margin_m: float = 20.0
    pattern_repeats: int = 2  # passes at the lowest search level
    # Later passes fly lower (fractions of the top search altitude, never below hand-over + 15 m):
    # at 100 m CLIPSeg's token grid smears anything under ~7 m, at 40 m under ~2.7 m. A pass
    # within 5 m of the one above it is not flown (from 40 m only the top level is).
    lower_search_fracs: tuple[float, ...] = (0.6, 0.4)

    # --- confirmation from high up ---
    # CLIPSeg's misreadings persist on the same ground at one scale and change with scale (the
    # simulated one anchors them in the world and lets them drift with log2 altitude), so looks
    # an octave apart err nearly independently. The looks taken at or above confirm_alt_m (scaled
    # with the start, and at least confirm_above_probe_m above the probe altitude, so a probe's own
    # looks never confirm what it found; at most the search altitude) also go to a second map covering the whole
    # search area (1 m cells, never decayed), and a spot is taken only where that map's promise
    # (the log-odds mean over the clearance disk) passes the gate. On tuning seeds
    # under harsh, probes chaining at 35 m over Dubai's lawn-and-tree "vegetation" landed on it
    # twice in 204 episodes (fused P 0.85-0.88 from 35 m down to 20 m); with the gate never.
    # The gate's level is the scene's (gate_frac); confirm False turns the gate off.
    confirm_alt_m: float = 55.0  # the 60 m search pass counts
    confirm_above_probe_m: float = 5.0
    confirm: bool = True

    # --- probes: a closer look at promising ground ---
    # From 100 m CLIPSeg's tokens (6.7 m) smear a lawn a few tokens wide into its surroundings:
    # ground that passes the spot test from 35 m reads a few tenths lower. While searching, an
    # area within probe_reach_m whose promise from high up passes the gate (the gate would refuse
    # a spot in anything less) is flown to and looked at from
    # probe_alt_m (scaled with the start, at least hand-over + 10 m) for probe_frames heatmaps; if no spot shows, it is
    # remembered as probed (nothing within probe_skip_m is probed again) and the search goes on.
    # Once the top pass is flown, likely ground (probe_now_frac) anywhere in the search area is
    # probed first, then admissible ground within probe_reach_m, then anywhere (the lower passes
    # stay near the start).
    # During the first, top pass only likely areas (probe_now_frac) are probed; the rest wait
    # until that pass has shown the whole area (on Dubai the first 12 probes once went to
    # vegetation around the start while a 14 m patch of open land 174 m away was never looked at).
    probe_alt_m: float = 35.0
    probe_alt_tol_m: float = 3.0  # "at the probe altitude" within this
    probe_descend_frac: float = 0.5  # descend once the area is within this share of the footprint width
    probe_frames: int = 4
    probe_reach_m: float = 120.0
    probe_skip_m: float = 20.0
    probe_dist_m: float = 400.0  # ranking: 0.1 of promise is worth 40 m of extra flight
    probe_timeout_s: float = 60.0  # the look's own time; the flight there adds distance / search_speed_m_s
    probe_max: int = 16  # probes per search (each costs ~10-60 s)

    # --- approach / descent ---
    approach_gain_per_s: float = 0.5  # lateral velocity = gain x error (capped)
    max_speed_m_s: float = 6.0
    lock_in_m: float = 1.5  # start descending within this (plus lock_alt_frac x altitude) ...
    lock_out_m: float = 3.0  # ... stop descending beyond this (hysteresis)
    lock_alt_frac: float = 0.02
    # Within final_band_m of the hand-over altitude the descent goes on only within lock_in (no
    # hysteresis): the hand-over is the vehicle over the checked ground. With the lock_out
    # hysteresis down to the hand-over, a re-check at 21 m that moved the target 2.4 m handed
    # over 3.1 m from it (tuning seed 1, Dubai, realistic vehicle: touchdown error 3.3 m).
    final_band_m: float = 5.0
    # The hand-over point's own disk must lie inside ground the map clears, with this to spare:
    # the map's clearance where the vehicle is (not only at the spot) >= safety radius + this.
    # Centred within lock_in (1.9 m at 20 m) over a spot cleared to just the required 3.5 m, the
    # vehicle's disk reached 0.4 m past the cleared ground (realistic downtown start 14 of 34,
    # seed 0: 11 % of the disk on a sidewalk, touchdown error 2.4 m). Half of margin_m: the rest
    # of the margin covers the map's blur, which the map's own clearance already holds.
    handover_margin_m: float = 0.75
    switch_gain: float = 0.3  # a new spot must score this much better to replace the target
    refine_radius_m: float = 4.0  # a target that fails its re-check moves within this, only for clearance
    descent_gain_per_s: float = 0.08  # descent speed = gain x height above hand-over + min
    descent_min_m_s: float = 1.0
    descent_max_m_s: float = 4.0
    climb_speed_m_s: float = 3.0
    fail_frames: int = 3  # consecutive failed re-checks that reject the target
    recheck_hysteresis: float = 0.85  # a locked target fails only below this x the required clearance

    # --- timeouts and limits ---
    warmup_frames: int = 3
    warmup_timeout_s: float = 10.0
    approach_timeout_s: float = 90.0
    descend_timeout_s: float = 180.0
    abort_timeout_s: float = 60.0
    gap_s: float = 1.5  # no heatmap for this long = perception gap: hold, map frozen
    gap_recover_frames: int = 3  # fresh heatmaps needed before leaving GAP_HOLD
    gap_hold_timeout_s: float = 30.0  # still blind after this: climb back (ABORT)
    # Aborts before "no safe spot found" (each blacklists its spot and costs ~30 s of climbing;
    # under harsh perception 4 ended searches with 570 s of their 900 s left).
    max_aborts: int = 8
    no_spot_after_s: float = 900.0  # searching this long: hold and report "no safe spot found"
    hold_gain_per_s: float = 0.3  # NO_SPOT holds its point by vision: speed = gain x error ...
    hold_speed_max_m_s: float = 2.0  # ... at most this

    def __post_init__(self) -> None:
        positive = (
            "decision_period_s", "safety_radius_m", "look_ref_alt_m", "look_weight_max", "handover_alt_m", "cell_per_alt", "cell_min_m", "cell_max_m",
            "look_period_s", "decay_tau_s", "looks_min", "looks_full", "reg_gate_m", "static_tau_s", "bias_tau_s",
            "key_scale_ratio", "dt_cap_s", "search_radius_m", "search_spacing_frac", "search_spacing_radius_frac",
            "search_speed_m_s", "blind_after_s", "blind_steady_s", "fence_gain_per_s", "anchor_scale_ratio", "anchor_reach_frac", "anchor_spacing_frac",
            "approach_gain_per_s", "max_speed_m_s", "lock_in_m", "lock_out_m", "probe_alt_m", "probe_reach_m", "confirm_alt_m",
            "ref_start_alt_m", "confirm_above_probe_m", "spot_drift_m_s", "spot_trust_s",
            "probe_skip_m", "probe_dist_m", "probe_timeout_s", "probe_alt_tol_m",
            "refine_radius_m", "descent_gain_per_s", "descent_min_m_s", "descent_max_m_s", "climb_speed_m_s",
            "warmup_timeout_s", "approach_timeout_s", "descend_timeout_s", "abort_timeout_s", "gap_s",
            "gap_hold_timeout_s", "no_spot_after_s", "hold_gain_per_s", "hold_speed_max_m_s", "levels_period_s",
        )
        for name in positive:
            validate.positive(f"ClearanceConfig.{name}", getattr(self, name))
        for name in ("blind_margin_m", "final_band_m", "handover_margin_m", "drift_frac", "drift_m_s", "anchor_gain_m", "margin_m", "dip_gain", "fence_margin_m", "reg_gate_frac", "reg_gate_m_s", "bias_max_m_s", "switch_gain"):
            validate.non_negative(f"ClearanceConfig.{name}", getattr(self, name))
        for name in ("spot_min_response", "probe_descend_frac", "anchor_min_response", "anchor_gate_frac", "reg_min_response", "reg_full_response", "reg_min_std", "reg_min_eigen_ratio", "reg_pos_gain", "cmd_weight",
                     "key_shift_frac", "recheck_hysteresis", "dip_kernel_frac", "gate_frac", "probe_now_frac",
                     "dip_floor_frac", "spot_frac", "level_slack_frac"):
            validate.in_range(f"ClearanceConfig.{name}", getattr(self, name), 0.0, 1.0)
        for name in ("p_clip", "scene_floor_p"):
            validate.in_range(f"ClearanceConfig.{name}", getattr(self, name), 1e-6, 1.0 - 1e-6)
        validate.non_negative("ClearanceConfig.spot_z", self.spot_z)
        for name in ("confirm", "scene_after_top_pass"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"ClearanceConfig.{name} must be true or false, got {getattr(self, name)!r}")
        for frac in self.lower_search_fracs:
            validate.in_range("ClearanceConfig.lower_search_fracs item", frac, 0.05, 1.0)
        if not self.fence_margin_m < self.search_radius_m:
            raise ConfigError(f"ClearanceConfig.fence_margin_m {self.fence_margin_m} must be below search_radius_m "
                              f"{self.search_radius_m}")
        if not self.spot_renew_ratio > 1.0:
            raise ConfigError(f"ClearanceConfig.spot_renew_ratio must be > 1, got {self.spot_renew_ratio!r}")
        if self.cell_min_m > self.cell_max_m:
            raise ConfigError(f"ClearanceConfig.cell_min_m {self.cell_min_m} exceeds cell_max_m {self.cell_max_m}")
        if self.lock_out_m < self.lock_in_m:
            raise ConfigError(f"ClearanceConfig.lock_out_m {self.lock_out_m} must be >= lock_in_m {self.lock_in_m}")
        for name in ("recheck_frames", "map_cells", "reg_size_px", "pattern_repeats", "fail_frames", "warmup_frames",
                     "gap_recover_frames", "max_aborts", "anchor_max", "probe_frames"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"ClearanceConfig.{name} must be an integer >= 1, got {value!r}")
        if self.map_cells < 32 or self.reg_size_px < 16:
            raise ConfigError("ClearanceConfig: map_cells must be >= 32 and reg_size_px >= 16")
        if isinstance(self.probe_max, bool) or not isinstance(self.probe_max, int) or self.probe_max < 0:
            raise ConfigError(f"ClearanceConfig.probe_max must be an integer >= 0, got {self.probe_max!r}")
        if self.probe_now_frac > self.gate_frac:
            raise ConfigError(f"ClearanceConfig.probe_now_frac {self.probe_now_frac} must be <= gate_frac "
                              f"{self.gate_frac}: a likely area is one the gate admits")
        if self.search_alt_m is not None and not self.search_alt_m > self.handover_alt_m:
            raise ConfigError(f"ClearanceConfig.search_alt_m {self.search_alt_m!r} must be above the hand-over "
                              f"altitude {self.handover_alt_m} m")

    def altitudes(self, start_alt_m: float) -> Altitudes:
        """The policy's altitudes for a start at `start_alt_m` (the altitude it first observes):
        the configured ones x start / ref_start_alt_m, each kept above its floor."""
        top = float(self.search_alt_m if self.search_alt_m is not None else max(start_alt_m, self.handover_alt_m + 10.0))
        scale = top / self.ref_start_alt_m
        floor = self.handover_alt_m + 15.0
        lower: tuple[float, ...] = ()
        for frac in self.lower_search_fracs:
            alt = max(frac * top, floor)
            if alt < (lower[-1] if lower else top) - 5.0:  # a pass within 5 m of the one above adds nothing
                lower += (alt,)
        probe = max(self.probe_alt_m * scale, self.handover_alt_m + 10.0)
        confirm = min(max(self.confirm_alt_m * scale, probe + self.confirm_above_probe_m), top)
        return Altitudes(search_m=top, lower_m=lower, confirm_m=confirm, probe_m=probe)

    @property
    def scene_floor_logit(self) -> float:
        """The floor in log-odds (0 for P 0.5)."""
        return math.log(self.scene_floor_p / (1.0 - self.scene_floor_p))

    @property
    def fence_m(self) -> float:
        """The dead-reckoned position never goes farther than this from the start."""
        return self.search_radius_m - self.fence_margin_m

    @property
    def required_clearance_m(self) -> float:
        """Metric clearance a spot needs: every cell within this radius is known and safe."""
        return self.safety_radius_m + self.margin_m

    def limited_to(self, horizontal_m_s: float, up_m_s: float, down_m_s: float) -> ClearanceConfig:
        """This config with every speed it commands within the vehicle's limits (ArduCopter's
        WPNAV_SPEED, WPNAV_SPEED_UP, WPNAV_SPEED_DN by default), so it never asks more than is flown."""
        for name, value in (("horizontal", horizontal_m_s), ("up", up_m_s), ("down", down_m_s)):
            validate.positive(f"vehicle speed limit {name} (m/s)", value)
        return self.replace(
            search_speed_m_s=min(self.search_speed_m_s, horizontal_m_s),
            max_speed_m_s=min(self.max_speed_m_s, horizontal_m_s),
            hold_speed_max_m_s=min(self.hold_speed_max_m_s, horizontal_m_s),
            climb_speed_m_s=min(self.climb_speed_m_s, up_m_s),
            descent_max_m_s=min(self.descent_max_m_s, down_m_s),
            descent_min_m_s=min(self.descent_min_m_s, down_m_s))

    def replace(self, **changes: object) -> ClearanceConfig:
        try:
            return dataclasses.replace(self, **changes)
        except TypeError as exc:
            raise ConfigError(f"ClearanceConfig: {exc}") from None


def clearance_preset(name: str) -> ClearanceConfig:
    """The config for a timing preset: only the nominal decision period differs."""
    t = shared_timing.timing(name)
    return ClearanceConfig(timing_name=t.name, decision_period_s=t.decision_period_s)
