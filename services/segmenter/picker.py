"""Pick the CLIPSeg variant by measurement: time what can run here, gate it, keep the fastest.

At start (variant `auto`) the segmenter builds every variant `backends.candidates` says can run
on this host, times each on a few frames (one untimed warm-up, then the median of the timed
ones) and runs the decision gate (`gate.py`) of each against fp32 on the same frames. The
fastest variant that passes wins; fp32 is the reference and always passes, so there is always a
choice. Variants that cannot run here are listed with the reason. A pinned variant (`--variant
onnx-int8`) is built without timing; if it cannot run here that is an error naming why.

The frames are `calibration_frames`: procedural ground-like scenes (smooth patches of colour with
straight edges, like fields, roads and roofs from above) at the model's 352 px, so the start-up
needs no camera; `dovesei bench-segmenter` gates on rendered camera views of the sim worlds.
"""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from .backends import REFERENCE_VARIANT, VariantUnavailable, build_variant, candidates
from .clipseg import ClipSegBackend
from .fusion import FusionConfig
from .gate import GateResult, gate
from .prompts import PromptSet

LOG = logging.getLogger(__name__)

AUTO = "auto"
CALIBRATION_FRAMES = 3
FRAME_PX = 352


def calibration_frames(n: int = CALIBRATION_FRAMES, seed: int = 0, size_px: int = FRAME_PX) -> list[np.ndarray]:
    """`n` deterministic ground-like RGB frames: smooth colour fields cut by straight strips."""
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n):
        small = rng.integers(30, 220, size=(6, 6, 3), dtype=np.uint8)
        image = cv2.resize(small, (size_px, size_px), interpolation=cv2.INTER_CUBIC)
        for _ in range(3):  # roads / walls: straight strips of one colour
            p0 = tuple(int(v) for v in rng.integers(0, size_px, 2))
            p1 = tuple(int(v) for v in rng.integers(0, size_px, 2))
            colour = tuple(int(v) for v in rng.integers(0, 256, 3))
            cv2.line(image, p0, p1, colour, int(rng.integers(4, 24)))
        noise = rng.normal(0.0, 6.0, image.shape)
        frames.append(np.clip(image + noise, 0, 255).astype(np.uint8))
    return frames


@dataclass(frozen=True)
class Candidate:
    """One variant's figures: median seconds per frame and its gate against fp32.

    `cpu_s_per_frame` is the median CPU time of this process per frame (all its threads): on a
    CPU shared with other jobs it grows much less than the wall time, so it says how much work
    a variant is, where the wall time also says how busy the machine was."""

    name: str
    s_per_frame: float
    gate: GateResult
    cpu_s_per_frame: float | None = None

    def as_dict(self) -> dict[str, object]:
        return {"s_per_frame": self.s_per_frame, "hz": 1.0 / self.s_per_frame, "cpu_s_per_frame": self.cpu_s_per_frame,
                "gate": self.gate.as_dict()}


@dataclass(frozen=True)
class Pick:
    """The outcome: the variant chosen, the figures of every variant timed, the refusals."""

    chosen: str
    how: str  # "measured" or "pinned"
    timed: tuple[Candidate, ...] = ()
    refused: dict[str, str] = field(default_factory=dict)

    def describe(self) -> str:
        if self.how == "pinned":
            return f"CLIPSeg variant {self.chosen} (pinned)"
        figures = "; ".join(f"{c.name} {c.s_per_frame:.3f} s/frame, gate {c.gate.describe()}" for c in self.timed)
        refused = "; ".join(f"{k}: {v}" for k, v in self.refused.items()) or "none"
        return f"CLIPSeg variant {self.chosen} picked by measurement ({figures}). Not candidates here: {refused}"

    def as_dict(self) -> dict[str, object]:
        return {"chosen": self.chosen, "how": self.how, "timed": {c.name: c.as_dict() for c in self.timed},
                "refused": dict(self.refused)}


def measure(model: ClipSegBackend, frames: Sequence[np.ndarray], prompts: PromptSet, fusion: FusionConfig,
            repeats: int = 1, cpu_s: list[float] | None = None) -> tuple[float, list[np.ndarray]]:
    """(median s/frame over `repeats` passes of `frames` after one warm-up frame, P(safe) per frame);
    the process CPU seconds of each timed frame are appended to `cpu_s` when given."""
    model.safe_probability(frames[0], prompts, fusion)  # warm-up: text cache, allocator, kernels
    durations_s, probs = [], []
    for repeat in range(repeats):
        for frame in frames:
            start_s, start_cpu_s = time.perf_counter(), time.process_time()
            prob = model.safe_probability(frame, prompts, fusion)
            durations_s.append(time.perf_counter() - start_s)
            if cpu_s is not None:
                cpu_s.append(time.process_time() - start_cpu_s)
            if repeat == 0:
                probs.append(prob)
    return statistics.median(durations_s), probs


def choose(base: ClipSegBackend, variant: str, prompts: PromptSet, fusion: FusionConfig, *,
           threads: int | None = None, frames: Sequence[np.ndarray] | None = None,
           repeats: int = 1, export: bool = False) -> tuple[ClipSegBackend, Pick]:
    """The model to serve with and how it was chosen. `variant` is `auto` or one of VARIANTS;
    `export` lets `auto` export onnx-int8 when its export is not cached yet (see `candidates`)."""
    if variant != AUTO:
        return build_variant(variant, base, threads=threads), Pick(chosen=variant, how="pinned")
    frames = list(frames) if frames is not None else calibration_frames()
    runnable, refused = candidates(base, export=export)
    models: dict[str, ClipSegBackend] = {}
    timed: list[Candidate] = []
    reference_probs: list[np.ndarray] = []
    for name in [REFERENCE_VARIANT, *(n for n in runnable if n != REFERENCE_VARIANT)]:
        try:
            model = build_variant(name, base, threads=threads)
        except (VariantUnavailable, RuntimeError, OSError, ValueError) as exc:
            # A variant that fails to build (export error, driver) is reported, never fatal: fp32 remains.
            refused[name] = f"could not be built: {exc}"
            LOG.warning("CLIPSeg variant %s could not be built, not a candidate: %s", name, exc)
            continue
        cpu_s: list[float] = []
        s_per_frame, probs = measure(model, frames, prompts, fusion, repeats, cpu_s)
        if name == REFERENCE_VARIANT:
            reference_probs = probs
        result = gate(reference_probs, probs)
        timed.append(Candidate(name, s_per_frame, result, statistics.median(cpu_s)))
        models[name] = model
        LOG.info("CLIPSeg variant %s: %.3f s/frame (%.2f Hz, %.3f CPU s), gate %s", name, s_per_frame,
                 1.0 / s_per_frame, timed[-1].cpu_s_per_frame, result.describe())
    passing = [c for c in timed if c.gate.passed]
    best = min(passing, key=lambda c: c.s_per_frame)
    pick = Pick(chosen=best.name, how="measured", timed=tuple(timed), refused=refused)
    LOG.info("%s", pick.describe())
    return models[best.name], pick
