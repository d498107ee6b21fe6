"""The controller as a Zenoh service (`dovesei-controller`): the loop around `ControllerCore`.

    heatmap key --Inbox--> ControllerCore.on_heatmap          (lockstep: FIFO, kept by seq;
                                                               real time: newest only)
    vehicle (sim over Zenoh, or MAVLink) --> VehicleState --> ControllerCore.tick
        --> VelocityCommand --> vehicle (the `cmd` key, or MAVLink setpoints)
        --> ControllerStatus --> status key (every tick)
    MAVLink only: VehicleState --> state key (the controller is the one owner of the autopilot link;
        the sim's camera mode and the camera service take the pose from here)
    MAVLink with --gnss-denied external-nav|attitude: odometry key --Inbox (FIFO)--> the adapter's
        on_visual_odometry each tick (to the EKF, or into the attitude loop); the adapter's
        nav_status() goes into every ControllerCore.tick (no descent without a trusted velocity)

Two loops, chosen by `ControllerConfig.lockstep`:

- lockstep: one tick per state message, in order. When the state awaits a frame's heatmap the loop
  waits for it (wall deadline), then decides; past the deadline it decides blind and the
  watchdog, which runs on the data clock, takes care of the rest. Host speed never changes a
  decision.
- real time: a fixed-rate loop on the wall clock (absolute schedule: tick k is due at t0 + k x
  period, so delays never accumulate); each tick uses the newest state and the newest heatmap.

`main` only parses flags, sets up logging and signals, opens the session and calls `run`; `run`
reads no flags or environment, so tests call it directly with a stop event. On stop the vehicle
is told to hold (zero velocity, or the MAVLink adapter's `hold()`) before everything is closed.

Takeoff (MAVLink, only with `takeoff_alt_m`): the adapter waits until the autopilot can arm, arms
and climbs in a thread while the loop publishes states; the policy starts once it is done, and a
failed takeoff ends `run` with the adapter's reason.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import sys
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import zenoh

from dovesei.controller.looker import Looker, SyncLooker, ThreadLooker, zenoh_ask
from dovesei.shared.messages import CropFrame, CropHeatmap
from dovesei.controller.core import HANDOVER_ACTIONS, ControllerConfig, ControllerCore, ControllerInputError, Mode
from dovesei.controller.gnss_denied import (
    EXTERNAL_NAV_MESSAGES,
    GNSS_DENIED_MODES,
    AttitudeGains,
    NavStatus,
    OdometryLimits,
)
from dovesei.controller.mavlink.proto import SpeedLimits, load_signing_key
from dovesei.controller.policies.registry import policy_names
from dovesei.controller.vehicle import Vehicle
from dovesei.shared import keys, validate
from dovesei.shared.cliconfig import CommandLine, Flag, non_blank
from dovesei.shared.clock import WallClock, wall_time_s
from dovesei.shared.codec import encode
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.lifecycle import Inbox, declare_alive, install_stop_handlers, write_stats
from dovesei.shared.mavurl import parse_mavlink_url
from dovesei.shared.messages import (
    ControllerStatus,
    SafetyHeatmap,
    VehicleState,
    VelocityCommand,
    VisualOdometry,
    replace,
)
from dovesei.shared.recording import FlightRecorder
from dovesei.shared.timing import DEFAULT_TIMING, TIMING_NAMES
from dovesei.shared.zconfig import open_session

log = logging.getLogger(__name__)

# Keep this many lateness samples (about 3 h at 20 Hz): enough for any benchmark, bounded forever.
_MAX_LATENESS_SAMPLES = 200_000


class ZenohVehicle:
    """The simulator seen through Zenoh: states from the `state` key, commands to the `cmd` key."""

    # The lockstep sim waits for one command per state, so zero commands keep flowing at hand-over.
    commands_during_handover = True
    is_link_owner = False  # the sim publishes its own states

    def __init__(self, session: zenoh.Session, vehicle_id: str, *, lockstep: bool) -> None:
        # Set when a state arrives; the lockstep loop shares it with the heatmap inbox so that it
        # sleeps until either comes and stamps each heatmap the moment it lands.
        self.wakeup = threading.Event()
        # Lockstep needs every state in order; real time only ever wants the newest one.
        self.states: Inbox[VehicleState] = Inbox(session, keys.state(vehicle_id), VehicleState,
                                                 newest_only=not lockstep, wakeup=self.wakeup)
        try:
            # Lockstep: a dropped command would stall the sim until its timeout, so block instead.
            flow = zenoh.CongestionControl.BLOCK if lockstep else zenoh.CongestionControl.DROP
            self._pub = session.declare_publisher(keys.cmd(vehicle_id), congestion_control=flow)
        except BaseException:
            self.states.close()
            raise
        self._last_cmd: VelocityCommand | None = None

    def connect(self, timeout_s: float) -> None:
        """Nothing to wait for: the sim's states simply start arriving."""

    def poll_state(self) -> VehicleState | None:
        return self.states.poll()

    def recv_state(self, timeout_s: float, stop: threading.Event) -> VehicleState | None:
        return self.states.recv(timeout_s, stop)

    def send(self, cmd: VelocityCommand) -> None:
        self._pub.put(encode(cmd))
        self._last_cmd = cmd  # remembered so `hold` can stamp its zero command consistently

    def hold(self) -> bool:
        """Publish a zero-velocity command; state_seq -1 marks it as no answer to a lockstep tick."""
        if self._last_cmd is None:
            return False  # never commanded anything: nothing to take back
        last = self._last_cmd
        self.send(VelocityCommand(last.vehicle_id, last.seq + 1, last.stamp, (0.0, 0.0, 0.0), 0.0,
                                  state_seq=-1, frame_seq=last.frame_seq, sent_wall_s=wall_time_s()))
        return True

    def handover(self) -> bool:
        """The sim's judge ends the episode at the hand-over altitude: nothing to switch."""
        return True

    def set_landing_target(self, angle_x_rad: float, angle_y_rad: float, distance_m: float) -> None:
        """The sim has no precision landing: the episode ends at the hand-over altitude."""

    def nav_status(self) -> NavStatus | None:
        """The sim publishes its velocity estimate as the state: no estimator health to judge."""
        return None

    def on_visual_odometry(self, odom: VisualOdometry) -> None:
        """The sim never loses GNSS (ControllerConfig refuses --gnss-denied with it)."""

    @property
    def rejected(self) -> int:
        return sum(self.states.rejected.values())

    def counters(self) -> dict[str, Any]:
        """No MAVLink link: nothing to count beyond `rejected`."""
        return {}

    def close(self) -> None:
        self.states.close()
        self._pub.undeclare()


def open_vehicle(session: zenoh.Session, config: ControllerConfig) -> Vehicle:
    """The sim over Zenoh, or a flight controller through the MAVLink adapter (imported lazily)."""
    if config.vehicle_url == "zenoh":
        # Subscribers are declared now so no state published after start-up is missed.
        return ZenohVehicle(session, config.vehicle_id, lockstep=config.lockstep)
    try:
        from dovesei.controller.mavlink.vehicle import MavlinkVehicle  # lazy: only a real vehicle needs it; a broken
        # pymavlink install then fails here with one clear line, never the sim's runs
    except ModuleNotFoundError as exc:
        raise ConfigError(
            f"--vehicle-url {config.vehicle_url!r} needs the MAVLink adapter, which cannot be imported "
            f"(missing module {exc.name!r}); install the package with pymavlink or use --vehicle-url zenoh"
        ) from None
    key_file = config.mavlink_signing_key_file
    limits = SpeedLimits(horizontal_m_s=config.mavlink_max_horizontal_m_s, up_m_s=config.mavlink_max_up_m_s,
                         down_m_s=config.mavlink_max_down_m_s)
    vehicle = MavlinkVehicle(config.vehicle_url, vehicle_id=config.vehicle_id, handover=config.handover_action,
                             alt_source=config.mavlink_alt_source,
                             allow_mode_switch=config.mavlink_allow_mode_switch,
                             yaw_control=config.mavlink_yaw_control, system_id=config.mavlink_system_id,
                             limits=limits, require_home=config.mavlink_require_home,
                             signing_key=load_signing_key(key_file) if key_file else None,
                             signing_timestamp_file=f"{key_file}.timestamp" if key_file else None,
                             gnss_denied=config.gnss_denied, ekf_source_set=config.ekf_source_set,
                             external_nav_message=config.external_nav_message,
                             odometry_limits=OdometryLimits(max_age_s=config.odometry_max_age_s,
                                                            min_quality=config.odometry_min_quality),
                             attitude_gains=AttitudeGains(max_tilt_rad=math.radians(config.attitude_max_tilt_deg),
                                                          climb_limit_up_m_s=limits.up_m_s,
                                                          climb_limit_down_m_s=limits.down_m_s))
    try:
        vehicle.connect(config.vehicle_connect_timeout_s)
    except BaseException:
        vehicle.close()
        raise
    return vehicle


@dataclass
class RunStats:
    """What one `run` did; lateness samples are real-time only (seconds after the schedule)."""

    ticks: int = 0
    commands_sent: int = 0
    heatmaps_received: int = 0
    heatmap_payloads_rejected: int = 0
    state_payloads_rejected: int = 0
    states_refused: int = 0
    heatmaps_missed: int = 0  # lockstep: awaited heatmaps that did not come before the deadline
    missed_ticks: int = 0  # real time: whole periods skipped after an overrun
    send_errors: int = 0
    states_published: int = 0  # MAVLink: vehicle states republished on the state key
    geofence_clipped: int = 0  # commands the geofence capped (see core.py)
    odometry_received: int = 0  # MAVLink --gnss-denied: visual velocities handed to the adapter
    odometry_payloads_rejected: int = 0
    core_refusals: dict[str, int] = field(default_factory=dict)
    vehicle_link: dict[str, Any] = field(default_factory=dict)  # the MAVLink adapter's counters
    wake_lateness_s: deque[float] = field(default_factory=lambda: deque(maxlen=_MAX_LATENESS_SAMPLES))
    publish_lateness_s: deque[float] = field(default_factory=lambda: deque(maxlen=_MAX_LATENESS_SAMPLES))


class _Loop:
    """The pieces both loops share: inboxes, publishers, the core and the per-tick plumbing."""

    def __init__(self, session: zenoh.Session, config: ControllerConfig, stop: threading.Event,
                 vehicle: Vehicle, core: ControllerCore, recorder: FlightRecorder | None = None) -> None:
        self.config, self.stop, self.vehicle, self.core = config, stop, vehicle, core
        self.stats = RunStats()
        self.recorder = recorder
        # Heatmaps received, by seq, until the core adopts one (the status names it): only adopted
        # ones are recorded, so a replay sees what this controller decided on.
        self._received: dict[int, SafetyHeatmap] = {}
        self._recorded_state: VehicleState | None = None
        self._recorded_frame_seq = -1
        self.heatmaps: Inbox[SafetyHeatmap] = Inbox(session, keys.heatmap(config.vehicle_id), SafetyHeatmap,
                                                    newest_only=not config.lockstep,
                                                    wakeup=vehicle.wakeup)
        self._state_pub: Any = None
        # The camera's velocity, every sample in order (each one is a measurement for the EKF).
        self.odometry: Inbox[VisualOdometry] | None = None
        try:
            if config.gnss_denied != "off":
                self.odometry = Inbox(session, keys.odometry(config.vehicle_id), VisualOdometry, newest_only=False)
            self._status_pub = session.declare_publisher(keys.status(config.vehicle_id))
            if vehicle.is_link_owner:
                # Newest wins for a pose: a congested link drops old states rather than queue them.
                self._state_pub = session.declare_publisher(keys.state(config.vehicle_id),
                                                            congestion_control=zenoh.CongestionControl.DROP)
        except BaseException:
            self.heatmaps.close()
            if self.odometry is not None:
                self.odometry.close()
            if self._state_pub is not None:
                self._state_pub.undeclare()
            raise
        self._mode: Mode | None = None

    def close(self) -> None:
        self.heatmaps.close()
        if self.odometry is not None:
            self.odometry.close()
        self._status_pub.undeclare()
        if self._state_pub is not None:
            self._state_pub.undeclare()

    def publish_state(self, state: VehicleState) -> None:
        """MAVLink: put the autopilot's state on the state key (the one owner of the link shares it)."""
        if self._state_pub is not None:
            self._state_pub.put(encode(replace(state, sent_wall_s=wall_time_s())))
            self.stats.states_published += 1
            self._record_state(state)

    def _record_state(self, state: VehicleState) -> None:
        # The real-time loop re-uses the newest state over several ticks: each is recorded once.
        if self.recorder is not None and state is not self._recorded_state:
            self.recorder.write(state)
            self._recorded_state = state

    def on_heatmap(self, hm: SafetyHeatmap) -> None:
        """Hand one received heatmap to the core (kept for the recording until it is adopted)."""
        self.stats.heatmaps_received += 1
        # Arrival time on the wall clock: only for the transport-latency figure, never decisions.
        accepted = self.core.on_heatmap(hm, self.heatmaps.last_recv_wall_s)
        if self.recorder is not None and accepted:  # a refused one (another vehicle's) is never adopted
            self._received[hm.seq] = hm
            while len(self._received) > self.config.heatmap_buffer_len:
                del self._received[min(self._received)]

    def _record_tick(self, state: VehicleState, cmd: VelocityCommand | None, status: ControllerStatus) -> None:
        if self.recorder is None:
            return
        self._record_state(state)
        if status.frame_seq >= 0 and status.frame_seq != self._recorded_frame_seq:
            adopted = self._received.pop(status.frame_seq, None)
            if adopted is not None:
                self.recorder.write(adopted)
            self._recorded_frame_seq = status.frame_seq
            for seq in [s for s in self._received if s < status.frame_seq]:
                del self._received[seq]  # older than the adopted one: never adopted now
        if cmd is not None:
            self.recorder.write(cmd)
        self.recorder.write(status)

    def drain_odometry(self) -> None:
        """Hand every waiting visual velocity to the adapter, oldest first (never blocks)."""
        if self.odometry is None:
            return
        while (odom := self.odometry.poll()) is not None:
            self.stats.odometry_received += 1
            self.vehicle.on_visual_odometry(odom)

    def drain_heatmaps(self) -> None:
        """Hand every waiting heatmap to the core (never blocks)."""
        while (hm := self.heatmaps.poll()) is not None:
            self.on_heatmap(hm)

    def step(self, state: VehicleState, wall_s: float | None) -> bool:
        """Tick the core on `state`, send the command, publish the status; False if refused."""
        try:
            cmd, status = self.core.tick(state, wall_s, self.vehicle.nav_status())
        except ControllerInputError as exc:
            self.stats.states_refused += 1
            log.warning("vehicle state refused: %s", exc)
            return False
        self.stats.ticks += 1
        mode = self.core.mode
        if mode is Mode.HANDOVER and self._mode is not Mode.HANDOVER:
            log.info("hand-over at %.1f m: telling the vehicle (action %s)", state.alt_agl_m,
                     self.config.handover_action)
            try:
                self.vehicle.handover()
            except DoveseiError as exc:
                log.warning("vehicle refused the hand-over action: %s", exc)
        self._mode = mode
        if mode is Mode.HANDOVER and self.config.handover_action == "precland":
            self._stream_landing_target(state)
        # A MAVLink vehicle stops receiving setpoints at hand-over: its adapter does the action.
        sent: VelocityCommand | None = None
        if mode is not Mode.HANDOVER or self.vehicle.commands_during_handover:
            try:
                out = replace(cmd, sent_wall_s=wall_time_s())
                self.vehicle.send(out)
                sent = out
                self.stats.commands_sent += 1
            except DoveseiError as exc:
                # The adapter refused (wrong flight mode, link lost...): say so, keep the loop alive.
                self.stats.send_errors += 1
                if self.stats.send_errors == 1 or self.stats.send_errors % 100 == 0:
                    log.warning("vehicle refused the command (%d so far): %s", self.stats.send_errors, exc)
        # Status goes out every tick, even at hand-over: operators see why nothing is commanded.
        self._status_pub.put(encode(status))
        self._record_tick(state, sent, status)
        return True

    def _stream_landing_target(self, state: VehicleState) -> None:
        """Precision landing: the spot as LANDING_TARGET, refreshed every tick until the vehicle has
        landed (the adapter streams it at 10 Hz while the autopilot is armed in LAND/PRECLAND)."""
        target = self.core.landing_target(state)
        if target is None:
            return
        try:
            self.vehicle.set_landing_target(*target)
        except DoveseiError as exc:
            log.debug("landing target not set: %s", exc)

    def finish(self) -> RunStats:
        stats = self.stats
        stats.heatmap_payloads_rejected = sum(self.heatmaps.rejected.values())
        if self.odometry is not None:
            stats.odometry_payloads_rejected = sum(self.odometry.rejected.values())
        stats.state_payloads_rejected = self.vehicle.rejected
        stats.core_refusals = dict(self.core.rejected)
        stats.geofence_clipped = self.core.geofence.clipped if self.core.geofence is not None else 0
        stats.vehicle_link = self.vehicle.counters()
        return stats


def _run_lockstep(loop: _Loop) -> None:
    """One tick per state, in order; wait (bounded) for the heatmap each state awaits."""
    cfg, core, vehicle = loop.config, loop.core, loop.vehicle
    assert isinstance(vehicle, ZenohVehicle)  # ControllerConfig refuses lockstep with MAVLink
    segmenter_late = False
    while not loop.stop.is_set():
        vehicle.wakeup.clear()  # before polling: anything arriving after this sets it again
        # Heatmaps are taken as they land (their arrival time is the transport figure), not
        # when the next state happens to come.
        loop.drain_heatmaps()
        state = vehicle.poll_state()
        if state is None:
            # Bounded: a stop request is noticed within 0.1 s even when the sim is idle.
            vehicle.wakeup.wait(0.1)
            continue
        awaited = state.await_frame_seq
        if awaited >= 0 and not core.has_heatmap(awaited):
            # After one miss the segmenter is presumed down: shorter waits keep the sim moving.
            wait_s = cfg.lockstep_heatmap_retry_s if segmenter_late else cfg.lockstep_heatmap_wait_s
            clock = WallClock()
            while not core.has_heatmap(awaited) and not loop.stop.is_set():
                remaining_s = wait_s - clock.now_s()
                if remaining_s <= 0:
                    break
                hm = loop.heatmaps.recv(remaining_s, loop.stop)
                if hm is not None:
                    loop.on_heatmap(hm)
            if not core.has_heatmap(awaited):
                if loop.stop.is_set():
                    break
                loop.stats.heatmaps_missed += 1
                if not segmenter_late:
                    log.warning("heatmap %d not received within %.2f s: deciding without it "
                                "(the watchdog applies); shorter waits until heatmaps return", awaited, wait_s)
                segmenter_late = True
            elif segmenter_late:
                log.info("heatmaps arriving again (frame %d)", awaited)
                segmenter_late = False
        loop.step(state, None)


class _Takeoff(threading.Thread):
    """The adapter's blocking arm-and-climb in its own thread, so the loop keeps publishing states."""

    def __init__(self, vehicle: Any, alt_m: float, ready_timeout_s: float) -> None:
        super().__init__(name="takeoff", daemon=True)
        self._vehicle, self._alt_m, self._ready_timeout_s = vehicle, alt_m, ready_timeout_s
        self.error: DoveseiError | None = None

    def run(self) -> None:
        try:
            log.warning("takeoff requested: arming %s and climbing to %.1f m", self._vehicle.url, self._alt_m)
            self._vehicle.arm_and_takeoff(self._alt_m, ready_timeout_s=self._ready_timeout_s)
        except DoveseiError as exc:
            self.error = exc


def _run_realtime(loop: _Loop, takeoff: _Takeoff | None = None) -> None:
    """Fixed rate on the wall clock: tick k is due at t0 + k x period, whatever happened before.

    With a takeoff in progress the loop only republishes states until it is done."""
    period_s = loop.config.period_s
    clock = WallClock()
    newest: VehicleState | None = None
    waiting_logged = False
    due_s = clock.now_s() + period_s
    while clock.sleep_until(due_s, loop.stop):
        woke_s = clock.now_s()
        # One poll: the state inbox keeps only the newest, and an adapter may return its latest.
        state = loop.vehicle.poll_state()
        if state is not None:
            newest = state
            loop.publish_state(state)
        loop.drain_odometry()
        loop.drain_heatmaps()
        if takeoff is not None and takeoff.is_alive():
            pass  # the adapter owns the vehicle until the climb is done; states still go out
        elif newest is not None:
            # The newest state is re-used while no newer one comes; the core notices it aging.
            loop.step(newest, woke_s)
            loop.stats.wake_lateness_s.append(woke_s - due_s)
            loop.stats.publish_lateness_s.append(clock.now_s() - due_s)
        elif not waiting_logged:
            log.info("waiting for the first vehicle state of %s", loop.config.vehicle_id)
            waiting_logged = True
        if takeoff is not None and takeoff.error is not None:
            raise takeoff.error  # the vehicle never reached its start: nothing to fly
        due_s += period_s
        behind_s = clock.now_s() - due_s
        if behind_s > 0:
            # Overran a whole period: skip the missed ticks instead of bursting to catch up.
            missed = math.floor(behind_s / period_s) + 1
            due_s += missed * period_s
            loop.stats.missed_ticks += missed
            log.warning("controller loop overran by %.1f ms: skipped %d tick(s)", behind_s * 1e3, missed)


def run(session: zenoh.Session, *, config: ControllerConfig, stop: threading.Event,
        vehicle: Vehicle | None = None, core: ControllerCore | None = None) -> RunStats:
    """Serve until `stop` is set; the vehicle is told to hold before returning.

    `vehicle` and `core` default to what `config` names (tests hand in doubles). With
    `config.record_path` the flight is recorded there (closed whatever ends the run).
    """
    core = core if core is not None else ControllerCore(config, looker=make_looker(session, config))
    with open_recorder(config) as recorder:
        return _serve(session, config, stop, vehicle, core, recorder)


def make_looker(session: zenoh.Session, config: ControllerConfig) -> Looker | None:
    """The close looks over Zenoh (crop key, then segment key): answered before the tick's command in
    lockstep (the sim waits meanwhile), on a worker thread in real time (the loop keeps commanding)."""
    if not config.close_look:
        return None
    ask = zenoh_ask(session)
    # Each look, crop and scores, on the look key (operators, `up`'s video); a put is thread-safe.
    key = keys.look(config.vehicle_id)

    def seen(crop: CropFrame, heatmap: CropHeatmap) -> None:
        session.put(key, encode(crop, jpeg_quality=90))
        session.put(key, encode(heatmap))

    return SyncLooker(ask, seen) if config.lockstep else ThreadLooker(ask, seen)


def open_recorder(config: ControllerConfig) -> FlightRecorder | contextlib.nullcontext[None]:
    """The MCAP recorder `config.record_path` asks for (a do-nothing context without one)."""
    if config.record_path is None:
        return contextlib.nullcontext()
    # What `dovesei replay` needs to rebuild this controller (the same "run" record `up` writes).
    run_meta = {"policy": config.policy, "timing": config.timing, "lockstep": config.lockstep,
                "vehicle_id": config.vehicle_id, "vehicle_url": config.vehicle_url}
    try:
        return FlightRecorder(config.record_path, metadata={"run": run_meta})
    except OSError as exc:
        raise ConfigError(f"--record {config.record_path}: cannot write the recording "
                          f"({exc.strerror or exc})") from None


def _serve(session: zenoh.Session, config: ControllerConfig, stop: threading.Event, vehicle: Vehicle | None,
           core: ControllerCore, recorder: FlightRecorder | None) -> RunStats:
    own_vehicle = vehicle is None
    vehicle = open_vehicle(session, config) if vehicle is None else vehicle
    loop: _Loop | None = None
    token = None
    try:
        loop = _Loop(session, config, stop, vehicle, core, recorder)
        # Declared last: whoever sees the token knows the subscribers are already in place.
        token = declare_alive(session, config.vehicle_id, "controller")
        log.info("controller %s up: policy %s (%s timing), %s, vehicle %s, keys %s -> %s",
                 config.vehicle_id, config.policy, config.timing,
                 "lockstep" if config.lockstep else f"real time at {config.rate_hz:g} Hz", config.vehicle_url,
                 keys.heatmap(config.vehicle_id), keys.cmd(config.vehicle_id))
        if config.lockstep:
            _run_lockstep(loop)
        else:
            takeoff = None
            if config.takeoff_alt_m is not None:
                takeoff = _Takeoff(vehicle, config.takeoff_alt_m, config.takeoff_ready_timeout_s)
                takeoff.start()
            _run_realtime(loop, takeoff)
        return loop.finish()
    finally:
        # Whatever ended the loop (stop, error), the vehicle must not keep the last velocity.
        try:
            vehicle.hold()
            log.info("controller %s stopping: vehicle told to hold", config.vehicle_id)
        finally:
            if token is not None:
                token.undeclare()
            if loop is not None:
                loop.close()
            if own_vehicle:
                vehicle.close()


def _check_vehicle_url(what: str, url: str) -> None:
    """The form only (the one parser `dovesei up` uses too); whether a device opens is seen at connect."""
    if url != "zenoh":
        parse_mavlink_url(url, what)


def _derived_defaults(given: Mapping[str, Any]) -> dict[str, Any]:
    """Defaults that follow the vehicle: the sim runs in lockstep (the sim's default too); a real
    vehicle runs in real time on true seconds."""
    real_vehicle = given.get("vehicle_url", ControllerConfig.vehicle_url) != "zenoh"
    return {"lockstep": not real_vehicle, "timing": "real" if real_vehicle else DEFAULT_TIMING}


# The one table of the controller's flags: `build_parser`, `config_from_args` and `to_argv` read it.
CLI = CommandLine(ControllerConfig, {
    "vehicle_url": Flag("--vehicle-url", "'zenoh' (the simulator) or a pymavlink URL: udpin:HOST:PORT, "
                        "udpout:HOST:PORT, tcp:HOST:PORT or a serial DEVICE,BAUD such as /dev/ttyAMA0,921600",
                        check=_check_vehicle_url, metavar="URL"),
    "vehicle_id": Flag("--vehicle-id", "vehicle id in the keys", check=lambda _w, v: keys.check_vehicle_id(v)),
    "policy": Flag("--policy", "landing policy", choices=policy_names()),
    "policy_config_file": Flag("--policy-config", "TOML file of the policy's constants (default: the timing "
                               "preset's; `dovesei policy-config --defaults POLICY` prints them)", metavar="FILE"),
    "timing": Flag("--timing", f"policy timing preset ({DEFAULT_TIMING} with the sim, real with a MAVLink vehicle)",
                   choices=TIMING_NAMES),
    "lockstep": Flag("--lockstep", "one tick per sim state, waiting for awaited heatmaps (default with the sim)",
                     off="--realtime", off_help="own fixed-rate loop on the wall clock (the only mode with MAVLink)"),
    "rate_hz": Flag("--rate-hz", "real-time loop rate", check=validate.positive),
    "close_look": Flag("--close-look", "clearance: look at the spot at full resolution (crop key + segmenter) "
                       "before committing below ~40 m, and keep looking down to the hand-over (issue 24)"),
    "heatmap_hold_after_s": Flag("--heatmap-hold-after-s", "hold position when the heatmap is older than this "
                                 "(data clock)", check=validate.positive),
    "heatmap_climb_after_s": Flag("--heatmap-climb-after-s", "climb to the search altitude when the heatmap is "
                                  "older than this", check=validate.positive),
    "state_stale_after_s": Flag("--state-stale-after-s", "zero velocity when the vehicle state stops updating for "
                                "this long (real time)", check=validate.positive),
    "climb_speed_m_s": Flag("--climb-speed-m-s", "largest climb speed of the climb watchdog", check=validate.positive),
    "search_alt_m": Flag("--search-alt-m", "altitude of the climb watchdog (default: the altitude first seen)",
                         check=validate.positive),
    "handover_alt_m": Flag("--handover-alt-m", "stop commanding at/below this altitude", check=validate.positive),
    "handover_action": Flag("--handover-action", "MAVLink action at the hand-over altitude", choices=HANDOVER_ACTIONS),
    # The adapter validates these too; literal choices keep --help free of a pymavlink import.
    "mavlink_alt_source": Flag("--alt-source", "MAVLink altitude source", choices=("local", "rangefinder")),
    "mavlink_yaw_control": Flag("--yaw-control", "MAVLink: 'rate' holds the heading with a closed-loop yaw rate "
                                "(body-frame velocity, mask 0x05C7); 'autopilot' has the autopilot hold it (velocity "
                                "in LOCAL_NED + the held heading as a yaw angle, mask 0x09C7)",
                                choices=("rate", "autopilot")),
    "mavlink_allow_mode_switch": Flag("--allow-mode-switch", "MAVLink: switch the autopilot to GUIDED/OFFBOARD when "
                                      "it is not (default: refuse to steer)"),
    "lockstep_heatmap_wait_s": Flag("--heatmap-wait-s", "lockstep: wall deadline for an awaited heatmap",
                                    check=validate.positive),
    "policy_dt_max_s": Flag("--policy-dt-max-s", "the policy's clock advances at most this much per heatmap",
                            check=validate.positive),
    "future_tolerance_s": Flag("--future-tolerance-s", "real time: refuse stamps leading the controller's clock by "
                               "more than this", check=validate.positive),
    "mavlink_system_id": Flag("--autopilot-system-id", "MAVLink: fly only the autopilot with this system id (default: "
                              "the first heard; pin it so a spoofer heard first is never followed)",
                              check=lambda w, v: validate.in_range(w, v, 1, 255)),
    "mavlink_max_horizontal_m_s": Flag("--max-horizontal-m-s", "MAVLink: largest horizontal setpoint (ArduCopter "
                                       "WPNAV_SPEED)", check=validate.positive),
    "mavlink_max_up_m_s": Flag("--max-up-m-s", "MAVLink: largest climb setpoint (WPNAV_SPEED_UP)",
                               check=validate.positive),
    "mavlink_max_down_m_s": Flag("--max-down-m-s", "MAVLink: largest descent setpoint (WPNAV_SPEED_DN)",
                                 check=validate.positive),
    "mavlink_signing_key_file": Flag("--signing-key", "MAVLink 2 signing key file (32 raw bytes, 64 hex digits or a "
                                     "passphrase line, SHA-256 as MAVProxy); the timestamp is kept in FILE.timestamp",
                                     check=non_blank, metavar="FILE"),
    "mavlink_require_home": Flag("--no-require-home", "takeoff: do not wait for the autopilot's home position",
                                 negate=True),
    "takeoff_alt_m": Flag("--takeoff-alt-m", "MAVLink: wait until the autopilot can arm, arm and climb to this "
                          "altitude before flying (never arms without it)",
                          check=lambda w, v: validate.in_range(w, v, 1.0, 500.0)),
    "takeoff_ready_timeout_s": Flag("--takeoff-ready-timeout-s", "takeoff: give up when the autopilot cannot arm "
                                    "within this, naming its pre-arm reasons", check=validate.positive),
    "camera_hfov_deg": Flag("--camera-hfov-deg", "the camera's horizontal field of view as published (after any "
                            "crop): heatmaps more than 25 %% off it are refused", check=validate.positive),
    "geofence_radius_m": Flag("--geofence-radius-m", "largest distance from the start, dead-reckoned from the "
                              "velocity estimate, that any policy may fly (default: off with the sim, "
                              "400 m with a MAVLink vehicle; 0: off)",
                              check=lambda w, v: validate.in_range(w, v, 0.0, 100_000.0)),
    "gnss_denied": Flag("--gnss-denied", "MAVLink without GNSS: 'external-nav' streams the camera's velocity to the "
                        "EKF (VISION_SPEED_ESTIMATE) and switches it to --ekf-source-set on a loss; 'attitude' "
                        "switches ArduPilot to GUIDED_NOGPS and flies attitude targets on it; 'off' reports the "
                        "loss and holds (docs/GNSS-DENIED.md gives the autopilot parameters)",
                        choices=GNSS_DENIED_MODES),
    "ekf_source_set": Flag("--ekf-source-set", "external-nav: the EK3 source set (1-3) whose VELXY is ExternalNav",
                           check=lambda w, v: validate.in_range(w, v, 1, 3)),
    "external_nav_message": Flag("--external-nav-message", "external-nav on ArduPilot: 'speed' sends "
                                 "VISION_SPEED_ESTIMATE, 'delta' VISION_POSITION_DELTA (body odometry: EKF3 keeps a "
                                 "relative position for GUIDED with it), 'both' the two", choices=EXTERNAL_NAV_MESSAGES),
    "odometry_min_quality": Flag("--odometry-min-quality", "visual velocity below this quality (0-1) is not flown on",
                                 check=lambda w, v: validate.in_range(w, v, 0.0, 1.0)),
    "odometry_max_age_s": Flag("--odometry-max-age-s", "visual velocity older than this at arrival is stale",
                               check=validate.positive),
    "attitude_max_tilt_deg": Flag("--max-tilt-deg", "attitude mode: largest roll/pitch demanded",
                                  check=lambda w, v: validate.in_range(w, v, 1.0, 35.0)),
    "nav_retreat_speed_m_s": Flag("--nav-retreat-speed-m-s", "a velocity lost in flight (over calm water): fly "
                                  "towards ground the camera sees, on the way it was last seen, or back over "
                                  "the ground it measured, at this speed, no descent",
                                  check=lambda w, v: validate.in_range(w, v, 0.1, 20.0)),
    "nav_retreat_max_s": Flag("--nav-retreat-max-s", "... the last two for at most this long each, then hold "
                              "(0: hold at once)",
                              check=lambda w, v: validate.in_range(w, v, 0.0, 600.0)),
    "record_path": Flag("--record", "write an MCAP flight recording (states, adopted heatmaps, commands, status) "
                        "to PATH", check=non_blank, metavar="PATH"),
}, derive=_derived_defaults, prog="dovesei-controller", description=__doc__.splitlines()[0])


build_parser = CLI.build_parser
config_from_args = CLI.from_args
to_argv = CLI.to_argv  # what `dovesei up` passes to a child process; parses back to the same config


def main(argv: list[str] | None = None) -> int:
    config, process, zconf = CLI.start(argv)  # a bad flag exits 2 with the usage line
    stop = install_stop_handlers()
    # A waking loop thread gets the GIL within 1 ms instead of the default 5 ms when another
    # Python thread (e.g. a MAVLink reader) is busy: that default alone would break the 5 ms jitter.
    sys.setswitchinterval(0.001)
    try:
        with open_session(zconf) as session:
            stats = run(session, config=config, stop=stop)
    except DoveseiError as exc:
        log.error("controller stopped: %s", exc)
        return 1
    log.info("controller done: %d ticks, %d commands, %d heatmaps (%d payloads rejected)",
             stats.ticks, stats.commands_sent, stats.heatmaps_received, stats.heatmap_payloads_rejected)
    steered, clamped = stats.vehicle_link.get("commands_steered"), stats.vehicle_link.get("commands_clamped")
    if steered:
        log.info("%d of %d commands (%.0f %%) asked for more than the vehicle's speed limits and were clamped",
                 clamped, steered, 100.0 * clamped / steered)
    if process.stats_out is not None:
        write_stats(process.stats_out, dataclasses.asdict(stats))
    return 0


if __name__ == "__main__":
    sys.exit(main())
