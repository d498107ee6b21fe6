"""Fair serving of many vehicles: one newest-frame slot per vehicle, served round-robin.

A ground-station segmenter subscribed to `dovesei/*/camera` gets frames from every vehicle. With a
single newest-frame slot for all of them, the vehicle whose frames happen to arrive last before
each inference wins every time and another can get nothing at all (measured: one of four vehicles
got 0 heatmaps in 40 s). Here every vehicle has its own slot:

    frame of vehicle v --offer--> slot[v]  (a newer frame replaces the waiting one: counted
                                            as superseded for v; the controller wants the newest)
    take() --> the next vehicle after the last one served, in order of first appearance, whose
               slot holds a frame (round-robin: with N vehicles waiting, each is served once per
               N inferences, whatever their frame rates, so none can starve)

Counts per vehicle (offered, served, superseded) go into the service stats; `overload_report`
returns, at most once per interval, a summary when frames were superseded (the segmenter serves
less than it is offered) or a frame waited longer than `starve_after_s`; the service logs it at
WARNING. Pure logic, no Zenoh: time is passed in (monotonic seconds).

Micro-batching (the waiting frames of several vehicles through one encoder pass) is not done: on
the team's 2 CPU cores a batch of 2 rd64 frames cost 12.3 s per frame against 13.8 s one at a
time, measured once with the machine loaded ~4x over its cores: within the noise, and it would
double every frame's latency. `ClipSegBackend.logits_batch` takes N frames for when a GPU makes
batching pay; measure there before wiring it in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")

OVERLOAD_REPORT_INTERVAL_S = 10.0
# A frame waiting this long is called out even when nothing was superseded (a stuck loop).
STARVE_AFTER_S = 5.0
# Vehicles one segmenter keeps slots and counters for: a sender inventing vehicle ids must not
# grow them without end (frames of further vehicles are refused, and the service counts them).
MAX_VEHICLES = 64


@dataclass
class VehicleCounts:
    """What happened to one vehicle's frames (cumulative, and since the last report)."""

    offered: int = 0
    served: int = 0
    superseded: int = 0  # replaced in the slot by a newer frame before being served
    served_since_report: int = 0
    offered_since_report: int = 0
    superseded_since_report: int = 0

    def as_dict(self) -> dict[str, int]:
        return {"offered": self.offered, "served": self.served, "superseded": self.superseded}


@dataclass
class _Slot(Generic[T]):
    item: T
    waiting_since_s: float  # when the slot became non-empty (kept when a newer frame replaces it)


@dataclass
class FairSlots(Generic[T]):
    """Newest item per vehicle, taken round-robin across vehicles (see the module docstring)."""

    report_interval_s: float = OVERLOAD_REPORT_INTERVAL_S
    starve_after_s: float = STARVE_AFTER_S
    max_vehicles: int = MAX_VEHICLES
    counts: dict[str, VehicleCounts] = field(default_factory=dict)
    _slots: dict[str, _Slot[T]] = field(default_factory=dict)
    _order: list[str] = field(default_factory=list)  # vehicles in order of first appearance
    _next: int = 0  # index in _order where the round-robin search starts
    _last_report_s: float | None = None

    def offer(self, vehicle: str, item: T, now_s: float) -> bool:
        """Put `item` in `vehicle`'s slot; False (nothing kept) for a vehicle beyond `max_vehicles`."""
        counts = self.counts.get(vehicle)
        if counts is None:
            if len(self._order) >= self.max_vehicles:
                return False
            counts = self.counts[vehicle] = VehicleCounts()
            self._order.append(vehicle)
        counts.offered += 1
        counts.offered_since_report += 1
        slot = self._slots.get(vehicle)
        if slot is None:
            self._slots[vehicle] = _Slot(item, now_s)
        else:
            counts.superseded += 1
            counts.superseded_since_report += 1
            slot.item = item  # the wait keeps counting from the first unserved frame
        return True

    def take(self) -> tuple[str, T] | None:
        """The next vehicle's newest frame (round-robin), or None when every slot is empty."""
        n = len(self._order)
        for step in range(n):
            index = (self._next + step) % n
            vehicle = self._order[index]
            slot = self._slots.pop(vehicle, None)
            if slot is not None:
                self._next = (index + 1) % n
                counts = self.counts[vehicle]
                counts.served += 1
                counts.served_since_report += 1
                return vehicle, slot.item
        return None

    def waiting(self) -> int:
        return len(self._slots)

    def longest_wait_s(self, now_s: float) -> float:
        return max((now_s - s.waiting_since_s for s in self._slots.values()), default=0.0)

    def stats(self) -> dict[str, dict[str, int]]:
        return {vehicle: self.counts[vehicle].as_dict() for vehicle in self._order}

    def overload_report(self, now_s: float) -> str | None:
        """A one-line summary when frames were superseded or one waited too long since the last
        report, at most once per `report_interval_s`; None otherwise (the counters keep going)."""
        if self._last_report_s is None:
            self._last_report_s = now_s
            return None
        elapsed_s = now_s - self._last_report_s
        if elapsed_s < self.report_interval_s:
            return None
        superseded = sum(c.superseded_since_report for c in self.counts.values())
        longest_s = self.longest_wait_s(now_s)
        text = None
        if superseded or longest_s > self.starve_after_s:
            per_vehicle = ", ".join(
                f"{v} served {c.served_since_report / elapsed_s:.2f} Hz of {c.offered_since_report / elapsed_s:.2f} Hz "
                f"offered ({c.superseded_since_report} superseded)"
                for v, c in ((v, self.counts[v]) for v in self._order))
            served = sum(c.served_since_report for c in self.counts.values())
            text = (f"overload: {len(self._order)} vehicle(s) offered more frames than the segmenter serves "
                    f"({served / elapsed_s:.2f} Hz served in {elapsed_s:.0f} s, {superseded} frames superseded, "
                    f"longest wait {longest_s:.1f} s): {per_vehicle}")
        for counts in self.counts.values():
            counts.served_since_report = counts.offered_since_report = counts.superseded_since_report = 0
        self._last_report_s = now_s
        return text
