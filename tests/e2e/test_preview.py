"""`dovesei preview` draws a world, the camera's views and the simulated perception."""

from __future__ import annotations

from pathlib import Path

import cv2

import dovesei.sim
from dovesei.pictures.world import render_preview, render_views
from dovesei.preview import main
from dovesei.sim.synthetic.generate import SyntheticParams
from dovesei.sim.world import load_world

DUBAI = Path(dovesei.sim.__file__).parent / "worlds" / "dubai-tile8-004"  # shipped as package data


def _png_size(path: Path) -> tuple[int, int]:
    img = cv2.imread(str(path))
    assert img is not None, f"{path} is not a readable PNG"
    return img.shape[:2]


def test_synthetic_world_pictures(tmp_path: Path) -> None:
    assert main(["--world", "synthetic:size_m=300,seed=2", "--out", str(tmp_path)]) == 0
    for name in ("world.png", "camera.png", "perception.png"):
        h, w = _png_size(tmp_path / name)
        assert h > 300 and w > 300


def test_world_folder_pictures(tmp_path: Path) -> None:
    assert main(["--world", str(DUBAI), "--out", str(tmp_path), "--no-perception"]) == 0
    assert _png_size(tmp_path / "world.png")[1] > 800  # image and labels side by side
    assert not (tmp_path / "perception.png").exists()


def test_a_point_outside_the_world_is_refused(tmp_path: Path, capsys) -> None:
    assert main(["--world", "synthetic:size_m=300,seed=2", "--at", "5000,10", "--out", str(tmp_path)]) == 2
    assert "outside the world" in capsys.readouterr().err


def test_render_views_writes_one_picture(tmp_path: Path) -> None:
    world = load_world("synthetic:size_m=300,seed=2,gsd_m=0.5")
    path = render_views(world, 150.0, 150.0, tmp_path / "views.png")
    h, w = _png_size(path)
    assert w == 3 * 352 + 2 * 8 and h > 2 * 352  # three altitudes, image above labels


def test_render_preview_writes_a_png(tmp_path: Path) -> None:
    out = render_preview(SyntheticParams(seed=1, size_m=200.0, gsd_m=0.5), tmp_path / "p.png",
                         crop_m=100.0, panel_px=200)
    h, w = _png_size(out)
    assert h > 200 and w >= 2 * 200


def test_the_dubai_alias_works_in_preview(tmp_path: Path) -> None:
    assert main(["--world", "dubai", "--out", str(tmp_path), "--no-perception"]) == 0
    assert _png_size(tmp_path / "camera.png")[0] > 352
