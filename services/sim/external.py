"""External-pose mode of the sim: no own dynamics, frames rendered where a real vehicle is.

The controller of a real or SITL autopilot is the one process that talks MAVLink; it publishes the
autopilot's `VehicleState` on the state key. Here the sim only listens:

    state key --Inbox (newest wins)--> newest state of our vehicle with a local position
        -> pose in the world (local NED origin at the start: north = +y, east = +x)
        -> judge (the controller's hand-over, time limit, leaving the world)
        -> camera frame at the pose,
           rendered tilted by the state's roll and pitch (the attitude the frame is labelled with:
           a body-fixed camera sees what the autopilot's attitude says, and a policy that de-tilts
           by that label finds the ground where it is)
    status key --Inbox (newest wins)--> the controller's `handover` (what ends the episode as a
        landing; until a status is heard the judge falls back on the altitude crossing)

Frames go out at the frame period of the wall clock, stamped with the state's own stamp (the
vehicle's clock); with `odometry_rate_hz` the loop also runs at that rate and publishes the visual
odometry of views rendered at the same pose (`dovesei.sim.odometry`), dated by the state's stamp
moved on by the wall time since it arrived. No state within `wait_timeout_s` of the start, or none for `state_timeout_s`
later, ends the episode as 'error' naming the key.

After the judged end, with `odometry_after_s` > 0, the camera's odometry goes on (no frames, no
judge) for at most that long, until `stop` or until the states stop: an autopilot whose EKF flies
on the camera's velocity (`--gnss-denied external-nav`) still needs it after the hand-over, until it
has landed (ArduCopter SITL: "EKF variance" about 5 s after the odometry ended with the episode).
The result goes out through `on_result` the moment it is judged, before that tail.

With a truth source (ArduPilot SITL's SIM_STATE, `dovesei.sim.sitl_truth`) the images, the odometry
views and the judge follow the simulator's TRUE pose and attitude instead, while everything a
policy reads stays the estimate's:

    state key (the EKF's estimate) --> the frame's stamp, altitude and attitude labels (what a policy sees)
    SIM_STATE (the physics' truth)  --> where and how tilted the image is rendered, the labels, the judge

so the camera sees the vehicle's real motion, as a real camera would, and the estimate's drift
shows. The states then need no local position (an EKF without GNSS may have none); a truth that
stops ends the episode as 'error' naming its source.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from dovesei.shared import keys
from dovesei.shared.clock import WallClock, wall_time_s
from dovesei.shared.lifecycle import Inbox
from dovesei.shared.crop import RateLimit
from dovesei.shared.messages import (CameraFrame, ControllerStatus, CropFrame, CropRequest, EpisodeResult,
                                     GroundTruth, VehicleState, VisualOdometry)
from dovesei.sim.camera import CameraError, optical_axis_ground_m, prebuild_pyramid, render
from dovesei.sim.core import SimConfig, crop_view, judge_result, truth_classes, unstarted_result
from dovesei.sim.dynamics import Pose
from dovesei.sim.judge import EpisodeJudge
from dovesei.sim.odometry import SimOdometry
from dovesei.sim.sitl_truth import TruePose
from dovesei.sim.starts import Start
from dovesei.sim.world import World

log = logging.getLogger(__name__)

# Frames start this long after the first local position: an autopilot's position and attitude
# streams start independently (yaw reads 0 until the first ATTITUDE).
POSE_WARMUP_S = 0.3
# When the loop falls this far behind its schedule (a stalled host) it restarts the schedule.
_MAX_BEHIND_S = 1.0
# The camera's pyramid levels are built before the first frame for views up to this factor above the
# start (a slant view tilted 48 deg, or a climb of half the start altitude): built lazily mid-flight
# each level stalls the real-time loop 1-3 s (measured against SITL), and the first frame, stamped
# 5 s late, became the segmenter's clock reference, which then refused every fresh frame as "from
# the future" until `up` declared it hung (issue 26).
PREBUILD_ALT_FACTOR = 1.5


class PoseCamera:
    """Renders `CameraFrame`s at poses given from outside, stamped with the vehicle's state."""

    def __init__(self, world: World, sim: SimConfig) -> None:
        self.world, self.sim = world, sim
        self._seen = world.perceived()  # what a camera sees (canopy split by the image); the judge reads `world`
        self.classes = truth_classes(self._seen)
        self.seq = -1
        self._t0_s: float | None = None
        # The newest frame with the true pose it was rendered at, for the close looks (`crop`).
        self._newest: tuple[CameraFrame, tuple[float, ...], float] | None = None
        self._crop_rate = RateLimit(sim.crop_limits.rate_hz, sim.crop_limits.burst)

    def frame(self, pose: Pose, state: VehicleState, attitude_rad: tuple[float, float] | None = None) -> CameraFrame:
        """The view at `pose` tilted by `attitude_rad` (roll, pitch; default the state's), labelled
        with what `state` says: a real camera's frame carries the autopilot's estimate of its
        altitude and attitude, never the truth it was taken at.

        CameraError when the attitude puts the view at the horizon (the caller skips that frame).
        """
        cam = self.sim.camera
        roll_rad, pitch_rad = (state.roll_rad, state.pitch_rad) if attitude_rad is None else attitude_rad
        # A vehicle on the ground still needs a view; 0.1 m keeps the pinhole model defined.
        alt_m = max(pose.alt_agl_m, 0.1)
        if self._t0_s is None:
            self._t0_s = pose.t_s
        # People walk on the episode's clock: seconds since the first frame, as the judge counts.
        image, labels, _valid = render(self._seen, pose.x_m, pose.y_m, alt_m, pose.yaw_rad, cam,
                                       roll_rad=roll_rad, pitch_rad=pitch_rad, t_s=pose.t_s - self._t0_s)
        centre = optical_axis_ground_m(pose.x_m, pose.y_m, alt_m, pose.yaw_rad, roll_rad, pitch_rad)
        truth = GroundTruth(labels, self.classes, centre, self.world.name) \
            if self.sim.attach_truth and labels is not None else None
        self.seq += 1
        frame = CameraFrame(self.sim.vehicle_id, self.seq, state.stamp, image, cam.hfov_rad, max(state.alt_agl_m, 0.0),
                            roll_rad=state.roll_rad, pitch_rad=state.pitch_rad, yaw_rad=state.yaw_rad,
                            sent_wall_s=wall_time_s(), truth=truth)
        self._newest = (frame, (pose.x_m, pose.y_m, alt_m, pose.yaw_rad, roll_rad, pitch_rad), pose.t_s - self._t0_s)
        return frame

    def crop(self, req: CropRequest) -> CropFrame:
        """A close look cut from the newest frame's view at its true pose (as `SimCore.crop`); the
        rate limit runs on the wall clock, as a real camera's. Thread-safe against `frame`."""
        return crop_view(self._seen, self.sim, self.classes, self._crop_rate, time.monotonic(), req, self._newest)


class TruthSource(Protocol):
    """Where the simulator's true pose comes from (`dovesei.sim.sitl_truth.SitlTruth`, or a test's)."""

    url: str

    def newest(self) -> TruePose | None: ...

    def at(self, boot_s: float) -> TruePose | None: ...


def pose_in_world(state: VehicleState, start: Start) -> Pose:
    """A vehicle's local NED state placed in the world: origin at the start, north +y, east +x."""
    north_m, east_m, _down_m = state.pos_local_ned_m
    return Pose(x_m=start.x_m + east_m, y_m=start.y_m + north_m, alt_agl_m=max(state.alt_agl_m, 0.0),
                yaw_rad=state.yaw_rad, t_s=state.stamp.t_s)


def pose_from_truth(true: TruePose, start: Start, t_s: float) -> Pose:
    """SITL's true pose placed in the world like `pose_in_world` (its origin at the start)."""
    return Pose(x_m=start.x_m + true.east_m, y_m=start.y_m + true.north_m, alt_agl_m=max(true.alt_agl_m, 0.0),
                vel_ned_m_s=true.vel_ned_m_s, yaw_rad=true.yaw_rad, t_s=t_s)


def newest_state(states: Inbox[VehicleState], vehicle_id: str, stats: Any, *,
                 need_position: bool = True) -> VehicleState | None:
    """The newest state of `vehicle_id` waiting in the inbox (with a local position unless told
    otherwise), or None."""
    newest = None
    while (state := states.poll()) is not None:
        if state.vehicle_id != vehicle_id:
            stats.states_foreign += 1
            continue
        # Without a truth source the local position IS the pose: none, nothing to render.
        if state.pos_valid or not need_position:
            newest = state
    return newest


def handover_heard(statuses: Inbox[ControllerStatus] | None, vehicle_id: str, last: bool | None) -> bool | None:
    """The controller's newest word on the hand-over (its status's `handover`); `last` when no new
    status of `vehicle_id` waits, None while none was ever heard."""
    while statuses is not None and (status := statuses.poll()) is not None:
        if status.vehicle_id == vehicle_id:
            last = status.handover
    return last


def run_external_pose(states: Inbox[VehicleState], publish_frame: Callable[[CameraFrame], None], world: World,
                      start: Start, sim: SimConfig, *, wait_timeout_s: float, state_timeout_s: float,
                      stop: threading.Event, stats: Any,
                      publish_odometry: Callable[[VisualOdometry], None] | None = None,
                      truth: TruthSource | None = None,
                      statuses: Inbox[ControllerStatus] | None = None, odometry_after_s: float = 0.0,
                      on_result: Callable[[EpisodeResult], None] | None = None,
                      camera: PoseCamera | None = None) -> EpisodeResult | None:
    """Render at the states received until the judge ends the episode; None when `stop` ends it first.

    With `truth`, frames, odometry views and the judge follow its newest pose and attitude instead
    (the states still stamp and label the frames).

    `stats` counts what happened (the service's SimStats: poses_received, states_foreign, steps,
    overruns, frames_skipped). With `sim.odometry_rate_hz` > 0 and `publish_odometry`, the loop
    runs at the faster of the two rates and each new state also gives an odometry view, dated by
    the state's own stamp (a state seen twice gives no second view: it would read as a hover).
    `statuses` carries the controller's hand-over. With `odometry_after_s` > 0 (and odometry on)
    the judged result goes to `on_result` at once and the odometry alone goes on for that long
    (see the module docstring); the same result is returned at the end.
    """
    judge = EpisodeJudge(world, handover_alt_m=sim.handover_alt_m, time_limit_s=sim.time_limit_s,
                         safety_radius_m=sim.safety_radius_m,
                         person_separation_m=sim.person_separation_m, vehicle_separation_m=sim.vehicle_separation_m)
    key = keys.state(sim.vehicle_id)
    camera = camera if camera is not None else PoseCamera(world, sim)
    build_s = prebuild_pyramid(world, sim.camera, PREBUILD_ALT_FACTOR * start.alt_m)
    log.info("camera pyramid ready for views up to %.0f m (%.1f s)", PREBUILD_ALT_FACTOR * start.alt_m, build_s)
    clock = WallClock()
    last_state_wall_s: float | None = None
    first_state_wall_s: float | None = None
    state: VehicleState | None = None
    handover: bool | None = None
    odometry = SimOdometry(world, sim.camera, sim.vehicle_id, sim.odometry_rate_hz) \
        if sim.odometry_rate_hz > 0 and publish_odometry is not None else None
    tick_s = sim.period_s if odometry is None else min(sim.period_s, odometry.period_s)
    due_s = next_frame_s = clock.now_s()
    result: EpisodeResult | None = None  # judged; the odometry's tail runs until tail_end_s
    tail_end_s = 0.0
    while clock.sleep_until(due_s, stop):
        due_s += tick_s
        if clock.now_s() - due_s > _MAX_BEHIND_S:
            stats.overruns += 1
            due_s = clock.now_s() + tick_s
        new = newest_state(states, sim.vehicle_id, stats, need_position=truth is None)
        if new is not None:
            state = new
            stats.poses_received += 1
            last_state_wall_s = clock.now_s()
            if first_state_wall_s is None:
                first_state_wall_s = last_state_wall_s
                log.info("first vehicle state%s on %s", "" if truth else " with a local position", key)
        true = truth.newest() if truth is not None else None
        if last_state_wall_s is None or (truth is not None and true is None):
            if clock.now_s() > wait_timeout_s:
                missing = (f"no SIM_STATE from SITL on {truth.url}" if last_state_wall_s is not None
                           else f"no vehicle state{'' if truth else ' with a local position'} on {key}")
                return unstarted_result(world, start, sim, f"{missing} within {wait_timeout_s:g} s (is the "
                                        "controller running against the autopilot, and does SITL send to "
                                        "the sim's own output?)", clock="vehicle")
            continue
        if clock.now_s() - last_state_wall_s > state_timeout_s:
            if result is not None:
                log.info("odometry after the episode ended: no vehicle state for %g s", state_timeout_s)
                return result
            return judge_result(sim.vehicle_id, judge, "error", f"no vehicle state on {key} for {state_timeout_s:g} s",
                                clock="vehicle")
        if true is not None and time.monotonic() - true.recv_monotonic_s > state_timeout_s:
            if result is not None:
                log.info("odometry after the episode ended: no SIM_STATE for %g s", state_timeout_s)
                return result
            return judge_result(sim.vehicle_id, judge, "error",
                                f"no SIM_STATE from SITL on {truth.url} for {state_timeout_s:g} s", clock="vehicle")
        if result is not None and clock.now_s() > tail_end_s:
            log.info("odometry after the episode ended: %g s are over", odometry_after_s)
            return result
        if last_state_wall_s - first_state_wall_s < POSE_WARMUP_S:
            continue
        if true is None:
            pose, attitude_rad = pose_in_world(state, start), (state.roll_rad, state.pitch_rad)
        else:
            # The truth at the instant of the state that labels this view (stamped on the vehicle's
            # clock), so image and label describe one moment; the newest truth when it cannot be dated.
            if state.stamp.clock == "vehicle":
                true = truth.at(state.stamp.t_s) or true
            pose, attitude_rad = pose_from_truth(true, start, state.stamp.t_s), (true.roll_rad, true.pitch_rad)
        if result is None:
            handover = handover_heard(statuses, sim.vehicle_id, handover)
            if judge.check(pose, handover=handover) is not None:
                result = judge_result(sim.vehicle_id, judge, judge.outcome, clock="vehicle")
                if odometry is None or odometry_after_s <= 0 or on_result is None:
                    return result
                on_result(result)
                tail_end_s = clock.now_s() + odometry_after_s
                log.info("episode judged; the camera's odometry goes on for up to %g s (the autopilot's EKF may fly "
                         "on it until it lands)", odometry_after_s)
        if odometry is not None:
            odo = odometry.observe(pose.x_m, pose.y_m, pose.alt_agl_m, pose.yaw_rad, state,
                                   roll_rad=attitude_rad[0], pitch_rad=attitude_rad[1])
            if odo is not None:
                publish_odometry(odo)
        if result is not None or clock.now_s() < next_frame_s - 1e-6:
            continue
        next_frame_s = next_frame_s + sim.period_s if clock.now_s() - next_frame_s < _MAX_BEHIND_S \
            else clock.now_s() + sim.period_s
        try:
            frame = camera.frame(pose, state, attitude_rad)
        except CameraError as exc:  # an attitude no camera frame can show: skip it, keep serving
            stats.frames_skipped += 1
            log.warning("frame at state %d skipped: %s", state.seq, exc)
            continue
        publish_frame(frame)
        stats.steps += 1
    return result  # stopped: None, or the result already handed to on_result
