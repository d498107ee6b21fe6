"""MAVLink vehicle adapter: a real autopilot (ArduPilot or PX4) behind the controller's interface.

Data flow (one I/O thread owns the link; callers only read snapshots and hand commands over):

    autopilot --HEARTBEAT, LOCAL_POSITION_NED, ATTITUDE, DISTANCE_SENSOR--> I/O thread
        -> every sample validated (finite, plausible ranges; bad ones counted, logged rate-limited,
           dropped) -> VehicleState (stamp on the 'vehicle' clock from time_boot_ms) -> poll_state()
    autopilot --SYS_STATUS, EKF_STATUS_REPORT, HOME_POSITION, STATUSTEXT--> ArmReadiness (takeoff),
        every STATUSTEXT logged at INFO with its severity
    send(VelocityCommand) -> checks (armed, GUIDED/OFFBOARD, link alive) -> clamp to SpeedLimits,
        heading hold -> SET_POSITION_TARGET_LOCAL_NED; the I/O thread repeats the newest command at
        `setpoint_rate_hz` (PX4 leaves OFFBOARD when the stream stops; ArduPilot stops a velocity
        after GUID_TIMEOUT, 3 s)
    I/O thread -> HEARTBEAT at 1 Hz as an onboard controller (MAV_TYPE_ONBOARD_CONTROLLER,
        MAV_AUTOPILOT_INVALID); LANDING_TARGET at 10 Hz during a precision-landing hand-over

Without GNSS (`gnss_denied`, the judgement and the attitude loop in `gnss_denied.py`):

    GPS_RAW_INT, EKF_STATUS_REPORT (ArduPilot), ESTIMATOR_STATUS (PX4), LOCAL_POSITION_NED arrivals
        -> NavJudge -> nav_status() (the controller's core stops descending when nothing is trusted);
           a loss or recovery logged once, counted in counters()
    on_visual_odometry(VisualOdometry) -> OdometryGate; "external-nav": each good sample out at once
        as VISION_SPEED_ESTIMATE (ArduPilot, NED via ATTITUDE, variance on the diagonal) or ODOMETRY
        (PX4, body-frame velocity), and on GNSS loss MAV_CMD_SET_EKF_SOURCE_SET(ekf_source_set)
        until acknowledged; while an ArduPilot is disarmed (on the ground, where the camera cannot
        measure) "external-nav" streams a zero velocity at 10 Hz instead, so VISO_TYPE's pre-arm check
        ("PreArm: VisOdom: not healthy") lets it arm; "attitude": on GNSS loss ArduPilot is
        switched GUIDED -> GUIDED_NOGPS and every command streams as SET_ATTITUDE_TARGET from the
        AttitudeLoop (PX4 stays in OFFBOARD)
    LOCAL_POSITION_NED stopped (ArduPilot's EKF without a position stops it): the state is then
        published on each ATTITUDE, altitude and climb rate from GLOBAL_POSITION_INT (relative_alt is
        the barometric height above home), horizontal velocity from the good visual velocity or zero

Size: one class, one lock domain (the I/O thread and the caller share every field below under
`_lock`); the pure parts live beside it (`proto` numbers and checks, `readiness`,
`takeoff`, `signing`), and splitting the rest would scatter the locking.

Why one thread and no callbacks into the caller: pymavlink's parser is not thread-safe, and the
controller's loop must never block on the radio. Sends from the caller's thread share a transmit
lock with the I/O thread (pymavlink's sequence counter and socket writes are not thread-safe).

Conventions (ArduPilot "Copter Commands in Guided Mode", PX4 offboard docs; numbers in
`proto`): body-frame velocities in MAV_FRAME_BODY_OFFSET_NED (ArduPilot) or
MAV_FRAME_BODY_NED (PX4), both heading-level frames; type mask 0x05C7 (velocity + yaw rate).
Heading: with `yaw_control="rate"` the yaw rate sent is the policy's plus a proportional
correction towards the heading held since steering began (read from ATTITUDE), so the camera does
not rotate under the map when the autopilot's heading drifts; "autopilot" sends the velocity in
MAV_FRAME_LOCAL_NED (rotated by the heading the command was meant in) with that held heading as a
yaw angle, for the autopilot's own heading controller to hold (velocity alone let ArduCopter turn
the nose by WP_YAW_BEHAVIOR, and the body-frame policy ran out of the world).

Trust: the autopilot is the first ArduPilot/PX4 heartbeat heard, or only `system_id` when pinned
(a spoofer heard first is never locked onto); another autopilot id later is refused, counted and
reported. With a signing key every frame we send is signed and every unsigned, wrong-key or
replayed frame is rejected and counted (the timestamp is persisted). Any exception in the I/O
thread is a permanent link loss: steering stops, `send()` raises, `lost_reason` says why.

Safety: nothing is sent that steers unless the autopilot is armed, in GUIDED (ArduPilot) or
OFFBOARD (PX4) and its heartbeat is fresh. The adapter never arms or takes off unless
`arm_and_takeoff` is called (only with the controller's `--takeoff-alt-m`). A mode switch into
GUIDED/OFFBOARD happens only with `allow_mode_switch=True`, and never again once the vehicle left
that mode after we steered it (a pilot who takes over keeps control). A command not refreshed
within `command_timeout_s` is replaced by zero velocity: a dead controller never leaves a non-zero
velocity repeating.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dovesei.controller.continuity import (
    ALTITUDE_NOISE_M, MAX_VERTICAL_SPEED_M_S, STEP_CONFIRM_SAMPLES, AltitudeContinuity,
)
from dovesei.controller.mavlink.proto import (
    ALT_SOURCES,
    AUTOPILOT_KINDS,
    HANDOVERS,
    LANDING_TARGET_TYPE_VISION_OTHER,
    MAV_AUTOPILOT_INVALID,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_COMP_ID_ONBOARD_COMPUTER,
    MAV_FRAME_BODY_FRD,
    MAV_FRAME_LOCAL_NED,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_IN_PROGRESS,
    MAV_SENSOR_ROTATION_PITCH_270,
    MAV_STATE_ACTIVE,
    MAV_TYPE_GCS,
    MAV_TYPE_ONBOARD_CONTROLLER,
    MSG_ID_ATTITUDE,
    ATTITUDE_TYPE_MASK_ANGLES_THRUST,
    MAV_CMD_SET_EKF_SOURCE_SET,
    MAV_ESTIMATOR_TYPE_VISION,
    MAV_FRAME_LOCAL_FRD,
    MSG_ID_DISTANCE_SENSOR,
    MSG_ID_EKF_STATUS_REPORT,
    MSG_ID_ESTIMATOR_STATUS,
    MSG_ID_GLOBAL_POSITION_INT,
    MSG_ID_GPS_RAW_INT,
    MSG_ID_LOCAL_POSITION_NED,
    MSG_ID_SYS_STATUS,
    STEER_FRAME,
    STEER_MODE,
    TYPE_MASK_VELOCITY_YAW,
    TYPE_MASK_VELOCITY_YAW_RATE,
    YAW_CONTROLS,
    MavlinkError,
    NotSteerableError,
    SpeedLimits,
    VehicleConnectError,
    check_attitude,
    check_distance_m,
    check_local_position,
    ALT_RANGE_M,
    SPEED_RANGE_M_S,
    check_url,
    clamp_setpoint,
    encode_mode,
    frd_to_ned,
    mode_name,
    ned_to_frd,
    open_link,
)
from dovesei.controller.mavlink import takeoff as mavlink_takeoff
from dovesei.shared.frames import to_ne
from dovesei.controller.gnss_denied import (
    EXTERNAL_NAV_MESSAGES,
    GNSS_DENIED_MODES,
    AttitudeGains,
    AttitudeLoop,
    NavJudge,
    NavStatus,
    OdometryGate,
    OdometryLimits,
    SOURCE_AUTOPILOT,
    SOURCE_NONE,
    SOURCE_VISUAL,
    body_odom_confidence,
    speed_message_takes,
    vision_speed_covariance,
)
from dovesei.controller.mavlink.readiness import ArmReadiness
from dovesei.controller.mavlink.signing import LinkSigning
from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.shared.keys import check_vehicle_id
from dovesei.shared.lifecycle import RateLimitedLog
from dovesei.shared.messages import Stamp, VehicleState, VelocityCommand, VisualOdometry

log = logging.getLogger(__name__)

_ATTITUDE_FRESH_S = 1.0  # heading hold only corrects from an attitude younger than this
# 10 Hz: ArduPilot's precland estimator initialises only on an update at least every 0.5 s for 2 s
# and drops a target not updated for 2 s (AC_PrecLand EKF_INIT_*, LANDING_TARGET_TIMEOUT_MS).
_LANDING_TARGET_PERIOD_S = 0.1
_LANDING_TARGET_FRESH_S = 1.0  # a spot older than this is no longer streamed
_NAV_PERIOD_S = 0.2  # the navigation judgement (and its loss / recovery log) at 5 Hz
_GPS_RAW_INTERVAL_US = 200_000.0  # GPS_RAW_INT at 5 Hz: a lost fix is noticed within a fifth of a second
_GLOBAL_FRESH_S = 1.0  # the fallback state's altitude (GLOBAL_POSITION_INT) is used only this fresh
_LOCAL_FALLBACK_S = 0.5  # LOCAL_POSITION_NED silent this long: states come from ATTITUDE (no stale-state gap)
_LOCAL_NEVER_S = 3.0  # ... or never heard this long after the streams were asked for
_SOURCE_SET_RETRY_S, _SOURCE_SET_TRIES = 1.0, 10
# "external-nav" on a disarmed ArduPilot: a zero velocity at 10 Hz. AP_VisualOdom is healthy only
# while a vision message came within 300 ms (AP_VISUALODOM_TIMEOUT_MS), and with VISO_TYPE set
# ArduCopter refuses to arm otherwise ("PreArm: VisOdom: not healthy", AP_Arming::visodom_checks);
# the camera cannot measure on the ground (its odometry needs >= 1 m), but a disarmed multirotor
# stands still on it.
_GROUND_VISION_PERIOD_S = 0.1
_GROUND_VISION_VAR_M2_S2 = 0.01  # (0.1 m/s)^2: standing still is known well; VISO_VEL_M_NSE floors it anyway


@dataclass(frozen=True)
class _Target:
    """The autopilot we talk to, learnt from its heartbeat."""

    system: int
    component: int
    autopilot: str  # "ardupilot" or "px4"


class MavlinkVehicle:
    """A flight controller on a MAVLink link, read as `VehicleState` and steered by body velocities.

    `connect()` opens the link and starts the I/O thread; `poll_state()` returns the newest state
    not yet returned; `send()` steers (or raises `NotSteerableError`); `close()` stops everything.
    With `read_only=True` every steering call raises and nothing but the companion heartbeat and
    stream requests is ever sent.
    """

    # The controller owns this link alone and republishes its states on the state key.
    is_link_owner = True
    # The adapter's own hand-over action flies the vehicle from there: no more setpoints.
    commands_during_handover = False
    wakeup = None  # the controller polls a real vehicle at its own rate

    def __init__(self, url: str, *, vehicle_id: str = "uav1", alt_source: str = "local",
                 handover: str = "hold", allow_mode_switch: bool = False, heartbeat_timeout_s: float = 3.0,
                 setpoint_rate_hz: float = 20.0, stream_rate_hz: float = 20.0, command_timeout_s: float = 1.0,
                 yaw_control: str = "rate", read_only: bool = False, source_system: int = 255,
                 source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER, system_id: int | None = None,
                 limits: SpeedLimits | None = None, yaw_hold_gain_per_s: float = 1.0,
                 signing_key: bytes | None = None, signing_timestamp_file: str | Path | None = None,
                 require_home: bool = True, gnss_denied: str = "off", ekf_source_set: int = 2,
                 external_nav_message: str = "both",
                 odometry_limits: OdometryLimits | None = None, attitude_gains: AttitudeGains | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        check_url(url)
        validate.one_of("gnss_denied", gnss_denied, GNSS_DENIED_MODES)
        validate.one_of("external_nav_message", external_nav_message, EXTERNAL_NAV_MESSAGES)
        validate.in_range("ekf_source_set", ekf_source_set, 1, 3)
        for name, value, choices in (("alt_source", alt_source, ALT_SOURCES), ("handover", handover, HANDOVERS),
                                     ("yaw_control", yaw_control, YAW_CONTROLS)):
            validate.one_of(name, value, choices)
        for name, value in (("heartbeat_timeout_s", heartbeat_timeout_s), ("setpoint_rate_hz", setpoint_rate_hz),
                            ("stream_rate_hz", stream_rate_hz), ("command_timeout_s", command_timeout_s),
                            ("yaw_hold_gain_per_s", yaw_hold_gain_per_s)):
            validate.positive(name, value)
        if setpoint_rate_hz < 10.0:
            # PX4 drops out of OFFBOARD below 2 Hz; we keep a wide margin.
            raise ConfigError(f"setpoint_rate_hz {setpoint_rate_hz} is below the 10 Hz minimum")
        for name, value in (("source_system", source_system), ("source_component", source_component),
                            ("system_id", 1 if system_id is None else system_id)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 255:
                raise ConfigError(f"{name} must be an integer in 1..255, got {value!r}")
        if signing_key is not None and (not isinstance(signing_key, bytes) or len(signing_key) != 32):
            raise ConfigError("a MAVLink signing key must be exactly 32 bytes")
        self.url, self.vehicle_id = url, check_vehicle_id(vehicle_id)
        self._ratelog = RateLimitedLog(log, f"MAVLink {url}")  # first of each kind, then summaries
        self.alt_source, self.handover_action, self.allow_mode_switch = alt_source, handover, allow_mode_switch
        self.heartbeat_timeout_s, self.command_timeout_s = float(heartbeat_timeout_s), float(command_timeout_s)
        self.setpoint_period_s, self.stream_rate_hz = 1.0 / setpoint_rate_hz, float(stream_rate_hz)
        self.yaw_control, self.yaw_hold_gain_per_s = yaw_control, float(yaw_hold_gain_per_s)
        self.type_mask = TYPE_MASK_VELOCITY_YAW_RATE if yaw_control == "rate" else TYPE_MASK_VELOCITY_YAW
        self.read_only, self.system_id = read_only, system_id
        self.limits = limits if limits is not None else SpeedLimits()
        self.source_system, self.source_component = source_system, source_component
        self._signing = (LinkSigning(signing_key, signing_timestamp_file, self._warn, clock)
                         if signing_key is not None else None)
        self.readiness = ArmReadiness(require_home=require_home)
        self._clock = clock
        self._conn: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._identified = threading.Event()
        self._lock = threading.Lock()  # guards every field below that both threads touch
        self._tx_lock = threading.Lock()  # pymavlink's encoder and socket writes
        self._ack_cond = threading.Condition(self._lock)
        self._target: _Target | None = None
        self._mode, self._custom_mode, self._armed = "", -1, False
        self._last_hb_s: float | None = None
        self._lost_reason: str | None = None
        self._fatal: str | None = None  # the I/O thread died: the link never comes back
        self._attitude_rad = (0.0, 0.0, 0.0)
        self._attitude_s: float | None = None
        self._local: tuple[float, float, float, float, float, float] | None = None  # x y z vx vy vz NED
        self._local_alt = AltitudeContinuity(MAX_VERTICAL_SPEED_M_S, ALTITUDE_NOISE_M, STEP_CONFIRM_SAMPLES,
                                             who="MAVLink LOCAL_POSITION_NED")
        self._range_m: float | None = None
        self._state: VehicleState | None = None
        self._state_seq, self._returned_seq = -1, -1
        self._acks: dict[int, int] = {}
        self._cmd: VelocityCommand | None = None  # newest command to stream (None: stream nothing)
        self._cmd_time_s = 0.0
        self._cmd_zeroed = False
        self._cmd_yaw_rad = 0.0  # heading when the newest command arrived
        self._prestream = False  # stream zero setpoints with no command (PX4 before OFFBOARD)
        self._yaw_ref_rad: float | None = None  # the heading held while steering
        self._steered = False  # we have streamed in GUIDED/OFFBOARD at least once
        self._mode_request: tuple[str, float] | None = None  # (mode name, give-up time) in progress
        self._mode_request_next_s = 0.0  # when the I/O thread sends the next DO_SET_MODE for it
        self._landing_target: tuple[float, float, float, float] | None = None  # ax, ay, dist, set at
        self._precland = False
        self._unsupported_seen: set[int] = set()  # MAV_AUTOPILOT values of heartbeats we cannot fly
        self._next_setpoint_s = 0.0
        # Without GNSS: the judgement, the camera's velocity, the attitude loop (gnss_denied.py).
        self.gnss_denied, self.ekf_source_set = gnss_denied, int(ekf_source_set)
        self.external_nav_message = external_nav_message
        self._nav = NavJudge(gnss_denied)
        self._odometry = OdometryGate(odometry_limits)
        self._attitude_gains = attitude_gains if attitude_gains is not None else AttitudeGains(
            climb_limit_up_m_s=self.limits.up_m_s, climb_limit_down_m_s=self.limits.down_m_s)
        self._attitude_loop: AttitudeLoop | None = None  # made once the autopilot (its thrust meaning) is known
        self._attitude_flying = False  # GNSS lost in "attitude": commands go out as attitude targets
        self._attitude_step_s: float | None = None
        self._global: tuple[float, float, float] | None = None  # GLOBAL_POSITION_INT relative alt, vz down, at
        self._local_s: float | None = None  # when the newest LOCAL_POSITION_NED arrived
        self._local_boot_ms: int | None = None  # ... and its time_boot_ms (the autopilot's clock)
        self._streams_asked_s: float | None = None  # when the streams were first asked for
        self._nav_status = NavStatus(False, False, True, "autopilot", "no estimator report yet")
        self._gnss_lost_seen = False
        self._source_set: tuple[int, float] | None = None  # (tries so far, next try) while switching
        # Counters for tests, operators' logs and the run's stats.
        self.vision_sent = 0
        self.ground_vision_sent = 0  # zero velocities streamed while disarmed (the VisOdom pre-arm check)
        self._ground_vision_logged = False
        self.attitude_targets_sent = 0
        self.gnss_losses = 0
        self.source_set_result: int | None = None  # MAV_RESULT of the source-set switch (None: none yet)
        self.setpoints_sent = 0
        self.stop_hold_s = 0.5  # close(): zero velocity streams this long (10 setpoints at 20 Hz)
        self.setpoints_clamped = 0  # every setpoint written, stream repeats included
        self.commands_steered = 0  # commands handed in by send() and flown
        self.commands_clamped = 0  # ... of which asked for more than the limits
        self.messages_received = 0
        self.landing_targets_sent = 0
        self.samples_rejected: Counter[str] = Counter()  # reason -> count
        self.intruders: Counter[int] = Counter()  # system id of another autopilot -> heartbeats refused
        self.send_failures = 0

    # ----------------------------------------------------------------- life cycle

    def connect(self, timeout_s: float = 10.0) -> None:
        """Open the link, wait for the autopilot's heartbeat, request the streams the state needs."""
        if self._conn is not None:
            raise MavlinkError("connect() called twice")
        self._conn = open_link(self.url, source_system=self.source_system, source_component=self.source_component)
        if self._signing is not None:
            self._signing.install(self._conn)
        self._thread = threading.Thread(target=self._io_main, name=f"mavlink-{self.vehicle_id}", daemon=True)
        self._thread.start()
        if not self._identified.wait(timeout_s):
            fatal = self._fatal
            self.close()
            if fatal is not None:
                raise VehicleConnectError(fatal)
            seen = (f"; heartbeats seen only from unsupported autopilots (MAV_AUTOPILOT "
                    f"{sorted(self._unsupported_seen)}), only ArduPilot and PX4 are supported"
                    if self._unsupported_seen else "")
            pinned = f" from system {self.system_id}" if self.system_id is not None else ""
            signed = f"; {dict(self.signing_rejected)} frames failed signing" if self.signing_rejected else ""
            raise VehicleConnectError(f"no ArduPilot/PX4 heartbeat{pinned} on {self.url!r} within {timeout_s:.1f} s"
                                      f"{seen}{signed} (for udpin the autopilot must send to us; for udpout we "
                                      "send first)")
        target = self._target
        assert target is not None
        log.info("connected to %s on %s (system %d component %d%s), mode %s, %s%s", target.autopilot, self.url,
                 target.system, target.component, ", pinned" if self.system_id is not None else "", self.mode,
                 "armed" if self.armed else "disarmed", ", signed link" if self._signing else "")

    def close(self) -> None:
        """Stop the I/O thread and close the link (the autopilot's own failsafes take over).

        If we were steering, zero velocity streams for `stop_hold_s` first: one lost datagram must
        not leave ArduCopter flying the last setpoint until GUID_TIMEOUT (3 s at 10 m/s was ~35 m
        blind on SITL), and the last thing the autopilot heard from us is "stop here".
        """
        with self._lock:
            steering = self._cmd is not None and self._refusal_locked() is None and self._thread is not None
            if steering:
                self._cmd, self._cmd_time_s, self._cmd_zeroed = self._zero(), self._clock(), True
                self._next_setpoint_s = self._clock()  # the first zero goes out now
        if steering:
            log.info("closing the MAVLink link: streaming zero velocity for %.1f s first", self.stop_hold_s)
            self._stop.wait(self.stop_hold_s)
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._conn is not None:
            if self._signing is not None:
                self._signing.persist()
            self._conn.close()
            self._conn = None

    def __enter__(self) -> MavlinkVehicle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- reading

    @property
    def autopilot(self) -> str:
        """'ardupilot' or 'px4' once connected, '' before."""
        return self._target.autopilot if self._target else ""

    @property
    def mode(self) -> str:
        with self._lock:
            return self._mode

    @property
    def armed(self) -> bool:
        with self._lock:
            return self._armed

    @property
    def lost_reason(self) -> str | None:
        """Why the link counts as lost (heartbeat timeout, I/O failure), or None while it is alive."""
        with self._lock:
            return self._lost_reason

    def poll_state(self) -> VehicleState | None:
        """The newest state not yet returned; None if nothing new or the link is lost (see lost_reason)."""
        with self._lock:
            if self._lost_reason is not None or self._state is None or self._state_seq == self._returned_seq:
                return None
            self._returned_seq = self._state_seq
            return self._state

    @property
    def signing_rejected(self) -> Counter[str]:
        """Frames refused by signing, by kind: unsigned, wrong key, replayed (empty without a key)."""
        return self._signing.rejected if self._signing is not None else Counter()

    @property
    def rejected(self) -> int:
        """No Zenoh state payloads here: bad MAVLink samples are counted in counters()["samples_rejected"]."""
        return 0

    def counters(self) -> dict[str, Any]:
        """What the link did, for the run's stats and the operator."""
        return {"setpoints_sent": self.setpoints_sent, "setpoints_clamped": self.setpoints_clamped,
                "commands_steered": self.commands_steered, "commands_clamped": self.commands_clamped,
                "messages_received": self.messages_received, "landing_targets_sent": self.landing_targets_sent,
                "samples_rejected": dict(self.samples_rejected), "intruder_heartbeats": dict(self.intruders),
                "signing_rejected": dict(self.signing_rejected), "send_failures": self.send_failures,
                "lost_reason": self.lost_reason, "gnss_denied": self.gnss_denied, "gnss_losses": self.gnss_losses,
                "vision_speed_sent": self.vision_sent, "ground_vision_sent": self.ground_vision_sent,
                "attitude_targets_sent": self.attitude_targets_sent,
                "ekf_source_set_result": self.source_set_result, "nav_reason": self.nav_status().reason}

    # ----------------------------------------------------------------- without GNSS

    def nav_status(self) -> NavStatus:
        """What may be trusted about the vehicle's motion now (refreshed by the I/O thread at 5 Hz)."""
        with self._lock:
            return self._nav_status

    def on_visual_odometry(self, odom: VisualOdometry) -> None:
        """The camera's newest velocity. "external-nav": each good sample goes to the EKF at once."""
        if not isinstance(odom, VisualOdometry):
            raise TypeError(f"on_visual_odometry() takes a VisualOdometry, got {type(odom).__name__}")
        if odom.vehicle_id != self.vehicle_id:
            self._reject("other vehicle's odometry", f"vehicle {odom.vehicle_id!r}, not {self.vehicle_id!r}")
            return
        now = self._clock()
        with self._lock:
            if not self._odometry.add(odom, now):
                return
            # Only a good sample goes to the EKF (one over the variance limit is dropped, not sent).
            good = self._odometry.sample_good(odom)
            attitude = self._attitude_rad if self._attitude_s is not None else None
            ground = self._ground_vision_locked()
        if self.gnss_denied != "external-nav" or not good or self.read_only or self._target is None:
            return
        if attitude is None:
            return  # no heading yet: a body velocity cannot be put in NED
        if ground:
            return  # disarmed on the ground: the zero stream speaks for the camera (one source at a time)
        # The capture time on the autopilot's clock when the camera tagged it so (time since boot,
        # what ArduPilot's jitter correction expects), else ours.
        t_s = odom.stamp.t_s if odom.stamp.clock == "vehicle" else now
        if self._send_vision(t_s, odom.vel_body_frd_m_s, odom.vel_var_m2_s2, odom.dt_s, odom.quality, attitude):
            self.vision_sent += 1

    def _ground_vision_locked(self) -> bool:
        """The zero-velocity stream applies now: "external-nav" on an ArduPilot that is disarmed. Caller holds the lock."""
        return (self.gnss_denied == "external-nav" and not self.read_only and self._target is not None
                and self._target.autopilot == "ardupilot" and not self._armed and self._lost_reason is None)

    def _ground_vision_tick(self, now: float) -> None:
        """While disarmed, a zero velocity for ArduPilot's VisOdom (its pre-arm check wants data within 300 ms).

        Only what is known: a disarmed multirotor stands on the ground. It stops the moment the
        heartbeat says armed (the arming itself was checked on it); from then on only the camera's
        good samples go out. The EKF fuses it only where the active source set takes ExternalNav.
        """
        with self._lock:
            if not self._ground_vision_locked():
                return
            attitude = self._attitude_rad
        if not self._ground_vision_logged:
            self._ground_vision_logged = True
            log.info("external-nav: the autopilot is disarmed, streaming a zero velocity to its visual odometry "
                     "at %.0f Hz until it arms (VISO_TYPE's pre-arm check wants data; the camera cannot measure "
                     "on the ground)", 1.0 / _GROUND_VISION_PERIOD_S)
        if self._send_vision(now, (0.0, 0.0, 0.0), _GROUND_VISION_VAR_M2_S2, _GROUND_VISION_PERIOD_S, 1.0, attitude):
            self.ground_vision_sent += 1

    def _send_vision(self, t_s: float, vel_body_frd_m_s: tuple[float, float, float], var: float, dt_s: float,
                     quality: float, attitude: tuple[float, float, float]) -> bool:
        """One velocity for the autopilot's EKF, in the message(s) its kind takes; True when written."""
        target = self._target
        assert target is not None
        usec = int(max(0.0, t_s) * 1e6)
        if target.autopilot == "px4":
            # PX4 has no VISION_SPEED_ESTIMATE handler: ODOMETRY with only a body-frame velocity (the
            # position fields NaN), fused with EKF2_EV_CTRL bit 2 (velocity).
            nan = float("nan")
            fwd, right, down = vel_body_frd_m_s
            velocity_cov = [var, 0.0, 0.0, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, 0.0, var] + [0.0] * 9
            return self._tx(lambda mav: mav.odometry_send(
                usec, MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD, nan, nan, nan, [nan, nan, nan, nan], fwd, right,
                down, nan, nan, nan, [nan] + [0.0] * 20, velocity_cov, 0, MAV_ESTIMATOR_TYPE_VISION,
                int(round(quality * 100))))
        speed = self.external_nav_message in ("both", "speed") and speed_message_takes(var)
        delta = self.external_nav_message in ("both", "delta")
        if not (speed or delta):
            return False  # a "speed"-only link and a sample too noisy for it: nothing written
        ok = True
        if speed:
            vn, ve, vd = frd_to_ned(vel_body_frd_m_s, *attitude)
            cov = vision_speed_covariance(var)
            ok = self._tx(lambda mav: mav.vision_speed_estimate_send(usec, vn, ve, vd, cov, 0))
        if delta:
            # The displacement between the two frames, body FRD at the newer one; the rotation between
            # them is left at zero: with the camera at the centre of gravity (VISO_POS_X/Y/Z 0) EKF3
            # uses it only for the lever arm.
            delta = [v * dt_s for v in vel_body_frd_m_s]
            dt_us = int(dt_s * 1e6)
            confidence = body_odom_confidence(var)
            ok = self._tx(lambda mav: mav.vision_position_delta_send(
                usec, dt_us, [0.0, 0.0, 0.0], delta, confidence)) and ok
        return ok

    def _nav_tick(self, now: float) -> None:
        """Judge the navigation; on a GNSS loss start what the mode asks (source set, GUIDED_NOGPS)."""
        with self._lock:
            status = self._nav.status(now, self._odometry)
            if self._attitude_flying and status.source == SOURCE_AUTOPILOT:
                # GNSS back, but we still fly attitude targets: only the camera's velocity closes the loop.
                good, why = self._odometry.judge(now)
                status = (NavStatus(False, False, True, SOURCE_VISUAL, "flying attitude targets on the visual "
                                    "velocity (GNSS back; the mode stays until the pilot changes it)") if good else
                          NavStatus(False, False, False, SOURCE_NONE, f"flying attitude targets and {why}: no descent"))
            previous, self._nav_status = self._nav_status, status
            target = self._target
            # Counted with the status that shows it, so a reader never sees one without the other. A
            # position lost without a fix ever seen (started after the loss) counts as the same loss,
            # but only once the vehicle is armed: on the ground before its first fix an EKF without a
            # position is booting, not lost (SITL: a controller started at boot latched that as the
            # loss, began flying attitude targets in STABILIZE and refused every command after takeoff).
            lost = status.gnss_lost or status.position_lost
            first_loss = lost and self._armed and not self._gnss_lost_seen
            if first_loss:
                self._gnss_lost_seen = True
                self.gnss_losses += 1
        if status.gnss_lost != previous.gnss_lost or status.position_lost != previous.position_lost:
            if status.gnss_lost or status.position_lost:
                log.warning("navigation: %s", status.reason)
            else:
                log.info("navigation: GNSS and position back (%s)", status.reason)
        elif status.velocity_trusted != previous.velocity_trusted:
            log.info("navigation: velocity %s: %s", "trusted" if status.velocity_trusted else "NOT trusted",
                     status.reason)
        if not lost or target is None or self.read_only:
            return
        if first_loss:
            if self.gnss_denied == "external-nav" and target.autopilot == "ardupilot":
                log.warning("GNSS lost: switching the EKF to source set %d (VELXY ExternalNav)", self.ekf_source_set)
                self._source_set = (0, now)
            elif self.gnss_denied == "attitude":
                self._start_attitude_flying(target)
        if self._source_set is not None and now >= self._source_set[1]:
            self._source_set_tick(now)

    def _source_set_tick(self, now: float) -> None:
        assert self._source_set is not None
        tries, _ = self._source_set
        with self._ack_cond:
            result = self._acks.pop(MAV_CMD_SET_EKF_SOURCE_SET, None)
        if result is not None:
            self.source_set_result = result
            if result == MAV_RESULT_ACCEPTED:
                log.info("EKF source set %d accepted by the autopilot", self.ekf_source_set)
                self._source_set = None
                return
        if tries >= _SOURCE_SET_TRIES:
            log.warning("the autopilot did not accept EKF source set %d after %d tries (last MAV_RESULT %s): the "
                        "EKF may not fuse the visual velocity; no descent until it does", self.ekf_source_set, tries,
                        result)
            self._source_set = None
            return
        self._send_command_long(MAV_CMD_SET_EKF_SOURCE_SET, float(self.ekf_source_set))
        self._source_set = (tries + 1, now + _SOURCE_SET_RETRY_S)

    def _start_attitude_flying(self, target: _Target) -> None:
        """GNSS lost in "attitude": from now on commands go out as attitude targets."""
        with self._lock:
            self._attitude_flying = True
            self._attitude_step_s = None
            if self._attitude_loop is None:
                # ArduCopter reads thrust as a climb rate (GUID_OPTIONS bit 3 clear); PX4 as thrust.
                self._attitude_loop = AttitudeLoop(self._attitude_gains,
                                                   thrust_mode="thrust" if target.autopilot == "px4" else "climb-rate")
            self._attitude_loop.reset()
            in_guided = self._mode == "GUIDED" and self._armed
            if target.autopilot == "ardupilot" and in_guided:
                # Our own switch, not a pilot's: GUIDED without a position ends in the EKF failsafe.
                self._request_mode_locked("GUIDED_NOGPS")
        if target.autopilot == "ardupilot":
            if in_guided:
                log.warning("GNSS lost: switching GUIDED -> GUIDED_NOGPS, flying attitude targets on the visual "
                            "velocity")
            else:
                log.warning("GNSS lost in %s: not switching to GUIDED_NOGPS (dovesei was not flying in GUIDED)",
                            self.mode)
        else:
            log.warning("GNSS lost: flying OFFBOARD attitude targets on the visual velocity")

    def _steer_mode_locked(self) -> str:
        """The mode we steer in: GUIDED_NOGPS once ArduPilot flies attitude targets. Caller holds the lock."""
        assert self._target is not None
        if self._attitude_flying and self._target.autopilot == "ardupilot":
            return "GUIDED_NOGPS"
        return STEER_MODE[self._target.autopilot]

    # ----------------------------------------------------------------- steering

    def send(self, cmd: VelocityCommand) -> None:
        """Steer with a body-frame FRD velocity and yaw rate, or raise NotSteerableError (nothing sent)."""
        if not isinstance(cmd, VelocityCommand):
            raise TypeError(f"send() takes a VelocityCommand, got {type(cmd).__name__}")
        with self._lock:
            reason = self._refusal_locked()
            if reason is None:
                self._cmd, self._cmd_time_s, self._cmd_zeroed = cmd, self._clock(), False
                # The body frame the command means: the heading when it arrives (yaw_control 'autopilot'
                # sends it in the local frame, so repeats never turn with the vehicle).
                self._cmd_yaw_rad = self._attitude_rad[2]
                self._steered = True
            else:
                reason = self._maybe_request_mode_locked(reason)
        if reason is not None:
            raise NotSteerableError(reason)
        # Out at once (the stream only fills the gaps); the stream's next repeat is a period away.
        if not self._send_setpoint(cmd):
            raise NotSteerableError("setpoint not sent: the link's socket refused it (see the log)")
        # Per command, not per repeat: how often the controller asked for more than the vehicle flies.
        self.commands_steered += 1
        if clamp_setpoint(cmd.vel_body_frd_m_s, 0.0, self.limits)[2]:
            self.commands_clamped += 1
        with self._lock:
            self._next_setpoint_s = self._clock() + self.setpoint_period_s

    def hold(self) -> bool:
        """Command zero velocity (the autopilot holds position); False (and a log) if not steerable."""
        try:
            self.send(self._zero())
        except NotSteerableError as exc:
            log.warning("hold not sent: %s", exc.reason)
            return False
        return True

    def handover(self) -> bool:
        """The configured action at the goal altitude: 'hold', 'land', 'precland' or 'none'.

        'land' and 'precland' stop our setpoints and ask the I/O thread for the mode (it retries
        each second for 5 s), so the controller's loop never blocks on the radio.
        """
        if self.handover_action == "none":
            # The user's own system takes over from here: our setpoints would fight it.
            with self._lock:
                self._cmd = None
            log.info("handover: no action configured (handover='none'); setpoint stream stopped")
            return True
        if self.handover_action == "hold":
            return self.hold()
        if self.read_only:
            raise NotSteerableError("read-only MAVLink adapter: handover refused")
        target = self._require_target()
        # PX4 lands precisely only in AUTO.PRECLAND; ArduPilot's LAND uses PLND_* when enabled.
        wanted = "PRECLAND" if self.handover_action == "precland" and target.autopilot == "px4" else "LAND"
        with self._lock:
            self._cmd = None  # the autopilot lands on its own now; our setpoints would fight it
            self._precland = self.handover_action == "precland"
            self._mode_request = (wanted, self._clock() + 5.0)
            self._mode_request_next_s = self._clock()
        log.info("handover: %s mode requested%s", wanted,
                 ", streaming LANDING_TARGET at the chosen spot" if self._precland else "")
        return True

    def set_landing_target(self, angle_x_rad: float, angle_y_rad: float, distance_m: float) -> None:
        """The chosen spot as seen from the camera (image x right, image y down = body backward)."""
        ax = validate.in_range("landing target angle_x", angle_x_rad, -math.pi / 2, math.pi / 2)
        ay = validate.in_range("landing target angle_y", angle_y_rad, -math.pi / 2, math.pi / 2)
        dist = validate.in_range("landing target distance", distance_m, 0.0, 10_000.0)
        with self._lock:
            self._landing_target = (ax, ay, dist, self._clock())

    def set_mode(self, name: str, timeout_s: float = 3.0) -> bool:
        """Ask for a mode by name and wait until the heartbeat shows it (True) or the timeout (False)."""
        if self.read_only:
            raise NotSteerableError(f"read-only MAVLink adapter: mode change to {name} refused")
        target = self._require_target()
        custom, p2, p3 = encode_mode(target.autopilot, name)
        result = self._command_long_wait(MAV_CMD_DO_SET_MODE, float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(p2),
                                         float(p3), timeout_s=min(1.0, timeout_s))
        if result is None:
            # Older firmware may ignore DO_SET_MODE; SET_MODE is the message every autopilot knows.
            self._tx(lambda mav: mav.set_mode_send(target.system, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom))
        elif result != MAV_RESULT_ACCEPTED:
            log.warning("autopilot refused mode %s (MAV_RESULT %d)", name, result)
            return False
        return self._wait(lambda: self._mode == name, timeout_s)

    def arm_and_takeoff(self, alt_m: float, timeout_s: float | None = None, *, ready_timeout_s: float = 120.0,
                        climb_rate_m_s: float | None = None) -> None:
        """Wait until the autopilot can arm, arm (retried with backoff) and climb to `alt_m`.

        Only when the user asked (the controller's `--takeoff-alt-m`). ArduPilot: GUIDED, ARM,
        NAV_TAKEOFF. PX4: zero setpoints streamed, OFFBOARD, ARM, then a climb velocity (no global
        position needed). Gives up after `ready_timeout_s` naming the autopilot's last pre-arm
        reasons; the climb limit is `timeout_s`, by default 30 s + 2 x alt / climb rate.
        """
        mavlink_takeoff.arm_and_takeoff(self, alt_m, climb_timeout_s=timeout_s, ready_timeout_s=ready_timeout_s,
                        climb_rate_m_s=climb_rate_m_s if climb_rate_m_s is not None else self.limits.up_m_s)

    # ----------------------------------------------------------------- internals: policy of refusal

    def _refusal_locked(self) -> str | None:
        """Why we may not steer now, or None. Caller holds the lock."""
        if self.read_only:
            return "read-only MAVLink adapter: it never steers"
        if self._target is None:
            return "not connected to an autopilot"
        if self._lost_reason is not None:
            return self._lost_reason
        if not self._armed:
            return "the autopilot is disarmed (dovesei never arms on its own)"
        wanted = self._steer_mode_locked()
        if self._mode != wanted:
            if self._mode_request is not None and self._mode_request[0] == wanted:
                return f"the autopilot is in {self._mode}, switching to {wanted}"
            return f"the autopilot is in {self._mode}, not {wanted}"
        return None

    def _maybe_request_mode_locked(self, reason: str) -> str:
        """With allow_mode_switch, start a switch into GUIDED/OFFBOARD; returns the refusal text."""
        target = self._target
        if (not self.allow_mode_switch or target is None or self.read_only or self._lost_reason is not None
                or not self._armed):
            return reason
        wanted = self._steer_mode_locked()
        if self._mode_request is not None and self._mode_request[0] == wanted:
            return reason  # our own switch is already under way
        if self._steered:
            # We flew it in that mode and someone switched away: a pilot's takeover wins, always.
            return f"{reason}; not switching back after a mode change away from {wanted} (pilot override)"
        if self._mode_request is None:
            self._request_mode_locked(wanted)
            log.info("requesting mode %s (allow_mode_switch)", wanted)
        return f"{reason}; switch to {wanted} requested"

    def _request_mode_locked(self, wanted: str) -> None:
        """Have the I/O thread ask for `wanted` each second for 5 s. Caller holds the lock."""
        now = self._clock()
        self._mode_request = (wanted, now + 5.0)
        px4_offboard = self._target is not None and self._target.autopilot == "px4" and wanted == "OFFBOARD"
        # PX4 refuses OFFBOARD until setpoints stream: let the zero pre-stream run first.
        self._mode_request_next_s = now + (0.3 if px4_offboard else 0.0)

    def _zero(self, seq: int = -1) -> VelocityCommand:
        return VelocityCommand(vehicle_id=self.vehicle_id, seq=seq, stamp=Stamp(0.0, "vehicle"),
                               vel_body_frd_m_s=(0.0, 0.0, 0.0))

    # ----------------------------------------------------------------- for the takeoff sequence (takeoff.py)

    def altitude_m(self) -> float | None:
        """The newest altitude above ground, or None before the first state."""
        with self._lock:
            return self._state.alt_agl_m if self._state is not None else None

    @property
    def closed(self) -> bool:
        """close() was called: every wait ends and nothing more is sent."""
        return self._stop.is_set()

    def pause(self, seconds: float) -> bool:
        """Wait up to `seconds`; True when the adapter was closed meanwhile (the caller stops)."""
        return self._stop.wait(seconds)

    def connected_autopilot(self) -> str:
        """'ardupilot' or 'px4'; NotSteerableError before connect()."""
        return self._require_target().autopilot

    def command_long(self, command: int, *params: float) -> None:
        """Send COMMAND_LONG to the autopilot without waiting for its answer."""
        self._send_command_long(command, *params)

    def command_long_wait(self, command: int, *params: float, timeout_s: float) -> int | None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK result (None: no answer in time)."""
        return self._command_long_wait(command, *params, timeout_s=timeout_s)

    def wait_armed(self, timeout_s: float) -> bool:
        """True once the autopilot's heartbeat says armed, within `timeout_s`."""
        return self._wait(lambda: self._armed, timeout_s)

    def zero_command(self) -> VelocityCommand:
        """A zero-velocity command of this vehicle (hold where you are)."""
        return self._zero()

    @contextmanager
    def prestreaming(self) -> Iterator[None]:
        """Stream zero setpoints while no command is given (PX4 enters OFFBOARD only while they stream)."""
        with self._lock:
            self._prestream = True
        try:
            yield
        finally:
            with self._lock:
                self._prestream = False

    # ----------------------------------------------------------------- internals: I/O thread

    def _io_main(self) -> None:
        """The I/O thread: any exception ends it as a reported, permanent link loss."""
        try:
            self._io_loop()
        except Exception as exc:  # noqa: BLE001 - the thread must never die silently
            reason = f"MAVLink I/O thread failed ({type(exc).__name__}: {exc}): link lost, steering stopped"
            with self._lock:
                self._fatal = self._lost_reason = reason
                self._cmd, self._prestream, self._precland = None, False, False
            log.error("%s", reason, exc_info=True)

    def _io_loop(self) -> None:
        next_hb_s = self._clock()  # send at once: an udpout peer learns our address from it
        next_stream_request_s = next_landing_s = next_sign_s = next_nav_s = next_ground_s = 0.0
        while not self._stop.is_set():
            now = self._clock()
            if now >= next_hb_s:
                self._send_heartbeat()
                next_hb_s = now + 1.0
            self._check_link(now)
            if self._target is not None and self._state is None and now >= next_stream_request_s:
                # Asked again every 2 s until the first state: a request is one UDP datagram.
                self._request_streams()
                next_stream_request_s = now + 2.0
            with self._lock:
                due = now >= self._next_setpoint_s
            if due:
                self._stream_tick(now)
                with self._lock:
                    self._next_setpoint_s = now + self.setpoint_period_s
            with self._lock:
                mode_due = self._mode_request is not None and now >= self._mode_request_next_s
            if mode_due:
                self._mode_request_tick(now)
            if self._precland and now >= next_landing_s:
                self._send_landing_target(now)
                next_landing_s = now + _LANDING_TARGET_PERIOD_S
            if self.gnss_denied == "external-nav" and self._target is not None and now >= next_ground_s:
                self._ground_vision_tick(now)
                next_ground_s = now + _GROUND_VISION_PERIOD_S
            if self._signing is not None and now >= next_sign_s:
                self._signing.tick(self._tx_lock)
                next_sign_s = now + 1.0
            with self._lock:
                wake_s = min(next_hb_s, self._next_setpoint_s)
            self._conn.select(max(0.0, min(wake_s - self._clock(), 0.05)))
            self._drain()
            # Judged after the drain: a burst read after a stall of ours is not an estimator going silent.
            now = self._clock()
            if self._target is not None and now >= next_nav_s:
                self._nav_tick(now)
                next_nav_s = now + _NAV_PERIOD_S

    def _drain(self) -> None:
        """Parse every message waiting on the link (the I/O thread is the only reader)."""
        for _ in range(1000):  # bound the burst so the stream deadlines still get served
            try:
                msg = self._conn.recv_msg()
            except OSError as exc:
                # Transient on UDP (ICMP refusals while the peer starts); a dead peer shows as
                # heartbeat loss, which is what stops steering.
                self._warn("recv", "MAVLink receive failed: %s", exc)
                return
            if msg is None:
                return
            self._handle(msg)

    def _warn(self, kind: str, fmt: str, *args: Any) -> None:
        """A warning that may repeat at stream rate: the first of its kind, then summaries."""
        self._ratelog.warn(kind, fmt % args)

    def _reject(self, reason: str, detail: str) -> None:
        self.samples_rejected[reason] += 1
        self._warn(reason, "autopilot sample dropped (%s): %s [%d so far]", reason, detail,
                          self.samples_rejected[reason])

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return  # corrupt or unauthenticated bytes; signing failures are counted where checked
        self.messages_received += 1
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, src_sys, src_comp)
            return
        target = self._target
        if target is None or src_sys != target.system:
            return  # another vehicle on a shared link, or data before we know who we talk to
        try:
            if kind == "DISTANCE_SENSOR":
                self._on_distance(msg)  # any component of the vehicle: a rangefinder may speak for itself
                return
            if src_comp != target.component:
                return  # e.g. a vision component's own estimate: the autopilot's is the one it flies on
            if kind == "LOCAL_POSITION_NED":
                local = check_local_position(msg)
                jump = self._local_alt.check(msg.time_boot_ms / 1000.0, -local[2])
                if jump is not None:  # a height no multirotor flew to: dropped before it is a state
                    self._reject("LOCAL_POSITION_NED jump", f"LOCAL_POSITION_NED: {jump}")
                    return
                with self._lock:
                    self._local, self._local_s, self._local_boot_ms = local, self._clock(), int(msg.time_boot_ms)
                    self._nav.on_local_position(self._local_s)
                if self.alt_source == "local":
                    self._publish_state(msg.time_boot_ms, -local[2])
            elif kind == "ATTITUDE":
                attitude = check_attitude(msg)
                with self._lock:
                    self._attitude_rad, self._attitude_s = attitude, self._clock()
                self._maybe_publish_fallback(msg.time_boot_ms)
            elif kind == "GLOBAL_POSITION_INT":
                # relative_alt: the barometric height above home, which outlives the horizontal position.
                alt_m = validate.in_range("GLOBAL_POSITION_INT.relative_alt", msg.relative_alt / 1000.0,
                                          *ALT_RANGE_M)
                vz = validate.in_range("GLOBAL_POSITION_INT.vz", msg.vz / 100.0, -SPEED_RANGE_M_S, SPEED_RANGE_M_S)
                with self._lock:
                    self._global = (alt_m, vz, self._clock())
            elif kind == "GPS_RAW_INT":
                with self._lock:
                    self._nav.on_gps_fix(int(msg.fix_type))
            elif kind == "ESTIMATOR_STATUS":
                with self._lock:
                    self._nav.on_ekf_flags(int(msg.flags) & 0x3FF)  # PX4's bits above 512 mean other things
            elif kind == "COMMAND_ACK":
                with self._ack_cond:
                    self._acks[msg.command] = msg.result
                    self._ack_cond.notify_all()
                if msg.result not in (MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS):
                    # Repeated requests (streams, home) would repeat the same line every 2 s.
                    self._warn(f"ack {msg.command}", "autopilot answered command %d with "
                                      "MAV_RESULT %d", msg.command, msg.result)
            elif kind == "STATUSTEXT":
                text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("utf-8", "replace")
                item = self.readiness.on_statustext(msg.severity, text.rstrip("\x00"))
                log.info("autopilot [%s] %s", item.severity_name, item.text)
            elif kind == "SYS_STATUS":
                self.readiness.on_sys_status(msg.onboard_control_sensors_present,
                                             msg.onboard_control_sensors_enabled,
                                             msg.onboard_control_sensors_health)
            elif kind == "EKF_STATUS_REPORT":
                self.readiness.on_ekf_status(msg.flags)
                with self._lock:
                    self._nav.on_ekf_flags(int(msg.flags) & 0xFFFF)
            elif kind == "HOME_POSITION":
                validate.finite_vector("HOME_POSITION x, y, z", (msg.x, msg.y, msg.z), 3)
                self.readiness.on_home()
        except ConfigError as exc:
            # One bad sample is dropped; the previous good one stays until the next good one.
            self._reject(f"bad {kind}", str(exc))

    def _on_heartbeat(self, msg: Any, src_sys: int, src_comp: int) -> None:
        if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER):
            return  # ground stations and companions (including a second dovesei process)
        kind = AUTOPILOT_KINDS.get(msg.autopilot)
        if self._target is None:
            if kind is None:
                self._unsupported_seen.add(int(msg.autopilot))  # a gimbal, a camera, another stack
                return
            if self.system_id is not None and src_sys != self.system_id:
                # Pinned: whoever speaks first, only the configured autopilot is ever locked onto.
                self.intruders[src_sys] += 1
                self._warn("unpinned", "heartbeat of an autopilot with system id %d "
                                  "ignored: pinned to system %d", src_sys, self.system_id)
                return
            self._target = _Target(src_sys, src_comp, kind)
        target = self._target
        if (src_sys, src_comp) != (target.system, target.component):
            if kind is not None:
                # A second autopilot (or a spoofer) mid-flight: never followed, always reported.
                self.intruders[src_sys] += 1
                self._warn(f"intruder {src_sys}", "a second autopilot (system %d component "
                                  "%d) is on the link: refused, still flying system %d [%d heartbeats so far]",
                                  src_sys, src_comp, target.system, self.intruders[src_sys])
            return
        custom = int(msg.custom_mode) if msg.base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED else -1
        name = mode_name(target.autopilot, custom) if custom >= 0 else f"BASE(0x{msg.base_mode:02x})"
        armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        with self._lock:
            if name != self._mode or armed != self._armed:
                if self._mode:
                    log.info("autopilot mode %s -> %s, %s", self._mode, name, "armed" if armed else "disarmed")
                if self._mode_request is not None and name == self._mode_request[0]:
                    self._mode_request = None
            self._mode, self._custom_mode, self._armed = name, custom, armed
            self._last_hb_s = self._clock()
            if self._lost_reason is not None and self._fatal is None:
                log.info("autopilot heartbeat back; steering resumes only with a new command")
                self._lost_reason = None
        self._identified.set()

    def _on_distance(self, msg: Any) -> None:
        if msg.orientation != MAV_SENSOR_ROTATION_PITCH_270:
            return  # only a downward sensor measures height above ground
        with self._lock:
            roll, pitch, _ = self._attitude_rad
        range_m = check_distance_m(msg, roll, pitch)
        with self._lock:
            self._range_m = range_m
        if self.alt_source == "rangefinder":
            if range_m is None:
                # No state at all: a made-up altitude is worse than the controller's stale-state hold.
                log.debug("rangefinder out of range (%d cm outside %d..%d cm)", msg.current_distance,
                          msg.min_distance, msg.max_distance)
                return
            self._publish_state(msg.time_boot_ms, range_m)

    def _publish_state(self, time_boot_ms: int, alt_agl_m: float) -> None:
        with self._lock:
            if self._attitude_s is None:
                return  # without the heading the body-frame velocity would be made up
            roll, pitch, yaw = self._attitude_rad
            local = self._local
            vel_frd = ned_to_frd(local[3:], roll, pitch, yaw) if local else (0.0, 0.0, 0.0)
            pos_ned = (float(local[0]), float(local[1]), float(local[2])) if local else (0.0, 0.0, 0.0)
            self._state_seq += 1
            self._state = VehicleState(
                vehicle_id=self.vehicle_id, seq=self._state_seq, stamp=Stamp(time_boot_ms / 1000.0, "vehicle"),
                alt_agl_m=float(alt_agl_m), vel_body_frd_m_s=vel_frd, roll_rad=float(roll),
                pitch_rad=float(pitch), yaw_rad=float(yaw), armed=self._armed, mode=self._mode,
                pos_valid=local is not None, pos_local_ned_m=pos_ned)

    def _maybe_publish_fallback(self, time_boot_ms: int) -> None:
        """The state once LOCAL_POSITION_NED has stopped: altitude from GLOBAL_POSITION_INT, stamped by ATTITUDE."""
        if self.alt_source != "local":
            return  # the rangefinder keeps publishing on its own
        now = self._clock()
        with self._lock:
            local_ms, glob, asked_s = self._local_boot_ms, self._global, self._streams_asked_s
            if local_ms is None:
                # Never had one: fall back only once it clearly is not coming (a controller started
                # after the loss); at a normal start the local position follows the request at once.
                if asked_s is None or now - asked_s <= _LOCAL_NEVER_S:
                    return
            elif time_boot_ms - local_ms <= _LOCAL_FALLBACK_S * 1000.0:
                # Judged on the autopilot's clock: a burst read after a stall of ours is still in order.
                return  # the local position still streams
            if glob is None or now - glob[2] > _GLOBAL_FRESH_S:
                return  # no altitude we believe: a made-up state is worse than the stale-state hold
            roll, pitch, yaw = self._attitude_rad
            visual = self._odometry.velocity(now)
            fwd, right = (visual[0], visual[1]) if visual is not None else (0.0, 0.0)
            # The vertical velocity rotated in from NED; the horizontal is the camera's (or zero).
            down = ned_to_frd((0.0, 0.0, glob[1]), roll, pitch, yaw)[2]
            self._state_seq += 1
            self._state = VehicleState(
                vehicle_id=self.vehicle_id, seq=self._state_seq, stamp=Stamp(time_boot_ms / 1000.0, "vehicle"),
                alt_agl_m=float(glob[0]), vel_body_frd_m_s=(float(fwd), float(right), float(down)),
                roll_rad=float(roll), pitch_rad=float(pitch), yaw_rad=float(yaw), armed=self._armed,
                mode=self._mode, pos_valid=False, pos_local_ned_m=(0.0, 0.0, 0.0))

    def _check_link(self, now: float) -> None:
        with self._lock:
            if self._last_hb_s is None or self._lost_reason is not None:
                return
            age_s = now - self._last_hb_s
            if age_s <= self.heartbeat_timeout_s:
                return
            self._lost_reason = (f"no autopilot heartbeat for {age_s:.1f} s (limit {self.heartbeat_timeout_s:.1f} s): "
                                 "setpoint stream stopped")
            # Forget the command: when the link returns, only a fresh decision may steer again.
            self._cmd = None
            reason = self._lost_reason
        log.warning("MAVLink link lost: %s", reason)

    def _stream_tick(self, now: float) -> None:
        """Repeat the newest command (or zero if it is stale) while steering is still allowed."""
        with self._lock:
            cmd = self._cmd
            if cmd is None:
                px4_switch = (self._mode_request is not None and self._mode_request[0] == "OFFBOARD"
                              and self._target is not None and self._target.autopilot == "px4")
                if not (px4_switch or self._prestream) or self._lost_reason is not None:
                    self._yaw_ref_rad = None  # a new steering session holds its own heading
                    return
                # PX4 accepts OFFBOARD only while setpoints already stream: zero velocity until it switches.
                cmd = self._zero()
            else:
                reason = self._refusal_locked()
                if reason is not None:
                    log.warning("setpoint stream stopped: %s", reason)
                    self._cmd, self._yaw_ref_rad = None, None
                    return
                if now - self._cmd_time_s > self.command_timeout_s and not self._cmd_zeroed:
                    log.warning("no new command for %.1f s: streaming zero velocity", now - self._cmd_time_s)
                    self._cmd_zeroed = True
                if self._cmd_zeroed:
                    cmd = self._zero(cmd.seq)
        self._send_setpoint(cmd)

    def _mode_request_tick(self, now: float) -> None:
        with self._lock:
            request, target = self._mode_request, self._target
        if request is None or target is None:
            return
        name, give_up_s = request
        if now > give_up_s:
            log.warning("autopilot did not enter %s within 5 s; giving up the mode switch", name)
            with self._lock:
                self._mode_request = None
            return
        with self._lock:
            self._mode_request_next_s = now + 1.0  # ask again each second until the heartbeat shows it
        _, p2, p3 = encode_mode(target.autopilot, name)
        self._send_command_long(MAV_CMD_DO_SET_MODE, float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(p2), float(p3))

    # ----------------------------------------------------------------- internals: sending

    def _tx(self, write: Callable[[Any], None]) -> bool:
        """One write under the transmit lock; a socket error is logged (rate-limited) and False."""
        conn = self._conn
        if conn is None:
            return False
        with self._tx_lock:
            try:
                write(conn.mav)
            except OSError as exc:
                self.send_failures += 1
                self._warn("send", "MAVLink send failed: %s [%d so far]", exc,
                                  self.send_failures)
                return False
        return True

    def _request_streams(self) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL for what the state is made of, at `stream_rate_hz`."""
        interval_us = float(int(1e6 / self.stream_rate_hz))
        if self._streams_asked_s is None:
            self._streams_asked_s = self._clock()
        # GLOBAL_POSITION_INT: the barometric height that outlives LOCAL_POSITION_NED without GNSS.
        wanted = [MSG_ID_LOCAL_POSITION_NED, MSG_ID_ATTITUDE, MSG_ID_GLOBAL_POSITION_INT]
        if self.alt_source == "rangefinder":
            wanted.append(MSG_ID_DISTANCE_SENSOR)
        for msg_id in wanted:
            self._send_command_long(MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)
        # Health at 1 Hz: what a ground station shows before it offers to arm.
        for msg_id in (MSG_ID_SYS_STATUS, MSG_ID_EKF_STATUS_REPORT):
            self._send_command_long(MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), 1e6)
        # The GNSS fix at 5 Hz (the first sign of a loss; the EKF notices seconds later), and PX4's
        # estimator flags (it has no EKF_STATUS_REPORT).
        self._send_command_long(MAV_CMD_SET_MESSAGE_INTERVAL, float(MSG_ID_GPS_RAW_INT), _GPS_RAW_INTERVAL_US)
        if self._target is not None and self._target.autopilot == "px4":
            self._send_command_long(MAV_CMD_SET_MESSAGE_INTERVAL, float(MSG_ID_ESTIMATOR_STATUS), _GPS_RAW_INTERVAL_US)

    def _send_heartbeat(self) -> None:
        self._tx(lambda mav: mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
                                                MAV_STATE_ACTIVE))

    def _final_setpoint(self, cmd: VelocityCommand) -> tuple[tuple[float, float, float], float]:
        """The command clamped to the limits, with the heading-hold correction added."""
        yaw_rate = cmd.yaw_rate_rad_s
        if self.yaw_control == "rate":
            with self._lock:
                fresh = self._attitude_s is not None and self._clock() - self._attitude_s <= _ATTITUDE_FRESH_S
                yaw = self._attitude_rad[2]
                if yaw_rate != 0.0 or not fresh:
                    # A deliberate turn (or no heading to hold): follow, and hold wherever it ends.
                    self._yaw_ref_rad = None
                else:
                    if self._yaw_ref_rad is None:
                        self._yaw_ref_rad = yaw
                    yaw_rate = self.yaw_hold_gain_per_s * math.remainder(self._yaw_ref_rad - yaw, 2.0 * math.pi)
        vel, yaw_rate, clamped = clamp_setpoint(cmd.vel_body_frd_m_s, yaw_rate, self.limits)
        if clamped:
            self.setpoints_clamped += 1
            self._warn("clamp", "setpoint %s m/s clamped to %s m/s (limits %s)",
                              cmd.vel_body_frd_m_s, tuple(round(v, 2) for v in vel), self.limits)
        return vel, yaw_rate

    def _send_setpoint(self, cmd: VelocityCommand) -> bool:
        target = self._target
        assert target is not None
        with self._lock:
            attitude_flying = self._attitude_flying
        if attitude_flying:
            return self._send_attitude_target(cmd, target)
        (vx, vy, vz), yaw_rate = self._final_setpoint(cmd)
        frame, mask, yaw = STEER_FRAME[target.autopilot], self.type_mask, 0.0
        if self.yaw_control == "autopilot":
            frame, mask, (vx, vy), yaw = self._local_setpoint(vx, vy, yaw_rate)
        time_boot_ms = int(self._clock() * 1000.0) & 0xFFFFFFFF
        ok = self._tx(lambda mav: mav.set_position_target_local_ned_send(
            time_boot_ms, target.system, target.component, frame, mask,
            0.0, 0.0, 0.0, vx, vy, vz, 0.0, 0.0, 0.0, yaw, yaw_rate))
        if ok:
            self.setpoints_sent += 1
        return ok

    def _local_setpoint(self, fwd: float, right: float,
                        yaw_rate: float) -> tuple[int, int, tuple[float, float], float]:
        """yaw_control 'autopilot': (frame, mask, north/east velocity, heading) of a body command.

        The body velocity is rotated by the heading it was meant in (when the command arrived) into
        MAV_FRAME_LOCAL_NED, and the heading held since steering began goes with it as an absolute
        yaw: the autopilot's heading controller holds it, so the camera, and with it the policy's
        body frame, does not turn (WP_YAW_BEHAVIOR would point the nose along the track). A
        deliberate turn (a yaw rate) is followed, and the heading is held wherever it ends.
        """
        with self._lock:
            meant_yaw, yaw = self._cmd_yaw_rad, self._attitude_rad[2]
            if yaw_rate != 0.0:
                self._yaw_ref_rad = None
            elif self._yaw_ref_rad is None:
                self._yaw_ref_rad = yaw
            ref = self._yaw_ref_rad
        north, east = to_ne(fwd, right, meant_yaw)
        if ref is None:
            return MAV_FRAME_LOCAL_NED, TYPE_MASK_VELOCITY_YAW_RATE, (north, east), 0.0
        return MAV_FRAME_LOCAL_NED, TYPE_MASK_VELOCITY_YAW, (north, east), ref

    def _send_attitude_target(self, cmd: VelocityCommand, target: _Target) -> bool:
        """The command flown by our own velocity loop: SET_ATTITUDE_TARGET from the visual velocity."""
        vel, yaw_rate, clamped = clamp_setpoint(cmd.vel_body_frd_m_s, cmd.yaw_rate_rad_s, self.limits)
        if clamped:
            self.setpoints_clamped += 1
        now = self._clock()
        with self._lock:
            loop = self._attitude_loop
            assert loop is not None
            measured = self._odometry.velocity(now)
            glob, local = self._global, self._local
            climb = None
            if local is not None and self._local_s is not None and now - self._local_s <= self._nav.local_stale_s:
                climb = -local[5]
            elif glob is not None and now - glob[2] <= _GLOBAL_FRESH_S:
                climb = -glob[1]
            dt_s = 0.0 if self._attitude_step_s is None else now - self._attitude_step_s
            self._attitude_step_s = now
            out = loop.step(vel, yaw_rate, measured, climb, self._attitude_rad[2], dt_s)
        time_boot_ms = int(now * 1000.0) & 0xFFFFFFFF
        ok = self._tx(lambda mav: mav.set_attitude_target_send(
            time_boot_ms, target.system, target.component, ATTITUDE_TYPE_MASK_ANGLES_THRUST, list(out.q), 0.0, 0.0,
            0.0, out.thrust))
        if ok:
            self.attitude_targets_sent += 1
        return ok

    def _send_landing_target(self, now: float) -> None:
        with self._lock:
            spot, mode, armed = self._landing_target, self._mode, self._armed
        if spot is None or now - spot[3] > _LANDING_TARGET_FRESH_S or mode not in ("LAND", "PRECLAND") or not armed:
            return
        ax, ay, dist, _ = spot
        usec = int(now * 1e6)
        if self._tx(lambda mav: mav.landing_target_send(usec, 0, MAV_FRAME_BODY_FRD, ax, ay, dist, 0.0, 0.0,
                                                         type=LANDING_TARGET_TYPE_VISION_OTHER)):
            self.landing_targets_sent += 1

    def _send_command_long(self, command: int, *params: float) -> None:
        target = self._require_target()
        p = list(params) + [0.0] * (7 - len(params))
        self._tx(lambda mav: mav.command_long_send(target.system, target.component, command, 0, *p))

    def _command_long_wait(self, command: int, *params: float, timeout_s: float) -> int | None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK result (None: no answer in time)."""
        with self._ack_cond:
            self._acks.pop(command, None)
        self._send_command_long(command, *params)
        deadline = time.monotonic() + timeout_s
        with self._ack_cond:
            while command not in self._acks:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._ack_cond.wait(remaining)
            return self._acks.pop(command)

    def _require_target(self) -> _Target:
        if self._target is None or self._conn is None:
            raise NotSteerableError("not connected to an autopilot (call connect() first)")
        return self._target

    def _wait(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Wait for a condition on the state the I/O thread keeps (polled: it changes at stream rate)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if predicate():
                    return True
            if self._stop.wait(0.01):
                return False
        with self._lock:
            return predicate()
