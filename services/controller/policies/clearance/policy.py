"""The `clearance` policy: our own lander, built to fix what REFERENCE.md lists as the paper's quirks.

Per heatmap, data flows one way:

    Observation (P(safe), camera model, altitude + attitude at capture, velocity estimate and its
                 displacement since the previous capture, time)
      -> EgoMotion   predict with the estimate's displacement (+ learnt bias), correct by
                     registering the heatmap against a keyframe and against anchors (motion)
      -> GroundMap   decay, follow the vehicle and the altitude's resolution, fuse the heatmap
                     in log-odds at the estimated pose                         (ground_map)
      -> high map    the looks from high up only, over the whole search area, never decayed:
                     its promise (the log-odds mean over the clearance disk) confirms spots and
                     plans probes                                              (ground_map)
      -> levels      every threshold read off the high map's distribution of log-odds: the
                     scene: its best disk, its median, its noise; never a fixed P (scene)
      -> spots       clearance = metric distance to the nearest unsafe/unknown cell; the best
                     confirmed spot, the current target re-checked, the most promising area
                     worth a probe                                             (ground_map)
      -> machine     one pure step: phase, target, reasons, velocity          (machine)
      -> Decision    body FRD velocity, state, target pixel, reason, spot (SpotReport: where,
                     clearance, confidence) and report (ClearanceReport: position estimate,
                     bias, scene levels, registration, probes; report.py)

Compared with `dovesei`: memory lives on the ground, not in the image (the drone's own motion is
compensated); a spot's real size is checked in metres and confirmed by looks from another scale;
the search is bounded, looks closer at promising ground and remembers rejected and probed areas;
an abort climbs back; a perception gap holds with the map frozen and never turns into a landing;
dt is capped; time is true data-clock seconds under every timing preset.
Never reads a true position: the Observation has none.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from dovesei.controller.policies.base import (Confirmation, Decision, Observation, PolicyInputError, SpotReport,
                                              checked_prob_safe, resolve_config)
from dovesei.controller.policies.clearance.config import Altitudes, ClearanceConfig, clearance_preset
from dovesei.controller.policies.clearance.machine import (
    TERMINAL, Inputs, Memory, Phase, committed, reject_target, search_route, step, toward, withdraw_handover,
)
from dovesei.controller.policies.clearance.ground_map import (GroundMap, Promise, clearance_at, emphasise_dips,
                                                      find_candidate, find_spot, footprint_width_m, logit,
                                                      look_weight, promise)
from dovesei.controller.policies.clearance.scene import SceneLevels, fine_noise, known_mean, map_levels, sigmoid
from dovesei.shared.frames import to_body, to_ne
from dovesei.controller.geofence import cap_outward
from dovesei.controller.policies.clearance.motion import EgoMotion, MotionStep, tilt_offset_ne
from dovesei.controller.policies.clearance.report import (ClearanceReport, ProbeReport, RegistrationReport,
                                                          SceneReport)

log = logging.getLogger(__name__)


def _resolve(config: ClearanceConfig | str | None) -> ClearanceConfig:
    return resolve_config(config, ClearanceConfig, clearance_preset, "clearance")


def fence(vel_body_frd_m_s: tuple[float, float, float], north_m: float, east_m: float, yaw_rad: float,
          cfg: ClearanceConfig, fence_m: float | None = None) -> tuple[tuple[float, float, float], bool]:
    """The command with its outward (away from the start) horizontal speed capped so the
    dead-reckoned position never passes the fence (`fence_m`, by default the config's search
    radius - fence margin); True when capped.

    The cap is fence_gain x the distance left to the fence, so the vehicle slows down as it nears
    the fence and, beyond it, is pulled back in; inward and tangential motion are untouched.
    """
    fwd, right, down = vel_body_frd_m_s
    (vn, ve), capped = cap_outward(north_m, east_m, to_ne(fwd, right, yaw_rad),
                                   cfg.fence_m if fence_m is None else fence_m, cfg.fence_gain_per_s)
    if not capped:
        return vel_body_frd_m_s, False
    f, rr = to_body(vn, ve, yaw_rad)
    return (f, rr, down), True


class ClearancePolicy:
    """Ground map + metric clearance + bounded search; `step` once per controller tick."""

    def __init__(self, config: ClearanceConfig | str | None = None, *, name: str = "clearance") -> None:
        self.name = name
        self.config = _resolve(config)
        self.reset()

    def reset(self) -> None:
        self.map = GroundMap(self.config)
        # The looks from high up only: the confirmation gate and where probes are planned from.
        # Made on the first observation, sized to the whole search area (it needs the camera's view).
        self.high: GroundMap | None = None
        self.motion = EgoMotion(self.config)
        self.memory: Memory | None = None
        self._last_t_s: float | None = None  # last heatmap
        # Set from outside before a step (the close look's gate): why the hand-over must wait ("": it need not).
        self.handover_withheld = ""
        self._search_alt_m: float | None = None
        self._alts: Altitudes | None = None  # this flight's altitudes, from the start altitude
        self._route: tuple[tuple[float, float, float], ...] = ()
        self._top_pass_end = 0  # waypoints of the route's first (top) pass
        self._hold_ne: tuple[float, float] | None = None  # NO_SPOT's or HANDOVER's hold point, in the local frame
        self._passes = 0
        self._cmd: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._last_motion: MotionStep | None = None
        self._confirmed: Confirmation | None = None  # the look that last confirmed the target
        self._levels: SceneLevels | None = None  # the scene's thresholds, from the high map
        self._spot_t = math.inf  # the spot threshold on the map now (log-odds; nothing safe at first)
        self._levels_t_s = -math.inf  # when the levels were last read
        self._levels_stale = False  # the high map got new looks since
        self._high_looks = 0  # looks fused into the high map so far
        self._whole: tuple[int, Promise] | None = None  # the whole high map's promise, at that many looks
        self._map_noise = 0.0  # the working map's per-cell scatter (log-odds), read with the levels
        self._scene_seen = False  # the top pass has shown the search area (spots and probes allowed)
        self._decision = Decision((0.0, 0.0, 0.0), 0.0, Phase.WARMUP.value, None, 0.0, None, "starting")
        # Where the controller stopped trusting the vehicle's velocity (Inputs.blind): the marks, and
        # the loss under way (when it began, where the vehicle was and where it was going).
        self._blind: list[tuple[float, float, float, float]] = []
        # The loss's goal is None when it marks nothing (any more).
        self._loss: tuple[float, float, float, tuple[float, float] | None] | None = None
        self._trusted_since_s: float | None = None  # the current trusted stretch's start

    def fence_m(self) -> float:
        """The fence for the estimate now: the search radius less the larger of the fence margin
        and the estimate's own uncertainty, so the true track keeps inside the radius while the
        error stays within that bound (it shrinks as the estimate drifts, and widens again
        after an anchor fix)."""
        cfg = self.config
        return max(cfg.search_radius_m - max(cfg.fence_margin_m, self.motion.uncertainty_m), 0.0)

    @property
    def state(self) -> Phase:
        return self.memory.phase if self.memory is not None else Phase.WARMUP

    def _plan(self, hfov_rad: float) -> tuple[tuple[tuple[float, float, float], ...], int, int]:
        """The search route: a pass at the top search altitude, one at each lower level, the
        lowest flown `pattern_repeats` times. Each pass is an expanding square spaced by its own
        footprint; lower passes cover a radius shrinking as sqrt(altitude / top), so a pass
        takes about as long as the first (radius^2 / spacing is constant) and they stay near the
        start, where the high pass saw most. Returns the route, its number of passes and the
        number of waypoints of the first pass."""
        cfg = self.config
        assert self._alts is not None
        top, lower = self._alts.search_m, self._alts.lower_m
        levels = (top, *lower, *(lower[-1:] if lower else (top,)) * (cfg.pattern_repeats - 1))
        outer = cfg.fence_m - 5.0  # the corners stay a little inside the fence (the vehicle overshoots)
        passes = []
        for alt in levels:
            radius = outer * math.sqrt(alt / top)
            spacing = min(cfg.search_spacing_frac * footprint_width_m(alt, hfov_rad),
                          cfg.search_spacing_radius_frac * radius)
            passes.append((alt, spacing, radius))
        return search_route(tuple(passes)), len(passes), len(search_route(tuple(passes[:1])))

    # ---- the step ----------------------------------------------------------------------

    def step(self, obs: Observation) -> Decision:
        prob = self._validate(obs)
        cfg = self.config
        if self.memory is None:
            self.memory = Memory(since_s=obs.t_s, start_s=obs.t_s)
            self._alts = cfg.altitudes(float(obs.alt_agl_m))
            self._search_alt_m = self._alts.search_m
            log.info("clearance: starting at %.1f m: search passes %s m, confirmation looks from %.0f m, probes "
                     "from %.0f m", obs.alt_agl_m, "/".join(f"{a:.0f}" for a in (self._alts.search_m, *self._alts.lower_m)),
                     self._alts.confirm_m, self._alts.probe_m)
            self._route, self._passes, self._top_pass_end = self._plan(obs.hfov_rad)
            # At the coarsest cell, centred on the start, covering every view the search can
            # take from its top altitude; never decayed and never resampled, so an area seen
            # from high up is remembered wherever the search goes (a map that followed the
            # vehicle forgot it once it flew on, and the lower passes then found no spot at all).
            reach_m = cfg.search_radius_m + footprint_width_m(self._search_alt_m, obs.hfov_rad) / 2.0
            # An even side, as the map's: the two grids' cell centres coincide at the coarsest
            # cell (an odd side put them half a cell apart, and the gate's nearest-cell lookup
            # then shifted it by a whole cell at ties).
            self.high = GroundMap(cfg, cells=2 * int(math.ceil(reach_m / cfg.cell_max_m)) + 2)
        phase = self.memory.phase
        if prob is None:
            if phase in TERMINAL:
                return self._decision
            # No new heatmap: nothing moves on the map; only a perception gap changes the decision.
            if (self._last_t_s is not None and obs.t_s - self._last_t_s > cfg.gap_s
                    and phase is not Phase.GAP_HOLD):
                return self._decide(obs, fresh=False, gap=True, best=None, check=None, clearance=None,
                                    fence_m=self.fence_m())
            return self._decision
        dt_s = cfg.decision_period_s if self._last_t_s is None else obs.t_s - self._last_t_s
        if self._last_t_s is not None and dt_s == 0.0:
            return self._decision  # the same capture time twice: nothing new
        self._last_t_s = obs.t_s
        gap = dt_s > cfg.gap_s
        dt_c = min(dt_s, cfg.dt_cap_s)

        # Ego-motion: predict with the estimate's own displacement between the capture stamps when
        # the controller integrated it, else with the estimate blended with what was commanded;
        # then register.
        cmd = obs.cmd_vel_body_frd_m_s if obs.cmd_vel_body_frd_m_s is not None else self._cmd
        est = obs.vel_est_body_frd_m_s if obs.vel_est_body_frd_m_s is not None else cmd
        w = cfg.cmd_weight
        vel = tuple((1.0 - w) * e + w * c for e, c in zip(est, cmd))
        self.motion.predict(dt_c, vel, obs.yaw_rad, obs.odom_delta_ne_m)  # type: ignore[arg-type]
        motion = self.motion.correct(prob, dt_s, obs.alt_agl_m, obs.hfov_rad, obs.yaw_rad, obs.roll_rad,
                                     obs.pitch_rad)
        self._last_motion = motion
        pn, pe = motion.north_m, motion.east_m
        self._note_velocity(obs, pn, pe)
        if phase in TERMINAL:
            # The map decides nothing any more and is not worked on (a held vehicle would spend a
            # core on it for as long as it hovers); the ego-motion still runs, for the hold: over
            # the point where the search gave up, or where the hand-over was declared until the
            # short-range sensors have it.
            return self._hold(obs, pn, pe)

        # Map: frozen across a gap (no decay); after one, only registered frames are fused.
        assert self.high is not None  # made with the memory, on the first observation
        if not gap:
            self.map.decay(dt_c)
        self.map.follow(obs.alt_agl_m, pn, pe)
        blind = gap or self.memory.phase is Phase.GAP_HOLD
        if not blind or motion.registered:
            tn, te = tilt_offset_ne(obs.alt_agl_m, obs.roll_rad, obs.pitch_rad, obs.yaw_rad)
            # Dips are deepened in log-odds, beyond a floor from the scene's contrast (none before
            # the scene is known: every dip counts).
            dip_floor = self._levels.dip_floor_logit if self._levels is not None else 0.0
            seen = emphasise_dips(logit(prob, cfg.p_clip), int(round(cfg.dip_kernel_frac * prob.shape[1])),
                                  cfg.dip_gain, dip_floor, clip=None)
            weight = min(1.0, dt_c / cfg.look_period_s) * look_weight(obs.alt_agl_m, cfg)
            self.map.fuse_logit(seen, obs.alt_agl_m, obs.hfov_rad, obs.yaw_rad, pn + tn, pe + te, weight=weight)
            if obs.alt_agl_m >= self._alts.confirm_m:
                self.high.fuse_logit(seen, obs.alt_agl_m, obs.hfov_rad, obs.yaw_rad, pn + tn, pe + te, weight=weight)
                self._levels_stale = True  # new looks from high up: the scene's levels are read again
                self._high_looks += 1
        # Read at most every levels_period_s: they move only as new ground comes into view (or the
        # working map changes resolution).
        if self._levels is None or obs.t_s - self._levels_t_s >= cfg.levels_period_s:
            if self._levels is None or self._levels_stale:
                self._levels, self._levels_stale = map_levels(self.high, cfg), False
            # The working map's own per-cell noise (it changes with altitude and resolution), every
            # other cell: as slow-moving as the levels.
            self._map_noise, self._levels_t_s = fine_noise(*known_mean(self.map, cfg, stride=2)), obs.t_s
        levels = self._levels
        self._spot_t = levels.spot_for(self._map_noise, cfg)
        clearance = self.map.clearance_m(self._spot_t)
        # What looked promising from high up, around the vehicle: as far as the map reaches (the
        # gate) and as far as a probe may go.
        mem = self.memory
        plan_probe = mem.phase is Phase.SEARCH and len(mem.probed) < cfg.probe_max
        high = None
        if cfg.confirm or plan_probe:
            half_m = max(self.map.n * self.map.cell_m / 2.0, cfg.probe_reach_m if plan_probe else 0.0)
            high = promise(self.high, cfg, pn, pe, half_m)
        # A spot only where the area looked promising from high up too (those looks err apart
        # from the low ones).
        gate = None
        if cfg.confirm:
            gate = self.high.mask_onto(high.at_least(levels.gate_logit), self.map, high.r0, high.c0)
        # A spot rejected high up is looked at again once well below that altitude (finer detail
        # may show it is fine, or why not); one rejected low down stays rejected.
        blacklist = tuple((n, e) for n, e, alt in self.memory.blacklist if obs.alt_agl_m >= 0.8 * alt)
        fence_m = self.fence_m()
        # The levels are the scene's only once the top pass has shown the search area: before,
        # the best ground in view may be a second-rate class that better ground further out outranks.
        if not self._scene_seen and (not cfg.scene_after_top_pass or mem.waypoint >= self._top_pass_end):
            self._scene_seen = True
            log.info("clearance: scene seen at t=%.1f s: best disk at log-odds %.2f, median %.2f", obs.t_s,
                     levels.best_logit, levels.typical_logit)
        best = None if not self._scene_seen else find_spot(
            self.map, clearance, cfg, north_m=pn, east_m=pe, blacklist=blacklist, fence_m=fence_m, gate=gate)
        # A closer look is planned only while searching with nothing good enough in view, at what
        # looked promising from high up.
        candidate = None
        if best is None and plan_probe and self._scene_seen:
            skip = mem.probed + tuple((n, e) for n, e, _ in mem.blacklist)
            # Where to look for a candidate, in order (the first that finds one wins). Once the top
            # pass is flown, likely ground (probe_now_frac of the scene's contrast below its best)
            # anywhere in the search area goes first: nearer ground that reads lower is likely a
            # second-rate class. Looked for within probe_reach_m first, admissible (gate-level)
            # areas won on distance: realistic Dubai starts 16 and 24 of 34 probed lawn-and-tree
            # "vegetation" about 100 m away (start 16: 0.3 log-odds under the best disk) and landed
            # on it, while the best disk, 270-280 m from the start, was open land; now both land
            # there. Last, with nothing within reach, promising ground anywhere is worth the flight:
            # the lower passes stay near the start (their radius shrinks with the altitude), so the
            # best ground the top pass saw, out near the fence, was never looked at (realistic
            # downtown start 28 of 34: its only ground above the gate lay 253 m from the start, and
            # the search held NO_SPOT).
            within_reach = (lambda: high, cfg.probe_reach_m, levels.probe_logit)
            tiers = ((within_reach,) if mem.waypoint < self._top_pass_end else
                     ((self._whole_promise, math.inf, levels.probe_now_logit), within_reach,
                      (self._whole_promise, math.inf, levels.probe_logit)))
            for promise_of, within_m, min_logit in tiers:
                candidate = find_candidate(self.high, promise_of(), cfg, north_m=pn, east_m=pe, skip=skip,
                                           fence_m=fence_m, within_m=within_m, min_logit=min_logit)
                if candidate is not None:
                    break
        check = recheck = None
        target = self.memory.target
        if target is not None:
            check = find_spot(self.map, clearance, cfg, north_m=pn, east_m=pe, blacklist=(),
                              near=(target.north_m, target.east_m), within_m=cfg.refine_radius_m,
                              need_m=cfg.required_clearance_m * cfg.recheck_hysteresis, fence_m=fence_m,
                              gate=gate)
            if self.memory.phase is Phase.DESCEND and not self._spot_known():
                # The footprint below, with the full clearance: what a re-check would land on.
                recheck = find_spot(self.map, clearance, cfg, north_m=pn, east_m=pe, blacklist=(), near=(pn, pe),
                                    within_m=cfg.refine_radius_m, fence_m=fence_m, gate=gate)
        likely = candidate is not None and candidate.p_safe >= sigmoid(levels.probe_now_logit)
        return self._decide(obs, fresh=True, gap=gap, best=best, check=check, clearance=clearance, fence_m=fence_m,
                            candidate=candidate, recheck=recheck, likely=likely)

    def reject_target(self, t_s: float, alt_m: float, reason: str) -> None:
        """Reject the current target for a reason the map cannot see (a close look found a person
        inside its margin): blacklisted, and the search goes on from where the vehicle is. Takes
        effect from the next step."""
        if self.memory is not None and self._moved_on(reject_target(self.memory, t_s, alt_m, reason), t_s, alt_m):
            self.motion.clear_spot()

    def withdraw_handover(self, t_s: float, alt_m: float, reason: str) -> None:
        """Take back a declared hand-over the controller has not completed yet (a close look found the
        never set inside the margin, or has no fresh clear look): the descent holds over the spot
        until released. Takes effect at once: the decision in hand stops being terminal."""
        if self.memory is None or not self._moved_on(withdraw_handover(self.memory, t_s, reason), t_s, alt_m):
            return
        self._hold_ne = None
        if self._decision is not None:
            # Until the next heatmap decides: hold, horizontally as the hand-over held.
            vf, vr, _ = self._decision.vel_body_frd_m_s
            self._decision = dataclasses.replace(self._decision, state=self.memory.phase.value, landing=False,
                                                 reason=self.memory.reason, vel_body_frd_m_s=(vf, vr, 0.0))

    def _moved_on(self, mem: Memory, t_s: float, alt_m: float) -> bool:
        """Take `mem` (a transition ordered from outside the map) as the memory, logged; False when
        it is the memory already (nothing to do)."""
        if mem is self.memory:
            return False
        log.info("clearance: %s -> %s at t=%.2f s, alt %.1f m: %s", self.memory.phase.value, mem.phase.value, t_s,
                 alt_m, mem.reason)
        self.memory = mem
        return True

    def _spot_known(self) -> bool:
        """Was the target fixed by vision (or re-checked) recently enough to descend on?"""
        return self.motion.spot_since_s <= self.config.spot_trust_s

    def _whole_promise(self) -> Promise:
        """The promise of the whole high map, made again only once it has new looks (after the top
        pass the lower passes add few, and a search with nothing in reach asks every step)."""
        assert self.high is not None
        if self._whole is None or self._whole[0] != self._high_looks:
            self._whole = (self._high_looks, promise(self.high, self.config, 0.0, 0.0,
                                                     self.high.n * self.high.cell_m / 2.0))
        return self._whole[1]

    def _hold(self, obs: Observation, pn: float, pe: float) -> Decision:
        """NO_SPOT and HANDOVER: stay over a point by vision; a new decision with only the velocity
        and the report's position changed."""
        vel, fenced, error_m = self._hold_velocity(pn, pe, obs.yaw_rad)
        self._cmd = vel
        report = self._decision.report
        if report is not None:
            report = dataclasses.replace(report, est_north_m=pn, est_east_m=pe, hold_error_m=error_m,
                                         fenced=bool(fenced))
        spot = self._decision.spot
        if spot is not None:  # seen from where the vehicle is now (a close look's crop is asked from here)
            spot = dataclasses.replace(spot, est_north_m=pn, est_east_m=pe)
        self._decision = dataclasses.replace(self._decision, vel_body_frd_m_s=tuple(float(v) for v in vel),
                                             report=report, spot=spot)
        return self._decision

    def _note_velocity(self, obs: Observation, pn: float, pe: float) -> None:
        """Mark where the camera stopped measuring the vehicle's velocity for `blind_after_s`: the
        ground beyond, the way the vehicle was going, gave it nothing to measure (calm water), and
        the search skips its waypoints there (`Inputs.blind`). A short loss marks nothing, nor one
        that did not end `blind_steady_s` of trusted velocity."""
        if obs.velocity_trusted:
            self._loss = None
            if self._trusted_since_s is None:
                self._trusted_since_s = obs.t_s
            return
        if self._loss is None:
            # Only a loss that ends a steady stretch says where the ground turned blind: one
            # after a flicker at the edge (on the way back, still over the water) marks nothing,
            # or the way back to land would be marked blind too (coast start 2 of 8).
            since = self._trusted_since_s
            steady = since is not None and obs.t_s - since >= self.config.blind_steady_s
            self._loss = (obs.t_s, pn, pe, self._heading_goal() if steady else None)
        self._trusted_since_s = None
        since_s, bn, be, goal = self._loss
        if goal is None or obs.t_s - since_s < self.config.blind_after_s:
            return
        self._loss = (since_s, bn, be, None)  # one mark per loss
        dn, de = goal[0] - bn, goal[1] - be
        dist = math.hypot(dn, de)
        if dist < 1.0:
            return
        self._blind.append((bn, be, dn / dist, de / dist))
        log.info("clearance: no trusted velocity for %.1f s since (%.0f, %.0f) m, heading %.0f deg: search waypoints "
                 "beyond skipped", obs.t_s - since_s, bn, be, math.degrees(math.atan2(de, dn)) % 360.0)

    def _heading_goal(self) -> tuple[float, float] | None:
        """Where the vehicle was flying to: its search waypoint or its probe (None otherwise)."""
        mem = self.memory
        if mem is None:
            return None
        if mem.phase is Phase.SEARCH and mem.waypoint < len(self._route):
            return self._route[mem.waypoint][0], self._route[mem.waypoint][1]
        if mem.phase is Phase.PROBE and mem.probe is not None:
            return mem.probe.north_m, mem.probe.east_m
        return None

    def _hold_velocity(self, pn: float, pe: float, yaw_rad: float) -> tuple[tuple[float, float, float], bool, float]:
        """The command that holds the vehicle over `_hold_ne` (set on the first call to where it
        is), its fence flag and the distance to the point.

        Without GNSS a zero-velocity command is no hold: the autopilot holds its own, biased,
        velocity estimate at zero, so wind and the estimate's bias carry the vehicle away for as
        long as it waits (138 m in a 300 s hold in the wind test of test_clearance_fence; 3.4 m in
        the 2.4 s a harsh baro took to confirm a hand-over, villas start 1 of 6). The registered
        position says where it went; this steers back inside the fence at a constant altitude.
        NO_SPOT holds where the search gave up, slowly. HANDOVER holds over its spot with the
        descent's own gain, so the command does not jump where the descent left it: the learnt
        bias is never exact, and the descent held still with the rest as a standing error.
        """
        cfg = self.config
        if self._hold_ne is None:
            self._hold_ne = (pn, pe)
        dn, de = self._hold_ne[0] - pn, self._hold_ne[1] - pe
        if self.state is Phase.HANDOVER:
            f, r = toward(dn, de, cfg.approach_gain_per_s, cfg.max_speed_m_s, yaw_rad)
        else:
            f, r = toward(dn, de, cfg.hold_gain_per_s, cfg.hold_speed_max_m_s, yaw_rad)
        vel, fenced = fence((f, r, 0.0), pn, pe, yaw_rad, cfg, self.fence_m())
        return self._through_bias(vel, yaw_rad), fenced, math.hypot(dn, de)

    def _through_bias(self, vel: tuple[float, float, float], yaw_rad: float) -> tuple[float, float, float]:
        """The command that gets `vel` flown: the autopilot steers its own velocity estimate onto
        the command, and that estimate is off by the bias the registration learnt (true = estimate
        + bias), so the bias is taken off, within the fastest speed the policy commands anyway.

        Without it the position loop (gain x error) sat bias / gain from its target: harsh crowded
        start 5 of 6 commanded 3 m/s for 20 s at 32 m and truly moved a few metres back and forth,
        never within the lock, until each approach timed out after 90 s."""
        bf, br = to_body(self.motion.bias_n_m_s, self.motion.bias_e_m_s, yaw_rad)
        f, r = vel[0] - bf, vel[1] - br
        speed, cap = math.hypot(f, r), max(self.config.search_speed_m_s, self.config.max_speed_m_s)
        if speed > cap:
            f, r = f * cap / speed, r * cap / speed
        return (float(f), float(r), vel[2])

    def _decide(self, obs: Observation, *, fresh: bool, gap: bool, best, check, clearance,
                fence_m: float, candidate=None, recheck=None, likely: bool = False) -> Decision:
        cfg = self.config
        assert self.memory is not None and self._search_alt_m is not None
        pn, pe = self.motion.north_m, self.motion.east_m
        inp = Inputs(t_s=obs.t_s, alt_agl_m=float(obs.alt_agl_m), north_m=pn, east_m=pe, yaw_rad=obs.yaw_rad,
                     fresh=fresh, gap=gap, search_alt_m=self._search_alt_m, route=self._route,
                     passes=self._passes, fence_m=fence_m,
                     best=best, check=check, hfov_rad=obs.hfov_rad, candidate=candidate,
                     top_pass_end=self._top_pass_end, probe_alt_m=self._alts.probe_m,
                     spot_known=self._spot_known(), recheck=recheck, candidate_likely=likely,
                     handover_withheld=self.handover_withheld, blind=tuple(self._blind),
                     below_clearance_m=None if clearance is None else clearance_at(self.map, clearance, pn, pe))
        prev = self.memory
        mem, vel = step(prev, inp, cfg)
        fenced = False
        self.memory = mem
        if mem.phase in TERMINAL:
            # An end holds still (the operator or the short-range sensors take over), in truth: by
            # vision, over the spot of the hand-over or where the search gave up.
            if self._hold_ne is None and mem.phase is Phase.HANDOVER and mem.target is not None:
                self._hold_ne = (mem.target.north_m, mem.target.east_m)
            vel, fenced, _ = self._hold_velocity(pn, pe, obs.yaw_rad)
        else:
            vel, fenced = fence(vel, pn, pe, obs.yaw_rad, cfg, fence_m)
            vel = self._through_bias(vel, obs.yaw_rad)
        anchored = fresh and mem.target is not None and mem.anchor != prev.anchor and self.motion.set_spot()
        if mem.target is None:
            self.motion.clear_spot()
        self._cmd = vel
        if mem.phase is not prev.phase or mem.reason != prev.reason:
            log.info("clearance: %s -> %s at t=%.2f s, alt %.1f m: %s", prev.phase.value, mem.phase.value, obs.t_s,
                     obs.alt_agl_m, mem.reason)
        m = self._last_motion
        lv = self._levels
        report = ClearanceReport(
            alt_agl_m=float(obs.alt_agl_m), est_north_m=pn, est_east_m=pe,
            bias_north_m_s=self.motion.bias_n_m_s, bias_east_m_s=self.motion.bias_e_m_s,
            cell_m=self.map.cell_m, aborts=int(mem.aborts), blacklisted=len(mem.blacklist),
            required_clearance_m=cfg.required_clearance_m, waypoint=int(mem.waypoint),
            fenced=bool(fenced), fence_m=float(fence_m), uncertainty_m=self.motion.uncertainty_m,
            anchors=int(self.motion.anchors), probes=len(mem.probed),
            # The scene's levels (log-odds); a threshold nothing meets (nothing safe) reports as 99.
            scene=None if lv is None else SceneReport(
                spot_logit=float(min(self._spot_t, 99.0)), gate_logit=float(min(lv.gate_logit, 99.0)),
                best_logit=float(max(lv.best_logit, -99.0)), typical_logit=float(lv.typical_logit)),
            probe=None if mem.probe is None else ProbeReport(mem.probe.north_m, mem.probe.east_m, mem.probe.p_safe),
            registration=None if m is None else RegistrationReport(
                registered=bool(m.registered), response=float(m.response), innovation_m=float(m.innovation_m),
                anchored=bool(m.anchored), spot_fixed=bool(m.spot_fixed), spot_response=float(m.spot_response),
                spot_since_s=min(self.motion.spot_since_s, 1e6)),
        )
        target_px = None
        spot_report = None
        spot = mem.target
        if spot is not None:
            # The clearance the map gives the spot now (the target's own figure is from its last check).
            spot_report = SpotReport(
                north_m=float(spot.north_m), east_m=float(spot.east_m),
                clearance_m=float(clearance_at(self.map, clearance, spot.north_m, spot.east_m)
                                  if clearance is not None else spot.clearance_m),
                confidence=float(spot.confidence), p_safe=float(spot.p_safe),
                distance_m=float(math.hypot(spot.north_m - pn, spot.east_m - pe)),
                est_north_m=float(pn), est_east_m=float(pe))
            if obs.prob_safe is not None:
                h, w = obs.prob_safe.shape
                gsd = footprint_width_m(obs.alt_agl_m, obs.hfov_rad) / w
                tn, te = tilt_offset_ne(obs.alt_agl_m, obs.roll_rad, obs.pitch_rad, obs.yaw_rad)
                f, r = to_body(spot.north_m - pn - tn, spot.east_m - pe - te, obs.yaw_rad)
                target_px = ((h - 1) / 2.0 - f / gsd, (w - 1) / 2.0 + r / gsd)
                # The look that chose (or re-checked) the target, or one registered against its
                # keyframe whose re-check passed, confirms it at this pixel: the estimate was just
                # put back on the checked ground, so the pixel is measured, not dead-reckoned.
                seen = anchored or (fresh and check is not None and m is not None and m.spot_fixed)
                if seen and -0.5 <= target_px[0] <= h - 0.5 and -0.5 <= target_px[1] <= w - 0.5:
                    self._confirmed = Confirmation(obs.frame_seq, float(target_px[0]), float(target_px[1]))
        else:
            self._confirmed = None
        self._decision = Decision(
            vel_body_frd_m_s=(float(vel[0]), float(vel[1]), float(vel[2])), yaw_rate_rad_s=0.0,
            state=mem.phase.value, target_px=None if target_px is None else (float(target_px[0]), float(target_px[1])),
            focus_radius_px=self._required_px(obs),
            threshold=sigmoid(self._spot_t),
            reason=mem.reason, confirmed=self._confirmed, spot=spot_report, report=report,
            landing=committed(mem),
        )
        return self._decision

    def _required_px(self, obs: Observation) -> float:
        """The required clearance disk in heatmap pixels (drawn like the reference's focus circle)."""
        if obs.prob_safe is None:
            return self._decision.focus_radius_px
        gsd = footprint_width_m(obs.alt_agl_m, obs.hfov_rad) / obs.prob_safe.shape[1]
        return self.config.required_clearance_m / gsd

    # ---- views for reports and videos ---------------------------------------------------

    def map_view(self) -> dict[str, object]:
        """The fused map for pictures: P, confidence, clearance (metres) and its geometry."""
        return {"p_safe": self.map.fused_p(), "confidence": self.map.confidence(),
                "clearance_m": self.map.clearance_m(self._spot_logit()), "cell_m": self.map.cell_m,
                "north0_m": self.map.north0_m, "east0_m": self.map.east0_m,
                "vehicle_ne_m": (self.motion.north_m, self.motion.east_m),
                "blacklist": self.memory.blacklist if self.memory else ()}

    def _spot_logit(self) -> float:
        """The scene's spot threshold now (nothing safe before the scene is known)."""
        return self._spot_t

    # ---- input checks ------------------------------------------------------------------

    def _validate(self, obs: Observation) -> np.ndarray | None:
        if not isinstance(obs.t_s, (int, float)) or not math.isfinite(obs.t_s):
            raise PolicyInputError(f"observation t_s must be a finite number of seconds, got {obs.t_s!r}")
        if self._last_t_s is not None and obs.t_s < self._last_t_s:
            raise PolicyInputError(f"observation t_s went backwards: {obs.t_s} s after a heatmap at {self._last_t_s} s")
        for name in ("alt_agl_m", "roll_rad", "pitch_rad", "yaw_rad"):
            v = getattr(obs, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise PolicyInputError(f"observation {name} must be a finite number, got {v!r}")
        if obs.alt_agl_m <= 0.0:
            raise PolicyInputError(f"observation alt_agl_m must be > 0, got {obs.alt_agl_m!r}")
        if abs(obs.roll_rad) >= 1.2 or abs(obs.pitch_rad) >= 1.2:
            raise PolicyInputError(f"observation attitude beyond +/-1.2 rad (roll {obs.roll_rad}, pitch {obs.pitch_rad})")
        if not (isinstance(obs.hfov_rad, (int, float)) and 0.0 < obs.hfov_rad < math.pi):
            raise PolicyInputError(f"observation hfov_rad must be in (0, pi), got {obs.hfov_rad!r}")
        for name, size in (("vel_est_body_frd_m_s", 3), ("cmd_vel_body_frd_m_s", 3), ("odom_delta_ne_m", 2)):
            v = getattr(obs, name)
            if v is not None and (len(v) != size or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v)):
                raise PolicyInputError(f"observation {name} must be {size} finite numbers or None, got {v!r}")
        if obs.prob_safe is None:
            return None
        prob = obs.prob_safe
        return checked_prob_safe(prob, min_side_px=16)
