"""Clocks: every decision uses the clock of the data, never the host's speed.

In simulation the data clock is sim time, advanced by the messages themselves (a `DataClock`
fed from stamps); in flight it is the vehicle's clock, equally fed from its state messages; a
`WallClock` serves the real-time loops that must tick on their own. Each clock is named, and the
name travels in every `Stamp` so a reader knows which timeline a number belongs to.
"""

from __future__ import annotations

import threading
import time

from dovesei.shared.messages import Stamp


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
