"""Clocks: every decision uses the clock of the data, never the host's speed.

In simulation the data clock is sim time, advanced by the messages themselves (a `DataClock`
fed from stamps); in flight it is the vehicle's clock, equally fed from its state messages; a
`WallClock` serves the real-time loops that must tick on their own. Each clock is named, and the
name travels in every `Stamp` so a reader knows which timeline a number belongs to.

A sender's stamp is a claim, not a fact: `StampBound` judges each one against the receiver's own
clock at arrival, so a stamp from the future (a skewed clock, a bug, a forgery) is refused and
counted before it can become "the newest" and make every honest sample look old.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from dovesei.shared.messages import CLOCKS, Stamp


class WallClock:
    """Monotonic wall time in seconds; `sleep_until` waits on an event so a stop wakes it."""

    name = "wall"

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now_s(self) -> float:
        return time.monotonic() - self._t0

    def stamp(self) -> Stamp:
        return Stamp(self.now_s(), self.name)

    def sleep_until(self, t_s: float, stop: threading.Event) -> bool:
        """Wait until `t_s` on this clock; False if `stop` was set first."""
        delay = t_s - self.now_s()
        return not stop.wait(delay) if delay > 0 else not stop.is_set()


class DataClock:
    """Time taken from the data ('sim' or 'vehicle'): it only moves when a message says so."""

    def __init__(self, name: str = "sim") -> None:
        if name not in ("sim", "vehicle"):
            raise ValueError(f"a data clock is 'sim' or 'vehicle', not {name!r}")
        self.name = name
        self._t_s: float | None = None
        self._lock = threading.Lock()

    def observe(self, stamp: Stamp) -> None:
        """Advance to a message's stamp; older stamps (reordered messages) never move it back."""
        if stamp.clock != self.name:
            raise ValueError(f"stamp on clock {stamp.clock!r} fed to a {self.name!r} clock")
        with self._lock:
            if self._t_s is None or stamp.t_s > self._t_s:
                self._t_s = stamp.t_s

    @property
    def started(self) -> bool:
        return self._t_s is not None

    def now_s(self) -> float:
        with self._lock:
            if self._t_s is None:
                raise RuntimeError(f"{self.name} clock has not received any data yet")
            return self._t_s

    def stamp(self) -> Stamp:
        return Stamp(self.now_s(), self.name)


def wall_time_s() -> float:
    """Wall time for transport-latency measurement only (comparable across local processes)."""
    return time.time()


DEFAULT_FUTURE_TOLERANCE_S = 1.0
# How many data seconds may pass per second of the receiver's monotonic clock, for clocks whose
# rate is known. The vehicle's clock runs on true seconds (5 % margin for crystal drift and
# latency jitter). Sim time runs at any multiple of real time in lockstep (bursts of frames are
# legitimate there), so only a real-time service bounds it by rate (`REALTIME_RATES`), and a
# lockstep receiver bounds it by its own sim time (`own`). 'wall' stamps come from each
# process's own monotonic clock and cannot be compared across processes.
MAX_DATA_RATE: Mapping[str, float] = {"vehicle": 1.05}
REALTIME_RATES: Mapping[str, float] = {"vehicle": 1.05, "sim": 1.05}


@dataclass(frozen=True)
class Arrival:
    """When a sample reached the receiver: its monotonic clock and, when it has one, its own data time."""

    mono_s: float
    own_s: float | None = None


LEARN_WINDOW_S = 10.0  # how long an on-time sample keeps vouching for the sender's clock
RELEARN_GRACE_S = 1.0  # after a silence longer than the window, how long the clock is learnt afresh
# A reference nobody confirms any more is re-anchored on the stream that leads it: this many
# leading samples in step with each other, after this long without one accepted sample. Was: an
# old first stamp (the sim's slow first render) was the only reference, every fresh frame led it
# and was refused for the whole 10 s window, longer than `up`'s 8 s stall limit (3 flights in 13).
REANCHOR_SAMPLES = 3
REANCHOR_AFTER_S = 1.0


class _Learnt:
    """One sender clock as the receiver learnt it: a sliding-window maximum of on-time samples.

    Each on-time sample (t, a) projects the sender's clock to t + rate * (a' - a) at a later
    arrival a'; the projection is the largest over the samples of the last `LEARN_WINDOW_S`, kept
    as a monotonic deque of t - rate * a (the largest value at the front).
    """

    __slots__ = ("rate", "window", "relearn_until_s", "accepted_mono_s", "leading")

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.window: deque[tuple[float, float]] = deque()  # (t_s - rate * mono_s, mono_s)
        self.relearn_until_s = -1.0
        self.accepted_mono_s = -float("inf")  # arrival of the newest accepted sample
        self.leading: list[tuple[float, float]] = []  # refused samples (t_s, mono_s) running in step

    def add(self, t_s: float, mono_s: float) -> None:
        v = t_s - self.rate * mono_s
        while self.window and self.window[-1][0] <= v:
            self.window.pop()
        self.window.append((v, mono_s))

    def accepted(self, mono_s: float) -> None:
        self.accepted_mono_s = max(self.accepted_mono_s, mono_s)
        self.leading.clear()

    def reanchors(self, t_s: float, mono_s: float, tolerance_s: float) -> bool:
        """Note a refused (leading) sample; True when the leading stream has become the reference.

        Only when no sample at all was accepted for `REANCHOR_AFTER_S`: while honest samples keep
        arriving on time, a forger's steady stream of future stamps stays refused.
        """
        if self.leading:
            last_t, last_mono = self.leading[-1]
            if abs((t_s - mono_s) - (last_t - last_mono)) > tolerance_s:
                self.leading.clear()  # not one clock running at our rate: start over
        self.leading.append((t_s, mono_s))
        if len(self.leading) < REANCHOR_SAMPLES or mono_s - self.accepted_mono_s < REANCHOR_AFTER_S:
            return False
        self.window.clear()
        for lt, lm in self.leading:
            self.add(lt, lm)
        self.accepted(mono_s)
        return True

    def projected(self, mono_s: float) -> float | None:
        while self.window and self.window[0][1] < mono_s - LEARN_WINDOW_S:
            self.window.popleft()
        return self.window[0][0] + self.rate * mono_s if self.window else None


class StampBound:
    """Judges sender stamps against the receiver's own clock at arrival; refuses the future.

    With `own` (a callable giving the receiver's time on `own_clock`, e.g. the sim's own sim time)
    a stamp may lead that time by at most `tolerance_s`. Without it the receiver learns each
    (source, clock) from the samples themselves: every on-time sample projects the sender's clock
    forward at the clock's largest rate (`rates`), the projection is the largest of those of the
    last `LEARN_WINDOW_S`, and a stamp may lead it by `tolerance_s`. A late, stale sample never
    lowers it (a backlog after an outage stays accepted); samples inside the tolerance are
    accepted but do not vouch, so a sender cannot ratchet the clock forward a tolerance per
    message. A stamp in the past is always accepted here (a restarted sim, a reordered sample):
    what is too old is the receiver's decision. The first sample of a source is trusted; after a
    silence longer than the window, so is everything in the next `RELEARN_GRACE_S` (a backlog
    flushed at once, then live samples, must relearn the clock rather than be refused). A
    reference that no accepted sample has confirmed for `REANCHOR_AFTER_S` gives way to a stream
    of `REANCHOR_SAMPLES` leading samples running in step (an old first stamp, a sender's clock
    that jumped): then the whole stream leads, not one forger beside honest samples.

    Thread-safe; one instance may be shared by several inboxes of a service, so a fast stream
    (states at 20 Hz) keeps the clock fresh for a slow one (heatmaps) on the same clock.
    """

    def __init__(self, tolerance_s: float = DEFAULT_FUTURE_TOLERANCE_S, *,
                 own: Callable[[], float | None] | None = None, own_clock: str | None = None,
                 rates: Mapping[str, float] = MAX_DATA_RATE) -> None:
        if not tolerance_s >= 0:
            raise ValueError(f"stamp tolerance must be >= 0 s, got {tolerance_s!r}")
        if (own is None) != (own_clock is None):
            raise ValueError("a receiver's own clock needs both `own` and `own_clock`")
        if own_clock is not None and own_clock not in CLOCKS:
            raise ValueError(f"own_clock {own_clock!r} is not one of {CLOCKS}")
        for clock, rate in rates.items():
            if clock not in CLOCKS or not rate > 0:
                raise ValueError(f"rate of clock {clock!r} must be > 0 data seconds per second, got {rate!r}")
        self.tolerance_s, self._own, self.own_clock = float(tolerance_s), own, own_clock
        self._rates = dict(rates)
        self._learnt: dict[tuple[str, str], _Learnt] = {}
        self._lock = threading.Lock()

    def arrive(self) -> Arrival:
        """Read the receiver's clocks now; called where a sample lands (cheap, any thread)."""
        own = self._own() if self._own is not None else None
        return Arrival(time.monotonic(), None if own is None else float(own))

    def judge(self, source: str, stamp: Stamp, arrival: Arrival) -> str | None:
        """None if the stamp is acceptable, else the reason it is refused."""
        if stamp.clock == self.own_clock:
            if arrival.own_s is not None and stamp.t_s > arrival.own_s + self.tolerance_s:
                return (f"stamp {stamp.t_s:.3f} s ({stamp.clock}) leads the receiver's clock "
                        f"{arrival.own_s:.3f} s by more than {self.tolerance_s:g} s")
            return None
        rate = self._rates.get(stamp.clock)
        if rate is None:
            return None
        t_s, mono_s = stamp.t_s, arrival.mono_s
        with self._lock:
            learnt = self._learnt.get((source, stamp.clock))
            if learnt is None:
                learnt = self._learnt[(source, stamp.clock)] = _Learnt(rate)
                learnt.add(t_s, mono_s)
                learnt.accepted(mono_s)
                return None
            projected = learnt.projected(mono_s)
            if projected is None:  # silent for longer than the window: learn afresh
                learnt.relearn_until_s = mono_s + RELEARN_GRACE_S
            if projected is None or mono_s <= learnt.relearn_until_s or t_s <= projected:
                learnt.add(t_s, mono_s)
                learnt.accepted(mono_s)
                return None
            if t_s <= projected + self.tolerance_s:
                learnt.accepted(mono_s)
                return None
            if learnt.reanchors(t_s, mono_s, self.tolerance_s):
                return None
        return (f"stamp {t_s:.3f} s ({stamp.clock}) leads the receiver's clock "
                f"(~{projected:.3f} s at arrival) by more than {self.tolerance_s:g} s")

    def forget(self, source: str | None = None) -> None:
        """Drop what was learnt (of one source, or all): the next sample is trusted afresh."""
        with self._lock:
            for key in [k for k in self._learnt if source is None or k[0] == source]:
                del self._learnt[key]


def own_time(clock: DataClock | WallClock) -> Callable[[], float | None]:
    """`own` for a `StampBound` from a receiver's clock: None until a data clock has started."""
    if isinstance(clock, DataClock):
        return lambda: clock.now_s() if clock.started else None
    return clock.now_s
