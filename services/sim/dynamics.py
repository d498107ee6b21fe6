"""Vehicle dynamics: a multirotor tracking body-frame velocity commands, as an autopilot does.

Data flow per `Vehicle.step(dt_s, cmd, yaw_rate, cmd_t_s)`:

    command (body FRD, m/s) --stale?--> zero (brake to hover)
        -> rotate by heading into NED -> clip to the speed limits
        -> first-order velocity loop, its change clipped by the acceleration limits
           (horizontal: min(accel limit, g * tan(tilt limit))) and, when a jerk limit is set,
           the change of that acceleration clipped by jerk x dt (ArduCopter's shaped velocity)
        -> / (1 + scale_error) + wind (constant + Ornstein-Uhlenbeck gusts) + drift (random walk)
           = ground velocity
        -> integrate position (world frame: x_m east, y_m north, alt_agl_m up; ground at 0)
        -> attitude: the roll and pitch that tilt the thrust to give the horizontal acceleration
           (plus linear drag on the vehicle's own velocity), for a camera fixed to the body

The velocity the autopilot controls (`vel_own_ned_m_s`) is relative to a frame that the
disturbances move: without GNSS the vehicle cannot see wind or estimator drift, so a hover
command still drifts at wind + drift. `scale_error` is the estimate's scale error: an autopilot
whose velocity estimate reads (1 + e) x the truth tracks its commands on that estimate, so it truly
flies its own velocity / (1 + e). The speed and acceleration limits bound the vehicle's own
velocity; `Pose.vel_ned_m_s` is the ground velocity and includes the disturbances.

An autopilot that fuses an external ground-velocity measurement (ArduCopter's EKF3 with a source
set whose VELXY is ExternalNav, fed VISION_SPEED_ESTIMATE: the camera's visual velocity) learns
what moves its frame: `fuse_ground_velocity(measured, dt, tau)` moves a correction toward the
innovation (measured - own, the error of what it believes it flies), and the correction comes off
the ground velocity: own / (1 + e) + disturbances - correction. With an exact measurement at a
steady state it converges on the disturbances and the scale error, so the vehicle truly flies its
commands; a measurement's own error (a heading error, noise, a wrong altitude) is what remains.

With the defaults (no jerk limit, scale error 0, no wind) the arithmetic is exactly that of the
model before these were added: the `ideal` vehicle profile relies on it.

Deterministic: the only randomness (gusts, drift) comes from one numpy Generator seeded at
construction, so the same seed and the same sequence of steps give the same trajectory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from dovesei.shared import validate
from dovesei.shared.errors import ConfigError, DoveseiError

GRAVITY_M_S2 = 9.80665


class DynamicsError(DoveseiError, ValueError):
    """Bad vehicle parameters or a bad step (non-finite command, non-positive dt)."""


@dataclass(frozen=True)
class VehicleParams:
    """Limits and disturbances of the simulated multirotor (defaults: a typical 2-5 kg quad)."""

    max_speed_h_m_s: float = 15.0
    max_speed_v_m_s: float = 5.0
    max_accel_h_m_s2: float = 4.0
    max_accel_v_m_s2: float = 3.0
    max_tilt_deg: float = 35.0  # caps horizontal acceleration at g * tan(tilt)
    max_yaw_rate_rad_s: float = math.radians(60.0)
    vel_time_constant_s: float = 0.3  # the autopilot's velocity loop, before acceleration limits
    cmd_timeout_s: float = 0.5  # a command older than this is dropped and the vehicle brakes
    wind_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)  # uncompensated mean drift
    gust_sigma_m_s: float = 0.0  # stationary std of each horizontal gust component
    gust_time_constant_s: float = 5.0
    drift_sigma_m_s_sqrt_s: float = 0.0  # random-walk velocity disturbance, per horizontal axis
    jerk_limit_h_m_s3: float | None = None  # None: the acceleration may step (the original model)
    scale_error: float = 0.0  # the velocity estimate reads (1 + e) x the truth; see the module docstring
    drag_per_s: float = 0.0  # linear drag: only the attitude sees it (the autopilot's loop absorbs it)
    max_descent_m_s: float | None = None  # None: max_speed_v_m_s both ways (ArduCopter: WPNAV_SPEED_DN)

    def __post_init__(self) -> None:
        positive = ("max_speed_h_m_s", "max_speed_v_m_s", "max_accel_h_m_s2", "max_accel_v_m_s2",
                    "max_yaw_rate_rad_s", "vel_time_constant_s", "cmd_timeout_s", "gust_time_constant_s")
        try:
            for name in positive:
                validate.positive(f"VehicleParams.{name}", getattr(self, name))
            for name in ("gust_sigma_m_s", "drift_sigma_m_s_sqrt_s", "drag_per_s"):
                validate.non_negative(f"VehicleParams.{name}", getattr(self, name))
            for name in ("jerk_limit_h_m_s3", "max_descent_m_s"):
                if getattr(self, name) is not None:
                    validate.positive(f"VehicleParams.{name}", getattr(self, name))
            validate.in_range("VehicleParams.scale_error", self.scale_error, -0.5, 0.5)
            validate.finite_vector("VehicleParams.wind_ned_m_s", self.wind_ned_m_s, 3)
        except ConfigError as exc:
            raise DynamicsError(str(exc)) from None
        if not (validate.is_number(self.max_tilt_deg) and 0.0 < self.max_tilt_deg < 90.0):
            raise DynamicsError(f"VehicleParams.max_tilt_deg must be in (0, 90), got {self.max_tilt_deg!r}")

    @property
    def accel_limit_h_m_s2(self) -> float:
        """The horizontal acceleration actually available: the tilt limit may be the tighter one."""
        return min(self.max_accel_h_m_s2, GRAVITY_M_S2 * math.tan(math.radians(self.max_tilt_deg)))


@dataclass(frozen=True)
class Pose:
    """Where the vehicle is: world frame position, ground velocity (NED), heading, sim time."""

    x_m: float  # east of the world image's left edge
    y_m: float  # north of the world image's bottom edge
    alt_agl_m: float
    vel_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)  # ground velocity, down positive
    yaw_rad: float = 0.0  # heading: 0 north, +pi/2 east
    t_s: float = 0.0
    roll_rad: float = 0.0  # FRD body attitude from the dynamics (right wing down > 0)
    pitch_rad: float = 0.0  # nose up > 0

    def vel_body_frd_m_s(self) -> tuple[float, float, float]:
        """Ground velocity in the body frame (forward, right, down), as a flight controller reports it."""
        n, e, d = self.vel_ned_m_s
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return (c * n + s * e, -s * n + c * e, d)


def body_frd_to_ned(vel_frd: tuple[float, float, float], yaw_rad: float) -> np.ndarray:
    """Rotate a body-frame (forward, right, down) vector into NED by the heading (level flight)."""
    f, r, d = vel_frd
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([c * f - s * r, s * f + c * r, d], dtype=np.float64)


def wrap_angle_rad(a: float) -> float:
    """An angle in (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


class Vehicle:
    """A multirotor under velocity control with limits, command timeout and disturbances."""

    def __init__(self, state: Pose, params: VehicleParams = VehicleParams(), seed: int = 0) -> None:
        for name in ("x_m", "y_m", "alt_agl_m", "yaw_rad", "t_s"):
            if not validate.is_number(getattr(state, name)):
                raise DynamicsError(f"initial Pose.{name} must be finite, got {getattr(state, name)!r}")
        if state.alt_agl_m < 0:
            raise DynamicsError(f"initial alt_agl_m must be >= 0 (ground), got {state.alt_agl_m}")
        self.params = params
        self._rng = np.random.default_rng(seed)
        self._gust_ned = np.zeros(3)
        self._drift_ned = np.zeros(3)
        self._nav_correction_ned = np.zeros(3)  # what fused ground-velocity measurements took off (horizontal)
        wind = np.asarray(params.wind_ned_m_s, dtype=np.float64)
        # The state's velocity is over ground; what the autopilot itself flies is that minus wind
        # (so a vehicle hovering in the wind starts with vel_ned_m_s = wind_ned_m_s).
        self._vel_own_ned = np.asarray(state.vel_ned_m_s, dtype=np.float64) - wind
        self._accel_own_ned = np.zeros(3)  # the last step's own acceleration (for the jerk limit)
        self._state = replace(state, yaw_rad=wrap_angle_rad(state.yaw_rad))
        self.last_command_stale = True  # did the last step brake because no fresh command existed?

    @property
    def state(self) -> Pose:
        return self._state

    @property
    def vel_own_ned_m_s(self) -> tuple[float, float, float]:
        """The velocity the autopilot controls (ground velocity minus wind, gusts and drift)."""
        return tuple(float(v) for v in self._vel_own_ned)

    @property
    def nav_correction_ned_m_s(self) -> tuple[float, float, float]:
        """The correction the fused ground-velocity measurements have learnt (0 without any)."""
        return tuple(float(v) for v in self._nav_correction_ned)

    def fuse_ground_velocity(self, measured_ne_m_s: tuple[float, float], dt_s: float, tau_s: float,
                             max_m_s: float = 10.0) -> None:
        """Fuse one horizontal ground-velocity measurement (north, east; m/s) covering `dt_s`: the
        correction moves toward the innovation by dt / tau (a first-order filter with time
        constant `tau_s`, the EKF's convergence), its size held within `max_m_s`."""
        if not (validate.is_number(dt_s) and dt_s > 0 and validate.is_number(tau_s) and tau_s > 0):
            raise DynamicsError(f"fusion dt_s and tau_s must be finite and > 0, got {dt_s!r}, {tau_s!r}")
        if len(measured_ne_m_s) != 2 or not all(validate.is_number(v) for v in measured_ne_m_s):
            raise DynamicsError(f"a fused ground velocity must be 2 finite numbers, got {measured_ne_m_s!r}")
        innovation = np.asarray(measured_ne_m_s, dtype=np.float64) - self._vel_own_ned[:2]
        corr = self._nav_correction_ned[:2] + min(1.0, dt_s / tau_s) * innovation
        size = math.hypot(corr[0], corr[1])
        if size > max_m_s:
            corr *= max_m_s / size
        self._nav_correction_ned[:2] = corr

    def step(
        self,
        dt_s: float,
        cmd_vel_body_frd_m_s: tuple[float, float, float] | None,
        cmd_yaw_rate_rad_s: float = 0.0,
        cmd_t_s: float | None = None,
    ) -> Pose:
        """Advance dt_s seconds under the newest command (issued at sim time cmd_t_s); returns the new state.

        A missing command (None, or no cmd_t_s), or one older than `cmd_timeout_s` at the start of the
        step, is replaced by zero velocity and zero yaw rate: the vehicle brakes to a hover instead
        of flying on.
        """
        p = self.params
        if not (validate.is_number(dt_s) and dt_s > 0):
            raise DynamicsError(f"dt_s must be finite and > 0, got {dt_s!r}")
        st = self._state
        stale = cmd_vel_body_frd_m_s is None or cmd_t_s is None or st.t_s - cmd_t_s > p.cmd_timeout_s
        self.last_command_stale = stale
        if stale:
            cmd_frd, yaw_rate = (0.0, 0.0, 0.0), 0.0
        else:
            cmd_frd, yaw_rate = tuple(cmd_vel_body_frd_m_s), cmd_yaw_rate_rad_s
            if len(cmd_frd) != 3 or not all(validate.is_number(v) for v in (*cmd_frd, yaw_rate)):
                raise DynamicsError(f"command must be 3 finite velocities and a finite yaw rate, "
                                    f"got {cmd_vel_body_frd_m_s!r}, {cmd_yaw_rate_rad_s!r}")

        yaw_rate = min(max(yaw_rate, -p.max_yaw_rate_rad_s), p.max_yaw_rate_rad_s)
        yaw_new = wrap_angle_rad(st.yaw_rad + yaw_rate * dt_s)
        # The command is in the body frame of the moment it is applied: use the mid-step heading.
        target = body_frd_to_ned(cmd_frd, st.yaw_rad + 0.5 * yaw_rate * dt_s)
        target = self._clip_velocity(target)

        # First-order loop integrated exactly (stable for any dt), then the acceleration limits.
        v0 = self._vel_own_ned.copy()
        dv = (target - v0) * (1.0 - math.exp(-dt_s / p.vel_time_constant_s))
        dv_h = math.hypot(dv[0], dv[1])
        max_dv_h = p.accel_limit_h_m_s2 * dt_s
        if dv_h > max_dv_h:
            dv[:2] *= max_dv_h / dv_h
        dv[2] = min(max(dv[2], -p.max_accel_v_m_s2 * dt_s), p.max_accel_v_m_s2 * dt_s)
        if p.jerk_limit_h_m_s3 is not None:
            # The horizontal acceleration may change by at most jerk x dt per step: a multirotor
            # has to tilt to accelerate, and ArduCopter shapes its velocity targets so it does
            # not tilt faster than the jerk limit allows.
            a_prev = self._accel_own_ned[:2]
            da = dv[:2] / dt_s - a_prev
            da_norm = math.hypot(da[0], da[1])
            if da_norm > p.jerk_limit_h_m_s3 * dt_s:
                dv[:2] = (a_prev + da * (p.jerk_limit_h_m_s3 * dt_s / da_norm)) * dt_s
        v1 = v0 + dv
        self._accel_own_ned = dv / dt_s

        disturb0 = self._gust_ned + self._drift_ned
        self._advance_disturbances(dt_s)
        wind = np.asarray(p.wind_ned_m_s, dtype=np.float64)
        if p.scale_error != 0.0:
            ground0 = v0 / (1.0 + p.scale_error) + wind + disturb0
            ground1 = v1 / (1.0 + p.scale_error) + wind + self._gust_ned + self._drift_ned
        else:
            ground0 = v0 + wind + disturb0
            ground1 = v1 + wind + self._gust_ned + self._drift_ned
        if self._nav_correction_ned.any():  # never touched without fused measurements: ideal stays exact
            ground0 = ground0 - self._nav_correction_ned
            ground1 = ground1 - self._nav_correction_ned
        move = 0.5 * (ground0 + ground1) * dt_s  # trapezoid: exact for the linear velocity ramp

        alt = st.alt_agl_m - move[2]
        if alt <= 0.0:
            # On the ground: it cannot sink further, and friction holds it where it touched down.
            alt = 0.0
            v1[0] = v1[1] = 0.0
            v1[2] = min(v1[2], 0.0)  # NED: only an upward (negative down) velocity survives
            ground1 = np.zeros(3)
        self._vel_own_ned = v1
        roll, pitch = self._attitude(yaw_new) if alt > 0.0 else (0.0, 0.0)
        self._state = Pose(
            x_m=st.x_m + move[1],
            y_m=st.y_m + move[0],
            alt_agl_m=alt,
            vel_ned_m_s=(float(ground1[0]), float(ground1[1]), float(ground1[2])),
            yaw_rad=yaw_new,
            t_s=st.t_s + dt_s,
            roll_rad=roll,
            pitch_rad=pitch,
        )
        return self._state

    def _attitude(self, yaw_rad: float) -> tuple[float, float]:
        """Roll and pitch whose thrust gives this step's own acceleration plus the drag to overcome.

        Thrust along body up must supply (a_forward, a_right, g - a_down) in the heading-level
        frame; for the ZYX attitude that is pitch = atan2(-a_f, g - a_d) (nose down to speed up)
        and roll = atan2(a_r, hypot(a_f, g - a_d)) (right wing down to go right).
        """
        a = self._accel_own_ned + self.params.drag_per_s * self._vel_own_ned
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        a_f, a_r = c * a[0] + s * a[1], -s * a[0] + c * a[1]
        up = max(GRAVITY_M_S2 - a[2], 0.1 * GRAVITY_M_S2)  # never a free fall: some thrust remains
        return math.atan2(a_r, math.hypot(a_f, up)), math.atan2(-a_f, up)

    def _clip_velocity(self, v_ned: np.ndarray) -> np.ndarray:
        p = self.params
        out = v_ned.copy()
        speed_h = math.hypot(out[0], out[1])
        if speed_h > p.max_speed_h_m_s:
            out[:2] *= p.max_speed_h_m_s / speed_h  # keep the direction, cap the magnitude
        down_m_s = p.max_speed_v_m_s if p.max_descent_m_s is None else p.max_descent_m_s
        out[2] = min(max(out[2], -p.max_speed_v_m_s), down_m_s)
        return out

    def _advance_disturbances(self, dt_s: float) -> None:
        p = self.params
        # Draw both every step, even at sigma 0, so turning one on does not reshuffle the other.
        noise = self._rng.standard_normal(4)
        if p.gust_sigma_m_s > 0:
            # Exact Ornstein-Uhlenbeck update: stationary std gust_sigma, correlation time tau.
            a = math.exp(-dt_s / p.gust_time_constant_s)
            self._gust_ned[:2] = a * self._gust_ned[:2] + p.gust_sigma_m_s * math.sqrt(1.0 - a * a) * noise[:2]
        if p.drift_sigma_m_s_sqrt_s > 0:
            self._drift_ned[:2] += p.drift_sigma_m_s_sqrt_s * math.sqrt(dt_s) * noise[2:]
