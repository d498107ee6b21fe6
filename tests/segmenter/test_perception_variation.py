"""The simulated perception varies as CLIPSeg does (per episode, per world, per patch, with the
sun) and stays inside the real statistics; its fast per-frame path equals the plain formulas."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dovesei.perception_stats import world_stats
from dovesei.segmenter.fusion import FusionConfig
from dovesei.segmenter.prompts import REFERENCE_PROMPTS
from dovesei.segmenter import sim_backend
from dovesei.segmenter.sim_backend import (
    INSTANCE_LOOKS, SimPerception, View, episode_draw, ground_field, profile_params,
)
from dovesei.sim.synthetic.generate import SyntheticParams, generate_city
from dovesei.sim.world import load_world

HFOV = math.radians(73.0)
CLASSES = {1: "grass", 2: "road", 3: "roof_flat", 4: "tree", 5: "sidewalk", 6: "water"}


def _lawn_level(profile: str, seed: int, world: str, centre=(300.0, 200.0)) -> float:
    """Mean P(safe) of a view of pure lawn at 100 m."""
    lab = np.full((352, 352), 1, np.uint8)
    view = View(centre, 100.0, HFOV, 0.0, world)
    return float(SimPerception(profile_params(profile), seed=seed).safe_probability(
        lab, CLASSES, view, 5, REFERENCE_PROMPTS, FusionConfig(mode="dovesei")).mean())


@pytest.mark.parametrize("profile", ["realistic", "harsh"])
def test_one_class_reads_differently_across_episodes_and_worlds(profile: str) -> None:
    by_seed = [_lawn_level(profile, seed, "world-a") for seed in range(6)]
    by_world = [_lawn_level(profile, 2, w) for w in ("world-a", "world-b", "world-c", "world-d")]
    # Pure lawn: a per-class constant would give one level; the episode's calibration and the
    # lawn's own looks move it by several hundredths of P between episodes and between worlds.
    assert max(by_seed) - min(by_seed) > 0.04, by_seed
    assert max(by_world) - min(by_world) > 0.02, by_world
    assert _lawn_level(profile, 2, "world-b") == by_world[1]  # deterministic per (seed, world)
    clean = {_lawn_level("clean", seed, w) for seed in range(3) for w in ("world-a", "world-b")}
    assert len(clean) == 1  # the clean profile does not vary


def test_the_draws_stay_in_the_stated_ranges() -> None:
    for name in ("realistic", "harsh"):
        p = profile_params(name)
        draws = [episode_draw(p, seed, world) for seed in range(40) for world in ("a", "b")]
        factors = [d.logit_scale_factor for d in draws]
        offsets = [d.positive_offset_logit for d in draws]
        elevations = [d.sun_elevation_deg for d in draws]
        assert 1 - p.calibration_scale_spread <= min(factors) and max(factors) <= 1 + p.calibration_scale_spread
        assert max(abs(o) for o in offsets) <= p.calibration_offset_logit
        assert max(factors) - min(factors) > p.calibration_scale_spread  # the range is used, not a corner
        assert abs(min(elevations) - (p.sun_elevation_deg - p.sun_elevation_spread_deg)) < 8.0
        # Confusion tables differ between worlds, not between episodes over one world.
        assert episode_draw(p, 1, "a").confusion == episode_draw(p, 9, "a").confusion
        assert episode_draw(p, 1, "a").confusion != episode_draw(p, 1, "b").confusion
    # noise 0 switches every variation off: the same draw for every seed and world.
    quiet = {(d.logit_scale_factor, d.positive_offset_logit, d.confusion)
             for d in (episode_draw(profile_params("realistic", 0.0), s, w) for s in range(5) for w in "ab")}
    assert len(quiet) == 1


def test_a_patch_keeps_its_look_at_every_altitude_and_shadows_turn_with_the_sun() -> None:
    east, north = np.meshgrid(np.linspace(0.0, 200.0, 9), np.linspace(0.0, 200.0, 9))
    keys = np.array([3, 4])
    # The per-patch looks are a field on the ground alone: no altitude enters.
    assert np.array_equal(ground_field(east, north, keys, 25.0), ground_field(east, north, keys, 25.0))
    assert np.std(ground_field(east, north, keys, 25.0)) > 0.5
    assert {"bare_ground", "tree"} == set(INSTANCE_LOOKS["lawn"])  # dry grass reads as soil
    # A roof block on lawn: its shadow points elsewhere three hours later.
    lab = np.full((352, 352), 1, np.uint8)
    lab[150:200, 150:200] = 3
    perception = SimPerception(profile_params("realistic"), seed=5)
    shadow = sim_backend.INDEX["shadow"]

    def shade(t_s: float) -> np.ndarray:
        return perception.fractions(lab, CLASSES, View((0.0, 0.0), 40.0, HFOV, 0.0, "w", t_s))[..., shadow]

    now, later = shade(0.0), shade(3 * 3600.0)
    assert now.sum() > 1.0 and later.sum() > 1.0
    assert np.abs(now - later).sum() > 0.3 * now.sum()
    assert np.array_equal(shade(0.0), now)


# --- the fast per-frame path against the plain formulas it replaces ---------------------------


def _world_views(n: int = 6):
    world = load_world("dubai")
    names = {cid: c.name for cid, c in world.classes.items()}
    from dovesei.sim.camera import CameraModel, render

    cam = CameraModel()
    rng = np.random.default_rng(4)
    for k in range(n):
        alt = (100.0, 50.0, 22.0)[k % 3]
        x, y = rng.uniform(0.2, 0.8) * world.width_m, rng.uniform(0.2, 0.8) * world.height_m
        yaw = rng.uniform(0.0, 2.0 * math.pi)
        _, labels, _ = render(world, x, y, alt, yaw, cam, with_image=False)
        yield labels, names, View((x, y), alt, cam.hfov_rad, yaw, world.name, 10.0 * k)


def _plain_shadow(perception: SimPerception, labels: np.ndarray, names: dict, view: View) -> np.ndarray:
    """The shadow rule pixel by pixel: every caster height in view throws each pixel at least
    that tall half and all of its shadow length away from the sun onto lower in-world ground."""
    tables = perception._tables(names)
    px_h = tables.height_m[labels]
    draw = perception.draw(view.world)
    az = draw.sun_azimuth_rad + sim_backend.SUN_RATE_RAD_S * view.time_s
    east, north = -math.sin(az), -math.cos(az)
    c, s = math.cos(view.yaw_rad), math.sin(view.yaw_rad)
    right, forward = c * east - s * north, s * east + c * north
    m_px = sim_backend.footprint.metres_per_px(view.alt_agl_m, view.hfov_rad, 352)
    out = np.zeros(labels.shape, bool)
    ys, xs = np.mgrid[0:352, 0:352]
    for h in np.unique(px_h[px_h > 0.5]):
        for frac in (0.5, 1.0):
            dx = int(round(right * h / math.tan(math.radians(draw.sun_elevation_deg)) * frac / m_px))
            dy = int(round(-forward * h / math.tan(math.radians(draw.sun_elevation_deg)) * frac / m_px))
            sy, sx = ys - dy, xs - dx
            ok = (sy >= 0) & (sy < 352) & (sx >= 0) & (sx < 352)
            cast = np.zeros(labels.shape, bool)
            cast[ok] = px_h[sy[ok], sx[ok]] >= h
            out |= cast & (px_h < h) & (labels != 255)
    return out


def test_fast_fractions_and_shadows_equal_the_plain_formulas() -> None:
    perception = SimPerception(profile_params("realistic"), seed=3)
    quiet = SimPerception(dataclasses.replace(profile_params("realistic"), shadow=0.0), seed=3)
    for labels, names, view in _world_views():
        tables = perception._tables(names)
        assert np.array_equal(perception._shadow_mask(tables.code_lut[labels], tables, view, labels.shape) > 0,
                              _plain_shadow(perception, labels, names, view))
        # Without shadows: each cell's fractions are the mean of its pixels' class mixes.
        plain = tables.mix[labels].reshape(44, 8, 44, 8, -1).mean(axis=(1, 3))
        assert np.abs(quiet.fractions(labels, names, view) - plain).max() < 1e-12


def _plain_value_noise(x: np.ndarray, y: np.ndarray, z: float, keys: np.ndarray) -> np.ndarray:
    """Trilinear value noise with smoothstep weights, each point's eight corners hashed on their own."""
    fx, fy, fz = np.floor(x), np.floor(y), math.floor(z)
    tx, ty, tz = ((t * t * (3.0 - 2.0 * t)) for t in (x - fx, y - fy, z - fz))
    ix, iy = fx.astype(np.int64), fy.astype(np.int64)
    out = np.zeros((keys.size,) + x.shape)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty) * (tz if dz else 1.0 - tz)
                out += w * sim_backend._hash_unit(ix + dx, iy + dy, np.full_like(ix, fz + dz), keys.reshape(-1, 1, 1))
    return out


def test_the_cached_lattice_gives_the_plain_value_noise() -> None:
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-8.0, 8.0, (16, 16)), rng.uniform(100.0, 116.0, (16, 16))
    keys = np.arange(5, dtype=np.int64) * 977
    for z in (2.3, -0.7, 0.0):
        # A new view, the same again (read from the cache), a little moved (still inside the kept
        # region), far moved (a new region).
        for shift in (0.0, 0.0, 2.5, 40.0):
            fast = sim_backend._noise_octaves(x + shift, y, ((1.0, z, keys, 1.0),))
            assert np.abs(fast - _plain_value_noise(x + shift, y, z, keys)).max() < 1e-12
    # Points spread over a box too large to tabulate are hashed per point, to the same values.
    far = sim_backend._noise_octaves(x * 50, y, ((1.0, 2.3, keys, 1.0),))
    assert np.abs(far - _plain_value_noise(x * 50, y, 2.3, keys)).max() < 1e-12
    # Octaves add up, each at its own scale, height and keys (here one tabulated, one hashed per point).
    both = sim_backend._noise_octaves(x, y, ((1.0, 2.3, keys, 0.75), (0.02, 19.6, keys + 7, 0.45)))
    plain = 0.75 * _plain_value_noise(x, y, 2.3, keys) + 0.45 * _plain_value_noise(x / 0.02, y / 0.02, 19.6, keys + 7)
    assert np.abs(both - plain).max() < 1e-12
    # The cache stays bounded however many fields pass through it.
    for k in range(40):
        sim_backend._noise_octaves(x + 100.0 * k, y, ((1.0, 1.5, keys + k, 1.0),))
    assert len(sim_backend._lattice_cache) <= sim_backend._LATTICE_CACHE_ENTRIES


# --- inside the real statistics -----------------------------------------------------------------


@pytest.fixture(scope="module")
def small_suite():
    """Dubai (shipped) and a 600 m world of each synthetic style: the suite's kinds of ground."""
    from dovesei.sim.synthetic.classes import SYNTHETIC_CLASSES
    from dovesei.sim.world import ClassInfo, World

    classes = {cid: ClassInfo(name, safe) for cid, (name, safe) in SYNTHETIC_CLASSES.items()}
    worlds = [load_world("dubai")]
    for i, style in enumerate(("downtown", "villas", "desert", "coast", "parkland")):
        image, labels = generate_city(SyntheticParams(seed=11 + i, size_m=600.0, gsd_m=0.5, style=style))
        worlds.append(World(image, labels, 0.5, classes, name=f"test-{style}"))
    return worlds


@pytest.mark.parametrize("profile", ["realistic", "harsh"])
def test_perception_stats_stay_inside_the_real_statistics(small_suite, profile: str) -> None:
    """The authors' logs: the reference's dynamic threshold has a median of 0.51 and went below
    0.85 on 99.8 % of frames; PEACE: the reference prompts found a safe zone 57 % of the time.
    Over the suite's kinds of ground, for three episodes (seeds) each, the frame-weighted median
    threshold must stay within 0.51 +- 0.10 and the lowered share >= 0.95: what the profiles are
    calibrated to. The share of frames whose target core is safe is a looser check (it follows
    the scene mix, and 96 frames sample it to +-0.1 at 2 sigma): within 0.35-0.85, i.e. neither
    far better than real CLIPSeg (which would flatter every policy) nor far worse."""
    for seed in (1, 2, 3):
        stats = [world_stats(w, profile_params(profile), 8, 2, seed) for w in small_suite]
        frames = sum(s.frames for s in stats)

        def mean(key: str) -> float:
            vals = [(getattr(s, key), s.frames) for s in stats if not math.isnan(getattr(s, key))]
            return sum(v * f for v, f in vals) / sum(f for _, f in vals)

        assert frames == 96
        assert 0.41 <= mean("median_threshold") <= 0.61, (seed, mean("median_threshold"))
        assert mean("lowered_fraction") >= 0.95
        assert 0.35 <= mean("core_precision") <= 0.85, (seed, mean("core_precision"))
