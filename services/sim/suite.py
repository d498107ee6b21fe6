"""The world suite: the worlds a benchmark flies when asked for `--suite default`.

`DEFAULT_SUITE` holds world specs as `load_world` takes them: the CC0 Dubai tile shipped with the
package and one synthetic world of each style (`synthetic.styles`; `crowded`, the plazas and parks with
crowds, last), each 1.6 km square at 0.25 m/px and seeded so the suite is the same on every machine. The synthetic worlds are generated once and
then read from the disk cache (`synthetic.load_or_generate`).
"""

from __future__ import annotations

from dovesei.shared.errors import ConfigError

DEFAULT_SUITE: tuple[str, ...] = (
    "dubai",
    "synthetic:style=downtown,seed=1",
    "synthetic:style=villas,seed=2",
    "synthetic:style=desert,seed=3",
    "synthetic:style=coast,seed=4",
    "synthetic:style=parkland,seed=5",
    "synthetic:style=crowded,seed=6",
)
SUITES: dict[str, tuple[str, ...]] = {"default": DEFAULT_SUITE}


def suite(name: str) -> tuple[str, ...]:
    """The world specs of the suite called `name`, or a ConfigError naming the suites."""
    try:
        return SUITES[name]
    except KeyError:
        raise ConfigError(f"suite {name!r}: choose one of {', '.join(sorted(SUITES))}") from None
