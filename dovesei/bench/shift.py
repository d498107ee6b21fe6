"""The robustness bench's perception shift: one monotone recalibration of every heatmap per episode.

`--perception-shift A_LO,A_HI,B` flies every start twice, plainly and with each heatmap P turned
into P' = sigmoid(a logit(P) + b) (`dovesei.segmenter.fusion.shift_probability`). The transform
keeps the order of the ground (P' grows with P) and moves its absolute levels, as another scene,
light or prompt set would move CLIPSeg's: a policy that ranks ground is untouched, one tuned to
levels is not. Per start, the same for every policy (paired comparison):

    u1, u2 = numpy.random.default_rng([seed, world index, start index, SHIFT_STREAM]).random(2)
    a = A_LO + (A_HI - A_LO) * u1          b = B * (2 * u2 - 1)

    plan_jobs --draw(a, b) per start--> job["perception_shift"] --EpisodeSpec--> SegmenterConfig.prob_shift
              --> every heatmap shifted; the record keeps a, b; summary.md shows both rows side by side
"""

from __future__ import annotations

import math

import numpy as np

from dovesei.shared.errors import ConfigError

SHIFT_STREAM = 25  # the draw's own stream: it never shares numbers with the starts or the perception
A_MAX = 10.0
B_MAX = 10.0
PLAIN_LABEL = "none"
HELP = ("A_LO,A_HI,B: fly every start also with each heatmap P turned into sigmoid(a logit(P) + b), a monotone "
        "recalibration; per start a = A_LO + (A_HI - A_LO) u1, b = B (2 u2 - 1) with (u1, u2) = numpy "
        f"default_rng([seed, world index, start index, {SHIFT_STREAM}]).random(2), the same for every policy; "
        f"0 < A_LO <= A_HI <= {A_MAX:g}, 0 <= B <= {B_MAX:g}; shown beside the plain runs (e.g. 0.6,1.6,0.8)")


def parse_shift(text: object, flag: str = "--perception-shift") -> tuple[float, float, float]:
    """(A_LO, A_HI, B) from "A_LO,A_HI,B" (or a 3-sequence), or one ConfigError naming what is wrong."""
    if isinstance(text, str):
        parts = [p.strip() for p in text.split(",")]
    elif isinstance(text, (list, tuple)):
        parts = list(text)
    else:
        raise ConfigError(f"{flag} {text!r}: expected A_LO,A_HI,B")
    if len(parts) != 3:
        raise ConfigError(f"{flag} {text!r}: expected three numbers A_LO,A_HI,B, got {len(parts)}")
    values = []
    for name, part in zip(("A_LO", "A_HI", "B"), parts):
        try:
            if isinstance(part, bool):
                raise ValueError
            value = float(part)
        except (TypeError, ValueError):
            raise ConfigError(f"{flag} {text!r}: {name} {part!r} is not a number") from None
        if not math.isfinite(value):
            raise ConfigError(f"{flag} {text!r}: {name} must be finite")
        values.append(value)
    a_lo, a_hi, b = values
    if not 0.0 < a_lo <= a_hi <= A_MAX:
        raise ConfigError(f"{flag} {text!r}: need 0 < A_LO <= A_HI <= {A_MAX:g} (a scales logit P; a <= 0 would "
                          "flip or flatten the map)")
    if not 0.0 <= b <= B_MAX:
        raise ConfigError(f"{flag} {text!r}: need 0 <= B <= {B_MAX:g} (b is drawn in [-B, B])")
    return a_lo, a_hi, b


def label(shift: tuple[float, float, float] | None) -> str:
    """The shift's name in records and tables: "none" for the plain runs, else "A_LO,A_HI,B"."""
    return PLAIN_LABEL if shift is None else ",".join(f"{v:g}" for v in shift)


def draw(shift: tuple[float, float, float], seed: int, world_index: int, start_index: int) -> tuple[float, float]:
    """(a, b) of one start (see the module docstring); rounded to 6 places as recorded and applied."""
    a_lo, a_hi, b_max = shift
    u1, u2 = np.random.default_rng([seed, world_index, start_index, SHIFT_STREAM]).random(2)
    return round(a_lo + (a_hi - a_lo) * float(u1), 6), round(b_max * (2.0 * float(u2) - 1.0), 6)


__all__ = ["HELP", "PLAIN_LABEL", "draw", "label", "parse_shift"]
