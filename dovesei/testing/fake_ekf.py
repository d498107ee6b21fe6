"""The fake autopilot's estimator when GNSS goes away: ArduPilot's EKF3 and Copter's EKF checks, as MAVLink shows them.

`FakeAutopilot` owns one `FakeEkf` and asks it, every physics step and every stream message:

    lose_gnss() / restore_gnss()       the test cuts GNSS (what SITL's SIM_GPS_DISABLE 1 does)
    on_vision_speed(VISION_SPEED_ESTIMATE)  a velocity for the EKF, fused only while the active
                                       source set is the one configured with VELXY = ExternalNav
                                       (EK3_SRCn_VELXY 6) and visual odometry is enabled (VISO_TYPE)
    on_vision_delta(VISION_POSITION_DELTA)  body odometry, fused under the same conditions
    set_source_set(n)                  MAV_CMD_SET_EKF_SOURCE_SET
    position_ok(now), flags(now), fix_type(), failsafe_due(now)
    visodom_prearm_failure(now)        ArduPilot's VisOdom pre-arm check (with `viso_arming_check`)

The timeline of a loss without another velocity source, as ArduCopter 4.6 SITL flew it
(issue 23): GPS_RAW_INT drops its fix at once; the EKF coasts on inertia for `coast_s` (SITL:
about 8 s before "EKF variance") with its flags unchanged, then loses horizontal velocity and
position (constant-position mode; LOCAL_POSITION_NED stops); after `failsafe_s` more (Copter's
ekf_check: 10 iterations at 10 Hz) the EKF failsafe fires (FS_EKF_ACTION). With the
external-nav velocity fused the EKF keeps its horizontal velocity, but what else depends on the
message (NavEKF3_core, see gnss_denied.EXTERNAL_NAV_MESSAGES): body odometry
(VISION_POSITION_DELTA) keeps a relative position for good (doingBodyVelNav); an ExternalNav
velocity alone (VISION_SPEED_ESTIMATE) keeps the old position valid only until
posRetryTimeUseVel (10 s after the loss), then the horizontal position flags drop (no
constant-position mode: the velocity is still aided) and the failsafe follows. When the body
odometry stops after the loss (the camera's stream ends: a controller stopped after its hand-over)
the EKF coasts `coast_s` from the last one it fused, then the same failsafe follows (ArduCopter
4.6.3 SITL: "EKF variance" about 5 s after `dovesei up` ended and its odometry with it).

Arming (`viso_arming_check`, ARMING_CHECK's VISION bit with VISO_TYPE set): AP_VisualOdom counts
as healthy only while a vision message (VISION_SPEED_ESTIMATE, VISION_POSITION_DELTA, ...) came
within AP_VISUALODOM_TIMEOUT_MS (300 ms; AP_VisualOdom_Backend::healthy), and AP_Arming's
visodom_checks refuses arming otherwise with "VisOdom: not healthy" ("PreArm: ..." in the periodic
pre-arm report, "Arm: ..." when an ARM is refused).
"""

from __future__ import annotations

from dovesei.controller.mavlink import proto as mv

VISION_FRESH_S = 0.5  # a vision velocity older than this is not being fused
VISODOM_HEALTHY_S = 0.3  # AP_VISUALODOM_TIMEOUT_MS: the VisOdom pre-arm check's freshness
VISODOM_PREARM_TEXT = "VisOdom: not healthy"  # AP_Arming::visodom_checks, AP_VisualOdom::pre_arm_check
POS_RETRY_USE_VEL_S = 10.0  # EKF3's posRetryTimeUseVel_ms: position kept on a velocity alone this long
GOOD_FLAGS = (mv.EKF_ATTITUDE | mv.EKF_VELOCITY_HORIZ | mv.EKF_VELOCITY_VERT | mv.EKF_POS_HORIZ_REL
              | mv.EKF_POS_HORIZ_ABS | mv.EKF_POS_VERT_ABS | mv.EKF_PRED_POS_HORIZ_REL)
EXTNAV_FLAGS = GOOD_FLAGS & ~mv.EKF_POS_HORIZ_ABS  # dead reckoning on the external velocity
LOST_FLAGS = mv.EKF_ATTITUDE | mv.EKF_VELOCITY_VERT | mv.EKF_POS_VERT_ABS | mv.EKF_CONST_POS_MODE
VELOCITY_ONLY_FLAGS = mv.EKF_ATTITUDE | mv.EKF_VELOCITY_HORIZ | mv.EKF_VELOCITY_VERT | mv.EKF_POS_VERT_ABS
FS_EKF_ACTIONS = {1: "LAND", 2: "ALT_HOLD", 3: "LAND"}  # 3: LAND even from modes without GPS


class FakeEkf:
    """GNSS, source sets and the fused external velocity; times on the fake's clock (seconds)."""

    def __init__(self, *, extnav_source_set: int | None = 2, viso_enabled: bool = True, coast_s: float = 3.0,
                 failsafe_s: float = 1.0, fs_ekf_action: int = 1,
                 pos_retry_use_vel_s: float = POS_RETRY_USE_VEL_S, viso_arming_check: bool = False) -> None:
        if fs_ekf_action not in FS_EKF_ACTIONS:
            raise ValueError(f"fs_ekf_action {fs_ekf_action!r}: choose one of {sorted(FS_EKF_ACTIONS)}")
        self.extnav_source_set, self.viso_enabled = extnav_source_set, viso_enabled
        self.coast_s, self.failsafe_s, self.fs_ekf_action = float(coast_s), float(failsafe_s), fs_ekf_action
        self.pos_retry_use_vel_s = float(pos_retry_use_vel_s)
        # ARMING_CHECK's VISION bit (AP_Arming::visodom_checks) with VISO_TYPE set. Off by default: the
        # fake's `viso_enabled` stands for the fusion most tests exercise, not for how they arm.
        self.viso_arming_check = bool(viso_arming_check)
        self.source_set = 1  # EK3_SRC1_*: GPS, what a vehicle boots with
        self.gnss_lost_at_s: float | None = None
        self.vision_at_s: float | None = None  # newest VISION_SPEED_ESTIMATE
        self.vision_ned_m_s: tuple[float, float, float] | None = None
        self.delta_at_s: float | None = None  # newest VISION_POSITION_DELTA
        self.position_lost_at_s: float | None = None  # when position_ok() last turned false
        self.failsafe_active = False

    def lose_gnss(self, now: float) -> None:
        if self.gnss_lost_at_s is None:
            self.gnss_lost_at_s = now

    def restore_gnss(self) -> None:
        self.gnss_lost_at_s = None

    @property
    def gnss_ok(self) -> bool:
        return self.gnss_lost_at_s is None

    def fix_type(self) -> int:
        return 3 if self.gnss_ok else 1  # GPS_FIX_TYPE_3D_FIX / GPS_FIX_TYPE_NO_FIX

    def set_source_set(self, source_set: int) -> int:
        """MAV_CMD_SET_EKF_SOURCE_SET: param1 1..3 (AP_NavEKF_Source), else MAV_RESULT_DENIED."""
        if source_set not in (1, 2, 3):
            return 2  # MAV_RESULT_DENIED
        self.source_set = source_set
        return mv.MAV_RESULT_ACCEPTED

    def on_vision_speed(self, now: float, vel_ned_m_s: tuple[float, float, float]) -> None:
        self.vision_at_s, self.vision_ned_m_s = now, vel_ned_m_s

    def on_vision_delta(self, now: float) -> None:
        self.delta_at_s = now

    def _extnav_selected(self) -> bool:
        """VISO enabled and the active source set is the one whose VELXY is ExternalNav."""
        return self.viso_enabled and self.extnav_source_set is not None and self.source_set == self.extnav_source_set

    def _extnav_reaches_filter(self, at_s: float | None, now: float) -> bool:
        """Right source set, VISO enabled, fresh data."""
        return self._extnav_selected() and at_s is not None and now - at_s <= VISION_FRESH_S

    def visodom_prearm_failure(self, now: float) -> str | None:
        """AP_VisualOdom's pre-arm failure (without "PreArm: "), or None when arming may go ahead."""
        if not (self.viso_enabled and self.viso_arming_check):
            return None
        newest = max((t for t in (self.vision_at_s, self.delta_at_s) if t is not None), default=None)
        return None if newest is not None and now - newest < VISODOM_HEALTHY_S else VISODOM_PREARM_TEXT

    def fusing_extnav(self, now: float) -> bool:
        """Body odometry fused: a relative position for as long as it comes."""
        return self._extnav_reaches_filter(self.delta_at_s, now)

    def fusing_velocity(self, now: float) -> bool:
        """An ExternalNav velocity fused (velocity aiding, no position)."""
        return self._extnav_reaches_filter(self.vision_at_s, now)

    def position_ok(self, now: float) -> bool:
        if self.gnss_ok or self.fusing_extnav(now):
            return True
        assert self.gnss_lost_at_s is not None
        since_s = now - self.gnss_lost_at_s
        if self.fusing_velocity(now):
            return since_s < self.pos_retry_use_vel_s  # the position times out even with a velocity
        # Inertia, until the variances grow: from the loss, or from the last body odometry fused after it.
        aided_until_s = self.gnss_lost_at_s
        if self._extnav_selected() and self.delta_at_s is not None:
            aided_until_s = max(aided_until_s, self.delta_at_s)
        return now - aided_until_s < self.coast_s

    def flags(self, now: float) -> int:
        if self.gnss_ok:
            return GOOD_FLAGS
        if self.fusing_extnav(now):
            return EXTNAV_FLAGS
        if self.position_ok(now):
            return GOOD_FLAGS
        return VELOCITY_ONLY_FLAGS if self.fusing_velocity(now) else LOST_FLAGS

    def failsafe_due(self, now: float) -> bool:
        """True once, when the position has been lost for `failsafe_s` (Copter's ekf_check)."""
        if self.position_ok(now):
            self.position_lost_at_s = None
            self.failsafe_active = False  # failsafe_ekf_off_event once the variances recover
            return False
        if self.position_lost_at_s is None:
            self.position_lost_at_s = now
        if not self.failsafe_active and now - self.position_lost_at_s >= self.failsafe_s:
            self.failsafe_active = True
            return True
        return False
