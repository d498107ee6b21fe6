"""Fair serving of many vehicles: the slot logic alone, then four vehicles over real Zenoh.

The Zenoh test is the issue's figure, through the very function `dovesei bench-segmenter` reports
it with (`dovesei.benchmarks.fair`): four vehicles ask 2 Hz each from one segmenter that serves
~3 Hz in total (a slow fake backend: its sleep stands for the model's inference time; the
vehicles' pacing sleeps stand for their cameras); each must get 25 % +/- 5 % of the served frames,
and the overload must be reported at WARNING with per-vehicle rates.
"""

from __future__ import annotations

from dovesei.benchmarks.fair import measure_fairness
from dovesei.segmenter.fair import FairSlots

VEHICLES = ("uav1", "uav2", "uav3", "uav4")


def test_round_robin_serves_every_waiting_vehicle_once_per_turn() -> None:
    slots: FairSlots[int] = FairSlots()
    # uav1 floods (10 frames per round), uav2 sends one, uav3 two: each is still served once a round.
    served: list[str] = []
    for round_ in range(5):
        for i in range(10):
            slots.offer("uav1", 100 * round_ + i, now_s=float(round_))
        slots.offer("uav2", round_, now_s=float(round_))
        slots.offer("uav3", round_, now_s=float(round_))
        slots.offer("uav3", round_ + 1, now_s=float(round_))
        for _ in range(3):
            vehicle, item = slots.take()
            served.append(vehicle)
            if vehicle == "uav1":
                assert item == 100 * round_ + 9  # the newest frame of that vehicle
        assert slots.take() is None
    assert [served.count(v) for v in ("uav1", "uav2", "uav3")] == [5, 5, 5]
    stats = slots.stats()
    assert stats["uav1"] == {"offered": 50, "served": 5, "superseded": 45}
    assert stats["uav2"] == {"offered": 5, "served": 5, "superseded": 0}
    assert stats["uav3"]["superseded"] == 5


def test_round_robin_resumes_after_the_last_vehicle_served() -> None:
    slots: FairSlots[str] = FairSlots()
    for vehicle in ("a", "b", "c"):
        slots.offer(vehicle, vehicle, 0.0)
    assert slots.take() == ("a", "a")
    slots.offer("a", "a2", 0.1)  # a is back before b and c were served: it waits its turn
    assert [slots.take()[0] for _ in range(3)] == ["b", "c", "a"]


def test_vehicles_beyond_the_cap_are_refused_not_kept() -> None:
    slots: FairSlots[int] = FairSlots(max_vehicles=2)
    assert slots.offer("a", 1, 0.0) and slots.offer("b", 1, 0.0)
    assert not slots.offer("c", 1, 0.0)
    assert slots.offer("a", 2, 0.0)  # known vehicles still served
    assert set(slots.stats()) == {"a", "b"} and slots.waiting() == 2


def test_overload_is_reported_once_per_interval_with_per_vehicle_rates() -> None:
    slots: FairSlots[int] = FairSlots(report_interval_s=10.0)
    assert slots.overload_report(0.0) is None  # starts the interval
    for i in range(20):
        slots.offer("uav1", i, float(i) * 0.5)
    slots.take()
    assert slots.overload_report(5.0) is None  # interval not over yet
    text = slots.overload_report(10.0)
    assert text is not None and "uav1 served 0.10 Hz of 2.00 Hz offered (19 superseded)" in text
    assert slots.overload_report(20.0) is None  # nothing superseded since: no report
    # A frame left waiting (a stuck loop) is reported even with nothing superseded.
    slots.offer("uav2", 1, 21.0)
    assert "longest wait 9.0 s" in slots.overload_report(30.0)


def test_four_vehicles_at_2_hz_share_a_3_hz_segmenter_fairly() -> None:
    # The benchmark's own measurement (`dovesei bench-segmenter` reports it as `fairness`).
    result = measure_fairness(duration_s=10.0, n_vehicles=4, rate_hz=2.0, serve_hz=3.0)
    total = sum(result.served.values())
    assert total >= 18, f"only {total} heatmaps in 10 s (served ~3 Hz expected)"
    assert result.passed and all(0.20 <= share <= 0.30 for share in result.shares.values()), result.shares
    # The service's own per-vehicle counters agree, and the overload (8 Hz offered, ~3 served) was reported.
    per_vehicle = result.service_counts
    assert set(per_vehicle) == set(VEHICLES)
    assert all(per_vehicle[v]["superseded"] > 0 and per_vehicle[v]["served"] >= 4 for v in VEHICLES), per_vehicle
    assert result.overload_warnings and all(v in result.overload_warnings[0] for v in VEHICLES), result.overload_warnings
    figures = result.as_dict()
    assert figures["passed"] and set(figures["per_vehicle"]) == set(VEHICLES)
    assert 2.0 <= figures["served_hz_total"] <= 3.5, figures


def test_a_starved_vehicle_fails_the_fairness_figure() -> None:
    from dovesei.benchmarks.fair import FairnessResult

    result = FairnessResult(vehicles=VEHICLES, rate_hz=2.0, serve_hz=3.0, counted_s=10.0,
                            served={"uav1": 10, "uav2": 10, "uav3": 10, "uav4": 0}, service_counts={},
                            overload_warnings=())
    assert not result.passed and result.shares["uav4"] == 0.0
