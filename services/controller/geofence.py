"""A circular fence around the start on the dead-reckoned position: no policy flies away.

The paper's policy (`dovesei`, REFERENCE.md) has a RESTARTING move that flies 60 s in one
direction at up to 10 m/s: against ArduCopter SITL that was a ~600 m blind transit at 38-53 m that
left the world in 2 of 4 flights. Nothing in a policy bounds it, so the controller's core does,
for every policy, on the only position it has without GNSS: the autopilot's velocity estimate
integrated from the start (never the simulator's truth, never a GNSS fix).

    each new state --add(t, vel FRD, yaw)--> north/east from the start (trapezoidal)
    each command   --cap(vel FRD, yaw)-----> outward speed <= gain x (radius - distance), pulled
                                             back in beyond the radius (at most max_inward_m_s);
                                             tangential, inward and vertical motion untouched

The cap slows the vehicle as it nears the fence, so a lagging vehicle does not overshoot it. The
estimate drifts with the velocity estimate's bias: the radius is what the operator can afford of
the true track, less that drift.
"""

from __future__ import annotations

import math

from dovesei.shared.frames import to_body, to_ne


def cap_outward(north_m: float, east_m: float, vel_ne_m_s: tuple[float, float], radius_m: float,
                gain_per_s: float, max_inward_m_s: float = math.inf) -> tuple[tuple[float, float], bool]:
    """The north/east velocity with its outward (away from the origin) component capped at
    gain x (radius - distance), never below -max_inward_m_s; True when capped."""
    r = math.hypot(north_m, east_m)
    if r < 1e-6:
        return vel_ne_m_s, False
    vn, ve = vel_ne_m_s
    un, ue = north_m / r, east_m / r
    outward = vn * un + ve * ue
    allowed = max(gain_per_s * (radius_m - r), -max_inward_m_s)
    if outward <= allowed:
        return vel_ne_m_s, False
    return (vn - (outward - allowed) * un, ve - (outward - allowed) * ue), True


class Geofence:
    """The dead-reckoned distance from the start and the cap on every command (pure, data clock)."""

    def __init__(self, radius_m: float, gain_per_s: float = 0.5, max_inward_m_s: float = 2.0) -> None:
        self.radius_m, self.gain_per_s, self.max_inward_m_s = radius_m, gain_per_s, max_inward_m_s
        self.north_m = self.east_m = 0.0
        self._last: tuple[float, float, float] | None = None  # t_s, vn, ve of the newest state
        self.clipped = 0  # commands capped so far

    @property
    def distance_m(self) -> float:
        return math.hypot(self.north_m, self.east_m)

    def add(self, t_s: float, vel_body_frd_m_s: tuple[float, float, float], yaw_rad: float) -> None:
        """One vehicle state; the same or an older stamp adds nothing (time going back is no motion)."""
        vn, ve = to_ne(vel_body_frd_m_s[0], vel_body_frd_m_s[1], yaw_rad)
        if self._last is not None:
            t0, vn0, ve0 = self._last
            dt = t_s - t0
            if dt <= 0.0:
                return
            # Across a gap in the states the mean of the velocities either side is the best guess:
            # a fence that forgot the gap would let the vehicle past it.
            self.north_m += 0.5 * (vn0 + vn) * dt
            self.east_m += 0.5 * (ve0 + ve) * dt
        self._last = (t_s, vn, ve)

    def cap(self, vel_body_frd_m_s: tuple[float, float, float], yaw_rad: float,
            pull_back: bool = True) -> tuple[tuple[float, float, float], str | None]:
        """The command within the fence, and why it was capped (None: untouched). Without
        `pull_back` (a watchdog's hold: blind or stale) a vehicle beyond the fence is only kept
        from going farther, never moved."""
        fwd, right, down = vel_body_frd_m_s
        ne = to_ne(fwd, right, yaw_rad)
        (vn, ve), capped = cap_outward(self.north_m, self.east_m, ne, self.radius_m, self.gain_per_s,
                                       self.max_inward_m_s if pull_back else 0.0)
        if not capped:
            return vel_body_frd_m_s, None
        self.clipped += 1
        f, r = to_body(vn, ve, yaw_rad)
        reason = (f"geofence: {self.distance_m:.0f} m from the start by dead reckoning (radius {self.radius_m:g} m): "
                  f"horizontal speed {math.hypot(*ne):.1f} -> {math.hypot(vn, ve):.1f} m/s")
        return (f, r, down), reason
