"""Body and level frames: forward/right (body, the camera's up/right) <-> north/east, by heading;
and the full attitude rotation (body FRD <-> NED) where roll and pitch matter.

Heading (yaw) 0 is north and grows towards east; the camera looks straight down, so image up is
body forward and image right is body right.
"""

from __future__ import annotations

import math


def to_ne(forward: float, right: float, yaw_rad: float) -> tuple[float, float]:
    """Body forward/right -> north/east for a heading `yaw_rad` (0 = north, + = towards east)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return forward * c - right * s, forward * s + right * c


def to_body(north: float, east: float, yaw_rad: float) -> tuple[float, float]:
    """North/east -> body forward/right."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return north * c + east * s, -north * s + east * c


def _rows(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[tuple[float, float, float], ...]:
    """R_ned<-body for ZYX Euler angles (MAVLink's ATTITUDE), row by row."""
    cr, sr, cp, sp = math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return ((cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy),
            (cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy),
            (-sp, sr * cp, cr * cp))


def body_frd_to_ned(vec_frd: tuple[float, ...], roll_rad: float, pitch_rad: float,
                    yaw_rad: float) -> tuple[float, float, float]:
    """Rotate a body FRD vector into NED (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    f, r, d = (float(v) for v in vec_frd)
    rows = _rows(roll_rad, pitch_rad, yaw_rad)
    return tuple(a * f + b * r + c * d for a, b, c in rows)  # type: ignore[return-value]


def ned_to_body_frd(vec_ned: tuple[float, ...], roll_rad: float, pitch_rad: float,
                    yaw_rad: float) -> tuple[float, float, float]:
    """Rotate a NED vector into the body FRD frame (the transpose of `body_frd_to_ned`)."""
    n, e, d = (float(v) for v in vec_ned)
    rows = _rows(roll_rad, pitch_rad, yaw_rad)
    return tuple(rows[0][i] * n + rows[1][i] * e + rows[2][i] * d for i in range(3))  # type: ignore[return-value]
