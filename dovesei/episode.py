"""One simulated landing episode with the three service cores wired by direct calls.

This is the lockstep protocol of the Zenoh services (see `dovesei.sim.core`) without the
network: the sim steps, a due camera frame goes to the segmenter, the heatmap is handed to the
controller at the step the sim says it becomes available (`await_frame_seq`), the controller
ticks and its command drives the next sim step. The same cores in three processes over Zenoh
give the same trajectory for the same seed (tests/e2e check it); the bench uses this runner
because it is much cheaper than three processes per episode.

    SimCore.step(cmd) --frame--> SegmenterCore.process --heatmap--> (held until due)
          ^                                                              |
          +---------- VelocityCommand <-- ControllerCore.tick(state) <---+
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.gnss_denied import NavJudge, NavStatus, OdometryGate, OdometryLimits
from dovesei.controller.looker import SyncLooker
from dovesei.controller.mavlink.proto import EKF_FLAGS_NEEDED, EKF_POS_HORIZ_ABS, GPS_FIX_TYPE_3D
from dovesei.controller.policies.registry import make_policy
from dovesei.controller.policies.config_file import config_from_values
from dovesei.segmenter.core import FrameRejected, SegmenterConfig, SegmenterCore, make_backend
from dovesei.segmenter.prompts import REFERENCE_PROMPTS, PromptSet
from dovesei.segmenter.simulated import DEFAULT_NOISE, DEFAULT_PROFILE, PROFILE_NAMES
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.messages import (
    CropFrame,
    CropHeatmap,
    CropRequest,
    EpisodeResult,
    Message,
    SafetyHeatmap,
    VisualOdometry,
)
from dovesei.shared.mission import HANDOVER_ALT_M, PERSON_SEPARATION_M, VEHICLE_SEPARATION_M
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.estimator import SIM_DEFAULT_VEHICLE_PROFILE
from dovesei.sim.starts import Start
from dovesei.sim.world import World

log = logging.getLogger(__name__)

# The paper's policies are flown with the paper's fusion (softmax over all prompts), on every
# backend: their thresholds were tuned on its output. Other policies get the segmenter's default.
REFERENCE_FUSION_POLICIES = ("dovesei", "dovesei-nofocus")
REFERENCE_FUSION = "dovesei"
DEFAULT_PERCEPTION = DEFAULT_PROFILE
# A bench vehicle on the camera's visual velocity (--gnss-denied external-nav): views at the camera
# service's rate and at the width its estimator works at (VisualVelocityConfig.work_width_px: a
# 640 px camera is area-averaged to 320 px). The controller judges those samples as on a real
# autopilot (`VisualNav`), so a narrower view would fly a worse camera than the real one: at 176 px
# the samples' own variance at 100 m was over the controller's limit in 2 of 48 pairs against 19
# of 48 at 320 px (0.5 s baseline; session measurement, docs/RESULTS.md).
BENCH_ODOMETRY_HZ = 10.0
BENCH_ODOMETRY_WIDTH_PX = 320


def perception_names() -> tuple[str, ...]:
    """The simulated perception profiles (dovesei.segmenter.simulated)."""
    return PROFILE_NAMES


def fusion_for(policy: str) -> str | None:
    """The fusion mode a policy must be flown with, or None for the segmenter's default."""
    return REFERENCE_FUSION if policy in REFERENCE_FUSION_POLICIES else None


def prompt_set(prompts: dict | PromptSet | None) -> PromptSet:
    """A PromptSet from a job's plain dict ({positive, negative, template}); None = the reference's."""
    if prompts is None:
        return REFERENCE_PROMPTS
    if isinstance(prompts, PromptSet):
        return prompts
    try:
        return PromptSet(positive=tuple(prompts["positive"]), negative=tuple(prompts["negative"]),
                         template=prompts.get("template", REFERENCE_PROMPTS.template))
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"prompt set {prompts!r}: {exc}") from None


@dataclass(frozen=True)
class EpisodeSpec:
    """Everything that defines one episode; equal specs give equal trajectories."""

    policy: str
    start: Start
    timing: str = "reference"
    seed: int = 0  # seeds the simulated perception and the vehicle's disturbances
    noise: float | None = None  # error scale within the perception profile (None: DEFAULT_NOISE, 1)
    time_limit_s: float = 1200.0
    vehicle_id: str = "uav1"
    perception: str = DEFAULT_PERCEPTION  # simulated perception profile
    prompts: PromptSet = REFERENCE_PROMPTS
    vehicle_profile: str = SIM_DEFAULT_VEHICLE_PROFILE  # what the autopilot reports (dovesei.sim.estimator)
    handover_alt_m: float = HANDOVER_ALT_M  # handed to the controller (and so the policy) and the sim's judge
    # The judge's separations from people and vehicles at the hand-over (0: that rule off).
    separation_m: tuple[float, float] = (PERSON_SEPARATION_M, VEHICLE_SEPARATION_M)
    # The policy's constants that differ from the timing preset's (a --policy-config file's), as
    # sorted (name, value) pairs so the spec stays hashable; () = the preset.
    policy_config: tuple[tuple[str, Any], ...] = ()
    # `clearance` looks at its spot at full resolution before committing (issue 24): the sim cuts
    # the crop, the segmenter scores it with the never set, both in this process.
    close_look: bool = True
    # (a, b): every heatmap is recalibrated to sigmoid(a logit P + b) (the bench's --perception-shift).
    perception_shift: tuple[float, float] | None = None
    # The autopilot fuses the camera's visual velocity (the bench's --gnss-denied external-nav): the
    # sim renders odometry views at BENCH_ODOMETRY_HZ, BENCH_ODOMETRY_WIDTH_PX wide (SimConfig.external_nav).
    external_nav: bool = False

    @classmethod
    def from_job(cls, job: dict, start: Start) -> EpisodeSpec:
        """The spec a bench job (a plain, picklable dict) describes."""
        return cls(policy=job["policy"], start=start, timing=job["timing"], seed=job["seed"], noise=job.get("noise"),
                   time_limit_s=job["time_limit_s"], perception=job.get("perception") or DEFAULT_PERCEPTION,
                   prompts=prompt_set(job.get("prompts")),
                   vehicle_profile=job.get("vehicle_profile") or SIM_DEFAULT_VEHICLE_PROFILE,
                   handover_alt_m=job.get("handover_alt_m", HANDOVER_ALT_M),
                   separation_m=tuple(job.get("separation_m") or (PERSON_SEPARATION_M, VEHICLE_SEPARATION_M)),
                   close_look=job.get("close_look", True),
                   policy_config=tuple(sorted((k, tuple(v) if isinstance(v, list) else v)
                                              for k, v in (job.get("policy_config") or {}).items())),
                   perception_shift=None if job.get("perception_shift") is None else
                   (float(job["perception_shift"]["a"]), float(job["perception_shift"]["b"])),
                   external_nav=job.get("gnss_denied") == "external-nav")


@dataclass
class EpisodeRecord:
    """The judge's verdict plus the path, for results and plots."""

    spec: EpisodeSpec
    result: EpisodeResult
    wall_time_s: float
    # One row per sim step: t_s, x_m, y_m, alt_agl_m (all true, the judge's view, never the
    # estimate); `states` holds the controller state per row.
    track: np.ndarray = dataclasses.field(repr=False, default_factory=lambda: np.zeros((0, 4)))
    states: list[str] = dataclasses.field(repr=False, default_factory=list)


def separation_fields(r: EpisodeResult) -> dict:
    """The judge's separation figures of a landing it judged (null when it judged none): the
    nearest person's and vehicle's footprint distance from the touchdown (null: none within the
    judge's search radius) and whether one was closer than its separation."""
    judged = bool(r.classes_found)  # a verdict always lists the disk's classes
    return {"nearest_person_m": round(r.nearest_person_m, 3) if judged and r.nearest_person_valid else None,
            "nearest_vehicle_m": round(r.nearest_vehicle_m, 3) if judged and r.nearest_vehicle_valid else None,
            "separation_violated": bool(r.separation_violated) if judged else None}


def build_cores(world: World, spec: EpisodeSpec, *, render_images: bool = False,
                record: Callable[[Message], None] | None = None) -> tuple[SimCore, SegmenterCore, ControllerCore]:
    """The three cores as the three services build them from the same options.

    The simulated perception reads only the frames' truth labels, so by default the sim skips
    drawing the pixels nobody looks at; the trajectory is the same either way. The controller's
    close looks are answered by the sim's `crop` and the segmenter's `process_crop` at once (as the
    lockstep services answer them while the sim waits); `record` sees each crop and its scores.
    """
    sim = SimCore(world, spec.start, SimConfig(vehicle_id=spec.vehicle_id, timing=spec.timing, seed=spec.seed,
                                               time_limit_s=spec.time_limit_s, render_image=render_images,
                                               vehicle_profile=spec.vehicle_profile,
                                               handover_alt_m=spec.handover_alt_m,
                                               person_separation_m=spec.separation_m[0],
                                               vehicle_separation_m=spec.separation_m[1],
                                               **(dict(external_nav=True, odometry_rate_hz=BENCH_ODOMETRY_HZ,
                                                       odometry_width_px=BENCH_ODOMETRY_WIDTH_PX)
                                                  if spec.external_nav else {})))
    seg_config = segmenter_config(spec)
    seg = SegmenterCore(make_backend(seg_config), seg_config)
    ctrl_config = ControllerConfig(vehicle_id=spec.vehicle_id, policy=spec.policy, timing=spec.timing,
                                   lockstep=True, handover_alt_m=spec.handover_alt_m, close_look=spec.close_look)
    # A policy file's constants, checked as the file was; the hand-over still the controller's.
    policy = None if not spec.policy_config else make_policy(
        spec.policy, config_from_values(spec.policy, dict(spec.policy_config), spec.timing, "episode policy_config"),
        handover_alt_m=spec.handover_alt_m, close_look=spec.close_look)
    ctrl = ControllerCore(ctrl_config, policy=policy, looker=SyncLooker(in_process_ask(sim, seg, record)))
    return sim, seg, ctrl


class VisualNav:
    """The controller's navigation judgement of a bench vehicle on the camera's velocity
    (`--gnss-denied external-nav`), as its MAVLink adapter makes it on a real autopilot.

    GNSS was lost before the episode (a 3D fix, then none) and the simulated EKF fuses the
    camera's velocity (it reports attitude, velocity and a relative position, no absolute one), so
    the velocity is trusted exactly while the controller's own `OdometryGate` holds a good sample
    (valid, quality >= odometry_min_quality, variance within its limit) newer than
    odometry_max_age_s. Without one the controller holds and does not descend
    (`Mode.NO_VELOCITY`): a bench that descended anyway would fly what dovesei never flies.
    """

    def __init__(self, config: ControllerConfig) -> None:
        self.gate = OdometryGate(OdometryLimits(max_age_s=config.odometry_max_age_s,
                                                min_quality=config.odometry_min_quality))
        self.judge = NavJudge("external-nav")
        self.judge.on_gps_fix(GPS_FIX_TYPE_3D)
        self.judge.on_ekf_flags(EKF_FLAGS_NEEDED | EKF_POS_HORIZ_ABS)
        self.judge.on_gps_fix(0)
        self.judge.on_ekf_flags(EKF_FLAGS_NEEDED)  # the absolute position gone with GNSS

    def add(self, odom: VisualOdometry) -> None:
        """A sample as the controller receives it: on the sim clock, at its own stamp."""
        self.gate.add(odom, odom.stamp.t_s)

    def status(self, now_s: float) -> NavStatus:
        return self.judge.status(now_s, self.gate)


def in_process_ask(sim: SimCore, seg: SegmenterCore, record: Callable[[Message], None] | None = None):
    """A close look answered in this process: the sim's crop, the segmenter's scores."""
    def ask(req: CropRequest) -> tuple[CropFrame, CropHeatmap]:
        crop = sim.crop(req)
        try:
            heatmap = seg.process_crop(crop)
        except FrameRejected as exc:
            raise DoveseiError(f"segment refused the crop: {exc}") from None
        if record is not None:
            record(crop)
            record(heatmap)
        return crop, heatmap
    return ask


def segmenter_config(spec: EpisodeSpec) -> SegmenterConfig:
    """The simulated segmenter's settings for an episode: profile, noise, seed, prompts, and the
    reference fusion for the paper's policies."""
    fusion = fusion_for(spec.policy)
    extra = {} if fusion is None else {"fusion": fusion}
    noise = DEFAULT_NOISE if spec.noise is None else spec.noise
    return SegmenterConfig(backend="sim", sim_profile=spec.perception, sim_noise=noise, sim_seed=spec.seed,
                           prompts=spec.prompts, prob_shift=spec.perception_shift, **extra)


def run_episode(world: World, spec: EpisodeSpec, *, record_track: bool = True,
                record: Callable[[Message], None] | None = None) -> EpisodeRecord:
    """Fly one episode to the judge's verdict, in this process; `record` sees every message
    (e.g. `dovesei.shared.recording.FlightRecorder.write`), in the order the services would."""
    record = record or (lambda msg: None)
    t0 = time.perf_counter()
    sim, seg, ctrl = build_cores(world, spec, record=record)
    pending: dict[int, SafetyHeatmap] = {}  # heatmaps computed but not yet due
    rows: list[tuple[float, float, float, float]] = []
    states: list[str] = []
    nav = VisualNav(ctrl.config) if spec.external_nav else None
    out = sim.reset()
    while True:
        if out.odometry is not None:
            record(out.odometry)
            if nav is not None:
                nav.add(out.odometry)
        record(out.state)
        if out.frame is not None:
            record(out.frame)
            pending[out.frame.seq] = seg.process(out.frame)
            record(pending[out.frame.seq])
        if record_track:
            truth = sim.true_pose()
            rows.append((out.state.stamp.t_s, truth.x_m, truth.y_m, truth.alt_agl_m))
        if out.result is not None:
            record(out.result)
            break
        due = out.state.await_frame_seq
        if due >= 0:
            ctrl.on_heatmap(pending.pop(due), time.time())
            # Older heatmaps that were never due (none with frame_period >= dt) would leak here.
            for seq in [s for s in pending if s < due]:
                del pending[seq]
        cmd, status = ctrl.tick(out.state, nav=nav.status(out.state.stamp.t_s) if nav is not None else None)
        sim.note_status(status)  # the judge learns the ground the policy last confirmed
        record(cmd)
        record(status)
        states.append(status.state)
        out = sim.step(cmd)
    if record_track:
        states.append(states[-1] if states else "SENSOR_ERROR")
    return EpisodeRecord(spec, out.result, time.perf_counter() - t0,
                         np.asarray(rows, dtype=np.float64).reshape(-1, 4), states)
