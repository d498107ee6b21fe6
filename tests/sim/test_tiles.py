"""Tile worlds against a tile server started here on 127.0.0.1: mosaic placement, cache, failures."""

from __future__ import annotations

import math
import re
import threading
from collections import Counter
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import cv2
import numpy as np
import pytest

from dovesei.sim.tiles import TileError, cache_root, load_tile_world, parse_tiles_spec, tile_url
from dovesei.sim.world import load_world

TILE_PX = 32
ZOOM = 16
LAT, LON = 48.8566, 2.3522


class TileServer:
    """Serves uniform tiles whose colour encodes their column (red) and row (green).

    Paths `/<kind>/<z>/<x>/<y>.png` give 32-px PNG tiles; `/geopf/wmts?<WMTS KVP>` answers like the
    Géoplateforme (256-px JPEG tiles, 400 for a request that is not a PM GetTile of one layer) and
    keeps each query's parameters in `wmts_queries`.
    """

    def __init__(self) -> None:
        self.requests: Counter[str] = Counter()
        self.wmts_queries: list[dict[str, str]] = []
        self.missing: set[tuple[int, int]] = set()
        self.release = threading.Event()  # lets /slow/ requests finish when the test ends
        self._lock = threading.Lock()
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # keep pytest output quiet
                pass

            def do_GET(self) -> None:
                with server._lock:
                    server.requests[self.path] += 1
                if self.headers.get("User-Agent", "").startswith("Python-urllib"):
                    self.send_error(403, "set a User-Agent")
                    return
                if self.path.startswith("/geopf/wmts?"):
                    self._wmts()
                    return
                m = re.fullmatch(r"/(\w+)/(\d+)/(\d+)/(\d+)\.png", self.path)
                if not m:
                    self.send_error(404)
                    return
                kind, z, x, y = m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4))
                if kind == "slow":
                    server.release.wait(10.0)
                if (x, y) in server.missing:
                    self.send_error(404, "no such tile")
                    return
                if kind == "garbage":
                    body = b"this is not a png"
                else:
                    tile = np.zeros((TILE_PX, TILE_PX, 3), np.uint8)
                    tile[:, :] = (z * 5 % 256, y % 256, x % 256)  # BGR: red = column, green = row
                    body = cv2.imencode(".png", tile)[1].tobytes()
                self._send(body, "image/png")

            def _wmts(self) -> None:
                q = {k.upper(): v[0] for k, v in parse_qs(urlsplit(self.path).query).items()}
                with server._lock:
                    server.wmts_queries.append(q)
                need = {"SERVICE": "WMTS", "REQUEST": "GetTile", "VERSION": "1.0.0", "TILEMATRIXSET": "PM"}
                if any(q.get(k) != v for k, v in need.items()) or not q.get("LAYER") or not q.get("STYLE"):
                    self.send_error(400, "not a PM GetTile")
                    return
                try:
                    z, row, col = int(q["TILEMATRIX"]), int(q["TILEROW"]), int(q["TILECOL"])
                except (KeyError, ValueError):
                    self.send_error(400, "bad tile indices")
                    return
                tile = np.zeros((256, 256, 3), np.uint8)
                tile[:, :] = (z * 5 % 256, row % 256, col % 256)
                ext = ".jpg" if q.get("FORMAT") == "image/jpeg" else ".png"
                self._send(cv2.imencode(ext, tile)[1].tobytes(), q.get("FORMAT", "image/png"))

            def _send(self, body: bytes, content_type: str) -> None:
                self.send_response(200)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                try:
                    self.wfile.write(body)
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the slow-tile test's client gave up (its timeout is what is tested)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.base = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    def total(self) -> int:
        with self._lock:
            return sum(self.requests.values())


@pytest.fixture()
def server() -> Iterator[TileServer]:
    srv = TileServer()
    srv.thread.start()
    try:
        yield srv
    finally:
        srv.release.set()
        srv.httpd.shutdown()
        srv.httpd.server_close()


def spec(server: TileServer, kind: str = "xyz", template: str = "{z}/{x}/{y}", **extra: object) -> str:
    opts = {"zoom": ZOOM, "lat": LAT, "lon": LON, "tile_px": TILE_PX, "extent_m": 600.0, **extra}
    return f"tiles:{server.base}/{kind}/{template}.png," + ",".join(f"{k}={v}" for k, v in opts.items())


def window(lat: float, lon: float, extent_m: float) -> tuple[int, int, int, float]:
    """Independent web-mercator arithmetic: (left px, top px, size px, gsd m/px) of the mosaic."""
    n = TILE_PX * 2**ZOOM
    gsd = 2 * math.pi * 6378137.0 * math.cos(math.radians(lat)) / n
    col = (lon + 180) / 360 * n
    lat_r = math.radians(lat)
    row = (1 - math.log(math.tan(lat_r) + 1 / math.cos(lat_r)) / math.pi) / 2 * n
    size = round(extent_m / gsd)
    return round(col - size / 2), round(row - size / 2), size, gsd


def test_mosaic_places_every_tile_and_caches(server: TileServer, tmp_path: Path) -> None:
    world = load_tile_world(spec(server), cache_dir=tmp_path)
    left, top, size, gsd = window(LAT, LON, 600.0)
    assert world.labels is None and world.gsd_m == pytest.approx(gsd, rel=1e-12)
    assert world.image_rgb.shape == (size, size, 3)
    cols = (left + np.arange(size)) // TILE_PX % 256
    rows = (top + np.arange(size)) // TILE_PX % 256
    np.testing.assert_array_equal(world.image_rgb[:, :, 0], np.broadcast_to(cols, (size, size)))
    np.testing.assert_array_equal(world.image_rgb[:, :, 1], np.broadcast_to(rows[:, None], (size, size)))
    n_tiles = len(set(cols)) * len(set(rows))
    assert n_tiles >= 4 and server.total() == n_tiles  # each tile fetched once
    # Second load: every tile from the disk cache, not one request.
    again = load_tile_world(spec(server), cache_dir=tmp_path)
    assert server.total() == n_tiles
    np.testing.assert_array_equal(again.image_rgb, world.image_rgb)


def test_wmts_template_and_load_world_with_env_cache(server: TileServer, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("DOVESEI_CACHE", str(tmp_path / "cache"))
    assert cache_root() == tmp_path / "cache"
    xyz = load_tile_world(spec(server), cache_dir=tmp_path / "other")
    wmts = load_world(spec(server, "wmts", "{TileMatrix}/{TileCol}/{TileRow}"))
    np.testing.assert_array_equal(wmts.image_rgb, xyz.image_rgb)
    assert any((tmp_path / "cache" / "tiles").rglob("*.tile"))
    assert any(p.startswith("/wmts/") for p in server.requests)


def test_missing_tile_names_its_url_and_is_not_cached(server: TileServer, tmp_path: Path) -> None:
    left, top, _, _ = window(LAT, LON, 600.0)
    bad = (left // TILE_PX + 1, top // TILE_PX + 1)
    server.missing.add(bad)
    url = f"{server.base}/xyz/{ZOOM}/{bad[0]}/{bad[1]}.png"
    with pytest.raises(TileError, match=re.escape(url) + ".*HTTP 404"):
        load_tile_world(spec(server), cache_dir=tmp_path)
    assert not list(tmp_path.glob(f"*/{ZOOM}/{bad[0]}/{bad[1]}.tile"))
    # Once the server has it, the retry fetches only what is still missing from the cache.
    server.missing.clear()
    load_tile_world(spec(server), cache_dir=tmp_path)
    assert server.requests[f"/xyz/{ZOOM}/{bad[0]}/{bad[1]}.png"] == 2


def test_garbage_and_timeout_name_the_url(server: TileServer, tmp_path: Path) -> None:
    with pytest.raises(TileError, match=r"/garbage/.*not a 32x32 image"):
        load_tile_world(spec(server, "garbage", extent_m=20.0), cache_dir=tmp_path)
    with pytest.raises(TileError, match=r"/slow/.*download failed"):
        load_tile_world(spec(server, "slow", extent_m=20.0, timeout_s=0.3), cache_dir=tmp_path)


def test_tms_row_flip() -> None:
    assert tile_url("https://h/{z}/{x}/{-y}.png", 3, 1, 0) == "https://h/3/1/7.png"
    assert tile_url("https://h/{TileMatrix}/{TileRow}/{TileCol}", 5, 2, 9) == "https://h/5/9/2"


@pytest.mark.parametrize(
    "bad, match",
    [
        ("tiles:https://h/{z}/{x}/{y}.png,lat=1,lon=2", "zoom= is required"),
        ("tiles:https://{s}.h/{z}/{x}/{y}.png,zoom=3,lat=1,lon=2", "unsupported placeholders"),
        ("tiles:ftp://h/{z}/{x}/{y}.png,zoom=3,lat=1,lon=2", "http"),
        ("tiles:https://h/{z}/{x}.png,zoom=3,lat=1,lon=2", "column and row"),
        ("tiles:https://h/{z}/{x}/{y}.png,zoom=3,lat=1,lon=2,colour=red", "unknown options"),
        ("tiles:https://h/{z}/{x}/{y}.png,zoom=x,lat=1,lon=2", "zoom"),
        ("tiles:https://h/{z}/{x}/{y}.png,zoom=3,lat=89,lon=2", "lat"),
    ],
)
def test_bad_specs(bad: str, match: str) -> None:
    with pytest.raises(TileError, match=match):
        parse_tiles_spec(bad)


def test_commas_inside_the_url_survive() -> None:
    ts = parse_tiles_spec("tiles:https://h/a,b/{z}/{x}/{y}.png?layers=1,2,zoom=3,lat=1,lon=2")
    assert ts.url_template == "https://h/a,b/{z}/{x}/{y}.png?layers=1,2" and ts.zoom == 3


def test_too_many_tiles_refused() -> None:
    with pytest.raises(TileError, match="max_tiles"):
        load_tile_world("tiles:http://127.0.0.1:9/{z}/{x}/{y}.png,zoom=19,lat=1,lon=2,extent_m=5000,max_tiles=10")
