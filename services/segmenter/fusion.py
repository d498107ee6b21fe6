"""Fusion of per-prompt CLIPSeg logits into one per-pixel probability that the ground is safe.

CLIPSeg produces one logit map per prompt, shape (P, h, w), positives first (see
``PromptSet.texts``). This module turns that stack into P(safe) in [0, 1], shape (h, w), then
smooths it with a box blur to hide the ViT's 16-pixel patch grid. It knows nothing about torch
or the model: numpy in, numpy out, so it is testable by hand and reusable by other backends.

Two modes:

``dovesei`` (the reference, reproduced exactly): softmax over all P prompts at each pixel, sum
of the positive probabilities, ``cv2.blur`` with a ``blur_px`` x ``blur_px`` box. Its output
depends on how many negative prompts there are: every extra negative takes probability mass
from the positives, so P(safe) drifts towards 0 as the vocabulary of "unsafe" grows, even when
the new prompt says nothing new.

``grouped`` (the default): each group is first reduced to one score, then the two scores are
compared.

    s_pos = logsumexp(l_positive) - log(n_positive)      (log-mean-exp of the positive logits)
    s_neg = logsumexp(l_negative) - log(n_negative)
    P(safe) = sigmoid((s_pos - s_neg) / temperature)

The log-mean-exp is a soft maximum that is normalised by the group size: it lies between the
group's mean and its maximum logit, a group of k prompts that all agree scores the same as one
of them, and repeating the whole group any number of times changes nothing. With n negatives,
one more negative that matches nothing lowers s_neg by log((n+1)/n) at most, and a copy of an
existing negative moves it by less than max(log(2n/(n+1)), log((n+1)/n)) < log 2 either way;
only a prompt that matches better than the group raises s_neg a lot, which is new information.
The reference's softmax, in contrast, is driven towards 0 by mere copies of one negative
prompt. The two-way comparison then gives P(safe) = 0.5 where the best-matching descriptions of
both groups are equally likely, which is a calibration point that a user can
read; ``temperature`` (> 0) sharpens (< 1) or softens (> 1) the transition. The same box blur
follows.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.shared import validate

FUSION_MODES = ("grouped", "dovesei")
DEFAULT_BLUR_PX = 15


class FusionError(ValueError):
    """Bad input to the fusion: shape, prompt split, mode or parameter."""


@dataclass(frozen=True)
class FusionConfig:
    """How to fuse prompt logits: ``mode`` in FUSION_MODES, sigmoid ``temperature`` (grouped
    only) and the box-blur side in pixels of the model output (1 disables the blur)."""

    mode: str = "grouped"
    temperature: float = 1.0
    blur_px: int = DEFAULT_BLUR_PX

    def __post_init__(self) -> None:
        _check_params(self.mode, self.temperature, self.blur_px)


def _check_params(mode: str, temperature: float, blur_px: int) -> None:
    if mode not in FUSION_MODES:
        raise FusionError(f"mode: unknown fusion mode {mode!r}, expected one of {FUSION_MODES}")
    if not (validate.is_number(temperature) and temperature > 0):
        raise FusionError(f"temperature: must be a finite number > 0, got {temperature!r}")
    if isinstance(blur_px, bool) or not isinstance(blur_px, (int, np.integer)) or blur_px < 1:
        raise FusionError(f"blur_px: must be an integer >= 1, got {blur_px!r}")


def _check_logits(logits: np.ndarray, n_positive: int) -> np.ndarray:
    if not isinstance(logits, np.ndarray):
        raise FusionError(f"logits: expected a numpy array, got {type(logits).__name__}")
    if logits.ndim != 3 or min(logits.shape) < 1:
        raise FusionError(f"logits: expected shape (P, h, w) with P, h, w >= 1, got {logits.shape}")
    n_prompts = logits.shape[0]
    if isinstance(n_positive, bool) or not isinstance(n_positive, (int, np.integer)):
        raise FusionError(f"n_positive: expected an integer, got {n_positive!r}")
    # Both groups must be non-empty: with no negative prompt "safe" has nothing to beat.
    if not 1 <= n_positive < n_prompts:
        raise FusionError(f"n_positive: must be in [1, {n_prompts - 1}] for {n_prompts} prompts, got {n_positive}")
    logits_f32 = np.asarray(logits, dtype=np.float32)
    if not np.isfinite(logits_f32).all():
        raise FusionError("logits: contain NaN or infinite values")
    return logits_f32


def _log_mean_exp(group: np.ndarray) -> np.ndarray:
    """log(mean(exp(group), axis=0)), stable for large logits."""
    peak = group.max(axis=0)
    return peak + np.log(np.exp(group - peak).mean(axis=0))


def blur_prob(prob: np.ndarray, blur_px: int = DEFAULT_BLUR_PX) -> np.ndarray:
    """The fusion's box blur alone (for a backend that fuses on a coarser grid and upsamples)."""
    _check_params("grouped", 1.0, blur_px)
    return _blur(np.asarray(prob, dtype=np.float32), blur_px)


def _blur(prob: np.ndarray, blur_px: int) -> np.ndarray:
    if blur_px == 1:
        return prob
    # cv2.blur's default border (reflect-101) is what the reference got.
    return cv2.blur(prob, (int(blur_px), int(blur_px)))


def fuse(
    logits: np.ndarray,
    n_positive: int,
    mode: str = "grouped",
    temperature: float = 1.0,
    blur_px: int = DEFAULT_BLUR_PX,
) -> np.ndarray:
    """Per-pixel P(safe), shape (h, w) float32 in [0, 1], from logits (P, h, w), positives first.

    Raises FusionError (a ValueError) on a bad shape, an impossible ``n_positive``, non-finite
    logits, an unknown mode or a bad parameter.
    """
    _check_params(mode, temperature, blur_px)
    logits_f32 = _check_logits(logits, n_positive)
    if mode == "dovesei":
        # Softmax over the prompt axis, max-shifted for stability (the shift cancels exactly).
        shifted = np.exp(logits_f32 - logits_f32.max(axis=0, keepdims=True))
        prob = shifted[:n_positive].sum(axis=0) / shifted.sum(axis=0)
    else:
        score_pos = _log_mean_exp(logits_f32[:n_positive])
        score_neg = _log_mean_exp(logits_f32[n_positive:])
        margin = (score_pos - score_neg) / np.float32(temperature)
        # 0.5 * (1 + tanh(x / 2)) is the logistic function without exp overflow for large |x|.
        prob = 0.5 * (1.0 + np.tanh(0.5 * margin))
    prob = _blur(prob.astype(np.float32, copy=False), blur_px)
    # Summation and blur rounding can leave values a few ulps outside [0, 1].
    return np.clip(prob, 0.0, 1.0, out=prob)


# A shifted map keeps P off exactly 0 and 1 (logit(0) is -inf); 1e-6 lies below any uint8 step.
SHIFT_EPS = 1e-6


def shift_probability(prob: np.ndarray, a: float, b: float) -> np.ndarray:
    """sigmoid(a * logit(P) + b) per pixel, float32: the same ranking of the ground, another calibration.

    Monotone (strictly increasing in P for a > 0), so a policy that ranks ground by P alone sees
    the same order; one that reads absolute levels sees them moved. P is clipped to
    [SHIFT_EPS, 1 - SHIFT_EPS] first. FusionError for a <= 0 or a non-finite a or b.
    """
    if not (validate.is_number(a) and a > 0 and validate.is_number(b)):
        raise FusionError(f"shift: a must be a finite number > 0 and b finite, got a={a!r}, b={b!r}")
    p = np.clip(np.asarray(prob, dtype=np.float32), np.float32(SHIFT_EPS), np.float32(1.0 - SHIFT_EPS))
    z = np.float32(a) * (np.log(p) - np.log1p(-p)) + np.float32(b)
    return (0.5 * (1.0 + np.tanh(0.5 * z))).astype(np.float32, copy=False)


def fuse_with(logits: np.ndarray, n_positive: int, config: FusionConfig) -> np.ndarray:
    """``fuse`` with the parameters taken from a FusionConfig."""
    return fuse(logits, n_positive, mode=config.mode, temperature=config.temperature, blur_px=config.blur_px)
