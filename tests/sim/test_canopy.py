"""A coarse class that lumps lawn with tree canopy is seen split by the world's image: the
perception reads the crowns the photo shows, the judge keeps the class as labelled."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dovesei.segmenter.sim_backend import View, profile_params, SimPerception
from dovesei.segmenter.prompts import REFERENCE_PROMPTS
from dovesei.segmenter.fusion import FusionConfig
from dovesei.bench import make_grid
from dovesei.bench.run import summary_markdown
from dovesei.bench.stats import canopy_counts, canopy_table, summarise
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.judge import JudgeError, canopy_figures, judge_landing
from dovesei.sim.starts import Start
from dovesei.sim.world import (CANOPY_CLASS_NAME, OPEN_CLASS_NAME, WorldError, load_world)

GSD_M = 0.5
SIDE_PX = 400  # 200 m
CROWNS = [(100 + 60 * i, 100 + 60 * j) for i in range(4) for j in range(4)]  # (row, col), 16 crowns
CROWN_R_PX = 8  # 4 m radius


def _folder(tmp_path: Path, canopy: object = True) -> Path:
    """A lawn (class 1, "vegetation", mixed) of mid-green with 16 dark crowns, a road (2) round it."""
    image = np.zeros((SIDE_PX, SIDE_PX, 3), np.uint8)
    image[...] = (110, 140, 70)  # RGB: a sunlit lawn
    for r, c in CROWNS:
        cv2.circle(image, (c, r), CROWN_R_PX, (30, 50, 25), -1)  # a crown and its shade
    labels = np.full((SIDE_PX, SIDE_PX), 1, np.uint8)
    labels[:40], labels[-40:], labels[:, :40], labels[:, -40:] = 2, 2, 2, 2
    image[labels == 2] = (90, 90, 95)
    folder = tmp_path / "w"
    folder.mkdir()
    cv2.imwrite(str(folder / "image.png"), image[:, :, ::-1])
    cv2.imwrite(str(folder / "labels.png"), labels)
    meta = {"gsd_m": GSD_M, "image": "image.png", "labels": "labels.png",
            "classes": {"1": {"name": "vegetation (lawns and trees, not separated)", "safe": False,
                              "canopy_from_image": canopy},
                        "2": {"name": "road", "safe": False}}}
    (folder / "world.json").write_text(json.dumps(meta))
    return folder


def test_the_perceived_world_splits_the_class_by_its_crowns_and_the_judge_keeps_it(tmp_path: Path) -> None:
    world = load_world(str(_folder(tmp_path)))
    seen = world.perceived()
    assert seen is world.perceived()  # built once
    names = {i: c.name for i, c in seen.classes.items()}
    canopy_id = next(i for i, n in names.items() if n == CANOPY_CLASS_NAME)
    open_id = next(i for i, n in names.items() if n == OPEN_CLASS_NAME)
    assert not seen.classes[canopy_id].safe and not seen.classes[open_id].safe  # the class's own flag
    for r, c in CROWNS:
        assert seen.labels[r, c] == canopy_id
        assert seen.labels[r, c + CROWN_R_PX + 6] == open_id  # 3 m beyond the crown's edge: lawn
    assert np.all(seen.labels[world.labels == 2] == 2)  # other classes as they are
    assert np.all(world.labels[world.labels != 2] == 1)  # the judge's labels untouched
    crown_px = len(CROWNS) * math.pi * CROWN_R_PX ** 2
    share = np.count_nonzero(seen.labels == canopy_id) / crown_px
    assert 1.0 <= share <= 2.0, share  # the crowns, grown by CANOPY_GROW_M for their sunlit side


def test_a_world_without_the_mark_is_its_own_perceived_world(tmp_path: Path) -> None:
    world = load_world(str(_folder(tmp_path, canopy=False)))
    assert world.perceived() is world


def test_a_bad_canopy_mark_is_named(tmp_path: Path) -> None:
    with pytest.raises(WorldError, match=r"classes\['1'\]: 'canopy_from_image' must be true or false, got 'yes'"):
        load_world(str(_folder(tmp_path, canopy="yes")))


def test_frames_carry_the_seen_classes_and_the_perception_reads_the_crowns_lower(tmp_path: Path) -> None:
    """The sim's frames and crops show the split (what a camera sees); the simulated perception then
    reads the crowns less safe than the lawn between them, which it could not while the class was
    one mix; the judge's verdict still reads the class as labelled."""
    world = load_world(str(_folder(tmp_path)))
    core = SimCore(world, Start(100.0, 100.0, 60.0, 0.0), SimConfig(vehicle_profile="ideal"))
    out = core.reset()
    truth = out.frame.truth
    names = {e.id: e.name for e in truth.classes}
    canopy_id = next(i for i, n in names.items() if n == CANOPY_CLASS_NAME)
    open_id = next(i for i, n in names.items() if n == OPEN_CLASS_NAME)
    assert 1 not in np.unique(truth.labels)  # the mixed class is not shown as such
    perception = SimPerception(profile_params("realistic"), seed=3)
    cam = SimConfig().camera
    view = View((100.0, 100.0), 60.0, cam.hfov_rad, 0.0, world.name)
    prob = perception.safe_probability(truth.labels, truth.classes, view, 0, REFERENCE_PROMPTS,
                                       FusionConfig(mode="dovesei"))
    on_crowns = float(np.median(prob[truth.labels == canopy_id]))
    on_lawn = float(np.median(prob[truth.labels == open_id]))
    assert on_crowns < on_lawn - 0.05, (on_crowns, on_lawn)
    assert core.judge.world is world and core.judge.world.labels[200, 200] == 1


def test_the_shipped_dubai_world_sees_its_vegetation_canopy() -> None:
    """Dubai's "vegetation (lawns and trees, not separated)" is marked: the image shows crowns in
    a share of it like the photo's (17 % on the tile), the rest reads as the lawn between them."""
    world = load_world("dubai")
    veg = [i for i, c in world.classes.items() if c.canopy_from_image]
    assert [world.classes[i].name for i in veg] == ["vegetation (lawns and trees, not separated)"]
    seen = world.perceived()
    names = {i: c.name for i, c in seen.classes.items()}
    in_veg = seen.labels[world.labels == veg[0]]
    share = np.mean([names[int(i)] == CANOPY_CLASS_NAME for i in in_veg[::97]])
    assert 0.08 <= share <= 0.3, share


def test_canopy_figures_measure_the_crowns_beside_a_landing_and_leave_the_verdict(tmp_path: Path) -> None:
    """The judge's canopy figures say how open the lumped ground under a landing was (a crown in
    the disk, the nearest crown) without changing its verdict; worlds that lump nothing get none."""
    world = load_world(str(_folder(tmp_path)))
    row, col = CROWNS[5]
    on_crown = canopy_figures(world, *world.pixel_to_world(row, col))
    assert on_crown == {"lumped": 1.0, "in_disk": 1.0, "nearest_m": 0.0}
    # 10 m from the crown's centre, on open lawn: the crown (4 m, grown by 1 m) is about 5 m off.
    x_m, y_m = world.pixel_to_world(row, col + 20)
    open_lawn = canopy_figures(world, x_m, y_m)
    assert open_lawn["lumped"] == 1.0 and open_lawn["in_disk"] == 0.0
    assert 4.0 <= open_lawn["nearest_m"] <= 6.0, open_lawn
    assert judge_landing(world, x_m, y_m).outcome == "unsafe"  # the class stays as labelled
    on_road = canopy_figures(world, *world.pixel_to_world(10, 10))
    assert on_road["lumped"] == 0.0 and on_road["in_disk"] == 0.0
    far = canopy_figures(world, x_m, y_m, search_radius_m=3.0)
    assert far["nearest_m"] is None  # no crown within the search radius
    (tmp_path / "plain").mkdir()
    assert canopy_figures(load_world(str(_folder(tmp_path / "plain", canopy=False))), x_m, y_m) is None
    with pytest.raises(JudgeError, match=r"landing point must be finite, got \(nan, "):
        canopy_figures(world, float("nan"), y_m)


def test_bench_summaries_count_unsafe_landings_beside_the_crowns() -> None:
    """Unsafe landings on the lumped class are counted with the canopy beside them; a bench whose
    records carry no canopy figures keeps its summary as it was."""
    base = {"policy": "p", "sim_time_s": 1.0, "path_length_m": 1.0, "wall_time_s": 1.0}
    eps = [{**base, "outcome": "unsafe", "canopy": {"lumped": 1.0, "in_disk": 0.0, "nearest_m": 11.5}},
           {**base, "outcome": "unsafe", "canopy": {"lumped": 0.6, "in_disk": 0.2, "nearest_m": 0.0}},
           {**base, "outcome": "unsafe", "canopy": {"lumped": 1.0, "in_disk": 0.0, "nearest_m": None}},
           {**base, "outcome": "unsafe", "canopy": {"lumped": 0.0, "in_disk": 0.0, "nearest_m": 3.0}},  # a road
           {**base, "outcome": "safe", "canopy": {"lumped": 0.0, "in_disk": 0.0, "nearest_m": 2.0}},
           {**base, "outcome": "timeout"}]
    s = summarise(eps, ["p"])["p"]
    assert (s["canopy_judged"], s["canopy_unsafe"]) == (5, 3)
    assert (s["canopy_unsafe_crown_in_disk"], s["canopy_unsafe_crown_near"]) == (1, 1)
    assert s["canopy_unsafe_median_crown_m"] == 11.5  # 0, 11.5 and none within 50 m (counted as 50)
    assert canopy_table({"p": s})[2] == "| p | 3/5 | 1 | 1 | 11.5 |"
    assert canopy_counts([base | {"outcome": "safe"}]) == {}
    assert canopy_table(summarise([base | {"outcome": "safe"}], ["p"])) == []
    config = make_grid(world_spec="dubai", episodes=1, seed=0, policies=("p",), noise=None, timing="real",
                       time_limit_s=60.0, start_alt_m=100.0, start_margin_m=50.0).config()
    page = summary_markdown({"config": config, "summary": {"p": s}})
    assert "## Unsafe landings on ground the labels do not separate from tree canopy" in page
    assert "| p | 3/5 | 1 | 1 | 11.5 |" in page
    assert "tree canopy" not in summary_markdown({"config": config, "summary": summarise([base | {"outcome": "safe"}],
                                                                                          ["p"])})
