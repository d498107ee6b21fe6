"""What the autopilot reports without GNSS: its state estimate, and the vehicle profiles that set it.

The sim's dynamics hold the truth (`dovesei.sim.dynamics`); the judge and the reports read it. What
the vehicle publishes on the state key, and what labels its camera frames, is the estimate made
here, the way an autopilot flying on an optical-flow EKF without GNSS reports itself:

    truth (Pose, the velocity the autopilot believes it flies, attitude from the dynamics)
      -> velocity: the believed velocity (what the autopilot tracks its commands on), `latency_s`
         old, + white noise. Its error against the truth (wind, gusts, the drifting bias, the
         scale error) lives in the dynamics, because the vehicle truly flies that error.
      -> altitude: a rangefinder below its usable height (alt x (1 + noise)), else the baro:
         truth + a slowly drifting offset (random walk) + white noise
      -> heading: truth + a fixed offset drawn per episode + a random walk
      -> roll, pitch: truth + a fixed offset + a slowly wandering error (the AHRS's level error)
      -> local position: the reported velocity integrated (dead reckoning), `pos_valid` False

Every random draw comes from the estimator's own generator, seeded from the episode seed apart
from the dynamics' generator, so a profile changes nothing else that the seed decides.

Profiles (`VEHICLE_PROFILES`):

- `ideal`: what the sim always did. The state is the truth (true ground velocity, true altitude,
  `pos_valid` True with the true local position), a perfect gimbal (frames nadir, roll = pitch =
  0), the dynamics' defaults (4 m/s^2, tau 0.3 s, a command dropped after 0.5 s). Records of the
  same seeds are unchanged (tests/sim/test_vehicle_profiles.py).
- `realistic`: an ArduCopter on an optical-flow EKF, no GNSS, a camera fixed to the body.
- `harsh`: the same with larger errors and a weaker, slower vehicle.

Where the values come from:

- Horizontal acceleration 2.5 m/s^2: ArduCopter's WPNAV_ACCEL default (250 cm/s^2), which GUIDED
  velocity control uses as its acceleration limit; also LOITER_BRAKE_ACCEL's default 2.5 m/s^2
  (libraries/AC_WPNav/AC_Loiter.cpp). Jerk 5 m/s^3: POSCONTROL_JERK_NE_MSSS, the position
  controller's default horizontal jerk (libraries/AC_AttitudeControl/AC_PosControl.h) and
  LOITER_BRAKE_JERK's default. Together: braking from 10 m/s takes 10 / 2.5 + 2.5 / 5 = 4.5 s,
  what ArduCopter SITL was measured to take (issue 23). Lean limit 30 deg: ANGLE_MAX's default
  (AC_ATTITUDE_CONTROL_ANGLE_MAX_DEFAULT). Vertical acceleration 1.0 m/s^2: WPNAV_ACCEL_Z's default
  (100 cm/s^2, AC_WPNav.cpp). Speeds 10 m/s horizontal, 2.5 up, 1.5 down: WPNAV_SPEED,
  WPNAV_SPEED_UP and WPNAV_SPEED_DN's defaults, the limits GUIDED velocity control takes.
- Command timeout 3 s: ArduCopter's GUID_TIMEOUT default; a GUIDED vehicle flies its last
  velocity setpoint that long before it stops (issue 26 measured 3.5 s and ~35 m of coasting).
- Velocity latency 0.1 s: the flow sensor's delay (EK3_FLOW_DELAY, 10 ms default, far less than
  the telemetry path) plus LOCAL_POSITION_NED streamed at 10 Hz; harsh 0.25 s (a 4 Hz stream).
- Drifting bias (random walk) 0.01 m/s/sqrt(s): issue 23's SITL flight on flow drifted 51 m from
  the truth in 19 minutes with no wind; a random walk of sigma q gives a position spread of
  q t^1.5 / sqrt(3), i.e. 51 m needs q ~ 0.002; 0.01 leaves room for real flow over poor
  texture. Harsh 0.03.
- Scale error: flow is scaled by the height estimate, so a baro height off by 1-2 m at 30-50 m is
  2-5 %: sigma 3 % realistic, 8 % harsh (drawn per episode).
- Velocity white noise 0.1 m/s (0.3 harsh): EK3_FLOW_M_NSE's default 0.25 rad/s of flow noise
  filtered by the EKF at 10 Hz over a few seconds.
- Unseen wind 0.3 m/s mean (direction drawn per episode) and gusts 0.3 m/s sigma, 5 s: the part a
  flow EKF does not absorb at once (flow measures ground motion; only the loop's lag and the
  flow's noise let wind through). Harsh: 1.0 m/s and 0.8 m/s.
- Baro: noise 0.3 m, drift 0.02 m/sqrt(s) (0.7 m sigma after 20 min; harsh 1.0 m and 0.06). The
  EKF's own assumption is looser: EK3_ALT_M_NSE 2 m (ArduPilot), EKF2_BARO_NOISE 3.5 m (PX4).
- Rangefinder: realistic has one of 70 m range used below 70 % of it, the set-up of issue 23's
  SITL flights (EK3_RNG_USE_HGT 70: EKF3 uses it as height below that percentage of RNGFND_MAX);
  noise 1 % of range. Harsh has none (baro only).
- Heading: 2 deg offset sigma (compass calibration residuals after COMPASS_MOT; harsh 5 deg) and
  a random walk of 0.02 deg/sqrt(s).
- Roll and pitch: 0.5 deg level error sigma (AHRS_TRIM residual; harsh 1.5) and a wandering error of
  0.2 deg sigma (harsh 0.5) that is correlated over `attitude_noise_tau_s` = 30 s (a first-order
  Gauss-Markov process). An AHRS integrates its gyros, so its attitude is smooth over a frame
  interval: its error drifts with vibration and acceleration misreadings, it does not jump. White
  noise of 0.2 deg per 0.05 s state made the attitude *change* between two frames 0.1 s apart
  ~3.5 mrad, i.e. ~5 m/s of false visual velocity at 100 m (bench-odometry measured 95 % median
  error under this profile); a gyro's noise density (~0.01 deg/s/sqrt(Hz) for MEMS IMUs such as
  the ICM-42688) integrates to ~0.002 deg over 0.1 s. With tau 30 s the change over 0.1 s is
  0.2 deg x sqrt(2 x 0.1 / 30) ~ 0.3 mrad: still larger than the gyro's, on the safe side.
  Tau is a modelling choice, not a measured value.
- Linear drag 0.2 /s for the attitude only: about 11 deg of pitch at 10 m/s. A modelling choice,
  not a measured value: it only makes a cruising body-fixed camera look slightly backwards.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.sim.dynamics import Pose, VehicleParams, body_frd_to_ned, wrap_angle_rad

ESTIMATOR_SEED_TAG = 0x65737469  # mixed into the episode seed so the estimator's draws are its own


@dataclass(frozen=True)
class EstimatorParams:
    """How far the reported state is from the truth (sigmas are per axis; see the module docstring)."""

    vel_noise_m_s: float = 0.0
    latency_s: float = 0.0
    baro_noise_m: float = 0.0
    baro_drift_m_sqrt_s: float = 0.0
    rangefinder_max_m: float = 0.0  # 0: none
    rangefinder_use_fraction: float = 0.7  # used as height below this fraction of its range (EK3_RNG_USE_HGT)
    rangefinder_noise_fraction: float = 0.01
    heading_offset_sigma_rad: float = 0.0
    heading_walk_rad_sqrt_s: float = 0.0
    level_offset_sigma_rad: float = 0.0
    attitude_noise_rad: float = 0.0  # stationary sigma of the wandering roll/pitch error
    attitude_noise_tau_s: float = 30.0  # its correlation time

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            validate.non_negative(f"EstimatorParams.{f.name}", getattr(self, f.name))
        validate.in_range("EstimatorParams.latency_s", self.latency_s, 0.0, 2.0)
        validate.in_range("EstimatorParams.rangefinder_use_fraction", self.rangefinder_use_fraction, 0.0, 1.0)


@dataclass(frozen=True)
class VehicleProfile:
    """A vehicle as the sim flies it: dynamics, what it reports, and how its camera is mounted.

    `dynamics` holds the limits and disturbances; the unseen wind's speed (`wind_speed_m_s`) and the
    estimate's scale error (`scale_error_sigma`) are drawn per episode from the seed, so they go in
    here, not in `dynamics`. `estimator` None: the state is the truth (`ideal`).
    """

    name: str
    dynamics: VehicleParams
    estimator: EstimatorParams | None
    gimbal: bool  # True: frames nadir whatever the attitude (roll = pitch = 0 on the frame)
    wind_speed_m_s: float = 0.0
    scale_error_sigma: float = 0.0

    def episode_dynamics(self, overrides: VehicleParams, seed: int) -> VehicleParams:
        """The dynamics of one episode: the profile's, with every field `overrides` changed from the
        defaults (an explicit flag wins over the profile) and the per-episode draws made."""
        base = VehicleParams()
        changed = {f.name: getattr(overrides, f.name) for f in dataclasses.fields(VehicleParams)
                   if getattr(overrides, f.name) != getattr(base, f.name)}
        params = dataclasses.replace(self.dynamics, **changed)
        if self.estimator is None:
            return params
        rng = np.random.default_rng([seed, ESTIMATOR_SEED_TAG, 1])
        heading = rng.uniform(-math.pi, math.pi)
        draws = {"scale_error": float(np.clip(rng.normal(0.0, self.scale_error_sigma), -0.3, 0.3))}
        if "wind_ned_m_s" not in changed:
            draws["wind_ned_m_s"] = (self.wind_speed_m_s * math.cos(heading), self.wind_speed_m_s * math.sin(heading), 0.0)
        return dataclasses.replace(params, **draws)


@dataclass(frozen=True)
class Estimate:
    """The reported state at one step (what the state key and the frame labels carry)."""

    alt_agl_m: float
    vel_body_frd_m_s: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    pos_local_ned_m: tuple[float, float, float]


class Estimator:
    """The autopilot's estimate of one episode, stepped with the truth after every sim step."""

    def __init__(self, params: EstimatorParams, seed: int, dt_s: float) -> None:
        validate.positive("estimator dt_s", dt_s)
        self.params, self.dt_s = params, dt_s
        self._rng = np.random.default_rng([seed, ESTIMATOR_SEED_TAG, 2])
        offsets = self._rng.standard_normal(3)
        self._heading_offset_rad = params.heading_offset_sigma_rad * float(offsets[0])
        self._level_offset_rad = (params.level_offset_sigma_rad * float(offsets[1]),
                                  params.level_offset_sigma_rad * float(offsets[2]))
        self._baro_offset_m = 0.0
        self._att_wander_rad = np.zeros(2)  # the Gauss-Markov part of the roll/pitch error
        # The believed velocities of the last `latency_s` (NED), newest last: the reported one is the oldest.
        self._delay_steps = int(round(params.latency_s / dt_s))
        self._believed: deque[np.ndarray] = deque(maxlen=self._delay_steps + 1)
        self._pos_ned = np.zeros(3)
        self.last: Estimate | None = None

    def update(self, pose: Pose, vel_own_ned_m_s: tuple[float, float, float]) -> Estimate:
        """The estimate after the step that reached `pose` (`vel_own_ned_m_s`: what the autopilot flies)."""
        p, rng = self.params, self._rng
        noise = rng.standard_normal(8)  # a fixed number of draws per step: the sequence never shifts
        self._believed.append(np.asarray(vel_own_ned_m_s, dtype=np.float64))
        vel_ned = self._believed[0] + p.vel_noise_m_s * np.array([noise[0], noise[1], 0.3 * noise[2]])
        step_sd = math.sqrt(self.dt_s)
        self._heading_offset_rad += p.heading_walk_rad_sqrt_s * step_sd * float(noise[3])
        yaw = wrap_angle_rad(pose.yaw_rad + self._heading_offset_rad)
        # The body-frame velocity is the NED estimate turned by the estimated heading, as an
        # autopilot derives it from its own (rotated) frame.
        c, s = math.cos(yaw), math.sin(yaw)
        vel_frd = (c * vel_ned[0] + s * vel_ned[1], -s * vel_ned[0] + c * vel_ned[1], float(vel_ned[2]))
        self._baro_offset_m += p.baro_drift_m_sqrt_s * step_sd * float(noise[4])
        if p.rangefinder_max_m > 0.0 and pose.alt_agl_m <= p.rangefinder_use_fraction * p.rangefinder_max_m:
            alt = pose.alt_agl_m * (1.0 + p.rangefinder_noise_fraction * float(noise[5]))
        else:
            alt = pose.alt_agl_m + self._baro_offset_m + p.baro_noise_m * float(noise[5])
        # First-order Gauss-Markov: stationary sigma `attitude_noise_rad`, correlated over tau.
        keep = math.exp(-self.dt_s / p.attitude_noise_tau_s) if p.attitude_noise_tau_s > 0.0 else 0.0
        self._att_wander_rad = keep * self._att_wander_rad + p.attitude_noise_rad * math.sqrt(1.0 - keep * keep) * noise[6:8]
        roll = pose.roll_rad + self._level_offset_rad[0] + float(self._att_wander_rad[0])
        pitch = pose.pitch_rad + self._level_offset_rad[1] + float(self._att_wander_rad[1])
        # Dead reckoning in the autopilot's (rotated) frame: what LOCAL_POSITION_NED reports on flow.
        self._pos_ned[:2] += body_frd_to_ned(vel_frd, yaw)[:2] * self.dt_s
        self.last = Estimate(alt_agl_m=max(alt, 0.0), vel_body_frd_m_s=tuple(float(v) for v in vel_frd),
                             roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
                             pos_local_ned_m=(float(self._pos_ned[0]), float(self._pos_ned[1]), -max(alt, 0.0)))
        return self.last


VEHICLE_PROFILES: dict[str, VehicleProfile] = {
    "ideal": VehicleProfile("ideal", VehicleParams(), None, gimbal=True),
    "realistic": VehicleProfile(
        "realistic",
        VehicleParams(max_speed_h_m_s=10.0, max_speed_v_m_s=2.5, max_descent_m_s=1.5, max_accel_h_m_s2=2.5,
                      max_accel_v_m_s2=1.0, max_tilt_deg=30.0, jerk_limit_h_m_s3=5.0,
                      cmd_timeout_s=3.0, gust_sigma_m_s=0.3, gust_time_constant_s=5.0, drift_sigma_m_s_sqrt_s=0.01,
                      drag_per_s=0.2),
        EstimatorParams(vel_noise_m_s=0.1, latency_s=0.1, baro_noise_m=0.3, baro_drift_m_sqrt_s=0.02,
                        rangefinder_max_m=70.0, heading_offset_sigma_rad=math.radians(2.0),
                        heading_walk_rad_sqrt_s=math.radians(0.02), level_offset_sigma_rad=math.radians(0.5),
                        attitude_noise_rad=math.radians(0.2)),
        gimbal=False, wind_speed_m_s=0.3, scale_error_sigma=0.03),
    "harsh": VehicleProfile(
        "harsh",
        VehicleParams(max_speed_h_m_s=10.0, max_speed_v_m_s=2.5, max_descent_m_s=1.5, max_accel_h_m_s2=2.0,
                      max_accel_v_m_s2=1.0, max_tilt_deg=30.0, jerk_limit_h_m_s3=3.0,
                      cmd_timeout_s=3.0, gust_sigma_m_s=0.8, gust_time_constant_s=4.0, drift_sigma_m_s_sqrt_s=0.03,
                      drag_per_s=0.3),
        EstimatorParams(vel_noise_m_s=0.3, latency_s=0.25, baro_noise_m=1.0, baro_drift_m_sqrt_s=0.06,
                        heading_offset_sigma_rad=math.radians(5.0), heading_walk_rad_sqrt_s=math.radians(0.05),
                        level_offset_sigma_rad=math.radians(1.5), attitude_noise_rad=math.radians(0.5)),
        gimbal=False, wind_speed_m_s=1.0, scale_error_sigma=0.08),
}
VEHICLE_PROFILE_NAMES = tuple(VEHICLE_PROFILES)
SIM_DEFAULT_VEHICLE_PROFILE = "ideal"  # the sim service and SimConfig; `bench` and `up` choose their own


def default_vehicle_profile(timing_name: str) -> str:
    """The profile `bench`, `sweep`, `up` and `faults` fly when none is asked for, by timing preset.

    `real` (true seconds, what a real vehicle flies): `realistic`, the vehicle dovesei exists for.
    `reference` (the reproduction of the paper, whose timers run at 6.5 % of true seconds): `ideal`,
    the paper's simulated drone, which knew its state exactly; ArduCopter's true-second limits
    (1.5 m/s down) on that compressed clock would leave the paper's policies no time to land.
    """
    return "ideal" if timing_name == "reference" else "realistic"


def vehicle_profile(name: str) -> VehicleProfile:
    """The named profile, or a ConfigError naming the choices."""
    try:
        return VEHICLE_PROFILES[name]
    except (KeyError, TypeError):
        raise ConfigError(f"--vehicle-profile {name!r}: choose one of {', '.join(VEHICLE_PROFILE_NAMES)}") from None
