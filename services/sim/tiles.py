"""Worlds from web map tiles (XYZ or WMTS), fetched over HTTP into a disk cache.

This is the world source the paper used (orthophoto tiles streamed from a map service). Data flow:

    "tiles:<url template>,zoom=Z,lat=..,lon=..[,extent_m=..]"  --parse_tiles_spec-->  TileSpec
    TileSpec -> web-mercator pixel window around (lat, lon) -> the tiles covering it
    each tile: disk cache hit, or urllib GET (timeout, User-Agent) -> decoded -> cached
    tiles pasted into a mosaic -> cropped to the window -> World(labels=None)

The template takes `{z}/{x}/{y}` (XYZ, `{-y}` for TMS row order) or the WMTS names
`{TileMatrix}/{TileCol}/{TileRow}`. Tiles are web mercator (EPSG:3857), so the ground sampling
distance is 2*pi*R*cos(lat) / (tile_px * 2^zoom); it is taken at the centre latitude (over a
1.5 km window the scale changes by well under 0.1 % at mid latitudes). A tile that fails to
download or decode raises `TileError` naming its URL: the mosaic never has silent black holes.
There are no labels, so episodes on a tile world cannot be judged. Use a service you are
licensed to use; the cache (see `cache_root`) keeps repeated runs off the network.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import re
import tempfile
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.sim.synthetic.generate import default_cache_dir
from dovesei.sim.world import World, WorldError

log = logging.getLogger(__name__)

EARTH_RADIUS_M = 6378137.0  # the web-mercator sphere
MAX_LAT_DEG = 85.05112878  # web mercator's square-world latitude limit
USER_AGENT = "dovesei-sim/0.1 (safe-landing simulator; caches tiles on disk)"
_PLACEHOLDERS = {
    "{z}": "z", "{x}": "x", "{y}": "y", "{-y}": "tms_y",
    "{TileMatrix}": "z", "{TileCol}": "x", "{TileRow}": "y",
}


class TileError(WorldError):
    """A tile world that cannot be built: bad spec, or a tile that could not be fetched or decoded."""


@dataclass(frozen=True)
class TileSpec:
    """What to fetch: the template, zoom, centre and extent of the mosaic, and how."""

    url_template: str
    zoom: int
    lat_deg: float
    lon_deg: float
    extent_m: float = 1500.0  # side of the square mosaic
    tile_px: int = 256
    timeout_s: float = 20.0
    max_tiles: int = 4096  # refuse accidental continent-sized requests
    workers: int = 4

    @property
    def gsd_m(self) -> float:
        """Metres per pixel at the centre latitude."""
        return 2.0 * math.pi * EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg)) / (self.tile_px * 2**self.zoom)


def cache_root() -> Path:
    """The dovesei cache folder ($DOVESEI_CACHE, else $XDG_CACHE_HOME/dovesei, else ~/.cache/dovesei).

    The rule is the synthetic worlds' (they cache in its "worlds" subfolder): one rule, one place.
    """
    return default_cache_dir().parent


def parse_tiles_spec(spec: str) -> TileSpec:
    """Parse "tiles:<template>,zoom=Z,lat=..,lon=..[,extent_m=..,tile_px=..,timeout_s=..,max_tiles=..]"."""
    body = spec[len("tiles:"):] if spec.startswith("tiles:") else spec
    # Split only at commas that start a key=value option: URL templates may contain commas.
    parts = re.split(r",(?=\s*[A-Za-z_]+\s*=)", body)
    template, options = parts[0].strip(), {}
    for part in parts[1:]:
        key, _, value = part.partition("=")
        options[key.strip()] = value.strip()
    if not re.match(r"^https?://", template):
        raise TileError(f"tiles spec {spec!r}: the URL template must start with http:// or https://")
    leftovers = [p for p in re.findall(r"\{[^{}]*\}", template) if p not in _PLACEHOLDERS]
    if leftovers:
        raise TileError(f"tiles spec {spec!r}: unsupported placeholders {leftovers} (known: {sorted(_PLACEHOLDERS)})")
    found = {_PLACEHOLDERS[p] for p in re.findall(r"\{[^{}]*\}", template)}
    if not ({"z", "x"} <= found and found & {"y", "tms_y"}):
        raise TileError(f"tiles spec {spec!r}: the template needs zoom, column and row placeholders "
                        "({z}/{x}/{y} or {TileMatrix}/{TileCol}/{TileRow})")
    known = {"zoom": int, "lat": float, "lon": float, "extent_m": float, "tile_px": int,
             "timeout_s": float, "max_tiles": int, "workers": int}
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise TileError(f"tiles spec {spec!r}: unknown options {unknown} (known: {sorted(known)})")
    values = {}
    for key, kind in known.items():
        if key in options:
            try:
                values[key] = kind(options[key])
            except ValueError:
                raise TileError(f"tiles spec {spec!r}: option {key}={options[key]!r} is not a valid {kind.__name__}") from None
    for key in ("zoom", "lat", "lon"):
        if key not in values:
            raise TileError(f"tiles spec {spec!r}: option {key}= is required")
    ts = TileSpec(template, values.pop("zoom"), values.pop("lat"), values.pop("lon"), **values)
    if not 0 <= ts.zoom <= 24:
        raise TileError(f"tiles spec {spec!r}: zoom must be in 0..24, got {ts.zoom}")
    if not (abs(ts.lat_deg) < MAX_LAT_DEG and -180.0 <= ts.lon_deg <= 180.0):
        raise TileError(f"tiles spec {spec!r}: lat must be within +-{MAX_LAT_DEG:.2f} and lon within +-180")
    for key, value in (("extent_m", ts.extent_m), ("tile_px", ts.tile_px), ("timeout_s", ts.timeout_s),
                       ("max_tiles", ts.max_tiles), ("workers", ts.workers)):
        try:
            validate.positive(f"tiles spec {spec!r}: option {key}", value)
        except ConfigError as exc:
            raise TileError(str(exc)) from None
    return ts


def tile_url(template: str, zoom: int, col: int, row: int) -> str:
    """The URL of one tile; row counts from the north (XYZ/WMTS), `{-y}` flips it for TMS."""
    values = {"z": zoom, "x": col, "y": row, "tms_y": 2**zoom - 1 - row}
    out = template
    for placeholder, key in _PLACEHOLDERS.items():
        out = out.replace(placeholder, str(values[key]))
    return out


def load_tile_world(spec: str | TileSpec, cache_dir: Path | None = None) -> World:
    """Fetch (or read from cache) the tiles around the centre and build a label-less World."""
    ts = parse_tiles_spec(spec) if isinstance(spec, str) else spec
    cache_dir = (cache_dir or cache_root() / "tiles") / hashlib.sha256(ts.url_template.encode()).hexdigest()[:16]
    scale = ts.tile_px * 2**ts.zoom  # global mosaic size in pixels at this zoom
    # Web mercator: column linear in longitude, row from the Mercator ordinate, both from the north-west.
    centre_col_px = (ts.lon_deg + 180.0) / 360.0 * scale
    centre_row_px = (1.0 - math.asinh(math.tan(math.radians(ts.lat_deg))) / math.pi) / 2.0 * scale
    size_px = max(1, round(ts.extent_m / ts.gsd_m))
    left, top = round(centre_col_px - size_px / 2), round(centre_row_px - size_px / 2)
    if left < 0 or top < 0 or left + size_px > scale or top + size_px > scale:
        raise TileError(f"tiles: a {ts.extent_m:g} m window at ({ts.lat_deg}, {ts.lon_deg}) crosses the map's edge")
    tx0, ty0 = left // ts.tile_px, top // ts.tile_px
    tx1, ty1 = (left + size_px - 1) // ts.tile_px, (top + size_px - 1) // ts.tile_px
    keys = [(tx, ty) for ty in range(ty0, ty1 + 1) for tx in range(tx0, tx1 + 1)]
    if len(keys) > ts.max_tiles:
        raise TileError(f"tiles: {len(keys)} tiles needed at zoom {ts.zoom} for {ts.extent_m:g} m, "
                        f"more than max_tiles={ts.max_tiles}")
    log.info("tiles: %d tiles at zoom %d (%.3f m/px), cache %s", len(keys), ts.zoom, ts.gsd_m, cache_dir)

    def one(key: tuple[int, int]) -> np.ndarray:
        tx, ty = key
        return _get_tile(tile_url(ts.url_template, ts.zoom, tx, ty),
                         cache_dir / str(ts.zoom) / str(tx) / f"{ty}.tile", ts)

    mosaic = np.zeros(((ty1 - ty0 + 1) * ts.tile_px, (tx1 - tx0 + 1) * ts.tile_px, 3), dtype=np.uint8)
    # A few concurrent downloads. The first failure (in tile order) is raised after the queued
    # downloads are cancelled, so a dead server fails fast instead of timing out tile by tile.
    with ThreadPoolExecutor(max_workers=ts.workers) as pool:
        futures = [pool.submit(one, key) for key in keys]
        try:
            for (tx, ty), future in zip(keys, futures):
                r0, c0 = (ty - ty0) * ts.tile_px, (tx - tx0) * ts.tile_px
                mosaic[r0: r0 + ts.tile_px, c0: c0 + ts.tile_px] = future.result()
        except BaseException:
            for future in futures:
                future.cancel()
            raise
    r0, c0 = top - ty0 * ts.tile_px, left - tx0 * ts.tile_px
    image = np.ascontiguousarray(mosaic[r0: r0 + size_px, c0: c0 + size_px])
    name = f"tiles z{ts.zoom} {ts.lat_deg:.6f},{ts.lon_deg:.6f}"
    return World(image, None, ts.gsd_m, {}, name=name)


def _get_tile(url: str, cache_path: Path, ts: TileSpec) -> np.ndarray:
    # Tiles never change under a fixed template and zoom as far as we are concerned: no expiry.
    if cache_path.is_file():
        tile = _decode(cache_path.read_bytes(), ts.tile_px)
        if tile is not None:
            return tile
        log.warning("tiles: cached %s is corrupt, fetching it again", cache_path)
    data = _download(url, ts.timeout_s)
    tile = _decode(data, ts.tile_px)
    if tile is None:
        raise TileError(f"tile {url}: the response is not a {ts.tile_px}x{ts.tile_px} image ({len(data)} bytes)")
    # Cache only what decoded, written atomically so a crash never leaves half a tile behind.
    cache_path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=cache_path.parent, suffix=".part")
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    os.replace(tmp, cache_path)
    return tile


def _download(url: str, timeout_s: float) -> bytes:
    request = urllib.request.Request(url, headers={"User-Agent": USER_AGENT})
    try:
        with urllib.request.urlopen(request, timeout=timeout_s) as response:
            return response.read()
    except urllib.error.HTTPError as exc:
        raise TileError(f"tile {url}: HTTP {exc.code} {exc.reason}") from exc
    except (urllib.error.URLError, OSError) as exc:  # TimeoutError is an OSError
        reason = getattr(exc, "reason", exc)
        raise TileError(f"tile {url}: download failed: {reason}") from exc


def _decode(data: bytes, tile_px: int) -> np.ndarray | None:
    bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.shape[:2] != (tile_px, tile_px):
        return None
    return bgr[:, :, ::-1]
