"""MAVLink vehicle adapter: a real autopilot (ArduPilot or PX4) behind the controller's interface.

Data flow (one I/O thread owns the link; callers only read snapshots and hand commands over):

    autopilot --HEARTBEAT, LOCAL_POSITION_NED, ATTITUDE, DISTANCE_SENSOR--> I/O thread
        -> VehicleState (stamp on the 'vehicle' clock from time_boot_ms) -> poll_state()
    send(VelocityCommand) -> checks (armed, GUIDED/OFFBOARD, link alive) -> SET_POSITION_TARGET_LOCAL_NED
        and the I/O thread repeats the newest command at `setpoint_rate_hz` (PX4 leaves OFFBOARD
        when the stream stops; ArduPilot stops a velocity after 3 s without an update)
    I/O thread -> HEARTBEAT at 1 Hz as an onboard controller (MAV_TYPE_ONBOARD_CONTROLLER,
        MAV_AUTOPILOT_INVALID), so the autopilot and a GCS see a live companion

Why one thread and no callbacks into the caller: pymavlink's parser is not thread-safe, and the
controller's loop must never block on the radio. Sends from the caller's thread (send, hold,
handover) share a transmit lock with the I/O thread because pymavlink's sequence counter and
socket writes are not thread-safe either.

Conventions followed exactly (ArduPilot "Copter Commands in Guided Mode", PX4 offboard docs):
- Body-frame velocity: ArduPilot takes MAV_FRAME_BODY_OFFSET_NED (9) for velocities relative to
  the vehicle's heading (its documented frame for this); PX4 takes MAV_FRAME_BODY_NED (8), which
  its receiver rotates by the heading (x forward, y right, z down). Both are heading-level frames:
  roll and pitch do not tilt the commanded vector, which is what a nadir servo wants.
- Type mask: velocity + yaw rate, 0x05C7 (ignore position, acceleration and yaw angle). The
  velocity-only mask 0x0DC7 also ignores yaw rate, and then ArduCopter (4.2+) falls back to
  WP_YAW_BEHAVIOR and turns the nose into the direction of travel, which rotates the camera under
  the controller's feet; `yaw_control="autopilot"` selects 0x0DC7 for users who want that.
- Modes: ArduCopter custom modes GUIDED 4, LAND 9, BRAKE 17; PX4 custom_mode =
  (main << 16) | (sub << 24) with OFFBOARD = main 6, AUTO.LAND = main 4 sub 6. Set with
  MAV_CMD_DO_SET_MODE (176), falling back to the SET_MODE message when it is not acknowledged.
- Streams: MAV_CMD_SET_MESSAGE_INTERVAL (511) for the messages the state needs (LOCAL_POSITION_NED,
  ATTITUDE, and DISTANCE_SENSOR with the rangefinder), repeated until the first state arrives.

Safety: nothing is sent that steers unless the autopilot is armed, in GUIDED (ArduPilot) or
OFFBOARD (PX4) and its heartbeat is fresh. The adapter never arms or takes off unless
`arm_and_takeoff` is called (only `dovesei up --takeoff` does). A mode switch into GUIDED/OFFBOARD
happens only with `allow_mode_switch=True`, and never again once the vehicle has left that mode
after we steered it (a pilot who takes over keeps control). A command not refreshed within
`command_timeout_s` is replaced by zero velocity in the stream: a dead controller never leaves a
non-zero velocity repeating.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.keys import check_vehicle_id
from dovesei.shared.messages import Stamp, VehicleState, VelocityCommand

log = logging.getLogger(__name__)

# MAVLink enum values used here (checked against pymavlink's in the tests).
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_PX4 = 12
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_STATE_ACTIVE = 4
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
MAV_FRAME_BODY_OFFSET_NED = 9
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
MAV_SENSOR_ROTATION_PITCH_270 = 25  # a downward-facing distance sensor
MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_COMP_ID_CAMERA = 100
MSG_ID_ATTITUDE = 30
MSG_ID_LOCAL_POSITION_NED = 32
MSG_ID_GLOBAL_POSITION_INT = 33
MSG_ID_DISTANCE_SENSOR = 132

# SET_POSITION_TARGET_LOCAL_NED type masks (bits set = field ignored).
TYPE_MASK_VELOCITY_YAW_RATE = 0x05C7  # use vx, vy, vz and yaw_rate
TYPE_MASK_VELOCITY_ONLY = 0x0DC7  # use vx, vy, vz; the autopilot chooses the heading

# Custom modes of the two autopilots, by the name we use for them.
ARDUCOPTER_MODES = {"GUIDED": 4, "LAND": 9, "BRAKE": 17, "LOITER": 5, "POSHOLD": 16, "RTL": 6,
                    "STABILIZE": 0, "ALT_HOLD": 2, "AUTO": 3}
PX4_MODES = {"OFFBOARD": (6, 0), "LAND": (4, 6), "LOITER": (4, 3), "TAKEOFF": (4, 2), "RTL": (4, 5),
             "MISSION": (4, 4), "POSCTL": (3, 0), "ALTCTL": (2, 0), "MANUAL": (1, 0), "STABILIZED": (7, 0)}
STEER_MODE = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}
STEER_FRAME = {"ardupilot": MAV_FRAME_BODY_OFFSET_NED, "px4": MAV_FRAME_BODY_NED}

ALT_SOURCES = ("local", "rangefinder")
HANDOVERS = ("hold", "land", "none")
YAW_CONTROLS = ("rate", "autopilot")


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 packs its main mode in bits 16-23 and its sub mode in bits 24-31 of custom_mode."""
    return (main << 16) | (sub << 24)


def mode_name(autopilot: str, custom_mode: int) -> str:
    """Our name for an autopilot's custom mode ('GUIDED', 'OFFBOARD', 'LAND', ...)."""
    if autopilot == "px4":
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        for name, (m, s) in PX4_MODES.items():
            # PX4 reports non-AUTO main modes with sub mode 0; AUTO needs both to match.
            if m == main and (s == sub or m != 4):
                return name
        return f"PX4({main}.{sub})"
    for name, number in ARDUCOPTER_MODES.items():
        if number == custom_mode:
            return name
    return f"MODE({custom_mode})"


def encode_mode(autopilot: str, name: str) -> tuple[int, int, int]:
    """(custom_mode, DO_SET_MODE param2, param3) for one of our mode names."""
    if autopilot == "px4":
        if name not in PX4_MODES:
            raise ConfigError(f"PX4 mode {name!r} unknown; choose one of {sorted(PX4_MODES)}")
        main, sub = PX4_MODES[name]
        return px4_custom_mode(main, sub), main, sub
    if name not in ARDUCOPTER_MODES:
        raise ConfigError(f"ArduCopter mode {name!r} unknown; choose one of {sorted(ARDUCOPTER_MODES)}")
    return ARDUCOPTER_MODES[name], ARDUCOPTER_MODES[name], 0


class MavlinkError(DoveseiError):
    """Something went wrong talking to the autopilot."""


class VehicleConnectError(MavlinkError, ConnectionError):
    """No autopilot heartbeat arrived, or the link could not be opened."""


class NotSteerableError(MavlinkError):
    """The adapter refuses to steer: `reason` says why (mode, disarmed, link lost, read-only)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def load_mavutil() -> Any:
    """pymavlink's mavutil speaking MAVLink 2 (the factory every user of pymavlink here calls).

    mavutil picks its wire protocol from the MAVLINK20 variable when it is imported and again on
    every set_dialect(); we set it here rather than at our import so importing this module has no
    side effect, and re-select the dialect in case something imported mavutil before us.
    """
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        mavutil.set_dialect(mavutil.current_dialect)
    return mavutil


def open_link(url: str, *, source_system: int, source_component: int) -> Any:
    """A pymavlink connection from a URL: udpin:/udpout:/tcp:/tcpin: host:port, or DEVICE[,BAUD]."""
    mavutil = load_mavutil()
    device, baud = url, 115200
    if "," in url and not url.startswith(("udp", "tcp")):
        device, _, baud_text = url.partition(",")
        if not baud_text.isdigit():
            raise ConfigError(f"MAVLink URL {url!r}: the baud rate after ',' must be an integer")
        baud = int(baud_text)
    try:
        return mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                          source_component=source_component, autoreconnect=False)
    except (OSError, ValueError) as exc:
        raise VehicleConnectError(f"cannot open MAVLink link {url!r}: {exc}") from None


AUTOPILOT_KINDS = {MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", MAV_AUTOPILOT_PX4: "px4"}


@dataclass(frozen=True)
class _Target:
    """The autopilot we talk to, learnt from its first heartbeat."""

    system: int
    component: int
    autopilot: str  # "ardupilot" or "px4"


class MavlinkVehicle:
    """A flight controller on a MAVLink link, read as `VehicleState` and steered by body velocities.

    `connect()` opens the link and starts the I/O thread; `poll_state()` returns the newest state
    not yet returned; `send()` steers (or raises `NotSteerableError`); `close()` stops everything.
    With `read_only=True` (the camera source) every steering call raises and nothing but the
    companion heartbeat and stream requests is ever sent.
    """

    def __init__(self, url: str, *, vehicle_id: str = "uav1", alt_source: str = "local",
                 handover: str = "hold", allow_mode_switch: bool = False, heartbeat_timeout_s: float = 3.0,
                 setpoint_rate_hz: float = 20.0, stream_rate_hz: float = 20.0, command_timeout_s: float = 1.0,
                 yaw_control: str = "rate", read_only: bool = False, source_system: int = 255,
                 source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not isinstance(url, str) or not url:
            raise ConfigError(f"MAVLink URL must be a non-empty string, got {url!r}")
        for name, value, choices in (("alt_source", alt_source, ALT_SOURCES), ("handover", handover, HANDOVERS),
                                     ("yaw_control", yaw_control, YAW_CONTROLS)):
            if value not in choices:
                raise ConfigError(f"{name} {value!r}: choose one of {choices}")
        for name, value in (("heartbeat_timeout_s", heartbeat_timeout_s), ("setpoint_rate_hz", setpoint_rate_hz),
                            ("stream_rate_hz", stream_rate_hz), ("command_timeout_s", command_timeout_s)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number, got {value!r}")
        if setpoint_rate_hz < 10.0:
            # PX4 drops out of OFFBOARD below 2 Hz; we keep a wide margin as the issue requires.
            raise ConfigError(f"setpoint_rate_hz {setpoint_rate_hz} is below the 10 Hz minimum")
        for name, value in (("source_system", source_system), ("source_component", source_component)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 255:
                raise ConfigError(f"{name} must be an integer in 1..255, got {value!r}")
        self.url, self.vehicle_id = url, check_vehicle_id(vehicle_id)
        self.alt_source, self.handover_action, self.allow_mode_switch = alt_source, handover, allow_mode_switch
        self.heartbeat_timeout_s, self.command_timeout_s = float(heartbeat_timeout_s), float(command_timeout_s)
        self.setpoint_period_s, self.stream_rate_hz = 1.0 / setpoint_rate_hz, float(stream_rate_hz)
        self.type_mask = TYPE_MASK_VELOCITY_YAW_RATE if yaw_control == "rate" else TYPE_MASK_VELOCITY_ONLY
        self.read_only = read_only
        self.source_system, self.source_component = source_system, source_component
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
        self._attitude_rad = (0.0, 0.0, 0.0)
        self._local: tuple[float, float, float, float, float, float] | None = None  # x y z vx vy vz NED
        self._range_m: float | None = None
        self._state: VehicleState | None = None
        self._state_seq, self._returned_seq = -1, -1
        self._acks: dict[int, int] = {}
        self._cmd: VelocityCommand | None = None  # newest command to stream (None: stream nothing)
        self._cmd_time_s = 0.0
        self._cmd_zeroed = False
        self._steered = False  # we have streamed in GUIDED/OFFBOARD at least once
        self._mode_request: tuple[str, float] | None = None  # (mode name, give-up time) in progress
        self._mode_request_next_s = 0.0  # when the I/O thread sends the next DO_SET_MODE for it
        self._unsupported_seen: set[int] = set()  # MAV_AUTOPILOT values of heartbeats we cannot fly
        self._next_setpoint_s = 0.0
        self.setpoints_sent = 0  # counters for tests and operators' logs
        self.messages_received = 0

    # ----------------------------------------------------------------- life cycle

    def connect(self, timeout_s: float = 10.0) -> None:
        """Open the link, wait for the autopilot's heartbeat, request the streams the state needs."""
        if self._conn is not None:
            raise MavlinkError("connect() called twice")
        self._conn = open_link(self.url, source_system=self.source_system, source_component=self.source_component)
        self._thread = threading.Thread(target=self._io_loop, name=f"mavlink-{self.vehicle_id}", daemon=True)
        self._thread.start()
        if not self._identified.wait(timeout_s):
            self.close()
            seen = (f"; heartbeats seen only from unsupported autopilots (MAV_AUTOPILOT "
                    f"{sorted(self._unsupported_seen)}), only ArduPilot and PX4 are supported"
                    if self._unsupported_seen else "")
            raise VehicleConnectError(f"no ArduPilot/PX4 heartbeat on {self.url!r} within {timeout_s:.1f} s{seen} "
                                      "(for udpin the autopilot must send to us; for udpout we send first)")
        target = self._target
        assert target is not None
        log.info("connected to %s on %s (system %d component %d), mode %s, %s", target.autopilot, self.url,
                 target.system, target.component, self.mode, "armed" if self.armed else "disarmed")

    def close(self) -> None:
        """Stop the I/O thread and close the link (the autopilot's own failsafes take over)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._conn is not None:
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
        """Why the link counts as lost (heartbeat timeout), or None while it is alive."""
        with self._lock:
            return self._lost_reason

    def poll_state(self) -> VehicleState | None:
        """The newest state not yet returned; None if nothing new or the link is lost (see lost_reason)."""
        with self._lock:
            if self._lost_reason is not None or self._state is None or self._state_seq == self._returned_seq:
                return None
            self._returned_seq = self._state_seq
            return self._state

    # ----------------------------------------------------------------- steering

    def send(self, cmd: VelocityCommand) -> None:
        """Steer with a body-frame FRD velocity and yaw rate, or raise NotSteerableError (nothing sent)."""
        if not isinstance(cmd, VelocityCommand):
            raise TypeError(f"send() takes a VelocityCommand, got {type(cmd).__name__}")
        with self._lock:
            reason = self._refusal_locked()
            if reason is None:
                self._cmd, self._cmd_time_s, self._cmd_zeroed = cmd, self._clock(), False
                self._steered = True
            else:
                reason = self._maybe_request_mode_locked(reason)
        if reason is not None:
            raise NotSteerableError(reason)
        # Out at once (the stream only fills the gaps); the stream's next repeat is a period away.
        self._send_setpoint(cmd)
        with self._lock:
            self._next_setpoint_s = self._clock() + self.setpoint_period_s

    def hold(self) -> bool:
        """Command zero velocity (the autopilot holds position); False (and a log) if not steerable."""
        zero = VelocityCommand(vehicle_id=self.vehicle_id, seq=-1, stamp=Stamp(0.0, "vehicle"),
                               vel_body_frd_m_s=(0.0, 0.0, 0.0))
        try:
            self.send(zero)
        except NotSteerableError as exc:
            log.warning("hold not sent: %s", exc.reason)
            return False
        return True

    def handover(self) -> bool:
        """The configured action at the goal altitude: 'hold', 'land' (LAND mode) or 'none'."""
        if self.handover_action == "none":
            # The user's own system takes over from here: stop streaming, or our setpoints
            # (zero velocity once the controller goes quiet) would fight it.
            with self._lock:
                self._cmd = None
            log.info("handover: no action configured (handover='none'); setpoint stream stopped")
            return True
        if self.handover_action == "hold":
            return self.hold()
        if self.read_only:
            raise NotSteerableError("read-only MAVLink adapter: handover refused")
        with self._lock:
            self._cmd = None  # the autopilot lands on its own now; our setpoints would fight it
        ok = self.set_mode("LAND")
        log.info("handover: LAND mode %s", "confirmed" if ok else "NOT confirmed by the autopilot")
        return ok

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
            with self._tx_lock:
                self._conn.mav.set_mode_send(target.system, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom)
        elif result != MAV_RESULT_ACCEPTED:
            log.warning("autopilot refused mode %s (MAV_RESULT %d)", name, result)
            return False
        return self._wait(lambda: self._mode == name, timeout_s)

    def arm_and_takeoff(self, alt_m: float, timeout_s: float = 60.0) -> None:
        """ArduPilot only, and only when the user asked (`dovesei up --takeoff`): GUIDED, arm, climb.

        PX4 is refused: its takeoff goes through AUTO.TAKEOFF and a switch to OFFBOARD with a
        setpoint stream already running, a sequence we have not flown; take off with the ground
        station and switch to OFFBOARD, then start dovesei.
        """
        if self.read_only:
            raise NotSteerableError("read-only MAVLink adapter: arm_and_takeoff refused")
        if not (isinstance(alt_m, (int, float)) and math.isfinite(alt_m) and 1.0 <= alt_m <= 500.0):
            raise ConfigError(f"takeoff altitude must be within 1..500 m, got {alt_m!r}")
        target = self._require_target()
        if target.autopilot != "ardupilot":
            raise NotSteerableError("arm_and_takeoff supports ArduPilot only: with PX4, take off from the ground "
                                    "station, then switch to OFFBOARD yourself or let dovesei do it "
                                    "(allow_mode_switch) once airborne")
        if not self.set_mode("GUIDED"):
            raise NotSteerableError(f"the autopilot did not enter GUIDED for takeoff (mode {self.mode})")
        log.info("arming (requested explicitly)")
        result = self._command_long_wait(MAV_CMD_COMPONENT_ARM_DISARM, 1.0, timeout_s=3.0)
        if result != MAV_RESULT_ACCEPTED or not self._wait(lambda: self._armed, 5.0):
            raise NotSteerableError(f"the autopilot refused to arm (MAV_RESULT {result}); check its pre-arm messages")
        result = self._command_long_wait(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, float(alt_m), timeout_s=3.0)
        if result != MAV_RESULT_ACCEPTED:
            raise NotSteerableError(f"the autopilot refused NAV_TAKEOFF to {alt_m} m (MAV_RESULT {result})")

        def high_enough() -> bool:
            return self._state is not None and self._state.alt_agl_m >= 0.95 * alt_m

        if not self._wait(high_enough, timeout_s):
            raise NotSteerableError(f"takeoff to {alt_m} m did not complete within {timeout_s:.0f} s")
        log.info("takeoff complete at %.1f m", self._state.alt_agl_m if self._state else float("nan"))

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
        wanted = STEER_MODE[self._target.autopilot]
        if self._mode != wanted:
            return f"the autopilot is in {self._mode}, not {wanted}"
        return None

    def _maybe_request_mode_locked(self, reason: str) -> str:
        """With allow_mode_switch, start a switch into GUIDED/OFFBOARD; returns the refusal text."""
        target = self._target
        if (not self.allow_mode_switch or target is None or self.read_only or self._lost_reason is not None
                or not self._armed):
            return reason
        wanted = STEER_MODE[target.autopilot]
        if self._steered:
            # We flew it in that mode and someone switched away: a pilot's takeover wins, always.
            return f"{reason}; not switching back after a mode change away from {wanted} (pilot override)"
        if self._mode_request is None:
            now = self._clock()
            self._mode_request = (wanted, now + 5.0)
            # PX4 refuses OFFBOARD until setpoints stream: let the zero pre-stream run first.
            self._mode_request_next_s = now + (0.3 if target.autopilot == "px4" else 0.0)
            log.info("requesting mode %s (allow_mode_switch)", wanted)
        return f"{reason}; switch to {wanted} requested"

    # ----------------------------------------------------------------- internals: I/O thread

    def _io_loop(self) -> None:
        next_hb_s = self._clock()  # send at once: an udpout peer learns our address from it
        next_stream_request_s = 0.0
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
            with self._lock:
                wake_s = min(next_hb_s, self._next_setpoint_s)
            self._conn.select(max(0.0, min(wake_s - self._clock(), 0.05)))
            self._drain()

    def _drain(self) -> None:
        """Parse every message waiting on the link (the I/O thread is the only reader)."""
        for _ in range(1000):  # bound the burst so the stream deadlines still get served
            try:
                msg = self._conn.recv_msg()
            except OSError as exc:
                log.warning("MAVLink receive failed: %s", exc)
                return
            if msg is None:
                return
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        self.messages_received += 1
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, src_sys, src_comp)
            return
        target = self._target
        if target is None or src_sys != target.system:
            return  # another vehicle on a shared link, or data before we know who we talk to
        if kind == "DISTANCE_SENSOR":
            self._on_distance(msg)  # any component of the vehicle: a rangefinder may speak for itself
            return
        if src_comp != target.component:
            return  # e.g. a vision component's own estimate: the autopilot's is the one it flies on
        if kind == "LOCAL_POSITION_NED":
            with self._lock:
                self._local = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
            if self.alt_source == "local":
                self._publish_state(msg.time_boot_ms, -msg.z)
        elif kind == "ATTITUDE":
            with self._lock:
                self._attitude_rad = (msg.roll, msg.pitch, msg.yaw)
        elif kind == "COMMAND_ACK":
            with self._ack_cond:
                self._acks[msg.command] = msg.result
                self._ack_cond.notify_all()
            if msg.result not in (MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS):
                log.warning("autopilot answered command %d with MAV_RESULT %d", msg.command, msg.result)

    def _on_heartbeat(self, msg: Any, src_sys: int, src_comp: int) -> None:
        if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER):
            return  # ground stations and companions (including a second dovesei process)
        if self._target is None:
            kind = AUTOPILOT_KINDS.get(msg.autopilot)
            if kind is None:
                self._unsupported_seen.add(int(msg.autopilot))  # a gimbal, a camera, another stack
                return
            self._target = _Target(src_sys, src_comp, kind)
        target = self._target
        if (src_sys, src_comp) != (target.system, target.component):
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
            if self._lost_reason is not None:
                log.info("autopilot heartbeat back; steering resumes only with a new command")
                self._lost_reason = None
        self._identified.set()

    def _on_distance(self, msg: Any) -> None:
        if msg.orientation != MAV_SENSOR_ROTATION_PITCH_270:
            return  # only a downward sensor measures height above ground
        in_range = msg.min_distance <= msg.current_distance <= msg.max_distance
        with self._lock:
            roll, pitch, _ = self._attitude_rad
            # The beam follows the body's down axis: its vertical share is cos(roll) * cos(pitch).
            self._range_m = msg.current_distance / 100.0 * math.cos(roll) * math.cos(pitch) if in_range else None
            range_m = self._range_m
        if self.alt_source == "rangefinder":
            if range_m is None:
                # No state at all: a made-up altitude is worse than the controller's stale-state hold.
                log.debug("rangefinder out of range (%d cm outside %d..%d cm)", msg.current_distance,
                          msg.min_distance, msg.max_distance)
                return
            self._publish_state(msg.time_boot_ms, range_m)

    def _publish_state(self, time_boot_ms: int, alt_agl_m: float) -> None:
        with self._lock:
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
                prestream = (self._mode_request is not None and self._target is not None
                             and self._target.autopilot == "px4" and self._lost_reason is None)
                if not prestream:
                    return
                # PX4 accepts OFFBOARD only while setpoints already stream: zero velocity until it switches.
                cmd = VelocityCommand(vehicle_id=self.vehicle_id, seq=-1, stamp=Stamp(0.0, "vehicle"),
                                      vel_body_frd_m_s=(0.0, 0.0, 0.0))
            else:
                reason = self._refusal_locked()
                if reason is not None:
                    log.warning("setpoint stream stopped: %s", reason)
                    self._cmd = None
                    return
                if now - self._cmd_time_s > self.command_timeout_s and not self._cmd_zeroed:
                    log.warning("no new command for %.1f s: streaming zero velocity", now - self._cmd_time_s)
                    self._cmd_zeroed = True
                if self._cmd_zeroed:
                    cmd = VelocityCommand(vehicle_id=self.vehicle_id, seq=cmd.seq, stamp=cmd.stamp,
                                          vel_body_frd_m_s=(0.0, 0.0, 0.0))
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

    def _request_streams(self) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL for what the state is made of, at `stream_rate_hz`."""
        interval_us = float(int(1e6 / self.stream_rate_hz))
        wanted = [MSG_ID_LOCAL_POSITION_NED, MSG_ID_ATTITUDE]
        if self.alt_source == "rangefinder":
            wanted.append(MSG_ID_DISTANCE_SENSOR)
        for msg_id in wanted:
            self._send_command_long(MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)

    def _send_heartbeat(self) -> None:
        with self._tx_lock:
            self._conn.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)

    def _send_setpoint(self, cmd: VelocityCommand) -> None:
        target = self._target
        assert target is not None
        vx, vy, vz = cmd.vel_body_frd_m_s
        time_boot_ms = int(self._clock() * 1000.0) & 0xFFFFFFFF
        with self._tx_lock:
            self._conn.mav.set_position_target_local_ned_send(
                time_boot_ms, target.system, target.component, STEER_FRAME[target.autopilot], self.type_mask,
                0.0, 0.0, 0.0, vx, vy, vz, 0.0, 0.0, 0.0, 0.0, cmd.yaw_rate_rad_s)
            self.setpoints_sent += 1

    def _send_command_long(self, command: int, *params: float) -> None:
        target = self._require_target()
        p = list(params) + [0.0] * (7 - len(params))
        with self._tx_lock:
            self._conn.mav.command_long_send(target.system, target.component, command, 0, *p)

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


def ned_to_frd(vel_ned: tuple[float, ...], roll_rad: float, pitch_rad: float,
               yaw_rad: float) -> tuple[float, float, float]:
    """Rotate a NED vector into the body FRD frame (ZYX Euler angles, as MAVLink's ATTITUDE gives)."""
    vn, ve, vd = (float(v) for v in vel_ned)
    cr, sr, cp, sp = math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    # Rows of R_body<-ned = (R_ned<-body)^T for R = Rz(yaw) Ry(pitch) Rx(roll).
    f = cp * cy * vn + cp * sy * ve - sp * vd
    r = (sr * sp * cy - cr * sy) * vn + (sr * sp * sy + cr * cy) * ve + sr * cp * vd
    d = (cr * sp * cy + sr * sy) * vn + (cr * sp * sy - sr * cy) * ve + cr * cp * vd
    return (f, r, d)
