"""A track that left the map ends at the panel's edge: its end markers are drawn whole inside the
map panel, never over the panel's title above it (matplotlib does not clip a marker whose centre
is inside the axes). The tracks end as timeouts: the out-of-world grey is also the grey of antialiased
title text, the timeout orange is not."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dovesei.pictures.plots import OUTCOME_COLOURS, POLICY_COLOURS, plot_bench_paths, plot_trajectory
from dovesei.sim.world import ClassInfo, World

GRASS_RGB = (60, 160, 60)


@pytest.fixture(scope="module")
def world() -> World:
    image = np.zeros((400, 400, 3), np.uint8)
    image[:] = GRASS_RGB
    return World(image, np.ones((400, 400), np.uint8), 0.5, {1: ClassInfo("grass", True)}, name="test")


def _track(n: int = 50, end_y_m: float = 200.3) -> np.ndarray:
    """Northwards from (100, 150) m to just past the world's north edge (200 m)."""
    return np.column_stack([np.arange(n) * 0.05, np.full(n, 100.0), np.linspace(150.0, end_y_m, n),
                            np.linspace(100, 50, n)])


def _rgb_mask(img_bgr: np.ndarray, hex_rgb: str, tol: int = 6) -> np.ndarray:
    rgb = np.array([int(hex_rgb[i:i + 2], 16) for i in (1, 3, 5)])
    return (np.abs(img_bgr[..., ::-1].astype(int) - rgb) <= tol).all(axis=-1)


def _map_top_row(img_bgr: np.ndarray) -> int:
    """The first image row that is mostly the grass of the map panel."""
    grass = (np.abs(img_bgr[..., ::-1].astype(int) - np.array(GRASS_RGB)) <= 6).all(axis=-1)
    rows = np.flatnonzero(grass.sum(axis=1) > 100)
    assert rows.size, "no map panel in the picture"
    return int(rows[0])


def _check(img_bgr: np.ndarray, hex_rgb: str) -> None:
    top = _map_top_row(img_bgr)
    marker = _rgb_mask(img_bgr, hex_rgb)
    assert marker[:top].sum() == 0, f"{marker[:top].sum()} marker pixels above the map panel (over the title)"
    assert marker[top:].sum() > 20  # drawn, inside the panel


def test_bench_paths_end_markers_of_a_track_off_the_map_stay_in_the_panel(world: World, tmp_path: Path) -> None:
    tracks = tmp_path / "tracks"
    tracks.mkdir()
    np.save(tracks / "clearance-0000.npy", _track())
    doc = {"episodes": [{"policy": "clearance", "index": 0, "outcome": "timeout", "sim_time_s": 2.0,
                         "path_length_m": 50.0}], "config": {"world": "test"}}
    img = cv2.imread(str(plot_bench_paths(world, doc, tracks, tmp_path / "p.png")))
    _check(img, OUTCOME_COLOURS["timeout"])
    # The policy's disc: the only other use of its colour is the legend, inside the panel.
    top = _map_top_row(img)
    assert _rgb_mask(img, POLICY_COLOURS[0])[:top].sum() == 0


def test_trajectory_end_marker_of_a_track_off_the_map_stays_in_the_panel(world: World, tmp_path: Path) -> None:
    t = _track()
    report = {"outcome": "timeout", "detail": "time limit at the map's edge", "policy": "clearance", "backend": "simulated",
              "simulated": True, "start": {"x_m": 100.0, "y_m": 150.0, "alt_m": 100.0},
              "final": {"x_m": 100.0, "y_m": float(t[-1, 2]), "alt_m": 50.0},
              "trajectory": {"t_s": t[:, 0].tolist(), "x_m": t[:, 1].tolist(), "y_m": t[:, 2].tolist(),
                             "alt_m": t[:, 3].tolist(), "state": ["SEARCH"] * len(t)}}
    img = cv2.imread(str(plot_trajectory(world, report, tmp_path / "t.png")))
    _check(img, OUTCOME_COLOURS["timeout"])
