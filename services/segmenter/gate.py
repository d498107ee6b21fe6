"""The accuracy gate of the faster CLIPSeg variants: judged on decisions, not on logits.

A variant (bf16, ONNX int8, CUDA fp16) may move every logit a little and still land the drone on
the same spot; or move few logits and flip the spot. So the gate compares what the system decides
from a heatmap with what it decides from the fp32 heatmap of the same frame:

    P(safe) HxW --dynamic threshold (the reference's: 0.85 lowered in steps of 0.0085 until at
                 least 10 % of the pixels pass)--> safe mask
                --L2 distance transform of the mask, first maximum--> target pixel (the point
                  deepest inside the safe area, where the controller's focus would aim)

Per frame: mask IoU against fp32 (pass: >= MIN_MASK_IOU) and the distance between the two target
pixels as a fraction of the frame width (pass: <= MAX_TARGET_SHIFT_FRAC); a variant passes when
its worst frame passes both. The threshold is the controller's `policies.dovesei.policy.dynamic_threshold`
written again here on purpose: a service imports only `dovesei.shared` and itself, and the gate
runs inside the segmenter at start; a test holds the two masks equal. With random weights this checks the numerics only; the same figures
on the real weights say whether a variant is safe to fly (README: run it once on the real model).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

MIN_MASK_IOU = 0.95
MAX_TARGET_SHIFT_FRAC = 0.02
# The reference's dynamic threshold (see docs/REFERENCE.md): start, step, share of pixels wanted.
THRESHOLD_START = 0.85
THRESHOLD_STEP = 0.0085
THRESHOLD_STEPS = 100
MIN_SAFE_FRACTION = 0.10


def dynamic_threshold_mask(prob_safe: np.ndarray) -> np.ndarray:
    """The reference's dynamic-threshold safe mask (bool HxW); all False when no step reaches 10 %."""
    prob = np.asarray(prob_safe, dtype=np.float32)
    for step in range(THRESHOLD_STEPS):
        mask = prob > THRESHOLD_START - THRESHOLD_STEP * step
        if mask.mean() >= MIN_SAFE_FRACTION:
            return mask
    return np.zeros(prob.shape, dtype=bool)


def target_pixel(mask: np.ndarray) -> tuple[int, int] | None:
    """(row, col) deepest inside the safe mask (first maximum of the L2 distance), None if empty."""
    if not mask.any():
        return None
    distance = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)
    row, col = np.unravel_index(int(np.argmax(distance)), distance.shape)
    return int(row), int(col)


@dataclass(frozen=True)
class FrameGate:
    """One frame's decision figures against fp32."""

    mask_iou: float
    target_shift_frac: float  # distance between target pixels / frame width (inf: one has no target)


@dataclass(frozen=True)
class GateResult:
    """A variant's worst figures over the gate's frames and whether it passes."""

    min_mask_iou: float
    max_target_shift_frac: float
    frames: int

    @property
    def passed(self) -> bool:
        return self.min_mask_iou >= MIN_MASK_IOU and self.max_target_shift_frac <= MAX_TARGET_SHIFT_FRAC

    def as_dict(self) -> dict[str, object]:
        return {"min_mask_iou": self.min_mask_iou, "max_target_shift_frac": self.max_target_shift_frac,
                "frames": self.frames, "passed": self.passed,
                "thresholds": {"min_mask_iou": MIN_MASK_IOU, "max_target_shift_frac": MAX_TARGET_SHIFT_FRAC}}

    def describe(self) -> str:
        return (f"{'passed' if self.passed else 'FAILED'} (worst of {self.frames} frames: mask IoU "
                f"{self.min_mask_iou:.3f} >= {MIN_MASK_IOU}, target shift {100 * self.max_target_shift_frac:.2f} % "
                f"<= {100 * MAX_TARGET_SHIFT_FRAC:.0f} % of the width)")


def compare_frame(reference_prob: np.ndarray, candidate_prob: np.ndarray) -> FrameGate:
    if reference_prob.shape != candidate_prob.shape:
        raise ValueError(f"gate: heatmaps differ in shape {reference_prob.shape} vs {candidate_prob.shape}")
    ref_mask, cand_mask = dynamic_threshold_mask(reference_prob), dynamic_threshold_mask(candidate_prob)
    union = np.logical_or(ref_mask, cand_mask).sum()
    # Two empty masks agree perfectly (both refuse the frame).
    iou = 1.0 if union == 0 else float(np.logical_and(ref_mask, cand_mask).sum() / union)
    ref_target, cand_target = target_pixel(ref_mask), target_pixel(cand_mask)
    if ref_target is None and cand_target is None:
        shift = 0.0
    elif ref_target is None or cand_target is None:
        shift = float("inf")
    else:
        shift = float(np.hypot(ref_target[0] - cand_target[0], ref_target[1] - cand_target[1])) / reference_prob.shape[1]
    return FrameGate(mask_iou=iou, target_shift_frac=shift)


def gate(reference_probs: Sequence[np.ndarray], candidate_probs: Sequence[np.ndarray]) -> GateResult:
    """The worst figures over paired heatmaps (same frames, fp32 first)."""
    if len(reference_probs) != len(candidate_probs) or not reference_probs:
        raise ValueError("gate: needs the same non-zero number of reference and candidate heatmaps")
    figures = [compare_frame(r, c) for r, c in zip(reference_probs, candidate_probs)]
    return GateResult(min_mask_iou=min(f.mask_iou for f in figures),
                      max_target_shift_frac=max(f.target_shift_frac for f in figures), frames=len(figures))
