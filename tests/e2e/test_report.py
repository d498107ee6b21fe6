"""The report's pictures: trajectory plot, bench paths and the episode video, on a tiny world."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from dovesei.pictures.common import ReportError, backend_label
from dovesei.pictures.plots import plot_bench_paths, plot_trajectory
from dovesei.pictures.video import BAR_PX, LEGEND_PX, PANELS, POLICY_TEXT_PX, VideoFrame, write_video
from dovesei.sim.world import ClassInfo, World

SIDE_PX = 352


@pytest.fixture(scope="module")
def world() -> World:
    """200 x 200 m at 0.5 m/px: grass (safe, class 1) with a road (unsafe, class 2) at x 90-110 m."""
    image = np.zeros((400, 400, 3), np.uint8)
    image[:] = (60, 160, 60)
    labels = np.ones((400, 400), np.uint8)
    image[:, 180:220] = (90, 90, 90)
    labels[:, 180:220] = 2
    return World(image, labels, 0.5, {1: ClassInfo("grass", True), 2: ClassInfo("road", False)}, name="test")


def _report(n: int = 200) -> dict:
    t = np.arange(n) * 0.05
    xs = 60.0 + 0.2 * np.arange(n)
    ys = 120.0 - 0.1 * np.arange(n)
    states = ["SEARCHING"] * (n // 3) + ["AIMING"] * (n // 3)
    states += ["LANDING"] * (n - len(states))
    return {"outcome": "safe", "detail": "0.0% of the disk is unsafe", "policy": "dovesei", "backend": "simulated",
            "simulated": True, "noise": 0.0, "timing": "reference", "sim_time_s": float(t[-1]),
            "path_length_m": 44.7, "safety_radius_m": 2.0,
            "start": {"x_m": float(xs[0]), "y_m": float(ys[0]), "alt_m": 100.0},
            "final": {"x_m": float(xs[-1]), "y_m": float(ys[-1]), "alt_m": 19.9},
            "trajectory": {"t_s": t.tolist(), "x_m": xs.tolist(), "y_m": ys.tolist(),
                           "alt_m": np.linspace(100, 20, n).tolist(), "state": states}}


def test_backend_label_never_hides_simulated_perception() -> None:
    assert backend_label("simulated", True, 0.5) == "simulated perception (noise 0.5)"
    assert backend_label("clipseg", False) == "clipseg"


def test_trajectory_plot_is_written(world: World, tmp_path) -> None:
    out = plot_trajectory(world, _report(), tmp_path / "t.png")
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] > 500 and img.shape[1] > 500
    # A drawn picture, not a blank canvas: many distinct colours (map, path, legend, inset).
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50


def test_trajectory_plot_survives_json_round_trip_and_short_state_list(world: World, tmp_path) -> None:
    rep = json.loads(json.dumps(_report()))
    rep["trajectory"]["state"] = rep["trajectory"]["state"][:10]  # padded, not a crash
    n = len(rep["trajectory"]["x_m"])
    rep["trajectory"]["watchdog"] = ["ok"] * (n - 20) + ["hold"] * 20  # drawn as 'watchdog hold'
    assert plot_trajectory(world, rep, tmp_path / "t.png").exists()


def test_trajectory_plot_refuses_an_empty_path(world: World, tmp_path) -> None:
    rep = _report()
    rep["trajectory"] = {"t_s": [], "x_m": [], "y_m": [], "state": []}
    with pytest.raises(ReportError, match="no trajectory"):
        plot_trajectory(world, rep, tmp_path / "t.png")


def test_bench_paths_one_panel_per_start(world: World, tmp_path) -> None:
    tracks = tmp_path / "tracks"
    tracks.mkdir()
    episodes = []
    for index in range(3):
        for k, pol in enumerate(("dovesei", "dovesei-nofocus")):
            n = 50
            track = np.column_stack([np.arange(n) * 0.05, 40 + 30 * index + k * np.arange(n) * 0.3,
                                     60 + np.arange(n) * 0.2, np.linspace(100, 20, n)]).astype(np.float32)
            np.save(tracks / f"{pol}-{index:04d}.npy", track)
            episodes.append({"policy": pol, "index": index, "outcome": ("safe", "timeout")[k], "sim_time_s": 2.45,
                             "path_length_m": 10.0})
    out = plot_bench_paths(world, {"episodes": episodes, "config": {"world": "test"}}, tracks, tmp_path / "p.png")
    assert out is not None and cv2.imread(str(out)) is not None
    # A policy that confirmed a spot: its ring and the line to the touchdown are drawn (the picture changes).
    episodes[0].update(confirmed={"x_m": 45.0, "y_m": 66.0}, touchdown_error_m=7.2)
    again = plot_bench_paths(world, {"episodes": episodes, "config": {"world": "test"}}, tracks, tmp_path / "q.png")
    assert not np.array_equal(cv2.imread(str(out)), cv2.imread(str(again)))


def test_bench_paths_without_tracks_writes_nothing(world: World, tmp_path) -> None:
    doc = {"episodes": [{"policy": "dovesei", "index": 0, "outcome": "safe"}]}
    assert plot_bench_paths(world, doc, tmp_path, tmp_path / "p.png") is None
    assert not (tmp_path / "p.png").exists()


def _frames(n: int) -> list[VideoFrame]:
    image = np.full((SIDE_PX, SIDE_PX, 3), 128, np.uint8)
    prob = np.zeros((SIDE_PX, SIDE_PX), np.float32)
    prob[:, SIDE_PX // 2:] = 1.0  # left half unsafe (red), right half safe (green)
    return [VideoFrame(t_s=0.05 * i, image_rgb=image, prob_safe=prob, alt_agl_m=100.0 - i, state="AIMING",
                       focus_radius_px=100.0, target_px=(176.0, 260.0)) for i in range(n)]


def test_video_has_every_frame_and_the_heatmap_colours(tmp_path) -> None:
    out = write_video(_frames(12), tmp_path / "episode.mp4")
    cap = cv2.VideoCapture(str(out))
    try:
        count = 0
        first = None
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            first = frame if first is None else first
            count += 1
    finally:
        cap.release()
    assert count == 12
    assert first.shape[:2] == (SIDE_PX + POLICY_TEXT_PX + BAR_PX + LEGEND_PX, PANELS * SIDE_PX)  # camera | heatmap | policy view
    # Heatmap panel (right half of the frame): P=0 is red, P=1 is green (BGR), away from overlays.
    unsafe_bgr = first[40, SIDE_PX + 10].astype(int)
    safe_bgr = first[40, 2 * SIDE_PX - 10].astype(int)
    assert unsafe_bgr[2] > 180 and unsafe_bgr[1] < 80
    assert safe_bgr[1] > 180 and safe_bgr[2] < 80


def test_video_without_frames_is_an_error(tmp_path) -> None:
    with pytest.raises(ReportError, match="no frames"):
        write_video([], tmp_path / "v.mp4")
