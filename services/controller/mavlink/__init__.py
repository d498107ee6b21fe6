"""The MAVLink vehicle adapter: `vehicle` (`MavlinkVehicle`, the I/O thread that owns the link) and
its pure parts: `proto` (numbers, conversions, checks), `readiness` (arming readiness), `takeoff`
(arm and climb) and `signing` (MAVLink 2 signing)."""
