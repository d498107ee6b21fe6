"""The autopilot's velocity estimate integrated into a level north/east track, read between two
capture stamps.

A heatmap describes the ground at its frame's CAPTURE time, and reaches the policy a perception
latency later (0.4 s with CLIPSeg on a ground station). Dead reckoning with the velocity of the
tick the heatmap arrives on is then wrong whenever the vehicle accelerates: in a turn from +8 to
-7 m/s the velocity 0.4 s late differs by up to 1.6 m/s, and the position the policy predicts for
the frame ran ~10 m ahead of the truth after each turn of a search pattern (replayed on the
suite's Dubai world), which registration then "corrected" into a fake velocity bias. Here every
accepted vehicle state adds its velocity (body FRD rotated by its own heading) to a track, kept
for `keep_s`, and the policy is given the displacement between the previous frame's capture and
this one's, which is exactly what its registration measures.

    tick(state) --add(t, vel FRD, yaw)--> track of (t, north, east)   (trapezoidal integration)
    heatmap captured at t1 --displacement(t0, t1)--> (north, east) metres, or None when the track
                                                     does not cover [t0, t1]
A gap in the states longer than `max_gap_s` (or time running backwards) restarts the track: a
displacement is never invented across it.

The same holds for the attitude: the heatmap is the ground as the camera saw it at capture, so the
policy must place it with the attitude AT CAPTURE. With a camera fixed to the body, the attitude
of the tick the heatmap arrives on is wrong by whatever the vehicle turned in the perception
latency: accelerating at 2.5 m/s^2 (ArduCopter's WPNAV_ACCEL) tilts it ~15 deg, which at 100 m
moves where the image centre looks by ~26 m. On the default `dovesei up --policy clearance` start
(realistic vehicle) a frame captured level reached the policy with the pitch of a vehicle leaning
into a probe (-14.6 deg): the policy's estimate jumped 20 m against the truth, the approach then
oscillated at +-15 deg of tilt and every lock was lost. The track keeps each state's roll, pitch
and heading too and gives them at a capture stamp (`attitude_at`).
"""

from __future__ import annotations

import bisect
import math

from dovesei.shared.frames import to_ne


class VelocityTrack:
    """A short history of the integrated velocity estimate; pure, on the data clock."""

    def __init__(self, keep_s: float = 10.0, max_gap_s: float = 1.0, extrapolate_s: float = 0.25) -> None:
        self.keep_s, self.max_gap_s, self.extrapolate_s = keep_s, max_gap_s, extrapolate_s
        self.reset()

    def reset(self) -> None:
        self._t: list[float] = []
        self._n: list[float] = []
        self._e: list[float] = []
        self._att: list[tuple[float, float, float]] = []  # (roll, pitch, yaw) radians per stamp
        self._v: tuple[float, float] = (0.0, 0.0)  # the newest north/east velocity

    def add(self, t_s: float, vel_body_frd_m_s: tuple[float, float, float], yaw_rad: float,
            roll_rad: float = 0.0, pitch_rad: float = 0.0) -> None:
        """One vehicle state (its stamp, velocity estimate, heading and attitude). The same stamp
        again is ignored; an older one (time went back) or one after a gap of more than
        `max_gap_s` restarts the track."""
        vn, ve = to_ne(vel_body_frd_m_s[0], vel_body_frd_m_s[1], yaw_rad)
        if self._t:
            dt = t_s - self._t[-1]
            if dt == 0.0:
                return
            if dt < 0.0 or dt > self.max_gap_s:
                self.reset()
        if not self._t:
            self._t, self._n, self._e, self._att = [t_s], [0.0], [0.0], [(roll_rad, pitch_rad, yaw_rad)]
        else:
            dt = t_s - self._t[-1]
            self._t.append(t_s)
            self._n.append(self._n[-1] + 0.5 * (self._v[0] + vn) * dt)
            self._e.append(self._e[-1] + 0.5 * (self._v[1] + ve) * dt)
            self._att.append((roll_rad, pitch_rad, yaw_rad))
            # Forget what is older than keep_s (in chunks: a list pop(0) per state would be O(n)).
            if self._t[0] < t_s - 2.0 * self.keep_s:
                cut = bisect.bisect_left(self._t, t_s - self.keep_s)
                del self._t[:cut], self._n[:cut], self._e[:cut], self._att[:cut]
        self._v = (vn, ve)

    def _at(self, t_s: float) -> tuple[float, float] | None:
        if not self._t or t_s < self._t[0]:
            return None
        last = self._t[-1]
        if t_s >= last:
            ahead = t_s - last
            if ahead > self.extrapolate_s:
                return None
            return self._n[-1] + self._v[0] * ahead, self._e[-1] + self._v[1] * ahead
        i = bisect.bisect_right(self._t, t_s)  # _t[i-1] <= t_s < _t[i]
        t0, t1 = self._t[i - 1], self._t[i]
        w = (t_s - t0) / (t1 - t0)
        return self._n[i - 1] + w * (self._n[i] - self._n[i - 1]), self._e[i - 1] + w * (self._e[i] - self._e[i - 1])

    def displacement_ne_m(self, t0_s: float, t1_s: float) -> tuple[float, float] | None:
        """North/east metres the estimate integrates to from t0 to t1; None when not covered."""
        a, b = self._at(t0_s), self._at(t1_s)
        if a is None or b is None:
            return None
        return b[0] - a[0], b[1] - a[1]

    def attitude_at(self, t_s: float) -> tuple[float, float, float] | None:
        """(roll, pitch, yaw) radians at `t_s`, linear between the two states around it (the
        heading along the shorter way round); the newest within `extrapolate_s` after it; None
        when the track does not cover `t_s`."""
        if not self._t or t_s < self._t[0] or t_s > self._t[-1] + self.extrapolate_s:
            return None
        if t_s >= self._t[-1]:
            return self._att[-1]
        i = bisect.bisect_right(self._t, t_s)  # _t[i-1] <= t_s < _t[i]
        t0, t1 = self._t[i - 1], self._t[i]
        w = (t_s - t0) / (t1 - t0)
        (r0, p0, y0), (r1, p1, y1) = self._att[i - 1], self._att[i]
        yaw = y0 + w * math.remainder(y1 - y0, 2.0 * math.pi)
        return r0 + w * (r1 - r0), p0 + w * (p1 - p0), math.remainder(yaw, 2.0 * math.pi)
