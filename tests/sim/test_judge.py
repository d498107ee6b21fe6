"""The judge on hand-made label maps: safe, unsafe, tolerance, edge of the world, people, episodes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.sim.dynamics import Pose
from dovesei.sim.judge import EpisodeJudge, JudgeError, closest_unsafe_m, disk_safe_map, judge_landing, nearest_safe_m
from dovesei.sim.world import ClassInfo, World

GRASS, ROAD, PERSON = 1, 2, 3
CLASSES = {GRASS: ClassInfo("grass", True), ROAD: ClassInfo("road", False), PERSON: ClassInfo("person", False)}


def world_of(labels: np.ndarray, gsd_m: float = 0.25) -> World:
    return World(np.zeros((*labels.shape, 3), np.uint8), labels, gsd_m, CLASSES, "hand-made")


def grass(side_px: int = 200) -> np.ndarray:
    return np.full((side_px, side_px), GRASS, np.uint8)


def centre_of(world: World, row: int, col: int) -> tuple[float, float]:
    return world.pixel_to_world(row, col)


def test_all_safe() -> None:
    world = world_of(grass())
    v = judge_landing(world, 25.0, 25.0)
    assert v.outcome == "safe" and v.unsafe_frac == 0.0
    assert [(c.name, c.fraction) for c in v.classes] == [("grass", 1.0)]
    assert v.closest_unsafe_m is None
    # A 2 m radius on a 0.25 m grid: about pi * 8^2 pixel centres.
    assert abs(v.disk_px - math.pi * 64) < 10


def test_one_unsafe_pixel_within_tolerance_at_large_radius_but_not_small() -> None:
    labels = grass()
    labels[100, 103] = ROAD
    world = world_of(labels)
    x_m, y_m = centre_of(world, 100, 100)
    big = judge_landing(world, x_m, y_m, safety_radius_m=4.0)  # ~800 px: 1 px is 0.12 %
    assert big.outcome == "safe" and 0 < big.unsafe_frac <= 0.01
    assert {c.name for c in big.classes} == {"grass", "road"}
    small = judge_landing(world, x_m, y_m, safety_radius_m=1.0)  # ~50 px: 1 px is 2 %
    assert small.outcome == "unsafe" and small.unsafe_frac > 0.01
    assert small.closest_unsafe_m == pytest.approx(0.75)
    # Just outside the disk, the pixel no longer counts.
    assert judge_landing(world, x_m, y_m, safety_radius_m=0.7).unsafe_frac == 0.0


def test_a_person_in_the_disk_is_unsafe_even_within_tolerance() -> None:
    labels = grass()
    labels[100, 104:106] = PERSON  # two pixels, 1 m from the landing point
    world = world_of(labels)
    x_m, y_m = centre_of(world, 100, 100)
    v = judge_landing(world, x_m, y_m, safety_radius_m=4.0)
    assert v.unsafe_frac < 0.01  # the tolerance alone would have let it pass
    assert v.outcome == "unsafe" and "person" in v.reason
    # The same two pixels as road are forgiven as anti-aliasing.
    labels = labels.copy()  # a World freezes its arrays
    labels[100, 104:106] = ROAD
    assert judge_landing(world_of(labels), x_m, y_m, safety_radius_m=4.0).outcome == "safe"


def test_edge_of_the_world_counts_as_unsafe() -> None:
    world = world_of(grass())
    v = judge_landing(world, 0.5, 25.0)  # 0.5 m from the west edge: part of the 2 m disk is outside
    assert v.outcome == "unsafe"
    outside = [c for c in v.classes if c.name == "outside the world"]
    assert outside and 0.2 < outside[0].fraction < 0.5
    assert v.closest_unsafe_m is None  # the edge is not a labelled obstacle


def test_tiny_radius_still_judges_the_pixel_underneath() -> None:
    labels = grass()
    labels[50, 50] = ROAD
    world = world_of(labels)
    x_m, y_m = centre_of(world, 50, 50)
    v = judge_landing(world, x_m + 0.1, y_m - 0.1, safety_radius_m=0.0)
    assert v.disk_px == 1 and v.outcome == "unsafe"


def test_closest_unsafe_distance_and_search_limit() -> None:
    labels = grass(400)
    labels[200, 240] = ROAD  # 40 px = 10 m east of (200, 200)
    world = world_of(labels)
    x_m, y_m = centre_of(world, 200, 200)
    assert closest_unsafe_m(world, x_m, y_m, 50.0) == pytest.approx(10.0)
    assert closest_unsafe_m(world, x_m, y_m, 9.0) is None


def test_unlisted_label_ids_are_unsafe() -> None:
    labels = grass()
    labels[90:110, 90:110] = 77
    v = judge_landing(world_of(labels), *centre_of(world_of(labels), 100, 100))
    assert v.outcome == "unsafe" and v.classes[0].name == "unknown id 77"


def test_world_without_labels_is_flown_but_never_judged() -> None:
    world = World(np.zeros((10, 10, 3), np.uint8), None, 1.0, {}, "tiles")
    with pytest.raises(JudgeError, match="no label map"):
        judge_landing(world, 5.0, 5.0)
    judge = EpisodeJudge(world, time_limit_s=100.0)
    assert judge.check(Pose(5.0, 5.0, 60.0, t_s=0.0)) is None
    assert judge.check(Pose(5.0, 5.0, 19.0, t_s=10.0)) == "not_judged" and judge.verdict is None
    late = EpisodeJudge(world, time_limit_s=5.0)
    late.check(Pose(5.0, 5.0, 60.0, t_s=0.0))
    assert late.check(Pose(5.0, 5.0, 60.0, t_s=6.0)) == "timeout"


def test_episode_ends_on_handover_with_a_verdict_and_path_length() -> None:
    world = world_of(grass())
    judge = EpisodeJudge(world)
    assert judge.check(Pose(10.0, 10.0, 100.0, t_s=0.0)) is None
    assert judge.check(Pose(13.0, 14.0, 60.0, t_s=10.0)) is None
    assert judge.check(Pose(13.0, 14.0, 20.0, t_s=20.0)) == "safe"
    assert judge.path_length_m == pytest.approx(5.0)
    assert judge.sim_time_s == 20.0 and judge.verdict is not None
    # Once ended it stays ended and stops accumulating.
    assert judge.check(Pose(40.0, 40.0, 5.0, t_s=30.0)) == "safe"
    assert judge.path_length_m == pytest.approx(5.0)
    summary = judge.summary()
    assert summary["outcome"] == "safe" and summary["verdict"]["outcome"] == "safe"


def test_only_the_controllers_handover_ends_an_episode_as_a_landing() -> None:
    world = world_of(grass())
    judge = EpisodeJudge(world)
    assert judge.check(Pose(10.0, 10.0, 30.0, t_s=0.0), handover=False) is None
    # An aborted descent sinking through 20 m (the harsh-profile case) is no landing ...
    assert judge.check(Pose(10.0, 10.0, 19.0, t_s=1.0), handover=False) is None
    assert judge.check(Pose(10.0, 10.0, 12.0, t_s=2.0), handover=False) is None and judge.verdict is None
    # ... the controller's hand-over is, at whatever altitude it is declared.
    assert judge.check(Pose(10.0, 10.0, 18.0, t_s=3.0), handover=True) == "safe" and judge.verdict is not None
    crash = EpisodeJudge(world)
    crash.check(Pose(10.0, 10.0, 30.0, t_s=0.0), handover=False)
    assert crash.check(Pose(10.0, 10.0, 0.0, t_s=9.0), handover=False) == "unsafe"
    assert crash.crashed and crash.verdict is None and crash.summary()["crashed"] is True


def test_episode_timeout_and_out_of_world() -> None:
    world = world_of(grass())  # 50 m square
    judge = EpisodeJudge(world, time_limit_s=100.0)
    judge.check(Pose(25.0, 25.0, 100.0, t_s=5.0))
    assert judge.check(Pose(25.0, 25.0, 90.0, t_s=104.9)) is None
    assert judge.check(Pose(25.0, 25.0, 90.0, t_s=105.0)) == "timeout"
    gone = EpisodeJudge(world)
    gone.check(Pose(49.0, 25.0, 100.0))
    assert gone.check(Pose(50.5, 25.0, 100.0, t_s=1.0)) == "out_of_world"
    # Leaving the world while low is still out of world: it cannot be judged.
    low = EpisodeJudge(world)
    assert low.check(Pose(-1.0, 25.0, 10.0)) == "out_of_world"


def test_unsafe_handover() -> None:
    labels = grass()
    labels[:, 100:] = ROAD
    world = world_of(labels)
    judge = EpisodeJudge(world)
    x_m, y_m = centre_of(world, 100, 150)
    assert judge.check(Pose(x_m, y_m, 19.0)) == "unsafe"
    assert judge.verdict.classes[0].name == "road"


def test_nearest_safe_ground_is_where_the_judge_would_say_safe() -> None:
    labels = np.full((400, 400), ROAD, np.uint8)  # 100 m of road ...
    labels[100:140, 240:280] = GRASS  # ... with a 10 m lawn
    labels[118, 258] = PERSON  # and somebody on it, near its middle
    world = world_of(labels)
    safe = disk_safe_map(world)
    # Every pixel it calls safe, the judge calls safe, and the person's surroundings are not.
    rows, cols = np.nonzero(safe)
    assert rows.size > 0
    for r, c in zip(rows[::97], cols[::97]):
        assert judge_landing(world, *centre_of(world, int(r), int(c))).outcome == "safe"
    assert judge_landing(world, *centre_of(world, 118, 256)).outcome == "unsafe" and not safe[118, 256]
    # From the west edge of the map, level with the lawn's north edge: the lawn's 2 m disks begin
    # 2 m inside its west edge (x = 60 m + 2 m), 2 m south of its north edge.
    x_m, y_m = centre_of(world, 100, 0)
    d = nearest_safe_m(world, safe, x_m, y_m, 100.0)
    assert d == pytest.approx(math.hypot(62.0 - x_m, 2.0), abs=0.3)
    assert nearest_safe_m(world, safe, x_m, y_m, 30.0) is None  # not that close


def blocks_world(flip: bool = False) -> World:
    """600 x 600 m at 1 m/px: lawn blocks between roads, a flat-roof block, a pond, a few people."""
    labels = np.full((600, 600), 2, np.uint8)  # road
    for r in range(0, 600, 150):
        for c in range(0, 600, 150):
            labels[r + 12:r + 138, c + 12:c + 138] = 1  # lawn
    labels[162:288, 312:438] = 3  # flat roof
    labels[312:438, 162:288] = 4  # pond
    labels[60, 60] = labels[400, 500] = 5  # people
    classes = {1: ClassInfo("grass", True), 2: ClassInfo("road", False), 3: ClassInfo("roof_flat", False),
               4: ClassInfo("water", False), 5: ClassInfo("person", False)}
    if flip:
        classes = {k: ClassInfo(v.name, not v.safe) for k, v in classes.items()}
    image = np.zeros((600, 600, 3), np.uint8)
    return World(image, labels, 1.0, classes, name="blocks-flipped" if flip else "blocks")


def test_disk_safe_map_agrees_with_the_judge() -> None:
    world = blocks_world()
    safe = disk_safe_map(world)
    rng = np.random.default_rng(1)
    # Pixel centres (the map holds one verdict per pixel), some next to class edges and people.
    points = np.floor(rng.uniform(0.0, 600.0, (300, 2))) + 0.5
    points = np.vstack([points, [[60.5, 539.5], [62.5, 539.5], [13.5, 300.5], [11.5, 300.5], [0.5, 0.5]]])
    disagree = 0
    for x_m, y_m in points:
        row, col = world.pixel_index(x_m, y_m)
        disagree += bool(safe[row, col]) != (judge_landing(world, float(x_m), float(y_m)).outcome == "safe")
    assert disagree == 0


def test_disk_safe_map_reads_a_reversed_view_of_the_labels_as_the_labels() -> None:
    # A world built on a view (flipped, strided) of another array: the map is that of a copy.
    labels = blocks_world().labels
    flipped = World(np.zeros((600, 600, 3), np.uint8), labels[::-1], 1.0, blocks_world().classes, "view")
    copied = World(np.zeros((600, 600, 3), np.uint8), labels[::-1].copy(), 1.0, blocks_world().classes, "copy")
    safe = disk_safe_map(flipped)
    assert safe.any() and not safe.all()
    assert np.array_equal(safe, disk_safe_map(copied))
