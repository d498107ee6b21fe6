"""The judge counts separation: no person within 3 m, no vehicle within 5 m of the touchdown at hand-over."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.bench.stats import nearest_cell, separation_cell, separation_counts, summarise
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.dynamics import Pose
from dovesei.sim.judge import EpisodeJudge, JudgeError, judge_landing
from dovesei.sim.objects import PERSON, VEHICLE, ObjectLayer, Population
from dovesei.sim.starts import Start
from dovesei.sim.world import ClassInfo, World
from dovesei.shared.messages import VelocityCommand, Stamp
from dovesei.shared.mission import PERSON_SEPARATION_M, VEHICLE_SEPARATION_M

GRASS, ROAD, PERSON_ID, CAR_ID = 1, 2, 3, 4
CLASSES = {GRASS: ClassInfo("grass", True), ROAD: ClassInfo("road", False), PERSON_ID: ClassInfo("person", False),
           CAR_ID: ClassInfo("car", False)}


def world_with(rows: list[tuple], labels: np.ndarray | None = None) -> World:
    lab = np.full((400, 400), GRASS, np.uint8) if labels is None else labels
    pop = Population(ObjectLayer.build(rows), (PERSON_ID, CAR_ID)) if rows else None
    return World(np.zeros((*lab.shape, 3), np.uint8), lab, 0.25, CLASSES, "lawn", population=pop)


def person_at(x: float, y: float, speed: float = 0.0, path: float = 0.0, heading: float = 0.0) -> tuple:
    return (PERSON, x, y, heading, speed, path, 0.0, 0.5, 0.5, (200, 40, 40), False)


def car_at(x: float, y: float, heading: float = 0.0) -> tuple:
    return (VEHICLE, x, y, heading, 0.0, 0.0, 0.0, 4.5, 1.8, (30, 30, 34), False)


@pytest.mark.parametrize("gap_m, outcome", [(2.9, "unsafe"), (3.0, "safe"), (3.1, "safe")])
def test_a_person_closer_than_3_m_makes_the_landing_unsafe(gap_m: float, outcome: str) -> None:
    # Footprint distance: the person's centre is gap + its 0.25 m radius from the touchdown.
    world = world_with([person_at(50.0 + gap_m + 0.25, 50.0)])
    v = judge_landing(world, 50.0, 50.0)
    assert v.outcome == outcome and v.separation_violated == (outcome == "unsafe")
    assert v.nearest_person_m == pytest.approx(gap_m) and v.nearest_vehicle_m is None
    if outcome == "unsafe":
        assert "person 2.9 m" in v.reason and "separation 3 m" in v.reason


@pytest.mark.parametrize("gap_m, outcome", [(4.9, "unsafe"), (5.0, "safe")])
def test_a_vehicle_closer_than_5_m_makes_the_landing_unsafe(gap_m: float, outcome: str) -> None:
    world = world_with([car_at(50.0, 50.0 + 2.25 + gap_m)])  # facing north: its rear bumper is the nearest
    v = judge_landing(world, 50.0, 50.0)
    assert v.outcome == outcome and v.nearest_vehicle_m == pytest.approx(gap_m)


def test_separation_is_configurable_and_off_at_zero_but_nobody_may_be_in_the_disk() -> None:
    world = world_with([person_at(52.0, 50.0), car_at(50.0, 56.0)])  # person 1.75 m, car 3.75 m away
    assert judge_landing(world, 50.0, 50.0).outcome == "unsafe"
    off = judge_landing(world, 50.0, 50.0, person_separation_m=0.0, vehicle_separation_m=0.0)
    assert off.outcome == "unsafe" and not off.separation_violated  # the person stands in the 2 m disk
    assert "person 1.8 m" in off.reason
    far = world_with([person_at(52.6, 50.0), car_at(50.0, 56.0)])  # person 2.35 m: outside the disk
    assert judge_landing(far, 50.0, 50.0, person_separation_m=0.0, vehicle_separation_m=0.0).outcome == "safe"
    assert judge_landing(far, 50.0, 50.0, person_separation_m=2.0, vehicle_separation_m=3.0).outcome == "safe"
    assert judge_landing(far, 50.0, 50.0, person_separation_m=2.0, vehicle_separation_m=4.0).outcome == "unsafe"
    with pytest.raises(JudgeError, match="person_separation_m"):
        judge_landing(far, 50.0, 50.0, person_separation_m=-1.0)


def test_labelled_people_and_cars_count_too() -> None:
    labels = np.full((400, 400), GRASS, np.uint8)
    labels[200, 212] = PERSON_ID  # 3 m east of the centre of pixel (200, 200)
    labels[180:184, 200:208] = CAR_ID  # a car's label ~4.5 m north
    world = world_with([], labels)
    x, y = world.pixel_to_world(200, 200)
    v = judge_landing(world, x, y)
    assert v.nearest_person_m == pytest.approx(3.0) and v.nearest_vehicle_m == pytest.approx(4.25)
    assert v.outcome == "unsafe" and v.separation_violated


def test_the_episode_judge_measures_where_people_are_at_the_hand_over() -> None:
    # A walker passes the touchdown point: at t = 0 it is 10 m west; walking east at 1 m/s it is
    # level with the point after 10 s and 10 m east of it after 20 s.
    world = world_with([person_at(40.0, 50.0, speed=1.0, path=30.0, heading=math.pi / 2)])
    for t_s, outcome, near in ((0.0, "safe", 9.75), (10.0, "unsafe", 0.0), (20.0, "safe", 9.75)):
        judge = EpisodeJudge(world)
        judge.check(Pose(50.0, 50.0, 30.0, t_s=0.0), handover=False)
        assert judge.check(Pose(50.0, 50.0, 19.0, t_s=t_s), handover=True) == outcome
        assert judge.verdict.nearest_person_m == pytest.approx(near, abs=1e-6)


def descend(core: SimCore):
    """Straight down at 2 m/s, handing over at 20 m; the episode's result."""
    out = core.reset()
    while out.result is None:
        out = core.step(VelocityCommand("uav1", out.state.seq, Stamp(out.state.stamp.t_s, "sim"), (0.0, 0.0, 2.0),
                                        0.0, handover=bool(out.state.alt_agl_m <= 20.0)))
    return out.result


def test_the_episode_result_carries_the_distances() -> None:
    world = world_with([person_at(54.25, 50.0), car_at(50.0, 60.0)])
    r = descend(SimCore(world, Start(50.0, 50.0, 25.0), SimConfig(timing="reference", vehicle_profile="ideal")))
    assert r.nearest_person_valid and r.nearest_person_m == pytest.approx(4.0, abs=0.2)
    assert r.nearest_vehicle_valid and r.nearest_vehicle_m == pytest.approx(7.75, abs=0.2)
    assert r.outcome == "safe" and not r.separation_violated
    strict = descend(SimCore(world, Start(50.0, 50.0, 25.0), SimConfig(timing="reference", vehicle_profile="ideal",
                                                                       vehicle_separation_m=8.0)))
    assert strict.outcome == "unsafe" and strict.separation_violated
    assert SimConfig().person_separation_m == PERSON_SEPARATION_M and SimConfig().vehicle_separation_m == VEHICLE_SEPARATION_M


def test_summaries_count_violations_and_give_the_nearest_person() -> None:
    eps = [{"policy": "p", "outcome": "safe", "sim_time_s": 1.0, "path_length_m": 1.0, "wall_time_s": 1.0,
            "nearest_person_m": 7.0, "nearest_vehicle_m": None, "separation_violated": False},
           {"policy": "p", "outcome": "unsafe", "sim_time_s": 1.0, "path_length_m": 1.0, "wall_time_s": 1.0,
            "nearest_person_m": 1.5, "nearest_vehicle_m": 20.0, "separation_violated": True},
           {"policy": "p", "outcome": "safe", "sim_time_s": 1.0, "path_length_m": 1.0, "wall_time_s": 1.0,
            "nearest_person_m": None, "nearest_vehicle_m": None, "separation_violated": False},
           {"policy": "p", "outcome": "timeout", "sim_time_s": 9.0, "path_length_m": 1.0, "wall_time_s": 1.0,
            "nearest_person_m": None, "nearest_vehicle_m": None, "separation_violated": None}]
    s = summarise(eps, ["p"])["p"]
    assert (s["separation_judged"], s["separation_violations"]) == (3, 1)
    assert (s["median_nearest_person_m"], s["min_nearest_person_m"]) == (7.0, 1.5)  # nobody near: counts as 50
    assert separation_cell(s) == "1/3" and nearest_cell(s) == "7.0 / 1.5" and nearest_cell(s, "vehicle") == ">= 50 / 20.0"
    assert separation_counts([])["separation_judged"] == 0 and separation_cell(separation_counts([])) == "-"
