"""A fake ArduCopter or PX4 autopilot on a MAVLink link, for tests and end-to-end runs without SITL.

It plays the autopilot's side of what `dovesei.controller.mavlink` relies on, with each
personality's documented rules, so the adapter meets the edges a real vehicle has:

    peer --SET_POSITION_TARGET_LOCAL_NED--> recorded; when armed in GUIDED/OFFBOARD flown within the
                                            personality's speed caps (body velocity rotated by
                                            the heading, integrated into a NED position)
    peer --COMMAND_LONG / SET_MODE--------> COMMAND_ACK; modes, arming, takeoff, message intervals,
                                            REQUEST_MESSAGE(HOME_POSITION)
    peer --LANDING_TARGET------------------> recorded; in LAND/PRECLAND the precision-landing estimator
                                            (below) takes it and, once initialised, lands on it
    fake --HEARTBEAT (mode, armed)--------> peer, at `heartbeat_hz` (stoppable: heartbeat-loss tests)
    fake --LOCAL_POSITION_NED, ATTITUDE, DISTANCE_SENSOR, GLOBAL_POSITION_INT, SYS_STATUS,
           EKF_STATUS_REPORT--> peer, only at the intervals asked for with SET_MESSAGE_INTERVAL
    fake --STATUSTEXT--> boot banner, pre-arm failures every `statustext_period_s` while booting,
                         arming refusals

Personalities (`flavour`):

- Boot: for `boot_s` (40 s by default, what ArduCopter 4.6 SITL needed; tests pass ~1 s) the
  pre-arm bit of SYS_STATUS is unhealthy, EKF flags come up one by one (attitude, velocities,
  positions), home appears at the end, and ARM is refused with the reasons as STATUSTEXT
  (ArduPilot "PreArm: ..."/MAV_RESULT_FAILED; PX4 "Preflight Fail: ..."/MAV_RESULT_DENIED).
  A fake created armed (in the air) has booted long ago.
- Speed caps: ArduPilot WPNAV_SPEED 10 m/s, WPNAV_SPEED_UP 2.5, WPNAV_SPEED_DN 1.5; PX4
  MPC_XY_VEL_MAX 12, MPC_Z_VEL_MAX_UP 3, MPC_Z_VEL_MAX_DN 1.5.
- ArduPilot flies a guided velocity not refreshed for GUID_TIMEOUT (`guid_timeout_s`, 3 s by
  default) as if it were, then stops and holds: a controller killed at 10 m/s coasts ~30 m. The
  GCS failsafe (`fs_gcs_enable` "land", FS_GCS_ENABLE 5) switches to LAND when no heartbeat from
  SYSID_MYGCS (255) came for FS_GCS_TIMEOUT (`fs_gcs_timeout_s`, 5 s) after one was heard. PX4 accepts
  OFFBOARD (and arming in it) only while setpoints stream and falls back to LOITER when they stop
  for COM_OF_LOSS_T (1 s).
- `heading_drift_rad_s`: the heading wanders while airborne (the 5-23 degrees seen on ArduCopter).
- Heading in GUIDED (ArduPilot): a setpoint with a yaw flies to that heading (absolute in
  LOCAL_NED, relative to the heading at arrival in the body frames); one with a yaw rate turns at
  it; one with neither turns the nose towards the direction of travel (WP_YAW_BEHAVIOR 2, the
  default, while moving faster than 0.5 m/s), at most ATC_SLEW_YAW's 60 deg/s.
- Precision landing (`precland`, ArduPilot's PLND_ENABLED with PLND_TYPE 1, AC_PrecLand's
  estimator): the first LANDING_TARGET in LAND says "PrecLand: Target Found"; the estimator
  initialises only when targets keep coming at least every 0.5 s for 2 s ("PrecLand: Init
  Complete"), else "PrecLand: Init Failed"; an initialised target not updated for 2 s is "PrecLand:
  Target Lost". Only an acquired target is flown to (and no descent while it is more than
  PLND_XY_DIST_MAX 2.5 m away); otherwise LAND descends straight down, blind.
- VisOdom pre-arm (ArduPilot, `FakeEkf(viso_arming_check=True)`): while disarmed and no vision
  message came within 300 ms, "PreArm: VisOdom: not healthy" is among the pre-arm failures (the
  periodic report, SYS_STATUS's pre-arm bit, ARM refused with "Arm: VisOdom: not healthy").
- `arm_refusals`: ARMs refused after boot by checks that run only at arming (a real case: the
  pre-arm bit says healthy, ARM still fails once).
- GNSS loss (ArduPilot, `lose_gnss()`; the estimator in `fake_ekf.FakeEkf`): GPS_RAW_INT loses its
  fix, the EKF coasts then drops to constant-position mode (LOCAL_POSITION_NED stops, the flags
  say so), modes that need a position (GUIDED, LOITER, ...) are refused ("Mode change failed:
  GUIDED requires position") and the EKF failsafe switches them to FS_EKF_ACTION (LAND by
  default) with "EKF variance"; the vehicle then drifts (drag, no position hold). GUIDED_NOGPS
  (mode 20) flies SET_ATTITUDE_TARGET only (rates all ignored or all given, else discarded;
  thrust read as a climb rate, 0.5 holds; level and hold after GUID_TIMEOUT); velocity setpoints
  do nothing there. VISION_SPEED_ESTIMATE is fused once MAV_CMD_SET_EKF_SOURCE_SET selects the
  set configured with VELXY = ExternalNav: the EKF keeps velocity and a relative position.
  PX4 (`lose_gnss()` too): ESTIMATOR_STATUS and GPS_RAW_INT follow the same estimator, the local
  position stops, OFFBOARD flies SET_ATTITUDE_TARGET with the thrust as collective thrust (hover
  0.5) and counts it as the offboard stream; PX4's failsafes on a position loss are not modelled.
- `gcs_set_mode()`: a second ground station switching modes; `inject()`: one hand-made message
  (NaN, out of range) in the fake's own stream; `signing_key`: MAVLink 2 signing, unsigned and
  wrong-key frames rejected and counted.

Setpoints in any frame other than the flavour's body frame (or LOCAL_NED) are recorded but not
flown. One thread owns the socket; `stop()` joins it and closes the link. `main()` runs one as a
process (`python -m dovesei.testing.fake_autopilot --url udpin:127.0.0.1:14550`).
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dovesei.controller.mavlink import proto as mv
from dovesei.controller.gnss_denied import GRAVITY_M_S2, quaternion_to_euler
from dovesei.testing import fake_ekf
from dovesei.testing.fake_ekf import FS_EKF_ACTIONS, FakeEkf
from dovesei.shared.lifecycle import install_stop_handlers

log = logging.getLogger(__name__)

FLAVOURS = ("ardupilot", "px4")
MAV_TYPE_QUADROTOR = 2
MAV_STATE_STANDBY = 3
MAV_MODE_FLAG_STABILIZE_ENABLED = 16
MAV_MODE_FLAG_GUIDED_ENABLED = 8
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4
MAV_SEVERITY_CRITICAL, MAV_SEVERITY_WARNING, MAV_SEVERITY_INFO = 2, 4, 6
PX4_OFFBOARD_LOSS_S = 1.0  # PX4's COM_OF_LOSS_T default
ARDUPILOT_GUIDED_VEL_TIMEOUT_S = 3.0  # ArduCopter's GUID_TIMEOUT default
SYSID_MYGCS = 255  # ArduCopter's default: heartbeats from this system keep the GCS failsafe away
LAND_RATE_M_S = 1.0
PRECLAND_GAIN_PER_S, PRECLAND_MAX_M_S = 0.5, 1.0
# AC_PrecLand.cpp (ArduPilot 4.6): EKF_INIT_TIME_MS, EKF_INIT_SENSOR_MIN_UPDATE_MS,
# LANDING_TARGET_TIMEOUT_MS; PLND_XY_DIST_MAX's default.
PRECLAND_INIT_S, PRECLAND_INIT_GAP_S, PRECLAND_TIMEOUT_S, PRECLAND_XY_DIST_MAX_M = 2.0, 0.5, 2.0, 2.5
# ArduCopter's heading in GUIDED: ATC_SLEW_YAW 6000 cdeg/s; a proportional turn towards the target.
YAW_SLEW_RAD_S, YAW_GAIN_PER_S, WP_YAW_MIN_SPEED_M_S = math.radians(60.0), 2.0, 0.5
DEFAULT_BOOT_S = 40.0
# ArduCopter modes whose requires_GPS() is true (ArduCopter/mode.h): refused without a position.
ARDUPILOT_GPS_MODES = ("GUIDED", "LOITER", "POSHOLD", "RTL", "AUTO", "BRAKE")
DRAG_PER_S = 0.3  # without position hold the horizontal velocity decays this fast (a few seconds)
PX4_HOVER_THRUST = 0.5  # MPC_THR_HOVER default
ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE = 64
ORIGIN_LAT_DEG, ORIGIN_LON_DEG = 47.3977, 8.5456  # any fixed point; only GLOBAL_POSITION_INT uses it


@dataclass(frozen=True)
class Personality:
    """What differs between the two autopilots, as far as the adapter can tell."""

    horizontal_cap_m_s: float
    up_cap_m_s: float
    down_cap_m_s: float
    arm_refused_result: int
    banner: str
    # (fraction of boot until which it fails, STATUSTEXT) in the autopilot's own words.
    prearm_failures: tuple[tuple[float, str], ...]


PERSONALITIES = {
    "ardupilot": Personality(10.0, 2.5, 1.5, MAV_RESULT_FAILED, "ArduCopter V4.6.0 (fake)", (
        (0.25, "PreArm: EKF attitude is bad"),
        (0.5, "PreArm: Need Alt Estimate"),
        (1.0, "PreArm: AHRS: waiting for home"),
    )),
    "px4": Personality(12.0, 3.0, 1.5, MAV_RESULT_DENIED, "PX4 v1.15.0 (fake)", (
        (0.5, "Preflight Fail: ekf2 missing data"),
        (1.0, "Preflight Fail: Attitude estimate not valid"),
    )),
}


@dataclass(frozen=True)
class ReceivedSetpoint:
    """One SET_POSITION_TARGET_LOCAL_NED as the fake received it (recv_s on time.monotonic)."""

    recv_s: float
    source_system: int
    source_component: int
    target_system: int
    target_component: int
    frame: int
    type_mask: int
    vel_m_s: tuple[float, float, float]  # as sent (FRD for the body frames)
    yaw_rate_rad_s: float
    yaw_rad: float = 0.0  # as sent: absolute in LOCAL_NED, relative to the heading in the body frames
    yaw_target_rad: float = 0.0  # the heading it asks for, made absolute when it arrived


@dataclass(frozen=True)
class ReceivedAttitudeTarget:
    """One SET_ATTITUDE_TARGET (recv_s on time.monotonic); `accepted`: flown (GUIDED_NOGPS, valid)."""

    recv_s: float
    type_mask: int
    q: tuple[float, float, float, float]
    thrust: float
    accepted: bool


@dataclass(frozen=True)
class ReceivedVisionSpeed:
    """One VISION_SPEED_ESTIMATE (NED m/s), VISION_POSITION_DELTA (body FRD, delta / dt; `covariance`
    holds its confidence) or PX4 ODOMETRY velocity (body FRD) as received."""

    recv_s: float
    usec: int
    vel_m_s: tuple[float, float, float]
    covariance: tuple[float, ...]
    kind: str  # "VISION_SPEED_ESTIMATE", "VISION_POSITION_DELTA" or "ODOMETRY"


@dataclass(frozen=True)
class ReceivedHeartbeat:
    recv_s: float
    system: int
    component: int
    mav_type: int
    autopilot: int


@dataclass(frozen=True)
class ReceivedCommand:
    recv_s: float
    command: int
    params: tuple[float, ...]
    result: int


@dataclass(frozen=True)
class ReceivedLandingTarget:
    recv_s: float
    frame: int
    angle_x_rad: float
    angle_y_rad: float
    distance_m: float


class FakeAutopilot:
    """A simulated multirotor autopilot speaking MAVLink 2 on `url` (default: listens, udpin)."""

    def __init__(self, url: str, *, flavour: str = "ardupilot", mode: str | None = None, armed: bool = True,
                 alt_m: float = 50.0, yaw_rad: float = 0.0, terrain_height_m: float = 0.0,
                 rangefinder_max_m: float = 40.0, heartbeat_hz: float = 1.0, physics_hz: float = 50.0,
                 offboard_loss_s: float = PX4_OFFBOARD_LOSS_S, system: int = 1, component: int = 1,
                 boot_s: float = DEFAULT_BOOT_S, heading_drift_rad_s: float = 0.0,
                 statustext_period_s: float = 2.0, signing_key: bytes | None = None, arm_refusals: int = 0,
                 precland: bool = True, ekf: FakeEkf | None = None,
                 guid_timeout_s: float = ARDUPILOT_GUIDED_VEL_TIMEOUT_S, fs_gcs_enable: str | None = None,
                 fs_gcs_timeout_s: float = 5.0) -> None:
        if flavour not in FLAVOURS:
            raise ValueError(f"flavour {flavour!r}: choose one of {FLAVOURS}")
        self.url, self.flavour, self.personality = url, flavour, PERSONALITIES[flavour]
        self._system, self._component = system, component
        self._heartbeat_period_s, self._physics_period_s = 1.0 / heartbeat_hz, 1.0 / physics_hz
        self._rangefinder_max_m = rangefinder_max_m
        self._offboard_loss_s = offboard_loss_s  # PX4 only; also the grace for starting in OFFBOARD
        self._signing_key = signing_key
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._conn: Any = None
        self._t0 = time.monotonic()
        self._custom_mode = mv.encode_mode(flavour, mode or ("LOITER"))[0]
        self._armed = armed
        # A vehicle that starts armed (in the air) booted long ago.
        self._boot_s = 0.0 if armed else max(0.0, float(boot_s))
        self._home_sent = False
        self._statustext_period_s = statustext_period_s
        self._arm_refusals = arm_refusals  # ARMs refused after boot (checks run only at arming)
        self._pos_ned_m = [0.0, 0.0, -float(alt_m)]  # the local origin is on the ground below the start
        self._vel_ned_m_s = [0.0, 0.0, 0.0]
        self._yaw_rad, self._yaw_rate_rad_s = float(yaw_rad), 0.0
        self._heading_drift_rad_s = float(heading_drift_rad_s)
        self.terrain_height_m = float(terrain_height_m)  # ground under the vehicle above the local origin
        self._takeoff_alt_m: float | None = None
        self._heartbeats_on = True
        self._intervals_s: dict[int, float] = {}
        self._next_send_s: dict[int, float] = {}
        self._last_setpoint: ReceivedSetpoint | None = None
        self._precland = precland
        self._guid_timeout_s = float(guid_timeout_s)
        if fs_gcs_enable not in (None, "land"):
            raise ValueError(f"fs_gcs_enable {fs_gcs_enable!r}: None (FS_GCS_ENABLE 0) or 'land' (5)")
        self._fs_gcs_land, self._fs_gcs_timeout_s = fs_gcs_enable == "land", float(fs_gcs_timeout_s)
        self._gcs_seen_s: float | None = None  # newest heartbeat from SYSID_MYGCS (time.monotonic)
        self._gcs_failsafe = False
        self._plnd_state = "none"  # none, init (Target Found, filling) or acquired (Init Complete)
        self._plnd_init_s = self._plnd_last_s = 0.0  # time.monotonic of the init and of the newest target
        self._plnd_target_ne_m: tuple[float, float] | None = None  # where the newest target puts it (NE)
        self.touchdown_ne_m: tuple[float, float] | None = None  # where a LAND ended on the ground
        self.touchdown_s: float | None = None  # when (time.monotonic)
        self.precland_targets_ne: list[tuple[float, float, float]] = []  # (recv_s, north, east) per measurement
        self._outbox: list[Callable[[Any], None]] = []  # sends queued for the fake's own thread
        self._started_s = time.monotonic()
        self.setpoints: list[ReceivedSetpoint] = []
        self.heartbeats: list[ReceivedHeartbeat] = []
        self.commands: list[ReceivedCommand] = []
        self.landing_targets: list[ReceivedLandingTarget] = []
        self.set_mode_messages: list[tuple[float, int, int]] = []  # (recv_s, base_mode, custom_mode)
        self.statustexts_sent: list[tuple[int, str]] = []
        self.peer_seen = threading.Event()
        self.ekf = ekf if ekf is not None else FakeEkf()
        self._roll_rad = self._pitch_rad = 0.0
        self._last_attitude: ReceivedAttitudeTarget | None = None
        self.attitude_targets: list[ReceivedAttitudeTarget] = []
        self.vision_speeds: list[ReceivedVisionSpeed] = []

    # ----------------------------------------------------------------- control from the test

    def start(self) -> FakeAutopilot:
        self._conn = mv.open_link(self.url, source_system=self._system, source_component=self._component)
        if self._signing_key is not None:
            # As a signing autopilot channel: sign everything, accept only frames signed with the key.
            self._conn.setup_signing(self._signing_key, sign_outgoing=True, allow_unsigned_callback=None,
                                     link_id=1)
        self._queue_statustext(MAV_SEVERITY_INFO, self.personality.banner)
        self._thread = threading.Thread(target=self._loop, name="fake-autopilot", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> FakeAutopilot:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def set_mode(self, name: str) -> None:
        """What a pilot's mode switch does."""
        with self._lock:
            self._custom_mode = mv.encode_mode(self.flavour, name)[0]

    def gcs_set_mode(self, name: str, gcs_system: int = 254) -> None:
        """A second ground station's DO_SET_MODE (recorded as a command from `gcs_system`)."""
        custom, p2, p3 = mv.encode_mode(self.flavour, name)
        with self._lock:
            result = self._command(mv.MAV_CMD_DO_SET_MODE, (1.0, float(p2), float(p3), 0.0, 0.0, 0.0, 0.0))
            self.commands.append(ReceivedCommand(time.monotonic(), mv.MAV_CMD_DO_SET_MODE, (1.0, p2, p3), result))
        log.info("fake: ground station %d switched the mode to %s (result %d)", gcs_system, name, result)

    def end_boot(self) -> None:
        """The pre-arm checks pass from now on (a boot the test ends once its peer has seen it)."""
        with self._lock:
            self._boot_s = min(self._boot_s, self._now_s())

    def lose_gnss(self) -> None:
        """Cut GNSS (SITL's SIM_GPS_DISABLE 1): the estimator's timeline in `fake_ekf` starts now."""
        with self._lock:
            self.ekf.lose_gnss(time.monotonic())
        log.info("fake: GNSS lost")

    def restore_gnss(self) -> None:
        with self._lock:
            self.ekf.restore_gnss()

    @property
    def attitude_rad(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw) as flown."""
        with self._lock:
            return self._roll_rad, self._pitch_rad, self._yaw_rad

    def set_armed(self, armed: bool) -> None:
        with self._lock:
            self._armed = armed

    def stop_heartbeats(self) -> None:
        with self._lock:
            self._heartbeats_on = False

    def resume_heartbeats(self) -> None:
        with self._lock:
            self._heartbeats_on = True

    def inject(self, name: str, **fields: Any) -> None:
        """Send one `name` message (e.g. 'attitude', 'local_position_ned') with the given fields."""
        sender = f"{name}_send"

        def send(mav: Any) -> None:
            getattr(mav, sender)(**fields)

        with self._lock:
            self._outbox.append(send)

    def spoof_heartbeat(self, system: int, count: int = 1) -> None:
        """Heartbeats claiming to be another autopilot (`system`) on this link: a spoofer, a second vehicle."""
        autopilot = mv.MAV_AUTOPILOT_ARDUPILOTMEGA if self.flavour == "ardupilot" else mv.MAV_AUTOPILOT_PX4

        def send(mav: Any) -> None:
            own, mav.srcSystem = mav.srcSystem, system
            try:
                for _ in range(count):
                    mav.heartbeat_send(MAV_TYPE_QUADROTOR, autopilot, mv.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0,
                                       MAV_STATE_STANDBY)
            finally:
                mav.srcSystem = own

        with self._lock:
            self._outbox.append(send)

    @property
    def mode(self) -> str:
        with self._lock:
            return mv.mode_name(self.flavour, self._custom_mode)

    @property
    def armed(self) -> bool:
        with self._lock:
            return self._armed

    @property
    def booted(self) -> bool:
        return self._now_s() >= self._boot_s

    @property
    def boot_end_s(self) -> float:
        """When the boot phase ends, on time.monotonic (as the recv_s of what it records)."""
        return self._t0 + self._boot_s

    @property
    def position_ned_m(self) -> tuple[float, float, float]:
        with self._lock:
            return tuple(self._pos_ned_m)  # type: ignore[return-value]

    @property
    def velocity_ned_m_s(self) -> tuple[float, float, float]:
        with self._lock:
            return tuple(self._vel_ned_m_s)  # type: ignore[return-value]

    @property
    def yaw_rad(self) -> float:
        with self._lock:
            return self._yaw_rad

    @property
    def signing_counts(self) -> dict[str, int]:
        """pymavlink's counters on the fake's side (bad signatures, unsigned rejected)."""
        signing = self._conn.mav.signing
        return {"goodsig": signing.goodsig_count, "badsig": signing.badsig_count,
                "unsigned": signing.reject_count}

    def received(self) -> tuple[list[ReceivedSetpoint], list[ReceivedHeartbeat], list[ReceivedCommand]]:
        """Copies of what was recorded so far (setpoints, heartbeats, commands)."""
        with self._lock:
            return list(self.setpoints), list(self.heartbeats), list(self.commands)

    # ----------------------------------------------------------------- the autopilot's thread

    def _now_s(self) -> float:
        return time.monotonic() - self._t0

    def _boot_fraction(self) -> float:
        return 1.0 if self._boot_s <= 0 else min(1.0, self._now_s() / self._boot_s)

    def _prearm_failures(self) -> list[str]:
        fraction = self._boot_fraction()
        failures = [text for until, text in self.personality.prearm_failures if fraction < until]
        if self.flavour == "ardupilot" and not self._armed:
            visodom = self.ekf.visodom_prearm_failure(time.monotonic())
            if visodom is not None:
                failures.append(f"PreArm: {visodom}")
        return failures

    def _queue_statustext(self, severity: int, text: str) -> None:
        self.statustexts_sent.append((severity, text))
        self._outbox.append(lambda mav: mav.statustext_send(severity, text.encode("ascii")[:50]))

    def _loop(self) -> None:
        next_hb_s = next_phys_s = next_text_s = self._now_s()
        last_phys_s = next_phys_s
        while not self._stop.is_set():
            now = self._now_s()
            if now >= next_phys_s:
                self._physics(now - last_phys_s)
                last_phys_s, next_phys_s = now, now + self._physics_period_s
            if now >= next_hb_s:
                with self._lock:
                    beat = self._heartbeats_on
                if beat:
                    self._send_heartbeat()
                next_hb_s = now + self._heartbeat_period_s
            if now >= next_text_s:
                with self._lock:
                    for text in self._prearm_failures():
                        self._queue_statustext(MAV_SEVERITY_CRITICAL, text)
                    if not self._home_sent and self.booted:
                        self._home_sent = True
                        self._outbox.append(self._send_home)
                next_text_s = now + self._statustext_period_s
            with self._lock:
                outbox, self._outbox = self._outbox, []
            for send in outbox:
                send(self._conn.mav)
            self._send_streams(now)
            with self._lock:
                wake_s = min([next_hb_s, next_phys_s, *self._next_send_s.values()])
            self._conn.select(max(0.0, min(wake_s - self._now_s(), 0.05)))
            for _ in range(1000):
                msg = self._conn.recv_msg()
                if msg is None:
                    break
                self._handle(msg)

    def _physics(self, dt_s: float) -> None:
        with self._lock:
            name = mv.mode_name(self.flavour, self._custom_mode)
            vel_ned, yaw_rate = [0.0, 0.0, 0.0], 0.0
            sp, now = self._last_setpoint, time.monotonic()
            last_sp_s = sp.recv_s if sp is not None else self._started_s
            if self._last_attitude is not None:
                last_sp_s = max(last_sp_s, self._last_attitude.recv_s)  # PX4: attitude setpoints stream too
            if self.flavour == "px4" and name == "OFFBOARD" and now - last_sp_s > self._offboard_loss_s:
                log.info("fake PX4: offboard setpoints lost for COM_OF_LOSS_T, failsafe to LOITER")
                self._custom_mode = mv.encode_mode("px4", "LOITER")[0]
                name = "LOITER"
            airborne = -self._pos_ned_m[2] > self.terrain_height_m + 0.05
            name = self._gcs_failsafe_check(name, now)
            name = self._ekf_failsafe(name, now)
            nav_ok = self.ekf.position_ok(now)
            steering = self._armed and name == mv.STEER_MODE[self.flavour] and nav_ok
            attitude_flown = self._attitude_flown(name, sp)
            if self._armed and airborne and (attitude_flown or not nav_ok):
                # No position control: attitude targets, or a level vehicle drifting on its momentum.
                vel_ned = self._unpositioned_velocity(name, sp, now, dt_s)
            elif steering and self._takeoff_alt_m is not None:
                vel_ned[2] = -self.personality.up_cap_m_s if -self._pos_ned_m[2] < self._takeoff_alt_m else 0.0
                if vel_ned[2] == 0.0:
                    self._takeoff_alt_m = None
            elif steering and sp is not None and now - sp.recv_s <= self._guid_timeout_s:
                vel_ned, yaw_rate = self._setpoint_to_ned(sp)
            elif self._armed and name in ("LAND", "PRECLAND"):
                self._precland_tick(now)
                vel_ned = self._landing_velocity()
            if not (self._armed and airborne and (attitude_flown or not nav_ok)):
                self._roll_rad = self._pitch_rad = 0.0  # position-controlled flight: level enough to ignore
            vel_ned = self._capped(vel_ned)
            drift = self._heading_drift_rad_s if airborne and self._armed else 0.0
            self._yaw_rad = math.remainder(self._yaw_rad + (yaw_rate + drift) * dt_s, 2.0 * math.pi)
            for i in range(3):
                self._pos_ned_m[i] += vel_ned[i] * dt_s
            if self._pos_ned_m[2] > -self.terrain_height_m:
                # On the ground: a landing ends with the motors disarmed, as both autopilots do.
                self._pos_ned_m[2], vel_ned[2] = -self.terrain_height_m, 0.0
                if name in ("LAND", "PRECLAND") and self._armed:
                    self._armed = False
                    self.touchdown_ne_m = (self._pos_ned_m[0], self._pos_ned_m[1])
                    self.touchdown_s = now
            self._vel_ned_m_s, self._yaw_rate_rad_s = vel_ned, yaw_rate + drift

    def _ekf_failsafe(self, name: str, now: float) -> str:
        """Copter's EKF failsafe (ArduPilot): FS_EKF_ACTION for modes that need a position. Caller holds the lock."""
        if self.flavour != "ardupilot" or not self._armed or not self.ekf.failsafe_due(now):
            return name
        self._queue_statustext(MAV_SEVERITY_CRITICAL, "EKF variance")
        if name in ARDUPILOT_GPS_MODES or self.ekf.fs_ekf_action == 3:
            action = FS_EKF_ACTIONS[self.ekf.fs_ekf_action]
            self._custom_mode = mv.encode_mode("ardupilot", action)[0]
            self._queue_statustext(MAV_SEVERITY_CRITICAL, f"EKF Failsafe: changed to {action} Mode")
            log.info("fake: EKF failsafe, %s -> %s", name, action)
            return action
        return name

    def _attitude_flown(self, name: str, sp: ReceivedSetpoint | None) -> bool:
        """Attitude targets fly the vehicle: ArduCopter's GUIDED_NOGPS, or PX4 OFFBOARD whose newest
        setpoint is an attitude one (caller holds the lock)."""
        if name == "GUIDED_NOGPS":
            return True
        target = self._last_attitude
        return (self.flavour == "px4" and name == "OFFBOARD" and target is not None
                and (sp is None or target.recv_s > sp.recv_s))

    def _unpositioned_velocity(self, name: str, sp: ReceivedSetpoint | None, now: float, dt_s: float) -> list[float]:
        """Flight without a horizontal position: attitude targets, else level and drifting."""
        vel = list(self._vel_ned_m_s)
        climb = 0.0
        target = self._last_attitude
        timeout_s = self._guid_timeout_s if self.flavour == "ardupilot" else self._offboard_loss_s
        if self._attitude_flown(name, sp) and target is not None and now - target.recv_s <= timeout_s:
            self._roll_rad, self._pitch_rad, self._yaw_rad = quaternion_to_euler(target.q)
            thrust = min(max(target.thrust, 0.0), 1.0)
            if self.flavour == "ardupilot":
                # ArduCopter's default GUID_OPTIONS: thrust is a climb rate, 0.5 holds the altitude.
                p = self.personality
                climb = (thrust - 0.5) * 2.0 * (p.up_cap_m_s if thrust >= 0.5 else p.down_cap_m_s)
            else:
                # PX4: collective thrust, hovering at MPC_THR_HOVER (0.5): a vertical acceleration.
                climb = -vel[2] + (GRAVITY_M_S2 * (thrust / PX4_HOVER_THRUST - 1.0) + DRAG_PER_S * vel[2]) * dt_s
        else:
            # Level (an attitude target timed out, ALT_HOLD or LAND without a position, GUIDED blind).
            self._roll_rad = self._pitch_rad = 0.0
            if name in ("LAND", "PRECLAND"):
                climb = -LAND_RATE_M_S
            elif name == "GUIDED" and sp is not None and now - sp.recv_s <= self._guid_timeout_s:
                climb = -sp.vel_m_s[2]  # the barometer still holds the vertical
        # Body acceleration from the tilt (nose down accelerates forward), into NED by the heading.
        a_fwd = -GRAVITY_M_S2 * math.tan(self._pitch_rad)
        a_right = GRAVITY_M_S2 * math.tan(self._roll_rad)
        c, s = math.cos(self._yaw_rad), math.sin(self._yaw_rad)
        acc = (c * a_fwd - s * a_right, s * a_fwd + c * a_right)
        for i in range(2):
            vel[i] += (acc[i] - DRAG_PER_S * vel[i]) * dt_s
        vel[2] = -climb
        return vel

    def _gcs_failsafe_check(self, name: str, now: float) -> str:
        """FS_GCS_ENABLE 5: LAND once SYSID_MYGCS fell silent for FS_GCS_TIMEOUT (caller holds the lock)."""
        if not (self._fs_gcs_land and self._armed and self._gcs_seen_s is not None) or self._gcs_failsafe:
            return name
        if now - self._gcs_seen_s > self._fs_gcs_timeout_s:
            self._gcs_failsafe = True
            self._queue_statustext(MAV_SEVERITY_CRITICAL, "GCS Failsafe")
            self._custom_mode = mv.encode_mode(self.flavour, "LAND")[0]
            return "LAND"
        return name

    def _capped(self, vel_ned: list[float]) -> list[float]:
        """The personality's speed limits (caller holds the lock)."""
        p = self.personality
        speed = math.hypot(vel_ned[0], vel_ned[1])
        scale = p.horizontal_cap_m_s / speed if speed > p.horizontal_cap_m_s else 1.0
        down = min(max(vel_ned[2], -p.up_cap_m_s), p.down_cap_m_s)
        return [vel_ned[0] * scale, vel_ned[1] * scale, down]

    def _landing_velocity(self) -> list[float]:
        """LAND descends; with an acquired precision-landing target it also moves over it, and holds
        its altitude while the target is more than PLND_XY_DIST_MAX away (caller holds the lock)."""
        vel = [0.0, 0.0, LAND_RATE_M_S]
        if self._plnd_state != "acquired" or self._plnd_target_ne_m is None:
            return vel
        offset = (self._plnd_target_ne_m[0] - self._pos_ned_m[0], self._plnd_target_ne_m[1] - self._pos_ned_m[1])
        for i, offset_m in enumerate(offset):
            vel[i] = max(-PRECLAND_MAX_M_S, min(PRECLAND_MAX_M_S, PRECLAND_GAIN_PER_S * offset_m))
        if math.hypot(*offset) > PRECLAND_XY_DIST_MAX_M:
            vel[2] = 0.0
        return vel

    def _precland_tick(self, now: float) -> None:
        """AC_PrecLand's init and timeout checks, once per physics step in LAND (caller holds the lock)."""
        if self._plnd_state == "init":
            if now - self._plnd_last_s > PRECLAND_INIT_GAP_S:
                self._plnd_state = "none"
                self._queue_statustext(MAV_SEVERITY_CRITICAL, "PrecLand: Init Failed")
            elif now - self._plnd_init_s > PRECLAND_INIT_S:
                self._plnd_state = "acquired"
                self._queue_statustext(MAV_SEVERITY_INFO, "PrecLand: Init Complete")
        elif self._plnd_state == "acquired" and now - self._plnd_last_s > PRECLAND_TIMEOUT_S:
            self._plnd_state = "none"
            self._queue_statustext(MAV_SEVERITY_CRITICAL, "PrecLand: Target Lost")

    def _precland_measure(self, target: ReceivedLandingTarget) -> None:
        """One LANDING_TARGET in LAND: the target's ground position from the line of sight (caller holds the lock)."""
        if not (self._precland and self._armed and mv.mode_name(self.flavour, self._custom_mode) in ("LAND", "PRECLAND")):
            return
        if not all(math.isfinite(v) for v in (target.angle_x_rad, target.angle_y_rad, target.distance_m)):
            return
        agl_m = max(0.0, -self._pos_ned_m[2] - self.terrain_height_m)
        # Image x right, image y down (= body backward): the ArduPilot companion convention. The
        # fake flies level, so the body line of sight is the level one; the distance, when given,
        # is along it (AC_PrecLand), else the height sets it.
        fwd, right, down = -math.tan(target.angle_y_rad), math.tan(target.angle_x_rad), 1.0
        scale = (target.distance_m / math.sqrt(fwd * fwd + right * right + 1.0) if target.distance_m > 0.0
                 else agl_m)
        c, s = math.cos(self._yaw_rad), math.sin(self._yaw_rad)
        fwd_m, right_m = fwd * scale, right * scale
        self._plnd_target_ne_m = (self._pos_ned_m[0] + c * fwd_m - s * right_m,
                                  self._pos_ned_m[1] + s * fwd_m + c * right_m)
        self.precland_targets_ne.append((target.recv_s, *self._plnd_target_ne_m))
        if self._plnd_state == "none":
            self._plnd_state, self._plnd_init_s = "init", target.recv_s
            self._queue_statustext(MAV_SEVERITY_INFO, "PrecLand: Target Found")
        self._plnd_last_s = target.recv_s

    def _setpoint_to_ned(self, sp: ReceivedSetpoint) -> tuple[list[float], float]:
        """What the autopilot would fly for a setpoint (caller holds the lock)."""
        if sp.type_mask & 0x38:  # any velocity component ignored: not a velocity setpoint
            return [0.0, 0.0, 0.0], 0.0
        yaw_rate = 0.0 if sp.type_mask & 0x800 else sp.yaw_rate_rad_s
        fwd, right, down = sp.vel_m_s
        if not all(math.isfinite(v) for v in (fwd, right, down, yaw_rate, sp.yaw_target_rad)):
            return [0.0, 0.0, 0.0], 0.0  # both autopilots ignore a setpoint with NaN velocities
        if sp.frame == mv.STEER_FRAME[self.flavour]:
            c, s = math.cos(self._yaw_rad), math.sin(self._yaw_rad)
            vel = [c * fwd - s * right, s * fwd + c * right, down]
        elif sp.frame == mv.MAV_FRAME_LOCAL_NED:
            vel = [fwd, right, down]
        else:
            return [0.0, 0.0, 0.0], 0.0
        if self.flavour == "ardupilot":
            yaw_rate = self._guided_yaw_rate(sp, vel, yaw_rate)
        return vel, yaw_rate

    def _guided_yaw_rate(self, sp: ReceivedSetpoint, vel_ned: list[float], yaw_rate: float) -> float:
        """ArduCopter's heading for a guided velocity setpoint (caller holds the lock)."""
        if not sp.type_mask & 0x400:
            error = math.remainder(sp.yaw_target_rad - self._yaw_rad, 2.0 * math.pi)  # a heading asked for
        elif not sp.type_mask & 0x800:
            return yaw_rate  # a yaw rate asked for
        elif math.hypot(vel_ned[0], vel_ned[1]) > WP_YAW_MIN_SPEED_M_S:
            # Neither: WP_YAW_BEHAVIOR 2 points the nose where the vehicle goes.
            error = math.remainder(math.atan2(vel_ned[1], vel_ned[0]) - self._yaw_rad, 2.0 * math.pi)
        else:
            return 0.0
        return max(-YAW_SLEW_RAD_S, min(YAW_SLEW_RAD_S, YAW_GAIN_PER_S * error))

    def _handle(self, msg: Any) -> None:
        kind, recv_s = msg.get_type(), time.monotonic()
        if kind == "BAD_DATA":
            return
        self.peer_seen.set()
        if kind == "HEARTBEAT":
            with self._lock:
                if msg.get_srcSystem() == SYSID_MYGCS:
                    self._gcs_seen_s = recv_s
                self.heartbeats.append(ReceivedHeartbeat(recv_s, msg.get_srcSystem(), msg.get_srcComponent(),
                                                         msg.type, msg.autopilot))
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            with self._lock:
                relative = msg.coordinate_frame in (mv.MAV_FRAME_BODY_OFFSET_NED, mv.MAV_FRAME_BODY_NED)
                target_yaw = msg.yaw + (self._yaw_rad if relative else 0.0)
                sp = ReceivedSetpoint(recv_s, msg.get_srcSystem(), msg.get_srcComponent(), msg.target_system,
                                      msg.target_component, msg.coordinate_frame, msg.type_mask,
                                      (msg.vx, msg.vy, msg.vz), msg.yaw_rate, msg.yaw, target_yaw)
                self.setpoints.append(sp)
                if msg.target_system == self._system:
                    self._last_setpoint = sp
        elif kind == "SET_ATTITUDE_TARGET":
            self._on_attitude_target(msg, recv_s)
        elif kind == "VISION_SPEED_ESTIMATE":
            speed = ReceivedVisionSpeed(recv_s, msg.usec, (msg.x, msg.y, msg.z), tuple(msg.covariance),
                                        "VISION_SPEED_ESTIMATE")
            with self._lock:
                self.vision_speeds.append(speed)
                if self.flavour == "ardupilot" and all(math.isfinite(v) for v in speed.vel_m_s):
                    self.ekf.on_vision_speed(recv_s, speed.vel_m_s)
        elif kind == "VISION_POSITION_DELTA":
            dt_s = msg.time_delta_usec / 1e6
            vel = tuple(d / dt_s for d in msg.position_delta) if dt_s > 0 else (math.nan,) * 3
            with self._lock:
                self.vision_speeds.append(ReceivedVisionSpeed(recv_s, msg.time_usec, vel, (float(msg.confidence),),
                                                              "VISION_POSITION_DELTA"))
                if self.flavour == "ardupilot" and all(math.isfinite(v) for v in vel):
                    self.ekf.on_vision_delta(recv_s)
        elif kind == "ODOMETRY":
            with self._lock:
                self.vision_speeds.append(ReceivedVisionSpeed(recv_s, msg.time_usec, (msg.vx, msg.vy, msg.vz),
                                                              tuple(msg.velocity_covariance), "ODOMETRY"))
        elif kind == "LANDING_TARGET":
            target = ReceivedLandingTarget(recv_s, msg.frame, msg.angle_x, msg.angle_y, msg.distance)
            with self._lock:
                self.landing_targets.append(target)
                self._precland_measure(target)
        elif kind == "SET_MODE":
            with self._lock:
                self.set_mode_messages.append((recv_s, msg.base_mode, msg.custom_mode))
                if msg.target_system == self._system and self._mode_allowed(msg.custom_mode):
                    self._custom_mode = msg.custom_mode
        elif kind == "COMMAND_LONG" and msg.target_system == self._system:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
            with self._lock:
                result = self._command(msg.command, params)
                self.commands.append(ReceivedCommand(recv_s, msg.command, params, result))
            self._conn.mav.command_ack_send(msg.command, result)

    def _on_attitude_target(self, msg: Any, recv_s: float) -> None:
        """ArduCopter's handle_message_set_attitude_target: guided modes only, rates all-or-none, thrust needed."""
        q = tuple(float(v) for v in msg.q)
        rates = msg.type_mask & 0x07
        unit = abs(math.sqrt(sum(v * v for v in q)) - 1.0) <= 1e-3
        with self._lock:
            name = mv.mode_name(self.flavour, self._custom_mode)
            flying = ("GUIDED", "GUIDED_NOGPS") if self.flavour == "ardupilot" else ("OFFBOARD",)
            accepted = (msg.target_system == self._system and name in flying and rates in (0, 7)
                        and not msg.type_mask & ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE and unit)
            target = ReceivedAttitudeTarget(recv_s, msg.type_mask, q, float(msg.thrust), accepted)  # type: ignore[arg-type]
            self.attitude_targets.append(target)
            if accepted:
                self._last_attitude = target

    def _streaming(self) -> bool:
        sp = self._last_setpoint
        return sp is not None and time.monotonic() - sp.recv_s <= self._offboard_loss_s

    def _mode_allowed(self, custom_mode: int) -> bool:
        """PX4 refuses OFFBOARD unless setpoints are already streaming (caller holds the lock)."""
        if self.flavour == "px4" and mv.mode_name("px4", custom_mode) == "OFFBOARD":
            return self._streaming()
        if self.flavour == "ardupilot" and mv.mode_name("ardupilot", custom_mode) in ARDUPILOT_GPS_MODES:
            return self.ekf.position_ok(time.monotonic())  # Mode::set_mode: requires_GPS and no position
        return True

    def _command(self, command: int, params: tuple[float, ...]) -> int:
        """Execute one COMMAND_LONG and return its MAV_RESULT (caller holds the lock)."""
        if command == mv.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(params[0]), params[1]
            if msg_id == mv.MSG_ID_EKF_STATUS_REPORT and self.flavour == "px4":
                return MAV_RESULT_UNSUPPORTED  # an ardupilotmega message; PX4 has ESTIMATOR_STATUS
            if interval_us < 0:
                self._intervals_s.pop(msg_id, None)
                self._next_send_s.pop(msg_id, None)
            else:
                self._intervals_s[msg_id] = interval_us / 1e6 if interval_us > 0 else 0.25  # 0: our default 4 Hz
                self._next_send_s[msg_id] = self._now_s()
            return mv.MAV_RESULT_ACCEPTED
        if command == mv.MAV_CMD_REQUEST_MESSAGE:
            if int(params[0]) != mv.MSG_ID_HOME_POSITION:
                return MAV_RESULT_UNSUPPORTED
            if not self.booted:
                return MAV_RESULT_FAILED  # no home yet
            self._outbox.append(self._send_home)
            return mv.MAV_RESULT_ACCEPTED
        if command == mv.MAV_CMD_DO_SET_MODE:
            if self.flavour == "px4":
                custom = mv.px4_custom_mode(int(params[1]), int(params[2]))
            else:
                custom = int(params[1])
            if not self._mode_allowed(custom):
                if self.flavour == "px4":
                    return MAV_RESULT_DENIED
                wanted = mv.mode_name(self.flavour, custom)
                self._queue_statustext(MAV_SEVERITY_WARNING, f"Mode change failed: {wanted} requires position")
                return MAV_RESULT_FAILED
            self._custom_mode = custom
            return mv.MAV_RESULT_ACCEPTED
        if command == mv.MAV_CMD_SET_EKF_SOURCE_SET:
            if self.flavour != "ardupilot":
                return MAV_RESULT_UNSUPPORTED
            result = self.ekf.set_source_set(int(params[0]))
            if result == mv.MAV_RESULT_ACCEPTED:
                self._queue_statustext(MAV_SEVERITY_INFO, f"EKF3 source set {int(params[0])} selected")
            return result
        if command == mv.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm(params[0] == 1.0)
        if command == mv.MAV_CMD_NAV_TAKEOFF:
            guided = mv.mode_name(self.flavour, self._custom_mode) == "GUIDED"
            if self.flavour != "ardupilot" or not guided or not self._armed:
                return MAV_RESULT_FAILED
            self._takeoff_alt_m = float(params[6])
            return mv.MAV_RESULT_ACCEPTED
        return MAV_RESULT_UNSUPPORTED

    def _arm(self, arm: bool) -> int:
        """ARM/DISARM with each personality's refusals (caller holds the lock)."""
        if not arm:
            self._armed = False
            return mv.MAV_RESULT_ACCEPTED
        failures = self._prearm_failures()
        name = mv.mode_name(self.flavour, self._custom_mode)
        if not failures and self.flavour == "px4" and name == "OFFBOARD" and not self._streaming():
            failures = ["Arming denied: offboard signal lost"]
        if not failures and self._arm_refusals > 0:
            self._arm_refusals -= 1
            failures = ["PreArm: Throttle too high" if self.flavour == "ardupilot" else "Arming denied: throttle"]
        if failures:
            for text in failures:
                # ArduPilot repeats its pre-arm failures with "Arm:" when an ARM is refused.
                said = "Arm: " + text.split(": ", 1)[-1] if self.flavour == "ardupilot" else text
                self._queue_statustext(MAV_SEVERITY_CRITICAL, said)
            return self.personality.arm_refused_result
        self._armed = True
        return mv.MAV_RESULT_ACCEPTED

    # ----------------------------------------------------------------- sending

    def _boot_ms(self) -> int:
        return int(self._now_s() * 1000.0)

    def _send_home(self, mav: Any) -> None:
        mav.home_position_send(int(ORIGIN_LAT_DEG * 1e7), int(ORIGIN_LON_DEG * 1e7), 0, 0.0, 0.0, 0.0,
                               [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)

    def _send_heartbeat(self) -> None:
        with self._lock:
            base = mv.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED | MAV_MODE_FLAG_GUIDED_ENABLED
            base |= mv.MAV_MODE_FLAG_SAFETY_ARMED if self._armed else 0
            custom, status = self._custom_mode, mv.MAV_STATE_ACTIVE if self._armed else MAV_STATE_STANDBY
        autopilot = mv.MAV_AUTOPILOT_ARDUPILOTMEGA if self.flavour == "ardupilot" else mv.MAV_AUTOPILOT_PX4
        self._conn.mav.heartbeat_send(MAV_TYPE_QUADROTOR, autopilot, base, custom, status)

    def _ekf_flags(self) -> int:
        fraction = self._boot_fraction()
        flags = mv.EKF_ATTITUDE if fraction >= 0.25 else mv.EKF_UNINITIALIZED
        if fraction >= 0.5:
            flags |= mv.EKF_VELOCITY_HORIZ | mv.EKF_VELOCITY_VERT | mv.EKF_POS_VERT_ABS
        if fraction >= 0.75:
            flags |= mv.EKF_POS_HORIZ_REL | mv.EKF_POS_HORIZ_ABS | mv.EKF_PRED_POS_HORIZ_REL
        return flags

    def _send_streams(self, now: float) -> None:
        with self._lock:
            due = [m for m, t in self._next_send_s.items() if now >= t]
            for msg_id in due:
                self._next_send_s[msg_id] = now + self._intervals_s[msg_id]
            pos, vel, yaw = list(self._pos_ned_m), list(self._vel_ned_m_s), self._yaw_rad
            yaw_rate, terrain_m = self._yaw_rate_rad_s, self.terrain_height_m
            roll, pitch = self._roll_rad, self._pitch_rad
            now_mono = time.monotonic()
            # ArduPilot stops LOCAL_POSITION_NED when its EKF has no position (GCS_MAVLINK::send_local_position).
            local_ok = self.ekf.position_ok(now_mono)
            # Booting gates the good bits; the estimator adds what the loss sets (constant-position mode).
            boot, ekf = self._ekf_flags(), self.ekf.flags(now_mono)
            ekf_flags = (boot & ekf & fake_ekf.GOOD_FLAGS) | ((boot | ekf) & ~fake_ekf.GOOD_FLAGS)
            fix_type = self.ekf.fix_type() if self._boot_fraction() >= 0.5 else 1
        boot_ms, mav = self._boot_ms(), self._conn.mav
        for msg_id in due:
            if msg_id == mv.MSG_ID_LOCAL_POSITION_NED:
                if local_ok:
                    mav.local_position_ned_send(boot_ms, pos[0], pos[1], pos[2], vel[0], vel[1], vel[2])
            elif msg_id == mv.MSG_ID_ATTITUDE:
                mav.attitude_send(boot_ms, roll, pitch, yaw, 0.0, 0.0, yaw_rate)
            elif msg_id == mv.MSG_ID_GPS_RAW_INT:
                mav.gps_raw_int_send(boot_ms * 1000, fix_type, 0, 0, 0, 65535, 65535, 65535, 65535,
                                     12 if fix_type >= 3 else 0)
            elif msg_id == mv.MSG_ID_ESTIMATOR_STATUS:
                mav.estimator_status_send(boot_ms * 1000, ekf_flags & 0x3FF, 0.1, 0.1, 0.1, 0.1, 0.0, 0.0, 0.5, 0.5)
            elif msg_id == mv.MSG_ID_SYS_STATUS:
                bit = mv.MAV_SYS_STATUS_PREARM_CHECK
                health = bit if not self._prearm_failures() else 0
                mav.sys_status_send(bit, bit, health, 100, 12000, -1, -1, 0, 0, 0, 0, 0, 0)
            elif msg_id == mv.MSG_ID_EKF_STATUS_REPORT:
                mav.ekf_status_report_send(ekf_flags, 0.1, 0.1, 0.1, 0.1, 0.0)
            elif msg_id == mv.MSG_ID_DISTANCE_SENSOR:
                agl_m = -pos[2] - terrain_m
                # Out of range reads as max + 1 cm, the convention ArduPilot's driver uses.
                max_cm = int(self._rangefinder_max_m * 100)
                dist_cm = int(round(agl_m * 100)) if agl_m <= self._rangefinder_max_m else max_cm + 1
                mav.distance_sensor_send(boot_ms, 20, max_cm, max(0, dist_cm), 0, 0, mv.MAV_SENSOR_ROTATION_PITCH_270,
                                         255)
            elif msg_id == mv.MSG_ID_GLOBAL_POSITION_INT:
                lat = ORIGIN_LAT_DEG + pos[0] / 111_320.0
                lon = ORIGIN_LON_DEG + pos[1] / (111_320.0 * math.cos(math.radians(ORIGIN_LAT_DEG)))
                mav.global_position_int_send(boot_ms, int(lat * 1e7), int(lon * 1e7), int(-pos[2] * 1000),
                                             int(-pos[2] * 1000), int(vel[0] * 100), int(vel[1] * 100),
                                             int(vel[2] * 100), int(math.degrees(yaw) % 360 * 100))


def main(argv: list[str] | None = None) -> int:
    """Run a fake autopilot until SIGTERM/SIGINT (for end-to-end runs of `dovesei up --vehicle`)."""
    p = argparse.ArgumentParser(prog="python -m dovesei.testing.fake_autopilot", description=__doc__.split("\n")[0])
    p.add_argument("--url", default="udpin:127.0.0.1:14550", help="pymavlink URL the fake listens or sends on")
    p.add_argument("--flavour", choices=FLAVOURS, default="ardupilot")
    p.add_argument("--mode", default=None, help="initial mode (default LOITER); GUIDED/OFFBOARD to accept setpoints")
    p.add_argument("--alt", type=float, default=100.0, help="initial altitude above the local origin, metres")
    p.add_argument("--disarmed", action="store_true", help="start disarmed (on the ground if --alt 0), booting")
    p.add_argument("--boot-s", type=float, default=DEFAULT_BOOT_S, help="pre-arm phase after start (disarmed only)")
    p.add_argument("--heading-drift-deg-s", type=float, default=0.0, help="heading drift while airborne")
    p.add_argument("--lose-gnss-below-m", type=float, default=None,
                   help="ArduPilot: cut GNSS once the vehicle descends below this altitude (SIM_GPS_DISABLE 1)")
    p.add_argument("--fs-ekf-action", type=int, choices=sorted(FS_EKF_ACTIONS), default=1,
                   help="ArduPilot FS_EKF_ACTION after a GNSS loss: 1 LAND, 2 ALT_HOLD, 3 LAND even without GPS modes")
    p.add_argument("--ekf-coast-s", type=float, default=3.0,
                   help="seconds the EKF coasts on inertia after a GNSS loss before its position is gone")
    args = p.parse_args(argv)
    if args.lose_gnss_below_m is not None and args.flavour != "ardupilot":
        p.error("--lose-gnss-below-m: the GNSS-loss personality is ArduPilot's")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = install_stop_handlers()
    ekf = FakeEkf(fs_ekf_action=args.fs_ekf_action, coast_s=args.ekf_coast_s)
    with FakeAutopilot(args.url, flavour=args.flavour, mode=args.mode, armed=not args.disarmed, alt_m=args.alt,
                       boot_s=args.boot_s, heading_drift_rad_s=math.radians(args.heading_drift_deg_s), ekf=ekf) as fake:
        log.info("fake %s autopilot on %s, mode %s", args.flavour, args.url, fake.mode)
        next_log_s = time.monotonic()
        while not stop.wait(0.1):
            n, e, d = fake.position_ned_m
            if args.lose_gnss_below_m is not None and fake.ekf.gnss_ok and fake.armed and -d < args.lose_gnss_below_m:
                fake.lose_gnss()  # once: the test of what follows is the point
                args.lose_gnss_below_m = None
            if time.monotonic() >= next_log_s:
                next_log_s += 5.0
                log.info("mode %s %s, position N %.1f E %.1f alt %.1f m, GNSS %s", fake.mode,
                         "armed" if fake.armed else "disarmed", n, e, -d, "ok" if fake.ekf.gnss_ok else "LOST")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
