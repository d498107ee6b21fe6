"""The report of one `dovesei up` run: a typed structure, written as report.json with its pictures.

    UpOptions + Recorder + the services' stats files --build_report--> RunReport (frozen sections)
        --to_dict--> report.json (flat top-level keys: "outcome", "detail", "judged", ... as read by
                     tests, the contracts check and `dovesei.pictures.plots.plot_trajectory`)
        --write_outputs--> report.json, trajectory.png, episode.mp4

Sections: the episode (what the judge said), the setup (what was flown), timing (wall clocks and
latencies, from the services' own stamps), counts, the failure if any, and the trajectory.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from dovesei.pictures import plots
from dovesei.pictures import video as videos
from dovesei.pictures.common import ReportError, backend_label
from dovesei.controller.policies.config_file import load_policy_config, policy_values, preset_config
from dovesei.episode import separation_fields
from dovesei.shared.messages import ControllerStatus
from dovesei.shared.mission import HANDOVER_ALT_M, SAFETY_RADIUS_M
from dovesei.up.launch import SERVICES
from dovesei.up.monitor import STAGES, Recorder
from dovesei.up.options import UpOptions

if TYPE_CHECKING:  # watch imports this module (Failure): the annotation only
    from dovesei.up.watch import LandingWait

log = logging.getLogger("dovesei.up")

JUDGE_OUTCOMES = ("safe", "unsafe", "timeout", "out_of_world")
TRANSPORT_DEFINITION = ("per decision: frame->segmenter + heatmap->controller + command->sim, each stamped by the "
                        "receiving service (real time: the heatmap hop as the monitor sees it); excludes inference, "
                        "policy and lockstep waits")
DELIVERY_DEFINITION = ("per decision: frame, heatmap and command delivery as the monitor's callbacks see them "
                       "(no service polling)")


@dataclass(frozen=True)
class Percentiles:
    """p50/p99 of one latency in milliseconds; `n` samples. Optional notes say how it was measured."""

    p50_ms: float | None
    p99_ms: float | None
    n: int
    measured_by: str | None = None
    note: str | None = None
    definition: str | None = None

    @classmethod
    def of_seconds(cls, values: Sequence[float], **notes: str | None) -> Percentiles:
        if not values:
            return cls(None, None, 0, **notes)
        arr = np.asarray(values, dtype=np.float64) * 1e3
        return cls(round(float(np.percentile(arr, 50)), 3), round(float(np.percentile(arr, 99)), 3), int(arr.size),
                   **notes)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"p50": self.p50_ms, "p99": self.p99_ms, "n": self.n}
        out.update({k: v for k, v in (("measured_by", self.measured_by), ("note", self.note),
                                      ("definition", self.definition)) if v is not None})
        return out


@dataclass(frozen=True)
class Position:
    """A point in world metres (x east, y north) and its altitude above ground."""

    x_m: float
    y_m: float
    alt_m: float


@dataclass(frozen=True)
class Failure:
    """Why the run did not reach a judged end: a child that died or hung, or a start-up timeout."""

    child: str | None
    returncode: int | None
    last_line: str
    message: str


@dataclass(frozen=True)
class Episode:
    outcome: str  # safe, unsafe, timeout, out_of_world (judged) or error
    detail: str
    judged: bool
    sim_time_s: float
    path_length_m: float
    start: Position
    final: Position | None
    classes_found: tuple[str, ...]
    closest_unsafe_m: float | None
    confirmed: Position | None = None  # the ground the policy last confirmed (the judge's placing)
    touchdown_error_m: float | None = None  # the hand-over's true distance to it
    # At the hand-over: the nearest person's / vehicle's footprint distance (None: none within the
    # judge's search radius, or not judged) and whether one was closer than its separation.
    nearest_person_m: float | None = None
    nearest_vehicle_m: float | None = None
    separation_violated: bool | None = None


@dataclass(frozen=True)
class Setup:
    world: str
    backend: str
    simulated: bool
    segmenter_option: str
    noise: float | None
    perception: str | None  # the simulated perception's profile (None: not simulated)
    policy: str
    timing: str
    seed: int
    mode: str  # lockstep or realtime
    vehicle: str  # "sim:<vehicle profile>" (dovesei.sim.estimator) or the autopilot's MAVLink URL
    vehicle_id: str
    safety_radius_m: float
    time_limit_s: float
    handover_alt_m: float = HANDOVER_ALT_M  # where the controller handed over and the sim judged
    policy_config_file: str | None = None  # --policy-config, and the constants it changed from the preset
    policy_config: Mapping[str, Any] | None = None


@dataclass(frozen=True)
class RunTiming:
    wall_time_s: float
    episode_wall_s: float | None
    latency: Mapping[str, Percentiles]  # by stage
    transport_overhead: Percentiles
    zenoh_delivery_overhead: Percentiles
    delivery: Mapping[str, Percentiles]  # by topic, as the monitor's callbacks see it


@dataclass(frozen=True)
class Counts:
    frames: int
    heatmaps: int
    commands: int  # steering commands the controller sent (to the sim or to the autopilot)
    commands_measured_by: str  # "monitor" (cmd key), "controller" (its stats) or "controller status"
    statuses: int
    states: int
    rejected: int
    results_refused: int
    foreign: int
    # MAVLink: commands that asked for more than the vehicle's speed limits (clamped by the adapter),
    # of `commands_steered` flown; None with the sim or without the controller's stats.
    commands_clamped: int | None = None
    commands_steered: int | None = None


@dataclass(frozen=True)
class Trajectory:
    t_s: tuple[float, ...]
    x_m: tuple[float, ...]
    y_m: tuple[float, ...]
    alt_m: tuple[float, ...]
    state: tuple[str, ...]
    watchdog: tuple[str, ...]
    cmd_down_m_s: tuple[float, ...]
    look: tuple[str, ...] = ()  # the policy's last close look's verdict at each row ("" before any)


@dataclass(frozen=True)
class Landing:
    """A real autopilot's own landing after the hand-over ('land' or 'precland'; any action with
    --gnss-denied external-nav), as `up` waited for it."""

    action: str
    landed: bool  # the autopilot reported itself disarmed
    reason: str
    waited_s: float
    touchdown: Position | None  # the last state's position (start + the autopilot's local NED)
    landing_targets_sent: int | None  # precision landing: LANDING_TARGET messages the controller sent
    external_nav_sent: int | None = None  # external-nav: camera velocities the controller sent the EKF (whole run)


@dataclass(frozen=True)
class Navigation:
    """A real autopilot's navigation as the controller's status reported it (None with the sim)."""

    gnss_lost: bool
    gnss_lost_t_s: float | None  # the vehicle clock of the first status that said so
    gnss_lost_alt_m: float | None
    position_lost: bool  # the autopilot had no horizontal position at some point
    sources: tuple[str, ...]  # the trusted velocity sources, in the order they came
    no_velocity_holds: int  # statuses holding for want of a trusted velocity
    first_reason: str  # the first loss's reason
    last_reason: str

    @classmethod
    def of(cls, statuses: Mapping[float, Any]) -> Navigation | None:
        ordered = [statuses[t] for t in sorted(statuses)]
        if not any(st.nav_source for st in ordered):
            return None  # the sim: nothing judged
        lost = [st for st in ordered if st.gnss_lost]
        sources: list[str] = []
        for st in ordered:
            if st.nav_source and (not sources or sources[-1] != st.nav_source):
                sources.append(st.nav_source)
        return cls(bool(lost), lost[0].stamp.t_s if lost else None, lost[0].alt_agl_m if lost else None,
                   any(st.position_lost for st in ordered), tuple(sources),
                   sum(1 for st in ordered if "no trusted velocity source" in st.reason),
                   lost[0].nav_reason if lost else "", ordered[-1].nav_reason)


@dataclass(frozen=True)
class RunReport:
    episode: Episode
    setup: Setup
    timing: RunTiming
    counts: Counts
    trajectory: Trajectory
    service_stats: Mapping[str, Any]  # each service's own --stats-out JSON, as it wrote it
    failure: Failure | None
    interrupted: bool
    files: Mapping[str, str] | None = None  # name -> file in the report folder; filled by write_outputs
    landing: Landing | None = None  # only when `up` waited for an autopilot's landing
    navigation: Navigation | None = None  # a real autopilot's GNSS / position losses (None: the sim)

    @property
    def outcome(self) -> str:
        return self.episode.outcome

    def to_dict(self) -> dict[str, Any]:
        """report.json: the sections' fields flattened to the top level, the names users know."""
        ep, t = self.episode, self.timing
        out: dict[str, Any] = {f.name: getattr(ep, f.name) for f in fields(ep)}
        out["start"] = asdict(ep.start)
        out["final"] = asdict(ep.final) if ep.final is not None else None
        out["confirmed"] = asdict(ep.confirmed) if ep.confirmed is not None else None
        out["classes_found"] = list(ep.classes_found)
        out.update(asdict(self.setup))
        out.update({"wall_time_s": t.wall_time_s, "episode_wall_s": t.episode_wall_s,
                    "latency_ms": {k: v.to_dict() for k, v in t.latency.items()},
                    "transport_overhead_ms": t.transport_overhead.to_dict(),
                    "zenoh_delivery_overhead_ms": t.zenoh_delivery_overhead.to_dict(),
                    "delivery_ms": {k: v.to_dict() for k, v in t.delivery.items()},
                    "counts": asdict(self.counts), "service_stats": dict(self.service_stats),
                    "failure": asdict(self.failure) if self.failure is not None else None,
                    "interrupted": self.interrupted,
                    "trajectory": {k: list(v) for k, v in asdict(self.trajectory).items()}})
        out["landing"] = asdict(self.landing) if self.landing is not None else None
        out["navigation"] = asdict(self.navigation) if self.navigation is not None else None
        if self.files is not None:
            out["files"] = dict(self.files)
        return out

    def perception_text(self) -> str:
        return backend_label(self.setup.backend, self.setup.simulated, self.setup.noise, self.setup.perception)


def read_stats(out: Path) -> dict[str, Any]:
    """Each service's --stats-out file (missing or unreadable ones are left out)."""
    stats = {}
    for name in SERVICES:
        path = out / "stats" / f"{name}.json"
        if path.exists():
            try:
                stats[name] = json.loads(path.read_text())
            except (OSError, ValueError) as exc:
                log.warning("stats of %s unreadable (%s): ignored", name, exc)
    return stats


def _command_to_sim(sim_stats: Mapping[str, Any] | None) -> tuple[list[float], dict[int, float] | None]:
    """The sim's own command receive latencies, if its stats carry them (seconds)."""
    if not sim_stats:
        return [], None
    by_frame = sim_stats.get("command_to_sim_s_by_frame")
    values = sim_stats.get("command_to_sim_s") or []
    by_frame = {int(k): float(v) for k, v in by_frame.items()} if isinstance(by_frame, dict) else None
    return [float(v) for v in values if isinstance(v, (int, float))], by_frame


def _rejected_in(stats: Any) -> int:
    """Sum of whatever a service reports as rejected (a number or counts by reason)."""
    if not isinstance(stats, dict):
        return 0
    total = 0
    for key, value in stats.items():
        if "reject" not in key and "refus" not in key:
            continue
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            total += int(value)
        elif isinstance(value, dict):
            total += sum(int(v) for v in value.values() if isinstance(v, (int, float)))
    return total


def _commands(options: UpOptions, rec: Recorder, stats: Mapping[str, Any]) -> tuple[int, str]:
    """How many steering commands the controller sent, from the best witness available.

    With a simulated vehicle they travel on the cmd key, which the monitor counts. A MAVLink
    vehicle's setpoints never touch Zenoh (the first SITL flight reported 0 for 3269 sent): the
    controller's own counter says, or failing its stats file, one command per status outside
    the hand-over.
    """
    if not options.vehicle_url:
        return rec.commands, "monitor"
    sent = (stats.get("controller") or {}).get("commands_sent")
    if isinstance(sent, int) and not isinstance(sent, bool):
        return sent, "controller"
    return rec.steering_statuses, "controller status"


def _latency(options: UpOptions, rec: Recorder, cmd_to_sim: list[float]) -> dict[str, Percentiles]:
    latency = {s: Percentiles.of_seconds(rec.latency[s]) for s in STAGES if s != "command_to_sim"}
    if not options.lockstep:
        latency["heatmap_to_controller"] = Percentiles.of_seconds(
            rec.latency["heatmap_to_controller"],
            note="stamped when the controller's 20 Hz loop takes the heatmap: includes up to one period of waiting")
    note = "real time: the sim takes the newest command at its next step (<= 50 ms)" if not options.lockstep else None
    if cmd_to_sim:
        latency["command_to_sim"] = Percentiles.of_seconds(cmd_to_sim, measured_by="sim", note=note)
    else:
        # The sim did not report its receive times: the same hop measured at the monitor instead.
        latency["command_to_sim"] = Percentiles.of_seconds(rec.delivery_s["cmd"], measured_by="monitor", note=note)
    return latency


def _policy_config(options: UpOptions) -> tuple[str | None, dict[str, Any] | None]:
    """The policy file flown and the constants it set differently from the timing preset's."""
    if options.policy_config is None:
        return None, None
    flown = policy_values(options.policy, load_policy_config(options.policy, options.policy_config, options.timing))
    preset = policy_values(options.policy, preset_config(options.policy, options.timing))
    return str(options.policy_config), {k: v for k, v in flown.items() if v != preset[k]}


def build_report(options: UpOptions, rec: Recorder, start: tuple[float, float, float], noise: float,
                 stats: Mapping[str, Any], failure: Failure | None, interrupted: bool,
                 wall_time_s: float, *, landing: LandingWait | None = None,
                 handover_action: str = "hold") -> RunReport:
    traj = rec.trajectory()
    res = rec.result
    cmd_to_sim, cmd_by_frame = _command_to_sim(stats.get("sim"))
    if rec.backend is not None:
        backend, simulated = rec.backend
    else:
        backend, simulated = f"{options.segmenter} (no heatmap seen)", options.segmenter == "sim"
    if res is not None:
        episode = Episode(res.outcome, res.detail, res.outcome in JUDGE_OUTCOMES, res.sim_time_s, res.path_length_m,
                          Position(*start), Position(res.final_x_m, res.final_y_m, res.final_alt_m),
                          tuple(res.classes_found), res.closest_unsafe_m if res.closest_unsafe_valid else None,
                          Position(res.confirmed_x_m, res.confirmed_y_m, 0.0) if res.confirmed_valid else None,
                          res.touchdown_error_m if res.touchdown_error_valid else None,
                          **separation_fields(res))
    else:
        detail = failure.message if failure else ("interrupted by the user" if interrupted else "no result")
        final = Position(traj["x_m"][-1], traj["y_m"][-1], traj["alt_m"][-1]) if traj["t_s"] else None
        sim_time_s = traj["t_s"][-1] - traj["t_s"][0] if traj["t_s"] else 0.0
        xy = np.column_stack([traj["x_m"], traj["y_m"]]) if traj["t_s"] else np.zeros((0, 2))
        path_length_m = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0
        episode = Episode("error", detail, False, sim_time_s, path_length_m, Position(*start), final, (), None)
    setup = Setup(options.world, backend, simulated, options.segmenter, noise if simulated else None,
                  options.perception if simulated else None, options.policy,
                  options.timing, options.seed, "lockstep" if options.lockstep else "realtime",
                  options.vehicle_url or f"sim:{options.sim_vehicle_profile}", options.vehicle_id, SAFETY_RADIUS_M,
                  options.time_limit_s, options.handover_alt_m, *_policy_config(options))
    episode_wall_s = (round(rec.result_wall_s - rec.first_state_wall_s, 3)
                      if rec.result_wall_s is not None and rec.first_state_wall_s is not None else None)
    timing = RunTiming(round(wall_time_s, 3), episode_wall_s, _latency(options, rec, cmd_to_sim),
                    Percentiles.of_seconds(rec.transport_overhead_s(cmd_by_frame, options.lockstep),
                                           definition=TRANSPORT_DEFINITION),
                    Percentiles.of_seconds(rec.zenoh_delivery_overhead_s(), definition=DELIVERY_DEFINITION),
                    {k: Percentiles.of_seconds(v) for k, v in rec.delivery_s.items()})
    commands, commands_by = _commands(options, rec, stats)
    link = (stats.get("controller") or {}).get("vehicle_link") or {}
    counts = Counts(rec.frames, rec.heatmaps, commands, commands_by, rec.status_count, len(rec.states),
                    rec.rejected + sum(_rejected_in(st) for st in stats.values()), rec.results_refused, rec.foreign,
                    link.get("commands_clamped"), link.get("commands_steered"))
    trajectory = Trajectory(**{k: tuple(v) for k, v in traj.items()})
    landed = None
    if landing is not None:
        last = rec.states[-1] if rec.states else None
        touchdown = (Position(start[0] + last.pos_local_ned_m[1], start[1] + last.pos_local_ned_m[0], last.alt_agl_m)
                     if last is not None else None)
        sent = link.get("landing_targets_sent")
        vision = link.get("vision_speed_sent")
        landed = Landing(handover_action, landing.landed, landing.reason, landing.waited_s, touchdown,
                         sent if isinstance(sent, int) and handover_action == "precland" else None,
                         vision if isinstance(vision, int) and options.gnss_denied == "external-nav" else None)
    return RunReport(episode, setup, timing, counts, trajectory, dict(stats), failure, interrupted, landing=landed,
                     navigation=Navigation.of(rec.statuses))


def write_outputs(world: Any, report: RunReport, rec: Recorder, out: Path, video: bool) -> RunReport:
    """report.json, trajectory.png and the video; a failing picture is logged, never fatal."""
    files = {"report": "report.json"}
    doc = report.to_dict()
    if report.trajectory.t_s:
        try:
            plots.plot_trajectory(world, doc, out / "trajectory.png")
            files["trajectory_plot"] = "trajectory.png"
        except (ImportError, ReportError) as exc:  # matplotlib is a dev extra
            log.warning("no trajectory plot: %s", exc)
    if video and rec.video_frames:
        try:
            path = videos.write_video(video_frames(rec, report.perception_text()), out / "episode.mp4",
                                      outcome=report.outcome, detail=report.episode.detail, policy=report.setup.policy)
            files["video"] = path.name
        except ReportError as exc:
            log.warning("no video: %s", exc)
    report = replace(report, files=files)
    (out / "report.json").write_text(json.dumps(report.to_dict(), indent=1))
    return report


def _look_at(rec: Recorder, t_s: float) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The newest complete close look captured at or before t_s (crop RGB, P(never)); Nones without one."""
    best = None
    for look in rec.looks.values():
        crop, hm = look.get("crop"), look.get("heatmap")
        if crop is not None and hm is not None and crop.stamp.t_s <= t_s and (best is None or
                                                                                crop.stamp.t_s >= best[0].stamp.t_s):
            best = (crop, hm)
    return (best[0].image_rgb, best[1].probabilities()[1]) if best is not None else (None, None)


def video_frames(rec: Recorder, perception: str) -> list[videos.VideoFrame]:
    frames = []
    changes = videos.state_change_times({t: st.state for t, st in rec.statuses.items()})
    for seq in sorted(rec.video_frames):
        kept = rec.video_frames[seq]
        image = cv2.cvtColor(cv2.imdecode(kept["jpeg"], cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        prob = None
        if "prob" in kept:
            arr, is_u8 = kept["prob"]
            prob = arr.astype(np.float32) / 255.0 if is_u8 else arr.astype(np.float32)
        st: ControllerStatus | None = kept.get("status")
        look_rgb, look_never = _look_at(rec, kept["t_s"]) if st is not None and st.look_verdict else (None, None)
        frames.append(videos.VideoFrame(
            t_s=kept["t_s"], image_rgb=image, prob_safe=prob, alt_agl_m=kept["alt"],
            state=st.state if st else "", watchdog=st.watchdog if st else "",
            focus_radius_px=st.focus_radius_px if st else 0.0,
            target_px=(st.target_row_px, st.target_col_px) if st and st.target_valid else None,
            threshold=st.threshold if st and st.threshold_valid else None,
            recent_changes=videos.changes_before(changes, kept["t_s"]),
            perception=perception, policy=st.policy if st else "", hfov_rad=kept.get("hfov"),
            spot_clearance_m=st.spot_clearance_m if st and st.spot_valid else None,
            policy_reason=st.policy_reason if st else "", look_verdict=st.look_verdict if st else "",
            look_rgb=look_rgb, look_never=look_never,
            confirmed_frames_ago=seq - st.confirmed_frame_seq if st and st.confirmed_valid else None,
            confirmed_px=((st.confirmed_row_px, st.confirmed_col_px)
                          if st and st.confirmed_valid and st.confirmed_frame_seq == seq else None)))
    return frames
