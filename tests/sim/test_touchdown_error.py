"""The judge's touchdown error: the true distance from the hand-over point to the ground the policy
last confirmed, placed from the confirming look's spot pixel with THAT frame's true pose (the sim
keeps the poses of recent frames), null for a policy that confirms nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.policies.base import Confirmation, Decision, Observation
from dovesei.episode import EpisodeSpec, run_episode
from dovesei.shared.messages import ControllerStatus, FieldError, Stamp
from dovesei.sim.camera import CameraModel, ground_point_m, pixel_to_world_homography
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.starts import Start
from tests.sim.test_sim_core import MID_Y_M, WEST_M, command, split_world


def _status(seq: int, look: tuple[int, float, float] | None) -> ControllerStatus:
    extra = {} if look is None else {"confirmed_valid": True, "confirmed_frame_seq": look[0],
                                     "confirmed_row_px": look[1], "confirmed_col_px": look[2]}
    return ControllerStatus("uav1", seq, Stamp(0.0, "sim"), "clearance", "DESCEND", "ok", "", 0, 0.0, 1.0, **extra)


@pytest.mark.parametrize("yaw_rad, roll_rad, pitch_rad", [(0.0, 0.0, 0.0), (0.7, 0.0, 0.0), (-2.5, 0.0, 0.0),
                                                        (0.7, 0.15, -0.1)])
def test_ground_point_is_the_renderers_own_map(yaw_rad: float, roll_rad: float, pitch_rad: float) -> None:
    world = split_world()
    cam = CameraModel()
    m = pixel_to_world_homography(world, 120.0, 210.0, 47.0, yaw_rad, roll_rad, pitch_rad, cam)
    for row, col in ((0.0, 0.0), (175.5, 175.5), (40.0, 300.0), (351.0, 12.0)):
        wc, wr, wz = m @ np.array([col, row, 1.0])
        x_m, y_m = world.pixel_to_world(wr / wz, wc / wz)
        got = ground_point_m(120.0, 210.0, 47.0, yaw_rad, row, col, cam, roll_rad, pitch_rad)
        assert got == pytest.approx((x_m, y_m), abs=1e-6)


def test_touchdown_error_uses_the_confirming_frames_own_pose() -> None:
    """Frame 0 is taken at the start; the look confirms the pixel 40 px above the centre (north,
    yaw 0). The vehicle then flies 10 m east and descends: the error is measured from where
    frame 0's pixel lies on the ground, not from where the vehicle was later."""
    core = SimCore(split_world(), Start(WEST_M, MID_Y_M, 40.0), SimConfig())
    out = core.reset()
    assert out.frame is not None and out.frame.seq == 0
    cam = CameraModel()
    centre = (cam.height_px - 1) / 2.0
    look = (0, centre - 40.0, centre)
    expected_xy = (WEST_M, MID_Y_M + 40.0 * cam.metres_per_px(40.0))
    seq = 0
    while out.result is None:
        seq += 1
        core.note_status(_status(seq, look))
        east = 1.0 if out.state.stamp.t_s < 10.0 else 0.0
        out = core.step(command(out.state, (0.0, east, 0.0 if east else 3.0)))
    r = out.result
    assert r.outcome == "safe" and r.confirmed_valid and r.touchdown_error_valid
    assert (r.confirmed_x_m, r.confirmed_y_m) == pytest.approx(expected_xy)
    assert r.final_x_m == pytest.approx(WEST_M + 10.0, abs=1.0)  # it did fly on after the look
    assert r.touchdown_error_m == pytest.approx(math.hypot(r.final_x_m - expected_xy[0], r.final_y_m - expected_xy[1]))
    assert r.touchdown_error_m > 10.0


def test_no_confirmation_means_no_touchdown_error_and_an_unknown_frame_is_not_guessed() -> None:
    core = SimCore(split_world(), Start(WEST_M, MID_Y_M, 25.0), SimConfig())
    out = core.reset()
    core.note_status(_status(1, (0, 10.0, 10.0)))
    core.note_status(_status(2, None))  # the policy dropped its spot: nothing confirmed any more
    out = core.step(command(out.state, (0.0, 0.0, 0.0)))
    core.note_status(_status(3, (999, 10.0, 10.0)))  # a frame the sim never rendered
    while out.result is None:
        out = core.step(command(out.state, (0.0, 0.0, 4.0)))
    r = out.result
    assert r.outcome == "safe" and not r.confirmed_valid and not r.touchdown_error_valid


def test_status_confirmed_pixel_is_range_checked() -> None:
    with pytest.raises(FieldError, match="confirmed_row_px"):
        _status(1, (3, -40.0, 10.0))
    with pytest.raises(FieldError, match="confirmed_frame_seq"):
        _status(1, (-5, 10.0, 10.0))


class _Confirming:
    """A policy double that hovers, descends and reports a confirmation (or a broken one)."""

    name = "double"

    def __init__(self, row_px: float) -> None:
        self.row_px = row_px

    def reset(self) -> None:
        pass

    def step(self, obs: Observation) -> Decision:
        return Decision((0.0, 0.0, 1.0), 0.0, "DESCEND", None, 1.0, None, "descending",
                        confirmed=Confirmation(obs.frame_seq, self.row_px, 5.0))


def test_controller_status_carries_the_confirming_look_and_drops_an_impossible_pixel() -> None:
    from dovesei.shared.messages import SafetyHeatmap, VehicleState  # lazy: only here

    for row_px, valid in ((12.5, True), (float("nan"), False), (1e7, False)):
        core = ControllerCore(ControllerConfig(lockstep=True), policy=_Confirming(row_px))
        hm = SafetyHeatmap("uav1", 7, Stamp(0.0, "sim"), np.full((32, 32), 0.9, np.float32), 60.0, 1.27,
                           "simulated", True, "p", "f", inference_s=0.0)
        core.on_heatmap(hm, 0.0)
        _, status = core.tick(VehicleState("uav1", 0, Stamp(0.0, "sim"), 60.0, (0.0, 0.0, 0.0), await_frame_seq=7))
        assert status.confirmed_valid is valid
        if valid:
            assert (status.confirmed_frame_seq, status.confirmed_row_px, status.confirmed_col_px) == (7, 12.5, 5.0)


SMALL_WORLD = (("scene_after_top_pass", False),)


def test_a_bench_episode_records_the_error_for_clearance_and_none_for_dovesei() -> None:
    """In-process episodes on the split world's grass: `clearance` confirms a spot and hands over
    near it; the paper's policy has no confirmed spot, so its record has none (not 0)."""
    world = split_world()
    start = Start(WEST_M, MID_Y_M, 60.0)
    # A 400 m world is smaller than clearance's search area: its scene is the first views
    # (scene_after_top_pass off), not a top pass that would fly off the world.
    clearance = run_episode(world, EpisodeSpec("clearance", start, timing="real", seed=2, time_limit_s=300.0,
                                               perception="clean", policy_config=SMALL_WORLD),
                            record_track=False).result
    assert clearance.outcome == "safe" and clearance.touchdown_error_valid, clearance
    assert clearance.touchdown_error_m < 10.0
    dovesei = run_episode(world, EpisodeSpec("dovesei", start, timing="real", seed=2, time_limit_s=60.0,
                                             perception="clean"), record_track=False).result
    assert not dovesei.touchdown_error_valid and not dovesei.confirmed_valid
