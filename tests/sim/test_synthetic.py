"""Tests of the procedural city world (dovesei.sim.synthetic).

Small worlds (300-600 m at 0.3 m/px) keep the file fast; one test builds the default world to
check its dimensions (no timing assertion: the machine is shared)."""

from __future__ import annotations

import logging
import zipfile

import cv2
import numpy as np
import pytest

from dovesei.shared.errors import ConfigError
from dovesei.sim.synthetic import generate as syn
from dovesei.sim.synthetic.generate import (
    BARE_SOIL, CAR, GRASS, PERSON, ROAD, SIDEWALK, SYNTHETIC_CLASSES, TREE, WATER,
    SyntheticParams, SyntheticWorldError, generate_city, load_or_generate, parse_spec,
)

SMALL = SyntheticParams(seed=3, size_m=300.0, gsd_m=0.3)
MID = SyntheticParams(seed=0, size_m=600.0, gsd_m=0.3)


@pytest.fixture(scope="module")
def small_world():
    return generate_city(SMALL)


@pytest.fixture(scope="module")
def mid_world():
    return generate_city(MID)


def _luma(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def test_class_table_is_the_agreed_one():
    assert sorted(SYNTHETIC_CLASSES) == list(range(1, 14))
    safe = {name for name, ok in SYNTHETIC_CLASSES.values() if ok}
    assert safe == {"plaza", "parking_lot", "grass", "sports_field", "bare_soil"}
    assert SYNTHETIC_CLASSES[13] == ("person", False)


def test_output_types_and_shapes(small_world):
    image, labels = small_world
    assert image.shape == (1000, 1000, 3) and image.dtype == np.uint8
    assert labels.shape == (1000, 1000) and labels.dtype == np.uint8


def test_same_seed_same_bytes_different_seed_differs(small_world):
    image, labels = small_world
    again_image, again_labels = generate_city(SyntheticParams(seed=3, size_m=300.0, gsd_m=0.3))
    assert again_image.tobytes() == image.tobytes()
    assert again_labels.tobytes() == labels.tobytes()
    other_image, other_labels = generate_city(SyntheticParams(seed=4, size_m=300.0, gsd_m=0.3))
    assert (other_labels != labels).mean() > 0.2
    assert other_image.tobytes() != image.tobytes()


def test_labels_only_known_ids_never_zero(small_world, mid_world):
    for _, labels in (small_world, mid_world):
        present = set(np.unique(labels).tolist())
        assert present <= set(SYNTHETIC_CLASSES), present
        assert 0 not in present


def test_every_class_present_in_a_mid_size_world(mid_world):
    _, labels = mid_world
    counts = np.bincount(labels.ravel(), minlength=14)
    missing = [SYNTHETIC_CLASSES[c][0] for c in SYNTHETIC_CLASSES if counts[c] == 0]
    assert not missing, f"classes absent: {missing}"


def test_drawn_colours_match_labels(mid_world):
    image, labels = mid_world
    classes = (GRASS, TREE, WATER, ROAD, SIDEWALK, BARE_SOIL)
    mean = {c: image[labels == c].reshape(-1, 3).mean(axis=0) for c in classes}
    r, g, b = mean[GRASS]
    assert g > r + 10 and g > b + 25, f"grass is not green: {mean[GRASS]}"
    assert mean[WATER][2] > mean[WATER][0] + 10, f"water is not bluish: {mean[WATER]}"
    assert mean[TREE][1] > mean[TREE][0] and mean[TREE][1] > mean[TREE][2]
    assert _luma(mean[TREE]) < _luma(mean[GRASS]) - 10, "tree canopy should be darker than lawn"
    assert _luma(mean[ROAD]) < 110, f"asphalt too light: {mean[ROAD]}"
    assert _luma(mean[SIDEWALK]) > _luma(mean[ROAD]) + 30
    assert mean[BARE_SOIL][0] > mean[BARE_SOIL][2] + 15, "soil should be brownish"


def test_people_present_small_and_on_walkable_ground(mid_world):
    image, labels = mid_world
    person = (labels == PERSON).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(person, connectivity=8)
    areas_m2 = stats[1:, cv2.CC_STAT_AREA] * MID.gsd_m**2
    assert n - 1 >= 30, f"only {n - 1} people in a 600 m world"
    assert np.median(areas_m2) <= 0.5, "a person seen from above is ~0.5 m across"
    assert areas_m2.max() <= 4.0, "person blobs should stay tiny (small groups at most)"


def test_safe_fraction_in_range_and_spread_out(mid_world):
    _, labels = mid_world
    frac = syn.safe_fraction(labels)
    assert 0.2 <= frac <= 0.42, frac
    # A 2 m-radius safe disk is reachable within 150 m from anywhere in the world.
    safe = np.isin(labels, [c for c, (_, ok) in SYNTHETIC_CLASSES.items() if ok]).astype(np.uint8)
    r_px = int(round(2.0 / MID.gsd_m))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r_px + 1, 2 * r_px + 1))
    landable = cv2.erode(safe, disk)
    far_px = cv2.distanceTransform(1 - landable, cv2.DIST_L2, 5).max()
    assert far_px * MID.gsd_m < 150.0


def test_trees_cover_what_is_under_them_and_cars_sit_on_paved_ground(mid_world):
    _, labels = mid_world
    # Cars stand on roads, parking lots or driveways, never in water.
    car = labels == CAR
    ring = cv2.dilate(car.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool) & ~car
    around = np.bincount(labels[ring], minlength=14)
    assert around[WATER] < 0.01 * around.sum()
    assert (around[ROAD] + around[syn.PARKING_LOT] + around[SIDEWALK]) > 0.6 * around.sum()


def test_default_world_dimensions():
    params = SyntheticParams()
    assert (params.size_m, params.gsd_m, params.side_px) == (1600.0, 0.25, 6400)
    image, labels = generate_city(params)
    assert image.shape == (6400, 6400, 3) and labels.shape == (6400, 6400)
    assert labels.min() >= 1 and labels.max() <= 13


@pytest.mark.parametrize("kwargs", [
    {"size_m": 150.0}, {"size_m": 6000.0}, {"gsd_m": 0.01}, {"gsd_m": 2.0},
    {"gsd_m": float("nan")}, {"seed": -1}, {"seed": 1.5}, {"seed": True},
    {"size_m": 5000.0, "gsd_m": 0.05},  # 100k px a side: refused, not an out-of-memory crash
])
def test_params_validation(kwargs):
    with pytest.raises(SyntheticWorldError):
        SyntheticParams(**kwargs)


def test_parse_spec_accepts_the_cli_forms():
    assert parse_spec("synthetic") == SyntheticParams()
    assert parse_spec("synthetic:seed=7") == SyntheticParams(seed=7)
    assert parse_spec(" synthetic:gsd_m=0.3, size_m=800 ,seed=2") == SyntheticParams(2, 800.0, 0.3)


@pytest.mark.parametrize("spec, words", [
    ("synthetic:colour=red", ["unknown key", "colour"]),
    ("synthetic:seed=abc", ["seed", "abc"]),
    ("synthetic:size_m=big", ["size_m"]),
    ("synthetic:seed", ["key=value"]),
    ("synthetic:seed=1,seed=2", ["twice"]),
    ("synthetic:", ["nothing after"]),
    ("world:seed=1", ["synthetic"]),
    ("synthetic:size_m=10", ["size_m", "200"]),
    ("synthetic:gsd_m=5", ["gsd_m"]),
])
def test_parse_spec_errors_are_clear(spec, words):
    with pytest.raises(SyntheticWorldError) as err:
        parse_spec(spec)
    assert isinstance(err.value, ValueError) and isinstance(err.value, ConfigError)
    for word in words:
        assert word in str(err.value), str(err.value)


def test_cache_round_trip(tmp_path, monkeypatch, small_world):
    image, labels = load_or_generate(SMALL, cache_dir=tmp_path)
    path = syn.cache_path(SMALL, tmp_path)
    assert path.exists() and path.parent == tmp_path
    for part in ("seed3", "size300m", "gsd0.3m", f"v{syn.GENERATOR_VERSION}"):
        assert part in path.name
    assert not [p for p in tmp_path.iterdir() if p != path], "temporary files left behind"

    def must_not_generate(params):
        raise AssertionError("the cached world should have been loaded")

    monkeypatch.setattr(syn, "generate_city", must_not_generate)
    image2, labels2 = load_or_generate(SMALL, cache_dir=tmp_path)
    np.testing.assert_array_equal(image2, small_world[0])
    np.testing.assert_array_equal(labels2, small_world[1])


@pytest.mark.parametrize("damage", ["garbage", "truncated", "wrong_shape"])
def test_corrupt_cache_is_regenerated_with_a_warning(tmp_path, caplog, small_world, damage):
    path = syn.cache_path(SMALL, tmp_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if damage == "garbage":
        path.write_bytes(b"not a zip file at all")
    elif damage == "truncated":
        with open(path, "wb") as fh:
            np.savez(fh, image=small_world[0], labels=small_world[1])
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        with open(path, "wb") as fh:
            np.savez(fh, image=np.zeros((10, 10, 3), np.uint8), labels=np.zeros((10, 10), np.uint8))
    with caplog.at_level(logging.WARNING, logger="dovesei.sim.synthetic"):
        image, labels = load_or_generate(SMALL, cache_dir=tmp_path)
    assert any("regenerating" in r.getMessage() for r in caplog.records)
    np.testing.assert_array_equal(labels, small_world[1])
    np.testing.assert_array_equal(image, small_world[0])
    # The damaged file was replaced by a good one.
    with np.load(path) as z:
        np.testing.assert_array_equal(z["labels"], small_world[1])
    assert zipfile.is_zipfile(path)


def test_default_cache_dir_follows_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("DOVESEI_CACHE", str(tmp_path / "d"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert syn.default_cache_dir() == tmp_path / "d" / "worlds"
    monkeypatch.delenv("DOVESEI_CACHE")
    assert syn.default_cache_dir() == tmp_path / "x" / "dovesei" / "worlds"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "h"))
    assert syn.default_cache_dir() == tmp_path / "h" / ".cache" / "dovesei" / "worlds"
