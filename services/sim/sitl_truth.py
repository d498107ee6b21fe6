"""The simulated vehicle's TRUE pose from ArduPilot SITL, for the sim's camera and judge only.

With a real autopilot simulator in the loop the controller republishes the EKF's estimate on the
state key. A camera rendered at that estimate sees only the estimate's own motion: drift would be
invisible, and a visual velocity could never correct it. ArduPilot SITL knows where its physics
model really is and says so in SIM_STATE (MAVLink common message 108, filled from the physics state
in libraries/SITL/SITL.cpp `SIM::sim_state_send`), sent on any of its outputs that asks for it.

    SITL --its own output, e.g. --serial2 udpclient:127.0.0.1:14552--> UDP socket bound here
        (udpin:127.0.0.1:14552; never the controller's link: `dovesei up` refuses a shared endpoint)
        --pymavlink's MAVLink 2 parser--> HEARTBEAT: ask for the EKF origin (MAV_CMD_REQUEST_MESSAGE
                                                     GPS_GLOBAL_ORIGIN), SIM_STATE and ATTITUDE (SET_MESSAGE_INTERVAL)
                                          GPS_GLOBAL_ORIGIN: the origin, pinned once
                                          ATTITUDE: the autopilot's boot clock (time_boot_ms) at arrival
                                          SIM_STATE: checked --> TruePose dated on that clock (last ~3 s kept)
    TruePose --> dovesei.sim.external: frames rendered and the judge's pose; never a VehicleState

SIM_STATE carries no time, so each sample is dated on the autopilot's boot clock by the ATTITUDE
that SITL sends beside it (both asked at the same rate, sent from the same scheduler pass): the
camera can then render the truth AT the instant of the state that labels the frame (`at(t_s)`).
Rendering the newest truth under an older state's attitude tilted the view against its label by
the attitude's change over the state's age (20 Hz states: up to ~50 ms, 1-2 deg while braking),
which read as metres per second of false motion in the visual odometry at 80 m (measured).

The only things sent are those two requests, on the sim's own output: nothing steers, arms or sets
a parameter. Positions are metres north/east of the autopilot's EKF origin (where it booted, the
origin of the LOCAL_POSITION_NED the controller republishes, so truth and estimate share one frame)
with ArduPilot's own flat-earth scaling; the altitude above ground is the altitude above the
origin's (SITL's ground is flat at its home altitude). The origin is asked for, not taken from the
first sample, because `dovesei up --takeoff` starts the sim only after the climb. ArduPilot 4.6
writes degrees x 1e7 into SIM_STATE's float `lat`/`lon` (the spec says degrees), so the integer
`lat_int`/`lon_int` extensions are read instead.
"""

from __future__ import annotations

import bisect
import logging
import math
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from dovesei.shared.errors import ConfigError

log = logging.getLogger(__name__)

MSG_ID_SIM_STATE = 108
MSG_ID_GPS_GLOBAL_ORIGIN = 49
MSG_ID_ATTITUDE = 30
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_AUTOPILOT_INVALID = 8  # a ground station's or companion's heartbeat, not the autopilot's
# ArduPilot's metres per 1e-7 degree of latitude (AP_Math/definitions.h LATLON_TO_M), used with
# cos(latitude) for longitude as in Location::get_distance_NE: our north/east match the EKF's.
LATLON_TO_M = 0.011131884502145034
DEFAULT_RATE_HZ = 50.0  # SIM_STATE rate asked for: a frame never waits more than 20 ms for a pose
_REQUEST_EVERY_S = 2.0  # re-ask this often until an answer comes (a request can be lost; SITL may reboot)
_RECV_TIMEOUT_S = 0.2  # the reader thread's socket timeout: how soon `close` is noticed
_HISTORY_S = 3.0  # truth kept for `at`: states reach the sim well within this (their staleness limit is 1 s)


def parse_truth_url(url: Any, flag: str = "--sitl-truth") -> tuple[str, int]:
    """(host, port) of `udpin:HOST:PORT`, the one form a SITL output (`udpclient:`) can reach."""
    text = url.strip() if isinstance(url, str) else ""
    scheme, _, rest = text.partition(":")
    host, _, port = rest.rpartition(":")
    if scheme != "udpin" or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(f"{flag} {url!r}: expected udpin:HOST:PORT (a port in 1..65535) where a SITL output "
                          "sends, e.g. udpin:127.0.0.1:14552 for SITL's --serial2 udpclient:127.0.0.1:14552")
    return host, int(port)


@dataclass(frozen=True)
class TruePose:
    """Where SITL's physics model is: metres from the first sample, attitude in radians (NED yaw)."""

    north_m: float
    east_m: float
    alt_agl_m: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    vel_ned_m_s: tuple[float, float, float]
    recv_monotonic_s: float  # when it arrived here (time.monotonic)
    boot_s: float | None = None  # the autopilot's time since boot it belongs to (None: no ATTITUDE seen yet)


@dataclass(frozen=True)
class Origin:
    lat_e7: int
    lon_e7: int
    alt_amsl_m: float


def _position_problem(lat_e7: int, lon_e7: int) -> str:
    if lat_e7 == 0 and lon_e7 == 0:
        return "no position (0, 0)"
    if not (-900_000_000 <= lat_e7 <= 900_000_000 and -1_800_000_000 <= lon_e7 <= 1_800_000_000):
        return f"position {lat_e7}, {lon_e7} (1e-7 deg) out of range"
    return ""


def origin_from(msg: Any) -> Origin | None:
    """The EKF origin of a GPS_GLOBAL_ORIGIN (altitude in mm AMSL), or None when it is unusable."""
    if _position_problem(msg.latitude, msg.longitude) or not -1_000_000 <= msg.altitude <= 20_000_000:
        return None
    return Origin(int(msg.latitude), int(msg.longitude), msg.altitude / 1000.0)


def sample_problem(msg: Any) -> str:
    """'' when a SIM_STATE is usable, else what is wrong with it (one line)."""
    lat_e7, lon_e7 = getattr(msg, "lat_int", 0), getattr(msg, "lon_int", 0)
    if lat_e7 == 0 and lon_e7 == 0:
        return "no lat_int/lon_int (a MAVLink 1 sender or an ArduPilot older than 4.1)"
    problem = _position_problem(lat_e7, lon_e7)
    if problem:
        return problem
    numbers = {"alt": msg.alt, "roll": msg.roll, "pitch": msg.pitch, "yaw": msg.yaw, "vn": msg.vn, "ve": msg.ve,
               "vd": msg.vd}
    bad = [k for k, v in numbers.items() if not math.isfinite(v)]
    if bad:
        return f"non-finite {', '.join(bad)}"
    if not -1000.0 <= msg.alt <= 20000.0:
        return f"altitude {msg.alt:g} m AMSL out of range"
    if max(abs(msg.roll), abs(msg.pitch), abs(msg.yaw)) > 2 * math.pi:
        return "attitude beyond 2 pi"
    if max(abs(msg.vn), abs(msg.ve), abs(msg.vd)) > 200.0:
        return "speed above 200 m/s"
    return ""


def true_pose(msg: Any, origin: Origin, recv_monotonic_s: float, boot_s: float | None = None) -> TruePose:
    """A checked SIM_STATE as metres from `origin` (ArduPilot's flat-earth scaling)."""
    mid_lat_rad = math.radians((msg.lat_int + origin.lat_e7) / 2 * 1e-7)
    # Longitude difference wrapped into +-180 deg, as ArduPilot's diff_longitude does.
    dlon_e7 = (msg.lon_int - origin.lon_e7 + 1_800_000_000) % 3_600_000_000 - 1_800_000_000
    yaw = math.atan2(math.sin(msg.yaw), math.cos(msg.yaw))
    return TruePose(north_m=(msg.lat_int - origin.lat_e7) * LATLON_TO_M,
                    east_m=dlon_e7 * LATLON_TO_M * max(math.cos(mid_lat_rad), 0.01),
                    alt_agl_m=float(msg.alt) - origin.alt_amsl_m, roll_rad=float(msg.roll),
                    pitch_rad=float(msg.pitch), yaw_rad=yaw, vel_ned_m_s=(float(msg.vn), float(msg.ve), float(msg.vd)),
                    recv_monotonic_s=recv_monotonic_s, boot_s=boot_s)


def interpolate(a: TruePose, b: TruePose, boot_s: float) -> TruePose:
    """The pose at `boot_s` between two dated samples (the heading the short way round)."""
    w = (boot_s - a.boot_s) / (b.boot_s - a.boot_s)

    def mix(x: float, y: float) -> float:
        return x + w * (y - x)

    dyaw = math.atan2(math.sin(b.yaw_rad - a.yaw_rad), math.cos(b.yaw_rad - a.yaw_rad))
    yaw = a.yaw_rad + w * dyaw
    return TruePose(north_m=mix(a.north_m, b.north_m), east_m=mix(a.east_m, b.east_m),
                    alt_agl_m=mix(a.alt_agl_m, b.alt_agl_m), roll_rad=mix(a.roll_rad, b.roll_rad),
                    pitch_rad=mix(a.pitch_rad, b.pitch_rad), yaw_rad=math.atan2(math.sin(yaw), math.cos(yaw)),
                    vel_ned_m_s=tuple(mix(x, y) for x, y in zip(a.vel_ned_m_s, b.vel_ned_m_s)),
                    recv_monotonic_s=mix(a.recv_monotonic_s, b.recv_monotonic_s), boot_s=boot_s)


class SitlTruth:
    """Reads SIM_STATE from one SITL output in a thread; `newest()` is the latest checked sample.

    Use as a context manager (or `start()`/`close()`). `source_system` is ours on that output, never
    the autopilot's or the controller's id; 253 by default (below a GCS's 255, above an autopilot's).
    """

    def __init__(self, url: str, *, rate_hz: float = DEFAULT_RATE_HZ, source_system: int = 253,
                 source_component: int = 190) -> None:
        self.url = url
        self.host, self.port = parse_truth_url(url)
        if not (math.isfinite(rate_hz) and 0 < rate_hz <= 400):
            raise ConfigError(f"SIM_STATE rate must be in (0, 400] Hz, got {rate_hz!r}")
        self.rate_hz = rate_hz
        # pymavlink's generated MAVLink 2 dialect module, imported here and not through mavutil: it
        # needs no MAVLINK20 variable and opens no socket of its own (ours is read-mostly).
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: PLC0415 (only the SITL mode needs it)

        self._mavlink2 = mavlink2
        self._mav = mavlink2.MAVLink(None, srcSystem=source_system, srcComponent=source_component)
        self._mav.robust_parsing = True  # a corrupt datagram is skipped, not raised
        self._lock = threading.Lock()
        self._newest: TruePose | None = None
        self._history: deque[TruePose] = deque()  # dated samples, oldest first, `_HISTORY_S` of them
        self._clock_ref: tuple[float, float] | None = None  # (time_boot s, arrival monotonic s) of the last ATTITUDE
        self._last_sim_state_s: float | None = None
        self._origin: Origin | None = None
        self._target: tuple[int, int] | None = None  # the autopilot's (system, component)
        self._last_request_s = {MSG_ID_SIM_STATE: -math.inf, MSG_ID_GPS_GLOBAL_ORIGIN: -math.inf,
                                MSG_ID_ATTITUDE: -math.inf}
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self.samples = 0  # SIM_STATEs used
        self.rejected = 0  # SIM_STATEs refused by `sample_problem`
        self.requests_sent = 0
        self.error: str | None = None  # why the reader stopped, if it did

    def start(self) -> SitlTruth:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise ConfigError(f"--sitl-truth {self.url!r}: cannot bind {self.host}:{self.port} ({exc.strerror}); "
                              "is another process (the controller?) on it?") from None
        sock.settimeout(_RECV_TIMEOUT_S)
        self._sock = sock
        self._thread = threading.Thread(target=self._read, name="sitl-truth", daemon=True)
        self._thread.start()
        log.info("SITL truth: listening for SIM_STATE on %s (read-only output of SITL; renders and judges only)",
                 self.url)
        return self

    def __enter__(self) -> SitlTruth:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def newest(self) -> TruePose | None:
        with self._lock:
            return self._newest

    def at(self, boot_s: float) -> TruePose | None:
        """The truth at the autopilot's time `boot_s`, interpolated between the dated samples around it
        (the nearest end when outside them); the newest sample while none is dated yet."""
        with self._lock:
            history, newest = list(self._history), self._newest
        if not history:
            return newest
        times = [p.boot_s for p in history]
        i = bisect.bisect_left(times, boot_s)
        if i == 0 or i == len(history):
            return history[min(i, len(history) - 1)]
        return interpolate(history[i - 1], history[i], boot_s)

    @property
    def origin(self) -> Origin | None:
        return self._origin

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    data, addr = self._sock.recvfrom(65536)
                except TimeoutError:
                    continue
                now = time.monotonic()
                for msg in self._mav.parse_buffer(data) or ():
                    self._handle(msg, addr, now)
        except OSError as exc:  # the socket failed under us: say so once, the sim sees the truth go stale
            self.error = f"SITL truth reader stopped: {exc}"
            log.warning("%s", self.error)

    def _handle(self, msg: Any, addr: tuple[str, int], now: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if msg.autopilot == MAV_AUTOPILOT_INVALID:
                return
            if self._target is None:  # the first autopilot heard is ours; another one is not followed
                self._target = (msg.get_srcSystem(), msg.get_srcComponent())
                log.info("SITL truth: autopilot system %d on %s", self._target[0], self.url)
            elif msg.get_srcSystem() != self._target[0]:
                return
            if self._origin is None:
                self._request(MSG_ID_GPS_GLOBAL_ORIGIN, addr, now)
            flowing = self._last_sim_state_s is not None and now - self._last_sim_state_s < _REQUEST_EVERY_S
            if not flowing:
                self._request(MSG_ID_SIM_STATE, addr, now)
            if self._clock_ref is None or now - self._clock_ref[1] > _REQUEST_EVERY_S:
                self._request(MSG_ID_ATTITUDE, addr, now)
        elif self._target is None or msg.get_srcSystem() != self._target[0]:
            return  # before the autopilot's heartbeat, or another system's: not ours
        elif kind == "GPS_GLOBAL_ORIGIN" and self._origin is None:
            self._origin = origin_from(msg)
            if self._origin is None:
                log.warning("SITL truth: GPS_GLOBAL_ORIGIN refused: %s", msg)
                return
            log.info("SITL truth origin (the EKF's): %.7f, %.7f at %.2f m AMSL, the ground",
                     self._origin.lat_e7 * 1e-7, self._origin.lon_e7 * 1e-7, self._origin.alt_amsl_m)
        elif kind == "ATTITUDE":
            self._clock_ref = (msg.time_boot_ms / 1000.0, now)
        elif kind == "SIM_STATE":
            self._last_sim_state_s = now
            problem = sample_problem(msg)
            if problem:
                self.rejected += 1
                if self.rejected == 1 or self.rejected % 500 == 0:
                    log.warning("SITL truth: SIM_STATE refused (%d so far): %s", self.rejected, problem)
                return
            if self._origin is None:
                return  # no frame to place it in yet (the EKF has no origin before its first fix)
            # Dated by the newest ATTITUDE plus the time since it arrived (the two come together).
            ref = self._clock_ref
            boot_s = None if ref is None or now - ref[1] > 1.0 else ref[0] + (now - ref[1])
            pose = true_pose(msg, self._origin, now, boot_s)
            with self._lock:
                self._newest = pose
                if boot_s is not None:
                    if self._history and boot_s <= self._history[-1].boot_s:
                        self._history.clear()  # the boot clock went back: SITL rebooted
                    self._history.append(pose)
                    while self._history and boot_s - self._history[0].boot_s > _HISTORY_S:
                        self._history.popleft()
            self.samples += 1

    def _request(self, msg_id: int, addr: tuple[str, int], now: float) -> None:
        """Ask the autopilot on this output for SIM_STATE at `rate_hz`, or once for the EKF origin;
        again after `_REQUEST_EVERY_S` while no answer comes (the ACK is not needed)."""
        if now - self._last_request_s[msg_id] < _REQUEST_EVERY_S:
            return
        system, component = self._target
        if msg_id in (MSG_ID_SIM_STATE, MSG_ID_ATTITUDE):
            cmd = (MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / self.rate_hz)
        else:
            cmd = (MAV_CMD_REQUEST_MESSAGE, msg_id, 0)
        packet = self._mav.command_long_encode(system, component, cmd[0], 0, cmd[1], cmd[2], 0, 0, 0, 0, 0).pack(self._mav)
        try:
            self._sock.sendto(packet, addr)
        except OSError as exc:
            log.warning("SITL truth: could not ask %s for message %d: %s", addr, msg_id, exc)
            return
        self._last_request_s[msg_id] = now
        self.requests_sent += 1
        log.log(logging.INFO if self.requests_sent <= 2 else logging.DEBUG,
                "SITL truth: asked system %d for message %d via %s:%d", system, msg_id, *addr)
