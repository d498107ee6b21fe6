"""The `clearance` policy's state machine: an enum and one pure step function.

    WARMUP --3 frames / 10 s--> SEARCH --a spot (clearance >= radius + margin, confirmed from
            high up)--> APPROACH
    SEARCH  --each pass flown: the next one lower (100 -> 60 -> 40 m from 100 m; every altitude
            scales with the start altitude, ClearanceConfig.altitudes), where detail resolves
            (each pass its own expanding square: spacing from its footprint, radius shrinking
            as sqrt(altitude), so every pass takes about as long as the first)
    SEARCH  --promising ground within reach (an area that reads well from high up but is not yet
            a spot; during the top pass only the likely ones; once it is flown, likely ground
            anywhere first, then what is within reach, then anywhere in the search area)--> PROBE
    PROBE   --fly there, look from the probe altitude: a spot--> APPROACH (a spot glimpsed on the
            way that fails its re-checks before the descent gives the probe back, same clock)
    PROBE   --nothing after probe_frames, probe_timeout_s + the flight there at the search speed,
            or the search's time--> SEARCH (the area
            remembered as probed; at most probe_max probes)
    SEARCH  --the whole route flown or no_spot_after_s--> NO_SPOT (hold: "no safe spot found");
            a route spent by the velocity-loss marks first holds one step, so the scene is read and
            its spots and probes are tried
    APPROACH --within the lock radius--> DESCEND --measured alt <= hand-over alt, centred, the disk
             below cleared with handover_margin_m to spare--> HANDOVER
    APPROACH --target fails fail_frames re-checks / approach_timeout_s--> SEARCH (blacklisted)
    APPROACH, DESCEND --a close look finds the never set near the spot--> SEARCH from where it is
             (blacklisted; `reject_target`)
    DESCEND  --target fails fail_frames re-checks / descend_timeout_s--> ABORT (blacklisted)
    DESCEND  --below the hand-over alt but off the spot or the spot not fixed--> DESCEND holding
             its altitude, steering onto the spot (the SITL flight that handed over 2.4 m off a
             spot whose clearance was 4.4 m, onto a path 0.6 m away)
    DESCEND  --lock lost (error > 3 x lock-out)--> APPROACH
    DESCEND  --the spot not fixed by vision for spot_trust_s--> DESCEND holding its altitude; after
             recheck_frames fresh looks the footprint below is re-checked and becomes the spot
             (a new keyframe): it never descends on a dead-reckoned guess of the checked ground
    ABORT    --back at the search altitude / abort_timeout_s--> SEARCH where the route was left,
             or NO_SPOT after max_aborts
    any live state --no heatmap for gap_s--> GAP_HOLD (map frozen, zero velocity)
    GAP_HOLD --gap_recover_frames fresh frames--> APPROACH (target kept, lock again) or SEARCH
             (a probe in progress is dropped, not counted)
    GAP_HOLD --still blind after gap_hold_timeout_s--> ABORT (climb to the search altitude, no
             blacklist)

Every live state has a timeout and a way out; NO_SPOT and HANDOVER are the chain's two ends
(the operator, or the short-range sensors, take over). Descent happens only in DESCEND, only with
the lateral error inside the lock (hysteresis: lock_in to start, lock_out to stop), and HANDOVER
only at the measured hand-over altitude; a probe descends to its altitude, never below hand-over
+ 10 m. Every transition carries its reason.

Positions are north/east metres in the policy's own frame; velocities come out body FRD.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum

from dovesei.shared.frames import to_body
from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.clearance.ground_map import Spot, footprint_width_m


class Phase(str, Enum):
    WARMUP = "WARMUP"
    SEARCH = "SEARCH"
    PROBE = "PROBE"
    APPROACH = "APPROACH"
    DESCEND = "DESCEND"
    ABORT = "ABORT"
    GAP_HOLD = "GAP_HOLD"
    NO_SPOT = "NO_SPOT"
    HANDOVER = "HANDOVER"


TERMINAL = (Phase.NO_SPOT, Phase.HANDOVER)


@dataclass(frozen=True)
class Memory:
    """Everything the machine remembers between steps (immutable: a step returns a new one)."""

    phase: Phase = Phase.WARMUP
    since_s: float = 0.0  # when the phase was entered
    start_s: float = 0.0  # when the policy started
    frames: int = 0  # fresh frames counted in the phase (warm-up, gap recovery)
    target: Spot | None = None
    fails: int = 0  # consecutive failed re-checks of the target
    aborts: int = 0
    blacklist: tuple[tuple[float, float, float], ...] = ()  # rejected spots: north, east, altitude seen
    waypoint: int = 0  # index into the search pattern (counts repeats)
    probe: Spot | None = None  # the area being probed (kept while a spot seen on the way is approached)
    probe_since_s: float = 0.0  # when that probe began (its clock, while a glimpsed spot is approached)
    probed: tuple[tuple[float, float], ...] = ()  # areas looked at closely without a spot showing
    descending: bool = False  # inside the lock (hysteresis state)
    reason: str = "starting"
    # Counts the looks that established a target (chosen, switched, re-checked below): the policy
    # takes the spot's keyframe from the look that changed it.
    anchor: int = 0


@dataclass(frozen=True)
class Inputs:
    """One step's view: time, the vehicle's estimated pose, what the map says."""

    t_s: float
    alt_agl_m: float
    north_m: float
    east_m: float
    yaw_rad: float
    fresh: bool  # a new heatmap this step
    gap: bool  # no heatmap for more than gap_s
    search_alt_m: float  # the top search altitude (where an abort climbs back to)
    route: tuple[tuple[float, float, float], ...]  # every search pass in order: north, east, altitude
    best: Spot | None  # the best spot on the map now (not blacklisted, inside the radius)
    check: Spot | None  # the target re-checked (moved if it failed in place; None: it fails), if any
    hfov_rad: float  # the camera's (how much ground a view covers)
    candidate: Spot | None = None  # the most promising area worth a closer look (SEARCH only)
    passes: int = 1  # how many passes the route holds (for the reason)
    top_pass_end: int | None = None  # the route's waypoints before this are the top pass (None: all)
    fence_m: float | None = None  # the fence now (None: the config's); route points beyond it are pulled in
    probe_alt_m: float | None = None  # this flight's probe altitude (None: the config's)
    spot_known: bool = True  # the target was fixed by vision (or re-checked) within spot_trust_s
    recheck: Spot | None = None  # the footprint below, re-checked (None: it does not qualify)
    candidate_likely: bool = False  # the candidate reads likely enough to probe during the top pass
    # Something outside the map withholds the hand-over (the close look: no fresh clear look of the
    # spot, or something of the never set inside its margin): below the hand-over altitude the
    # descent holds, steering onto the spot, until it is released or the descent times out.
    handover_withheld: str = ""
    # Where the camera stopped measuring the vehicle's velocity, each (north, east, unit north,
    # unit east): the vehicle's position and the way it was going. The ground beyond gave it
    # nothing to measure (calm water): search waypoints past such a line are skipped.
    blind: tuple[tuple[float, float, float, float], ...] = ()
    # The map's clearance where the vehicle is (None: not measured; the target's clearance less
    # the distance to it stands in, which the triangle inequality makes a lower bound).
    below_clearance_m: float | None = None


def search_pattern(spacing_m: float, radius_m: float) -> tuple[tuple[float, float], ...]:
    """An expanding square around the start (0, 0): legs 1, 1, 2, 2, 3, 3... x spacing, turning
    N, E, S, W; it stops before a corner would leave the radius, then returns to the start."""
    points: list[tuple[float, float]] = []
    n = e = 0.0
    dirs = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))
    leg = 0
    while len(points) < 64:
        length = (leg // 2 + 1) * spacing_m
        dn, de = dirs[leg % 4]
        nn, ne = n + dn * length, e + de * length
        if math.hypot(nn, ne) > radius_m:
            break
        points.append((nn, ne))
        n, e = nn, ne
        leg += 1
    points.append((0.0, 0.0))
    return tuple(points)


def search_route(passes: tuple[tuple[float, float, float], ...]) -> tuple[tuple[float, float, float], ...]:
    """The search route from its passes, each (altitude, spacing, radius): one expanding square
    per pass at its altitude, flown in order."""
    route: list[tuple[float, float, float]] = []
    for alt, spacing, radius in passes:
        route.extend((n, e, alt) for n, e in search_pattern(spacing, radius))
    return tuple(route)


def beyond_blind(north_m: float, east_m: float, blind: tuple[tuple[float, float, float, float], ...],
                 margin_m: float) -> bool:
    """Is the point past (or within `margin_m` short of) a line where the velocity was lost?"""
    return any((north_m - bn) * un + (east_m - be) * ue > -margin_m for bn, be, un, ue in blind)


def search_level_alt(waypoint: int, inp: Inputs) -> float:
    """The altitude of the search pass `waypoint` belongs to (the last one's past the end)."""
    if not inp.route:
        return inp.search_alt_m
    return inp.route[min(waypoint, len(inp.route) - 1)][2]


def _top_pass(waypoint: int, inp: Inputs) -> bool:
    """Is the search still on its first pass (at the top level)?"""
    return waypoint < (len(inp.route) if inp.top_pass_end is None else inp.top_pass_end)


def committed(mem: Memory) -> bool:
    """Is the policy landing where it is (the controller may hand over at the hand-over altitude)?
    Only in HANDOVER, or in DESCEND while it descends: centred on a spot fixed by vision. A
    DESCEND holding its altitude (off the spot, or re-checking it) is not a landing, so a hold
    sagging through the hand-over altitude hands nothing over."""
    return mem.phase is Phase.HANDOVER or (mem.phase is Phase.DESCEND and mem.descending)


# The phases a probe lives through: its own, the approach of a spot glimpsed on its way (which gives
# the probe back if it fails before the descent), and a perception gap in either. Any other phase
# ends it.
_PROBE_PHASES = (Phase.PROBE, Phase.APPROACH, Phase.GAP_HOLD)


def _go(mem: Memory, phase: Phase, t_s: float, reason: str, **changes: object) -> Memory:
    if phase not in _PROBE_PHASES:
        changes.setdefault("probe", None)
    return dataclasses.replace(mem, phase=phase, since_s=t_s, frames=0, fails=0, descending=False, reason=reason,
                               **changes)


def _blacklisted(mem: Memory, spot: Spot, alt_m: float) -> tuple[tuple[float, float, float], ...]:
    return mem.blacklist + ((spot.north_m, spot.east_m, alt_m),)


def reject_target(mem: Memory, t_s: float, alt_m: float, reason: str) -> Memory:
    """The target rejected from outside the map (a close look saw what must never be near it):
    blacklisted, and the search goes on from where the vehicle is, a descent's too.

    The map was not wrong: the spot was clear ground with somebody on it, and the other spots it
    confirmed are as good as they were. So nothing climbs back: another confirmed spot is taken
    at once (its own close look follows), else the search's probes and route go on (the route
    climbs back to its level). Climbing to the search altitude after each finding cost ~200 s a
    time (`harsh` parkland start 8: four findings, 1200 s, no landing), and on a crowded beach it
    left a handful of tries where there is time for dozens."""
    if mem.target is None or mem.phase in TERMINAL:
        return mem
    return _go(mem, Phase.SEARCH, t_s, reason + ": rejected, searching on", target=None,
               blacklist=_blacklisted(mem, mem.target, alt_m))


def withdraw_handover(mem: Memory, t_s: float, reason: str) -> Memory:
    """A declared hand-over taken back before the controller completed it (a close look saw the
    never set come into the margin while the altitude was being confirmed: people walk in): DESCEND
    over the same spot again, which holds its altitude while the hand-over is withheld and declares
    it again once released. Anything else is left as it is."""
    if mem.phase is not Phase.HANDOVER or mem.target is None:
        return mem
    return _go(mem, Phase.DESCEND, t_s, reason + ": hand-over withdrawn, holding over the spot")


def toward(north_err: float, east_err: float, gain: float, vmax: float, yaw: float) -> tuple[float, float]:
    """Body forward/right velocity = gain x the north/east error, capped at vmax."""
    vn, ve = gain * north_err, gain * east_err
    speed = math.hypot(vn, ve)
    if speed > vmax:
        vn, ve = vn * vmax / speed, ve * vmax / speed
    return to_body(vn, ve, yaw)


def _hold_alt(alt: float, goal: float, cfg: ClearanceConfig) -> float:
    """Vertical speed (+down) holding an altitude; never below the hand-over altitude."""
    up = min(max(0.5 * (goal - alt), -cfg.climb_speed_m_s), cfg.climb_speed_m_s)
    return -up


def step(mem: Memory, inp: Inputs, cfg: ClearanceConfig) -> tuple[Memory, tuple[float, float, float]]:
    """One decision: the next memory and the body FRD velocity (+down)."""
    t, p = inp.t_s, mem.phase
    if p in TERMINAL:
        return mem, (0.0, 0.0, 0.0)
    elapsed = t - mem.since_s  # time in the phase; recomputed after a transition within this step

    # --- perception gap: freeze and hold, from any live state ---
    if inp.gap and p is not Phase.GAP_HOLD:
        mem = _go(mem, Phase.GAP_HOLD, t, f"no heatmap for more than {cfg.gap_s:g} s: map frozen, holding")
        return mem, (0.0, 0.0, 0.0)
    if p is Phase.GAP_HOLD:
        if elapsed > cfg.gap_hold_timeout_s:
            return _go(mem, Phase.ABORT, t, f"blind for {cfg.gap_hold_timeout_s:g} s: climbing to the search "
                                            "altitude"), (0.0, 0.0, -cfg.climb_speed_m_s)
        frames = mem.frames + (1 if inp.fresh and not inp.gap else 0)
        if frames >= cfg.gap_recover_frames:
            if mem.target is not None:
                return _go(mem, Phase.APPROACH, t, "perception back: re-locking on the target"), (0.0, 0.0, 0.0)
            return _go(mem, Phase.SEARCH, t, "perception back: searching"), (0.0, 0.0, 0.0)
        return dataclasses.replace(mem, frames=frames), (0.0, 0.0, 0.0)

    if p is Phase.WARMUP:
        frames = mem.frames + (1 if inp.fresh else 0)
        if frames >= cfg.warmup_frames or elapsed > cfg.warmup_timeout_s:
            mem = _go(mem, Phase.SEARCH, t, f"warm-up done after {frames} frames")
            p = Phase.SEARCH
        else:
            return dataclasses.replace(mem, frames=frames), (0.0, 0.0, 0.0)

    probe_alt = cfg.probe_alt_m if inp.probe_alt_m is None else inp.probe_alt_m
    if p is Phase.PROBE:
        probe = mem.probe
        assert probe is not None
        if inp.best is not None:
            p = Phase.SEARCH  # a spot: taken below, as from the search
        else:
            looked = mem.frames + (1 if inp.fresh else 0)
            err_n, err_e = probe.north_m - inp.north_m, probe.east_m - inp.east_m
            err = math.hypot(err_n, err_e)
            over = err < cfg.lock_out_m + cfg.lock_alt_frac * inp.alt_agl_m
            low = inp.alt_agl_m <= probe_alt + cfg.probe_alt_tol_m
            done = over and low and looked >= cfg.probe_frames
            # The time a probe may take: the look's own, and the flight there at the search speed.
            timeout_s = cfg.probe_timeout_s + probe.distance_m / cfg.search_speed_m_s
            if done or elapsed > timeout_s or t - mem.start_s > cfg.no_spot_after_s:
                why = (f"probed from {inp.alt_agl_m:.0f} m: no spot" if done
                       else f"probe took over {timeout_s:.0f} s" if elapsed > timeout_s
                       else f"the search's {cfg.no_spot_after_s:g} s are up")
                return _go(mem, Phase.SEARCH, t, why + ": searching on",
                           probed=mem.probed + ((probe.north_m, probe.east_m),)), (0.0, 0.0, 0.0)
            mem = dataclasses.replace(mem, frames=looked if over and low else 0)
            vf, vr = toward(err_n, err_e, cfg.approach_gain_per_s, cfg.search_speed_m_s, inp.yaw_rad)
            # Down only once nearly over it (the view from above covers it on the way).
            near = err < cfg.probe_descend_frac * footprint_width_m(inp.alt_agl_m, inp.hfov_rad)
            return mem, (vf, vr, _hold_alt(inp.alt_agl_m, probe_alt if near else inp.alt_agl_m, cfg))

    if p is Phase.SEARCH:
        if inp.best is not None:
            s = inp.best
            mem = _go(mem, Phase.APPROACH, t, f"spot {s.distance_m:.0f} m away: clearance {s.clearance_m:.1f} m, "
                                              f"confidence {s.confidence:.2f}", target=s, anchor=mem.anchor + 1)
            p = Phase.APPROACH
        elif (inp.candidate is not None and len(mem.probed) < cfg.probe_max
              and t - mem.start_s <= cfg.no_spot_after_s
              and (inp.candidate_likely or not _top_pass(mem.waypoint, inp))):
            c = inp.candidate
            return _go(mem, Phase.PROBE, t, f"promising ground {c.distance_m:.0f} m away (P {c.p_safe:.2f} over the "
                                            f"disk): a closer look from {probe_alt:.0f} m", probe=c,
                       probe_since_s=t), (0.0, 0.0, 0.0)
        elif t - mem.start_s > cfg.no_spot_after_s:
            return _go(mem, Phase.NO_SPOT, t, f"no safe spot found in {cfg.no_spot_after_s:g} s"), (0.0, 0.0, 0.0)
        else:
            wp = mem.waypoint
            skipped = 0
            while wp < len(inp.route) and beyond_blind(inp.route[wp][0], inp.route[wp][1], inp.blind, cfg.blind_margin_m):
                wp, skipped = wp + 1, skipped + 1
            if skipped:
                mem = dataclasses.replace(mem, waypoint=wp, reason=f"{skipped} search waypoint(s) beyond ground where "
                                                                   "the camera measured no velocity: skipped")
            if wp >= len(inp.route):
                if skipped:
                    # The marks spent the route before the search had judged what it saw (the spots
                    # and probes of the passes flown wait for the route's end): hold here one step
                    # so the scene is read and its spots and probes are tried; NO_SPOT only then.
                    # Two marks once ended harsh desert searches at 150-180 s over open soil.
                    return dataclasses.replace(mem, reason=mem.reason + "; the route is spent: judging what it saw"), \
                        (0.0, 0.0, 0.0)
                return _go(mem, Phase.NO_SPOT, t, f"no safe spot found within {cfg.search_radius_m:g} m "
                                                  f"({inp.passes} search passes)"), (0.0, 0.0, 0.0)
            goal_n, goal_e, level_alt = inp.route[wp]
            # A waypoint beyond the fence (shrunk while the estimate is uncertain) is flown to the
            # fence's edge instead: the vehicle would otherwise press on the fence and never arrive.
            reach = max((cfg.fence_m if inp.fence_m is None else inp.fence_m) - 5.0, 0.0)
            r_goal = math.hypot(goal_n, goal_e)
            if r_goal > reach:
                goal_n, goal_e = goal_n * reach / r_goal, goal_e * reach / r_goal
            err_n, err_e = goal_n - inp.north_m, goal_e - inp.east_m
            if math.hypot(err_n, err_e) < 5.0 and abs(inp.alt_agl_m - level_alt) < 5.0:
                mem = dataclasses.replace(mem, waypoint=wp + 1)
                if wp + 1 < len(inp.route) and search_level_alt(wp + 1, inp) != level_alt:
                    mem = dataclasses.replace(mem, reason=f"no spot at {level_alt:.0f} m: searching lower, at "
                                                          f"{search_level_alt(wp + 1, inp):.0f} m")
            vf, vr = toward(err_n, err_e, cfg.approach_gain_per_s, cfg.search_speed_m_s, inp.yaw_rad)
            return mem, (vf, vr, _hold_alt(inp.alt_agl_m, level_alt, cfg))

    if p is Phase.ABORT:
        back = inp.alt_agl_m >= inp.search_alt_m - 2.0
        if back or elapsed > cfg.abort_timeout_s:
            why = "back at the search altitude" if back else f"climb took over {cfg.abort_timeout_s:g} s"
            if mem.aborts >= cfg.max_aborts:
                return _go(mem, Phase.NO_SPOT, t, f"no safe spot found: {mem.aborts} aborts ({why})"), (0.0, 0.0, 0.0)
            # The route goes on where it was left: flown again from its start, every abort cost
            # a whole pass (the top one alone takes ~280 s over a 300 m radius).
            return _go(mem, Phase.SEARCH, t, f"{why}: searching again"), (0.0, 0.0, 0.0)
        return mem, (0.0, 0.0, -cfg.climb_speed_m_s)

    # --- APPROACH and DESCEND: a target is held ---
    target = mem.target
    assert target is not None
    fails = mem.fails
    if inp.fresh:
        if inp.check is None:
            fails += 1
        else:
            fails = 0
            target = inp.check  # where it is, or moved within the refine radius if it failed in place
    if fails >= cfg.fail_frames:
        why = f"target failed {fails} re-checks (clearance or confidence too low at {inp.alt_agl_m:.0f} m)"
        if p is Phase.DESCEND:
            return _go(mem, Phase.ABORT, t, why + ": abort, climbing back", target=None, aborts=mem.aborts + 1,
                       blacklist=_blacklisted(mem, target, inp.alt_agl_m)), (0.0, 0.0, -cfg.climb_speed_m_s)
        # Not yet descending: rejected. A spot glimpsed on the way to a probe (a few looks at the edge
        # of the view from 100 m, the top of the map's noise) gives the probe back, on the probe's
        # own clock: dropping it sent the search to another probe, and harsh desert starts 11 and
        # 32 of 34 churned so (spot at confidence 0.4-0.5, failed within 1-8 s, new probe) for 900 s
        # without a probe ever reaching its altitude. Otherwise the search takes the vehicle back
        # to its route's altitude.
        if p is Phase.APPROACH and mem.probe is not None:
            return dataclasses.replace(_go(mem, Phase.PROBE, t, why + ": rejected, the closer look goes on", target=None,
                                           blacklist=_blacklisted(mem, target, inp.alt_agl_m)),
                                       since_s=mem.probe_since_s), (0.0, 0.0, 0.0)
        return _go(mem, Phase.SEARCH, t, why + ": rejected", target=None,
                   blacklist=_blacklisted(mem, target, inp.alt_agl_m)), (0.0, 0.0, 0.0)
    err_n, err_e = target.north_m - inp.north_m, target.east_m - inp.east_m
    err = math.hypot(err_n, err_e)
    lock_in = cfg.lock_in_m + cfg.lock_alt_frac * inp.alt_agl_m
    lock_out = cfg.lock_out_m + cfg.lock_alt_frac * inp.alt_agl_m
    mem = dataclasses.replace(mem, target=target, fails=fails)

    if p is Phase.APPROACH:
        if t - mem.since_s > cfg.approach_timeout_s:
            return _go(mem, Phase.SEARCH, t, f"approach took over {cfg.approach_timeout_s:g} s: rejected",
                       target=None, blacklist=_blacklisted(mem, target, inp.alt_agl_m)), (0.0, 0.0, 0.0)
        best = inp.best
        if (best is not None and best.score > target.score + cfg.switch_gain
                and math.hypot(best.north_m - target.north_m, best.east_m - target.east_m) > cfg.refine_radius_m):
            mem = _go(mem, Phase.APPROACH, t, f"better spot: clearance {best.clearance_m:.1f} m, confidence "
                                              f"{best.confidence:.2f}, score {best.score:.2f} > {target.score:.2f}",
                      target=best, anchor=mem.anchor + 1)
            target = best
            err_n, err_e = target.north_m - inp.north_m, target.east_m - inp.east_m
            err = math.hypot(err_n, err_e)
        elif err < lock_in:
            mem = _go(mem, Phase.DESCEND, t, f"locked within {err:.1f} m: descending, re-checking the footprint",
                      target=target)
            p = Phase.DESCEND
        if p is Phase.APPROACH:
            vf, vr = toward(err_n, err_e, cfg.approach_gain_per_s, cfg.max_speed_m_s, inp.yaw_rad)
            return mem, (vf, vr, _hold_alt(inp.alt_agl_m, max(inp.alt_agl_m, cfg.handover_alt_m + 5.0), cfg))

    # DESCEND
    # The hand-over needs the measured altitude, the spot fixed by vision, the vehicle centred on
    # it (within lock_in) and the map clearing the vehicle's own disk: the checked clearance holds
    # the 2 m disk only around the spot. Below the hand-over altitude otherwise (an altitude hold
    # sagging while the spot is re-checked, say) the vehicle holds its altitude and steers onto
    # the spot first.
    room = target.clearance_m - err if inp.below_clearance_m is None else inp.below_clearance_m
    roomy = room >= cfg.safety_radius_m + cfg.handover_margin_m  # the hand-over point's own disk is cleared
    if (inp.alt_agl_m <= cfg.handover_alt_m and inp.spot_known and err <= lock_in and roomy
            and not inp.handover_withheld):
        return _go(mem, Phase.HANDOVER, t, f"at the hand-over altitude over the spot (error {err:.1f} m, "
                                           f"clearance {target.clearance_m:.1f} m, {room:.1f} m below)"), (0.0, 0.0, 0.0)
    if t - mem.since_s > cfg.descend_timeout_s:
        return _go(mem, Phase.ABORT, t, f"descent took over {cfg.descend_timeout_s:g} s: abort", target=None,
                   aborts=mem.aborts + 1, blacklist=_blacklisted(mem, target, inp.alt_agl_m)), (0.0, 0.0, -cfg.climb_speed_m_s)
    if err > 3.0 * lock_out:
        return _go(mem, Phase.APPROACH, t, f"lock lost ({err:.1f} m off): approaching again"), (0.0, 0.0, 0.0)
    if not inp.spot_known:
        # Where the checked ground went is a guess: hold the altitude, and after a few fresh
        # looks take the footprint below, re-checked, as the spot.
        looked = mem.frames + (1 if inp.fresh else 0)
        if looked >= cfg.recheck_frames and inp.recheck is not None:
            s = inp.recheck
            # The descent's clock runs on (its timeout bounds a descent that keeps re-checking).
            return dataclasses.replace(mem, target=s, anchor=mem.anchor + 1, frames=0, fails=0, descending=False,
                                       reason=f"spot not fixed by vision: re-checked the footprint below at "
                                              f"{inp.alt_agl_m:.0f} m (clearance {s.clearance_m:.1f} m)"), (0.0, 0.0, 0.0)
        vf, vr = toward(err_n, err_e, cfg.approach_gain_per_s, cfg.max_speed_m_s, inp.yaw_rad)
        return dataclasses.replace(mem, frames=looked, descending=False), (vf, vr, 0.0)
    final = inp.alt_agl_m <= cfg.handover_alt_m + cfg.final_band_m  # centred on the spot for the hand-over
    descending = err < lock_in or (mem.descending and err <= (lock_in if final else lock_out))
    if descending != mem.descending or mem.frames:
        mem = dataclasses.replace(mem, descending=descending, frames=0)
    vf, vr = toward(err_n, err_e, cfg.approach_gain_per_s, cfg.max_speed_m_s, inp.yaw_rad)
    vz = 0.0
    if (inp.handover_withheld or not roomy) and inp.alt_agl_m <= cfg.handover_alt_m:
        vz = _hold_alt(inp.alt_agl_m, cfg.handover_alt_m, cfg)  # sagged below it: back up to it, no lower
    elif descending:
        vz = min(max(cfg.descent_gain_per_s * (inp.alt_agl_m - cfg.handover_alt_m) + cfg.descent_min_m_s,
                     cfg.descent_min_m_s), cfg.descent_max_m_s)
    return mem, (vf, vr, vz)
