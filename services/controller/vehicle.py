"""What the controller's loop needs from a vehicle: every member declared, so no caller probes.

Two vehicles implement it: `ZenohVehicle` (the simulator over Zenoh, `service.py`) and
`MavlinkVehicle` (a real autopilot, `mavlink/vehicle.py`). The loop reads states, sends body-frame
velocities, holds, hands over, and at the end reads the vehicle's counters; what differs between
the two is stated by a declared attribute (`wakeup`, `is_link_owner`, `commands_during_handover`),
never by asking whether an attribute exists.
"""

from __future__ import annotations

import threading
from typing import Any, Protocol

from dovesei.controller.gnss_denied import NavStatus
from dovesei.shared.messages import VehicleState, VelocityCommand, VisualOdometry


class Vehicle(Protocol):
    """A vehicle the controller steers."""

    # Set whenever a state arrives (the lockstep loop sleeps on it); None: poll (a real vehicle).
    wakeup: threading.Event | None
    # This process owns the vehicle's link, so it publishes the vehicle's states on the `state` key.
    is_link_owner: bool
    # Commands keep flowing at hand-over (the lockstep sim waits for one per state); False: the
    # vehicle's own hand-over action flies it and it gets no more setpoints.
    commands_during_handover: bool

    @property
    def rejected(self) -> int:
        """State payloads refused at decoding (a MAVLink link counts its bad samples in `counters`)."""
        ...

    def connect(self, timeout_s: float) -> None: ...

    def poll_state(self) -> VehicleState | None:
        """The newest state not yet returned; None when nothing is new."""
        ...

    def send(self, cmd: VelocityCommand) -> None: ...

    def hold(self) -> bool:
        """Stop moving (zero velocity); False when nothing was sent (nothing to take back, no link)."""
        ...

    def handover(self) -> bool:
        """Start the hand-over action; False when the vehicle refused it or did not confirm it."""
        ...

    def set_landing_target(self, angle_x_rad: float, angle_y_rad: float, distance_m: float) -> None:
        """Precision landing: where the spot lies from the camera (a vehicle without it ignores it)."""
        ...

    def nav_status(self) -> NavStatus | None:
        """The estimator's health; None when the vehicle has none to judge (the sim)."""
        ...

    def on_visual_odometry(self, odom: VisualOdometry) -> None: ...

    def counters(self) -> dict[str, Any]:
        """The link's counters for the run's statistics ({} when there is no link)."""
        ...

    def close(self) -> None: ...
