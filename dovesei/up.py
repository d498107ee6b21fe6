"""`dovesei up`: fly one episode with the three services as separate OS processes on Zenoh.

    dovesei up ──starts──> dovesei.sim.service         (camera frames, vehicle states, judge)
               ──starts──> dovesei.segmenter.service   (heatmaps)
               ──starts──> dovesei.controller.service  (velocity commands, status)
               ──monitor session──> records states, statuses, commands, heatmaps, a subsample
                                    of the camera frames and the EpisodeResult
               ──at the end──> <out>/report.json, trajectory.png, episode.mp4
                               <out>/logs/<service>.log (each child's output), stats/<service>.json
                               (from services with --stats-out), pids.json (written at start)

The services talk only over Zenoh: peers on 127.0.0.1 with multicast scouting off, each
listening on its own free port and connecting to the others (or all connecting to a router
given with --connect). `up` never steps anything itself: the sim runs the episode (lockstep by
default, so the trajectory equals `dovesei.episode.run_episode` for the same spec) and `up`
watches the keys like any operator would.

Life cycle: a child that exits before the episode's result makes `up` keep recording for
`--after-failure-s` (so the report shows how the others reacted: the controller's watchdog
holding the vehicle), then stop the others (SIGTERM, SIGKILL after a grace period) and exit 1
naming the child and its last log line. SIGINT/SIGTERM stop every child the same way (exit 130).
An episode that reached the judge's outcome (safe, unsafe, timeout, out_of_world) exits 0.

Latency (report.json `latency_ms`, p50/p99 per stage) comes from the services' own stamps: the
segmenter's frame->segmenter and inference (on each heatmap), the controller's heatmap->controller
and policy (on each command), the sim's command->sim (its stats file). Those stamps are taken
when each service's loop takes a message, so `zenoh_delivery_overhead_ms` adds the same hops as
the monitor's callbacks see them: what Zenoh itself costs.

With `--vehicle URL` a real autopilot flies instead of the simulated vehicle: the sim renders the
world at the pose the autopilot reports (its local origin placed at --start) and judges there;
the controller steers the autopilot over MAVLink in real time.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dovesei.shared import keys
from dovesei.shared.codec import decode
from dovesei.shared.errors import ConfigError, DoveseiError, ProtocolError
from dovesei.shared.lifecycle import install_stop_handlers
from dovesei.shared.messages import (
    CameraFrame, ControllerStatus, EpisodeResult, SafetyHeatmap, VehicleState, VelocityCommand,
)
from dovesei.shared.zconfig import free_port

log = logging.getLogger("dovesei.up")

SERVICES = ("sim", "segmenter", "controller")  # start order: the sim waits for the other two
MODULES = {"sim": "dovesei.sim.service", "segmenter": "dovesei.segmenter.service",
           "controller": "dovesei.controller.service"}
JUDGE_OUTCOMES = ("safe", "unsafe", "timeout", "out_of_world")
STAGES = ("frame_to_segmenter", "inference", "heatmap_to_controller", "policy", "command_to_sim")
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
TERM_GRACE_S = 5.0  # SIGTERM -> SIGKILL
RESULT_AFTER_EXIT_S = 2.0  # a sim that exits right after publishing: give the result time to arrive
MAX_VIDEO_FRAMES = 900
PROGRESS_EVERY_S = 10.0  # sim seconds between progress lines (state changes are logged at once)
STATE_LOG_MIN_S = 1.0  # sim seconds: faster state changes are counted, not logged one by one


class UpError(DoveseiError):
    """`dovesei up` could not start or run the episode; the message says what and why."""


# ------------------------------------------------------------------------ options


@dataclass(frozen=True)
class UpOptions:
    """Everything `up` was asked to do (built from flags; tests may build it directly)."""

    world: str = "synthetic"
    segmenter: str = "auto"
    policy: str = "dovesei"
    timing: str = "reference"
    seed: int = 0
    noise: float | None = None  # None: the simulated perception's calibrated default
    start: tuple[float, float, float] | None = None  # (x_m, y_m, alt_m); None: from start_seed
    start_seed: int | None = None  # None: --seed
    start_alt_m: float = 100.0
    out: Path = Path("runs/up")
    realtime: bool = False
    connect: tuple[str, ...] = ()
    vehicle: str | None = None
    pose_url: str | None = None
    takeoff: bool = False
    time_limit_s: float = 1200.0
    video: bool = True
    model: str | None = None
    vehicle_id: str = "uav1"
    heatmap_wait_s: float | None = None
    heatmap_hold_after_s: float | None = None
    after_failure_s: float = 5.0
    startup_timeout_s: float = 120.0
    log_level: str = "INFO"

    def __post_init__(self) -> None:
        keys.check_vehicle_id(self.vehicle_id)
        if self.takeoff and not self.vehicle:
            raise ConfigError("--takeoff only applies with --vehicle (a real autopilot)")
        if self.segmenter not in ("auto", "clipseg", "sim"):
            raise ConfigError(f"--segmenter {self.segmenter!r}: choose auto, clipseg or sim")
        if self.timing not in ("reference", "real"):
            raise ConfigError(f"--timing {self.timing!r}: choose reference or real")
        if self.start is not None and not self.start[2] > 0:
            raise ConfigError(f"--start altitude must be > 0 m, got {self.start[2]!r}")
        for name in ("heatmap_wait_s", "heatmap_hold_after_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ConfigError(f"--{name.replace('_', '-')} must be > 0, got {value!r}")
        if not (math.isfinite(self.time_limit_s) and self.time_limit_s > 0):
            raise ConfigError(f"--time-limit-s must be > 0, got {self.time_limit_s!r}")
        if self.noise is not None and not (math.isfinite(self.noise) and self.noise >= 0):
            raise ConfigError(f"--noise must be >= 0, got {self.noise!r}")
        if not (math.isfinite(self.after_failure_s) and self.after_failure_s >= 0):
            raise ConfigError(f"--after-failure-s must be >= 0, got {self.after_failure_s!r}")

    @property
    def lockstep(self) -> bool:
        # A real autopilot cannot wait for anyone: real time whenever one flies.
        return not self.realtime and not self.vehicle


def parse_start(text: str) -> tuple[float, float, float | None]:
    """`X,Y` or `X,Y,ALT` in world metres (x east, y north)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"--start {text!r}: expected X,Y or X,Y,ALT in metres") from None
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"--start {text!r}: expected two or three finite numbers X,Y[,ALT]")
    return values[0], values[1], (values[2] if len(values) == 3 else None)


def resolve_start(world: Any, options: UpOptions) -> tuple[float, float, float]:
    """The start `up` hands the sim explicitly, so it also knows where the local frame's origin is.

    Without --start it is the first of `generate_starts(world, n, seed)`, i.e. exactly the bench's
    start 0 for the same seed.
    """
    from dovesei.sim.starts import generate_starts

    if options.start is not None:
        x_m, y_m, alt_m = options.start
        if not world.contains(x_m, y_m):
            raise ConfigError(f"--start {x_m:g},{y_m:g} lies outside the world "
                              f"({world.width_m:.0f} x {world.height_m:.0f} m, x east, y north)")
        return float(x_m), float(y_m), float(alt_m)
    seed = options.seed if options.start_seed is None else options.start_seed
    st = generate_starts(world, 1, seed, alt_m=options.start_alt_m)[0]
    return st.x_m, st.y_m, st.alt_m


# ------------------------------------------------------------------------ children


def _parser_flags(module: str) -> set[str]:
    """The option strings a service's parser accepts (to pass optional flags only where they exist)."""
    import importlib

    try:
        parser = importlib.import_module(module).build_parser()
    except (ImportError, AttributeError) as exc:
        raise UpError(f"cannot read the command line of {module}: {exc}") from exc
    return set(parser._option_string_actions)  # argparse keeps no public list of its flags


def zenoh_flags(name: str, ports: dict[str, int], connect: Sequence[str]) -> list[str]:
    """Peer-to-peer on loopback (each listens, connects to every other), or clients of a router."""
    if connect:
        return ["--mode", "client", *[a for ep in connect for a in ("--connect", ep)]]
    flags = ["--mode", "peer", "--no-multicast-scouting", "--listen", f"tcp/127.0.0.1:{ports[name]}"]
    for other, port in ports.items():
        if other != name:
            flags += ["--connect", f"tcp/127.0.0.1:{port}"]
    return flags


def child_commands(options: UpOptions, start: tuple[float, float, float], ports: dict[str, int],
                   out: Path, noise: float, flags: dict[str, set[str]] | None = None) -> dict[str, list[str]]:
    """The argv of each service; `flags` (what each parser accepts) gates the optional ones."""
    flags = flags if flags is not None else {n: _parser_flags(MODULES[n]) for n in SERVICES}
    lock = ["--lockstep"] if options.lockstep else ["--realtime"]
    vid = options.vehicle_id

    def stats(name: str) -> list[str]:
        return ["--stats-out", str(out / "stats" / f"{name}.json")] if "--stats-out" in flags[name] else []

    x_m, y_m, alt_m = start
    sim = [sys.executable, "-m", MODULES["sim"], "--vehicle-id", vid, "--world", options.world,
           "--start", f"{x_m!r},{y_m!r},{alt_m!r}", "--timing", options.timing, "--seed", str(options.seed),
           "--time-limit-s", repr(float(options.time_limit_s)), *lock, *stats("sim")]
    if "--wait-for" in flags["sim"]:
        sim += ["--wait-for", "segmenter,controller"]
    if options.vehicle:
        sim += ["--external-pose"]  # renders at the states the controller publishes (it alone opens MAVLink)

    seg = [sys.executable, "-m", MODULES["segmenter"], "--vehicle", vid, "--backend", options.segmenter,
           "--sim-noise", repr(float(noise)), "--sim-seed", str(options.seed), *stats("segmenter")]
    if options.lockstep:
        seg.append("--lockstep")
    if options.model:
        seg += ["--model", options.model]

    ctrl = [sys.executable, "-m", MODULES["controller"], "--vehicle-id", vid, "--policy", options.policy,
            "--timing", options.timing, *lock, *stats("controller")]
    if options.vehicle:
        ctrl += ["--vehicle", options.vehicle]
    if options.heatmap_wait_s is not None:
        ctrl += ["--heatmap-wait-s", repr(float(options.heatmap_wait_s))]
    if options.heatmap_hold_after_s is not None:
        ctrl += ["--heatmap-hold-after-s", repr(float(options.heatmap_hold_after_s))]

    cmds = {"sim": sim, "segmenter": seg, "controller": ctrl}
    for name, argv in cmds.items():
        argv += ["--log-level", options.log_level, *zenoh_flags(name, ports, options.connect)]
    return cmds


def child_env(name: str, options: UpOptions) -> dict[str, str]:
    """Extra environment of a child: `auto` means weights found LOCALLY, so no Hub lookups."""
    if name == "segmenter" and options.segmenter == "auto":
        # Without this an offline host spends minutes in the Hub client's retries before falling back.
        return {"HF_HUB_OFFLINE": "1"}
    return {}


def _describe_exit(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"killed by signal {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exited with code {returncode}"


def last_error_line(log_path: Path, max_bytes: int = 16384) -> str:
    """The child's last ERROR/CRITICAL/exception line, else its last line ('' for an empty log)."""
    try:
        with log_path.open("rb") as fh:
            fh.seek(0, os.SEEK_END)
            fh.seek(max(0, fh.tell() - max_bytes))
            lines = [ln.strip() for ln in fh.read().decode("utf-8", "replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    for line in reversed(lines):
        if " ERROR " in line or " CRITICAL " in line or "Error:" in line or "Exception" in line:
            return _clip(line)
    return _clip(lines[-1]) if lines else ""


def _clip(line: str, max_chars: int = 300) -> str:
    return line if len(line) <= max_chars else line[:max_chars - 3] + "..."


class Children:
    """The three service processes: start, watch, stop; each one's output goes to its own log."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: dict[str, Any] = {}

    def start(self, name: str, argv: list[str], env: dict[str, str] | None = None) -> subprocess.Popen:
        log_path = self.log_dir / f"{name}.log"
        fh = log_path.open("wb")
        self._logs[name] = fh
        # Own session: a Ctrl-C in the terminal reaches only `up`, which then stops the children
        # in order and reaps them, instead of racing them through the same signal.
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                                start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
        self.procs[name] = proc
        log.info("started %s (pid %d): %s", name, proc.pid, " ".join(argv[2:]))
        return proc

    def wait_exit(self, name: str, timeout_s: float) -> bool:
        """Let a child finish on its own (True when it has exited within `timeout_s`)."""
        try:
            self.procs[name].wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return False
        return True

    def exited(self) -> list[tuple[str, int]]:
        return [(n, p.returncode) for n, p in self.procs.items() if p.poll() is not None]

    def log_path(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def stop_all(self, grace_s: float = TERM_GRACE_S) -> dict[str, int]:
        """SIGTERM every running child, SIGKILL what is left after `grace_s`; reap all."""
        for name, proc in self.procs.items():
            if proc.poll() is None:
                log.debug("stopping %s (pid %d)", name, proc.pid)
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for name, proc in self.procs.items():
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s (pid %d) ignored SIGTERM for %.0f s: killing it", name, proc.pid, grace_s)
                proc.kill()
                proc.wait()
        for fh in self._logs.values():
            fh.close()
        return {n: p.returncode for n, p in self.procs.items()}


# ------------------------------------------------------------------------ the monitor


@dataclass
class Sample:
    """One received payload, stamped on arrival in Zenoh's thread; decoded later by the Recorder."""

    topic: str
    recv_wall_s: float
    payload: bytes


class Recorder:
    """What the monitor saw, decoded and kept for the report (one thread: the caller's)."""

    def __init__(self, start: tuple[float, float, float], video: bool, video_period_s: float = 0.25) -> None:
        self.start = start
        self.video = video
        self.states: list[VehicleState] = []
        self.statuses: dict[float, ControllerStatus] = {}  # by the state stamp they answer
        self.status_count = 0
        self.commands = 0
        self.latency: dict[str, list[float]] = {s: [] for s in STAGES}
        self.delivery_s: dict[str, list[float]] = {"camera": [], "heatmap": [], "cmd": [], "state": []}
        self.heatmap_delivery_by_seq: dict[int, float] = {}
        self.hm_to_ctrl_by_seq: dict[int, float] = {}  # the controller's own stamp per frame
        self.camera_delivery_by_seq: dict[int, float] = {}
        self.frame_to_seg_by_seq: dict[int, float] = {}
        self.cmd_delivery_by_frame: dict[int, float] = {}
        self.frames = 0
        self.heatmaps = 0
        self.rejected = 0
        self.backend: tuple[str, bool] | None = None
        self.result: EpisodeResult | None = None
        self.first_state_wall_s: float | None = None  # wall clock at the monitor: the episode's duration
        self.result_wall_s: float | None = None
        self.last_state_name, self.last_watchdog = "", ""
        self.logged_state, self.logged_watchdog = "", ""
        self.unlogged_changes = 0
        self.last_progress_t_s = -math.inf
        # Video: frames kept every `video_period_s` of sim time; the period doubles when too many.
        self.video_period_s = video_period_s
        self._next_video_t_s = 0.0
        self.video_frames: dict[int, dict[str, Any]] = {}
        self._latency_seen: set[int] = set()

    def handle(self, s: Sample) -> None:
        expected = {"state": VehicleState, "status": ControllerStatus, "cmd": VelocityCommand,
                    "heatmap": SafetyHeatmap, "camera": CameraFrame, "episode": EpisodeResult}[s.topic]
        try:
            msg = decode(s.payload, expected, key=s.topic)
        except ProtocolError as exc:
            self.rejected += 1
            log.warning("monitor rejected a %s message: %s", s.topic, exc.problem)
            return
        sent = getattr(msg, "sent_wall_s", 0.0)
        if sent > 0 and s.topic in self.delivery_s:
            self.delivery_s[s.topic].append(s.recv_wall_s - sent)
            if s.topic == "camera":
                self.camera_delivery_by_seq[msg.seq] = s.recv_wall_s - sent
        getattr(self, f"_on_{s.topic}")(msg, s)

    def _on_state(self, st: VehicleState, s: Sample) -> None:
        if not self.states:
            self.first_state_wall_s = s.recv_wall_s
        self.states.append(st)

    def _on_status(self, st: ControllerStatus, s: Sample) -> None:
        self.status_count += 1
        self.statuses[st.stamp.t_s] = st
        kept = self.video_frames.get(st.frame_seq)
        if kept is not None and "status" not in kept:
            kept["status"] = st  # the first decision taken with this frame's heatmap
        changed = st.state != self.last_state_name or st.watchdog != self.last_watchdog
        since_s = st.stamp.t_s - self.last_progress_t_s
        if changed and since_s < STATE_LOG_MIN_S:
            # The reference policy can flip state every tick (its AIMING/LANDING oscillation):
            # count the flips and say so once instead of flooding the log.
            self.unlogged_changes += 1
        elif changed or since_s >= PROGRESS_EVERY_S or (self.unlogged_changes and since_s >= STATE_LOG_MIN_S):
            state = st.state if st.state == self.logged_state else f"{self.logged_state or 'start'} -> {st.state}"
            watchdog = (st.watchdog if st.watchdog == self.logged_watchdog
                        else f"{self.logged_watchdog or 'start'} -> {st.watchdog}")
            flips = f"; {self.unlogged_changes} more changes since the last line" if self.unlogged_changes else ""
            log.info("t=%.2f s alt %.1f m: controller %s, watchdog %s%s", st.stamp.t_s, st.alt_agl_m, state,
                     watchdog, flips)
            self.logged_state, self.logged_watchdog, self.unlogged_changes = st.state, st.watchdog, 0
            self.last_progress_t_s = st.stamp.t_s
        self.last_state_name, self.last_watchdog = st.state, st.watchdog

    def _on_cmd(self, cmd: VelocityCommand, s: Sample) -> None:
        self.commands += 1
        if cmd.sent_wall_s > 0 and cmd.frame_seq >= 0:
            self.cmd_delivery_by_frame.setdefault(cmd.frame_seq, s.recv_wall_s - cmd.sent_wall_s)
        # A decision's latency rides on every command until the next one: count it once.
        if cmd.latency is not None and cmd.frame_seq not in self._latency_seen:
            self._latency_seen.add(cmd.frame_seq)
            lat = cmd.latency
            self.latency["heatmap_to_controller"].append(lat.heatmap_to_controller_s)
            self.hm_to_ctrl_by_seq[cmd.frame_seq] = lat.heatmap_to_controller_s
            self.latency["policy"].append(lat.policy_s)

    def _on_heatmap(self, hm: SafetyHeatmap, s: Sample) -> None:
        self.heatmaps += 1
        if self.backend is None:
            self.backend = (hm.backend, hm.simulated)
            log.info("perception: %s%s", hm.backend, " (SIMULATED: a test instrument, not a model)" if hm.simulated
                     else "")
        self.latency["frame_to_segmenter"].append(hm.frame_to_segmenter_s)
        self.latency["inference"].append(hm.inference_s)
        self.frame_to_seg_by_seq[hm.seq] = hm.frame_to_segmenter_s
        if hm.sent_wall_s > 0:
            self.heatmap_delivery_by_seq[hm.seq] = s.recv_wall_s - hm.sent_wall_s
        kept = self.video_frames.get(hm.seq)
        if kept is not None:
            kept["prob"] = (np.asarray(hm.prob_safe).copy(), hm.prob_safe.dtype == np.uint8)

    def _on_camera(self, frame: CameraFrame, s: Sample) -> None:
        self.frames += 1
        if not self.video or frame.stamp.t_s + 1e-9 < self._next_video_t_s:
            return
        self._next_video_t_s = frame.stamp.t_s + self.video_period_s
        # Kept as JPEG: a 1200 s episode keeps up to MAX_VIDEO_FRAMES frames, ~40 kB each instead of 370 kB.
        bgr = cv2.cvtColor(frame.image_rgb, cv2.COLOR_RGB2BGR)
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 85])
        if ok:
            self.video_frames[frame.seq] = {"t_s": frame.stamp.t_s, "alt": frame.alt_agl_m, "jpeg": jpeg}
        if len(self.video_frames) > MAX_VIDEO_FRAMES:
            # Long episode: keep every other frame and halve the rate from now on (bounded memory).
            for seq in sorted(self.video_frames)[1::2]:
                del self.video_frames[seq]
            self.video_period_s *= 2.0

    def _on_episode(self, result: EpisodeResult, s: Sample) -> None:
        if self.result is None:
            self.result = result
            self.result_wall_s = s.recv_wall_s
            log.info("episode result: %s after %.1f s of sim time (%s)", result.outcome, result.sim_time_s,
                     result.detail)

    # -- derived --------------------------------------------------------------------------------

    def trajectory(self) -> dict[str, list]:
        """Per state: time, world position (start + local NED), altitude, the controller's state."""
        x0, y0, _ = self.start
        rows: dict[str, list] = {"t_s": [], "x_m": [], "y_m": [], "alt_m": [], "state": [], "watchdog": [],
                                 "cmd_down_m_s": []}
        name, watchdog, down_m_s = "INIT", "hold", 0.0
        for st in self.states:
            status = self.statuses.get(st.stamp.t_s)
            if status is not None:
                name, watchdog, down_m_s = status.state, status.watchdog, status.vel_body_frd_m_s[2]
            north_m, east_m, _down_m = st.pos_local_ned_m
            rows["t_s"].append(st.stamp.t_s)
            rows["x_m"].append(x0 + east_m)
            rows["y_m"].append(y0 + north_m)
            rows["alt_m"].append(st.alt_agl_m)
            rows["state"].append(name)
            rows["watchdog"].append(watchdog)
            rows["cmd_down_m_s"].append(down_m_s)  # what the controller commanded at this tick
        return rows

    def transport_overhead_s(self, command_to_sim_s: dict[int, float] | None, lockstep: bool) -> list[float]:
        """Per decision: frame->segmenter + heatmap->controller + command->sim, wall seconds.

        Everything between a frame's publication and its command's arrival except inference,
        policy and the lockstep protocol's deliberate waits (a heatmap is held until it is due).
        Each hop is the receiving service's own stamp. In real time the controller takes a
        heatmap at its next 20 Hz tick, a wait that is the loop's, not transport: that hop is
        then the monitor's delivery time instead.
        """
        cmd_hops = command_to_sim_s if command_to_sim_s else self.cmd_delivery_by_frame
        hm_hops = self.hm_to_ctrl_by_seq if lockstep else self.heatmap_delivery_by_seq
        return self._chain(self.frame_to_seg_by_seq, hm_hops, cmd_hops)

    def zenoh_delivery_overhead_s(self) -> list[float]:
        """The same three hops as Zenoh delivers them (arrival stamped in the monitor's callbacks)."""
        return self._chain(self.camera_delivery_by_seq, self.heatmap_delivery_by_seq, self.cmd_delivery_by_frame)

    @staticmethod
    def _chain(first: dict[int, float], middle: dict[int, float], last: dict[int, float]) -> list[float]:
        out = []
        for seq, first_s in first.items():
            hm_s, last_s = middle.get(seq), last.get(seq)
            if hm_s is not None and last_s is not None:
                out.append(first_s + hm_s + last_s)
        return out


class Monitor:
    """`up`'s own Zenoh session: callbacks only stamp arrival and queue; `drain()` decodes."""

    TOPICS = ("state", "status", "cmd", "heatmap", "camera", "episode")

    def __init__(self, session: Any, vehicle_id: str, recorder: Recorder, with_camera: bool) -> None:
        self.recorder = recorder
        self._queue: deque[Sample] = deque()  # deque.append/popleft are atomic: no lock needed
        self._subs = []
        for topic in self.TOPICS:
            if topic == "camera" and not with_camera:
                continue
            key = getattr(keys, topic)(vehicle_id)
            self._subs.append(session.declare_subscriber(key, self._callback(topic)))

    def _callback(self, topic: str):
        queue = self._queue

        def on_sample(sample: Any) -> None:
            # Arrival stamped here, in Zenoh's thread: it is the transport measurement.
            queue.append(Sample(topic, time.time(), sample.payload.to_bytes()))

        return on_sample

    def drain(self, max_items: int = 10_000) -> int:
        n = 0
        while self._queue and n < max_items:
            self.recorder.handle(self._queue.popleft())
            n += 1
        return n

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()


# ------------------------------------------------------------------------ the report


def _percentiles_ms(values: Sequence[float]) -> dict[str, float | int | None]:
    if not values:
        return {"p50": None, "p99": None, "n": 0}
    arr = np.asarray(values, dtype=np.float64) * 1e3
    return {"p50": round(float(np.percentile(arr, 50)), 3), "p99": round(float(np.percentile(arr, 99)), 3),
            "n": int(arr.size)}


def _read_stats(out: Path) -> dict[str, Any]:
    stats = {}
    for name in SERVICES:
        path = out / "stats" / f"{name}.json"
        if path.exists():
            try:
                stats[name] = json.loads(path.read_text())
            except (OSError, ValueError) as exc:
                log.warning("stats of %s unreadable (%s): ignored", name, exc)
    return stats


def _command_to_sim(sim_stats: dict[str, Any] | None) -> tuple[list[float], dict[int, float] | None]:
    """The sim's own command receive latencies, if its stats carry them (seconds)."""
    if not sim_stats:
        return [], None
    by_frame = sim_stats.get("command_to_sim_s_by_frame")
    values = sim_stats.get("command_to_sim_s") or []
    by_frame = {int(k): float(v) for k, v in by_frame.items()} if isinstance(by_frame, dict) else None
    return [float(v) for v in values if isinstance(v, (int, float))], by_frame


def build_report(options: UpOptions, rec: Recorder, start: tuple[float, float, float], noise: float,
                 stats: dict[str, Any], failure: dict[str, Any] | None, interrupted: bool,
                 wall_time_s: float) -> dict[str, Any]:
    traj = rec.trajectory()
    res = rec.result
    cmd_to_sim, cmd_by_frame = _command_to_sim(stats.get("sim"))
    latency = {s: _percentiles_ms(rec.latency[s]) for s in STAGES if s != "command_to_sim"}
    if not options.lockstep:
        latency["heatmap_to_controller"]["note"] = (
            "stamped when the controller's 20 Hz loop takes the heatmap: includes up to one period of waiting")
    if cmd_to_sim:
        latency["command_to_sim"] = {**_percentiles_ms(cmd_to_sim), "measured_by": "sim"}
    else:
        # The sim did not report its receive times: the same hop measured at the monitor instead.
        latency["command_to_sim"] = {**_percentiles_ms(rec.delivery_s["cmd"]), "measured_by": "monitor"}
    if not options.lockstep:
        latency["command_to_sim"]["note"] = "real time: the sim takes the newest command at its next step (<= 50 ms)"
    if rec.backend is not None:
        backend, simulated = rec.backend
    else:
        backend, simulated = f"{options.segmenter} (no heatmap seen)", options.segmenter == "sim"
    if res is not None:
        outcome, detail = res.outcome, res.detail
        final = {"x_m": res.final_x_m, "y_m": res.final_y_m, "alt_m": res.final_alt_m}
        sim_time_s, path_length_m = res.sim_time_s, res.path_length_m
    else:
        outcome = "error"
        detail = failure["message"] if failure else ("interrupted by the user" if interrupted else "no result")
        final = ({"x_m": traj["x_m"][-1], "y_m": traj["y_m"][-1], "alt_m": traj["alt_m"][-1]}
                 if traj["t_s"] else None)
        sim_time_s = traj["t_s"][-1] - traj["t_s"][0] if traj["t_s"] else 0.0
        xy = np.column_stack([traj["x_m"], traj["y_m"]]) if traj["t_s"] else np.zeros((0, 2))
        path_length_m = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0
    overhead = rec.transport_overhead_s(cmd_by_frame, options.lockstep)
    return {
        "outcome": outcome, "detail": detail, "judged": res is not None and res.outcome in JUDGE_OUTCOMES,
        "sim_time_s": sim_time_s, "path_length_m": path_length_m,
        "start": {"x_m": start[0], "y_m": start[1], "alt_m": start[2]}, "final": final,
        "classes_found": list(res.classes_found) if res else [],
        "closest_unsafe_m": res.closest_unsafe_m if res and res.closest_unsafe_valid else None,
        "world": options.world, "backend": backend, "simulated": simulated, "segmenter_option": options.segmenter,
        "noise": noise if simulated else None, "policy": options.policy, "timing": options.timing,
        "seed": options.seed, "mode": "lockstep" if options.lockstep else "realtime",
        "vehicle": options.vehicle or "sim", "vehicle_id": options.vehicle_id, "safety_radius_m": 2.0,
        "time_limit_s": options.time_limit_s, "wall_time_s": round(wall_time_s, 3),
        "episode_wall_s": (round(rec.result_wall_s - rec.first_state_wall_s, 3)
                           if rec.result_wall_s is not None and rec.first_state_wall_s is not None else None),
        "latency_ms": latency,
        "transport_overhead_ms": {**_percentiles_ms(overhead), "definition": (
            "per decision: frame->segmenter + heatmap->controller + command->sim, each stamped by the "
            "receiving service (real time: the heatmap hop as the monitor sees it); excludes inference, "
            "policy and lockstep waits")},
        "zenoh_delivery_overhead_ms": {**_percentiles_ms(rec.zenoh_delivery_overhead_s()), "definition": (
            "per decision: frame, heatmap and command delivery as the monitor's callbacks see them "
            "(no service polling)")},
        "delivery_ms": {k: _percentiles_ms(v) for k, v in rec.delivery_s.items()},
        "counts": {"frames": rec.frames, "heatmaps": rec.heatmaps, "commands": rec.commands,
                   "statuses": rec.status_count, "states": len(rec.states), "rejected": rec.rejected
                   + sum(_rejected_in(st) for st in stats.values())},
        "service_stats": stats,
        "failure": failure, "interrupted": interrupted,
        "trajectory": traj,
    }


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


def write_outputs(world: Any, report: dict[str, Any], rec: Recorder, out: Path, video: bool) -> dict[str, str]:
    """report.json, trajectory.png and the video; a failing picture is logged, never fatal."""
    from dovesei.pictures import common as pictures, plots, video as videos

    files = {"report": "report.json"}
    if report["trajectory"]["t_s"]:
        try:
            plots.plot_trajectory(world, report, out / "trajectory.png")
            files["trajectory_plot"] = "trajectory.png"
        except (ImportError, pictures.ReportError) as exc:
            log.warning("no trajectory plot: %s", exc)
    if video and rec.video_frames:
        try:
            path = videos.write_video(_video_frames(rec, backend_text(report)), out / "episode.mp4")
            files["video"] = path.name
        except pictures.ReportError as exc:
            log.warning("no video: %s", exc)
    report["files"] = files
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return files


def _video_frames(rec: Recorder, perception: str) -> list:
    from dovesei.pictures.video import VideoFrame

    frames = []
    for seq in sorted(rec.video_frames):
        kept = rec.video_frames[seq]
        image = cv2.cvtColor(cv2.imdecode(kept["jpeg"], cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        prob = None
        if "prob" in kept:
            arr, is_u8 = kept["prob"]
            prob = arr.astype(np.float32) / 255.0 if is_u8 else arr.astype(np.float32)
        st: ControllerStatus | None = kept.get("status")
        frames.append(VideoFrame(
            t_s=kept["t_s"], image_rgb=image, prob_safe=prob, alt_agl_m=kept["alt"],
            state=st.state if st else "", watchdog=st.watchdog if st else "",
            focus_radius_px=st.focus_radius_px if st else 0.0,
            target_px=(st.target_row_px, st.target_col_px) if st and st.target_valid else None,
            perception=perception))
    return frames


# ------------------------------------------------------------------------ run


def takeoff(options: UpOptions, alt_m: float) -> None:
    """Only with --takeoff: GUIDED, arm and climb to the start altitude, then hand the link back."""
    from dovesei.controller.mavlink import MavlinkVehicle

    log.warning("--takeoff: arming %s and climbing to %.1f m", options.vehicle, alt_m)
    with MavlinkVehicle(options.vehicle, vehicle_id=options.vehicle_id) as vehicle:
        vehicle.connect(30.0)
        vehicle.arm_and_takeoff(alt_m)


def run(options: UpOptions, *, stop: threading.Event) -> int:
    """Fly one episode; writes the report folder and returns the exit code."""
    import zenoh

    from dovesei.segmenter.simulated import SimPerceptionParams
    from dovesei.shared.zconfig import zenoh_config
    from dovesei.sim.world import load_world

    t0 = time.monotonic()
    out = options.out
    (out / "logs").mkdir(parents=True, exist_ok=True)
    (out / "stats").mkdir(exist_ok=True)
    world = load_world(options.world)
    start = resolve_start(world, options)
    noise = SimPerceptionParams().noise if options.noise is None else float(options.noise)
    log.info("world %s (%.0f x %.0f m), start (%.1f, %.1f) m at %.0f m, policy %s, %s timing, %s, segmenter %s",
             options.world, world.width_m, world.height_m, *start, options.policy, options.timing,
             "lockstep" if options.lockstep else "real time", options.segmenter)
    if options.vehicle and options.segmenter == "sim":
        log.warning("--segmenter sim with --vehicle: heatmaps come from the world's labels at the autopilot's "
                    "pose, not from a model")
    if options.segmenter != "sim" and options.lockstep and options.timing == "reference":
        log.warning("a model segmenter in lockstep with reference timing runs one inference per 0.05 s of sim "
                    "time; --timing real needs ten times fewer")
    if options.takeoff:
        takeoff(options, start[2])

    ports = {name: free_port() for name in (*SERVICES, "monitor")}
    commands = child_commands(options, start, ports, out, noise)
    monitor_conf = (zenoh_config(mode="client", connect=options.connect, env={}) if options.connect else
                    zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{ports['monitor']}"], multicast_scouting=False,
                                 env={}))
    rec = Recorder(start, video=options.video)
    children = Children(out / "logs")
    failure: dict[str, Any] | None = None
    interrupted = False
    session = zenoh.open(monitor_conf)
    monitor = None
    try:
        # Subscribed before any child starts: the first state the sim publishes is recorded.
        monitor = Monitor(session, options.vehicle_id, rec, with_camera=options.video)
        for name in SERVICES:
            children.start(name, commands[name], child_env(name, options))
        (out / "pids.json").write_text(json.dumps({"up": os.getpid(), **{n: p.pid for n, p in children.procs.items()}}))
        failure, interrupted = _watch(options, rec, monitor, children, stop, t0)
        if rec.result is not None:
            # The sim ends its run once the result is out: a signal now would only cut its shutdown.
            children.wait_exit("sim", RESULT_AFTER_EXIT_S)
    finally:
        codes = children.stop_all()
        if monitor is not None:
            monitor.drain()
            monitor.close()
        session.close()
    log.info("children stopped: %s", ", ".join(f"{n} {_describe_exit(c)}" for n, c in codes.items()))

    stats = _read_stats(out)
    report = build_report(options, rec, start, noise, stats, failure, interrupted, time.monotonic() - t0)
    files = write_outputs(world, report, rec, out, options.video)
    log.info("report: %s (%s)", out / "report.json", ", ".join(files.values()))
    if failure is not None:
        print(f"dovesei up: {failure['message']}", file=sys.stderr)
        return EXIT_FAILED
    if interrupted:
        print("dovesei up: interrupted; every service stopped", file=sys.stderr)
        return EXIT_INTERRUPTED
    summary = (f"{report['outcome']}: {report['detail']} ({report['sim_time_s']:.1f} s sim in "
               f"{report['episode_wall_s'] or report['wall_time_s']:.1f} s wall, path {report['path_length_m']:.0f} m, "
               f"{backend_text(report)}); transport overhead p50 {report['transport_overhead_ms']['p50']} ms")
    print(summary)
    return EXIT_OK if report["judged"] else EXIT_FAILED


def backend_text(report: dict[str, Any]) -> str:
    from dovesei.pictures.common import backend_label

    return backend_label(report["backend"], report["simulated"], report.get("noise"))


def _watch(options: UpOptions, rec: Recorder, monitor: Monitor, children: Children, stop: threading.Event,
           t0: float) -> tuple[dict[str, Any] | None, bool]:
    """Record until the result, a dead child (plus --after-failure-s) or a stop; returns (failure, interrupted)."""
    failure: dict[str, Any] | None = None
    failure_deadline = math.inf
    while True:
        monitor.drain()
        if rec.result is not None:
            return failure, False
        if stop.is_set():
            return failure, True
        now = time.monotonic()
        if failure is None:
            dead = children.exited()
            if dead:
                name, code = dead[0]
                if name == "sim":
                    # A sim that ended the episode publishes its result just before exiting (code 1
                    # for an 'error' ending, such as a silent controller): let the result arrive.
                    deadline = now + RESULT_AFTER_EXIT_S
                    while rec.result is None and time.monotonic() < deadline:
                        monitor.drain()
                        stop.wait(0.01)
                    if rec.result is not None:
                        return None, False
                line = last_error_line(children.log_path(name))
                message = (f"{name} (pid {children.procs[name].pid}) {_describe_exit(code)} before the episode "
                           f"ended; last log line: {line or '(empty log)'}")
                log.error("%s", message)
                failure = {"child": name, "returncode": code, "last_line": line, "message": message}
                # The others keep running for a while so the report shows how they reacted.
                failure_deadline = now + (options.after_failure_s if name != "sim" else 0.0)
        if now >= failure_deadline:
            return failure, False
        if failure is None and not rec.states and not rec.status_count and now - t0 > options.startup_timeout_s:
            message = (f"no vehicle state or controller status within {options.startup_timeout_s:.0f} s of "
                       f"starting; see the logs in {children.log_dir}")
            log.error("%s", message)
            return {"child": None, "returncode": None, "last_line": "", "message": message}, False
        stop.wait(0.005)




# ------------------------------------------------------------------------ command line


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dovesei up", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", default="synthetic", help="synthetic[:seed=N,size_m=X,...] or a world folder")
    p.add_argument("--segmenter", default="auto", choices=("auto", "clipseg", "sim"),
                   help="auto: CLIPSeg when its weights load locally, else the simulated perception")
    p.add_argument("--model", help="CLIPSeg Hub id or local directory (default: the segmenter's)")
    p.add_argument("--policy", default="dovesei", help="landing policy (dovesei, dovesei-nofocus)")
    p.add_argument("--timing", default="reference", choices=("reference", "real"), help="timing preset")
    p.add_argument("--seed", type=int, default=0, help="seed of the perception noise and of the start")
    p.add_argument("--noise", type=float, help="simulated perception noise scale (default: calibrated)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--start", metavar="X,Y[,ALT]", help="start position in world metres (x east, y north)")
    where.add_argument("--start-seed", type=int, help="draw the start like the bench's start 0 with this seed")
    p.add_argument("--start-alt-m", type=float, default=100.0, help="start altitude when --start gives none")
    p.add_argument("--time-limit-s", type=float, default=None,
                   help="sim-time limit of the episode (default: the paper's 1200 s on the preset's clock, "
                        "as `dovesei bench`: 60 s with --timing reference, 1200 s with --timing real)")
    p.add_argument("--out", type=Path, help="report folder (default: runs/up-<timestamp>)")
    p.add_argument("--realtime", action="store_true", help="wall-clock rate instead of lockstep")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="use a Zenoh router at this endpoint instead of loopback peers (repeatable)")
    p.add_argument("--vehicle", metavar="URL",
                   help="fly a real autopilot (pymavlink URL); it must already fly in GUIDED/OFFBOARD")
    p.add_argument("--pose-url", metavar="URL",
                   help="with --vehicle: the MAVLink URL the sim reads the pose from (default: --vehicle)")
    p.add_argument("--takeoff", action="store_true", help="with --vehicle: arm and climb to the start altitude first")
    p.add_argument("--video", action=argparse.BooleanOptionalAction, default=True, help="write episode.mp4")
    p.add_argument("--vehicle-id", default="uav1")
    p.add_argument("--heatmap-wait-s", type=float,
                   help="controller, lockstep: wall seconds to wait for a due heatmap (default: the controller's)")
    p.add_argument("--heatmap-hold-after-s", type=float,
                   help="controller watchdog: hold when the heatmap is older than this (default: the controller's)")
    p.add_argument("--after-failure-s", type=float, default=5.0,
                   help="after a service dies, keep recording this long before stopping the others")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return p


def options_from_args(args: argparse.Namespace) -> UpOptions:
    from dovesei.bench import paper_time_limit_s

    start = None
    if args.start:
        x_m, y_m, alt_m = parse_start(args.start)
        start = (x_m, y_m, args.start_alt_m if alt_m is None else alt_m)
    out = args.out or Path("runs") / f"up-{datetime.now().strftime('%Y%m%d-%H%M%S')}"
    return UpOptions(world=args.world, segmenter=args.segmenter, policy=args.policy, timing=args.timing,
                     seed=args.seed, noise=args.noise, start=start, start_seed=args.start_seed,
                     start_alt_m=args.start_alt_m, out=out, realtime=args.realtime, connect=tuple(args.connect),
                     vehicle=args.vehicle, pose_url=args.pose_url, takeoff=args.takeoff,
                     time_limit_s=paper_time_limit_s(args.timing) if args.time_limit_s is None else args.time_limit_s,
                     video=args.video, model=args.model, vehicle_id=args.vehicle_id,
                     heatmap_wait_s=args.heatmap_wait_s, heatmap_hold_after_s=args.heatmap_hold_after_s,
                     after_failure_s=args.after_failure_s, log_level=args.log_level)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = install_stop_handlers()
    from dovesei.sim.world import WorldError

    try:
        options = options_from_args(args)
        from dovesei.controller.policies import policy_names

        if options.policy not in policy_names():
            raise ConfigError(f"--policy {options.policy!r}: choose one of {', '.join(policy_names())}")
        return run(options, stop=stop)
    except (ConfigError, WorldError) as exc:  # bad flags, or a world or start that cannot be used
        print(f"dovesei up: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except DoveseiError as exc:  # could not run: takeoff refused, a service command line unreadable
        print(f"dovesei up: {exc}", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
