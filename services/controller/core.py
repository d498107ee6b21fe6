"""The controller's pure core: heatmaps and vehicle states in, one velocity command per tick out.

No Zenoh and no MAVLink in here: the Zenoh service (`service.py`) and the in-process bench both
drive this class with direct calls, so one process or three give the same trajectory.

Data flow per tick:

    on_heatmap(hm, recv_wall_s) --> buffer (lockstep: kept by seq until due; real time: newest)
                                          |
    tick(state) --> the state's velocity estimate into a short track (odometry.VelocityTrack)
                --> adopt the due / newest heatmap --> Policy.step(Observation) once per heatmap,
                    with the track's displacement since the previous heatmap's capture
                --> watchdog on the DATA clock (state time - adopted heatmap's stamp)
                --> VelocityCommand (every tick) + ControllerStatus (every tick)

Geofence (`geofence.py`): every command, whatever the mode or policy, keeps the dead-reckoned
position (the state's velocity estimate integrated from the first state) within
`geofence_radius_m` of the start; a capped command says so in the status reason. Default: off with
the sim (the paper's experiment stays as published), DEFAULT_VEHICLE_GEOFENCE_M on a real vehicle.

Watchdog modes, highest priority first (each change is logged once at INFO with its reason):

    state_stale  the vehicle state stopped advancing (real time only, wall clock) -> zero velocity
    handover     at/below the hand-over altitude with the policy landing (Decision.landing, its
                 word not run out: Decision.landing_until_s): stop commanding, short-range sensors
                 take over; the command says so (`handover`)
    no_velocity  (MAVLink) no horizontal velocity source is trusted: GNSS lost with
                 `--gnss-denied off`, stale or poor visual velocity, an EKF that does not fuse
                 it (gnss_denied.NavStatus says why)   -> no descent: lost in flight, level back
                 over the ground the camera measured (gnss_denied.NavRetreat), then zero velocity
    policy_fault the policy raised, or declared LANDED/HANDOVER above the hand-over altitude
                 (measured)                                                      -> zero velocity
    no_heatmap   nothing adopted yet                                             -> zero velocity
    climb        heatmap older than `heatmap_climb_after_s`  -> climb to the search altitude, hold
    hold         heatmap older than `heatmap_hold_after_s`   -> zero velocity (stop descending);
                 or the policy's landing word ran out        -> its horizontal command, no descent
    ok           the policy's newest decision is sent

A stale decision is never re-sent: outside `ok` the command is built from the mode, not from the
policy. Recovery is automatic: the next fresh heatmap is adopted, the policy steps, `ok` resumes.

Clocks, in front of every policy: the policy sees the data clock with every step capped at
`policy_dt_max_s` (a 14 s perception gap is not 14 s of progress for its timers), and a jump of
the state stamp never resets it mid-flight (only the lockstep sim's new episode, whose state
sequence restarts, does). In real time a stamp is judged on the controller's own monotonic clock:
a state or heatmap leading it by more than `future_tolerance_s` is refused and counted, so one
future stamp cannot make every honest sample look old.
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any

from dovesei.controller.gnss_denied import EXTERNAL_NAV_MESSAGES, GNSS_DENIED_MODES, NavRetreat, NavStatus
from dovesei.controller.looker import Looker
from dovesei.controller.policies.base import Decision, LookRequest, LookResult, Observation, Policy, PolicyInputError
from dovesei.controller.policies.registry import make_policy, policy_names
from dovesei.controller.continuity import (
    ALTITUDE_NOISE_M, MAX_VERTICAL_SPEED_M_S, STEP_CONFIRM_SAMPLES, AltitudeContinuity, AltitudeTrack,
)
from dovesei.shared.frames import body_frd_to_ned, ned_to_body_frd, to_body, to_ne
from dovesei.controller.geofence import Geofence
from dovesei.controller.odometry import VelocityTrack
from dovesei.controller.policies.dovesei.config import TIMING_PRESETS
from dovesei.controller.policies.config_file import load_policy_config
from dovesei.shared import footprint, keys, validate
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.mission import HANDOVER_ALT_M
from dovesei.shared.messages import (
    ControllerStatus, CropRequest, FieldError, SafetyHeatmap, StageLatency, VehicleState, VelocityCommand, replace,
)
from dovesei.shared.timing import DEFAULT_TIMING, timing

log = logging.getLogger(__name__)

HANDOVER_ACTIONS = ("hold", "land", "precland", "none")
# Decisions that end the policy's job; accepted only at/below the hand-over altitude.
TERMINAL_STATES = ("LANDED", "HANDOVER")
MAX_POLICY_SPEED = 100.0  # m/s and rad/s: a policy asking for more is faulty (messages allow 300)
DT_CAP_PERIODS = 2.0  # a perception gap advances the policy's clock by at most this many nominal periods
# The vehicle clock runs on true seconds; 5 % margin for crystal drift and latency jitter.
_DATA_RATE_MARGIN = 1.05
# Real time: a state behind the newest accepted one moves the clock back only when this many
# consecutive states agree on the earlier timeline (advancing with the wall clock); a lone past
# stamp is refused. One forged past state used to re-anchor the clock, and every genuine state
# after it was refused as "from the future" for good (dovesei faults, clock-skew).
JUMP_CONFIRM_STATES = 3
STAMP_EPS_S = 1e-6  # stamps closer than this are the same instant (0.05 * 19 is not 0.95 in floats)
# A heatmap's capture altitude must be one a camera can see the ground from: below 1 m a nadir
# camera sees a blur and the paper's policy declared LANDED at alt 0 (and -999).
MIN_HEATMAP_ALT_M, MAX_HEATMAP_ALT_M = 1.0, 1000.0
# ... and agree with the vehicle's own states: within this share of the altitude (a frame may be
# taken with the truth in the sim and the baro in the state), or this many times the noise.
HEATMAP_ALT_FRAC = 0.25
HEATMAP_ALT_NOISE_MULT = 2.0
_ALT_TRACK_LEN = 200  # accepted (t, alt) states kept: 10 s at 20 Hz, covers any perception latency
# A real vehicle's fence when none is given: `clearance` searches within 300 m of the start (its
# own fence 10 m inside), plus room for the raw velocity estimate's drift over a search. The
# paper's policy has no bound of its own (a 600 m RESTARTING transit on ArduCopter SITL).
DEFAULT_VEHICLE_GEOFENCE_M = 400.0


class ControllerInputError(DoveseiError, ValueError):
    """A message the controller cannot use (another vehicle's, another clock's)."""


@dataclass(frozen=True)
class ControllerConfig:
    """Everything the loop needs besides the policy's own constants; names carry units."""

    vehicle_id: str = "uav1"
    policy: str = "dovesei"
    # A TOML file of the policy's constants (policies/config_file.py); None: the timing preset's.
    policy_config_file: str | None = None
    # `clearance` looks at its spot at full resolution before committing below ~40 m (issue 24;
    # the crop and segment queryables must answer, or it holds there).
    close_look: bool = False
    timing: str = DEFAULT_TIMING  # policy timing preset (dovesei.shared.timing); a real vehicle runs "real"
    lockstep: bool = True  # True: one tick per sim state (as the sim's default); False: own 20 Hz loop
    rate_hz: float = 20.0  # real-time loop rate on the wall clock
    heatmap_hold_after_s: float = 1.5  # data-clock age beyond which the vehicle holds position
    heatmap_climb_after_s: float = 10.0  # data-clock age beyond which it climbs to search_alt_m
    state_stale_after_s: float = 0.5  # wall seconds without a newer state (real time only)
    climb_speed_m_s: float = 2.0  # max vertical speed of the climb watchdog
    climb_gain_per_s: float = 0.5  # climb speed = gain x altitude error (capped): no overshoot
    search_alt_m: float | None = None  # None: the altitude at which the vehicle was first seen
    handover_alt_m: float = HANDOVER_ALT_M  # at/below: stop commanding, report HANDOVER (handed to the policy)
    handover_release_m: float = 2.0  # hysteresis: leave HANDOVER only above handover + this
    handover_action: str = "hold"  # MAVLink adapter action at hand-over: hold, land, precland or none
    vehicle_url: str = "zenoh"  # "zenoh" (the sim over Zenoh) or a pymavlink connection URL
    policy_dt_max_s: float = 1.0  # the policy's clock advances at most this much per heatmap
    future_tolerance_s: float = 1.0  # real time: stamps may lead the controller's clock this much
    vehicle_connect_timeout_s: float = 30.0  # MAVLink: wait this long for the autopilot's heartbeat
    mavlink_alt_source: str = "local"  # MAVLink altitude: "local" position or "rangefinder"
    mavlink_allow_mode_switch: bool = False  # MAVLink: may switch to GUIDED/OFFBOARD itself
    # MAVLink: "rate" sends body-frame velocity + a yaw rate closed on ATTITUDE (mask 0x05C7);
    # "autopilot" sends LOCAL_NED velocity + the held heading as a yaw angle (0x09C7) for the
    # autopilot's heading controller. Either way the heading, and so the camera, is held.
    mavlink_yaw_control: str = "rate"
    mavlink_system_id: int | None = None  # MAVLink: fly only this autopilot system id (None: the first heard)
    # MAVLink setpoint limits, ArduCopter's defaults: WPNAV_SPEED, WPNAV_SPEED_UP, WPNAV_SPEED_DN.
    mavlink_max_horizontal_m_s: float = 10.0
    mavlink_max_up_m_s: float = 2.5
    mavlink_max_down_m_s: float = 1.5
    mavlink_signing_key_file: str | None = None  # MAVLink 2 signing key (32 bytes, 64 hex or a passphrase)
    mavlink_require_home: bool = True  # takeoff waits for the autopilot's home position
    takeoff_alt_m: float | None = None  # MAVLink: arm and climb here before flying (None: never arms)
    takeoff_ready_timeout_s: float = 120.0  # give up when the autopilot cannot arm within this
    lockstep_heatmap_wait_s: float = 5.0  # wall deadline for an awaited heatmap (lockstep)
    lockstep_heatmap_retry_s: float = 0.25  # shorter deadline while the segmenter seems down
    heatmap_buffer_len: int = 64  # lockstep: early heatmaps kept by seq
    # The camera every heatmap must come from (its frame's field of view, size and altitude are
    # checked before any policy sees it). The defaults are the sim's and the reference's camera;
    # the tolerance lets a cropped output pass (a 4:3 source cut square reads 20 % narrower).
    camera_hfov_deg: float = footprint.REFERENCE_HFOV_DEG
    camera_hfov_tolerance_frac: float = 0.25
    camera_size_px: tuple[int, int] | None = None  # (height, width) exactly; None: any up to the limit
    max_heatmap_side_px: int = 1024  # no camera we fly sends more; a 4096 px map only costs time
    # What a multirotor's altitude can do between two states plus the altitude source's own noise:
    # a larger step is refused (a forged or glitched state; dovesei.controller.continuity).
    max_vertical_speed_m_s: float = MAX_VERTICAL_SPEED_M_S
    altitude_noise_m: float = ALTITUDE_NOISE_M
    altitude_step_confirm_states: int = STEP_CONFIRM_SAMPLES  # a step held this long is real
    # The hand-over needs this many of the last 2n-1 distinct states at/below the hand-over altitude
    # (a majority: one forged or glitched low state is no altitude, and a noisy baro reading 20.4 m
    # once among 19.x m states does not restart the count). A policy that declares its terminal
    # state while the recent states' median is at most handover_release_m above the altitude (it
    # measured the altitude with its heatmap; the next state read above it by the baro's noise)
    # is confirmed, not refused: the vehicle sinks at handover_sink_m_s, never below
    # handover_alt_m - handover_release_m measured, until the states confirm it. Under `harsh` (baro noise 1 m per state) the single-state rule refused
    # a policy's HANDOVER at 19.5 m because the next state read 22.2 m, and the restarted policy
    # timed out at 20 m (villas start 0, seed 0).
    handover_confirm_states: int = 3
    handover_sink_m_s: float = 0.3
    # A policy that declared its terminal state on a heatmap captured at or below the hand-over
    # altitude measured it there: one of these same states read it. The median of the recent
    # states may then sit further above it than handover_release_m, and is confirmed up to this:
    # under `harsh` (baro noise 1 m a state, its offset drifting) a HANDOVER declared on a heatmap
    # captured at 19.1 m met a median of 22.2 m; refused, the policy restarted at 20 m and timed out
    # (coast start 23 of 34, seed 0, the vehicle on the camera's velocity; 12 such restarts in 238
    # episodes). 4 m is two sigma of the EKF's own baro noise assumption (EK3_ALT_M_NSE 2 m).
    handover_declared_band_m: float = 4.0
    record_path: str | None = None  # write an MCAP flight recording here (states, heatmaps, commands, status)
    # Largest dead-reckoned distance from the start; None: off with the sim, DEFAULT_VEHICLE_GEOFENCE_M
    # with a real vehicle; 0: off.
    geofence_radius_m: float | None = None
    geofence_gain_per_s: float = 0.5  # outward speed allowed per metre left to the fence
    # MAVLink without GNSS (gnss_denied.py): "off" reports and holds, "external-nav" feeds the visual
    # velocity to the EKF (source set `ekf_source_set`), "attitude" flies GUIDED_NOGPS attitude targets.
    gnss_denied: str = "off"
    ekf_source_set: int = 2  # the EK3_SRCn set whose VELXY is ExternalNav (6)
    external_nav_message: str = "both"  # ArduPilot: VISION_SPEED_ESTIMATE, VISION_POSITION_DELTA or both
    odometry_min_quality: float = 0.5  # visual velocity below this quality is not flown on
    odometry_max_age_s: float = 0.5  # nor one older than this at arrival (receiver's clock)
    attitude_max_tilt_deg: float = 15.0  # attitude mode: largest roll/pitch demanded
    # A velocity lost in flight (over water): fly towards measurable ground the camera still sees
    # aside (a coast in the view), else back over the ground it measured, at this speed, no
    # descent; on the way the ground was last seen, once it leaves the view, and the way back,
    # each for at most nav_retreat_max_s (0: hold at once, none of them);
    # gnss_denied.NavRetreat and OdometryGate.ground_seen.
    nav_retreat_speed_m_s: float = 4.0
    nav_retreat_max_s: float = 30.0

    def __post_init__(self) -> None:
        keys.check_vehicle_id(self.vehicle_id)
        if self.policy not in policy_names():
            raise ConfigError(f"policy {self.policy!r}: choose one of {', '.join(policy_names())}")
        if self.timing not in TIMING_PRESETS:
            raise ConfigError(f"timing {self.timing!r}: choose one of {', '.join(sorted(TIMING_PRESETS))}")
        self.policy_config()  # a bad file is one line now, not a policy fault in flight
        positive = ("rate_hz", "heatmap_hold_after_s", "heatmap_climb_after_s", "state_stale_after_s",
                    "climb_speed_m_s", "climb_gain_per_s", "handover_alt_m", "vehicle_connect_timeout_s",
                    "lockstep_heatmap_wait_s", "lockstep_heatmap_retry_s", "policy_dt_max_s",
                    "future_tolerance_s", "takeoff_ready_timeout_s")
        for name in positive:
            validate.positive(f"ControllerConfig.{name}", getattr(self, name))
        validate.non_negative("ControllerConfig.handover_release_m", self.handover_release_m)
        validate.non_negative("ControllerConfig.handover_declared_band_m", self.handover_declared_band_m)
        if self.heatmap_climb_after_s <= self.heatmap_hold_after_s:
            raise ConfigError(
                f"heatmap_climb_after_s ({self.heatmap_climb_after_s} s) must exceed "
                f"heatmap_hold_after_s ({self.heatmap_hold_after_s} s): hold first, then climb"
            )
        if self.search_alt_m is not None and not (math.isfinite(self.search_alt_m)
                                                  and self.search_alt_m > self.handover_alt_m):
            raise ConfigError(
                f"search_alt_m {self.search_alt_m!r} must be above the hand-over altitude {self.handover_alt_m} m"
            )
        if self.handover_action not in HANDOVER_ACTIONS:
            raise ConfigError(f"handover_action {self.handover_action!r}: choose one of {HANDOVER_ACTIONS}")
        if self.mavlink_yaw_control not in ("rate", "autopilot"):
            raise ConfigError(f"mavlink_yaw_control {self.mavlink_yaw_control!r}: choose 'rate' or 'autopilot'")
        if self.gnss_denied not in GNSS_DENIED_MODES:
            raise ConfigError(f"gnss_denied {self.gnss_denied!r}: choose one of {', '.join(GNSS_DENIED_MODES)}")
        if self.gnss_denied != "off" and self.vehicle_url == "zenoh":
            raise ConfigError(f"gnss_denied {self.gnss_denied!r} needs a MAVLink vehicle (--vehicle-url); the sim "
                              "never loses GNSS")
        validate.in_range("ControllerConfig.ekf_source_set", self.ekf_source_set, 1, 3)
        validate.one_of("ControllerConfig.external_nav_message", self.external_nav_message, EXTERNAL_NAV_MESSAGES)
        validate.in_range("ControllerConfig.odometry_min_quality", self.odometry_min_quality, 0.0, 1.0)
        validate.positive("ControllerConfig.odometry_max_age_s", self.odometry_max_age_s)
        validate.in_range("ControllerConfig.attitude_max_tilt_deg", self.attitude_max_tilt_deg, 1.0, 35.0)
        validate.in_range("ControllerConfig.nav_retreat_speed_m_s", self.nav_retreat_speed_m_s, 0.1,
                          self.mavlink_max_horizontal_m_s)
        validate.in_range("ControllerConfig.nav_retreat_max_s", self.nav_retreat_max_s, 0.0, 600.0)
        if self.heatmap_buffer_len < 1:
            raise ConfigError(f"heatmap_buffer_len must be >= 1, got {self.heatmap_buffer_len}")
        validate.in_range("ControllerConfig.camera_hfov_deg", self.camera_hfov_deg, 1.0, 179.0)
        validate.in_range("ControllerConfig.camera_hfov_tolerance_frac", self.camera_hfov_tolerance_frac, 0.0, 0.9)
        validate.in_range("ControllerConfig.max_heatmap_side_px", self.max_heatmap_side_px, 1, 8192)
        if self.camera_size_px is not None:
            validate.finite_vector("ControllerConfig.camera_size_px", self.camera_size_px, 2)
            if not all(isinstance(v, int) and 1 <= v <= self.max_heatmap_side_px for v in self.camera_size_px):
                raise ConfigError(f"ControllerConfig.camera_size_px must be two integers in 1..{self.max_heatmap_side_px}"
                                  f", got {self.camera_size_px!r}")
        for name in ("max_vertical_speed_m_s", "altitude_noise_m"):
            validate.positive(f"ControllerConfig.{name}", getattr(self, name))
        for name in ("altitude_step_confirm_states", "handover_confirm_states"):
            validate.in_range(f"ControllerConfig.{name}", getattr(self, name), 1, 1000)
        if self.lockstep and self.vehicle_url != "zenoh":
            raise ConfigError("lockstep needs the simulator (--vehicle-url zenoh); a real vehicle runs in real time")
        if self.geofence_radius_m is not None:
            validate.in_range("ControllerConfig.geofence_radius_m", self.geofence_radius_m, 0.0, 100_000.0)
        validate.positive("ControllerConfig.geofence_gain_per_s", self.geofence_gain_per_s)
        validate.in_range("ControllerConfig.handover_sink_m_s", self.handover_sink_m_s, 0.0, 2.0)
        for name in ("mavlink_max_horizontal_m_s", "mavlink_max_up_m_s", "mavlink_max_down_m_s"):
            validate.in_range(f"ControllerConfig.{name}", getattr(self, name), 0.01, 50.0)
        if self.mavlink_system_id is not None:
            validate.in_range("ControllerConfig.mavlink_system_id", self.mavlink_system_id, 1, 255)
        if self.takeoff_alt_m is not None:
            validate.in_range("ControllerConfig.takeoff_alt_m", self.takeoff_alt_m, 1.0, 500.0)
            if self.vehicle_url == "zenoh":
                raise ConfigError("takeoff_alt_m needs a MAVLink vehicle (--vehicle-url); the sim starts in the air")
        if self.vehicle_url != "zenoh" and self.timing != "real":
            # The reference preset's timers are 5 % of true seconds: against a real vehicle its
            # 60 s limit ran out at 28.8 m. A real vehicle always runs on true seconds.
            raise ConfigError(f"timing {self.timing!r} with a real vehicle ({self.vehicle_url}): a real vehicle "
                              "runs on true seconds, use --timing real")

    def policy_config(self) -> Any:
        """What the policy is built from: the file's constants on the timing preset, or the preset's name."""
        if self.policy_config_file is None:
            return self.timing
        return load_policy_config(self.policy, self.policy_config_file, self.timing)

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def geofence_m(self) -> float | None:
        """The fence in force: None when off."""
        radius = self.geofence_radius_m
        if radius is None:
            return DEFAULT_VEHICLE_GEOFENCE_M if self.vehicle_url != "zenoh" else None
        return radius if radius > 0.0 else None

    @property
    def vehicle_speed_limits_m_s(self) -> tuple[float, float, float] | None:
        """(horizontal, up, down) the MAVLink adapter flies at most; None with the sim (its own limits)."""
        if self.vehicle_url == "zenoh":
            return None
        return self.mavlink_max_horizontal_m_s, self.mavlink_max_up_m_s, self.mavlink_max_down_m_s


class Mode(str, Enum):
    """The loop's safety mode (see the module docstring for priorities)."""

    OK = "ok"
    NO_HEATMAP = "no_heatmap"
    HOLD = "hold"
    CLIMB = "climb"
    STATE_STALE = "state_stale"
    HANDOVER = "handover"
    POLICY_FAULT = "policy_fault"
    NO_VELOCITY = "no_velocity"

    @property
    def watchdog(self) -> str:
        """The status key's `watchdog` field: ok, hold, climb or state_stale."""
        if self in (Mode.NO_HEATMAP, Mode.POLICY_FAULT, Mode.NO_VELOCITY):
            return "hold"
        if self is Mode.HANDOVER:
            return "ok"  # not a fault: the status `state` says HANDOVER
        return self.value


@dataclass(frozen=True)
class _Adopted:
    """The heatmap the current decision was computed from, what it cost, and the attitude (roll,
    pitch, yaw) the policy was given with it."""

    hm: SafetyHeatmap
    latency: StageLatency
    attitude_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)


class ControllerCore:
    """Policy + heatmap buffer + watchdog; `tick` returns a command and a status every time."""

    def __init__(self, config: ControllerConfig, policy: Policy | None = None,
                 mono: Callable[[], float] = time.monotonic, looker: Looker | None = None) -> None:
        self.config = config
        self._mono = mono  # the controller's own clock (stamps are judged on it in real time)
        # The real wiring always goes through the factory; tests may hand in a double.
        self.policy = policy if policy is not None else make_policy(config.policy, config.policy_config(),
                                                                    config.vehicle_speed_limits_m_s,
                                                                    handover_alt_m=config.handover_alt_m,
                                                                    close_look=config.close_look)
        # Carries out the policy's close looks (camera crop + segmenter); None: every look is refused,
        # and a policy gated on them never commits below its look altitude.
        self.looker = looker
        self._look_seq = 0
        self._look_unanswered: LookResult | None = None
        self.rejected: Counter[str] = Counter()  # reason -> count (heatmaps and states refused)
        self.adopted_count = 0
        self._tick_seq = 0
        self.policy_errors = 0
        # A gap is worth at most this much policy time: the configured cap, and never more than
        # DT_CAP_PERIODS nominal decision periods of the preset. Under `reference` (0.05 s periods,
        # timers x 1/0.065) a 1 s step was 15 reference seconds, and the dovesei policy's descent
        # estimate (speed x dt) declared LANDED at 45 m after a 4 s segmenter hang (dovesei faults).
        self._policy_dt_max_s = min(config.policy_dt_max_s, DT_CAP_PERIODS * timing(config.timing).decision_period_s)
        self._reset_episode()

    # ---- episode bookkeeping -------------------------------------------------------------

    def _reset_episode(self) -> None:
        self._buffer: dict[int, tuple[SafetyHeatmap, float]] = {}  # lockstep: seq -> (hm, recv wall s)
        self._pending: tuple[SafetyHeatmap, float] | None = None  # real time: newest not yet adopted
        self._adopted: _Adopted | None = None
        self._decision: Decision | None = None
        self._last_state_t_s: float | None = None
        self._state_advanced_wall_s: float | None = None
        self._first_alt_m: float | None = None
        self._in_handover = False
        self._below_uncommitted = False  # below the hand-over altitude without the policy landing
        # The altitudes of the last 2n-1 distinct accepted states (n = handover_confirm_states).
        self._recent_alts: deque[float] = deque(maxlen=2 * self.config.handover_confirm_states - 1)
        self._recent_t_s: float | None = None  # the newest of them
        self._confirming = False  # a terminal decision near the altitude, waiting for the states
        self._word_expired = False  # the decision's landing word ran out (landing_until_s): no descent
        self._word_until_s: float | None = None  # that word's end on the data clock
        # The capture altitude of the heatmap on which the policy declared its current terminal
        # state (read only while the decision is terminal): later heatmaps of the same terminal
        # state may read higher on a noisy baro, the declaration was made there.
        self._declared_alt_m: float | None = None
        self._alt_track = AltitudeTrack(_ALT_TRACK_LEN)  # (t_s, alt) accepted
        cfg = self.config
        self._altitude = AltitudeContinuity(cfg.max_vertical_speed_m_s, cfg.altitude_noise_m,
                                            cfg.altitude_step_confirm_states, who=f"controller {cfg.vehicle_id}")
        self._mode: Mode | None = None
        self._last_state_seq: int | None = None
        self._state_anchor: tuple[float, float] | None = None  # (state t_s, own mono s): on-time state
        self._jump_states: list[tuple[float, float]] = []  # (t_s, own mono s): consecutive states behind
        # The on-time state that put the vehicle's clock furthest ahead of our own monotonic clock:
        # no honest state can lead its projection, whatever gaps, backlogs or re-syncs came since.
        self._best_anchor: tuple[float, float] | None = None
        self._policy_offset_s = 0.0  # policy clock = heatmap stamp + offset (changes only at jumps)
        self._last_policy_t_s: float | None = None
        self._policy_fault: str | None = None  # why the newest policy step cannot be followed
        self._refused_decision: Decision | None = None  # the terminal decision refused above hand-over
        self._track = VelocityTrack()  # the velocity estimate integrated, to read between capture stamps
        # The way back over measured ground when the velocity is lost in flight (MAVLink only).
        self._retreat = NavRetreat(self.config.nav_retreat_speed_m_s, self.config.nav_retreat_max_s)
        self._nav_trusted = True  # the newest tick's verdict, for the policy's observation
        self._retreat_ne: tuple[float, float] | None = None  # this tick's way back (north/east m/s), if any
        self._last_capture_t_s: float | None = None  # capture stamp of the heatmap the policy last took
        # Precision landing: the chosen spot relative to the vehicle (north, east, down metres) at
        # data-clock time t_s, fixed at the hand-over and carried by dead reckoning from then on.
        self._spot_rel_ned_m: tuple[float, float, float] | None = None
        self._spot_t_s = 0.0
        radius = self.config.geofence_m
        self.geofence = Geofence(radius, self.config.geofence_gain_per_s) if radius is not None else None
        self._fenced = False  # the previous command was capped (its start and end are logged)

    def _maybe_new_episode(self, state: VehicleState) -> None:
        """Time running backwards is a new sim episode only in lockstep with a restarted state
        sequence; anywhere else it is a clock jump, and the policy goes on (never reset mid-flight)."""
        if self._last_state_t_s is None or state.stamp.t_s >= self._last_state_t_s - STAMP_EPS_S:
            return
        restarted = self._last_state_seq is not None and state.seq <= self._last_state_seq
        if self.config.lockstep and restarted:
            log.info("controller %s: data clock went back from %.3f s to %.3f s: new episode, policy reset",
                     self.config.vehicle_id, self._last_state_t_s, state.stamp.t_s)
            buffered = self._buffer
            self._reset_episode()
            self.policy.reset()
            # Heatmaps of the new episode may already be buffered; older episodes' are in the future.
            self._buffer = {seq: item for seq, item in buffered.items() if item[0].stamp.t_s <= state.stamp.t_s}
            return
        self._refuse("clock jump", "controller %s: state clock jumped back from %.3f s to %.3f s: policy kept, "
                     "heatmaps of the old timeline dropped (holding until a new one)", self.config.vehicle_id,
                     self._last_state_t_s, state.stamp.t_s)
        # The adopted decision's age can no longer be measured on the new timeline: hold until a
        # heatmap of the new one arrives (NO_HEATMAP), and judge stamps afresh.
        self._adopted, self._decision, self._pending, self._state_anchor = None, None, None, None
        self._best_anchor, self._last_capture_t_s = None, None
        self._buffer = {seq: item for seq, item in self._buffer.items() if item[0].stamp.t_s <= state.stamp.t_s}

    def _projected_now_s(self) -> float | None:
        """Real time: the vehicle clock now, projected from the newest on-time state (None: no anchor)."""
        anchor = self._state_anchor
        if self.config.lockstep or anchor is None:
            return None
        return anchor[0] + _DATA_RATE_MARGIN * max(0.0, self._mono() - anchor[1])

    def _unconfirmed_jump(self, state: VehicleState) -> str | None:
        """Real time: is the state behind the newest accepted one, on a timeline not yet confirmed by
        JUMP_CONFIRM_STATES consecutive states (stamps advancing as our own clock does)?"""
        last = self._last_state_t_s
        if self.config.lockstep or last is None or state.stamp.t_s >= last - STAMP_EPS_S:
            self._jump_states.clear()
            return None
        seen, now = self._jump_states, self._mono()
        if seen and not (state.stamp.t_s > seen[-1][0] and abs((state.stamp.t_s - seen[0][0]) - (now - seen[0][1]))
                         <= self.config.future_tolerance_s):
            seen.clear()
        seen.append((state.stamp.t_s, now))
        if len(seen) >= JUMP_CONFIRM_STATES:
            seen.clear()
            return None
        return (f"state {state.seq} stamped {state.stamp.t_s:.3f} s is behind the newest accepted one ({last:.3f} s): "
                f"the clock goes back only after {JUMP_CONFIRM_STATES} consecutive states agree")

    def _state_from_future(self, state: VehicleState, wall_s: float | None) -> str | None:
        """Real time: does the state lead the controller's own clock? Learns it from on-time states."""
        if self.config.lockstep:
            return None  # lockstep: the sim's states are the clock
        projected = self._projected_now_s()
        if projected is None or state.stamp.t_s <= projected:
            # On time: re-anchor. A stamp inside the tolerance never moves the anchor, so a sender
            # cannot ratchet the clock forward one tolerance per message. Only a state that
            # advanced moves it: the loop re-ticks the last state through an outage, and anchoring
            # that old stamp to "now" froze the projection, so after a 3 s router restart every
            # state looked 3 s early and was refused for a minute (dovesei faults, router-restart).
            anchor = self._state_anchor
            if anchor is None or state.stamp.t_s > anchor[0]:
                self._state_anchor = (state.stamp.t_s, self._mono())
            best = self._best_anchor
            if best is None or state.stamp.t_s - self._mono() > best[0] - best[1]:
                self._best_anchor = (state.stamp.t_s, self._mono())
            return None
        if state.stamp.t_s <= projected + self.config.future_tolerance_s:
            return None
        last_wall_s = self._state_advanced_wall_s
        since_s = wall_s - last_wall_s if wall_s is not None and last_wall_s is not None else 0.0
        best = self._best_anchor
        ceiling = None if best is None else best[0] + _DATA_RATE_MARGIN * max(0.0, self._mono() - best[1])
        if since_s > self.config.state_stale_after_s and (
                ceiling is None or state.stamp.t_s <= ceiling + self.config.future_tolerance_s):
            # Nothing accepted for a while: the anchor itself is suspect. After a hang of our own
            # the backlog arrives first and anchored a 4 s old stamp to "now", so every live state
            # was refused for a minute (dovesei faults, controller-hang). Re-synchronise on this
            # one; a forged lead taken here shows as a backward jump at the next genuine state,
            # which holds until a fresh heatmap and re-anchors.
            log.warning("controller %s: no vehicle state accepted for %.1f s: clock re-synchronised on state %d "
                        "(%.3f s, ~%.3f s expected)", self.config.vehicle_id, since_s, state.seq, state.stamp.t_s,
                        projected)
            self._state_anchor = (state.stamp.t_s, self._mono())
            return None
        # A lead beyond even the best projection is refused after a gap too: otherwise any pause of
        # the genuine states (a loaded host) let a forged state set the clock 30 s ahead, and the
        # forger's heatmaps stamped to match were then fresh (dovesei faults, clock-skew).
        return (f"state {state.seq} stamped {state.stamp.t_s:.3f} s leads the controller's clock "
                f"(~{projected:.3f} s) by more than {self.config.future_tolerance_s:g} s")

    # ---- inputs --------------------------------------------------------------------------

    def on_heatmap(self, hm: SafetyHeatmap, recv_wall_s: float) -> bool:
        """Buffer a heatmap (never used before it is due); False when refused (counted, logged)."""
        if hm.vehicle_id != self.config.vehicle_id:
            return self._refuse("other vehicle", "heatmap for vehicle %r ignored (this is %r)",
                                hm.vehicle_id, self.config.vehicle_id)
        problem = self._camera_mismatch(hm)
        if problem is not None:
            return self._refuse("camera model", "heatmap %d refused: %s", hm.seq, problem)
        if self.config.lockstep:
            # Everything is kept by seq: the tick decides what is due (a new episode's seq 0 too).
            self._buffer[hm.seq] = (hm, recv_wall_s)
            while len(self._buffer) > self.config.heatmap_buffer_len:
                dropped = min(self._buffer)
                del self._buffer[dropped]
                log.debug("heatmap buffer full: dropped seq %d", dropped)
            return True
        projected = self._projected_now_s()
        if projected is not None and hm.stamp.t_s > projected + self.config.future_tolerance_s:
            # Refused before it can become "the newest" and make every honest heatmap look old.
            return self._refuse("heatmap from the future", "heatmap %d stamped %.3f s leads the controller's "
                                "clock (~%.3f s) by more than %g s: refused", hm.seq, hm.stamp.t_s, projected,
                                self.config.future_tolerance_s)
        # Real time: "newest" is the latest capture time, whatever order the network delivers.
        newest_t_s = self._adopted.hm.stamp.t_s if self._adopted is not None else -math.inf
        if self._pending is not None:
            newest_t_s = max(newest_t_s, self._pending[0].stamp.t_s)
        if hm.stamp.t_s <= newest_t_s:
            return self._refuse("old heatmap", "heatmap %d (t=%.3f s) ignored: a newer one is held",
                                hm.seq, hm.stamp.t_s, level=logging.DEBUG)
        self._pending = (hm, recv_wall_s)
        return True

    def has_heatmap(self, seq: int) -> bool:
        """Lockstep: is the heatmap of frame `seq` buffered (so a tick awaiting it can decide)?"""
        return seq in self._buffer

    def _refuse(self, reason: str, fmt: str, *args: Any, level: int = logging.WARNING) -> bool:
        """Count a refusal; warn on the first of its kind and every 100th (a misconfiguration
        repeats with every heatmap: the log must not drown the transitions)."""
        self.rejected[reason] += 1
        count = self.rejected[reason]
        loud = count == 1 or count % 100 == 0
        log.log(level if loud else logging.DEBUG, fmt + " [%d so far]", *args, count)
        return False

    # ---- the tick ------------------------------------------------------------------------

    def tick(self, state: VehicleState, wall_s: float | None = None,
             nav: NavStatus | None = None) -> tuple[VelocityCommand, ControllerStatus]:
        """One control tick on `state`'s data clock.

        `wall_s` is the real-time loop's monotonic wall time (None in lockstep): it only serves to
        notice that the vehicle state stopped advancing, which data time alone cannot show.
        `nav` is the MAVLink adapter's judgement of the velocity sources (None: the sim, trusted).
        Raises ControllerInputError for another vehicle's state or one from the future; a state
        whose altitude no multirotor could have reached is answered with a hold (counted).
        """
        cfg = self.config
        if state.vehicle_id != cfg.vehicle_id:
            self.rejected["other vehicle"] += 1
            raise ControllerInputError(f"state for vehicle {state.vehicle_id!r} sent to controller {cfg.vehicle_id!r}")
        past = self._unconfirmed_jump(state)
        if past is not None:
            self._refuse("state from the past", "%s: refused", past)
            raise ControllerInputError(past)
        future = self._state_from_future(state, wall_s)
        if future is not None:
            self._refuse("state from the future", "%s: refused", future)
            raise ControllerInputError(future)
        self._maybe_new_episode(state)
        jump = self._altitude.check(state.stamp.t_s, state.alt_agl_m)
        if jump is not None:
            reason = f"state {state.seq}: {jump}"
            self._refuse("altitude jump", "%s: refused, holding", reason)
            return self._refused_state_answer(state, f"{reason}: refused, holding position", nav)
        self._alt_track.add(state.stamp.t_s, state.alt_agl_m)
        if self._recent_t_s is None or state.stamp.t_s > self._recent_t_s:
            # Distinct states only: the real-time loop re-ticks the newest one while none arrives.
            self._recent_alts.append(state.alt_agl_m)
            self._recent_t_s = state.stamp.t_s
        now_s = state.stamp.t_s
        if self._last_state_t_s is None or now_s > self._last_state_t_s or self._state_advanced_wall_s is None:
            self._state_advanced_wall_s = wall_s
        self._last_state_t_s, self._last_state_seq = now_s, state.seq
        self._track.add(now_s, state.vel_body_frd_m_s, state.yaw_rad, state.roll_rad, state.pitch_rad)
        self._nav_trusted = nav is None or nav.velocity_trusted
        self._retreat_ne = None
        if nav is not None:
            self._retreat_ne = self._retreat.update(
                now_s, to_ne(state.vel_body_frd_m_s[0], state.vel_body_frd_m_s[1], state.yaw_rad), self._nav_trusted,
                nav.ground_seen_ne)
        if self.geofence is not None:
            self.geofence.add(now_s, state.vel_body_frd_m_s, state.yaw_rad)
        if self._first_alt_m is None:
            self._first_alt_m = state.alt_agl_m

        self._adopt_due(state)
        mode, reason = self._judge(state, wall_s, nav)
        if mode is not self._mode:
            log.info("controller %s: watchdog %s -> %s at t=%.3f s (alt %.1f m): %s", cfg.vehicle_id,
                     self._mode.value if self._mode else "start", mode.value, now_s, state.alt_agl_m, reason)
            self._mode = mode

        vel, yaw_rate = self._velocity(mode, state)
        vel, reason = self._fence(vel, state, reason, pull_back=mode is Mode.OK)
        if mode is not Mode.HANDOVER:
            self._spot_rel_ned_m = None  # a new hand-over fixes its own spot
        self._tick_seq += 1
        adopted = self._adopted
        frame_seq = adopted.hm.seq if adopted is not None else -1
        cmd = VelocityCommand(
            vehicle_id=cfg.vehicle_id, seq=self._tick_seq, stamp=state.stamp, vel_body_frd_m_s=vel,
            yaw_rate_rad_s=yaw_rate, state_seq=state.seq, frame_seq=frame_seq,
            latency=adopted.latency if adopted is not None else None, handover=mode is Mode.HANDOVER,
        )
        return cmd, self._status(mode, reason, state, vel, nav)

    def _refused_state_answer(self, state: VehicleState, reason: str,
                              nav: NavStatus | None) -> tuple[VelocityCommand, ControllerStatus]:
        """A zero command answering a state whose altitude was refused: a lockstep sim waits for an
        answer to every state, and nothing of this one (altitude, stamp, velocity) is used."""
        self._tick_seq += 1
        adopted = self._adopted
        zero = (0.0, 0.0, 0.0)
        cmd = VelocityCommand(vehicle_id=self.config.vehicle_id, seq=self._tick_seq, stamp=state.stamp,
                              vel_body_frd_m_s=zero, state_seq=state.seq,
                              frame_seq=adopted.hm.seq if adopted is not None else -1)
        believed = replace(state, alt_agl_m=self._altitude.last[1])  # the status shows the altitude we hold to
        return cmd, self._status(Mode.HOLD, reason, believed, zero, nav)

    def _adopt_due(self, state: VehicleState) -> None:
        """Lockstep: adopt exactly the awaited seq; real time: the newest pending heatmap."""
        if self.config.lockstep:
            seq = state.await_frame_seq
            if seq < 0:
                return  # nothing becomes available this step: keep the last decision
            item = self._buffer.pop(seq, None)
            # Older buffered seqs can never become due any more.
            for old in [s for s in self._buffer if s < seq]:
                del self._buffer[old]
            if item is None:
                self._refuse("awaited heatmap missing",
                             "state %d awaited heatmap %d, not received: deciding without it", state.seq, seq)
                return
        else:
            item, self._pending = self._pending, None
            if item is None:
                return
        hm, recv_wall_s = item
        if hm.stamp.clock != state.stamp.clock:
            self._refuse("clock mismatch", "heatmap %d on clock %r, vehicle state on %r: ignored",
                         hm.seq, hm.stamp.clock, state.stamp.clock)
            return
        # Lockstep: a frame from the future cannot be due (another episode's leftover); real time:
        # nothing captured after the newest state by more than the tolerance is real.
        lead_s = 0.0 if self.config.lockstep else self.config.future_tolerance_s
        if hm.stamp.t_s > state.stamp.t_s + lead_s:
            self._refuse("heatmap from the future", "heatmap %d stamped %.3f s after state %.3f s: ignored",
                         hm.seq, hm.stamp.t_s, state.stamp.t_s)
            return
        problem = self._altitude_mismatch(hm)
        if problem is not None:
            self._refuse("heatmap altitude", "heatmap %d refused: %s", hm.seq, problem)
            return
        self._run_policy(hm, recv_wall_s, state)

    # ---- input checks against the camera model and the vehicle's own altitude ---------------

    def _camera_mismatch(self, hm: SafetyHeatmap) -> str | None:
        """Why a heatmap cannot come from the configured camera (None: it can). Valid on the wire
        is not enough: hfov 1e-6 made the focus radius 1.5e6 px and the status could not be built."""
        cfg = self.config
        h, w = hm.prob_safe.shape
        if cfg.camera_size_px is not None and (h, w) != tuple(cfg.camera_size_px):
            return f"{w}x{h} px, the camera's heatmaps are {cfg.camera_size_px[1]}x{cfg.camera_size_px[0]} px"
        if max(h, w) > cfg.max_heatmap_side_px:
            return f"{w}x{h} px, more than {cfg.max_heatmap_side_px} px a side"
        hfov_deg = math.degrees(hm.hfov_rad)
        if abs(hfov_deg - cfg.camera_hfov_deg) > cfg.camera_hfov_tolerance_frac * cfg.camera_hfov_deg:
            return (f"field of view {hfov_deg:.4g} deg, the camera's is {cfg.camera_hfov_deg:g} deg "
                    f"(+-{cfg.camera_hfov_tolerance_frac:.0%})")
        if not MIN_HEATMAP_ALT_M <= hm.alt_agl_m <= MAX_HEATMAP_ALT_M:
            return f"altitude {hm.alt_agl_m:g} m outside {MIN_HEATMAP_ALT_M:g}..{MAX_HEATMAP_ALT_M:g} m"
        return None

    def _altitude_mismatch(self, hm: SafetyHeatmap) -> str | None:
        """Why the heatmap's capture altitude disagrees with the vehicle's own states around its
        capture stamp (None: it agrees, or no state is near enough to tell)."""
        cfg = self.config
        near = self._alt_track.nearest(hm.stamp.t_s)
        if near is None:
            return None
        t_s, alt_m = near
        allowed_m = (max(cfg.altitude_noise_m * HEATMAP_ALT_NOISE_MULT, HEATMAP_ALT_FRAC * alt_m)
                     + cfg.max_vertical_speed_m_s * abs(t_s - hm.stamp.t_s))
        if abs(hm.alt_agl_m - alt_m) <= allowed_m:
            return None
        return (f"captured at {hm.alt_agl_m:.1f} m, the vehicle was at {alt_m:.1f} m (state at {t_s:.3f} s; "
                f"at most {allowed_m:.1f} m apart)")


    def _policy_time_s(self, hm: SafetyHeatmap) -> float:
        """The policy's clock: the heatmap's stamp, shifted only when a step would exceed
        `policy_dt_max_s` or go backwards (so normal runs see the exact stamps)."""
        t_s = hm.stamp.t_s + self._policy_offset_s
        last = self._last_policy_t_s
        if last is not None:
            dt_s = t_s - last
            dt_max_s = self._policy_dt_max_s
            if dt_s > dt_max_s or dt_s <= 0.0:
                capped_s = dt_max_s if dt_s > 0.0 else min(1e-3, dt_max_s)
                self._policy_offset_s = last + capped_s - hm.stamp.t_s
                log.info("controller %s: heatmap %d is %.3f s after the previous one: the policy's clock "
                         "advances %.3f s", self.config.vehicle_id, hm.seq, dt_s, capped_s)
                t_s = last + capped_s
        self._last_policy_t_s = t_s
        return t_s

    def _run_policy(self, hm: SafetyHeatmap, recv_wall_s: float, state: VehicleState) -> None:
        if self._decision is not None and self._decision is self._refused_decision:
            # A terminal decision refused above the hand-over altitude would hold the vehicle for
            # good (a policy that has LANDED never steers again): the mission starts over from
            # here with the policy's initial state, the vehicle holding until it decides.
            log.warning("controller %s: restarting the policy after its refused %s (alt %.1f m)",
                        self.config.vehicle_id, self._decision.state, state.alt_agl_m)
            self.policy.reset()
            self._last_capture_t_s = None
            self.rejected["policy restarted"] += 1
            self._decision = None
        # Altitude and camera model at capture come with the heatmap; attitude and the autopilot's
        # velocity estimate from the state of this tick (the heatmap carries none), and that
        # estimate integrated between the two capture stamps. Never a position.
        odom = None
        if self._last_capture_t_s is not None:
            odom = self._track.displacement_ne_m(self._last_capture_t_s, hm.stamp.t_s)
        # The attitude the frame was captured with (a body-fixed camera turns with the vehicle
        # during the perception latency); this tick's only when the track does not reach back.
        roll, pitch, yaw = self._track.attitude_at(hm.stamp.t_s) or (state.roll_rad, state.pitch_rad, state.yaw_rad)
        look, self._look_unanswered = self._look_unanswered, None
        if look is None and self.looker is not None:
            look = self.looker.poll()
        obs = Observation(t_s=self._policy_time_s(hm), alt_agl_m=hm.alt_agl_m, prob_safe=hm.probability(), hfov_rad=hm.hfov_rad,
                          roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
                          vel_est_body_frd_m_s=state.vel_body_frd_m_s, odom_delta_ne_m=odom, frame_seq=hm.seq,
                          look=look, velocity_trusted=self._nav_trusted,
                          delay_s=max(0.0, state.stamp.t_s - hm.stamp.t_s))
        start = time.perf_counter()
        try:
            decision = self.policy.step(obs)
        except PolicyInputError as exc:
            # Refused before the policy took anything from it: the next displacement still counts
            # from the heatmap before.
            self._refuse("policy refused", "policy refused heatmap %d: %s", hm.seq, exc)
            return
        except Exception as exc:  # noqa: BLE001 - caught once here: a policy bug must end in a hold
            self._last_capture_t_s = None  # how much of it the policy took is unknown
            self.policy_errors += 1
            self._policy_fault = f"policy raised {type(exc).__name__} on heatmap {hm.seq}: {exc}"
            self._refuse("policy error", "%s (holding)", self._policy_fault, level=logging.ERROR)
            if self.policy_errors == 1:
                log.error("first policy error, with its traceback", exc_info=True)
            self._decision = None
            return
        # The policy has taken this heatmap (even if its decision is refused below): the next
        # displacement counts from it, or it would be dead-reckoned twice.
        self._last_capture_t_s = hm.stamp.t_s
        speeds = (*decision.vel_body_frd_m_s, decision.yaw_rate_rad_s)
        until = decision.landing_until_s
        fault = None
        if not all(math.isfinite(v) and abs(v) <= MAX_POLICY_SPEED for v in speeds):
            # Sent as it is, the command fails its own field check and the exception ends the
            # loop (the dovesei policy's integrator once wound up to 18 km/s over a static view).
            fault = f"policy commanded {speeds} (limit {MAX_POLICY_SPEED:g}) on heatmap {hm.seq}"
        elif until is not None and not validate.is_number(until):
            fault = f"policy's landing_until_s {until!r} is not a finite time on heatmap {hm.seq}"
        if fault is not None:
            self.policy_errors += 1
            self._policy_fault = fault
            self._refuse("policy error", "%s (holding)", self._policy_fault, level=logging.ERROR)
            self._decision = None
            return
        self._policy_fault = None
        policy_s = time.perf_counter() - start
        # Transport latency only means something when the sender stamped its wall time.
        to_controller_s = recv_wall_s - hm.sent_wall_s if hm.sent_wall_s > 0.0 else 0.0
        latency = StageLatency(frame_to_segmenter_s=hm.frame_to_segmenter_s, inference_s=hm.inference_s,
                               heatmap_to_controller_s=to_controller_s, policy_s=policy_s)
        was_terminal = self._decision is not None and self._decision.state in TERMINAL_STATES
        if decision.state in TERMINAL_STATES and not was_terminal:  # declared now (a restart or fault clears it)
            self._declared_alt_m = hm.alt_agl_m
        self._adopted = _Adopted(hm, latency, (obs.roll_rad, obs.pitch_rad, obs.yaw_rad))
        self._decision = decision
        # The word's end on the data clock (the policy's clock runs behind it after a capped gap).
        self._word_until_s = None if until is None else until - self._policy_offset_s
        if decision.look_request is not None:
            self._request_look(decision.look_request, state)
        self.adopted_count += 1
        log.debug("adopted heatmap %d: policy %.2f ms, state %s", hm.seq, policy_s * 1e3, decision.state)

    def _request_look(self, look: LookRequest, state: VehicleState) -> None:
        """Hand the policy's close look to the looker (its answer comes with a later heatmap)."""
        self._look_seq += 1
        try:
            req = CropRequest(self.config.vehicle_id, self._look_seq, state.stamp, look.centre_frd_m, look.side_m,
                              look.out_px, sent_wall_s=time.time())
        except FieldError as exc:  # a policy asking for what no wire message can carry
            self._look_unanswered = LookResult(self._look_seq, refusal=f"look request not sendable: {exc}")
            return
        if self.looker is None:
            self._look_unanswered = LookResult(self._look_seq, refusal="no camera to look with (no looker configured)")
            return
        self.looker.submit(req)

    # ---- watchdog ------------------------------------------------------------------------

    def heatmap_age_s(self, state: VehicleState) -> float | None:
        """Data-clock age of the adopted heatmap at this state (None before the first)."""
        if self._adopted is None:
            return None
        return max(0.0, state.stamp.t_s - self._adopted.hm.stamp.t_s)

    def _judge(self, state: VehicleState, wall_s: float | None, nav: NavStatus | None = None) -> tuple[Mode, str]:
        cfg = self.config
        self._confirming = self._word_expired = False
        if wall_s is not None and self._state_advanced_wall_s is not None:
            frozen_s = wall_s - self._state_advanced_wall_s
            if frozen_s > cfg.state_stale_after_s:
                return Mode.STATE_STALE, (f"vehicle state not updated for more than {cfg.state_stale_after_s:g} s: "
                                          "zero velocity")
        # Hysteresis so altitude noise around the hand-over altitude cannot flap the mode. Entry
        # needs the policy's word: a descent it has aborted (WAITING, CLIMBING, ABORT) that sinks
        # through the altitude on inertia is no landing; the policy keeps flying (it climbs back).
        if self._in_handover:
            self._in_handover = state.alt_agl_m <= cfg.handover_alt_m + cfg.handover_release_m
        else:
            decision = self._decision
            committed = (decision is not None and (decision.landing or decision.state in TERMINAL_STATES)
                         and self._policy_fault is None and not self._word_ran_out(state))
            # One low sample is no altitude: a majority of the recent states must be at or below it
            # (a forged 19 m state handed over for a tick).
            self._in_handover = committed and self._states_within(0.0) >= cfg.handover_confirm_states
            if state.alt_agl_m <= cfg.handover_alt_m and not committed and not self._below_uncommitted:
                log.warning("controller %s: at %.1f m, below the hand-over altitude %g m, but the policy is not "
                            "landing (%s): no hand-over, following the policy", cfg.vehicle_id, state.alt_agl_m,
                            cfg.handover_alt_m, self._decision.state if self._decision is not None else "no decision")
                self.rejected["below hand-over, not landing"] += 1
            # Once per sink: a noisy baro crossing the altitude again and again while the policy
            # holds below it (a close look waiting on someone) is the same sink until it climbs
            # clear of the hand-over band.
            if committed or state.alt_agl_m > cfg.handover_alt_m + cfg.handover_release_m:
                self._below_uncommitted = False
            elif state.alt_agl_m <= cfg.handover_alt_m:
                self._below_uncommitted = True
        if self._in_handover:
            return Mode.HANDOVER, (f"at/below the hand-over altitude {cfg.handover_alt_m:g} m: "
                                   "short-range sensors take over")
        if nav is not None and not nav.velocity_trusted:
            # Descending blind drifts onto ground nobody checked: no descent until a source is
            # trusted; lost in flight, the way back over the ground that was measured first.
            reason = f"no trusted velocity source: {nav.reason}"
            if self._retreat_ne is not None:  # flown on: towards ground seen, the way it was seen, or back
                speed = f"at {self.config.nav_retreat_speed_m_s:g} m/s, no descent"
                bearing = f"{math.degrees(math.atan2(self._retreat_ne[1], self._retreat_ne[0])) % 360:.0f} deg"
                if self._retreat.seen_ne is not None:  # set by this tick's update, when flown towards
                    reason += (f"; flying towards the ground the camera can measure, "
                               f"{math.hypot(*self._retreat.seen_ne) * state.alt_agl_m:.0f} m away at {bearing}, "
                               f"{speed}")
                elif self._retreat.seen_ago_s is not None:
                    reason += (f"; flying on towards the ground the camera measured "
                               f"{self._retreat.seen_ago_s:.0f} s ago (of {self.config.nav_retreat_max_s:g} s), "
                               f"at {bearing}, {speed}")
                else:
                    reason += (f"; flying back over the ground the camera measured {speed} "
                               f"({self._retreat.lost_for_s(state.stamp.t_s):.0f} of "
                               f"{self.config.nav_retreat_max_s:g} s)")
            return Mode.NO_VELOCITY, reason
        if self._policy_fault is not None:
            return Mode.POLICY_FAULT, f"{self._policy_fault}: holding position"
        decision = self._decision
        band_m = cfg.handover_release_m
        if self._declared_alt_m is not None and self._declared_alt_m <= cfg.handover_alt_m:
            band_m = max(band_m, cfg.handover_declared_band_m)  # measured at the altitude on its own heatmap
        self._confirming = (decision is not None and decision.state in TERMINAL_STATES
                            and (state.alt_agl_m <= cfg.handover_alt_m
                                 or statistics.median(self._recent_alts) <= cfg.handover_alt_m + band_m))
        if self._confirming and self._word_ran_out(state):
            self._confirming, self._word_expired = False, True
            return Mode.HOLD, self._word_reason()
        if self._confirming:
            # Declared at the altitude (within the baro's noise of it): the hand-over follows once
            # the states confirm it, the vehicle sinking slowly meanwhile (`_velocity`).
            return Mode.HOLD, (f"policy declared {decision.state} at {state.alt_agl_m:.1f} m: confirming the "
                               f"altitude ({self._states_within(0.0)} of the last {len(self._recent_alts)} "
                               f"states at or below {cfg.handover_alt_m:g} m, {cfg.handover_confirm_states} needed)")
        if decision is not None and decision.state in TERMINAL_STATES:
            if decision is not self._refused_decision:  # counted once per decision, not per tick
                self._refused_decision = decision
                self.rejected["terminal above hand-over"] += 1
            return Mode.POLICY_FAULT, (f"policy declared {decision.state} at {state.alt_agl_m:.1f} m, above the "
                                       f"hand-over altitude {cfg.handover_alt_m:g} m: refused, holding position")
        age_s = self.heatmap_age_s(state)
        if age_s is None:
            return Mode.NO_HEATMAP, "no heatmap received yet: holding position"
        if age_s > cfg.heatmap_climb_after_s:
            return Mode.CLIMB, (f"heatmap older than {cfg.heatmap_climb_after_s:g} s: "
                                f"climbing to the search altitude {self.search_alt_m:.1f} m and holding")
        if age_s > cfg.heatmap_hold_after_s:
            return Mode.HOLD, f"heatmap older than {cfg.heatmap_hold_after_s:g} s: descent stopped, holding position"
        if decision is not None and decision.landing and self._word_ran_out(state):
            self._word_expired = True
            return Mode.HOLD, self._word_reason()
        return Mode.OK, "heatmaps fresh: following the policy"

    def _word_ran_out(self, state: VehicleState) -> bool:
        """The current decision's landing word has run out (its landing_until_s is past at this state)."""
        return self._decision is not None and self._word_until_s is not None and state.stamp.t_s > self._word_until_s

    def _word_reason(self) -> str:
        return (f"the policy's landing word ran out at t={self._word_until_s:.2f} s (its clearance of the "
                "ground is that old): descent stopped until it renews it")

    def _fence(self, vel: tuple[float, float, float], state: VehicleState, reason: str,
               pull_back: bool) -> tuple[tuple[float, float, float], str]:
        """Every command through the geofence; the status reason says when it capped one."""
        if self.geofence is None:
            return vel, reason
        vel, why = self.geofence.cap(vel, state.yaw_rad, pull_back)
        fenced = why is not None
        if fenced != self._fenced:
            log.log(logging.WARNING if fenced else logging.INFO, "controller %s: %s", self.config.vehicle_id,
                    why if fenced else f"geofence: back within {self.geofence.radius_m:g} m, commands untouched")
            self._fenced = fenced
        return vel, (f"{reason}; {why}" if fenced else reason)

    @property
    def search_alt_m(self) -> float:
        """Where the climb watchdog goes: the configured altitude or the first one seen."""
        if self.config.search_alt_m is not None:
            return self.config.search_alt_m
        return self._first_alt_m if self._first_alt_m is not None else 0.0

    def _states_within(self, above_m: float) -> int:
        """How many of the recent distinct states read at most `above_m` over the hand-over altitude."""
        limit_m = self.config.handover_alt_m + above_m
        return sum(1 for alt_m in self._recent_alts if alt_m <= limit_m)

    def _velocity(self, mode: Mode, state: VehicleState) -> tuple[tuple[float, float, float], float]:
        if mode is Mode.HOLD and self._confirming:
            # Confirming a declared hand-over: sink slowly onto the altitude, never far below it,
            # and fly the policy's horizontal command. Without GNSS a zero command is no hold: the
            # autopilot holds its own biased velocity estimate at zero, and a policy that learnt
            # the bias commands its opposite (harsh villas start 1 of 6 drifted 3.4 m at 1.5 m/s
            # in the 2.4 s the baro's noise took to confirm, off the lawn onto a sidewalk).
            cfg = self.config
            sinking = state.alt_agl_m > cfg.handover_alt_m - cfg.handover_release_m
            fwd, right = 0.0, 0.0
            if self._decision is not None:
                fwd, right, _ = self._as_meant(self._decision.vel_body_frd_m_s, state)
            return (fwd, right, cfg.handover_sink_m_s if sinking else 0.0), 0.0
        if mode is Mode.OK and self._decision is not None:
            return self._as_meant(self._decision.vel_body_frd_m_s, state), self._decision.yaw_rate_rad_s
        if mode is Mode.HOLD and self._word_expired and self._decision is not None:
            # Over the spot, waiting for the policy's next word: its horizontal command (a zero one
            # is no hold without GNSS, see above), no descent.
            fwd, right, down = self._as_meant(self._decision.vel_body_frd_m_s, state)
            return (fwd, right, min(down, 0.0)), self._decision.yaw_rate_rad_s
        if mode is Mode.NO_VELOCITY and self._retreat_ne is not None:
            fwd, right = to_body(self._retreat_ne[0], self._retreat_ne[1], state.yaw_rad)
            return (fwd, right, 0.0), 0.0
        if mode is Mode.CLIMB:
            error_m = self.search_alt_m - state.alt_agl_m
            # FRD: negative down is up. Proportional near the target, never a descent.
            up_m_s = min(self.config.climb_speed_m_s, self.config.climb_gain_per_s * error_m) if error_m > 0 else 0.0
            return (0.0, 0.0, -up_m_s if up_m_s > 0 else 0.0), 0.0
        return (0.0, 0.0, 0.0), 0.0

    def _as_meant(self, vel: tuple[float, float, float], state: VehicleState) -> tuple[float, float, float]:
        """The decision's body velocity in the body frame of this tick: the policy meant the frame
        of the heading it was given with its heatmap; if the vehicle has turned since (an autopilot
        that yaws, heading drift), the horizontal command turns back by as much."""
        adopted = self._adopted
        if adopted is None:
            return vel
        turned_rad = math.remainder(adopted.attitude_rad[2] - state.yaw_rad, 2.0 * math.pi)
        if turned_rad == 0.0:
            return vel
        fwd, right = to_ne(vel[0], vel[1], turned_rad)
        return fwd, right, vel[2]

    @property
    def mode(self) -> Mode | None:
        return self._mode

    def landing_target(self, state: VehicleState) -> tuple[float, float, float] | None:
        """The spot to land on as MAVLink's LANDING_TARGET sees it from the vehicle now: (angle_x,
        angle_y, distance) in the body FRD frame (image x right, image y down = body backward);
        None without a spot.

        The spot is fixed on the ground the first time this is asked after the hand-over began:
        the newest decision's target pixel, cast with the attitude it was decided with onto flat
        ground at the heatmap's altitude. From then on it is carried by the autopilot's velocity
        estimate integrated tick by tick (no position), never by the policy's later views: below
        the hand-over altitude the camera's verdict is the short-range sensors' job, and a target
        pixel re-sent as fixed angles would run away with the vehicle as it moves over it.
        """
        now_s = state.stamp.t_s
        if self._spot_rel_ned_m is None:
            spot = self._spot_at_capture()
            if spot is None:
                return None
            self._spot_rel_ned_m, self._spot_t_s = spot
        moved = self._track.displacement_ne_m(self._spot_t_s, now_s)
        if moved is None:
            return None  # the velocity track has a gap: better no target than a made-up one
        n, e, d = self._spot_rel_ned_m
        # The ground below is flat: the spot stays `alt` metres down whatever the descent did.
        self._spot_rel_ned_m, self._spot_t_s = (n - moved[0], e - moved[1], max(state.alt_agl_m, 0.0)), now_s
        fwd, right, down = ned_to_body_frd(self._spot_rel_ned_m, state.roll_rad, state.pitch_rad, state.yaw_rad)
        down = max(down, 1e-3)  # a spot at or above the horizon would be a broken geometry, not a target
        return math.atan2(right, down), math.atan2(-fwd, down), math.sqrt(fwd * fwd + right * right + down * down)

    def _spot_at_capture(self) -> tuple[tuple[float, float, float], float] | None:
        """(spot relative to the vehicle in NED metres, capture time) from the newest decision."""
        adopted, decision = self._adopted, self._decision
        if adopted is None or decision is None or decision.target_px is None:
            return None
        h, w = adopted.hm.prob_safe.shape
        focal_px = footprint.focal_px(w, adopted.hm.hfov_rad)  # square pixels: one focal length
        row, col = decision.target_px
        # The pixel's ray in the body frame (camera looking down: image up = forward), then NED.
        ray_ned = body_frd_to_ned((-(row - (h - 1) / 2.0) / focal_px, (col - (w - 1) / 2.0) / focal_px, 1.0),
                                  *adopted.attitude_rad)
        if ray_ned[2] <= 1e-3:
            return None
        scale = max(adopted.hm.alt_agl_m, 0.0) / ray_ned[2]
        return (ray_ned[0] * scale, ray_ned[1] * scale, ray_ned[2] * scale), adopted.hm.stamp.t_s

    @property
    def decision(self) -> Decision | None:
        return self._decision

    def _status(self, mode: Mode, reason: str, state: VehicleState,
                vel: tuple[float, float, float], nav: NavStatus | None = None) -> ControllerStatus:
        decision = self._decision
        age_s = self.heatmap_age_s(state)
        target = decision.target_px if decision is not None else None
        threshold = decision.threshold if decision is not None else None
        # The chosen spot, as a policy with a ground map reports it (explainable status).
        spot = decision.spot if decision is not None else None
        if mode is Mode.HANDOVER:
            state_name = "HANDOVER"
        else:
            state_name = decision.state if decision is not None else "INIT"
        return ControllerStatus(
            vehicle_id=self.config.vehicle_id, seq=self._tick_seq, stamp=state.stamp,
            policy=getattr(self.policy, "name", self.config.policy), state=state_name, watchdog=mode.watchdog,
            reason=reason, frame_seq=self._adopted.hm.seq if self._adopted is not None else -1,
            heatmap_age_s=age_s if age_s is not None else -1.0,
            focus_radius_px=float(decision.focus_radius_px) if decision is not None else 0.0,
            target_valid=target is not None,
            target_row_px=float(target[0]) if target is not None else 0.0,
            target_col_px=float(target[1]) if target is not None else 0.0,
            threshold_valid=threshold is not None, threshold=float(threshold) if threshold is not None else 0.0,
            vel_body_frd_m_s=vel, alt_agl_m=state.alt_agl_m,
            policy_reason=decision.reason if decision is not None else "",
            spot_valid=spot is not None, spot_north_m=float(spot.north_m) if spot else 0.0,
            spot_east_m=float(spot.east_m) if spot else 0.0,
            spot_clearance_m=max(float(spot.clearance_m), 0.0) if spot else 0.0,
            spot_confidence=min(max(float(spot.confidence), 0.0), 1.0) if spot else 0.0,
            handover=mode is Mode.HANDOVER,
            nav_source=nav.source if nav is not None else "", gnss_lost=nav.gnss_lost if nav is not None else False,
            position_lost=nav.position_lost if nav is not None else False,
            nav_reason=nav.reason if nav is not None else "",
            look_verdict=decision.look_verdict if decision is not None else "",
            **_confirmed_fields(decision),
        )


def _confirmed_fields(decision: Decision | None) -> dict[str, Any]:
    """The status fields of the decision's confirming look; none when it has none or its pixel is
    not one a frame can have (a policy bug must not take the status message down with it)."""
    c = decision.confirmed if decision is not None else None
    lo, hi = ControllerStatus.RANGES["confirmed_row_px"]
    if c is None or c.frame_seq < 0 or not all(math.isfinite(v) and lo <= v <= hi for v in (c.row_px, c.col_px)):
        return {}
    return {"confirmed_valid": True, "confirmed_frame_seq": int(c.frame_seq), "confirmed_row_px": float(c.row_px),
            "confirmed_col_px": float(c.col_px)}
