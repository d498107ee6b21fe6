"""`--world paper-paris`: the paper's rectangle, starts and zoom, IGN's WMTS request form, refusals.

Offline: the orthophotos come from the tile server of `test_tiles.py` on 127.0.0.1 (a free port),
asked exactly what the Géoplateforme would be asked.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dovesei.sim import paris
from dovesei.sim.paris import IGN_ORTHO_WMTS, N_STARTS, parse_spec, start_latlon
from dovesei.sim.service import SimServiceConfig
from dovesei.sim.service import resolve_start as sim_resolve_start
from dovesei.sim.starts import Start
from dovesei.sim.tiles import TileError
from dovesei.sim.world import load_world, unjudged_reason
from tests.sim.test_tiles import TileServer, server  # noqa: F401  (the local tile server fixture)

REPO = Path(__file__).resolve().parents[2]


def local_url(server: TileServer) -> str:
    """IGN's own request, sent to the local server instead of data.geopf.fr."""
    assert IGN_ORTHO_WMTS.startswith("https://data.geopf.fr/wmts?")
    return IGN_ORTHO_WMTS.replace("https://data.geopf.fr/wmts?", f"{server.base}/geopf/wmts?")


def test_the_default_is_the_papers_rectangle_ign_orthophotos_and_a_tenth_to_a_third_of_a_metre() -> None:
    tiles, k = parse_spec("paper-paris")
    assert k == 0 and tiles.zoom == 19 and 0.1 <= tiles.gsd_m <= 0.3
    for part in ("LAYER=ORTHOIMAGERY.ORTHOPHOTOS", "TILEMATRIXSET=PM", "REQUEST=GetTile", "TILEMATRIX={TileMatrix}",
                 "TILEROW={TileRow}", "TILECOL={TileCol}"):
        assert part in tiles.url_template
    assert parse_spec("paper-paris:zoom=20")[0].gsd_m == pytest.approx(tiles.gsd_m / 2)
    starts = np.array([start_latlon(i) for i in range(N_STARTS)])
    assert ((starts[:, 0] >= paris.SOUTH_LAT_DEG) & (starts[:, 0] <= paris.NORTH_LAT_DEG)).all()
    assert ((starts[:, 1] >= paris.WEST_LON_DEG) & (starts[:, 1] <= paris.EAST_LON_DEG)).all()
    # Uniform over the rectangle: each half holds about half of the 50 (binomial sd 3.5).
    mid_lat = (paris.SOUTH_LAT_DEG + paris.NORTH_LAT_DEG) / 2
    mid_lon = (paris.WEST_LON_DEG + paris.EAST_LON_DEG) / 2
    assert 15 <= int((starts[:, 0] > mid_lat).sum()) <= 35 and 15 <= int((starts[:, 1] > mid_lon).sum()) <= 35
    assert tuple(starts[7]) == start_latlon(7) and (tiles.lat_deg, tiles.lon_deg) == start_latlon(0)


@pytest.mark.parametrize("bad, match", [
    ("paper-paris:start=50", "start must be"), ("paper-paris:zoom=17", "zoom must be"),
    ("paper-paris:extent_m=100", "extent_m must be"), ("paper-paris:colour=red", "unknown options"),
    ("paper-paris:start", "not key=value"), ("paper-paris:url=ftp://example.org/{TileMatrix}", "url= must"),
    ("paper-paris:zoom=high", "must be integers"),
])
def test_bad_specs_name_what_is_wrong(bad: str, match: str) -> None:
    with pytest.raises(TileError, match=match):
        load_world(bad)


def test_flies_from_the_centre_of_a_window_of_ign_tiles(server: TileServer, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("DOVESEI_CACHE", str(tmp_path / "cache"))
    spec = f"paper-paris:start=3,extent_m=300,url={local_url(server)}"
    world = load_world(spec)
    tiles, _ = parse_spec(spec)
    assert world.labels is None and world.gsd_m == pytest.approx(tiles.gsd_m)
    assert world.width_m == pytest.approx(300.0, abs=0.5) and world.home_xy_m == (world.width_m / 2, world.height_m / 2)
    queries = list(server.wmts_queries)
    assert queries and all(q["LAYER"] == "ORTHOIMAGERY.ORTHOPHOTOS" and q["FORMAT"] == "image/jpeg"
                           and q["TILEMATRIX"] == "19" and q["STYLE"] == "normal" for q in queries)
    # The home pixel lies in the tile holding the start's web-mercator position (colour = row, col).
    lat, lon = start_latlon(3)
    n = 256 * 2**19
    col = int((lon + 180.0) / 360.0 * n) // 256
    row = int((1.0 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2.0 * n) // 256
    r, c = world.pixel_index(*world.home_xy_m)
    pixel = world.image_rgb[r, c].astype(int)
    assert abs(pixel[0] - col % 256) <= 3 and abs(pixel[1] - row % 256) <= 3  # JPEG: within a few levels
    # The sim started on its own starts there too, as `dovesei up` does (one answer for paper-paris).
    assert sim_resolve_start(world, SimServiceConfig(world=spec, start_alt_m=80.0)) == Start(*world.home_xy_m, 80.0)
    again = load_world(spec)  # from the disk cache: not one request more
    assert len(server.wmts_queries) == len(queries)
    np.testing.assert_array_equal(again.image_rgb, world.image_rgb)


def test_commands_that_judge_refuse_it_in_one_line_before_any_download(server: TileServer, tmp_path: Path,
                                                                       capsys) -> None:
    from dovesei import calibrate, perception_stats
    from dovesei.bench import main as bench_main

    spec = f"paper-paris:url={local_url(server)}"
    assert unjudged_reason("synthetic") is None and unjudged_reason("dubai") is None
    runs = {"bench": lambda: bench_main(["--world", spec, "--episodes", "1", "--out", str(tmp_path / "b")]),
            "calibrate": lambda: calibrate.main(["--world", spec, "--out", str(tmp_path / "c")]),
            "perception-stats": lambda: perception_stats.main(["--world", spec])}
    for name, run in runs.items():
        assert run() == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "has no labels" in err[0] and "--segmenter clipseg" in err[0], (name, err)
    assert server.total() == 0 and not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


@pytest.mark.slow
def test_up_flies_it_with_clipseg_and_does_not_judge(server: TileServer, tmp_path: Path,
                                                     tiny_clipseg_dir: Path) -> None:
    model = tiny_clipseg_dir
    out = tmp_path / "run"
    spec = f"paper-paris:start=1,extent_m=300,url={local_url(server)}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "HF_HUB_OFFLINE": "1", "DOVESEI_CACHE": str(tmp_path / "cache")}
    argv = [sys.executable, "-m", "dovesei.cli", "up", "--world", spec, "--segmenter", "clipseg", "--model",
            str(model), "--time-limit-s", "1", "--no-video", "--no-record", "--out", str(out)]
    proc = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    report = json.loads((out / "report.json").read_text())
    # Exit 3: the run ended (a 1 s limit from 100 m, 20 CLIPSeg frames: a timeout), and nothing on it
    # was judged safe.
    assert proc.returncode == 3, proc.stderr[-3000:]
    assert report["outcome"] in ("timeout", "not_judged") and report["backend"] != "simulated"
    st = report["start"]
    assert (st["x_m"], st["y_m"]) == pytest.approx((150.0, 150.0), abs=0.5)  # the window's centre: the start
    # The simulated perception has no labels to read there: refused before any process starts.
    sim = subprocess.run([*argv[:6], "--segmenter", "sim", "--out", str(tmp_path / "sim")], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    assert sim.returncode == 2 and "--segmenter clipseg" in sim.stderr.strip().splitlines()[-1], sim.stderr[-2000:]
