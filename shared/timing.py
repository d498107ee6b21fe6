"""The two timing presets, the one place that defines them for the sim, the policies and the CLI.

REFERENCE.md, "Time in the reference": the reference's simulator ran at ~5 % of real time while its
timers (5 s, 60 s, 300 s, the 1200 s experiment limit) ran on the wall clock and a heatmap arrived
~1.3 times per wall second. Two presets follow:

- ``reference``: what the reference's simulated UAV experienced, counted in decisions. A frame every
  controller tick (0.05 s), one tick old when used, and every frame is one of the reference's
  heatmap cycles (1/1.3 wall s), so one sim second is 20 x 0.77 = 15.4 reference seconds: timers
  and the limit are x 0.065 in sim seconds (the reference's simulator at 6.5 % of real time, within
  its measured 3-8 %). Sim and policy agree on 20 decisions per sim second.
- ``real``: true seconds; perception at what a real CLIPSeg achieves on a ground station (2 Hz,
  0.4 s latency). A real vehicle always runs on this one.

Neither is "the paper's setup": the paper's behaviour depended on its host's speed.
"""

from __future__ import annotations

from dataclasses import dataclass

from dovesei.shared.errors import ConfigError

PAPER_TIME_LIMIT_S = 1200.0  # the paper's experiment limit, in its own (wall) seconds

# The reference's heatmap rate on the wall clock, and the sim's frame period under this preset.
REFERENCE_WALL_HEATMAP_HZ = 1.3
REFERENCE_FRAME_PERIOD_S = 0.05
# One frame = one reference heatmap cycle: sim seconds per reference (wall) second.
REFERENCE_SIM_SPEED = REFERENCE_FRAME_PERIOD_S * REFERENCE_WALL_HEATMAP_HZ


@dataclass(frozen=True)
class Timing:
    """One preset: how often the sim renders a frame, how late perception answers, how the policy's
    timers map onto the data clock."""

    name: str
    frame_period_s: float  # sim seconds between camera frames
    latency_s: float  # modelled perception latency, sim seconds
    timer_scale: float  # data-clock seconds per reference (wall) second
    decision_period_s: float  # nominal data-clock time between heatmaps, as the policy assumes it

    @property
    def time_limit_s(self) -> float:
        """The paper's 1200 s limit on this preset's clock."""
        return PAPER_TIME_LIMIT_S * self.timer_scale


TIMINGS: dict[str, Timing] = {
    "reference": Timing(
        name="reference", frame_period_s=REFERENCE_FRAME_PERIOD_S, latency_s=0.05, timer_scale=REFERENCE_SIM_SPEED,
        # The policy decides on every frame: its period IS the sim's frame period (20 per sim s).
        decision_period_s=REFERENCE_FRAME_PERIOD_S,
    ),
    "real": Timing(name="real", frame_period_s=0.5, latency_s=0.4, timer_scale=1.0, decision_period_s=0.5),
}
TIMING_NAMES = tuple(sorted(TIMINGS))
DEFAULT_TIMING = "reference"  # simulation default (the reproduction); a real vehicle forces "real"


def timing(name: str) -> Timing:
    """The preset called `name`, or a ConfigError naming the choices."""
    try:
        return TIMINGS[name]
    except KeyError:
        raise ConfigError(f"timing {name!r}: choose one of {', '.join(TIMING_NAMES)}") from None
