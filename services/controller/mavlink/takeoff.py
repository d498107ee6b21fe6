"""Takeoff the way a ground station does it: wait until the autopilot can arm, arm, climb.

Only ever called when the user asked for a takeoff (the controller's `--takeoff-alt-m`):

    wait for readiness (ArmReadiness: SYS_STATUS pre-arm bit, EKF flags, home) --timeout--> give up,
        naming what still blocks and the autopilot's last pre-arm STATUSTEXTs
    ArduPilot: GUIDED -> ARM (retried with backoff 1, 2, 4, 8 s) -> NAV_TAKEOFF(alt) -> wait for alt
    PX4:       zero setpoints streaming -> OFFBOARD -> ARM (same retries) -> climb velocity -> zero

PX4 goes through OFFBOARD rather than AUTO.TAKEOFF because its NAV_TAKEOFF takes an AMSL altitude
(a global position), which a GNSS-free vehicle does not have; OFFBOARD with a velocity climb needs
only the local estimate it flies on anyway. Arming is retried because the autopilot runs more checks
at arming time than it reports beforehand; every refusal is logged with the autopilot's reasons.
The climb limit follows the altitude: `30 s + 2 x alt / climb rate` unless given.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Protocol

from dovesei.controller.mavlink.proto import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_RESULT_ACCEPTED,
    MSG_ID_HOME_POSITION,
    NotSteerableError,
)
from dovesei.controller.mavlink.readiness import ArmReadiness
from dovesei.shared import validate
from dovesei.shared.messages import Stamp, VelocityCommand

log = logging.getLogger(__name__)

_BACKOFF_FIRST_S, _BACKOFF_MAX_S = 1.0, 8.0
_WAIT_LOG_PERIOD_S = 5.0
_TOP_FRACTION = 0.95  # the climb counts as done at 95 % of the target altitude


class TakeoffLink(Protocol):
    """What the takeoff sequence uses of the adapter (`MavlinkVehicle`): public members only."""

    vehicle_id: str
    read_only: bool
    readiness: ArmReadiness

    @property
    def armed(self) -> bool: ...

    @property
    def mode(self) -> str: ...

    @property
    def lost_reason(self) -> str | None: ...

    @property
    def closed(self) -> bool: ...

    def altitude_m(self) -> float | None: ...

    def pause(self, seconds: float) -> bool: ...

    def connected_autopilot(self) -> str: ...

    def command_long(self, command: int, *params: float) -> None: ...

    def command_long_wait(self, command: int, *params: float, timeout_s: float) -> int | None: ...

    def wait_armed(self, timeout_s: float) -> bool: ...

    def set_mode(self, name: str, timeout_s: float = 3.0) -> bool: ...

    def send(self, cmd: VelocityCommand) -> None: ...

    def zero_command(self) -> VelocityCommand: ...

    def prestreaming(self) -> AbstractContextManager[None]: ...


def _check_alive(v: TakeoffLink) -> None:
    if v.closed:
        raise NotSteerableError("takeoff aborted: the MAVLink adapter was closed")
    lost = v.lost_reason
    if lost is not None:
        raise NotSteerableError(f"takeoff aborted: {lost}")


def _said(v: TakeoffLink) -> str:
    reasons = v.readiness.reasons()
    return "; ".join(f"'{r}'" for r in reasons) if reasons else "nothing"


def wait_until_ready(v: TakeoffLink, deadline_s: float, ready_timeout_s: float) -> None:
    """Block until nothing in ArmReadiness blocks arming, or raise at the deadline."""
    next_log_s = next_home_s = 0.0
    while True:
        _check_alive(v)
        blockers = v.readiness.blockers()
        if not blockers:
            log.info("autopilot reports it can arm")
            return
        now = time.monotonic()
        if now >= deadline_s:
            raise NotSteerableError(f"the autopilot was not ready to arm within {ready_timeout_s:.0f} s: "
                                    f"{'; '.join(blockers)}; its last pre-arm messages: {_said(v)}")
        if not v.readiness.has_home and now >= next_home_s:
            # ArduPilot sends HOME_POSITION on request (and when home changes), not on a stream.
            v.command_long(MAV_CMD_REQUEST_MESSAGE, float(MSG_ID_HOME_POSITION))
            next_home_s = now + 2.0
        if now >= next_log_s:
            log.info("waiting before arming: %s (autopilot says %s)", "; ".join(blockers), _said(v))
            next_log_s = now + _WAIT_LOG_PERIOD_S
        v.pause(0.1)


def arm_with_backoff(v: TakeoffLink, deadline_s: float) -> None:
    """ARM, retried after 1, 2, 4, 8, 8... s while the deadline allows; raise naming the reasons."""
    delay_s, attempt = _BACKOFF_FIRST_S, 0
    while True:
        _check_alive(v)
        attempt += 1
        log.info("arming (requested explicitly), attempt %d", attempt)
        result = v.command_long_wait(MAV_CMD_COMPONENT_ARM_DISARM, 1.0, timeout_s=3.0)
        if result == MAV_RESULT_ACCEPTED and v.wait_armed(3.0):
            log.info("armed")
            return
        if time.monotonic() + delay_s > deadline_s:
            raise NotSteerableError(f"the autopilot refused to arm {attempt} time(s) (last MAV_RESULT {result}); "
                                    f"its last pre-arm messages: {_said(v)}")
        log.warning("arming refused (MAV_RESULT %s; autopilot says %s): retrying in %.0f s", result, _said(v),
                    delay_s)
        if v.pause(delay_s):
            raise NotSteerableError("takeoff aborted: the MAVLink adapter was closed")
        delay_s = min(2.0 * delay_s, _BACKOFF_MAX_S)


def arm_and_takeoff(v: TakeoffLink, alt_m: float, *, climb_timeout_s: float | None, ready_timeout_s: float,
                    climb_rate_m_s: float) -> None:
    """See `MavlinkVehicle.arm_and_takeoff`."""
    if v.read_only:
        raise NotSteerableError("read-only MAVLink adapter: arm_and_takeoff refused")
    alt_m = validate.in_range("takeoff altitude (m)", alt_m, 1.0, 500.0)
    ready_timeout_s = validate.positive("takeoff ready timeout (s)", ready_timeout_s)
    climb_rate_m_s = validate.positive("takeoff climb rate (m/s)", climb_rate_m_s)
    if climb_timeout_s is None:
        climb_timeout_s = 30.0 + 2.0 * alt_m / climb_rate_m_s
    climb_timeout_s = validate.positive("takeoff climb timeout (s)", climb_timeout_s)
    autopilot = v.connected_autopilot()
    current = v.altitude_m()
    if v.armed and current is not None and current >= _TOP_FRACTION * alt_m:
        log.info("takeoff skipped: already armed at %.1f m (asked for %.1f m)", current, alt_m)
        return
    deadline_s = time.monotonic() + ready_timeout_s
    wait_until_ready(v, deadline_s, ready_timeout_s)
    if autopilot == "ardupilot":
        _ardupilot(v, alt_m, deadline_s, climb_timeout_s)
    else:
        _px4(v, alt_m, deadline_s, climb_timeout_s, climb_rate_m_s)
    log.info("takeoff complete at %.1f m", v.altitude_m() or float("nan"))


def _wait_climb(v: TakeoffLink, alt_m: float, climb_timeout_s: float,
                step: Callable[[float | None], None] | None = None) -> None:
    deadline_s = time.monotonic() + climb_timeout_s
    while True:
        _check_alive(v)
        current = v.altitude_m()
        if current is not None and current >= _TOP_FRACTION * alt_m:
            return
        if time.monotonic() >= deadline_s:
            shown = f"{current:.1f} m" if current is not None else "no altitude"
            raise NotSteerableError(f"takeoff to {alt_m:g} m did not complete within {climb_timeout_s:.0f} s "
                                    f"(at {shown}; mode {v.mode}, {'armed' if v.armed else 'disarmed'})")
        if step is not None:
            step(current)
        v.pause(0.1)


def _ardupilot(v: TakeoffLink, alt_m: float, deadline_s: float, climb_timeout_s: float) -> None:
    if not v.set_mode("GUIDED"):
        raise NotSteerableError(f"the autopilot did not enter GUIDED for takeoff (mode {v.mode})")
    arm_with_backoff(v, deadline_s)
    result = v.command_long_wait(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, float(alt_m), timeout_s=3.0)
    if result != MAV_RESULT_ACCEPTED:
        raise NotSteerableError(f"the autopilot refused NAV_TAKEOFF to {alt_m:g} m (MAV_RESULT {result}); "
                                f"it says {_said(v)}")
    _wait_climb(v, alt_m, climb_timeout_s)


def _px4(v: TakeoffLink, alt_m: float, deadline_s: float, climb_timeout_s: float, climb_rate_m_s: float) -> None:
    with v.prestreaming():  # PX4 enters OFFBOARD only while setpoints already stream
        v.pause(0.3)
        if not v.set_mode("OFFBOARD"):
            raise NotSteerableError(f"the autopilot did not enter OFFBOARD for takeoff (mode {v.mode}); "
                                    f"it says {_said(v)}")
        arm_with_backoff(v, deadline_s)

        def climb(current: float | None) -> None:
            error_m = alt_m - (current or 0.0)
            # Slow down over the last metres so the top is not overshot.
            up_m_s = min(climb_rate_m_s, max(0.3, 0.5 * error_m))
            v.send(VelocityCommand(vehicle_id=v.vehicle_id, seq=-1, stamp=Stamp(0.0, "vehicle"),
                                   vel_body_frd_m_s=(0.0, 0.0, -up_m_s)))

        _wait_climb(v, alt_m, climb_timeout_s, climb)
        v.send(v.zero_command())
