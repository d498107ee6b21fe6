"""The rules every fault run is held to, judged from what an observer saw on the router.

Data clock = the sim's seconds; one tick = the controller's loop period. Per run:

- blind: a status whose heatmap is older than the hold limit plus one tick, by the controller's
  own count or by the genuine heatmaps the observer saw (forged ones do not count), must not be
  `ok` (hold within one tick) and must command no descent;
- after `BRAKE_S` of a blind (or silent-controller) stretch the vehicle's altitude never drops;
- no LANDED or HANDOVER followed above the hand-over altitude (+ release): a "mid-air" hand-over;
  one the core refused still breaks the recovery rule ("refused terminal");
- after a fault that ends, the controller is `ok` again on a newer heatmap (resumption);
- the run's report names the service the fault should name (or none), and never takes a forged
  episode result.

A run whose fault was never injected (it left the world, landed or timed out before the descent
the fault waits for) is void: the fault's own rules (report, hold, resumption) are not judged and
it is reported as void, never as violations (on seed 12 all 10 runs left the 400 m world first
and made 25 "violations"). The safety rules still hold in a void run: they need no fault.
"""

from __future__ import annotations

import bisect
import math
import threading
from typing import Any

from dovesei.controller.core import ControllerConfig
from dovesei.faults.inject import FORGED_RESULT_DETAIL, FORGED_SEQ_BASE
from dovesei.shared.codec import decode
from dovesei.shared.errors import ProtocolError
from dovesei.shared.messages import ControllerStatus, EpisodeResult, SafetyHeatmap, VehicleState, VelocityCommand
from dovesei.up.monitor import LIVELINESS, Recorder, Sample

_DEFAULTS = ControllerConfig()  # what the services run with in every scenario
TICK_S = 1.0 / _DEFAULTS.rate_hz
HOLD_S = _DEFAULTS.heatmap_hold_after_s
HANDOVER_M, RELEASE_M = _DEFAULTS.handover_alt_m, _DEFAULTS.handover_release_m
ARRIVAL_MARGIN_S = 0.15  # the observer and the controller see a heatmap a few ms apart, under load more
BRAKE_S = 1.5  # the sim's velocity loop (0.3 s, 3 m/s^2) stops a 2.5 m/s descent well within this
CLIMB_TOLERANCE_M = 0.05
FORGED_DOWN_M_S = 4.0  # faster than any policy descends: only a forged command flies this


class Observer:
    """The fault suite's own record (Monitor calls `handle`): every message with its arrival time."""

    TYPES = {"state": VehicleState, "status": ControllerStatus, "cmd": VelocityCommand, "heatmap": SafetyHeatmap,
             "episode": EpisodeResult}

    def __init__(self, vehicle_id: str) -> None:
        self.vehicle_id = vehicle_id
        self.states: list[tuple[float, VehicleState]] = []
        self.statuses: list[tuple[float, ControllerStatus]] = []
        self.heatmaps: list[tuple[float, int, float]] = []  # (arrival wall s, seq, stamp t_s): genuine ones
        self.forged_heatmaps = 0
        self.rejected = 0
        self.lock = threading.Lock()  # the script thread drains, the checks read after the run

    def handle(self, s: Sample) -> None:
        if s.topic == LIVELINESS or s.topic not in self.TYPES:
            return
        try:
            msg = decode(s.payload, self.TYPES[s.topic], key=s.topic)
        except ProtocolError:
            self.rejected += 1
            return
        if getattr(msg, "vehicle_id", self.vehicle_id) != self.vehicle_id:
            return
        if s.topic == "state" and msg.seq < FORGED_SEQ_BASE:
            self.states.append((s.recv_wall_s, msg))
        elif s.topic == "status":
            self.statuses.append((s.recv_wall_s, msg))
        elif s.topic == "heatmap":
            if msg.seq >= FORGED_SEQ_BASE:
                self.forged_heatmaps += 1
            else:
                self.heatmaps.append((s.recv_wall_s, msg.seq, msg.stamp.t_s))

    @property
    def last_status(self) -> ControllerStatus | None:
        return self.statuses[-1][1] if self.statuses else None

    @property
    def last_state(self) -> VehicleState | None:
        return self.states[-1][1] if self.states else None


def check_run(fault: Any, obs: Observer, rec: Recorder, failure: Any, fault_start_wall_s: float | None,
              fault_end_wall_s: float | None) -> tuple[list[str], dict]:
    """Every rule of the module docstring for one run of `fault` (a scenario.Fault); returns
    (violations, facts for the record). The wall times are the observer's clock (None: not injected/ended)."""
    v: list[str] = []
    statuses = sorted(obs.statuses, key=lambda p: p[1].stamp.t_s)
    hm_arrivals = sorted(obs.heatmaps)
    # The genuine capture time of each heatmap seq, as the segmenter stamped it (first seen wins).
    genuine_t: dict[int, float] = {}
    for _, seq, t_s in hm_arrivals:
        genuine_t.setdefault(seq, t_s)
    limit_s = HOLD_S + TICK_S
    # The vehicle's clock as the observer knew it at each arrival: the newest genuine state so far.
    state_arr, state_newest, newest = [], [], -math.inf
    for recv_s, st in sorted(obs.states, key=lambda p: p[0]):
        newest = max(newest, st.stamp.t_s)
        state_arr.append(recv_s)
        state_newest.append(newest)
    forged_adopted = 0  # ticks that held a forged heatmap without following it
    held = False
    blind_t: list[tuple[float, bool]] = []  # per status: (t_s, blind)
    for recv_s, st in statuses:
        if st.state == "HANDOVER" or st.alt_agl_m <= HANDOVER_M + RELEASE_M:
            blind_t.append((st.stamp.t_s, False))
            continue
        # The adopted heatmap's age by its genuine stamp: a skewed copy of a real seq shows here. A
        # seq the observer missed (its own subscription lagging after a router restart) is unknown.
        adopted_t = genuine_t.get(st.frame_seq)
        true_age = st.stamp.t_s - adopted_t if adopted_t is not None else -math.inf
        own_blind = st.heatmap_age_s > limit_s or st.heatmap_age_s < 0
        true_blind = true_age > limit_s + ARRIVAL_MARGIN_S
        blind = own_blind or true_blind or st.watchdog != "ok"
        blind_t.append((st.stamp.t_s, blind))
        if st.watchdog != "ok" and fault_start_wall_s is not None and recv_s >= fault_start_wall_s:
            held = True
        if (own_blind or true_blind) and st.watchdog == "ok" and st.heatmap_age_s >= 0:
            v.append(f"blind but ok at t={st.stamp.t_s:.2f} s: heatmap age {st.heatmap_age_s:.2f} s (own), "
                     f"{true_age:.2f} s (genuine), limit {HOLD_S:g} s + one tick")
        if blind and st.vel_body_frd_m_s[2] > 1e-6:
            v.append(f"blind descent commanded at t={st.stamp.t_s:.2f} s ({st.vel_body_frd_m_s[2]:.2f} m/s down, "
                     f"watchdog {st.watchdog})")
        if st.state in ("LANDED", "HANDOVER") and st.alt_agl_m > HANDOVER_M + RELEASE_M:
            # Followed (watchdog ok) it is a hand-over in mid-air; refused by the core it still
            # breaks the recovery rule (the policy must not think it has landed up here).
            kind = "mid-air" if st.watchdog == "ok" else "refused terminal:"
            v.append(f"{kind} {st.state} at {st.alt_agl_m:.1f} m (t={st.stamp.t_s:.2f} s, watchdog {st.watchdog})")
        if st.frame_seq >= FORGED_SEQ_BASE:
            # Followed on the vehicle's own timeline, a forged heatmap steers it. Adopted on a forged
            # (past-stamped) state's tick, its command carries that stale stamp and the sim drops it;
            # counted as a fact, not a violation (plain mode cannot tell a forgery in time).
            j = bisect.bisect_right(state_arr, recv_s) - 1
            on_timeline = j < 0 or st.stamp.t_s >= state_newest[j] - 1.0  # not a forged past state's tick
            if st.watchdog == "ok" and on_timeline:
                v.append(f"blind: a forged heatmap ({st.frame_seq}) was followed at t={st.stamp.t_s:.2f} s")
            else:
                forged_adopted += 1
    v += _physical(obs, blind_t)
    if rec.result is not None and rec.result.outcome in ("safe", "unsafe") and \
            rec.result.final_alt_m > HANDOVER_M + RELEASE_M:
        v.append(f"mid-air judged end: {rec.result.outcome} at {rec.result.final_alt_m:.1f} m")
    for _, st in obs.states:
        if st.vel_body_frd_m_s[2] > FORGED_DOWN_M_S:
            v.append(f"forged command obeyed: descending {st.vel_body_frd_m_s[2]:.1f} m/s at t={st.stamp.t_s:.2f} s")
            break
    if fault_start_wall_s is None:
        # Void: only the safety rules above apply (the fault's own rules need the fault).
        return v, _facts(obs, rec, statuses, hm_arrivals, held, None, forged_adopted)
    # The report.
    named = failure.child if failure is not None else None
    if named != fault.names:
        v.append(f"report: expected {'a failure naming ' + fault.names if fault.names else 'no failure'}, got "
                 f"{failure.message if failure is not None else 'none'}")
    if rec.result is not None and rec.result.detail == FORGED_RESULT_DETAIL:
        v.append("report: the forged episode result was taken as the sim's")
    if fault.name == "forged" and rec.results_refused < 1 and fault_start_wall_s is not None:
        v.append("report: the forged episode result was not refused")
    if fault.names is not None or fault.name == "segmenter-kill":
        # A hung controller cannot hold (the sim's vehicle brakes on its own), and in lockstep the
        # sim's clock stops with the hung service: no data time passes, so nobody goes blind.
        if not held and not fault.name.startswith("controller-hang") and not fault.lockstep:
            v.append("no hold after the fault (the controller never stopped following the policy)")
    resumed = None
    if fault.resumes and fault_end_wall_s is not None:
        after = [st for recv_s, st in obs.statuses if recv_s > fault_end_wall_s]
        seq0 = max((st.frame_seq for recv_s, st in obs.statuses if recv_s <= fault_start_wall_s
                    and st.frame_seq < FORGED_SEQ_BASE), default=-1)
        resumed = any((st.watchdog == "ok" or st.state == "HANDOVER") and seq0 < st.frame_seq < FORGED_SEQ_BASE
                      for st in after)
        if not resumed:
            v.append("no resumption: the controller was never ok on a new heatmap after the fault ended")
    return v, _facts(obs, rec, statuses, hm_arrivals, held, resumed, forged_adopted)


def _facts(obs: Observer, rec: Recorder, statuses: list, hm_arrivals: list, held: bool, resumed: bool | None,
           forged_adopted: int) -> dict:
    return {"held": held, "resumed": resumed, "statuses": len(statuses), "heatmaps": len(hm_arrivals),
            "forged_heatmaps_seen": obs.forged_heatmaps, "monitor_rejected": rec.rejected,
            "results_refused": rec.results_refused, "forged_heatmap_ticks_not_followed": forged_adopted,
            "min_alt_m": round(min((st.alt_agl_m for _, st in obs.states), default=math.nan), 2)}


def _physical(obs: Observer, blind_t: list[tuple[float, bool]]) -> list[str]:
    """The vehicle's true altitude (the sim's states) never drops after BRAKE_S of blindness or silence."""
    if not obs.states:
        return []
    st_t = [t for t, _ in blind_t]
    out: list[str] = []
    since: float | None = None  # data time at which the current blind stretch began
    ref_alt: float | None = None
    for _, s in sorted(obs.states, key=lambda p: p[1].stamp.t_s):
        t = s.stamp.t_s
        i = bisect.bisect_right(st_t, t) - 1
        silent = i < 0 or t - st_t[i] > HOLD_S  # the controller said nothing for longer than the hold limit
        blind = silent or blind_t[i][1]
        if i < 0 or s.alt_agl_m <= HANDOVER_M + RELEASE_M:
            blind = False  # before the first status the vehicle waits; at hand-over nothing is judged
        if not blind:
            since, ref_alt = None, None
            continue
        if since is None:
            since = t
        if t - since < BRAKE_S:
            continue
        if ref_alt is None:
            ref_alt = s.alt_agl_m
        elif s.alt_agl_m < ref_alt - CLIMB_TOLERANCE_M:
            out.append(f"descent while blind: {ref_alt - s.alt_agl_m:.2f} m lost between t={since + BRAKE_S:.2f} "
                       f"and {t:.2f} s")
            since, ref_alt = None, None
        else:
            ref_alt = max(ref_alt, s.alt_agl_m)  # a climb is welcome; coming back down from it is not
    return out
