"""Can the autopilot arm yet? What a ground station reads before it offers the ARM button.

The MAVLink adapter's I/O thread feeds this tracker; `arm_and_takeoff` asks it what still blocks:

    SYS_STATUS          -> pre-arm check bit (MAV_SYS_STATUS_PREARM_CHECK): present + enabled means
                           the autopilot runs arming checks, healthy means they pass (both stacks)
    EKF_STATUS_REPORT   -> ArduPilot's estimator flags: attitude, velocities, relative horizontal
                           and vertical position must be good before guided flight makes sense
    HOME_POSITION       -> ArduPilot says "AHRS: waiting for home" until it has one; optional
    STATUSTEXT          -> the autopilot's own words ("PreArm: ...", "Arm: ...", "Preflight Fail: ...")
                           kept so a refusal or a give-up can name them

Readiness gates the first ARM attempt; the autopilot's answer to ARM stays the final word (the
checks it runs at arming are a superset of what it reports), so arming is retried with backoff.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass

from dovesei.controller.mavlink.proto import (
    EKF_ATTITUDE,
    EKF_FLAGS_NEEDED,
    EKF_POS_HORIZ_REL,
    EKF_POS_VERT_ABS,
    EKF_UNINITIALIZED,
    EKF_VELOCITY_HORIZ,
    EKF_VELOCITY_VERT,
    MAV_SYS_STATUS_PREARM_CHECK,
    SEVERITY_NAMES,
)

_EKF_NAMES = {EKF_ATTITUDE: "attitude", EKF_VELOCITY_HORIZ: "horizontal velocity",
              EKF_VELOCITY_VERT: "vertical velocity", EKF_POS_HORIZ_REL: "relative horizontal position",
              EKF_POS_VERT_ABS: "vertical position"}
# Texts that explain a refusal to arm, in either autopilot's wording.
_PREARM_PREFIXES = ("prearm", "arm:", "arming", "preflight", "ekf", "ahrs", "need", "waiting")
_WARNING = 4  # MAV_SEVERITY_WARNING: this and more severe explain refusals too


@dataclass(frozen=True)
class StatusText:
    """One STATUSTEXT as received (recv_s on time.monotonic)."""

    recv_s: float
    severity: int
    text: str

    @property
    def severity_name(self) -> str:
        return SEVERITY_NAMES[self.severity] if 0 <= self.severity < len(SEVERITY_NAMES) else str(self.severity)


class ArmReadiness:
    """Thread-safe record of what the autopilot reports about its readiness to arm."""

    def __init__(self, *, require_home: bool = True, history: int = 32) -> None:
        self.require_home = require_home
        self._lock = threading.Lock()
        self._sys_status_seen = False
        self._prearm_reported = False  # the autopilot runs pre-arm checks and says so
        self._prearm_ok = False
        self._ekf_flags: int | None = None  # None: the autopilot sends no EKF_STATUS_REPORT
        self._home = False
        self._texts: deque[StatusText] = deque(maxlen=history)

    def on_sys_status(self, present: int, enabled: int, health: int) -> None:
        with self._lock:
            self._sys_status_seen = True
            self._prearm_reported = bool(present & enabled & MAV_SYS_STATUS_PREARM_CHECK)
            self._prearm_ok = bool(health & MAV_SYS_STATUS_PREARM_CHECK)

    def on_ekf_status(self, flags: int) -> None:
        with self._lock:
            self._ekf_flags = int(flags)

    def on_home(self) -> None:
        with self._lock:
            self._home = True

    def on_statustext(self, severity: int, text: str) -> StatusText:
        item = StatusText(time.monotonic(), int(severity), text)
        with self._lock:
            self._texts.append(item)
        return item

    @property
    def has_home(self) -> bool:
        with self._lock:
            return self._home

    def blockers(self) -> list[str]:
        """What still stands between the autopilot and arming (empty: try to arm)."""
        with self._lock:
            out = []
            if not self._sys_status_seen:
                out.append("no SYS_STATUS from the autopilot yet")
            elif self._prearm_reported and not self._prearm_ok:
                out.append("pre-arm checks failing (SYS_STATUS)")
            flags = self._ekf_flags
            if flags is not None:
                missing = [name for bit, name in _EKF_NAMES.items() if not flags & bit]
                if flags & EKF_UNINITIALIZED or flags & EKF_FLAGS_NEEDED != EKF_FLAGS_NEEDED:
                    out.append("EKF not ready" + (f" (no {', '.join(missing)})" if missing else " (uninitialised)"))
            if self.require_home and not self._home:
                out.append("no home position yet")
            return out

    def reasons(self, within_s: float = 30.0, most: int = 4) -> list[str]:
        """The newest distinct pre-arm texts of the last `within_s` seconds, oldest first."""
        now = time.monotonic()
        with self._lock:
            texts = [t for t in self._texts if now - t.recv_s <= within_s]
        picked: list[str] = []
        for t in reversed(texts):
            lowered = t.text.lower()
            if (t.severity <= _WARNING or lowered.startswith(_PREARM_PREFIXES)) and t.text not in picked:
                picked.append(t.text)
            if len(picked) >= most:
                break
        return list(reversed(picked))

    def statustexts(self) -> list[StatusText]:
        with self._lock:
            return list(self._texts)
