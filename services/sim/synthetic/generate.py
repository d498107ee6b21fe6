"""Procedural aerial worlds: an orthophoto-like RGB image and its per-pixel class map.

This is the simulator's embedded default world (DESIGN.md section 7a) and the synthetic part of
the world suite. Everything is derived from `SyntheticParams` (seed, size, ground sample
distance, style), so the same params always give the same bytes, and `load_or_generate` caches
the result on disk. This module is the front door: the spec, the cache and the pipeline; the
work is done by concern in

    classes        class ids, which are safe, palettes and texture tables
    canvas         the drawing surface (image, labels, heights with one polygon) and geometry
    layout         road grid, blocks, river (`CityStyle` sets the mix of block kinds)
    objects, blocks, parks, streets   what is drawn
    styles         the suite's styles: other block mixes, the coast's sea, the open desert
    render         shadows, textures, colour grading, blur

Data flow of `generate_city` (the city styles):

    seed -> layout (road grid, blocks of one kind each, optional river, sun direction)
         -> drawing pass on a `Canvas` (flat colours into RGB, class ids into labels and object
            heights into a height map, all with the SAME polygons; shadow casters are queued)
         -> trees last (their canopy covers, and relabels, whatever is under them)
         -> shadow pass (queued casters rasterised into a "shadow height" map; a pixel is in
            shadow where something taller stands between it and the sun)
         -> texture pass (per-class noise at several scales, tints, shadows, colour grading)
         -> slight camera blur of the image (labels stay crisp)

World frame: x to the right (image columns), y down (image rows), metres from the top-left
corner; pixel (r, c) covers [c, c+1) x [r, r+1) times `gsd_m`. Shadows are not a class: they
only darken what they fall on. Class ids and which are safe: `SYNTHETIC_CLASSES`.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.sim.objects import PERSON as OBJ_PERSON, ObjectLayer
from dovesei.sim.synthetic.blocks import draw_apartments, draw_commercial, draw_parking, draw_plaza, draw_residential
from dovesei.sim.synthetic.canvas import Canvas, FastRng
from dovesei.sim.synthetic.classes import (  # noqa: F401  (the class ids are part of this module's API)
    BARE_SOIL, CAR, GRASS, PAL_ASPHALT, PARKING_LOT, PERSON, PLAZA, ROAD, ROOF_FLAT, ROOF_PITCHED, SIDEWALK,
    SPORTS_FIELD, SYNTHETIC_CLASSES, TREE, WATER,
)
from dovesei.sim.synthetic.layout import CITY, NO_TREES, CityStyle, make_layout, make_river
from dovesei.sim.synthetic.objects import draw_tree
from dovesei.sim.synthetic.parks import draw_construction, draw_park, draw_sports, draw_water
from dovesei.sim.synthetic.render import finish_world
from dovesei.sim.synthetic.streets import draw_river, draw_segment, draw_sidewalk, draw_street_life
from dovesei.sim.synthetic.styles import CITY_EXTRAS, CITY_STYLES, OPEN_STYLES, STYLE_DENSITY, STYLES  # noqa: F401

log = logging.getLogger(__name__)

# Bump whenever the look or the layout changes: it is part of the cache file name.
GENERATOR_VERSION = 3  # 3: an object shows while any pixel of its label does
DEFAULT_STYLE = "city"  # the original world; its bytes must never change for a given seed

SIZE_RANGE_M = (200.0, 5000.0)
GSD_RANGE_M = (0.05, 1.0)
# 16384^2 px is ~1 GB of RGB + labels; beyond that the world does not fit "reasonable memory".
MAX_SIDE_PX = 16384


class SyntheticWorldError(ConfigError):
    """Bad synthetic-world parameters or spec string."""


@dataclass(frozen=True)
class SyntheticParams:
    """What a synthetic world is a function of; equal params give byte-identical worlds."""

    seed: int = 0
    size_m: float = 1600.0
    gsd_m: float = 0.25
    style: str = DEFAULT_STYLE

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise SyntheticWorldError(f"seed must be an integer, got {self.seed!r}")
        if not 0 <= int(self.seed) < 2**63:
            raise SyntheticWorldError(f"seed must be in [0, 2**63), got {self.seed}")
        for name, value, (lo, hi) in (
            ("size_m", self.size_m, SIZE_RANGE_M),
            ("gsd_m", self.gsd_m, GSD_RANGE_M),
        ):
            try:
                validate.in_range(name, float(value) if isinstance(value, (np.floating, np.integer)) else value, lo, hi)
            except ConfigError as exc:
                raise SyntheticWorldError(str(exc)) from None
        if self.style not in STYLES:
            raise SyntheticWorldError(f"style {self.style!r}: choose one of {', '.join(STYLES)}")
        if self.side_px > MAX_SIDE_PX:
            raise SyntheticWorldError(
                f"size_m / gsd_m = {self.side_px} px per side exceeds {MAX_SIDE_PX} px; "
                "use a coarser gsd_m or a smaller size_m"
            )

    @property
    def side_px(self) -> int:
        return int(round(self.size_m / self.gsd_m))


def parse_spec(spec: str) -> SyntheticParams:
    """Parse the CLI form `synthetic[:seed=N,size_m=X,gsd_m=Y,style=S]` (any subset, any order)."""
    if not isinstance(spec, str):
        raise SyntheticWorldError(f"world spec must be a string, got {type(spec).__name__}")
    head, sep, tail = spec.strip().partition(":")
    if head != "synthetic":
        raise SyntheticWorldError(f"world spec {spec!r} does not start with 'synthetic'")
    if sep and not tail.strip():
        raise SyntheticWorldError(f"world spec {spec!r}: nothing after ':'")
    kinds = {"seed": int, "size_m": float, "gsd_m": float, "style": str}
    values: dict[str, float | int | str] = {}
    for item in tail.split(",") if tail.strip() else []:
        key, eq, raw = (s.strip() for s in item.partition("="))
        if not eq or not key or not raw:
            raise SyntheticWorldError(f"world spec {spec!r}: expected key=value, got {item!r}")
        if key not in kinds:
            raise SyntheticWorldError(
                f"world spec {spec!r}: unknown key {key!r} (known: {', '.join(kinds)})"
            )
        if key in values:
            raise SyntheticWorldError(f"world spec {spec!r}: key {key!r} given twice")
        try:
            values[key] = kinds[key](raw)
        except ValueError:
            raise SyntheticWorldError(
                f"world spec {spec!r}: {key}={raw!r} is not a valid {kinds[key].__name__}"
            ) from None
    return SyntheticParams(**values)  # type: ignore[arg-type]


BLOCK_RENDERERS = {"residential": draw_residential, "apartments": draw_apartments,
                   "commercial": draw_commercial, "parking": draw_parking, "plaza": draw_plaza,
                   "sports": draw_sports, "water": draw_water, "construction": draw_construction,
                   "park": draw_park,
                   "riverside": lambda cv, rng, b: draw_park(cv, rng, b, riverside=True)}


def generate_city(params: SyntheticParams) -> tuple[np.ndarray, np.ndarray]:
    """Build the world: RGB image (H, W, 3) uint8 and labels (H, W) uint8, class ids of
    `SYNTHETIC_CLASSES`. Pure: no I/O, same params -> same bytes."""
    cv = _draw(params)
    return cv.img, cv.lab


def generate_world(params: SyntheticParams) -> SyntheticWorld:
    """`generate_city` plus the people and cars its drawing placed (the baked objects)."""
    cv = _draw(params)
    return SyntheticWorld(cv.img, cv.lab, baked_objects(cv), _shadow_east_north(cv))


@dataclass(frozen=True, eq=False)
class SyntheticWorld:
    """A generated world: image, labels, the people and cars drawn into them (static, `baked`),
    and the sun's shadow offset (east, north metres per metre of height)."""

    image: np.ndarray
    labels: np.ndarray
    baked: ObjectLayer
    shadow_per_m: tuple[float, float]


def _shadow_east_north(cv: Canvas) -> tuple[float, float]:
    # The canvas's y runs down (south); the world's north.
    return float(cv.shadow_per_m[0]), float(-cv.shadow_per_m[1])


def baked_objects(cv: Canvas) -> ObjectLayer:
    """The people and cars the drawing pass placed that are still visible in the finished labels
    (a tree's canopy or the coast's sea may have covered some), in world coordinates.

    Visible means any pixel of its footprint still carries its label: the judge counts those
    pixels, so the simulator must draw the object there too (a person whose centre a crown covers
    but whose shoulder shows is still a person the close look has to see)."""
    size_m = cv.side_px * cv.gsd_m
    rows = []
    for kind, x, y, ang, length, width, rgb in cv.objects:
        # (One standing on the world's edge counts too: its centre may be just outside.)
        if not cv.label_near(x, y, 0.5 * max(length, width), PERSON if kind == OBJ_PERSON else CAR):
            continue
        # Canvas angle from +x (east) towards +y (south) -> heading from north towards east.
        heading = math.atan2(math.cos(ang), -math.sin(ang))
        rows.append((kind, x, size_m - y, heading, 0.0, 0.0, 0.0, length, width, rgb, True))
    return ObjectLayer.build(rows)


def _draw(params: SyntheticParams) -> Canvas:
    if not isinstance(params, SyntheticParams):
        raise SyntheticWorldError(f"expected SyntheticParams, got {type(params).__name__}")
    t0, c0 = time.perf_counter(), time.process_time()
    # Independent streams: layout, per-object details, textures. Changing one stage's number of
    # draws does not reshuffle the others.
    ss_layout, ss_draw, ss_tex = np.random.SeedSequence([int(params.seed), 0xD0E5E1]).spawn(3)
    rng_layout, rng, rng_tex = (np.random.default_rng(ss_layout), FastRng(ss_draw),
                                np.random.default_rng(ss_tex))
    sun_az = rng_layout.uniform(0, 2 * math.pi)
    sun_el = math.radians(rng_layout.uniform(35, 65))
    cv = Canvas(params.side_px, params.gsd_m, sun_az, sun_el)
    if params.style in OPEN_STYLES:
        OPEN_STYLES[params.style](cv, rng_layout, rng)
    else:
        _draw_city(cv, rng_layout, rng, CITY_STYLES.get(params.style, CITY))
        if params.style in CITY_EXTRAS:
            CITY_EXTRAS[params.style](cv, rng)
    # Trees last, so their canopy covers what is under it; none grow in the water.
    for t in cv.trees:
        inside = cv.in_world(t.x_m - t.r_m, t.y_m - t.r_m, t.x_m + t.r_m, t.y_m + t.r_m)
        if inside and cv.label_at(t.x_m, t.y_m) not in NO_TREES:
            draw_tree(cv, rng, t)
    t1, c1 = time.perf_counter(), time.process_time()
    finish_world(cv, rng_tex, params.gsd_m)
    log.debug("synthetic world %s: drawing %.2f s (cpu %.2f s), finishing %.2f s (cpu %.2f s), "
              "%d casters, %d trees", params, t1 - t0, c1 - c0, time.perf_counter() - t1,
              time.process_time() - c1, len(cv.casts), len(cv.trees))
    return cv


def _draw_city(cv: Canvas, rng_layout, rng, city: CityStyle) -> None:
    """The street grid of blocks (every style but the open ones), all but the trees."""
    size_m = cv.side_px * cv.gsd_m
    # Everything starts as carriageway; blocks are drawn over it. (Row-wise fill: broadcasting
    # a 3-tuple over the whole image is several times slower.)
    cv.img[0] = PAL_ASPHALT
    cv.img[1:] = cv.img[0]
    cv.lab[:] = ROAD
    river = make_river(rng_layout, size_m, city)
    xr, yr, blocks, owner = make_layout(rng_layout, size_m, river, city)
    for blk in blocks:
        if not cv.in_world(blk.x0, blk.y0, blk.x1, blk.y1):
            continue
        draw_sidewalk(cv, rng, blk)
        BLOCK_RENDERERS[blk.kind](cv, rng, blk)
    if river is not None:
        draw_river(cv, rng, river, xr, yr)
    # Road segments between junctions; a street swallowed by a merged block has none.
    for i, road in enumerate(xr):
        for j in range(len(yr) - 1):
            if owner.get((i - 1, j), -1) == owner.get((i, j), -2):
                continue
            a0, a1 = yr[j].centre_m + yr[j].width_m / 2, yr[j + 1].centre_m - yr[j + 1].width_m / 2
            if cv.in_world(road.centre_m - 20, a0, road.centre_m + 20, a1):
                draw_segment(cv, rng, road, a0, a1, vertical=True)
    for j, road in enumerate(yr):
        for i in range(len(xr) - 1):
            if owner.get((i, j - 1), -1) == owner.get((i, j), -2):
                continue
            a0, a1 = xr[i].centre_m + xr[i].width_m / 2, xr[i + 1].centre_m - xr[i + 1].width_m / 2
            if cv.in_world(a0, road.centre_m - 20, a1, road.centre_m + 20):
                draw_segment(cv, rng, road, a0, a1, vertical=False)
    for blk in blocks:
        if cv.in_world(blk.x0, blk.y0, blk.x1, blk.y1):
            draw_street_life(cv, rng, blk)


def safe_fraction(labels: np.ndarray) -> float:
    """Fraction of pixels whose class is safe in SYNTHETIC_CLASSES."""
    safe = np.zeros(256, bool)
    for cls, (_, ok) in SYNTHETIC_CLASSES.items():
        safe[cls] = ok
    return float(safe[labels].mean())


# ----------------------------------------------------------------------------------------------
# Disk cache


def default_cache_dir() -> Path:
    """`$DOVESEI_CACHE/worlds`, else `$XDG_CACHE_HOME/dovesei/worlds`, else
    `~/.cache/dovesei/worlds`."""
    if os.environ.get("DOVESEI_CACHE"):
        return Path(os.environ["DOVESEI_CACHE"]) / "worlds"
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]) / "dovesei" / "worlds"
    return Path.home() / ".cache" / "dovesei" / "worlds"


def cache_path(params: SyntheticParams, cache_dir: Path | None = None) -> Path:
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    # The original city keeps its file name (caches made before styles existed stay valid).
    style = "" if params.style == DEFAULT_STYLE else f"-{params.style}"
    return root / (f"synthetic-v{GENERATOR_VERSION}{style}-seed{int(params.seed)}"
                   f"-size{params.size_m:g}m-gsd{params.gsd_m:g}m.npz")


def _load_cached(path: Path, params: SyntheticParams) -> SyntheticWorld:
    with np.load(path, allow_pickle=False) as z:
        image, labels = z["image"], z["labels"]
        # A cache written before worlds kept their objects lacks these: KeyError, regenerated.
        baked, shadow = ObjectLayer.from_arrays(z, "baked_"), tuple(float(v) for v in z["shadow_per_m"])
    side = params.side_px
    if image.shape != (side, side, 3) or image.dtype != np.uint8:
        raise ValueError(f"image has shape {image.shape} {image.dtype}, "
                         f"expected ({side}, {side}, 3) uint8")
    if labels.shape != (side, side) or labels.dtype != np.uint8:
        raise ValueError(f"labels have shape {labels.shape} {labels.dtype}, "
                         f"expected ({side}, {side}) uint8")
    if len(shadow) != 2:
        raise ValueError(f"shadow_per_m has {len(shadow)} values, expected 2")
    return SyntheticWorld(image, labels, baked, shadow)  # type: ignore[arg-type]


def load_or_generate(params: SyntheticParams, cache_dir: Path | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Image and labels of the world for `params` (`load_or_generate_world`)."""
    world = load_or_generate_world(params, cache_dir)
    return world.image, world.labels


def load_or_generate_world(params: SyntheticParams, cache_dir: Path | None = None) -> SyntheticWorld:
    """The world for `params`, from the disk cache when present, else generated and cached.

    A cache file that cannot be read is regenerated (with a warning). Writes are atomic: a
    temporary file in the same folder, then `os.replace`, so concurrent users never see half
    a file."""
    path = cache_path(params, cache_dir)
    if path.exists():
        try:
            world = _load_cached(path, params)
            log.info("synthetic world %s loaded from %s", params, path)
            return world
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("synthetic world cache %s is unreadable (%s); regenerating", path, exc)
    t0 = time.perf_counter()
    world = generate_world(params)
    log.info("synthetic world %s generated in %.1f s (safe fraction %.2f, %d people and cars drawn)",
             params, time.perf_counter() - t0, safe_fraction(world.labels), len(world.baked))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as fh:
                np.savez(fh, image=world.image, labels=world.labels, shadow_per_m=np.array(world.shadow_per_m),
                         **world.baked.to_arrays("baked_"))
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
    except OSError as exc:
        # A read-only or full disk costs speed next time, not correctness now.
        log.warning("could not cache synthetic world at %s: %s", path, exc)
    return world


def main(argv: list[str] | None = None) -> int:
    """`python -m dovesei.sim.synthetic.generate [SPEC]`: time the generation of a world (pictures: `dovesei preview`)."""
    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("spec", nargs="?", default="synthetic",
                    help="synthetic[:seed=N,size_m=X,gsd_m=Y,style=S]")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        params = parse_spec(args.spec)
    except SyntheticWorldError as exc:
        log.error("%s", exc)
        return 2
    t0 = time.perf_counter()
    _, labels = generate_city(params)
    print(f"generated {params} in {time.perf_counter() - t0:.2f} s, "
          f"safe fraction {safe_fraction(labels):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
