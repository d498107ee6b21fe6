"""The simulator as the onboard camera's visual odometry: the same estimator on rendered views.

    true pose (render) + reported state (altitude, attitude: what the camera is tagged with)
      -> a view at the camera model's size, bilinear (a real sensor integrates its pixel's area;
         nearest lookups would snap every pixel to the world's grid)
      -> dovesei.shared.visual_velocity against the previous view -> VisualOdometry

So a sim flight (`SimCore` with `odometry_rate_hz`) and a SITL flight in external-pose mode carry
the odometry stream a real vehicle's camera service publishes, computed the same way. The view is
rendered where the vehicle truly is; the estimator only ever sees the pixels and the reported
altitude and attitude, never the truth. Views are separate from the `CameraFrame`s (which come at
the perception rate, 2 Hz in the `real` timing) and numbered on their own.
"""

from __future__ import annotations

import logging

from dovesei.shared.clock import wall_time_s
from dovesei.shared.messages import Stamp, VehicleState, VisualOdometry
from dovesei.shared.visual_velocity import FrameMeta, VisualVelocity, odometry_message
from dovesei.sim.camera import CameraError, CameraModel, render
from dovesei.sim.world import World

log = logging.getLogger(__name__)

_EPS_S = 1e-9


class SimOdometry:
    """Visual odometry from rendered views, due every 1 / rate_hz seconds of the caller's clock."""

    def __init__(self, world: World, camera: CameraModel, vehicle_id: str, rate_hz: float) -> None:
        if not rate_hz > 0.0:
            raise ValueError(f"odometry rate must be > 0 Hz, got {rate_hz!r}")
        self.world, self.camera, self.vehicle_id = world, camera, vehicle_id
        self.period_s = 1.0 / rate_hz
        self._estimator = VisualVelocity()
        self._seq = -1
        self._next_s: float | None = None
        self.skipped = 0  # views that could not be rendered (an attitude at the horizon)

    def due(self, t_s: float) -> bool:
        return self._next_s is None or t_s >= self._next_s - _EPS_S

    def observe(self, x_m: float, y_m: float, alt_m: float, yaw_rad: float, state: VehicleState, *,
                roll_rad: float = 0.0, pitch_rad: float = 0.0, t_s: float | None = None,
                tag_roll_pitch_rad: tuple[float, float] | None = None) -> VisualOdometry | None:
        """The odometry of a view rendered at the true pose (x, y, alt, yaw, roll, pitch) when one is due.

        `state` is what the camera is tagged with (the autopilot's report: altitude, heading and,
        unless `tag_roll_pitch_rad` says otherwise, roll and pitch; a gimballed camera is tagged
        level whatever the body does); its stamp dates the view unless `t_s` (same clock) is given.
        None when nothing is due, for the first view, and when the view cannot be rendered (then
        the next one starts afresh).
        """
        t_s = state.stamp.t_s if t_s is None else t_s
        if not self.due(t_s):
            return None
        # An absolute schedule, restarted after a gap, so the rate never drifts with the step size.
        self._next_s = t_s + self.period_s if self._next_s is None or t_s - self._next_s > self.period_s \
            else self._next_s + self.period_s
        try:
            image, _labels, _valid = render(self.world, x_m, y_m, max(alt_m, 0.1), yaw_rad, self.camera,
                                            roll_rad=roll_rad, pitch_rad=pitch_rad, with_labels=False,
                                            interpolation="linear", t_s=t_s, ground_detail=True)
        except CameraError as exc:
            self.skipped += 1
            self._estimator.reset()
            log.debug("odometry view skipped: %s", exc)
            return None
        self._seq += 1
        tag_roll, tag_pitch = (state.roll_rad, state.pitch_rad) if tag_roll_pitch_rad is None else tag_roll_pitch_rad
        meta = FrameMeta(self._seq, t_s, state.alt_agl_m, self.camera.hfov_rad, tag_roll, tag_pitch, state.yaw_rad)
        est = self._estimator.update(image, meta)
        if est is None:
            return None
        return odometry_message(est, meta, vehicle_id=self.vehicle_id, stamp=Stamp(t_s, state.stamp.clock),
                                sent_wall_s=wall_time_s())
