"""The simulator as a Zenoh service (`dovesei-sim`): `SimCore` on the wire, one episode per run.

    SimCore.reset/step --CameraFrame--> camera key     (JPEG on the wire with --jpeg-quality)
                       --VisualOdometry-> odometry key (with --odometry-rate-hz; before the state)
                       --VehicleState-> state key
                       --EpisodeResult-> episode key   (once, at the end; also logged)
    crop key (queryable) --CropServer thread--> SimCore.crop --> CropFrame (the newest frame's view)
    cmd key --Inbox--> VelocityCommand --> SimCore.step
    status key --Inbox (newest)--> ControllerStatus --> SimCore.note_status (the judge's confirmed
                                   ground: where the policy's confirming look lies, for the touchdown error)

Three ways to run an episode, chosen by the config:

- lockstep (default; deterministic on any host): at step k the frame due (if any) is published
  before state k, then the sim waits for the command whose `state_seq == k` (FIFO inbox; older
  answers are stale and dropped). No answer within `cmd_timeout_s` wall seconds ends the episode
  as 'error' naming the controller. Waiting sleeps in `Inbox.recv`, it never spins.
- real time: step k is due at t0 + k x dt / speed on the wall clock (absolute schedule, so delays
  never accumulate); each step takes the newest command and never waits. A controller that falls
  silent is handled by the vehicle itself: its command times out in sim time and it brakes.
- external pose (`external_pose`, run by `dovesei.sim.external`): no own dynamics and no
  commands. The sim LISTENS on the state key, where the controller of a real or SITL autopilot
  publishes the autopilot's VehicleState (only the controller opens MAVLink); the newest state
  with a local position is placed in the world with the local origin at the start (north = +y,
  east = +x), frames are rendered there at the frame rate of the wall clock and the judge
  watches the same world. Nothing is published on the state key in this mode: monitors read
  the controller's states there directly. With `--sitl-truth udpin:HOST:PORT` (ArduPilot SITL),
  the image and the judge follow SITL's TRUE pose, read from SIM_STATE on a SEPARATE SITL output
  (`dovesei.sim.sitl_truth`), while the frames keep the estimate's stamp, altitude and attitude:
  the truth never reaches a policy. With `--odometry-after-result-s` the camera's odometry goes on
  after the result (published at once) until stopped: the autopilot's EKF may fly on it to touchdown.

`main` only parses flags, sets up logging and signals, loads the world, opens the session and
calls `run`; `run` reads no flags or environment, so tests call it with a hand-made world.
Exit status: 0 when the episode reached an outcome (or was stopped by a signal), 1 on 'error'.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import zenoh

from dovesei.shared import keys, validate
from dovesei.shared.cliconfig import CommandLine, Flag, integer_in, non_blank
from dovesei.shared.clock import WallClock
from dovesei.shared.codec import encode
from dovesei.shared.crop_server import CropServer
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.lifecycle import Inbox, declare_alive, install_stop_handlers, is_alive, write_stats
from dovesei.shared.messages import CameraFrame, ControllerStatus, EpisodeResult, VehicleState, VelocityCommand, VisualOdometry
from dovesei.shared.timing import TIMING_NAMES
from dovesei.shared.zconfig import open_session
from dovesei.sim.core import SimConfig, SimCore, StepOut, unstarted_result
from dovesei.sim.estimator import VEHICLE_PROFILE_NAMES
from dovesei.sim.external import PoseCamera, run_external_pose
from dovesei.sim.sitl_truth import SitlTruth, parse_truth_url
from dovesei.sim.starts import Start, generate_starts
from dovesei.sim.world import World, WorldError, load_world

log = logging.getLogger(__name__)

WAITABLE = ("segmenter", "controller")  # services whose liveliness --wait-for accepts
# Real time: when the loop falls this far behind its schedule (a stalled host), it drops the debt
# and restarts the schedule from now instead of bursting through the missed steps.
_MAX_BEHIND_S = 1.0
_MAX_LATENCY_SAMPLES = 200_000  # about 3 h of commands at 20 Hz: bounded memory for any episode


@dataclass(frozen=True)
class SimServiceConfig:
    """Everything `run` needs besides the session and the world; built from flags by `config_from_args`."""

    sim: SimConfig = field(default_factory=SimConfig)
    world: str = "synthetic"  # the --world spec (loaded by main; named in logs)
    start_xy_alt_m: tuple[float, float, float] | None = None  # None: generated from start_seed
    start_seed: int = 0
    start_alt_m: float = 100.0  # altitude of a generated start
    lockstep: bool = True
    speed: float = 1.0  # real time only: sim seconds per wall second
    jpeg_quality: int | None = None  # None: raw frames on the wire
    external_pose: bool = False  # render at the VehicleState received on the state key, no own dynamics
    # External pose against ArduPilot SITL: render and judge at SIM_STATE read on this SITL output
    # (udpin:HOST:PORT, never the controller's link) instead of at the controller's estimate.
    sitl_truth: str | None = None
    wait_for: tuple[str, ...] = ()  # liveliness tokens to see before the episode starts
    wait_timeout_s: float = 60.0
    cmd_timeout_s: float = 10.0  # lockstep: wall wait for a command; external pose: for a new state
    # External pose with odometry: after the judged end the camera's odometry goes on (no frames) for at
    # most this long, until stopped: an autopilot whose EKF flies on it still needs it until it has landed.
    odometry_after_result_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("speed", "wait_timeout_s", "cmd_timeout_s", "start_alt_m"):
            validate.positive(f"sim service {name}", getattr(self, name))
        if self.jpeg_quality is not None:
            validate.in_range("--jpeg-quality", self.jpeg_quality, 1, 100)
        unknown = [s for s in self.wait_for if s not in WAITABLE]
        if unknown:
            raise ConfigError(f"--wait-for {','.join(unknown)}: choose among {','.join(WAITABLE)}")
        if self.start_xy_alt_m is not None:
            validate.finite_vector("--start", self.start_xy_alt_m, 3)
        validate.in_range("--odometry-after-result-s", self.odometry_after_result_s, 0.0, 3600.0)
        if self.odometry_after_result_s > 0 and not (self.external_pose and self.sim.odometry_rate_hz > 0):
            raise ConfigError("--odometry-after-result-s applies to the camera mode with odometry only "
                              "(--external-pose and --odometry-rate-hz above 0)")
        if not isinstance(self.external_pose, bool):
            raise ConfigError(f"sim service external_pose must be true or false, got {self.external_pose!r}")
        if self.sitl_truth is not None:
            parse_truth_url(self.sitl_truth)
            if not self.external_pose:
                raise ConfigError("--sitl-truth applies to the camera mode only (--external-pose): the sim's own "
                                  "dynamics already know the truth")


@dataclass
class SimStats:
    """What one `run` did (tests and the shutdown log read it)."""

    steps: int = 0
    frames_sent: int = 0
    odometry_sent: int = 0
    states_sent: int = 0
    commands_used: int = 0
    commands_stale: int = 0  # lockstep: answers to an earlier state (or the controller's hold)
    commands_not_fresh: int = 0  # real time: stamps too old (or ahead, or not on the sim clock): dropped
    commands_foreign: int = 0  # a vehicle id other than ours on our key
    commands_rejected: int = 0  # payloads the codec refused (counted by the inbox)
    states_rejected: int = 0  # external pose: state payloads the codec refused
    poses_received: int = 0  # external pose: states of our vehicle with a local position used
    truth_samples: int = 0  # external pose with --sitl-truth: SIM_STATEs received and checked
    truth_rejected: int = 0  # ... and refused (out of range, non-finite)
    states_foreign: int = 0  # external pose: a vehicle id other than ours on our state key
    overruns: int = 0  # real time: schedule restarts after falling behind
    frames_skipped: int = 0  # external pose: states whose attitude no frame can show (view at the horizon)
    crops_answered: int = 0  # close looks served on the crop key
    crops_refused: int = 0
    # Transport latency of each command used (wall: received here - sent by the controller), and
    # of the first command made from each frame's heatmap (for `dovesei up`'s per-frame budget).
    command_to_sim_s: deque[float] = field(default_factory=lambda: deque(maxlen=_MAX_LATENCY_SAMPLES))
    command_to_sim_s_by_frame: dict[int, float] = field(default_factory=dict)

    def on_command(self, cmd: VelocityCommand, recv_wall_s: float) -> None:
        self.commands_used += 1
        if cmd.sent_wall_s > 0:  # 0: a sender that does not stamp (then nothing to measure)
            hop_s = recv_wall_s - cmd.sent_wall_s
            self.command_to_sim_s.append(hop_s)
            if cmd.frame_seq >= 0 and len(self.command_to_sim_s_by_frame) < _MAX_LATENCY_SAMPLES:
                self.command_to_sim_s_by_frame.setdefault(cmd.frame_seq, hop_s)

    def to_json(self) -> dict:
        out = {k: v for k, v in vars(self).items() if isinstance(v, int)}
        out["command_to_sim_s"] = [round(v, 6) for v in self.command_to_sim_s]
        out["command_to_sim_s_by_frame"] = {str(k): round(v, 6) for k, v in self.command_to_sim_s_by_frame.items()}
        return out


def resolve_start(world: World, config: SimServiceConfig) -> Start:
    """The start of the episode: the explicit --start; a world built around one start (paper-paris:
    its home), as `dovesei up` flies it; else generate_starts(seed)[0]."""
    if config.start_xy_alt_m is not None:
        x_m, y_m, alt_m = config.start_xy_alt_m
        if not world.contains(x_m, y_m):
            raise ConfigError(f"--start {x_m:g},{y_m:g} lies outside world {world.name!r} "
                              f"({world.width_m:.0f} x {world.height_m:.0f} m, origin at its south-west corner)")
        if alt_m <= 0:
            raise ConfigError(f"--start altitude must be > 0 m, got {alt_m:g}")
        return Start(x_m, y_m, alt_m)
    if world.home_xy_m is not None:
        return Start(float(world.home_xy_m[0]), float(world.home_xy_m[1]), float(config.start_alt_m))
    return generate_starts(world, 1, config.start_seed, alt_m=config.start_alt_m, cam=config.sim.camera)[0]


class _Wire:
    """Publishers, the command inbox and the liveliness token of one run; closed together."""

    def __init__(self, session: zenoh.Session, config: SimServiceConfig) -> None:
        vid = config.sim.vehicle_id
        self.session = session
        self.jpeg_quality = config.jpeg_quality
        self._closers: list = []
        try:
            # Lockstep must lose nothing (a dropped state stalls the episode): block under congestion.
            # Real time prefers dropping an old frame to delaying the next one (Zenoh's default).
            flow = zenoh.CongestionControl.BLOCK if config.lockstep else zenoh.CongestionControl.DROP
            self.camera = self._keep(session.declare_publisher(keys.camera(vid), congestion_control=flow))
            self.odometry = self._keep(session.declare_publisher(keys.odometry(vid), congestion_control=flow)) \
                if config.sim.odometry_rate_hz > 0 else None
            self.state = None
            self.states: Inbox[VehicleState] | None = None
            # The controller's newest status: its hand-over, which alone ends an external-pose
            # episode as a landing (sim.judge), and the look that confirmed its spot.
            self.statuses = self._keep(Inbox(session, keys.status(vid), ControllerStatus, newest_only=True))
            if config.external_pose:
                # The controller publishes the autopilot's state here; the sim only listens.
                self.states = self._keep(Inbox(session, keys.state(vid), VehicleState, newest_only=True))
            else:
                self.state = self._keep(session.declare_publisher(keys.state(vid), congestion_control=flow))
            # The result is published once, just before the session closes: no batching delay.
            self.episode = self._keep(session.declare_publisher(
                keys.episode(vid), congestion_control=zenoh.CongestionControl.BLOCK, express=True))
            self.cmds: Inbox[VelocityCommand] | None = None
            if not config.external_pose:
                # Lockstep needs every answer in order; real time only ever wants the newest.
                self.cmds = self._keep(Inbox(session, keys.cmd(vid), VelocityCommand,
                                             newest_only=not config.lockstep))
            # Declared last: whoever sees the token knows our subscriber is already in place.
            self.token = self._keep(declare_alive(session, vid, "sim"))
            self.result_sent = False
        except BaseException:
            self.close()
            raise

    def _keep(self, thing):
        self._closers.append(thing)
        return thing

    def publish(self, out: StepOut, stats: SimStats) -> None:
        """Frame first, then state: the protocol's order for one step."""
        if out.frame is not None:
            self.publish_frame(out.frame, stats)
        if out.odometry is not None:
            self.publish_odometry(out.odometry, stats)
        self.state.put(encode(out.state))
        stats.states_sent += 1

    def publish_result(self, result: EpisodeResult) -> None:
        """The episode's result, once (the camera mode may send it before its odometry's tail)."""
        if not self.result_sent:
            self.episode.put(encode(result))
            self.result_sent = True

    def end_episode(self, result: EpisodeResult) -> None:
        """The result before the odometry's tail, and the run's liveliness token dropped with it: the
        episode is over (a watcher takes a result as the sim's once the sim has ended its run; the
        odometry that goes on is the camera's, not the episode's)."""
        self.publish_result(result)
        if self.token in self._closers:
            self._closers.remove(self.token)
            self.token.undeclare()

    def publish_frame(self, frame: CameraFrame, stats: SimStats) -> None:
        self.camera.put(encode(frame, jpeg_quality=self.jpeg_quality))
        stats.frames_sent += 1

    def publish_odometry(self, odometry: VisualOdometry, stats: SimStats) -> None:
        if self.odometry is not None:
            self.odometry.put(encode(odometry))
            stats.odometry_sent += 1

    def close(self) -> None:
        for thing in reversed(self._closers):
            thing.close() if isinstance(thing, Inbox) else thing.undeclare()
        self._closers.clear()


def run(session: zenoh.Session, *, config: SimServiceConfig, stop: threading.Event, world: World | None = None,
        stats: SimStats | None = None) -> EpisodeResult | None:
    """Fly one episode and publish its result; None when `stop` ended it first.

    `world` defaults to loading `config.world` (main passes the world it loaded); `stats`, when
    given, is filled in as the run goes.
    """
    stats = stats if stats is not None else SimStats()
    world = world if world is not None else load_world(config.world)
    start = resolve_start(world, config)
    wire = _Wire(session, config)
    try:
        mode = ("external pose from " + keys.state(config.sim.vehicle_id) if config.external_pose
                else "lockstep" if config.lockstep else f"real time x{config.speed:g}")
        log.info("sim %s up: world %s (%.0f x %.0f m), start (%.1f, %.1f) m at %.0f m, %s timing "
                 "(frame every %.2f s, latency %.2f s), %s, keys %s",
                 config.sim.vehicle_id, world.name, world.width_m, world.height_m, start.x_m, start.y_m, start.alt_m,
                 config.sim.timing, config.sim.period_s, config.sim.delay_s, mode, keys.camera(config.sim.vehicle_id))
        missing = _wait_for_services(session, config, stop)
        if stop.is_set():
            return None
        if missing:
            result = _never_started(world, start, config, missing)
        elif config.external_pose:
            result = _run_external(wire, world, start, config, stop, stats)
        else:
            core = SimCore(world, start, config.sim)
            # The camera's close looks (crop key), answered on their own thread from the newest frame.
            crops = CropServer(session, config.sim.vehicle_id, core.crop)
            try:
                if config.lockstep:
                    result = _run_lockstep(wire, core, config, stop, stats)
                else:
                    result = _run_realtime(wire, core, config, stop, stats)
            finally:
                crops.close()
                stats.crops_answered, stats.crops_refused = crops.answered, sum(crops.refused.values())
        if wire.cmds is not None:
            stats.commands_rejected = sum(wire.cmds.rejected.values())
        if wire.states is not None:
            stats.states_rejected = sum(wire.states.rejected.values())
        if result is None:
            log.info("sim %s stopped before the episode ended", config.sim.vehicle_id)
            return None
        log.info("episode %s: %s after %.1f s, path %.1f m, at (%.1f, %.1f) m alt %.1f m: %s",
                 result.vehicle_id, result.outcome, result.sim_time_s, result.path_length_m, result.final_x_m,
                 result.final_y_m, result.final_alt_m, result.detail)
        wire.publish_result(result)
        return result
    finally:
        wire.close()


def _run_external(wire: _Wire, world: World, start: Start, config: SimServiceConfig, stop: threading.Event,
                  stats: SimStats) -> EpisodeResult | None:
    """Camera mode: render at the controller's states, or at SITL's truth when configured; the
    close looks (crop key) are cut from the newest frame's view, as in the sim's own flights."""
    camera = PoseCamera(world, config.sim)

    def fly(truth: SitlTruth | None) -> EpisodeResult | None:
        crops = CropServer(wire.session, config.sim.vehicle_id, camera.crop)
        try:
            return run_external_pose(wire.states, lambda frame: wire.publish_frame(frame, stats), world, start,
                                     config.sim, publish_odometry=lambda odo: wire.publish_odometry(odo, stats),
                                     wait_timeout_s=config.wait_timeout_s, state_timeout_s=config.cmd_timeout_s,
                                     stop=stop, stats=stats, truth=truth, statuses=wire.statuses,
                                     odometry_after_s=config.odometry_after_result_s, on_result=wire.end_episode,
                                     camera=camera)
        finally:
            crops.close()
            stats.crops_answered, stats.crops_refused = crops.answered, sum(crops.refused.values())

    if config.sitl_truth is None:
        return fly(None)
    with SitlTruth(config.sitl_truth) as truth:
        try:
            return fly(truth)
        finally:
            stats.truth_samples, stats.truth_rejected = truth.samples, truth.rejected


def _never_started(world: World, start: Start, config: SimServiceConfig, detail: str) -> EpisodeResult:
    """The 'error' result of an episode that could not begin, placed at the start."""
    return unstarted_result(world, start, config.sim, detail, clock="vehicle" if config.external_pose else "sim")


def _wait_for_services(session: zenoh.Session, config: SimServiceConfig, stop: threading.Event) -> str:
    """Wait for the liveliness tokens of `config.wait_for`; '' when all are up, else what is missing."""
    vid = config.sim.vehicle_id
    clock = WallClock()
    pending = list(config.wait_for)
    while pending and not stop.is_set():
        # is_alive asks the network and waits for the replies: this loop never spins.
        pending = [s for s in pending if not is_alive(session, vid, s, timeout_s=0.25)]
        if pending and clock.now_s() >= config.wait_timeout_s:
            return (f"{', '.join(pending)} of {vid} not alive within {config.wait_timeout_s:g} s "
                    f"(no liveliness token on {keys.alive(vid, pending[0])})")
        if pending:
            stop.wait(0.05)
    if config.wait_for and not stop.is_set():
        log.info("services up: %s", ", ".join(config.wait_for))
    return ""


def _run_lockstep(wire: _Wire, core: SimCore, config: SimServiceConfig, stop: threading.Event,
                  stats: SimStats) -> EpisodeResult | None:
    out = core.reset()
    while not stop.is_set():
        wire.publish(out, stats)
        if out.result is not None:
            return out.result
        cmd = _await_answer(wire.cmds, out.state.seq, config, stop, stats)
        if cmd is None:
            if stop.is_set():
                return None
            vid = config.sim.vehicle_id
            return core.abort(f"no command from the controller of {vid} answering state {out.state.seq} "
                              f"within {config.cmd_timeout_s:g} s (key {keys.cmd(vid)})")
        stats.on_command(cmd, wire.cmds.last_recv_wall_s)
        _note_status(wire, core, config)
        out = core.step(cmd)
        stats.steps += 1
    return None


def _note_status(wire: _Wire, core: SimCore, config: SimServiceConfig) -> None:
    """Hand the controller's newest status (ours only) to the core's judge."""
    if wire.statuses is None:
        return
    status = None
    while (st := wire.statuses.poll()) is not None:
        if st.vehicle_id == config.sim.vehicle_id:
            status = st
    if status is not None:
        core.note_status(status)


def _await_answer(cmds: Inbox[VelocityCommand], state_seq: int, config: SimServiceConfig, stop: threading.Event,
                  stats: SimStats) -> VelocityCommand | None:
    """The command answering `state_seq`, waiting at most `cmd_timeout_s` wall seconds; None if none came."""
    clock = WallClock()
    while True:
        remaining_s = config.cmd_timeout_s - clock.now_s()
        if remaining_s <= 0:
            return None
        cmd = cmds.recv(remaining_s, stop)
        if cmd is None:
            return None
        if cmd.vehicle_id != config.sim.vehicle_id:
            stats.commands_foreign += 1
            log.warning("command for vehicle %r on the key of %r ignored", cmd.vehicle_id, config.sim.vehicle_id)
            continue
        if cmd.state_seq == state_seq:
            return cmd
        # Older answers (a late duplicate, the controller's hold with state_seq -1) are stale here.
        stats.commands_stale += 1
        log.log(logging.WARNING if cmd.state_seq > state_seq else logging.DEBUG,
                "command %d answers state %d while waiting for %d: dropped", cmd.seq, cmd.state_seq, state_seq)


def _run_realtime(wire: _Wire, core: SimCore, config: SimServiceConfig, stop: threading.Event,
                  stats: SimStats) -> EpisodeResult | None:
    period_s = config.sim.dt_s / config.speed
    clock = WallClock()
    out = core.reset()
    wire.publish(out, stats)
    due_s = clock.now_s() + period_s
    while out.result is None and clock.sleep_until(due_s, stop):
        cmd = _newest_command(wire.cmds, config, stats)
        _note_status(wire, core, config)
        out = core.step(cmd)  # None keeps the last command, which then times out in the vehicle
        stats.steps += 1
        stats.commands_not_fresh = core.commands_dropped
        wire.publish(out, stats)
        due_s += period_s
        behind_s = clock.now_s() - due_s
        if behind_s > _MAX_BEHIND_S:
            stats.overruns += 1
            log.warning("sim %.2f s behind real time: restarting the schedule (sim time now lags the wall)",
                        behind_s)
            due_s = clock.now_s() + period_s
    return out.result


def _newest_command(cmds: Inbox[VelocityCommand], config: SimServiceConfig, stats: SimStats) -> VelocityCommand | None:
    """The newest valid command for our vehicle waiting in the inbox, or None."""
    newest = None
    while (cmd := cmds.poll()) is not None:
        if cmd.vehicle_id != config.sim.vehicle_id:
            stats.commands_foreign += 1
            continue
        newest, newest_recv_wall_s = cmd, cmds.last_recv_wall_s
    if newest is not None:
        stats.on_command(newest, newest_recv_wall_s)
    return newest


# ------------------------------------------------------------------------------------------------ flags


def parse_start(text: str) -> tuple[float, float, float]:
    """'X_M,Y_M[,ALT_M]' in world metres (x east, y north of the world's south-west corner);
    the altitude defaults to that of a generated start."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (2, 3):
        raise ValueError("expected X_M,Y_M or X_M,Y_M,ALT_M")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError("expected numbers X_M,Y_M[,ALT_M]") from None
    if not all(validate.is_number(v) for v in values):
        raise ValueError("values must be finite")
    if len(values) == 2:
        values.append(SimServiceConfig.start_alt_m)
    if values[2] <= 0:
        raise ValueError(f"the altitude must be > 0 m, got {values[2]:g}")
    return values[0], values[1], values[2]


def _render_start(start: tuple[float, float, float]) -> str:
    return ",".join(repr(float(v)) for v in start)


# The one table of the sim's flags: `build_parser`, `config_from_args` and `to_argv` all read it.
CLI = CommandLine(SimServiceConfig, {
    "sim.vehicle_id": Flag("--vehicle-id", "vehicle id in the keys", check=lambda _w, v: keys.check_vehicle_id(v)),
    "world": Flag("--world", "synthetic[:seed=N,size_m=X,gsd_m=Y], dubai (shipped), tiles:<url>,... or a "
                  "world folder", check=non_blank),
    "start_xy_alt_m": Flag("--start", "start in world metres (x east, y north of the south-west corner); "
                           f"altitude default {SimServiceConfig.start_alt_m:g}", parse=parse_start,
                           render=_render_start, metavar="X_M,Y_M[,ALT_M]", group="start"),
    "start_seed": Flag("--start-seed", "seed of the generated start (the first of generate_starts)", group="start"),
    "sim.timing": Flag("--timing", "frame period and perception latency preset", choices=TIMING_NAMES),
    "lockstep": Flag("--lockstep", "advance only when the controller has answered each state (deterministic)",
                     off="--realtime", off_help="step on the wall clock and never wait for commands"),
    "speed": Flag("--speed", "real time: sim seconds per wall second", check=validate.positive),
    "sim.time_limit_s": Flag("--time-limit-s", "sim-time limit of the episode", check=validate.positive),
    "sim.handover_alt_m": Flag("--handover-alt-m", "the episode ends (and is judged) at this altitude",
                               check=validate.non_negative),
    "sim.person_separation_m": Flag("--person-separation-m", "the judge calls a landing unsafe with a person closer "
                                    "than this to the touchdown (0 = rule off)", check=validate.non_negative),
    "sim.vehicle_separation_m": Flag("--vehicle-separation-m", "... or a vehicle closer than this (0 = rule off)",
                                     check=validate.non_negative),
    "sim.seed": Flag("--seed", "seed of the vehicle's disturbances"),
    "sim.vehicle_profile": Flag("--vehicle-profile", "what the vehicle reports and how it flies: ideal (the truth, "
                                "a gimbal), realistic (an optical-flow EKF without GNSS, a body-fixed camera, "
                                "ArduCopter's limits) or harsh", choices=VEHICLE_PROFILE_NAMES),
    "sim.vehicle.cmd_timeout_s": Flag("--cmd-max-age-s", "drop a velocity command whose stamp is older than this "
                                      "on the sim clock, as ArduPilot's GUID_TIMEOUT (the vehicle then brakes to a "
                                      "hover)", check=validate.positive),
    "sim.odometry_rate_hz": Flag("--odometry-rate-hz", "publish the camera's visual odometry (dovesei.shared."
                                 "visual_velocity on views rendered at the true pose) on the odometry key at this "
                                 "rate, e.g. 10 (0 = off)", check=lambda w, v: validate.in_range(w, v, 0.0, 100.0)),
    "sim.odometry_width_px": Flag("--odometry-width-px", "render the odometry views this many pixels wide "
                                  "(default: the camera's width)", check=lambda w, v: validate.in_range(w, v, 32, 8192)),
    "sim.external_nav": Flag("--external-nav", "the simulated autopilot also fuses its camera's visual velocity "
                             "into its velocity estimate (EKF3 on an ExternalNav source; needs --odometry-rate-hz "
                             "and a vehicle profile other than ideal)"),
    "sim.frame_period_s": Flag("--frame-period-s", "override the preset's frame period", check=validate.positive),
    "sim.latency_s": Flag("--latency-s", "override the preset's perception latency", check=validate.non_negative),
    "jpeg_quality": Flag("--jpeg-quality", "send frames JPEG-compressed at quality Q (1-100; default raw)",
                         check=integer_in(1, 100), metavar="Q"),
    "sim.attach_truth": Flag("--no-truth", "do not attach ground-truth labels to frames", negate=True),
    "external_pose": Flag("--external-pose", "render at the vehicle state the controller publishes on the state "
                          "key (a real or SITL autopilot) instead of simulating the flight; the sim then sends no "
                          "states"),
    "sitl_truth": Flag("--sitl-truth", "with --external-pose against ArduPilot SITL: render and judge at the "
                       "simulator's TRUE pose, read from SIM_STATE on this SEPARATE SITL output (udpin:HOST:PORT, "
                       "e.g. SITL's --serial2 udpclient:127.0.0.1:14552; never the controller's link); frames keep "
                       "the estimate's altitude and attitude", check=lambda w, v: parse_truth_url(v, w),
                       metavar="URL"),
    "wait_for": Flag("--wait-for", "comma list of services (segmenter,controller) whose liveliness to wait for "
                     "before starting", choices=WAITABLE, metavar="SERVICES"),
    "wait_timeout_s": Flag("--wait-timeout-s", "give up waiting for --wait-for services (or the first "
                           "external-pose state) after this long", check=validate.positive),
    "odometry_after_result_s": Flag("--odometry-after-result-s", "camera mode with odometry: after the episode's "
                                    "result keep publishing the camera's odometry (no frames) for at most this long, "
                                    "until stopped (an autopilot flying on it needs it until it has landed)",
                                    check=lambda w, v: validate.in_range(w, v, 0.0, 3600.0)),
    "cmd_timeout_s": Flag("--cmd-timeout-s", "lockstep: wall seconds to wait for each command (external pose: "
                          "for a new state) before ending the episode as 'error'", check=validate.positive),
}, prog="dovesei-sim", description=__doc__.splitlines()[0])


build_parser = CLI.build_parser
config_from_args = CLI.from_args
to_argv = CLI.to_argv  # what `dovesei up` passes to a child process; parses back to the same config


def main(argv: Sequence[str] | None = None) -> int:
    config, process, zconf = CLI.start(argv)
    stop = install_stop_handlers()
    stats = SimStats()
    try:
        t0 = time.perf_counter()
        world = load_world(config.world)  # the heavy factory: seconds for a new synthetic world
        log.info("world %s ready in %.1f s", world.name, time.perf_counter() - t0)
        with open_session(zconf) as session:
            result = run(session, config=config, stop=stop, world=world, stats=stats)
    except (WorldError, DoveseiError) as exc:
        log.error("sim stopped: %s", exc)
        return 1
    finally:
        if process.stats_out is not None:
            write_stats(process.stats_out, stats.to_json())
    log.info("sim done: %d steps, %d frames, %d commands used (%d stale, %d rejected payloads)",
             stats.steps, stats.frames_sent, stats.commands_used, stats.commands_stale, stats.commands_rejected)
    if result is None:
        return 0  # stopped by a signal: a clean shutdown, not a failure
    return 1 if result.outcome == "error" else 0


if __name__ == "__main__":
    sys.exit(main())
