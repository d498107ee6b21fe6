"""Close-look crops: a known square from a known pose lands on the right ground; bad requests are refused.

Two independent paths are checked against the world: the sim renders the square from its world
(`SimCore.crop`), and a camera cuts it from a full-resolution frame with `shared.crop`'s homography
(here a frame the sim's own tilted renderer drew, so the two geometries must agree).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.shared.crop import CropLimits, CropRefused, RateLimit, cut_crop, plan_crop
from dovesei.shared.messages import CropRequest, Stamp
from dovesei.sim.camera import CameraModel, render
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.starts import Start
from dovesei.sim.world import ClassInfo, World

GSD_M = 0.05  # 5 cm world pixels: a marker of 5x5 px is 25 cm wide
SIDE_PX = 2400  # a 120 m square world
START = Start(61.3, 58.7, 40.0, yaw_rad=0.6)
MARKER_ID = 7
# The marker's offset from the vehicle in the heading-level body frame: 6 m forward, -4.5 m right.
MARKER_FRD_M = (6.0, -4.5)


def _world_point(start: Start, fwd: float, right: float) -> tuple[float, float]:
    c, s = math.cos(start.yaw_rad), math.sin(start.yaw_rad)
    return start.x_m + c * right + s * fwd, start.y_m + c * fwd - s * right


def marker_world() -> World:
    """Dark ground with one bright 5x5-pixel marker (its own label) at MARKER_FRD_M from START."""
    image = np.full((SIDE_PX, SIDE_PX, 3), 40, np.uint8)
    labels = np.zeros((SIDE_PX, SIDE_PX), np.uint8)
    probe = World(image.copy(), None, GSD_M, {}, "probe")
    row, col = probe.pixel_index(*_world_point(START, *MARKER_FRD_M))
    image[row - 2: row + 3, col - 2: col + 3] = 255
    labels[row - 2: row + 3, col - 2: col + 3] = MARKER_ID
    return World(image, labels, GSD_M, {0: ClassInfo("grass", True), MARKER_ID: ClassInfo("person", False)}, "marker")


@pytest.fixture(scope="module")
def world() -> World:
    return marker_world()


def _request(seq: int = 1, centre=MARKER_FRD_M, side_m: float = 4.0, out_px: int = 128, frame_seq: int = -1):
    return CropRequest("uav1", seq, Stamp(0.0, "sim"), centre, side_m, out_px, frame_seq)


def _bright_centroid(image: np.ndarray) -> tuple[float, float]:
    rows, cols = np.nonzero(image.max(axis=2) > 150)
    assert rows.size, "the marker is not in the crop"
    return float(rows.mean()), float(cols.mean())


def test_a_sim_crop_of_a_known_square_from_a_known_pose_is_centred_on_the_marker(world: World) -> None:
    core = SimCore(world, START, SimConfig(vehicle_profile="ideal"))
    core.reset()
    crop = core.crop(_request())
    centre = (crop.image_rgb.shape[0] - 1) / 2.0
    row, col = _bright_centroid(crop.image_rgb)
    # 4 m over 128 px: 3.1 cm/px; the marker's pixel grid puts it within a world pixel (5 cm).
    assert abs(row - centre) * crop.m_per_px < 0.05 and abs(col - centre) * crop.m_per_px < 0.05
    assert crop.truth is not None and crop.truth.labels[64, 64] == MARKER_ID
    assert crop.truth.centre_world_m == pytest.approx(_world_point(START, *MARKER_FRD_M))
    # Tagged with the capture: the frame it was cut from, its altitude; the source detail at 40 m.
    assert crop.frame_seq == 0 and crop.alt_agl_m == pytest.approx(40.0)
    assert crop.source_m_per_px == pytest.approx(2 * 40.0 * math.tan(math.radians(36.5)) / 4000, rel=0.05)
    # Image up is body forward: a square 1.5 m further forward shows the marker 1.5 m lower.
    core._crop_rate = RateLimit(100.0, 100)
    moved = core.crop(_request(2, centre=(MARKER_FRD_M[0] + 1.5, MARKER_FRD_M[1])))
    row2, col2 = _bright_centroid(moved.image_rgb)
    assert (row2 - row) * moved.m_per_px == pytest.approx(1.5, abs=0.06)
    assert abs(col2 - col) * moved.m_per_px < 0.06


@pytest.mark.parametrize("roll_deg, pitch_deg", [(0.0, 0.0), (6.0, -4.0), (-3.0, 8.0)])
def test_a_camera_crop_cut_from_a_tilted_full_resolution_frame_lands_on_the_marker(world: World, roll_deg: float,
                                                                                    pitch_deg: float) -> None:
    cam = CameraModel(1600, 1200, 73.0)  # the "full-resolution" frame
    roll, pitch = math.radians(roll_deg), math.radians(pitch_deg)
    full, _labels, _valid = render(world, START.x_m, START.y_m, START.alt_m, START.yaw_rad, cam, roll_rad=roll,
                                   pitch_rad=pitch, with_labels=False, interpolation="linear")
    req = _request(out_px=160)
    plan = plan_crop(req, CropLimits(), RateLimit(5.0, 5), 0.0, vehicle_id="uav1", newest_seq=3, alt_agl_m=START.alt_m,
                     roll_rad=roll, pitch_rad=pitch, width_px=cam.width_px, height_px=cam.height_px,
                     hfov_rad=cam.hfov_rad)
    crop = cut_crop(full, plan.homography, req.out_px)
    row, col = _bright_centroid(crop)
    centre = (req.out_px - 1) / 2.0
    m_per_px = req.side_m / req.out_px
    # A source pixel at 40 m is ~5 cm: the marker lands within about one of them of the centre.
    assert math.hypot(row - centre, col - centre) * m_per_px < 0.08


@pytest.mark.parametrize("changes, expected", [
    ({"side_m": 0.01}, "side 0.01 m outside"),
    ({"side_m": 5000.0}, "side 5000 m outside"),
    ({"out_px": 4096}, "output 4096 px outside"),
    ({"out_px": 2}, "output 2 px outside"),
    ({"centre": (80.0, 0.0)}, "outside the camera's view"),
    ({"out_px": 1024, "side_m": 0.5}, "finer than the frame"),
    ({"frame_seq": 12}, "frame 12 is not kept"),
])
def test_bad_crop_requests_are_refused_with_a_reason(world: World, changes: dict, expected: str) -> None:
    core = SimCore(world, START, SimConfig(vehicle_profile="ideal"))
    core.reset()
    with pytest.raises(CropRefused, match=expected):
        core.crop(_request(**changes))
    core.crop(_request())  # and the camera still answers a good one


def test_crops_asked_too_often_are_refused_until_the_bucket_refills(world: World) -> None:
    core = SimCore(world, START, SimConfig(vehicle_profile="ideal", crop_limits=CropLimits(rate_hz=2.0, burst=2)))
    core.reset()
    core.crop(_request(1))
    core.crop(_request(2))
    with pytest.raises(CropRefused, match="too frequent: at most 2 crops/s"):
        core.crop(_request(3))
    for _ in range(10):  # half a second of sim time: one token back
        core.step(None)
    core.crop(_request(4))


def test_a_crop_for_another_vehicle_is_refused(world: World) -> None:
    core = SimCore(world, START, SimConfig(vehicle_profile="ideal"))
    core.reset()
    with pytest.raises(CropRefused, match="request for vehicle 'uav9'"):
        core.crop(CropRequest("uav9", 1, Stamp(0.0, "sim"), (0.0, 0.0), 4.0, 128))


def test_the_camera_mode_sim_answers_the_same_close_look_from_its_newest_frame(world: World) -> None:
    # A sim rendering at an autopilot's states (`up --vehicle-url`, SITL) served no crop key, and a
    # SITL flight's clearance held at 42 m for 126 unanswered close looks until it aborted.
    from dovesei.shared.messages import VehicleState
    from dovesei.sim.dynamics import Pose
    from dovesei.sim.external import PoseCamera

    camera = PoseCamera(world, SimConfig(vehicle_profile="ideal"))
    with pytest.raises(CropRefused):
        camera.crop(_request())  # no frame yet
    state = VehicleState("uav1", 5, Stamp(12.0, "vehicle"), START.alt_m, (0.0, 0.0, 0.0), yaw_rad=START.yaw_rad)
    frame = camera.frame(Pose(START.x_m, START.y_m, START.alt_m, yaw_rad=START.yaw_rad, t_s=12.0), state)
    crop = camera.crop(_request())
    core = SimCore(world, START, SimConfig(vehicle_profile="ideal"))
    core.reset()
    same = core.crop(_request())
    assert crop.frame_seq == frame.seq and crop.stamp == state.stamp and crop.alt_agl_m == pytest.approx(START.alt_m)
    assert crop.truth is not None and crop.truth.labels[64, 64] == MARKER_ID
    assert crop.truth.centre_world_m == pytest.approx(same.truth.centre_world_m)
    assert np.array_equal(crop.image_rgb, same.image_rgb) and crop.source_m_per_px == pytest.approx(same.source_m_per_px)
