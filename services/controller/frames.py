"""Body and level frames: forward/right (body, the camera's up/right) <-> north/east, by heading.

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
