"""The world suite and the synthetic styles: each style draws what its name promises, from its seed.

Styles are generated small here (400-600 m at 0.5 m/px) to keep the file fast; the suite's own
worlds are checked for their size and form without generating them.
"""

from __future__ import annotations

import numpy as np
import pytest

from dovesei.shared.errors import ConfigError
from dovesei.sim.synthetic import generate as syn
from dovesei.sim.starts import generate_starts
from dovesei.sim.suite import DEFAULT_SUITE, suite
from dovesei.sim.synthetic.styles import STYLES
from dovesei.sim.synthetic.generate import (
    BARE_SOIL, GRASS, ROOF_FLAT, ROOF_PITCHED, SYNTHETIC_CLASSES, TREE, WATER, SyntheticParams, generate_city,
    parse_spec,
)
from dovesei.sim.world import load_world

NEW_STYLES = ("downtown", "villas", "desert", "coast", "parkland", "crowded")


def fractions(labels: np.ndarray) -> np.ndarray:
    return np.bincount(labels.ravel(), minlength=256) / labels.size


@pytest.fixture(scope="module")
def worlds() -> dict[str, np.ndarray]:
    return {style: generate_city(SyntheticParams(seed=3, size_m=600.0, gsd_m=0.5, style=style))[1]
            for style in ("city", *NEW_STYLES)}


def test_the_default_suite_is_dubai_and_the_six_styles_each_at_least_1_5_km() -> None:
    assert DEFAULT_SUITE[0] == "dubai" and suite("default") == DEFAULT_SUITE
    params = [parse_spec(spec) for spec in DEFAULT_SUITE[1:]]
    assert sorted(p.style for p in params) == sorted(NEW_STYLES)
    assert all(p.size_m >= 1500.0 for p in params)
    assert len({p.seed for p in params}) == len(params)  # not one seed for all
    with pytest.raises(ConfigError, match="default"):
        suite("everything")


def test_each_style_draws_what_its_name_says(worlds) -> None:
    f = {style: fractions(labels) for style, labels in worlds.items()}
    roofs = {s: v[ROOF_FLAT] + v[ROOF_PITCHED] for s, v in f.items()}
    green = {s: v[GRASS] + v[TREE] for s, v in f.items()}
    assert roofs["downtown"] > max(roofs["villas"], roofs["parkland"], roofs["desert"]) and roofs["downtown"] > 0.2
    assert f["downtown"][ROOF_FLAT] > 3 * f["villas"][ROOF_FLAT]  # blocks of offices and flats, not houses
    assert f["villas"][ROOF_PITCHED] > 2 * f["villas"][ROOF_FLAT] and f["villas"][ROOF_PITCHED] > 0.05
    assert f["desert"][BARE_SOIL] > 0.7 and roofs["desert"] < 0.15 and green["desert"] < 0.05
    assert f["coast"][WATER] > 0.2 and f["coast"][BARE_SOIL] > 0.02  # the sea and its beach
    assert green["parkland"] > 0.4 and green["parkland"] > green["downtown"] + 0.2 and green["parkland"] > green["city"]
    for labels in worlds.values():  # only the agreed class ids, nothing unlabelled
        present = set(np.flatnonzero(np.bincount(labels.ravel(), minlength=256)))
        assert present <= set(SYNTHETIC_CLASSES)


def test_a_style_is_a_function_of_its_seed() -> None:
    a = generate_city(SyntheticParams(seed=5, size_m=400.0, gsd_m=0.5, style="desert"))
    b = generate_city(SyntheticParams(seed=5, size_m=400.0, gsd_m=0.5, style="desert"))
    c = generate_city(SyntheticParams(seed=6, size_m=400.0, gsd_m=0.5, style="desert"))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[1], c[1])


def test_styles_differ_from_the_city_and_the_city_keeps_its_cache_name(tmp_path, worlds) -> None:
    assert all(not np.array_equal(worlds["city"], worlds[s]) for s in NEW_STYLES)
    city = syn.cache_path(SyntheticParams(seed=3), tmp_path).name
    assert city == f"synthetic-v{syn.GENERATOR_VERSION}-seed3-size1600m-gsd0.25m.npz"  # as before styles existed
    assert "-coast-" in syn.cache_path(SyntheticParams(seed=3, style="coast"), tmp_path).name


def test_style_specs_parse_and_bad_styles_are_named() -> None:
    assert parse_spec("synthetic:style=desert,seed=3") == SyntheticParams(seed=3, style="desert")
    assert parse_spec("synthetic") == SyntheticParams(style="city")
    with pytest.raises(syn.SyntheticWorldError, match="style 'moon'.*desert"):
        parse_spec("synthetic:style=moon")
    assert set(STYLES) == {"city", *NEW_STYLES}


def test_suite_worlds_load_and_give_starts(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("DOVESEI_CACHE", str(tmp_path))
    for style in NEW_STYLES:
        world = load_world(f"synthetic:style={style},seed=2,size_m=500,gsd_m=0.5")
        starts = generate_starts(world, 5, seed=0, alt_m=100.0)
        assert len(starts) == 5 and all(world.contains(s.x_m, s.y_m) for s in starts)
    assert load_world("dubai").labels is not None
