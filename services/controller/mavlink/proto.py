"""MAVLink vocabulary for the adapter: enum values, mode numbers, sample checks, limits, signing keys.

Everything here is pure (no thread, no socket): `vehicle.py` owns the link and calls these to turn
what the autopilot says into validated numbers and what the controller wants into bounded
setpoints. Values follow the MAVLink common and ardupilotmega dialects (the tests compare them
with pymavlink's) and the two autopilots' documented conventions:

- Modes: ArduCopter custom modes GUIDED 4, LAND 9, BRAKE 17, GUIDED_NOGPS 20; PX4 custom_mode =
  (main << 16) | (sub << 24) with OFFBOARD = main 6, AUTO.LAND = main 4 sub 6.
- Speed limits: ArduCopter flies guided velocities within WPNAV_SPEED (default 10 m/s),
  WPNAV_SPEED_UP (2.5 m/s) and WPNAV_SPEED_DN (1.5 m/s); PX4 within MPC_XY_VEL_MAX (12 m/s),
  MPC_Z_VEL_MAX_UP (3 m/s) and MPC_Z_VEL_MAX_DN (1.0-1.5 m/s by release). Our defaults are the
  lower of each pair, so the setpoint we log is the velocity the vehicle really flies.
- Signing: a 32-byte secret; a passphrase becomes SHA-256(passphrase) as MAVProxy's
  `signing setup` does; the timestamp counts 10 us units since 2015-01-01 00:00 UTC.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dovesei.shared.frames import body_frd_to_ned, ned_to_body_frd
from dovesei.shared import validate
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.mavurl import check_serial_device, parse_mavlink_url

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
MAV_FRAME_BODY_FRD = 12
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_SET_EKF_SOURCE_SET = 42007  # ardupilotmega: param1 = EK3 source set 1..3
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_IN_PROGRESS = 5
MAV_SENSOR_ROTATION_PITCH_270 = 25  # a downward-facing distance sensor
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_COMP_ID_CAMERA = 100
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000
LANDING_TARGET_TYPE_VISION_OTHER = 3
MSG_ID_SYS_STATUS = 1
MSG_ID_ATTITUDE = 30
MSG_ID_LOCAL_POSITION_NED = 32
MSG_ID_GLOBAL_POSITION_INT = 33
MSG_ID_GPS_RAW_INT = 24
MSG_ID_VISION_SPEED_ESTIMATE = 103
MSG_ID_DISTANCE_SENSOR = 132
MSG_ID_EKF_STATUS_REPORT = 193
MSG_ID_ESTIMATOR_STATUS = 230
MSG_ID_HOME_POSITION = 242
MSG_ID_ODOMETRY = 331
MSG_ID_VISION_POSITION_DELTA = 11011  # ardupilotmega: body-frame displacement between two frames
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VISION = 2
GPS_FIX_TYPE_3D = 3  # GPS_RAW_INT.fix_type: below this there is no position fix

# EKF_STATUS_REPORT flags ArduCopter needs before it flies guided velocities: attitude, horizontal
# and vertical velocity, relative horizontal position and vertical position (no GNSS needed).
EKF_ATTITUDE, EKF_VELOCITY_HORIZ, EKF_VELOCITY_VERT, EKF_POS_HORIZ_REL = 1, 2, 4, 8
EKF_POS_HORIZ_ABS, EKF_POS_VERT_ABS, EKF_CONST_POS_MODE, EKF_PRED_POS_HORIZ_REL = 16, 32, 128, 256
EKF_UNINITIALIZED = 1024
# PX4's ESTIMATOR_STATUS flags share bits 1..512 with EKF_STATUS_REPORT (ESTIMATOR_STATUS_FLAGS).
EKF_FLAGS_NEEDED = EKF_ATTITUDE | EKF_VELOCITY_HORIZ | EKF_VELOCITY_VERT | EKF_POS_HORIZ_REL | EKF_POS_VERT_ABS

# STATUSTEXT severities (MAV_SEVERITY), by value.
SEVERITY_NAMES = ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING", "NOTICE", "INFO", "DEBUG")

# SET_POSITION_TARGET_LOCAL_NED type masks (bits set = field ignored).
TYPE_MASK_VELOCITY_YAW_RATE = 0x05C7  # use vx, vy, vz and yaw_rate
TYPE_MASK_VELOCITY_ONLY = 0x0DC7  # use vx, vy, vz; the autopilot chooses the heading
TYPE_MASK_VELOCITY_YAW = 0x09C7  # use vx, vy, vz and yaw (an absolute heading in MAV_FRAME_LOCAL_NED)
# SET_ATTITUDE_TARGET: ignore all three body rates (bits 0-2), use the quaternion and thrust.
# ArduCopter takes the rates all or none: a partial mask is discarded and guided re-initialised
# (GCS_Mavlink.cpp handle_message_set_attitude_target), so the heading rides in the quaternion.
ATTITUDE_TYPE_MASK_ANGLES_THRUST = 0x07

# Custom modes of the two autopilots, by the name we use for them.
ARDUCOPTER_MODES = {"GUIDED": 4, "LAND": 9, "BRAKE": 17, "LOITER": 5, "POSHOLD": 16, "RTL": 6,
                    "STABILIZE": 0, "ALT_HOLD": 2, "AUTO": 3, "GUIDED_NOGPS": 20}
PX4_MODES = {"OFFBOARD": (6, 0), "LAND": (4, 6), "PRECLAND": (4, 9), "LOITER": (4, 3), "TAKEOFF": (4, 2), "RTL": (4, 5),
             "MISSION": (4, 4), "POSCTL": (3, 0), "ALTCTL": (2, 0), "MANUAL": (1, 0), "STABILIZED": (7, 0)}
STEER_MODE = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}
STEER_FRAME = {"ardupilot": MAV_FRAME_BODY_OFFSET_NED, "px4": MAV_FRAME_BODY_NED}
AUTOPILOT_KINDS = {MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", MAV_AUTOPILOT_PX4: "px4"}

ALT_SOURCES = ("local", "rangefinder")
# hold: zero velocity; land: the autopilot's LAND mode; precland: LAND while streaming
# LANDING_TARGET at the chosen spot (ArduPilot PLND_TYPE=1, PX4 precision landing); none: stop.
HANDOVERS = ("hold", "land", "precland", "none")
# rate: body-frame velocity + a yaw rate that holds the heading seen from ATTITUDE (our closed
# loop, mask 0x05C7); autopilot: velocity in MAV_FRAME_LOCAL_NED + the held heading as a yaw angle
# (0x09C7), so the autopilot's own heading controller holds it. Velocity alone (0x0DC7) let
# ArduCopter turn the nose by WP_YAW_BEHAVIOR and the body-frame policy ran out of the world.
YAW_CONTROLS = ("rate", "autopilot")

# Plausible ranges of what an autopilot reports; anything outside is a fault, not a flight.
ALT_RANGE_M = (-10.0, 10_000.0)  # a few metres below the local origin (baro noise, a slope)
HORIZONTAL_RANGE_M = 100_000.0  # |north|, |east| from the local origin
SPEED_RANGE_M_S = 100.0  # per component: no multirotor flies 360 km/h
ANGLE_RANGE_RAD = 2.0 * math.pi  # MAVLink says -pi..pi; some stacks send 0..2pi for yaw
RATE_RANGE_RAD_S = 35.0  # about a 2000 deg/s gyro's full scale


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


def check_url(url: Any) -> tuple[str, int]:
    """(device, baud) of a MAVLink URL, by the one parser `dovesei up` uses too (`dovesei.shared.mavurl`)."""
    ep = parse_mavlink_url(url)
    return ep.device, ep.baud


def open_link(url: str, *, source_system: int, source_component: int) -> Any:
    """A pymavlink connection from a URL (see `check_url`); any failure is one VehicleConnectError line."""
    mavutil = load_mavutil()
    ep = parse_mavlink_url(url)
    try:
        check_serial_device(ep)
    except ConfigError as exc:
        raise VehicleConnectError(f"cannot open MAVLink link: {exc}") from None
    try:
        return mavutil.mavlink_connection(ep.device, baud=ep.baud, source_system=source_system,
                                          source_component=source_component, autoreconnect=False)
    except ImportError as exc:  # pymavlink imports pyserial only for a serial port
        raise VehicleConnectError(f"cannot open MAVLink link {url!r}: a serial port needs pyserial "
                                  f"(pip install pyserial; {exc})") from None
    except (OSError, ValueError) as exc:  # pyserial's SerialException is an OSError
        raise VehicleConnectError(f"cannot open MAVLink link {url!r}: {exc}") from None


def ned_to_frd(vel_ned: tuple[float, ...], roll_rad: float, pitch_rad: float,
               yaw_rad: float) -> tuple[float, float, float]:
    """Rotate a NED vector into the body FRD frame (ZYX Euler angles, as MAVLink's ATTITUDE gives)."""
    return ned_to_body_frd(vel_ned, roll_rad, pitch_rad, yaw_rad)


def frd_to_ned(vel_frd: tuple[float, ...], roll_rad: float, pitch_rad: float,
               yaw_rad: float) -> tuple[float, float, float]:
    """Rotate a body FRD vector into NED (the transpose of `ned_to_frd`)."""
    return body_frd_to_ned(vel_frd, roll_rad, pitch_rad, yaw_rad)


# ---------------------------------------------------------------------- incoming samples


def check_local_position(msg: Any) -> tuple[float, float, float, float, float, float]:
    """LOCAL_POSITION_NED as (x, y, z, vx, vy, vz), or ConfigError naming the bad field."""
    x = validate.in_range("LOCAL_POSITION_NED.x", msg.x, -HORIZONTAL_RANGE_M, HORIZONTAL_RANGE_M)
    y = validate.in_range("LOCAL_POSITION_NED.y", msg.y, -HORIZONTAL_RANGE_M, HORIZONTAL_RANGE_M)
    # z is down: the altitude above the origin is -z.
    z = validate.in_range("LOCAL_POSITION_NED.z", msg.z, -ALT_RANGE_M[1], -ALT_RANGE_M[0])
    vel = [validate.in_range(f"LOCAL_POSITION_NED.{n}", getattr(msg, n), -SPEED_RANGE_M_S, SPEED_RANGE_M_S)
           for n in ("vx", "vy", "vz")]
    return (x, y, z, vel[0], vel[1], vel[2])


def check_attitude(msg: Any) -> tuple[float, float, float]:
    """ATTITUDE as (roll, pitch, yaw) with yaw wrapped to [-pi, pi], or ConfigError."""
    angles = [validate.in_range(f"ATTITUDE.{n}", getattr(msg, n), -ANGLE_RANGE_RAD, ANGLE_RANGE_RAD)
              for n in ("roll", "pitch", "yaw")]
    for n in ("rollspeed", "pitchspeed", "yawspeed"):
        validate.in_range(f"ATTITUDE.{n}", getattr(msg, n), -RATE_RANGE_RAD_S, RATE_RANGE_RAD_S)
    return angles[0], angles[1], math.remainder(angles[2], 2.0 * math.pi)


def check_distance_m(msg: Any, roll_rad: float, pitch_rad: float) -> float | None:
    """A downward DISTANCE_SENSOR as metres above ground (tilt-corrected); None when out of range."""
    for n in ("min_distance", "max_distance", "current_distance"):
        validate.in_range(f"DISTANCE_SENSOR.{n}", getattr(msg, n), 0, 65535)
    if not msg.min_distance <= msg.current_distance <= msg.max_distance:
        return None
    # The beam follows the body's down axis: its vertical share is cos(roll) * cos(pitch).
    return msg.current_distance / 100.0 * math.cos(roll_rad) * math.cos(pitch_rad)


# ---------------------------------------------------------------------- outgoing setpoints


@dataclass(frozen=True)
class SpeedLimits:
    """What the adapter ever commands; defaults follow ArduCopter's WPNAV_* (see the docstring)."""

    horizontal_m_s: float = 10.0  # WPNAV_SPEED 1000 cm/s (PX4 MPC_XY_VEL_MAX 12 m/s)
    up_m_s: float = 2.5  # WPNAV_SPEED_UP 250 cm/s (PX4 MPC_Z_VEL_MAX_UP 3 m/s)
    down_m_s: float = 1.5  # WPNAV_SPEED_DN 150 cm/s (PX4 MPC_Z_VEL_MAX_DN 1.0-1.5 m/s)
    yaw_rate_rad_s: float = math.radians(30.0)  # heading corrections stay gentle for the camera

    def __post_init__(self) -> None:
        for name in ("horizontal_m_s", "up_m_s", "down_m_s", "yaw_rate_rad_s"):
            validate.in_range(f"speed limit {name}", getattr(self, name), 0.01, 50.0)


def clamp_setpoint(vel_frd_m_s: tuple[float, float, float], yaw_rate_rad_s: float,
                   limits: SpeedLimits) -> tuple[tuple[float, float, float], float, bool]:
    """The setpoint within `limits`: horizontal speed scaled (direction kept), vertical and yaw rate
    clipped. Returns (velocity, yaw rate, clamped?); a non-finite input raises ConfigError."""
    fwd, right, down = validate.finite_vector("setpoint velocity", vel_frd_m_s, 3)
    yaw_rate = validate.finite("setpoint yaw rate", yaw_rate_rad_s)
    clamped = False
    # Scale by the larger component first: hypot of two 1e308 values would overflow to inf.
    big = max(abs(fwd), abs(right))
    if big > 0:
        speed = big * math.hypot(fwd / big, right / big)
        if speed > limits.horizontal_m_s:
            scale = limits.horizontal_m_s / speed
            fwd, right, clamped = fwd * scale, right * scale, True
    lo, hi = -limits.up_m_s, limits.down_m_s  # FRD: negative down is up
    if not lo <= down <= hi:
        down, clamped = min(max(down, lo), hi), True
    if abs(yaw_rate) > limits.yaw_rate_rad_s:
        yaw_rate, clamped = math.copysign(limits.yaw_rate_rad_s, yaw_rate), True
    return (fwd, right, down), yaw_rate, clamped


# ---------------------------------------------------------------------- signing

SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01 00:00:00 UTC, MAVLink 2's signing epoch


def signing_key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte secret MAVProxy's `signing setup <passphrase>` derives: SHA-256 of the text."""
    if not isinstance(passphrase, str) or not passphrase:
        raise ConfigError("a MAVLink signing passphrase must be a non-empty string")
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def load_signing_key(path: str | Path) -> bytes:
    """A signing key file: exactly 32 raw bytes, 64 hex digits, or one line of passphrase."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"MAVLink signing key {str(p)!r} cannot be read: {exc.strerror}") from None
    if len(raw) == 32:
        return raw
    try:
        text = raw.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise ConfigError(f"MAVLink signing key {str(p)!r}: neither 32 raw bytes, 64 hex digits nor a "
                          "text passphrase") from None
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return signing_key_from_passphrase(text)


def signing_timestamp_now() -> int:
    """Now in signing units (10 us since 2015-01-01 UTC)."""
    return int((max(time.time(), SIGNING_EPOCH_UNIX_S) - SIGNING_EPOCH_UNIX_S) * 100_000)


def read_signing_timestamp(path: str | Path | None) -> int:
    """The persisted timestamp (0 when there is none yet); a corrupt file is an error, not a reset."""
    if path is None or not Path(path).exists():
        return 0
    text = Path(path).read_text(encoding="utf-8").strip()
    if not text.isdigit():
        raise ConfigError(f"MAVLink signing timestamp file {str(path)!r} holds {text[:40]!r}, not an integer")
    return int(text)


def write_signing_timestamp(path: str | Path | None, timestamp: int) -> None:
    """Persist atomically (write then rename), so a crash never leaves a half-written number."""
    if path is None:
        return
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(f"{int(timestamp)}\n", encoding="utf-8")
    os.replace(tmp, p)
