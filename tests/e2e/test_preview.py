"""`dovesei preview` draws a world, the camera's views and the simulated perception."""

from __future__ import annotations

from pathlib import Path

import cv2

import dovesei.sim
from dovesei.preview import main

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
