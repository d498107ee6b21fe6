"""Flying an autopilot that has lost its position: what is trusted, and the attitude loop.

Pure pieces (no thread, no socket) that the MAVLink adapter feeds and asks:

    EKF_STATUS_REPORT / ESTIMATOR_STATUS flags, GPS_RAW_INT fix, LOCAL_POSITION_NED arrivals
        --> NavJudge --> NavStatus (GNSS lost? position lost? which velocity is trusted, and why)
    VisualOdometry (the camera's velocity, from Zenoh) --> OdometryGate (fresh, valid, good quality?)
    VelocityCommand + visual velocity + climb rate --> AttitudeLoop --> roll, pitch, yaw, thrust
        (SET_ATTITUDE_TARGET in ArduCopter GUIDED_NOGPS or PX4 OFFBOARD attitude)

The three `--gnss-denied` modes (what happens once GNSS is gone):

    external-nav  the visual velocity is streamed to the autopilot (VISION_SPEED_ESTIMATE on
                  ArduPilot, ODOMETRY on PX4) and ArduPilot is switched to an EK3 source set whose
                  VELXY is ExternalNav (MAV_CMD_SET_EKF_SOURCE_SET): the EKF keeps a velocity and a
                  relative position, so GUIDED/OFFBOARD velocity setpoints keep working. Trusted
                  while the odometry is good AND the autopilot reports horizontal velocity and
                  relative position (it is really fusing it).
    attitude      ArduPilot is switched to GUIDED_NOGPS (PX4 stays in OFFBOARD) and dovesei closes
                  the velocity loop itself with attitude targets from the visual velocity.
                  Trusted while the odometry is good.
    off           nothing is switched: the loss is reported and the controller holds.

Whatever the mode, a velocity that is not trusted means no descent (`core.Mode.NO_VELOCITY`); a
vehicle that lost it in flight flies towards measurable ground its camera still sees aside
(`OdometryGate.ground_seen`), on the way it was last seen for a bounded time once it leaves the
view, else back over the ground the camera measured (`NavRetreat`), for a bounded time, on the
autopilot's inertial estimate: in `attitude` mode the loop has no velocity to close and levels.

Sources: EKF_STATUS_REPORT flag bits (MAVLink ardupilotmega EKF_STATUS_FLAGS) and PX4's
ESTIMATOR_STATUS (ESTIMATOR_STATUS_FLAGS) share bits 1..512; ArduCopter's position_ok() needs
horiz_pos_abs or horiz_pos_rel and not const_pos_mode once armed, and counts a relative position
only when optical flow or visual odometry (VISO_TYPE) is enabled (ArduCopter/system.cpp
ekf_has_relative_position). SET_ATTITUDE_TARGET thrust: ArduCopter reads it as a climb rate
(0.5 holds, 1 climbs at WPNAV_SPEED_UP, 0 descends at WPNAV_SPEED_DN) unless GUID_OPTIONS bit 3
(8, SetAttitudeTarget_ThrustAsThrust) is set (GCS_Mavlink.cpp handle_message_set_attitude_target);
PX4 reads it as collective thrust, hovering at MPC_THR_HOVER (0.5 by default).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

from dovesei.controller.mavlink.proto import (
    EKF_ATTITUDE,
    EKF_CONST_POS_MODE,
    EKF_POS_HORIZ_ABS,
    EKF_POS_HORIZ_REL,
    EKF_VELOCITY_HORIZ,
    GPS_FIX_TYPE_3D,
)
from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import VisualOdometry

GNSS_DENIED_MODES = ("off", "external-nav", "attitude")
# What "external-nav" sends ArduPilot for each camera velocity (PX4 always gets ODOMETRY):
#   speed  VISION_SPEED_ESTIMATE: EKF3 fuses it as an ExternalNav velocity (FuseVelPosNED), which keeps
#          the velocity but, with no position source, times the position out after posRetryTimeUseVel
#          (10 s) so horiz_pos_rel drops and ArduCopter's position_ok() with it;
#   delta  VISION_POSITION_DELTA: EKF3 fuses it as body odometry (SelectBodyOdomFusion, with
#          EK3_SRCn_VELXY = ExternalNav), which sets horiz_pos_rel (doingBodyVelNav,
#          NavEKF3_core::updateFilterStatus): a relative position GUIDED flies on;
#   both   the two (the default): the camera's velocity counts twice in the EKF, so its noise floors
#          (VISO_VEL_M_NSE and the confidence) should not be set tighter than the camera's variance.
EXTERNAL_NAV_MESSAGES = ("both", "delta", "speed")
# How ArduPilot 4.6 weighs each message (read in its source), and so what dovesei sends in it:
#   delta  NavEKF3_core::writeBodyFrameOdom: velErr = EK3_VIS_VERR_MIN + (EK3_VIS_VERR_MAX -
#          EK3_VIS_VERR_MIN) x (1 - confidence / 100), defaults 0.1 and 0.9 m/s (AP_NavEKF3.cpp): the
#          confidence sent makes velErr the camera's own standard deviation (clamped to that range);
#   speed  GCS_MAVLINK::handle_vision_speed_estimate ignores the covariance, and AP_VisualOdom_MAV
#          fuses every sample at VISO_VEL_M_NSE: only samples at least that good go in it (the
#          recommended VISO_VEL_M_NSE is this limit). In SITL, samples up to 1 m/s sent at the 0.1 m/s
#          default were followed by "EKF variance" and the EKF failsafe's LAND at 88 m (docs/sitl.md).
EK3_VIS_VERR_MIN_M_S, EK3_VIS_VERR_MAX_M_S = 0.1, 0.9
SPEED_MESSAGE_MAX_SD_M_S = 0.5
THRUST_MODES = ("climb-rate", "thrust")
GRAVITY_M_S2 = 9.80665

# Where the trusted velocity comes from (the status's `nav_source`).
SOURCE_AUTOPILOT = "autopilot"  # the autopilot's own estimate (GNSS, or flow it was set up with)
SOURCE_EXTERNAL_NAV = "external-nav"  # the autopilot's EKF, fusing our visual velocity
SOURCE_VISUAL = "visual"  # our visual velocity, closed by our own attitude loop
SOURCE_NONE = "none"


@dataclass(frozen=True)
class NavStatus:
    """What the controller may trust about the vehicle's motion now, and why (one line)."""

    gnss_lost: bool  # no GNSS fix, or the EKF lost its absolute position
    position_lost: bool  # the autopilot has no horizontal position at all (GUIDED would be refused)
    velocity_trusted: bool  # some horizontal velocity source is trusted: descent allowed
    source: str  # SOURCE_* above
    reason: str
    # Untrusted only: where the camera's newest frame sees measurable ground, north/east metres of
    # level ground per metre of altitude from below the vehicle (`OdometryGate.ground_seen`).
    ground_seen_ne: tuple[float, float] | None = None


@dataclass(frozen=True)
class EkfHealth:
    """The estimator flags read as the questions a multirotor's guided flight asks."""

    attitude: bool
    velocity_horizontal: bool
    position_absolute: bool
    position_relative: bool
    const_pos_mode: bool

    @property
    def position(self) -> bool:
        """ArduCopter's position_ok() once armed: a horizontal position, not in constant-position mode."""
        return (self.position_absolute or self.position_relative) and not self.const_pos_mode

    def missing(self) -> str:
        """The missing pieces as words, for a reason text."""
        words = [name for ok, name in ((self.attitude, "attitude"), (self.velocity_horizontal, "horizontal velocity"),
                                       (self.position_absolute or self.position_relative, "horizontal position"))
                 if not ok]
        if self.const_pos_mode:
            words.append("constant-position mode")
        return ", ".join(words) if words else "nothing"


def ekf_health(flags: int) -> EkfHealth:
    """EKF_STATUS_REPORT.flags (ArduPilot) or ESTIMATOR_STATUS.flags (PX4) as an `EkfHealth`."""
    if isinstance(flags, bool) or not isinstance(flags, int) or not 0 <= flags < 1 << 16:
        raise ConfigError(f"estimator flags must be a 16-bit integer, got {flags!r}")
    return EkfHealth(attitude=bool(flags & EKF_ATTITUDE), velocity_horizontal=bool(flags & EKF_VELOCITY_HORIZ),
                     position_absolute=bool(flags & EKF_POS_HORIZ_ABS),
                     position_relative=bool(flags & EKF_POS_HORIZ_REL),
                     const_pos_mode=bool(flags & EKF_CONST_POS_MODE))


@dataclass(frozen=True)
class OdometryLimits:
    """When a visual velocity is good enough to fly on (receiver's clock, seconds)."""

    max_age_s: float = 0.5  # a camera at >= 10 Hz: five frames missed is a lost source
    min_quality: float = 0.5
    max_var_m2_s2: float = 1.0  # 1 m/s standard deviation: beyond it the EKF would refuse it anyway
    # Measurable ground seen aside (`ground_seen`): at least this share of the frame's grid cells
    # with a corner (a 320 px work image has ~200: six of them, a pier's worth, not one wave) whose
    # centre lies at least this far off the nadir, per metre of altitude (10 m at 100 m: a view
    # textured all over, whose velocity failed for another reason, has its centre at the nadir).
    seen_min_share: float = 0.03
    seen_min_offset: float = 0.1

    def __post_init__(self) -> None:
        validate.positive("odometry max_age_s", self.max_age_s)
        validate.in_range("odometry min_quality", self.min_quality, 0.0, 1.0)
        validate.positive("odometry max_var_m2_s2", self.max_var_m2_s2)
        validate.in_range("odometry seen_min_share", self.seen_min_share, 0.0, 1.0)
        validate.in_range("odometry seen_min_offset", self.seen_min_offset, 0.0, 10.0)


class OdometryGate:
    """The newest visual velocity and whether the source may be flown on now (not thread-safe: one owner).

    The source is trusted while a good sample (fresh, valid, confident) came within `max_age_s`:
    one noisy frame pair is not a lost source. Judging the newest sample alone stopped a SITL
    descent at 75-82 m for ten minutes: a pair over `max_var_m2_s2` every few frames flipped the
    trust off again and again, though the EKF only ever received the good ones.
    """

    def __init__(self, limits: OdometryLimits | None = None) -> None:
        self.limits = limits if limits is not None else OdometryLimits()
        self._newest: VisualOdometry | None = None
        self._recv_s = 0.0
        self._good: VisualOdometry | None = None  # the newest good sample and when it came
        self._good_recv_s = 0.0

    def add(self, odom: VisualOdometry, recv_s: float) -> bool:
        """Keep `odom` if it is newer than the one held; True when kept."""
        if self._newest is not None and odom.frame_seq <= self._newest.frame_seq and odom.stamp.t_s <= \
                self._newest.stamp.t_s:
            return False  # a duplicate or a reordered older sample
        self._newest, self._recv_s = odom, float(recv_s)
        if not self._fault(odom):
            self._good, self._good_recv_s = odom, float(recv_s)
        return True

    @property
    def newest(self) -> VisualOdometry | None:
        return self._newest

    def _fault(self, odom: VisualOdometry) -> str:
        """Why this sample may not be flown on ('' when it may)."""
        lim = self.limits
        if not odom.valid:
            return f"visual velocity invalid (quality {odom.quality:.2f})"
        if odom.quality < lim.min_quality:
            return f"visual velocity quality {odom.quality:.2f} below {lim.min_quality:g}"
        if odom.vel_var_m2_s2 > lim.max_var_m2_s2:
            return f"visual velocity variance {odom.vel_var_m2_s2:.2f} m2/s2 above {lim.max_var_m2_s2:g}"
        return ""

    def sample_good(self, odom: VisualOdometry) -> bool:
        """May this one sample be sent on (valid, confident)? Freshness is the receiver's to judge."""
        return not self._fault(odom)

    def judge(self, now_s: float) -> tuple[bool, str]:
        """(good, why not) at `now_s` on the receiver's clock: a good sample within `max_age_s`."""
        odom, lim = self._newest, self.limits
        if odom is None:
            return False, "no visual velocity received"
        if self._good is not None and now_s - self._good_recv_s <= lim.max_age_s:
            return True, ""
        age_s = now_s - self._recv_s
        if age_s > lim.max_age_s:
            return False, f"visual velocity {age_s:.1f} s old (limit {lim.max_age_s:g} s)"
        return False, f"{self._fault(odom)} (no good sample for {lim.max_age_s:g} s)"

    def ground_seen(self, now_s: float) -> tuple[float, float] | None:
        """Where the newest frame, fresh at `now_s`, sees measurable ground aside: north/east metres
        of level ground per metre of altitude from below the vehicle, or None (none seen, too
        little of it, straight below, or no fresh frame)."""
        odom, lim = self._newest, self.limits
        if odom is None or now_s - self._recv_s > lim.max_age_s or odom.texture_share < lim.seen_min_share:
            return None
        fwd, right = odom.texture_offset
        if math.hypot(fwd, right) < lim.seen_min_offset:
            return None
        cy, sy = math.cos(odom.yaw_rad), math.sin(odom.yaw_rad)
        return fwd * cy - right * sy, fwd * sy + right * cy

    def velocity(self, now_s: float) -> tuple[float, float, float] | None:
        """The newest good sample's body FRD velocity while the source is trusted at `now_s`, else None."""
        good, _ = self.judge(now_s)
        return self._good.vel_body_frd_m_s if good and self._good is not None else None


class NavJudge:
    """Turns what the autopilot says about its estimate into a `NavStatus` for one `--gnss-denied` mode.

    GNSS is lost when GPS_RAW_INT reports less than a 3D fix after having had one, or when the EKF
    flags lose the absolute position after having had it (a vehicle that never had GNSS, e.g. one
    set up to fly on optical flow, is judged by its flags alone). The position is lost when the EKF flags say so, or
    (PX4, which simply stops LOCAL_POSITION_NED when its position is invalid) when the local
    position stopped while the attitude still streams. With no GPS_RAW_INT and no flags at all
    nothing is judged lost: the autopilot's velocity is trusted as before (the sim, a flow setup).
    """

    def __init__(self, mode: str = "off", *, local_stale_s: float = 2.0) -> None:
        validate.one_of("gnss_denied", mode, GNSS_DENIED_MODES)
        self.mode = mode
        self.local_stale_s = validate.positive("local_stale_s", local_stale_s)
        self._fix_type: int | None = None
        self._had_fix = False
        self._health: EkfHealth | None = None
        self._had_absolute = False
        self._local_s: float | None = None

    def on_gps_fix(self, fix_type: int) -> None:
        self._fix_type = int(fix_type)
        self._had_fix = self._had_fix or self._fix_type >= GPS_FIX_TYPE_3D

    def on_ekf_flags(self, flags: int) -> None:
        health = ekf_health(flags)
        self._had_absolute = self._had_absolute or (health.position_absolute and not health.const_pos_mode)
        self._health = health

    def on_local_position(self, now_s: float) -> None:
        self._local_s = float(now_s)

    @property
    def health(self) -> EkfHealth | None:
        return self._health

    def gnss_lost(self) -> tuple[bool, str]:
        if self._had_fix and self._fix_type is not None and self._fix_type < GPS_FIX_TYPE_3D:
            return True, f"GNSS lost (GPS_RAW_INT fix type {self._fix_type})"
        health = self._health
        if health is not None and self._had_absolute and not (health.position_absolute and not health.const_pos_mode):
            return True, "GNSS lost (the EKF has no absolute position any more)"
        return False, ""

    def position_lost(self, now_s: float) -> tuple[bool, str]:
        health = self._health
        if health is not None and not health.position:
            return True, f"the autopilot's EKF has no position (missing: {health.missing()})"
        if self._local_s is not None and now_s - self._local_s > self.local_stale_s:
            return True, f"no LOCAL_POSITION_NED for {now_s - self._local_s:.1f} s (the estimator stopped it)"
        return False, ""

    def status(self, now_s: float, odometry: OdometryGate) -> NavStatus:
        """The judgement now; untrusted, with where the camera sees measurable ground (modes that
        fly on the camera)."""
        status = self._status(now_s, odometry)
        if status.velocity_trusted or self.mode == "off":
            return status
        return replace(status, ground_seen_ne=odometry.ground_seen(now_s))

    def _status(self, now_s: float, odometry: OdometryGate) -> NavStatus:
        gnss_lost, gnss_why = self.gnss_lost()
        pos_lost, pos_why = self.position_lost(now_s)
        health = self._health
        ekf_velocity = health is None or health.velocity_horizontal
        if not gnss_lost and not pos_lost:
            if ekf_velocity:
                return NavStatus(False, False, True, SOURCE_AUTOPILOT, "the autopilot's estimate is healthy")
            return NavStatus(False, False, False, SOURCE_NONE,
                             "the autopilot's EKF has no horizontal velocity: no descent")
        lost = "; ".join(w for w in (gnss_why, pos_why) if w)
        if self.mode == "off":
            return NavStatus(gnss_lost, pos_lost, False, SOURCE_NONE,
                             f"{lost}; --gnss-denied off: holding, no descent")
        good, odo_why = odometry.judge(now_s)
        if self.mode == "attitude":
            if good:
                return NavStatus(gnss_lost, pos_lost, True, SOURCE_VISUAL,
                                 f"{lost}; flying attitude targets on the visual velocity")
            return NavStatus(gnss_lost, pos_lost, False, SOURCE_NONE, f"{lost}; {odo_why}: no descent")
        # external-nav: trusted only once the autopilot really fuses it.
        if not good:
            return NavStatus(gnss_lost, pos_lost, False, SOURCE_NONE, f"{lost}; {odo_why}: no descent")
        if pos_lost or not ekf_velocity:
            return NavStatus(gnss_lost, pos_lost, False, SOURCE_NONE,
                             f"{lost}; the EKF is not fusing the visual velocity yet: no descent")
        return NavStatus(gnss_lost, False, True, SOURCE_EXTERNAL_NAV,
                         f"{lost}; the EKF flies on the visual velocity (external nav)")


class NavRetreat:
    """Back over ground the camera measured, when its velocity is lost in flight (pure; one owner).

    Over calm water, or any ground without texture, the camera measures no velocity, and a hold
    there is no hold: the autopilot holds its unaided estimate at zero and drifts with the wind
    and the estimate's bias for as long as it waits (the coast's search flew out over the sea and
    held there until the time ran out, 8 of 20 `realistic` starts). A vehicle that flew onto such
    ground came from ground that was measured: it flies back there, on the autopilot's own
    estimate, at `speed_m_s` with no vertical motion, until a velocity is trusted again or `max_s`
    are spent; then it holds. `max_s` 0 turns it off.

    Where to: towards the position (the velocity estimate integrated) `back_s` before the end of
    the last trusted stretch that lasted `solid_s`, straight, and on past it if the velocity is
    still not trusted there. A short trusted stretch at the water's edge (quality flickering over
    the threshold) neither ends the loss nor moves that point: reversing its velocity (the way
    back out of the sea), or aiming again at a point already passed, sent the vehicle out again
    (coast start 2 of 8). From 100 m the loss comes with the land's edge near the frame's edge,
    some 70 m out; 3 s back at the search's 8 m/s was still over the water, 10 s is not.
    """

    def __init__(self, speed_m_s: float, max_s: float, solid_s: float = 3.0, back_s: float = 10.0) -> None:
        validate.positive("NavRetreat speed_m_s", speed_m_s)
        validate.non_negative("NavRetreat max_s", max_s)
        self.speed_m_s, self.max_s, self.solid_s, self.back_s = speed_m_s, max_s, solid_s, back_s
        self.reset()

    def reset(self) -> None:
        self._t_s: float | None = None
        self._pos = (0.0, 0.0)  # the velocity estimate integrated (north, east m), trusted or not
        self._run_t_s: float | None = None  # when the current trusted stretch began
        self._run: deque[tuple[float, float, float]] = deque()  # its last back_s seconds: (t_s, north, east)
        self._good: tuple[float, float] | None = None  # where to go back to
        self._lost_t_s: float | None = None
        self._way: tuple[float, float] | None = None  # the newest way back (north/east m/s)
        self.seen_ne: tuple[float, float] | None = None  # this tick's ground seen, when flown towards
        # (t_s, unit north, unit east): where ground was last seen, until a steady stretch ends the loss
        self._seen_last: tuple[float, float, float] | None = None
        self.seen_ago_s: float | None = None  # this tick flies on towards ground seen this long ago

    def update(self, t_s: float, vel_ne_m_s: tuple[float, float], trusted: bool,
               seen_ne: tuple[float, float] | None = None) -> tuple[float, float] | None:
        """One tick (the autopilot's velocity estimate, north/east, whether it is trusted, and where
        the camera sees measurable ground, `NavStatus.ground_seen_ne`): the north/east velocity to
        fly on, or None (trusted: follow the policy; else hold).

        Ground seen now is flown towards before the remembered way back (a measurement, re-taken
        every frame, not a dead-reckoned guess), with no time limit while it is seen; `seen_ne`
        says when it is (None otherwise). When it leaves the view the vehicle flies on the way it
        was last seen for up to `max_s` (`seen_ago_s` says so), before the way back: the blind
        vehicle's estimate is unaided, so the wind it does not know of carries it off while the
        edge of the view is still 70 m short of the coast, and a hold there drifts for good
        (coast start 6, `harsh`: the coast's share of the view sank under the gate's 3 % at 76 s,
        the hold drifted 470 m on the wind and out of the world)."""
        way = self._update(t_s, vel_ne_m_s, trusted)
        self.seen_ne, self.seen_ago_s = None, None
        if trusted or self.max_s <= 0:
            return way
        norm = math.hypot(*seen_ne) if seen_ne is not None else 0.0
        if 0.0 < norm < math.inf:
            self.seen_ne, self._seen_last = seen_ne, (t_s, seen_ne[0] / norm, seen_ne[1] / norm)
        elif self._seen_last is not None and t_s - self._seen_last[0] <= self.max_s:
            self.seen_ago_s = t_s - self._seen_last[0]
        else:
            return way  # none seen this loss (or a gate configured with no minimum offset saw it at the nadir)
        _, north, east = self._seen_last
        return north * self.speed_m_s, east * self.speed_m_s

    def _update(self, t_s: float, vel_ne_m_s: tuple[float, float], trusted: bool) -> tuple[float, float] | None:
        if self._t_s is not None and t_s < self._t_s:
            self.reset()  # time went back: another timeline
        if self._t_s is not None:
            dt_s = min(t_s - self._t_s, 1.0)
            self._pos = (self._pos[0] + vel_ne_m_s[0] * dt_s, self._pos[1] + vel_ne_m_s[1] * dt_s)
        self._t_s = t_s
        if trusted:
            if self._run_t_s is None:
                self._run_t_s = t_s
                self._run.clear()
            self._run.append((t_s, *self._pos))
            while len(self._run) > 1 and self._run[1][0] <= t_s - self.back_s:
                self._run.popleft()
            if t_s - self._run_t_s >= self.solid_s:
                # A steady stretch: the loss before it is over, and this is the ground to go back to.
                self._good = (self._run[0][1], self._run[0][2])
                self._lost_t_s, self._way, self._seen_last = None, None, None
            return None
        self._run_t_s = None
        if self._lost_t_s is None:
            # The way is set once per loss and flown straight, past the point too (it is no more
            # than a guess of the ground's edge): towards the point from where the loss began.
            self._lost_t_s, self._way = t_s, None
            if self._good is not None:
                dn, de = self._good[0] - self._pos[0], self._good[1] - self._pos[1]
                dist = math.hypot(dn, de)
                if dist > 1.0:
                    self._way = (dn / dist * self.speed_m_s, de / dist * self.speed_m_s)
        if t_s - self._lost_t_s >= self.max_s:
            return None
        return self._way

    def lost_for_s(self, t_s: float) -> float:
        """Seconds since the loss began (0 while trusted)."""
        return 0.0 if self._lost_t_s is None else max(0.0, t_s - self._lost_t_s)


def body_odom_confidence(var_m2_s2: float) -> float:
    """VISION_POSITION_DELTA's confidence (0-100) for which EKF3's velErr is the camera's standard deviation."""
    sd = math.sqrt(validate.in_range("visual velocity variance", var_m2_s2, 0.0, 1e6))
    frac = (EK3_VIS_VERR_MAX_M_S - sd) / (EK3_VIS_VERR_MAX_M_S - EK3_VIS_VERR_MIN_M_S)
    return float(round(100.0 * min(max(frac, 0.0), 1.0)))


def speed_message_takes(var_m2_s2: float) -> bool:
    """Is the sample good enough for VISION_SPEED_ESTIMATE, which ArduPilot fuses at VISO_VEL_M_NSE?"""
    return var_m2_s2 <= SPEED_MESSAGE_MAX_SD_M_S ** 2


def vision_speed_covariance(var_m2_s2: float) -> list[float]:
    """VISION_SPEED_ESTIMATE's row-major 3x3 covariance: the camera's variance on each NED axis.

    The camera measures the horizontal motion; its vertical rides along through the rotation, so
    the autopilot's vertical velocity source must stay the barometer (EK3_SRCn_VELZ 0)."""
    var = validate.in_range("visual velocity variance", var_m2_s2, 0.0, 1e6)
    return [var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var]


def euler_to_quaternion(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the ZYX rotation NED -> body FRD, MAVLink's SET_ATTITUDE_TARGET convention."""
    cr, sr = math.cos(roll_rad / 2.0), math.sin(roll_rad / 2.0)
    cp, sp = math.cos(pitch_rad / 2.0), math.sin(pitch_rad / 2.0)
    cy, sy = math.cos(yaw_rad / 2.0), math.sin(yaw_rad / 2.0)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def quaternion_to_euler(q: tuple[float, ...]) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of a (w, x, y, z) quaternion (the inverse of `euler_to_quaternion`)."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


@dataclass(frozen=True)
class AttitudeTarget:
    """One SET_ATTITUDE_TARGET: attitude as a quaternion (w, x, y, z) and the thrust field."""

    q: tuple[float, float, float, float]
    thrust: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass(frozen=True)
class AttitudeGains:
    """The velocity loop's numbers. Tilt bounded well inside ArduCopter's ANGLE_MAX (30 deg default)
    and PX4's MPC_MAN_TILT_MAX (35 deg): a camera tilted more sees the horizon, not the ground."""

    vel_p_per_s: float = 1.0  # m/s^2 of acceleration per m/s of velocity error
    vel_i_per_s2: float = 0.2  # integral: wind the autopilot cannot see is a steady error
    accel_max_m_s2: float = 2.5  # ArduCopter's WPNAV_ACCEL 250 cm/s^2
    max_tilt_rad: float = math.radians(15.0)
    climb_limit_up_m_s: float = 2.5  # the thrust field's full scale, ArduCopter WPNAV_SPEED_UP
    climb_limit_down_m_s: float = 1.5  # WPNAV_SPEED_DN
    hover_thrust: float = 0.5  # "thrust" mode: PX4 MPC_THR_HOVER default
    thrust_p_per_m_s: float = 0.1  # "thrust" mode: thrust per m/s of climb-rate error
    thrust_i_per_m: float = 0.05
    thrust_min: float = 0.1
    thrust_max: float = 0.9

    def __post_init__(self) -> None:
        for name in ("vel_p_per_s", "accel_max_m_s2", "climb_limit_up_m_s", "climb_limit_down_m_s",
                     "thrust_p_per_m_s"):
            validate.positive(f"attitude loop {name}", getattr(self, name))
        for name in ("vel_i_per_s2", "thrust_i_per_m"):
            validate.non_negative(f"attitude loop {name}", getattr(self, name))
        validate.in_range("attitude loop max_tilt_rad", self.max_tilt_rad, math.radians(1.0), math.radians(35.0))
        validate.in_range("attitude loop hover_thrust", self.hover_thrust, 0.05, 0.95)
        if not 0.0 <= self.thrust_min < self.hover_thrust < self.thrust_max <= 1.0:
            raise ConfigError("attitude loop thrust: need 0 <= thrust_min < hover_thrust < thrust_max <= 1")


class AttitudeLoop:
    """Body velocity demand + measured velocity -> an attitude target with bounded tilt.

    Horizontal: acceleration = P x error + I x integral (clamped to `accel_max_m_s2`), tilt =
    atan(acceleration / g) (pitch forward is negative pitch in FRD), the tilt vector bounded by
    `max_tilt_rad`; the integrator stops growing while the tilt is saturated. Vertical:
    `climb-rate` (ArduCopter's default) sends the climb-rate demand on the thrust scale and lets
    the autopilot close it on its barometer; `thrust` (PX4, ArduCopter with GUID_OPTIONS 8) closes
    it here around the hover thrust from the measured climb rate. Heading: the yaw held since the
    loop started, moved by the commanded yaw rate. Without a measured velocity it levels the
    vehicle (zero tilt): the caller has already stopped descending then.
    """

    def __init__(self, gains: AttitudeGains | None = None, *, thrust_mode: str = "climb-rate") -> None:
        validate.one_of("thrust_mode", thrust_mode, THRUST_MODES)
        self.gains = gains if gains is not None else AttitudeGains()
        self.thrust_mode = thrust_mode
        self.reset()

    def reset(self) -> None:
        self._i_fwd = self._i_right = self._i_climb = 0.0
        self._yaw_ref_rad: float | None = None

    def step(self, demand_frd_m_s: tuple[float, float, float], yaw_rate_rad_s: float,
             measured_frd_m_s: tuple[float, float, float] | None, climb_m_s: float | None, yaw_rad: float,
             dt_s: float) -> AttitudeTarget:
        g = self.gains
        dt_s = min(max(float(dt_s), 0.0), 0.5)  # a stalled caller must not wind the integrators
        if self._yaw_ref_rad is None:
            self._yaw_ref_rad = float(yaw_rad)
        self._yaw_ref_rad = math.remainder(self._yaw_ref_rad + yaw_rate_rad_s * dt_s, 2.0 * math.pi)
        fwd_d, right_d, down_d = demand_frd_m_s
        if measured_frd_m_s is None:
            acc_fwd = acc_right = 0.0
            self._i_fwd = self._i_right = 0.0
        else:
            e_fwd, e_right = fwd_d - measured_frd_m_s[0], right_d - measured_frd_m_s[1]
            acc_fwd = g.vel_p_per_s * e_fwd + g.vel_i_per_s2 * self._i_fwd
            acc_right = g.vel_p_per_s * e_right + g.vel_i_per_s2 * self._i_right
            acc = math.hypot(acc_fwd, acc_right)
            limit = min(g.accel_max_m_s2, GRAVITY_M_S2 * math.tan(g.max_tilt_rad))
            if acc > limit:
                acc_fwd, acc_right = acc_fwd * limit / acc, acc_right * limit / acc
            else:
                # Anti-windup: integrate only while the demand is inside the bounds.
                self._i_fwd += e_fwd * dt_s
                self._i_right += e_right * dt_s
        pitch = -math.atan(acc_fwd / GRAVITY_M_S2)  # nose down accelerates forward
        roll = math.atan(acc_right / GRAVITY_M_S2)  # right wing down accelerates right
        climb_d = -down_d
        if self.thrust_mode == "climb-rate":
            if climb_d >= 0.0:
                thrust = 0.5 + 0.5 * min(climb_d / g.climb_limit_up_m_s, 1.0)
            else:
                thrust = 0.5 - 0.5 * min(-climb_d / g.climb_limit_down_m_s, 1.0)
        else:
            error = climb_d - (climb_m_s if climb_m_s is not None else 0.0)
            raw = g.hover_thrust + g.thrust_p_per_m_s * error + g.thrust_i_per_m * self._i_climb
            thrust = min(max(raw, g.thrust_min), g.thrust_max)
            if thrust == raw and climb_m_s is not None:
                self._i_climb += error * dt_s
        return AttitudeTarget(euler_to_quaternion(roll, pitch, self._yaw_ref_rad), thrust, roll, pitch,
                              self._yaw_ref_rad)
