"""`--world paper-paris`: the paper's own setup, IGN orthophotos of Paris through the Géoplateforme WMTS.

The DOVESEI authors flew their simulated UAV over Paris on IGN orthophoto tiles, from 50 starts
drawn uniformly (latitude and longitude independently) over one rectangle of the city, at 100 m.
This preset rebuilds that for users with a network:

    "paper-paris[:start=K,zoom=Z,extent_m=E,url=<WMTS template>]"
      --start K (0..49)--> the K-th of 50 seeded draws uniform over the paper's rectangle
      --tiles.load_tile_world--> an E-metre square of IGN ORTHOIMAGERY.ORTHOPHOTOS (tile matrix
        set PM, web mercator) centred on that draw, cached on disk like any tile world
      --> World(labels=None, home_xy_m = its centre): `up` starts there (the paper's start)

Zoom 19 gives 0.197 m/px at Paris' latitude (the paper's simulator asked for zoom 20, 0.098 m/px:
`zoom=20` gets it at four times the tiles). The extent (default 1000 m) keeps the start 420 m
from the edge, farther than the paper's flights went (74-82 m on average). `url=` points the same
request at another server with the same WMTS parameters (a mirror, or the tests' local server);
it must come last, since a URL may hold anything.

There are no labels, so nothing here can be judged: it is flown with CLIPSeg (`dovesei up
--world paper-paris --segmenter clipseg`), and `bench`, `calibrate` and `perception-stats`
refuse it (`refuse_unjudged`). The imagery is IGN's, under its open licence (Licence Ouverte /
Etalab); the cache keeps repeated runs off the network.
"""

from __future__ import annotations

import re

import numpy as np

from dovesei.sim.tiles import TileError, TileSpec, load_tile_world
from dovesei.sim.world import World

NAME = "paper-paris"
# The authors' rectangle (utils/experiments.bash of their repository): two opposite corners,
# (48.8810503932738, 2.2926285019834536) and (48.837230391660526, 2.389960496086875).
SOUTH_LAT_DEG, NORTH_LAT_DEG = 48.837230391660526, 48.8810503932738
WEST_LON_DEG, EAST_LON_DEG = 2.2926285019834536, 2.389960496086875
N_STARTS = 50  # the paper's episodes
START_SEED = 2023  # our own draw (the paper's list came from an unseeded one)
IGN_ORTHO_WMTS = ("https://data.geopf.fr/wmts?SERVICE=WMTS&REQUEST=GetTile&VERSION=1.0.0"
                  "&LAYER=ORTHOIMAGERY.ORTHOPHOTOS&STYLE=normal&FORMAT=image/jpeg&TILEMATRIXSET=PM"
                  "&TILEMATRIX={TileMatrix}&TILEROW={TileRow}&TILECOL={TileCol}")
DEFAULT_ZOOM = 19
ZOOMS = (18, 19, 20)  # 0.39, 0.20, 0.10 m/px at Paris: the paper's ~0.1-0.3 m/px and one coarser
DEFAULT_EXTENT_M = 1000.0
MIN_EXTENT_M = 300.0  # the 148 m footprint at 100 m plus room to move
MAX_EXTENT_M = 3000.0


def is_paper_paris(spec: str) -> bool:
    return spec.strip() == NAME or spec.strip().startswith(NAME + ":")


def start_latlon(k: int) -> tuple[float, float]:
    """The K-th paper-style start: uniform over the rectangle, latitude and longitude apart."""
    if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < N_STARTS:
        raise TileError(f"{NAME}: start must be an integer in 0..{N_STARTS - 1}, got {k!r}")
    u = np.random.default_rng(START_SEED).uniform(0.0, 1.0, size=(N_STARTS, 2))[k]
    return (SOUTH_LAT_DEG + u[0] * (NORTH_LAT_DEG - SOUTH_LAT_DEG),
            WEST_LON_DEG + u[1] * (EAST_LON_DEG - WEST_LON_DEG))


def parse_spec(spec: str) -> tuple[TileSpec, int]:
    """(the tile request, the start index) of a `paper-paris[:...]` spec; TileError naming what is wrong."""
    spec = spec.strip()
    if not is_paper_paris(spec):
        raise TileError(f"not a {NAME} spec: {spec!r}")
    body = spec[len(NAME) + 1:] if spec.startswith(NAME + ":") else ""
    url = IGN_ORTHO_WMTS
    m = re.search(r"(?:^|,)\s*url=", body)
    if m:
        url, body = body[m.end():].strip(), body[:m.start()]
        if not re.match(r"^https?://", url):
            raise TileError(f"{NAME}: url= must start with http:// or https://, got {url!r}")
    options: dict[str, str] = {}
    for part in (p for p in body.split(",") if p.strip()):
        key, sep, value = part.partition("=")
        if not sep:
            raise TileError(f"{NAME}: option {part.strip()!r} is not key=value (known: start, zoom, extent_m, url)")
        options[key.strip()] = value.strip()
    unknown = sorted(set(options) - {"start", "zoom", "extent_m"})
    if unknown:
        raise TileError(f"{NAME}: unknown options {unknown} (known: start, zoom, extent_m, url)")
    try:
        k = int(options.get("start", "0"))
        zoom = int(options.get("zoom", str(DEFAULT_ZOOM)))
        extent_m = float(options.get("extent_m", str(DEFAULT_EXTENT_M)))
    except ValueError:
        raise TileError(f"{NAME}: start and zoom must be integers and extent_m a number, got {options}") from None
    if zoom not in ZOOMS:
        raise TileError(f"{NAME}: zoom must be one of {ZOOMS} (0.39, 0.20, 0.10 m/px), got {zoom}")
    if not MIN_EXTENT_M <= extent_m <= MAX_EXTENT_M:
        raise TileError(f"{NAME}: extent_m must be in {MIN_EXTENT_M:g}..{MAX_EXTENT_M:g} m, got {extent_m:g}")
    lat, lon = start_latlon(k)
    return TileSpec(url, zoom, lat, lon, extent_m=extent_m), k


def load_paper_paris(spec: str = NAME) -> World:
    """The orthophoto window around the K-th start, its centre as the world's home (where `up` starts)."""
    tiles, k = parse_spec(spec)
    world = load_tile_world(tiles)
    half_x, half_y = world.width_m / 2.0, world.height_m / 2.0
    return World(world.image_rgb, None, world.gsd_m, {}, name=f"{NAME} start {k} ({tiles.lat_deg:.6f}, "
                 f"{tiles.lon_deg:.6f}) z{tiles.zoom}", home_xy_m=(half_x, half_y))


__all__ = ["IGN_ORTHO_WMTS", "NAME", "N_STARTS", "is_paper_paris", "load_paper_paris", "parse_spec", "start_latlon"]
