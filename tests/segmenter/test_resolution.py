"""The simulated perception honours resolution: a person or car answers by how many tokens it covers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dovesei.segmenter.prompts import REFERENCE_PROMPTS
from dovesei.segmenter.sim_backend import OBJECT_GAIN_MAX, TOKEN_PX, object_gain
from dovesei.segmenter.simulated import SimPerception, View, profile_params

NAMES = {8: "grass", 13: "person", 7: "car"}
VIEW = View((500.0, 500.0), 100.0, np.radians(73.0))


def test_the_curve_rises_with_the_tokens_covered_from_area_alone_to_its_ceiling() -> None:
    n = np.geomspace(1e-3, 50.0, 200)
    g = object_gain(n)
    assert np.all(np.diff(g) > 0)
    assert g[0] == pytest.approx(1.0, abs=1e-5) and g[-1] == pytest.approx(OBJECT_GAIN_MAX, abs=0.01)
    assert object_gain(1.0) == pytest.approx(1.0 + (OBJECT_GAIN_MAX - 1.0) / 2)


def _darkest_p(perception: SimPerception, area_px: int, cls: int = 13) -> tuple[float, float]:
    """P(safe) at the darkest point near an object of about area_px at the view's centre, and on bare lawn."""
    lab = np.full((352, 352), 8, np.uint8)
    side = max(1, int(round(np.sqrt(area_px))))
    lab[176 - side // 2: 176 - side // 2 + side, 176 - side // 2: 176 - side // 2 + side] = cls
    p = perception.safe_probability(lab, NAMES, VIEW, 0, REFERENCE_PROMPTS)
    lawn = perception.safe_probability(np.full((352, 352), 8, np.uint8), NAMES, VIEW, 0, REFERENCE_PROMPTS)
    return float(p[150:202, 150:202].min()), float(lawn[176, 176])


@pytest.mark.parametrize("cls", [13, 7])
def test_an_object_under_one_token_is_a_small_dip_and_across_several_is_clearly_seen(cls: int) -> None:
    perception = SimPerception(profile_params("realistic", noise=0.0), seed=0)  # the curve, not the noise
    areas = [1, 4, 16, 64, 144, 256, 576, 1024, 2304]  # 0.004 .. 9 tokens
    dips = []
    for area in areas:
        darkest, lawn = _darkest_p(perception, area, cls)
        dips.append(lawn - darkest)
    assert all(b >= a - 1e-6 for a, b in zip(dips, dips[1:])), dips  # monotone in the tokens covered
    assert dips[0] < 0.01 and dips[2] < 0.03  # a person at 100 m (1 px), at 40 m (~16 px): a dip in the ripple
    assert dips[-1] > 0.6 and dips[-2] > 0.5  # four tokens and more: clearly not lawn
    # More than in proportion to its area once it fills a token: four times the pixels, over four times the dip.
    assert dips[5] > 4.0 * dips[3]


def test_the_gain_is_per_object_not_per_class() -> None:
    """Sixteen one-pixel people spread over a token answer as sixteen dips, not as one 16-px object."""
    perception = SimPerception(profile_params("realistic", noise=0.0), seed=0)
    crowd = np.full((352, 352), 8, np.uint8)
    crowd[168:184:4, 168:184:4] = 13  # 16 separate pixels (8-connectivity never joins them)
    block = np.full((352, 352), 8, np.uint8)
    block[174:178, 174:178] = 13  # the same 16 pixels in one piece
    p_crowd = perception.safe_probability(crowd, NAMES, VIEW, 0, REFERENCE_PROMPTS)[160:192, 160:192].min()
    p_block = perception.safe_probability(block, NAMES, VIEW, 0, REFERENCE_PROMPTS)[160:192, 160:192].min()
    assert p_block <= p_crowd + 1e-6
    assert TOKEN_PX == 16
