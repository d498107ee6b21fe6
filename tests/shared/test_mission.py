"""The mission constants' one owner (shared/mission.py) and the footprint's one formula (shared/footprint.py)."""

from __future__ import annotations

import inspect
import math

import numpy as np
import pytest

from dovesei.controller.core import ControllerConfig
from dovesei.controller.policies.clearance.config import ClearanceConfig
from dovesei.controller.policies.dovesei.config import DoveseiConfig
from dovesei.shared import footprint
from dovesei.shared.errors import ConfigError
from dovesei.shared.mission import HANDOVER_ALT_M, MIN_DESCENT_M, SAFETY_RADIUS_M, check_handover_below_start
from dovesei.sim.core import SimConfig
from dovesei.sim.judge import EpisodeJudge


def test_every_config_takes_its_default_from_the_mission() -> None:
    assert ControllerConfig().handover_alt_m == ClearanceConfig().handover_alt_m == SimConfig().handover_alt_m == \
        inspect.signature(EpisodeJudge).parameters["handover_alt_m"].default == HANDOVER_ALT_M == 20.0
    assert ClearanceConfig().safety_radius_m == DoveseiConfig().safety_radius_m == SimConfig().safety_radius_m == \
        inspect.signature(EpisodeJudge).parameters["safety_radius_m"].default == SAFETY_RADIUS_M == 2.0


@pytest.mark.parametrize("handover, start, ok", [(20.0, 100.0, True), (10.0, 25.0, True), (95.0, 100.0, True),
                                                 (96.0, 100.0, False), (100.0, 100.0, False), (120.0, 100.0, False),
                                                 (0.0, 100.0, False), (-5.0, 100.0, False), (math.nan, 100.0, False),
                                                 ("20", 100.0, False)])
def test_the_handover_must_lie_below_the_start(handover: object, start: float, ok: bool) -> None:
    if ok:
        assert check_handover_below_start(handover, start) == handover
        return
    with pytest.raises(ConfigError) as err:
        check_handover_below_start(handover, start)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("--handover-alt-m")
    if isinstance(handover, float) and handover > 0:
        assert f"{MIN_DESCENT_M:g} m below the start altitude {start:g} m" in msg


def test_the_footprint_is_the_pinhole_geometry() -> None:
    hfov = math.radians(90.0)  # tan(45 deg) = 1: the half-width equals the altitude
    assert footprint.half_width_m(30.0, hfov) == pytest.approx(30.0)
    assert footprint.width_m(30.0, hfov) == pytest.approx(60.0)
    assert footprint.metres_per_px(30.0, hfov, 600) == pytest.approx(0.1)
    assert footprint.focal_px(600, hfov) == pytest.approx(300.0)
    # One pixel at the centre seen through the focal length covers what metres_per_px says.
    assert 30.0 / footprint.focal_px(352, math.radians(73.0)) == pytest.approx(
        footprint.metres_per_px(30.0, math.radians(73.0), 352))


def test_the_footprint_gives_the_bits_the_formulas_it_replaced_gave() -> None:
    # Bench records stay unchanged only if every caller gets the same floats as before.
    rng = np.random.default_rng(3)
    for alt, hfov_deg, width in zip(rng.uniform(0.1, 300.0, 500), rng.uniform(5.0, 150.0, 500),
                                    rng.integers(8, 4096, 500)):
        hfov, width = math.radians(hfov_deg), int(width)
        assert footprint.half_width_m(alt, hfov) == math.tan(hfov / 2.0) * alt
        assert footprint.width_m(alt, hfov) == 2.0 * alt * math.tan(hfov / 2.0)
        assert footprint.metres_per_px(alt, hfov, width) == 2.0 * math.tan(hfov / 2.0) * alt / width
        assert footprint.focal_px(width, hfov) == width / (2.0 * math.tan(hfov / 2.0))
        assert footprint.focal_px(width, hfov) == (width / 2.0) / math.tan(hfov / 2.0)
