"""The simulator's core: one episode stepped in fixed sim-time steps, no transport inside.

Each step k (t = k * dt) produces, in this order:

1. a `CameraFrame` when one is due (every `frame_period_s` of sim time), rendered at the
   vehicle's true pose (tilted with the body unless the vehicle profile has a gimbal), labelled
   with the altitude and attitude the autopilot reports, with the ground-truth labels attached
   (sim only: the simulated perception needs them, a real camera never has them);
2. the `VehicleState` of step k, whose `await_frame_seq` names the frame whose heatmap becomes
   available at this step (captured `latency_s` earlier; -1 when none does). Under the `ideal`
   vehicle profile it is the truth; under the others it is the autopilot's estimate
   (`dovesei.sim.estimator`), `pos_valid` False: the truth stays here, with the judge;
3. with `odometry_rate_hz` > 0, a `VisualOdometry` when one is due: the onboard camera's visual
   velocity from views rendered at the true pose, tagged with the state's altitude and attitude
   (`dovesei.sim.odometry`; published before the state, so a controller has it when it decides).
   With `external_nav` the vehicle's autopilot also fuses each valid sample of at least
   `external_nav_min_quality` into its velocity estimate, as ArduCopter's EKF3 does with
   VISION_SPEED_ESTIMATE on an ExternalNav VELXY source (what `--gnss-denied external-nav` sets
   up on a real autopilot): the sample, turned into NED with the attitude it is tagged with (the
   estimate's, heading error included), corrects what the wind, gusts, drift and scale error do
   to the vehicle (`Vehicle.fuse_ground_velocity`, time constant `external_nav_tau_s`);
4. the `EpisodeResult` once the judge ends the episode (the controller's hand-over, the time
   limit, the vehicle leaving the world or reaching the ground without a hand-over).

The true pose of each of the last `FRAME_POSES_KEPT` frames is kept: `note_status` places the spot
pixel of the controller's confirming look (`ControllerStatus.confirmed_*`) on the ground with the
pose THAT frame was rendered at, and hands the point to the judge (touchdown error).

`step(cmd)` applies the controller's answer to step k for dt and returns step k+1. A command
counts only while it is fresh on the sim's own clock, as an autopilot's guided mode does
(ArduPilot's GUID_TIMEOUT): its stamp must be on the "sim" clock, not in the future, and at most
the vehicle's `cmd_timeout_s` old; otherwise it is dropped (counted in `commands_dropped`) and the
vehicle flies on the last fresh one until that, too, times out and it brakes to a hover. In
lockstep every command carries the stamp of the state it answers, so none is ever dropped. The Zenoh
service publishes these in lockstep or real time; the bench calls them directly. Timing presets
(`reference`, `real`) set the perception rate and latency; see REFERENCE.md "Time in the
reference".
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from dovesei.shared import validate
from dovesei.shared.clock import wall_time_s
from dovesei.shared.crop import CropLimits, RateLimit, plan_crop
from dovesei.shared.errors import ConfigError
from dovesei.shared.mission import HANDOVER_ALT_M, PERSON_SEPARATION_M, SAFETY_RADIUS_M, VEHICLE_SEPARATION_M
from dovesei.shared.timing import DEFAULT_TIMING, timing
from dovesei.shared.messages import (
    CameraFrame, ClassEntry, ControllerStatus, CropFrame, CropRequest, EpisodeResult, GroundTruth, Stamp, VehicleState,
    VelocityCommand, VisualOdometry,
)
from dovesei.sim.camera import (
    CameraError, CameraModel, ground_point_m, optical_axis_ground_m, render, render_ground_square,
)
from dovesei.shared.frames import body_frd_to_ned
from dovesei.sim.dynamics import Pose, Vehicle, VehicleParams
from dovesei.sim.estimator import SIM_DEFAULT_VEHICLE_PROFILE, Estimate, Estimator, vehicle_profile
from dovesei.sim.judge import NO_HANDOVER_REASON, EpisodeJudge
from dovesei.sim.odometry import SimOdometry
from dovesei.sim.starts import Start
from dovesei.sim.world import World

# The frame period and perception latency of each preset come from dovesei.shared.timing (its one
# owner): `reference` renders a frame every controller tick, one tick old when used; `real` is a
# CLIPSeg on a ground station (2 Hz, 0.4 s).
_EPS_S = 1e-9  # float slack when comparing accumulated sim times
# True poses of this many recent frames are kept for the judge: 34 min of frames at 2 Hz, 3.4 min
# at the reference's 20 Hz; a confirmation older than that is reported as unknown, never guessed.
FRAME_POSES_KEPT = 4096

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimConfig:
    """Everything the sim needs besides the world and the start; units in the names."""

    vehicle_id: str = "uav1"
    timing: str = DEFAULT_TIMING
    dt_s: float = 0.05  # one step = one controller tick (20 Hz)
    frame_period_s: float | None = None  # None: the timing preset's
    latency_s: float | None = None  # None: the timing preset's
    camera: CameraModel = field(default_factory=CameraModel)
    # The profile's dynamics, with every field of `vehicle` that differs from VehicleParams()
    # taking precedence (an explicit --cmd-max-age-s wins over the profile's GUID_TIMEOUT).
    vehicle_profile: str = SIM_DEFAULT_VEHICLE_PROFILE
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    handover_alt_m: float = HANDOVER_ALT_M  # the judge ends and judges the episode here
    time_limit_s: float = 1200.0
    safety_radius_m: float = SAFETY_RADIUS_M  # the judge's landing disk
    # The judge's separations from people and vehicles at the hand-over (0: that rule off).
    person_separation_m: float = PERSON_SEPARATION_M
    vehicle_separation_m: float = VEHICLE_SEPARATION_M
    seed: int = 0
    attach_truth: bool = True
    # False: frames carry a blank image (truth labels only). For the in-process bench with the
    # simulated perception, which reads only the labels: skips the costliest warp per frame.
    render_image: bool = True
    odometry_rate_hz: float = 0.0  # visual odometry views per sim second (10 = the camera's); 0 = off
    # Odometry views this wide (square pixels, the camera's field of view; None: the camera's
    # width). The bench renders them at half width for speed: fewer, coarser corners, a noisier
    # velocity than the camera's own (dovesei bench-odometry measures both).
    odometry_width_px: int | None = None
    # The autopilot fuses the odometry into its velocity estimate (see 3. above). A modelling
    # choice, not a measured value: tau 1 s, about what EKF3 takes to pull its velocity onto a
    # 10 Hz measurement whose variance is far below its own (EK3_VELNE_M_NSE 0.5 m/s); the
    # quality floor and variance ceiling are the controller's (`odometry_min_quality`,
    # OdometryLimits.max_var_m2_s2): its MAVLink adapter sends the EKF those samples only.
    external_nav: bool = False
    external_nav_tau_s: float = 1.0
    external_nav_min_quality: float = 0.5
    external_nav_max_var_m2_s2: float = 1.0
    # Close looks (`crop`): the simulated camera's full-resolution width (its frames are `camera`
    # shrunk from it; a 12 MP drone camera is 4000 px wide) and what it agrees to cut, on sim time.
    crop_source_px: int = 4000
    crop_limits: CropLimits = field(default_factory=CropLimits)

    def __post_init__(self) -> None:
        timing(self.timing)  # a ConfigError naming the presets
        profile = vehicle_profile(self.vehicle_profile)  # a ConfigError naming the profiles
        for name in ("dt_s", "time_limit_s", "safety_radius_m"):
            validate.positive(f"sim {name}", getattr(self, name))
        validate.non_negative("sim handover_alt_m", self.handover_alt_m)
        validate.non_negative("sim person_separation_m", self.person_separation_m)
        validate.non_negative("sim vehicle_separation_m", self.vehicle_separation_m)
        validate.in_range("sim odometry_rate_hz", self.odometry_rate_hz, 0.0, 100.0)
        if self.odometry_width_px is not None:
            validate.in_range("sim odometry_width_px", self.odometry_width_px, 32, self.camera.width_px)
            if isinstance(self.odometry_width_px, bool) or not isinstance(self.odometry_width_px, int):
                raise ConfigError(f"sim odometry_width_px must be an integer, got {self.odometry_width_px!r}")
        if self.external_nav:
            if not self.odometry_rate_hz > 0.0:
                raise ConfigError("sim external_nav fuses the visual odometry: it needs odometry_rate_hz > 0")
            if profile.estimator is None:
                raise ConfigError(f"sim external_nav needs a vehicle that estimates its velocity; vehicle profile "
                                  f"{self.vehicle_profile!r} reports the truth")
        validate.positive("sim external_nav_tau_s", self.external_nav_tau_s)
        validate.in_range("sim external_nav_min_quality", self.external_nav_min_quality, 0.0, 1.0)
        validate.positive("sim external_nav_max_var_m2_s2", self.external_nav_max_var_m2_s2)
        validate.in_range("sim crop_source_px", self.crop_source_px, self.camera.width_px, 16384)
        for name in ("frame_period_s", "latency_s"):
            if getattr(self, name) is not None:
                validate.non_negative(f"sim {name}", getattr(self, name))
        if self.period_s < self.dt_s - _EPS_S:
            raise ConfigError(f"frame period {self.period_s} s is shorter than the step {self.dt_s} s")
        if not 0.0 <= self.delay_s <= 10.0:
            raise ConfigError(f"perception latency {self.delay_s} s outside 0..10 s")

    @property
    def odometry_camera(self) -> CameraModel:
        """The camera the odometry views are rendered with: the camera's, `odometry_width_px` wide."""
        w = self.odometry_width_px
        if w is None or w == self.camera.width_px:
            return self.camera
        return CameraModel(w, max(1, round(self.camera.height_px * w / self.camera.width_px)), self.camera.hfov_deg)

    @property
    def period_s(self) -> float:
        return timing(self.timing).frame_period_s if self.frame_period_s is None else self.frame_period_s

    @property
    def delay_s(self) -> float:
        return timing(self.timing).latency_s if self.latency_s is None else self.latency_s


@dataclass(frozen=True)
class StepOut:
    state: VehicleState
    frame: CameraFrame | None
    result: EpisodeResult | None
    odometry: VisualOdometry | None = None


class SimCore:
    """One episode on one world from one start; deterministic for a given config."""

    def __init__(self, world: World, start: Start, config: SimConfig = SimConfig()) -> None:
        self.world, self.start, self.config = world, start, config
        # Frames and crops show the world as a camera sees it (`World.perceived`); the judge reads `world`.
        self._seen = world.perceived()
        self._classes = truth_classes(self._seen)
        self.judge: EpisodeJudge | None = None
        self.vehicle: Vehicle | None = None
        self._newest: tuple[CameraFrame, tuple[float, ...]] | None = None  # before reset: nothing to crop
        self._crop_rate = RateLimit(config.crop_limits.rate_hz, config.crop_limits.burst)

    def reset(self) -> StepOut:
        cfg = self.config
        profile = vehicle_profile(cfg.vehicle_profile)
        self.vehicle = Vehicle(Pose(self.start.x_m, self.start.y_m, self.start.alt_m, yaw_rad=self.start.yaw_rad),
                               profile.episode_dynamics(cfg.vehicle, cfg.seed), seed=cfg.seed)
        self._gimbal = profile.gimbal
        self.estimator = None if profile.estimator is None else Estimator(profile.estimator, cfg.seed, cfg.dt_s)
        self.judge = EpisodeJudge(self.world, handover_alt_m=cfg.handover_alt_m, time_limit_s=cfg.time_limit_s,
                                  safety_radius_m=cfg.safety_radius_m, person_separation_m=cfg.person_separation_m,
                                  vehicle_separation_m=cfg.vehicle_separation_m)
        self._odometry = SimOdometry(self.world, cfg.odometry_camera, cfg.vehicle_id, cfg.odometry_rate_hz) \
            if cfg.odometry_rate_hz > 0 else None
        self.fused = 0  # odometry samples the autopilot fused (external_nav)
        self._fused_t_s: float | None = None  # the stamp of the last one
        self._k = 0
        self._frame_seq = -1
        self._in_flight: deque[tuple[int, float]] = deque()  # (frame seq, sim time its heatmap is due)
        self._last_cmd: VelocityCommand | None = None
        self._result: EpisodeResult | None = None
        self.commands_dropped = 0
        # frame seq -> the true pose it was rendered at: x, y, altitude, yaw, roll, pitch
        self._frame_poses: OrderedDict[int, tuple[float, ...]] = OrderedDict()
        self._confirmed_look: tuple[int, float, float] | None = None
        # The newest frame and the true pose it was rendered at (one tuple, replaced whole: a
        # crop served from another thread reads it without a lock).
        self._newest: tuple[CameraFrame, tuple[float, ...]] | None = None
        self._crop_rate = RateLimit(cfg.crop_limits.rate_hz, cfg.crop_limits.burst)
        return self._emit()

    @property
    def t_s(self) -> float:
        """Sim time of the current step (the stamps' time)."""
        return round(self._k * self.config.dt_s, 9)

    def position_m(self) -> tuple[float, float]:
        """Ground truth world position (x east, y north): for reports, never sent to the controller."""
        st = self.vehicle.state
        return st.x_m, st.y_m

    def true_pose(self) -> Pose:
        """The vehicle's true pose (position, altitude, attitude): for the judge and reports only."""
        return self.vehicle.state

    def step(self, cmd: VelocityCommand | None) -> StepOut:
        """Apply the newest command for one step (None: keep the last one; it times out in the vehicle)."""
        if self.vehicle is None:
            raise RuntimeError("SimCore.step() before reset()")
        if self._result is not None:
            raise RuntimeError("the episode has ended; reset() to fly another")
        if cmd is not None:
            if self.is_fresh(cmd):
                self._last_cmd = cmd
            else:
                self.commands_dropped += 1
        c = self._last_cmd
        self.vehicle.step(self.config.dt_s, c.vel_body_frd_m_s if c else None, c.yaw_rate_rad_s if c else 0.0,
                          c.stamp.t_s if c else None)
        self._k += 1
        return self._emit()

    def _fuse(self, odom: VisualOdometry) -> None:
        """The autopilot's EKF takes one odometry sample (external_nav): valid and good enough only."""
        cfg = self.config
        if (not odom.valid or odom.quality < cfg.external_nav_min_quality
                or odom.vel_var_m2_s2 > cfg.external_nav_max_var_m2_s2 or not odom.dt_s > 0.0):
            return
        n, e, _d = body_frd_to_ned(odom.vel_body_frd_m_s, odom.roll_rad, odom.pitch_rad, odom.yaw_rad)
        # Each sample weighs the time since the last one fused, not the interval it spans: the
        # camera compares frames up to 0.5 s apart at 10 Hz, and overlapping intervals would
        # otherwise count the same motion five times over.
        last = self._fused_t_s
        weight_s = odom.dt_s if last is None or odom.stamp.t_s <= last else min(odom.stamp.t_s - last, odom.dt_s)
        self._fused_t_s = odom.stamp.t_s
        self.vehicle.fuse_ground_velocity((n, e), weight_s, cfg.external_nav_tau_s)
        self.fused += 1

    def is_fresh(self, cmd: VelocityCommand) -> bool:
        """True when the command's stamp is on the sim clock, not ahead of it and not too old."""
        age_s = self.t_s - cmd.stamp.t_s
        return cmd.stamp.clock == "sim" and -_EPS_S <= age_s <= self.vehicle.params.cmd_timeout_s + _EPS_S

    def note_status(self, status: ControllerStatus) -> None:
        """Take the controller's confirming look from its status: the spot pixel of that frame,
        placed on the ground with the frame's true pose, becomes the judge's confirmed point."""
        if self.judge is None or self._result is not None:
            return
        look = ((status.confirmed_frame_seq, status.confirmed_row_px, status.confirmed_col_px)
                if status.confirmed_valid else None)
        if look == self._confirmed_look:
            return  # the same look again: nothing to place
        self._confirmed_look = look
        if look is None:
            self.judge.confirm(None)
            return
        pose = self._frame_poses.get(look[0])
        if pose is None:
            log.warning("confirming frame %d is not among the %d frames kept: touchdown error unknown", look[0],
                        len(self._frame_poses))
            self.judge.confirm(None)
            return
        x_m, y_m, alt_m, yaw_rad, roll_rad, pitch_rad = pose
        try:
            point = ground_point_m(x_m, y_m, alt_m, yaw_rad, look[1], look[2], self.config.camera, roll_rad, pitch_rad)
        except CameraError as exc:
            log.warning("confirming look (frame %d): %s: touchdown error unknown", look[0], exc)
            point = None
        self.judge.confirm(point)

    @property
    def result(self) -> EpisodeResult | None:
        """The episode's result once it has ended (by the judge or by `abort`), else None."""
        return self._result

    def abort(self, detail: str) -> EpisodeResult:
        """End the episode as 'error' (e.g. the controller stopped answering); `detail` says why.

        The result carries the time, path and pose reached so far; an episode that already has a
        verdict keeps it (the judge's word is final).
        """
        if self.vehicle is None:
            raise RuntimeError("SimCore.abort() before reset()")
        if self._result is None:
            self._result = self._episode_result("error", detail)
        return self._result

    def _emit(self) -> StepOut:
        cfg = self.config
        # Sim time is k * dt rounded to the nanosecond, not the vehicle's running sum: summing
        # 0.05 s drifts (60 steps sum to 2.9999999999999996 s), which would shift frames and
        # time limits by a step depending on float luck.
        sched_t_s = round(self._k * cfg.dt_s, 9)
        pose = dataclasses.replace(self.vehicle.state, t_s=sched_t_s)
        # The hand-over is the controller's word on its newest fresh command, never the altitude.
        outcome = self.judge.check(pose, handover=self._last_cmd is not None and self._last_cmd.handover)
        est = None if self.estimator is None else self.estimator.update(pose, self.vehicle.vel_own_ned_m_s)
        frame = None
        if outcome is None and sched_t_s >= (self._frame_seq + 1) * cfg.period_s - _EPS_S:
            frame = self._render(pose, est)
            self._in_flight.append((frame.seq, sched_t_s + cfg.delay_s))
        await_seq = -1
        # At most one heatmap becomes due per step (frame period >= step); take the newest due.
        while self._in_flight and self._in_flight[0][1] <= sched_t_s + _EPS_S:
            await_seq = self._in_flight.popleft()[0]
        if est is None:
            state = VehicleState(
                vehicle_id=cfg.vehicle_id, seq=self._k, stamp=Stamp(pose.t_s, "sim"), alt_agl_m=pose.alt_agl_m,
                vel_body_frd_m_s=pose.vel_body_frd_m_s(), yaw_rad=pose.yaw_rad, armed=True, mode="SIM",
                pos_valid=True, pos_local_ned_m=(pose.y_m - self.start.y_m, pose.x_m - self.start.x_m, -pose.alt_agl_m),
                await_frame_seq=await_seq, sent_wall_s=wall_time_s())
        else:
            # What the autopilot reports: no GNSS, so no valid position (the dead-reckoned one
            # travels along for displays, flagged invalid); the truth stays with the judge.
            state = VehicleState(
                vehicle_id=cfg.vehicle_id, seq=self._k, stamp=Stamp(pose.t_s, "sim"), alt_agl_m=est.alt_agl_m,
                vel_body_frd_m_s=est.vel_body_frd_m_s, roll_rad=est.roll_rad, pitch_rad=est.pitch_rad,
                yaw_rad=est.yaw_rad, armed=True, mode="SIM", pos_valid=False, pos_local_ned_m=est.pos_local_ned_m,
                await_frame_seq=await_seq, sent_wall_s=wall_time_s())
        odometry = None
        if self._odometry is not None and outcome is None:
            # Rendered where the vehicle truly is (tilted with the body unless gimballed), told
            # only what the state reports.
            roll, pitch = (0.0, 0.0) if self._gimbal else (pose.roll_rad, pose.pitch_rad)
            odometry = self._odometry.observe(pose.x_m, pose.y_m, pose.alt_agl_m, pose.yaw_rad, state,
                                              roll_rad=roll, pitch_rad=pitch,
                                              tag_roll_pitch_rad=(0.0, 0.0) if self._gimbal else None)
            if cfg.external_nav and odometry is not None:
                self._fuse(odometry)
        if outcome is not None:
            self._result = self._episode_result(outcome)
        return StepOut(state, frame, self._result, odometry)

    def _render(self, pose: Pose, est: Estimate | None) -> CameraFrame:
        """The frame at the true pose, tilted with the body unless gimballed, labelled with the
        estimate (the altitude and attitude a real camera service takes from the autopilot)."""
        cfg = self.config
        alt_m = max(pose.alt_agl_m, 0.1)
        roll, pitch = (0.0, 0.0) if self._gimbal else (pose.roll_rad, pose.pitch_rad)
        image, labels, _valid = render(self._seen, pose.x_m, pose.y_m, alt_m, pose.yaw_rad, cfg.camera,
                                       roll_rad=roll, pitch_rad=pitch, with_image=cfg.render_image,
                                       with_labels=cfg.attach_truth,  # labels unused: skip their warp
                                       t_s=pose.t_s)  # people and cars where they are now
        if image is None:
            image = self._blank_image()
        centre = (pose.x_m, pose.y_m) if roll == 0.0 and pitch == 0.0 else \
            optical_axis_ground_m(pose.x_m, pose.y_m, alt_m, pose.yaw_rad, roll, pitch)
        truth = GroundTruth(labels, self._classes, centre, self.world.name) \
            if cfg.attach_truth and labels is not None else None
        self._frame_seq += 1
        if est is None:
            frame = CameraFrame(cfg.vehicle_id, self._frame_seq, Stamp(pose.t_s, "sim"), image, cfg.camera.hfov_rad,
                                pose.alt_agl_m, yaw_rad=pose.yaw_rad, sent_wall_s=wall_time_s(), truth=truth)
        else:
            # A gimballed camera's frame is level whatever the autopilot's attitude says.
            label_roll, label_pitch = (0.0, 0.0) if self._gimbal else (est.roll_rad, est.pitch_rad)
            frame = CameraFrame(cfg.vehicle_id, self._frame_seq, Stamp(pose.t_s, "sim"), image, cfg.camera.hfov_rad,
                                est.alt_agl_m, roll_rad=label_roll, pitch_rad=label_pitch, yaw_rad=est.yaw_rad,
                                sent_wall_s=wall_time_s(), truth=truth)
        # The TRUE pose the frame was rendered at, attitude included (not the frame's labels, which
        # are the estimate), for placing its pixels later.
        self._frame_poses[frame.seq] = (pose.x_m, pose.y_m, alt_m, pose.yaw_rad, roll, pitch)
        self._newest = (frame, self._frame_poses[frame.seq])
        if len(self._frame_poses) > FRAME_POSES_KEPT:
            self._frame_poses.popitem(last=False)
        return frame

    def crop(self, req: CropRequest) -> CropFrame:
        """A close look: the square the request names, cut from the newest frame's full-resolution
        view (rendered from the world at that frame's TRUE pose; tagged, like the frame, with what
        the autopilot reported). CropRefused (one line) for a request a camera would refuse; the
        rate limit runs on sim time, so a lockstep episode stays deterministic."""
        newest = self._newest
        view = None if newest is None else (newest[0], newest[1], newest[0].stamp.t_s)
        return crop_view(self._seen, self.config, self._classes, self._crop_rate,
                         self.t_s if self.vehicle is not None else 0.0, req, view)

    def _blank_image(self):
        if getattr(self, "_blank", None) is None:
            cam = self.config.camera
            self._blank = np.zeros((cam.height_px, cam.width_px, 3), np.uint8)
            self._blank.flags.writeable = False  # shared by every frame: nobody may draw on it
        return self._blank

    def _episode_result(self, outcome: str, detail: str = "") -> EpisodeResult:
        return judge_result(self.config.vehicle_id, self.judge, outcome, detail, clock="sim")


def truth_classes(world: World) -> tuple[ClassEntry, ...]:
    """A world's classes as frames and crops carry them with their truth labels (id order)."""
    return tuple(ClassEntry(int(i), c.name, bool(c.safe)) for i, c in sorted(world.classes.items()))


def crop_view(world: World, cfg: SimConfig, classes: tuple, rate: RateLimit, now_s: float, req: CropRequest,
              view: tuple[CameraFrame, tuple[float, ...], float] | None) -> CropFrame:
    """The crop `req` asks for from `view`: (the newest frame, the TRUE pose it was rendered at as
    (x, y, alt, yaw, roll, pitch), the episode time its people stood at), None before any frame.
    CropRefused (one line) for a request a camera would refuse; `rate` is checked at `now_s`."""
    frame, (x_m, y_m, alt_m, yaw_rad, roll, pitch), people_t_s = view if view is not None else (None, (0.0,) * 6, 0.0)
    width = cfg.crop_source_px
    height = round(width * cfg.camera.height_px / cfg.camera.width_px)
    plan = plan_crop(req, cfg.crop_limits, rate, now_s, vehicle_id=cfg.vehicle_id,
                     newest_seq=None if frame is None else frame.seq, alt_agl_m=alt_m, roll_rad=roll,
                     pitch_rad=pitch, width_px=width, height_px=height, hfov_rad=cfg.camera.hfov_rad)
    fwd, right = req.centre_frd_m
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    cx, cy = x_m + c * right + s * fwd, y_m + c * fwd - s * right  # as the renderer turns body into world
    image, labels, _valid = render_ground_square(world, cx, cy, yaw_rad, req.side_m, req.out_px,
                                                 with_image=cfg.render_image, with_labels=cfg.attach_truth,
                                                 t_s=people_t_s)  # people where they were at the capture
    if image is None:
        image = np.zeros((req.out_px, req.out_px, 3), np.uint8)
    truth = GroundTruth(labels, classes, (cx, cy), world.name) if labels is not None else None
    return CropFrame(cfg.vehicle_id, req.request_seq, frame.seq, frame.stamp, image, req.centre_frd_m, req.side_m,
                     frame.alt_agl_m, plan.source_m_per_px, roll_rad=frame.roll_rad, pitch_rad=frame.pitch_rad,
                     yaw_rad=frame.yaw_rad, sent_wall_s=wall_time_s(), truth=truth)


def unstarted_result(world: World, start: Start, config: SimConfig, detail: str, clock: str = "sim") -> EpisodeResult:
    """The 'error' result of an episode that could not begin (`detail` says why), placed at the start."""
    judge = EpisodeJudge(world, handover_alt_m=config.handover_alt_m, time_limit_s=config.time_limit_s,
                         safety_radius_m=config.safety_radius_m, person_separation_m=config.person_separation_m,
                         vehicle_separation_m=config.vehicle_separation_m)
    judge.check(Pose(start.x_m, start.y_m, start.alt_m, yaw_rad=start.yaw_rad), handover=False)
    return judge_result(config.vehicle_id, judge, "error", detail, clock=clock)


def judge_result(vehicle_id: str, judge: EpisodeJudge, outcome: str, detail: str = "",
                 clock: str = "sim") -> EpisodeResult:
    """The wire `EpisodeResult` of an episode the judge has watched (also for 'error' endings).

    Shared by `SimCore` and the service's external-pose mode, whose pose comes from an autopilot
    and whose stamps are on the vehicle's clock.
    """
    pose, v = judge.last_state, judge.verdict
    classes = tuple(f"{c.name}:{c.fraction:.3f}" for c in v.classes) if v else ()
    closest = v.closest_unsafe_m if v else None
    if not detail and judge.crashed:
        detail = NO_HANDOVER_REASON
    if not detail:
        detail = v.reason if v else {"timeout": f"no landing within {judge.time_limit_s:.0f} s of {clock} time",
                                     "out_of_world": "the vehicle left the world",
                                     "not_judged": "reached the hand-over altitude over a world without labels: "
                                                   "not judged"}.get(outcome, "")
    t_s, x_m, y_m, alt_m = (pose.t_s, pose.x_m, pose.y_m, pose.alt_agl_m) if pose else (0.0, 0.0, 0.0, 0.0)
    confirmed, error = judge.confirmed_xy_m, judge.touchdown_error_m
    return EpisodeResult(vehicle_id, Stamp(t_s, clock), outcome, judge.sim_time_s, judge.path_length_m,
                         x_m, y_m, alt_m, classes, closest is not None,
                         float(closest) if closest is not None else 0.0, detail,
                         confirmed_valid=confirmed is not None,
                         confirmed_x_m=float(confirmed[0]) if confirmed is not None else 0.0,
                         confirmed_y_m=float(confirmed[1]) if confirmed is not None else 0.0,
                         touchdown_error_valid=error is not None,
                         touchdown_error_m=float(error) if error is not None else 0.0,
                         nearest_person_valid=v is not None and v.nearest_person_m is not None,
                         nearest_person_m=float(v.nearest_person_m or 0.0) if v else 0.0,
                         nearest_vehicle_valid=v is not None and v.nearest_vehicle_m is not None,
                         nearest_vehicle_m=float(v.nearest_vehicle_m or 0.0) if v else 0.0,
                         separation_violated=bool(v and v.separation_violated))
