"""Fusion of prompt logits into P(safe), and the prompt sets that order those logits.

Pure numpy: no model, no torch in the code under test (torch is used once, to replay the
reference's own softmax).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dovesei.segmenter.fusion import FusionConfig, FusionError, fuse, fuse_with
from dovesei.segmenter.prompts import (
    REFERENCE_NEGATIVE,
    REFERENCE_POSITIVE,
    REFERENCE_PROMPTS,
    REFERENCE_TEMPLATE,
    PromptError,
    PromptSet,
)


def _logits(seed: int, n_prompts: int = 5, height_px: int = 24, width_px: int = 32, spread: float = 4.0):
    return (np.random.default_rng(seed).normal(0.0, spread, size=(n_prompts, height_px, width_px))).astype(np.float32)


def _logit(p: np.ndarray) -> np.ndarray:
    p64 = p.astype(np.float64)
    return np.log(p64) - np.log1p(-p64)


# -- dovesei (the reference) ---------------------------------------------------------------------


def test_dovesei_matches_hand_computation_without_blur():
    logits = _logits(0, n_prompts=4)
    prob = fuse(logits, n_positive=2, mode="dovesei", blur_px=1)
    for row, col in [(0, 0), (5, 7), (23, 31)]:
        exps = [math.exp(float(logits[k, row, col])) for k in range(4)]
        expected = (exps[0] + exps[1]) / sum(exps)
        assert prob[row, col] == pytest.approx(expected, abs=1e-6)


def test_dovesei_blur_is_a_15px_box_mean_in_the_interior():
    logits = _logits(1, n_prompts=3, height_px=40, width_px=40)
    unblurred = fuse(logits, 1, mode="dovesei", blur_px=1)
    blurred = fuse(logits, 1, mode="dovesei")
    row, col = 20, 19
    assert blurred[row, col] == pytest.approx(unblurred[row - 7 : row + 8, col - 7 : col + 8].mean(), abs=1e-6)


def test_dovesei_replays_the_reference_pipeline():
    torch = pytest.importorskip("torch")
    logits = _logits(2, n_prompts=13, height_px=64, width_px=64)
    # The reference: torch softmax over prompts, positives summed, cv2.blur 15x15 (positives were
    # last there; here they are first, and the softmax does not care about the order).
    soft = torch.from_numpy(logits).softmax(dim=0).numpy()
    expected = cv2.blur(soft[:3].sum(axis=0), (15, 15))
    np.testing.assert_allclose(fuse(logits, 3, mode="dovesei"), expected, atol=1e-6)


def test_dovesei_depends_on_duplicated_negatives_grouped_does_not():
    single = _logits(3, n_prompts=2)  # one positive, one negative
    tripled = np.concatenate([single, single[1:], single[1:]])  # the same negative three times
    for mode, should_change in [("dovesei", True), ("grouped", False)]:
        one = fuse(single, 1, mode=mode, blur_px=1)
        three = fuse(tripled, 1, mode=mode, blur_px=1)
        if should_change:
            # softmax: exp(p) / (exp(p) + 3 exp(n)) < exp(p) / (exp(p) + exp(n)) (equal only
            # where float32 saturates at 1).
            assert (three <= one).all() and (three < one).mean() > 0.9
        else:
            np.testing.assert_allclose(three, one, atol=1e-6)


# -- grouped (the default) ------------------------------------------------------------------------


def test_grouped_invariant_to_repeating_the_negative_group():
    logits = _logits(4, n_prompts=6)  # 2 positives, 4 distinct negatives
    repeated = np.concatenate([logits, logits[2:], logits[2:]])
    np.testing.assert_allclose(fuse(repeated, 2), fuse(logits, 2), atol=1e-6)


def test_grouped_one_extra_negative_moves_the_margin_by_a_bounded_amount():
    logits = _logits(5, n_prompts=5, spread=2.0)  # 2 positives, 3 negatives
    margin = _logit(fuse(logits, 2, blur_px=1))
    # A copy of an existing negative: |change| < log(2n / (n + 1)) = log(1.5).
    margin_copy = _logit(fuse(np.concatenate([logits, logits[2:3]]), 2, blur_px=1))
    assert 0 < np.abs(margin_copy - margin).max() <= math.log(1.5) + 1e-4
    # A negative that matches nothing: the margin rises by exactly log((n + 1) / n).
    silent = np.full_like(logits[:1], -1e3)
    margin_silent = _logit(fuse(np.concatenate([logits, silent]), 2, blur_px=1))
    np.testing.assert_allclose(margin_silent - margin, math.log(4 / 3), atol=1e-3)
    # The reference's P(safe) has no such bound: many copies of one negative crush it.
    reference = fuse(logits, 2, mode="dovesei", blur_px=1)
    crushed = fuse(np.concatenate([logits] + [logits[2:3]] * 200), 2, mode="dovesei", blur_px=1)
    assert (crushed <= reference).all() and crushed.mean() < 0.25 * reference.mean()


def test_grouped_formula_and_temperature():
    logits = np.array([[[2.0]], [[0.0]], [[1.0]], [[-1.0]]], dtype=np.float32)  # 2 pos, 2 neg
    s_pos = math.log((math.exp(2.0) + math.exp(0.0)) / 2)
    s_neg = math.log((math.exp(1.0) + math.exp(-1.0)) / 2)
    for temperature in (0.5, 1.0, 3.0):
        expected = 1 / (1 + math.exp(-(s_pos - s_neg) / temperature))
        got = fuse(logits, 2, temperature=temperature, blur_px=1)[0, 0]
        assert got == pytest.approx(expected, abs=1e-6)


def test_grouped_is_one_half_when_groups_tie():
    logits = np.stack([np.full((8, 8), 1.5, np.float32)] * 5)
    np.testing.assert_allclose(fuse(logits, 2), 0.5, atol=1e-6)


@pytest.mark.parametrize("mode", ["grouped", "dovesei"])
def test_monotone_in_positive_logits(mode):
    logits = _logits(6, n_prompts=6)
    base = fuse(logits, 2, mode=mode)
    raised = logits.copy()
    raised[1] += np.abs(_logits(7, n_prompts=1)[0])  # raise one positive map, by varying amounts
    higher = fuse(raised, 2, mode=mode)
    assert (higher >= base - 1e-7).all()
    assert (higher > base).mean() > 0.9
    lowered_negative = logits.copy()
    lowered_negative[4] -= 2.0
    assert (fuse(lowered_negative, 2, mode=mode) >= base - 1e-7).all()


@pytest.mark.parametrize("mode", ["grouped", "dovesei"])
@pytest.mark.parametrize("spread", [1e-3, 5.0, 1e4])
def test_output_in_unit_interval_float32(mode, spread):
    logits = _logits(8, n_prompts=13, spread=spread)
    prob = fuse(logits, 3, mode=mode)
    assert prob.shape == (24, 32) and prob.dtype == np.float32
    assert np.isfinite(prob).all() and prob.min() >= 0.0 and prob.max() <= 1.0


def test_fuse_with_config_equals_keywords():
    logits = _logits(9)
    config = FusionConfig(mode="grouped", temperature=2.0, blur_px=5)
    np.testing.assert_array_equal(fuse_with(logits, 2, config), fuse(logits, 2, temperature=2.0, blur_px=5))


@pytest.mark.parametrize(
    "logits, n_positive, kwargs, field",
    [
        (np.zeros((24, 32), np.float32), 1, {}, "logits"),
        (np.zeros((1, 24, 32), np.float32), 1, {}, "n_positive"),
        (np.zeros((3, 0, 32), np.float32), 1, {}, "logits"),
        (np.zeros((3, 24, 32), np.float32), 0, {}, "n_positive"),
        (np.zeros((3, 24, 32), np.float32), 3, {}, "n_positive"),
        (np.zeros((3, 24, 32), np.float32), 1.0, {}, "n_positive"),
        (np.full((3, 4, 4), np.nan, np.float32), 1, {}, "NaN"),
        ([[[0.0]], [[1.0]]], 1, {}, "logits"),
        (np.zeros((3, 24, 32), np.float32), 1, {"mode": "softmax"}, "mode"),
        (np.zeros((3, 24, 32), np.float32), 1, {"temperature": 0.0}, "temperature"),
        (np.zeros((3, 24, 32), np.float32), 1, {"temperature": float("inf")}, "temperature"),
        (np.zeros((3, 24, 32), np.float32), 1, {"blur_px": 0}, "blur_px"),
        (np.zeros((3, 24, 32), np.float32), 1, {"blur_px": 2.5}, "blur_px"),
    ],
)
def test_bad_input_raises_value_error_naming_the_field(logits, n_positive, kwargs, field):
    with pytest.raises(FusionError, match=field):
        fuse(logits, n_positive, **kwargs)
    assert issubclass(FusionError, ValueError)


def test_bad_fusion_config_is_refused_at_construction():
    with pytest.raises(FusionError, match="mode"):
        FusionConfig(mode="max")


# -- prompt sets ------------------------------------------------------------------------------------


def test_reference_prompts_are_the_references():
    assert REFERENCE_PROMPTS.positive == REFERENCE_POSITIVE and len(REFERENCE_POSITIVE) == 3
    assert REFERENCE_PROMPTS.negative == REFERENCE_NEGATIVE and len(REFERENCE_NEGATIVE) == 10
    assert REFERENCE_TEMPLATE == "aerial view, drone footage photo of {}, shade, shadows, low resolution"
    assert REFERENCE_POSITIVE[0] == "grass, dead grass, backyard, frontyard, courtyard, lawn"
    assert REFERENCE_NEGATIVE[-1] == "stairs, steps, footsteps"
    texts = REFERENCE_PROMPTS.texts()
    assert len(texts) == 13
    assert texts[0] == (
        "aerial view, drone footage photo of grass, dead grass, backyard, frontyard, courtyard, lawn, "
        "shade, shadows, low resolution"
    )
    assert texts[3].startswith("aerial view, drone footage photo of building, house")  # negatives after positives


def test_set_id_is_short_stable_and_content_addressed():
    a = PromptSet(positive=["grass"], negative=["road", "water"], template="photo of {}")
    b = PromptSet(positive=("grass",), negative=("road", "water"), template="photo of {}")
    assert a == b and a.set_id == b.set_id
    assert len(a.set_id) == 12 and int(a.set_id, 16) >= 0
    assert PromptSet(positive=["grass"], negative=["water", "road"], template="photo of {}").set_id != a.set_id
    assert PromptSet(positive=["grass"], negative=["road", "water"], template="{}").set_id != a.set_id
    # Moving a prompt from one group to the other is a different set.
    assert PromptSet(positive=["grass", "road"], negative=["water"], template="photo of {}").set_id != a.set_id
    # Known value: the id must not drift between releases (heatmaps carry it).
    assert REFERENCE_PROMPTS.set_id == PromptSet(
        positive=list(REFERENCE_POSITIVE), negative=list(REFERENCE_NEGATIVE), template=REFERENCE_TEMPLATE
    ).set_id


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"positive": [], "negative": ["road"]}, "positive"),
        ({"positive": ["grass"], "negative": []}, "negative"),
        ({"positive": ["grass", "  "], "negative": ["road"]}, r"positive\[1\]"),
        ({"positive": "grass", "negative": ["road"]}, "positive"),
        ({"positive": ["grass"], "negative": [3]}, r"negative\[0\]"),
        ({"positive": ["grass"], "negative": ["x" * 201]}, r"negative\[0\]"),
        ({"positive": ["grass"] * 33, "negative": ["road"]}, "positive"),
        ({"positive": ["gr{ass}"], "negative": ["road"]}, r"positive\[0\]"),
        ({"positive": ["grass"], "negative": ["road"], "template": "photo of"}, "template"),
        ({"positive": ["grass"], "negative": ["road"], "template": "{} and {}"}, "template"),
        ({"positive": ["grass"], "negative": ["road"], "template": "{0} photo"}, "template"),
        ({"positive": ["grass"], "negative": ["road"], "template": "x" * 301 + "{}"}, "template"),
    ],
)
def test_prompt_set_validation_names_the_field(kwargs, field):
    with pytest.raises(PromptError, match=field):
        PromptSet(**kwargs)
    assert issubclass(PromptError, ValueError)


def test_prompt_set_is_frozen_and_strips_whitespace():
    prompts = PromptSet(positive=[" grass "], negative=["road"], template="{}")
    assert prompts.positive == ("grass",)
    with pytest.raises(AttributeError):
        prompts.template = "photo of {}"  # type: ignore[misc]
