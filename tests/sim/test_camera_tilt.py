"""The body-fixed camera tilted with the vehicle: markers land where a tilted pinhole projects them.

The prediction here is the textbook projection (world point -> NED offset -> body frame by the
transpose of R_z(yaw) R_y(pitch) R_x(roll) -> pinhole), written independently of the renderer's
homography (which goes the other way, pixel -> ray -> ground).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.sim.camera import (
    CameraError, CameraModel, optical_axis_ground_m, pixel_to_world_affine, pixel_to_world_homography, render,
)
from tests.sim.test_camera import CAM_X_M, CAM_Y_M, marker_world


def body_to_ned(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw),
                              math.sin(yaw))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def projected_px(cam: CameraModel, x_m: float, y_m: float, alt_m: float, roll: float, pitch: float, yaw: float,
                 px_m: float, py_m: float) -> tuple[float, float] | None:
    """(row, col) of the ground point (px_m, py_m) seen from (x_m, y_m, alt_m) with that attitude."""
    ned = np.array([py_m - y_m, px_m - x_m, alt_m])
    fwd, right, down = body_to_ned(roll, pitch, yaw).T @ ned
    if down <= 0:
        return None
    f_px = cam.width_px / (2.0 * math.tan(cam.hfov_rad / 2.0))
    return (cam.height_px - 1) / 2 - f_px * fwd / down, (cam.width_px - 1) / 2 + f_px * right / down


@pytest.fixture(scope="module")
def markers():
    return marker_world()


@pytest.mark.parametrize("roll_deg,pitch_deg,yaw_deg", [(0.0, 12.0, 0.0), (-9.0, 0.0, 30.0), (14.0, -11.0, -120.0),
                                                        (4.0, 20.0, 75.0)])
def test_markers_land_where_a_tilted_pinhole_projects_them(markers, roll_deg: float, pitch_deg: float,
                                                           yaw_deg: float) -> None:
    world, centres = markers
    cam = CameraModel()
    roll, pitch, yaw = math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg)
    alt_m = 50.0
    _img, labels, _valid = render(world, CAM_X_M, CAM_Y_M, alt_m, yaw, cam, roll_rad=roll, pitch_rad=pitch)
    seen = 0
    for cid, (wx, wy) in centres.items():
        want = projected_px(cam, CAM_X_M, CAM_Y_M, alt_m, roll, pitch, yaw, wx, wy)
        if want is None or not (8 <= want[0] <= cam.height_px - 9 and 8 <= want[1] <= cam.width_px - 9):
            continue  # outside this view
        rows, cols = np.nonzero(labels == cid)
        if len(rows) == 0:
            continue  # a marker smaller than a pixel at this range (the 100 m ones are 1.25 m wide)
        seen += 1
        assert abs(rows.mean() - want[0]) < 1.5 and abs(cols.mean() - want[1]) < 1.5, (cid, rows.mean(), cols.mean(), want)
    assert seen >= 3  # the check above must have compared something


def test_nose_up_looks_forward_and_right_wing_down_looks_left() -> None:
    # Heading north: forward = +y, right = +x.
    x, y = optical_axis_ground_m(0.0, 0.0, 100.0, 0.0, pitch_rad=math.radians(10.0))
    assert x == pytest.approx(0.0, abs=1e-9) and y == pytest.approx(100.0 * math.tan(math.radians(10.0)))
    x, y = optical_axis_ground_m(0.0, 0.0, 100.0, 0.0, roll_rad=math.radians(10.0))
    assert x == pytest.approx(-100.0 * math.tan(math.radians(10.0))) and y == pytest.approx(0.0, abs=1e-9)


def test_a_level_homography_is_the_nadir_affine_map(markers) -> None:
    world, _ = markers
    cam = CameraModel(width_px=320, height_px=240, hfov_deg=60.0)
    h = pixel_to_world_homography(world, 150.0, 210.0, 40.0, 0.7, 0.0, 0.0, cam)
    a = pixel_to_world_affine(world, 150.0, 210.0, 40.0, 0.7, cam)
    np.testing.assert_allclose(h[:2] / h[2, 2], a, atol=1e-9)
    np.testing.assert_allclose(h[2], [0.0, 0.0, 1.0], atol=1e-12)


def test_a_tilted_render_is_a_different_view_and_a_view_to_the_horizon_is_refused(markers) -> None:
    world, _ = markers
    level, _, _ = render(world, CAM_X_M, CAM_Y_M, 50.0, 0.0)
    tilted, _, _ = render(world, CAM_X_M, CAM_Y_M, 50.0, 0.0, pitch_rad=math.radians(15.0))
    assert not np.array_equal(level, tilted)
    with pytest.raises(CameraError, match="horizon"):
        render(world, CAM_X_M, CAM_Y_M, 50.0, 0.0, roll_rad=math.radians(60.0))
    with pytest.raises(CameraError, match="finite"):
        render(world, CAM_X_M, CAM_Y_M, 50.0, 0.0, roll_rad=float("nan"))


def test_camera_mode_renders_at_the_attitude_the_frame_is_labelled_with(markers) -> None:
    """Issue 26: the external-pose sim once rendered nadir but labelled frames with the autopilot's
    roll and pitch, so a policy de-tilting by the label saw alt x tan(tilt) of false motion."""
    from dovesei.shared.messages import Stamp, VehicleState
    from dovesei.sim.core import SimConfig
    from dovesei.sim.dynamics import Pose
    from dovesei.sim.external import PoseCamera

    world, centres = markers
    camera = PoseCamera(world, SimConfig())
    roll, pitch, yaw = math.radians(-8.0), math.radians(13.0), math.radians(40.0)
    alt_m = 50.0
    state = VehicleState(vehicle_id="uav1", seq=3, stamp=Stamp(1.0, "vehicle"), alt_agl_m=alt_m,
                         vel_body_frd_m_s=(0.0, 0.0, 0.0), roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, pos_valid=True)
    frame = camera.frame(Pose(CAM_X_M, CAM_Y_M, alt_m, yaw_rad=yaw), state)
    assert (frame.roll_rad, frame.pitch_rad, frame.yaw_rad) == (roll, pitch, yaw)
    cam = camera.sim.camera
    compared = 0
    for cid, (wx, wy) in centres.items():
        want = projected_px(cam, CAM_X_M, CAM_Y_M, alt_m, roll, pitch, yaw, wx, wy)
        rows, cols = np.nonzero(frame.truth.labels == cid)
        if want is None or len(rows) == 0 or not (8 <= want[0] <= cam.height_px - 9 and 8 <= want[1] <= cam.width_px - 9):
            continue
        compared += 1
        assert abs(rows.mean() - want[0]) < 1.5 and abs(cols.mean() - want[1]) < 1.5
    assert compared >= 3
    # The truth's optical-axis point is where the tilted axis meets the ground, not below the vehicle.
    ax, ay = frame.truth.centre_world_m
    assert math.hypot(ax - CAM_X_M, ay - CAM_Y_M) == pytest.approx(
        alt_m * math.hypot(math.tan(pitch), math.tan(roll) / math.cos(pitch)), rel=1e-6)
