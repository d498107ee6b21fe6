"""`dovesei replay <recording.mcap>`: a recorded flight's inputs run again through a policy.

    recording.mcap --FlightRecording--> states, frames, heatmaps (as recorded, checked by the codec)
        [--segmenter sim|clipseg: frames --SegmenterCore--> new heatmaps, same seq]
        --ControllerCore (the recording's timing, lockstep or real time)--> commands, statuses
        --> <out>/replay.json (decisions, agreement with the recorded ones), <out>/replay.mcap

Replay is open loop: the vehicle's states are the recorded ones, so a different policy's commands
are what it *would* have sent at each moment, not a new trajectory. With the recorded policy and
heatmaps a lockstep recording replays to the very same decisions (the test checks it), which is
what makes a recording from a real drone with real CLIPSeg a fair input for comparing policies or
prompt sets offline. Lockstep: each state is one tick, and the heatmap it awaits is handed over
first (as the sim protocol does). Real time: heatmaps and ticks in the order the recorder saw them,
a tick at each recorded status, on the recorded wall clock.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dovesei.controller.core import ControllerConfig, ControllerCore, ControllerInputError
from dovesei.controller.policies.registry import make_policy, policy_names
from dovesei.controller.policies.config_file import config_from_values, policy_values
from dovesei.episode import EpisodeSpec, segmenter_config
from dovesei.pictures import plots
from dovesei.pictures.common import ReportError
from dovesei.segmenter.core import SegmenterConfig, SegmenterCore, make_backend
from dovesei.segmenter.prompts import PromptSet
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.errors import ConfigError
from dovesei.shared.mission import HANDOVER_ALT_M
from dovesei.shared.messages import (
    CameraFrame, ControllerStatus, EpisodeResult, SafetyHeatmap, VehicleState,
)
from dovesei.shared.recording import FlightRecorder, FlightRecording, RecordingError, find_recording
from dovesei.sim.camera import CameraModel
from dovesei.sim.world import WorldError, load_world

log = logging.getLogger("dovesei.replay")


def episode_metadata(spec: EpisodeSpec, world: str = "") -> dict[str, dict[str, Any]]:
    """The metadata records of an in-process episode's recording (what replay needs to rebuild it)."""
    return flight_metadata(segmenter_config(spec), policy=spec.policy, timing=spec.timing, lockstep=True,
                           vehicle_id=spec.vehicle_id, seed=spec.seed, world=world,
                           start=(spec.start.x_m, spec.start.y_m, spec.start.alt_m), camera=CameraModel(),
                           handover_alt_m=spec.handover_alt_m)


def flight_metadata(seg: SegmenterConfig, *, policy: str, timing: str, lockstep: bool, vehicle_id: str, seed: int,
                    world: str, start: tuple[float, float, float], camera: Any = None,
                    handover_alt_m: float = HANDOVER_ALT_M,
                    policy_config: dict[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """Metadata records of a recording: the run, the segmenter, the prompt set and the camera model,
    and the policy's constants when a --policy-config changed them (replay flies them again)."""
    out = {
        "run": {"policy": policy, "timing": timing, "lockstep": lockstep, "vehicle_id": vehicle_id, "seed": seed,
                "world": world, "start": list(start), "handover_alt_m": handover_alt_m},
        "segmenter": segmenter_metadata(seg),
        "prompts": {"positive": list(seg.prompts.positive), "negative": list(seg.prompts.negative),
                    "template": seg.prompts.template},
    }
    if policy_config is not None:
        out["policy_config"] = policy_config
    if camera is not None:
        out["camera"] = {k: v for k, v in asdict(camera).items() if isinstance(v, (int, float, str, bool))}
    return out


def up_recorder(out: Path, configs: Any, options: Any, start: tuple[float, float, float]) -> FlightRecorder:
    """`dovesei up`'s recording, <out>/recording.mcap, with its services' own configs as metadata."""
    sim = configs.sim.sim
    meta = flight_metadata(configs.segmenter.segmenter, policy=configs.controller.policy, timing=sim.timing,
                           lockstep=bool(options.lockstep), vehicle_id=options.vehicle_id, seed=sim.seed,
                           world=str(options.world), start=start, camera=sim.camera,
                           handover_alt_m=configs.controller.handover_alt_m,
                           policy_config=(None if configs.controller.policy_config_file is None else
                                          policy_values(configs.controller.policy, configs.controller.policy_config())))
    return FlightRecorder(Path(out) / "recording.mcap", metadata=meta)


def segmenter_metadata(seg: SegmenterConfig) -> dict[str, Any]:
    return {"backend": seg.backend, "fusion": seg.fusion, "sim_profile": seg.sim_profile, "sim_noise": seg.sim_noise,
            "sim_seed": seg.sim_seed, "model": seg.model, "heatmap_dtype": seg.heatmap_dtype}


@dataclass(frozen=True)
class ReplayResult:
    """What a replay decided, and how it compares with the decisions in the recording."""

    policy: str
    segmenter: str  # "recorded" or the backend that made new heatmaps
    lockstep: bool
    ticks: int
    heatmaps: int
    compared: int  # ticks with a recorded decision to compare against
    same: int  # of those, identical state, target, focus and command
    first_difference: str  # "" when every compared decision matched
    recorded_outcome: str
    states: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["state_changes"] = sum(1 for a, b in zip(self.states, self.states[1:]) if a != b)
        del out["states"]
        return out


def _decision(st: ControllerStatus) -> tuple:
    return (st.state, st.watchdog, st.target_valid, st.target_row_px, st.target_col_px, st.focus_radius_px,
            st.vel_body_frd_m_s)


def replay(recording: FlightRecording, *, policy: str | None = None, segmenter: SegmenterConfig | None = None,
           record: FlightRecorder | None = None) -> ReplayResult:
    """Run `policy` (default: the recorded one) on the recording's inputs; see the module docstring."""
    run = recording.meta("run")
    if not run:
        raise RecordingError(f"recording {recording.path}: no 'run' metadata (not a dovesei flight recording)")
    recorded_policy = str(run.get("policy", ""))
    policy = policy or recorded_policy
    if policy not in policy_names():
        raise ConfigError(f"--policy {policy!r}: choose one of {', '.join(policy_names())}")
    lockstep = bool(run.get("lockstep", True))
    config = ControllerConfig(vehicle_id=str(run.get("vehicle_id", "uav1")), policy=policy,
                              timing=str(run.get("timing", "reference")), lockstep=lockstep,
                              handover_alt_m=float(run.get("handover_alt_m", HANDOVER_ALT_M)))
    values = recording.meta("policy_config")
    # The recorded policy flies again with the constants it flew with; another policy with its own defaults.
    built = None if not values or policy != recorded_policy else make_policy(
        policy, config_from_values(policy, values, config.timing, f"recording {recording.path} policy_config"),
        config.vehicle_speed_limits_m_s, handover_alt_m=config.handover_alt_m)
    ctrl = ControllerCore(config, policy=built)
    seg = SegmenterCore(make_backend(segmenter), segmenter) if segmenter is not None else None
    events = list(recording.messages((VehicleState, CameraFrame, SafetyHeatmap, ControllerStatus, EpisodeResult)))
    recorded = {st.stamp.t_s: st for _, st in events if isinstance(st, ControllerStatus)}
    # The sim's last state comes with the verdict; the live controller may never have ticked on it.
    end_s = min((r.sim_time_s for _, r in events if isinstance(r, EpisodeResult)), default=float("inf"))
    heatmaps: dict[int, tuple[SafetyHeatmap, float]] = {}
    outcome, states, compared, same, first = "", [], 0, 0, ""
    latest: VehicleState | None = None

    def tick(state: VehicleState, wall_s: float | None) -> None:
        nonlocal compared, same, first
        try:
            cmd, status = ctrl.tick(state, wall_s)
        except ControllerInputError as exc:
            log.warning("state %d refused as the live controller would: %s", state.seq, exc)
            return
        states.append(status.state)
        if record is not None:
            record.write(cmd)
            record.write(status)
        old = recorded.get(status.stamp.t_s)
        if old is not None and policy == recorded_policy:
            compared += 1
            if _decision(old) == _decision(status):
                same += 1
            elif not first:
                first = (f"t={status.stamp.t_s:.2f} s: recorded {_decision(old)}, replayed {_decision(status)}")

    if lockstep:
        # The sim waits for each command, so the heatmap a state awaits may arrive after it (over
        # Zenoh it does): all heatmaps first, then one tick per state with the one it awaits.
        for wall_s, msg in events:
            if isinstance(msg, CameraFrame) and seg is not None:
                hm = seg.process(msg)
                heatmaps[hm.seq] = (hm, wall_s)
            elif isinstance(msg, SafetyHeatmap) and seg is None:
                heatmaps[msg.seq] = (msg, wall_s)
    for wall_s, msg in events:
        if not lockstep and isinstance(msg, CameraFrame) and seg is not None:
            ctrl.on_heatmap(seg.process(msg), wall_s)
        elif not lockstep and isinstance(msg, SafetyHeatmap) and seg is None:
            ctrl.on_heatmap(msg, wall_s)
        elif isinstance(msg, VehicleState):
            latest = msg
            if lockstep:
                due = msg.await_frame_seq
                if due >= 0 and due in heatmaps:
                    ctrl.on_heatmap(*heatmaps.pop(due))
                if msg.stamp.t_s < end_s or msg.stamp.t_s in recorded:
                    tick(msg, None)
        elif isinstance(msg, ControllerStatus) and not lockstep and latest is not None:
            tick(latest, wall_s)  # the live controller ticked here, on its own clock
        elif isinstance(msg, EpisodeResult):
            outcome = msg.outcome
        if record is not None and isinstance(msg, (VehicleState, EpisodeResult)):
            record.write(msg, recv_wall_s=wall_s)
    n_heatmaps = sum(1 for _, m in events if isinstance(m, CameraFrame if seg is not None else SafetyHeatmap))
    return ReplayResult(policy=policy, segmenter=segmenter.backend if segmenter is not None else "recorded",
                        lockstep=lockstep, ticks=len(states), heatmaps=n_heatmaps, compared=compared, same=same,
                        first_difference=first, recorded_outcome=outcome, states=tuple(states))


def _segmenter(args: argparse.Namespace, recording: FlightRecording) -> SegmenterConfig | None:
    if args.segmenter is None:
        return None
    seg_meta, prompts = recording.meta("segmenter"), recording.meta("prompts")
    try:
        prompt_set = PromptSet(positive=tuple(prompts["positive"]), negative=tuple(prompts["negative"]),
                               template=prompts.get("template", "{}")) if prompts else None
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"recording {recording.path}: bad 'prompts' metadata: {exc}") from None
    extra: dict[str, Any] = {} if prompt_set is None else {"prompts": prompt_set}
    if args.segmenter == "sim":
        # The live run's simulated perception: same profile, noise and seed give the same heatmaps.
        for name in ("fusion", "sim_profile", "sim_noise", "sim_seed"):
            if name in seg_meta:
                extra[name] = seg_meta[name]
        return SegmenterConfig(backend="sim", **extra)
    return SegmenterConfig(backend="clipseg", model=args.model, device=args.device,
                           **({"fusion": seg_meta["fusion"]} if "fusion" in seg_meta else {}), **extra)


def _plot(recording: FlightRecording, result: ReplayResult, png: Path) -> bool:
    """The recorded path over the world, labelled with the replayed policy's states (open loop)."""
    run = recording.meta("run")
    try:
        world = load_world(str(run.get("world", "")))
    except (WorldError, ConfigError) as exc:
        log.warning("no trajectory plot: world %r not loaded (%s)", run.get("world"), exc)
        return False
    x0, y0, alt0 = (list(run.get("start") or (0.0, 0.0, 0.0)) + [0.0, 0.0, 0.0])[:3]
    traj: dict[str, list] = {"t_s": [], "x_m": [], "y_m": [], "alt_m": []}
    result_msg = None
    for _, msg in recording.messages((VehicleState, EpisodeResult)):
        if isinstance(msg, EpisodeResult):
            result_msg = msg
            continue
        north_m, east_m, _ = msg.pos_local_ned_m
        for key, value in (("t_s", msg.stamp.t_s), ("x_m", x0 + east_m), ("y_m", y0 + north_m),
                           ("alt_m", msg.alt_agl_m)):
            traj[key].append(value)
    if not traj["t_s"]:
        return False
    n = len(traj["t_s"])
    traj["state"] = (list(result.states) + [result.states[-1] if result.states else "INIT"] * n)[:n]
    seg = recording.meta("segmenter")
    report = {"trajectory": traj, "start": {"x_m": x0, "y_m": y0, "alt_m": alt0},
              "outcome": result.recorded_outcome or "no outcome", "policy": f"{result.policy} (replayed)",
              "backend": "simulated" if (seg.get("backend") == "sim") else str(seg.get("backend", "")),
              "simulated": seg.get("backend") == "sim", "noise": seg.get("sim_noise"), "timing": run.get("timing"),
              "sim_time_s": traj["t_s"][-1] - traj["t_s"][0],
              "path_length_m": float(np.sum(np.hypot(np.diff(traj["x_m"]), np.diff(traj["y_m"])))),
              "detail": f"recorded flight replayed; {result.same}/{result.compared} decisions as recorded"}
    if result_msg is not None:
        report["final"] = {"x_m": result_msg.final_x_m, "y_m": result_msg.final_y_m, "alt_m": result_msg.final_alt_m}
    try:
        plots.plot_trajectory(world, report, png)
    except (ImportError, ReportError) as exc:  # matplotlib is a dev extra
        log.warning("no trajectory plot: %s", exc)
        return False
    return True


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(prog="dovesei replay", description=__doc__.split("\n")[0])
    parser.add_argument("recording", help="a report folder of dovesei up (its recording.mcap) or a flight "
                        "recording (.mcap) written by dovesei up or a service")
    parser.add_argument("--policy", help=f"the policy to run (default: the recorded one): {', '.join(policy_names())}")
    parser.add_argument("--segmenter", choices=("sim", "clipseg"),
                        help="make new heatmaps from the recorded frames (default: use the recorded heatmaps)")
    parser.add_argument("--model", default=SegmenterConfig.model, help="CLIPSeg model (Hub id or directory)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", help="report folder (default: <recording>-replay)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    recording = FlightRecording(find_recording(args.recording))
    out = Path(args.out) if args.out else recording.path.with_name(recording.path.stem + "-replay")
    out.mkdir(parents=True, exist_ok=True)
    seg = _segmenter(args, recording)
    run = {**recording.metadata.get("run", {}), "policy": args.policy or recording.meta("run").get("policy", ""),
           "replay_of": str(recording.path)}
    metadata = {**recording.metadata, "run": run}
    if seg is not None:
        metadata["segmenter"] = segmenter_metadata(seg)
    with FlightRecorder(out / "replay.mcap", metadata=metadata) as rec:
        result = replay(recording, policy=args.policy, segmenter=seg, record=rec)
    if recording.cut is not None:
        print(recording.describe())  # a crash or power loss cut it: what came before the cut was replayed
    doc = {"recording": str(recording.path), "open_loop": True, "recording_cut": recording.cut,
           "recovered_messages": recording.recovered, **result.to_dict()}
    doc["files"] = {"replay": "replay.json", "recording": "replay.mcap"}
    if _plot(recording, result, out / "trajectory.png"):
        doc["files"]["trajectory_plot"] = "trajectory.png"
    (out / "replay.json").write_text(json.dumps(doc, indent=2) + "\n")
    agree = f", {result.same}/{result.compared} decisions as recorded" if result.compared else ""
    print(f"replayed {result.ticks} ticks with {result.policy} on {result.segmenter} heatmaps{agree}; "
          f"report in {out}")
    return 0
