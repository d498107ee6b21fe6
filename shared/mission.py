"""The mission's constants, the one place that defines their defaults for every service and tool.

DESIGN.md, section 1: a policy brings the vehicle down to the hand-over altitude (20 m), where a
short-range stereo or depth method takes over; success is reaching it over ground whose landing
disk (the paper's 2 m radius) is safe. These defaults are written here once; every consumer
receives the value from its parent object (the controller's config hands it to the core, the core
to the policy; the sim's config to its judge; `up` and `bench` to both), so a flag set once is the
value every part of a flight uses.
"""

from __future__ import annotations

from dovesei.shared.errors import ConfigError
from dovesei.shared.validate import is_number

# DESIGN.md: "descends to a hand-over altitude (20 m), where a short-range stereo/depth method would
# take over". A sensor with a shorter or longer range hands over lower or higher (`--handover-alt-m`).
HANDOVER_ALT_M = 20.0
# The paper's landing disk: success means every class under this radius around the touchdown is safe.
SAFETY_RADIUS_M = 2.0
# Separation from what a lander must never come down near (DESIGN.md 1; SORA-style ground risk):
# no person within 3 m and no vehicle within 5 m of the touchdown point. The close look checks
# them before committing; the judge counts them.
PERSON_SEPARATION_M = 3.0
VEHICLE_SEPARATION_M = 5.0
# A start must leave at least this much descent above the hand-over altitude, or there is nothing
# to judge (the smallest start `bench` and `up` accept at the default hand-over is 25 m).
MIN_DESCENT_M = 5.0


def check_handover_below_start(handover_alt_m: float, start_alt_m: float, what: str = "--handover-alt-m") -> float:
    """The hand-over altitude when it lies at least MIN_DESCENT_M below the start, else a one-line
    ConfigError naming both (an episode starting at or below its hand-over has nothing to fly)."""
    if not (is_number(handover_alt_m) and handover_alt_m > 0):
        raise ConfigError(f"{what} must be a positive number of metres, got {handover_alt_m!r}")
    if not handover_alt_m <= start_alt_m - MIN_DESCENT_M:
        raise ConfigError(f"{what} {handover_alt_m:g} m must be at least {MIN_DESCENT_M:g} m below the start "
                          f"altitude {start_alt_m:g} m")
    return float(handover_alt_m)
