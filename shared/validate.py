"""Checks on numbers, one copy for every message, config and flag in the project.

Each helper returns the value (as float where it is a number) or raises `ConfigError` naming
`what` and the accepted range, so a caller writes ``self.dt_s = positive("sim dt_s", dt_s)`` or
just calls it for the check. Booleans are refused where a number is expected: ``True`` is an int
to Python but never a deliberate altitude.
"""

from __future__ import annotations

import math
from typing import Any

from dovesei.shared.errors import ConfigError


def is_number(value: Any) -> bool:
    """True for a real int or float (not bool) that is finite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def finite(what: str, value: Any) -> float:
    """`value` as a float; it must be a finite number."""
    if not is_number(value):
        raise ConfigError(f"{what} must be a finite number, got {value!r}")
    return float(value)


def positive(what: str, value: Any) -> float:
    """A finite number > 0."""
    if not (is_number(value) and value > 0):
        raise ConfigError(f"{what} must be a finite number > 0, got {value!r}")
    return float(value)


def non_negative(what: str, value: Any) -> float:
    """A finite number >= 0."""
    if not (is_number(value) and value >= 0):
        raise ConfigError(f"{what} must be a finite number >= 0, got {value!r}")
    return float(value)


def in_range(what: str, value: Any, lo: float, hi: float) -> float:
    """A finite number with lo <= value <= hi."""
    if not (is_number(value) and lo <= value <= hi):
        raise ConfigError(f"{what} must be a finite number in [{lo:g}, {hi:g}], got {value!r}")
    return float(value)


def finite_vector(what: str, values: Any, length: int | None = None) -> tuple[float, ...]:
    """A sequence of finite numbers, of `length` items when given."""
    try:
        items = tuple(values)
    except TypeError:
        raise ConfigError(f"{what} must be a sequence of numbers, got {values!r}") from None
    if length is not None and len(items) != length:
        raise ConfigError(f"{what} must have {length} numbers, got {len(items)}")
    for v in items:
        if not is_number(v):
            raise ConfigError(f"{what} must hold finite numbers only, got {values!r}")
    return tuple(float(v) for v in items)


def one_of(what: str, value: Any, choices: Any) -> Any:
    """`value` if it is one of `choices`, else an error listing them."""
    if value not in choices:
        raise ConfigError(f"{what} {value!r}: choose one of {', '.join(map(str, sorted(choices)))}")
    return value
