"""Is an altitude one the vehicle can have flown to since the last one? One check, two users.

A multirotor's altitude moves at most `max_speed_m_s` between two samples, plus the source's own
noise. A sample beyond that is refused (a forged or glitched state: one 100 m jump was accepted,
one forged 19 m state handed over for a tick). A step that persists over `confirm` samples that
agree with each other is real (an estimator reset, a rangefinder passing over a roof) and becomes
the new reference, with a warning. The controller's core checks every `VehicleState`; the
MAVLink adapter checks every LOCAL_POSITION_NED before it becomes one.

    check(t_s, alt_m) --within reach of the last accepted--> None (accepted)
                      --beyond reach, not yet confirmed-->   the reason it is refused
                      --the confirm-th agreeing step-->       None (re-anchored, logged)
"""

from __future__ import annotations

import bisect
import logging
from collections import deque

log = logging.getLogger(__name__)

# A racing quad climbs ~20 m/s. A baro's noise between two samples: the sim's harsh profile has
# 1 m sd per sample (1.4 m sd of a difference), so 6 m + 1 m per 50 ms is 5 sd: never in a flight.
MAX_VERTICAL_SPEED_M_S = 20.0
ALTITUDE_NOISE_M = 6.0
STEP_CONFIRM_SAMPLES = 3  # a step that persists this many samples is real (EKF reset, roof)


class AltitudeContinuity:
    """The last accepted (t_s, alt_m) and the refused samples agreeing on a new level."""

    def __init__(self, max_speed_m_s: float, noise_m: float, confirm: int, who: str = "") -> None:
        self.max_speed_m_s, self.noise_m, self.confirm, self.who = max_speed_m_s, noise_m, confirm, who
        self.last: tuple[float, float] | None = None
        self._step: list[tuple[float, float]] = []

    def reset(self) -> None:
        self.last, self._step = None, []

    def _reach_m(self, a_t_s: float, b_t_s: float) -> float:
        return self.noise_m + self.max_speed_m_s * abs(a_t_s - b_t_s)

    def check(self, t_s: float, alt_m: float) -> str | None:
        """None when (t_s, alt_m) is accepted (and becomes the reference), else why not."""
        if self.last is None or abs(alt_m - self.last[1]) <= self._reach_m(t_s, self.last[0]):
            self.last, self._step = (t_s, alt_m), []
            return None
        if self._step and abs(alt_m - self._step[-1][1]) > self._reach_m(t_s, self._step[-1][0]):
            self._step = []  # not one new level: start counting again
        self._step.append((t_s, alt_m))
        last_t_s, last_alt_m = self.last
        if len(self._step) >= self.confirm:
            log.warning("%s: the altitude stepped from %.1f m to %.1f m and held for %d samples: taken as the "
                        "new altitude", self.who, last_alt_m, alt_m, len(self._step))
            self.last, self._step = (t_s, alt_m), []
            return None
        return (f"altitude {alt_m:.1f} m is {alt_m - last_alt_m:+.1f} m from {last_alt_m:.1f} m "
                f"{abs(t_s - last_t_s):.2f} s earlier (a multirotor moves at most {self._reach_m(t_s, last_t_s):.1f} m)")


class AltitudeTrack:
    """The last `n` accepted (t_s, alt_m) states, and the one nearest a given time.

    `nearest(t)` is `min(states, key=|t_s - t|)` (the first of equally near ones, in the order
    they came): by bisection while the times in the window run in order (every flight; a
    re-ticked state repeats its time), by a scan while one that came back in time is still in it.
    The controller asks it for every heatmap, over 200 states.
    """

    def __init__(self, n: int) -> None:
        self._states: deque[tuple[float, float]] = deque(maxlen=n)
        self._added = 0
        self._unordered_until = 0  # while _added < this, a time that went back is in the window

    def add(self, t_s: float, alt_m: float) -> None:
        if self._states and t_s < self._states[-1][0]:
            self._unordered_until = self._added + self._states.maxlen
        self._states.append((t_s, alt_m))
        self._added += 1

    def nearest(self, t_s: float) -> tuple[float, float] | None:
        states = self._states
        if self._added < self._unordered_until:
            return min(states, key=lambda ta: abs(ta[0] - t_s), default=None)
        i = bisect.bisect_left(states, t_s, key=_time)  # times before i < t_s <= times from i
        if i == 0:
            return states[0] if states else None
        # The first of the latest time before t_s: min keeps the first of equally near states.
        before = states[bisect.bisect_left(states, states[i - 1][0], key=_time)]
        if i == len(states) or abs(before[0] - t_s) <= abs(states[i][0] - t_s):
            return before
        return states[i]


def _time(state: tuple[float, float]) -> float:
    return state[0]
