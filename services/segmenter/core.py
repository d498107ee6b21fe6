"""The segmenter's pure core: CameraFrame in, SafetyHeatmap out, no Zenoh inside.

Both the Zenoh service (`service.py`) and the in-process bench call this one object, so a frame
gives the same heatmap whether the three services run in one process or three.

Data flow for one frame:

    CameraFrame --checks (size limits, truth present for sim)--> FrameRejected(reason) on failure
                --backend: image (clipseg) or truth labels (simulated) + current PromptSet
                --> P(safe) float32 HxW at the frame's size
                --wire dtype (uint8 = P*255 rounded, or float16)--> SafetyHeatmap
                   (seq, stamp, alt_agl_m, hfov_rad copied from the frame; backend, simulated,
                    prompt_set_id, fusion, inference_s filled here)

Backends sit behind `FrameBackend`, a two-method interface (`prepare(prompts)` once per prompt
set, `safe_probability(frame, prompts, fusion)` per frame); the core's config decides the fusion.
`make_backend(config)` is the factory that builds one from a `SegmenterConfig`: `clipseg` loads
the weights (never at import; torch is imported only then, so the onboard install without torch
can still import this module), `sim` builds the simulated perception (a test instrument that
refuses frames without the sim's ground truth), and `auto` tries CLIPSeg and falls back to `sim`
with a WARNING that names the reason.

Wall time never enters here: `frame_to_segmenter_s` and `sent_wall_s` are transport figures that
the service fills in; `inference_s` is a duration measured with `perf_counter`.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.messages import CameraFrame, CropFrame, CropHeatmap, PromptSetMsg, SafetyHeatmap

# `.clipseg` imports torch, which the onboard install does not have: it is imported only when a
# CLIPSeg backend is built, so the simulated backend and the service run without torch.
from .fusion import FUSION_MODES, FusionConfig, fuse, shift_probability
from .options import DEFAULT_MODEL, DTYPES
from .prompts import NEVER_PROMPTS, REFERENCE_PROMPTS, PromptError, PromptSet, crop_prompt_set, never_prompts, never_set_id
from .sim_backend import INPUT_PX
from .simulated import (
    DEFAULT_NOISE, DEFAULT_PROFILE, PROFILE_NAMES, MissingTruthError, SimPerception, crop_view_of, profile_params,
    view_of,
)

log = logging.getLogger(__name__)

BACKENDS = ("auto", "clipseg", "sim")
HEATMAP_DTYPES = ("uint8", "float16")
# The heatmap's `fusion` field for a backend that has no prompt logits to fuse.
SIM_FUSION = "none"

# Reasons a frame is refused; the service counts them under these names.
REJECT_SIZE = "size"
REJECT_NO_TRUTH = "no_truth"
REJECT_BAD_TRUTH = "bad_truth"
REJECT_IMAGE = "image"
REJECT_VEHICLE = "vehicle_mismatch"  # used by the service: key and frame name different vehicles
# The never map is blurred less than the landing map: a person is ~15-20 px of a 352 px crop, and the
# landing map's 15 px box would halve its peak.
NEVER_BLUR_PX = 5
CROP_FLICKER_SEQ0 = 1 << 40


class BackendUnavailableError(DoveseiError, RuntimeError):
    """The configured backend cannot be built (weights missing, torch not installed)."""


class FrameRejected(ValueError):
    """A frame the segmenter will not process; `reason` is a short counter name, the text says why."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"frame rejected ({reason}): {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class SegmenterConfig:
    """Everything that decides how frames become heatmaps (no transport settings here).

    `fusion`: "grouped" (our default, independent of the number of negative prompts) or
    "dovesei" (the reference's softmax over all prompts). Frame sides outside
    [min_side_px, max_side_px], or different from `expected_size_px` (height, width) when it is
    set, are rejected. `sim_profile`/`sim_noise`/`sim_seed` drive the simulated backend only.
    """

    backend: str = "auto"
    model: str = DEFAULT_MODEL  # Hub id or local directory
    device: str = "cpu"
    dtype: str = "float32"
    compile: bool = False
    threads: int | None = None  # torch intra-op threads (None: torch's default)
    fusion: str = "grouped"
    fusion_temperature: float = 1.0
    sim_profile: str = DEFAULT_PROFILE  # clean | realistic | harsh, see dovesei.segmenter.simulated
    sim_noise: float = DEFAULT_NOISE  # error scale within the profile
    sim_seed: int = 0
    heatmap_dtype: str = "uint8"
    min_side_px: int = 16
    max_side_px: int = 4096
    expected_size_px: tuple[int, int] | None = None
    prompts: PromptSet = field(default=REFERENCE_PROMPTS)
    # Scored on crops only (close looks): what must never be inside the landing's separation margin.
    never: tuple[str, ...] = NEVER_PROMPTS
    # (a, b): every heatmap becomes sigmoid(a logit P + b) before it is sent (the bench's
    # --perception-shift: the same ranking, another calibration); None leaves P alone.
    prob_shift: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        _choice("backend", self.backend, BACKENDS)
        _choice("dtype", self.dtype, DTYPES)
        _choice("fusion", self.fusion, FUSION_MODES)
        _choice("heatmap_dtype", self.heatmap_dtype, HEATMAP_DTYPES)
        if not isinstance(self.model, str) or not self.model.strip():
            raise ConfigError(f"SegmenterConfig.model: expected a Hub id or a directory, got {self.model!r}")
        if not isinstance(self.compile, bool):
            raise ConfigError(f"SegmenterConfig.compile: expected a bool, got {self.compile!r}")
        if self.threads is not None and not (_is_int(self.threads) and self.threads >= 1):
            raise ConfigError(f"SegmenterConfig.threads: expected an integer >= 1 or None, got {self.threads!r}")
        if not (_is_number(self.fusion_temperature) and self.fusion_temperature > 0):
            raise ConfigError(f"SegmenterConfig.fusion_temperature: expected a number > 0, got {self.fusion_temperature!r}")
        _choice("sim_profile", self.sim_profile, PROFILE_NAMES)
        if not (_is_number(self.sim_noise) and 0.0 <= self.sim_noise <= 4.0):
            raise ConfigError(f"SegmenterConfig.sim_noise: expected a number in [0, 4], got {self.sim_noise!r}")
        if not (_is_int(self.sim_seed) and self.sim_seed >= 0):
            raise ConfigError(f"SegmenterConfig.sim_seed: expected an integer >= 0, got {self.sim_seed!r}")
        if not (_is_int(self.min_side_px) and _is_int(self.max_side_px) and 1 <= self.min_side_px <= self.max_side_px):
            raise ConfigError(
                f"SegmenterConfig: frame side limits must satisfy 1 <= min_side_px <= max_side_px, "
                f"got {self.min_side_px!r}..{self.max_side_px!r}"
            )
        if self.prob_shift is not None:
            shift = self.prob_shift
            if not (isinstance(shift, tuple) and len(shift) == 2 and all(_is_number(v) for v in shift)
                    and shift[0] > 0):
                raise ConfigError(f"SegmenterConfig.prob_shift: expected (a > 0, b) finite numbers, got {shift!r}")
        if self.expected_size_px is not None:
            size = self.expected_size_px
            if not (isinstance(size, tuple) and len(size) == 2 and all(_is_int(s) and s >= 1 for s in size)):
                raise ConfigError(f"SegmenterConfig.expected_size_px: expected (height_px, width_px), got {size!r}")
            if not all(self.min_side_px <= s <= self.max_side_px for s in size):
                raise ConfigError(
                    f"SegmenterConfig.expected_size_px {size} lies outside the side limits "
                    f"{self.min_side_px}..{self.max_side_px} px"
                )
        if not isinstance(self.prompts, PromptSet):
            raise ConfigError(f"SegmenterConfig.prompts: expected a PromptSet, got {type(self.prompts).__name__}")
        try:
            crop_prompt_set(self.prompts, never_prompts(self.never))
        except PromptError as exc:
            raise ConfigError(f"SegmenterConfig.never: {exc}") from None

    @property
    def fusion_config(self) -> FusionConfig:
        return FusionConfig(mode=self.fusion, temperature=float(self.fusion_temperature))


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _choice(name: str, value: object, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ConfigError(f"SegmenterConfig.{name}: {value!r} is not one of {allowed}")


# --- backends behind one interface ----------------------------------------------------------


class FrameBackend(Protocol):
    """What the core needs from a backend: frame + prompts -> P(safe) at the frame's size."""

    name: str  # goes into SafetyHeatmap.backend
    simulated: bool
    fuses: bool  # True when the output comes from fusing prompt logits (the heatmap names the mode)
    reason: str  # why this backend was chosen (for logs and reports)

    def describe(self) -> str: ...

    def prepare(self, prompts: PromptSet) -> None: ...

    def safe_probability(self, frame: CameraFrame, prompts: PromptSet, fusion: FusionConfig) -> np.ndarray: ...

    def crop_logits(self, crop: CropFrame, prompts: PromptSet) -> tuple[np.ndarray, np.ndarray | None]:
        """(P, n, n) logits of a crop for `prompts` (landing + never) on the backend's square output
        grid, and the share of each cell inside the world (None: all of it)."""
        ...


class ClipSegFrameBackend:
    """CLIPSeg on the frame's RGB image; text embeddings are cached per prompt set by the model."""

    name = "clipseg"
    simulated = False
    fuses = True

    def __init__(self, model: object, reason: str = "configured") -> None:
        from .clipseg import ImageError  # lazy: torch; already loaded here, `model` is a ClipSegBackend

        self._image_error = ImageError
        self.model = model
        self.reason = reason

    def describe(self) -> str:
        return f"clipseg model={self.model.model_id} device={self.model.device} dtype={self.model.dtype}"

    def prepare(self, prompts: PromptSet) -> None:
        # Encoding the texts now, not on the next frame, means a prompt set the text encoder
        # cannot take (too many tokens) is refused while the old one is still in force.
        self.model.text_embeddings(prompts)

    def safe_probability(self, frame: CameraFrame, prompts: PromptSet, fusion: FusionConfig) -> np.ndarray:
        try:
            return self.model.safe_probability(frame.image_rgb, prompts, fusion)
        except self._image_error as exc:
            raise FrameRejected(REJECT_IMAGE, str(exc)) from None

    def crop_logits(self, crop: CropFrame, prompts: PromptSet) -> tuple[np.ndarray, np.ndarray | None]:
        # One vision pass decodes every prompt (landing and never) from the shared activations.
        try:
            return self.model.logits(crop.image_rgb, prompts), None
        except self._image_error as exc:
            raise FrameRejected(REJECT_IMAGE, str(exc)) from None


class SimFrameBackend:
    """Simulated perception: per-prompt logits from the frame's truth labels, then the fusion."""

    name = "simulated"
    simulated = True
    fuses = True  # the same fusion as after CLIPSeg: the heatmap names its mode

    def __init__(self, model: SimPerception, reason: str = "configured") -> None:
        self.model = model
        self.reason = reason

    def describe(self) -> str:
        return f"{self.model.describe()} (test instrument, needs sim ground truth)"

    def prepare(self, prompts: PromptSet) -> None:
        """Build the prompt response table now, so a new prompt set is checked before it is used."""
        self.model.responses(prompts)

    def safe_probability(self, frame: CameraFrame, prompts: PromptSet, fusion: FusionConfig) -> np.ndarray:
        if frame.truth is None:
            # A real camera never carries truth: this is what keeps the sim backend off a vehicle.
            raise FrameRejected(REJECT_NO_TRUTH, f"{MissingTruthError()} (vehicle {frame.vehicle_id}, seq {frame.seq})")
        try:
            return self.model.safe_probability(frame.truth.labels, frame.truth.classes, view_of(frame), frame.seq,
                                               prompts, fusion, out_size=frame.image_rgb.shape[:2])
        except ValueError as exc:
            raise FrameRejected(REJECT_BAD_TRUTH, str(exc)) from None

    def crop_logits(self, crop: CropFrame, prompts: PromptSet) -> tuple[np.ndarray, np.ndarray | None]:
        """The crop's truth labels read as a frame from a camera that saw just the square: at its
        resolution a person spans several tokens and is seen (at 100 m in the whole view, a dip)."""
        if crop.truth is None:
            raise FrameRejected(REJECT_NO_TRUTH, f"{MissingTruthError()} (crop {crop.request_seq} of {crop.vehicle_id})")
        try:
            # Flicker is seeded per look: a crop is keyed apart from the frames' own sequence.
            logits, in_world = self.model.logits(crop.truth.labels, crop.truth.classes, crop_view_of(crop),
                                                 CROP_FLICKER_SEQ0 + crop.request_seq, prompts)
        except ValueError as exc:
            raise FrameRejected(REJECT_BAD_TRUTH, str(exc)) from None
        # Fused on the sim's fusion grid (88 for the profiles), as its frames are: a tenth of the cost of
        # CLIPSeg's 352 output grid, and the logits are smooth below a cell anyway.
        grid = max(self.model.params.fusion_grid_px, logits.shape[-1])
        n = logits.shape[0]
        if grid != logits.shape[-1]:
            logits = cv2.resize(np.ascontiguousarray(logits.transpose(1, 2, 0)), (grid, grid),
                                interpolation=cv2.INTER_LINEAR).reshape(grid, grid, n).transpose(2, 0, 1)
            in_world = cv2.resize(in_world, (grid, grid), interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(logits), in_world


def as_frame_backend(backend: object) -> FrameBackend:
    """Wrap a raw ClipSegBackend / SimPerception; pass a FrameBackend through unchanged."""
    clipseg = sys.modules.get(f"{__package__}.clipseg")  # not imported: cannot be a ClipSegBackend
    if clipseg is not None and isinstance(backend, clipseg.ClipSegBackend):
        return ClipSegFrameBackend(backend)
    if isinstance(backend, SimPerception):
        return SimFrameBackend(backend)
    if all(hasattr(backend, a) for a in ("name", "simulated", "fuses", "prepare", "safe_probability")):
        return backend  # type: ignore[return-value]
    raise TypeError(f"not a segmenter backend: {type(backend).__name__}")


def make_backend(config: SegmenterConfig) -> FrameBackend:
    """Build the configured backend (loads weights for clipseg; may fall back to sim for auto).

    Raises BackendUnavailableError when `clipseg` was asked for explicitly and cannot be loaded,
    ValueError on bad options. `auto` only falls back when the weights or torch are missing; a
    bad option is still an error.
    """
    if config.backend == "sim":
        return _make_sim(config, "configured (--backend sim)")
    try:
        if config.backend == "auto":
            missing = weights_missing(config.model)
            if missing is not None:
                raise BackendUnavailableError(missing)
        return _make_clipseg(config, "configured" if config.backend == "clipseg" else "auto: CLIPSeg weights loaded")
    except BackendUnavailableError as exc:
        if config.backend == "clipseg":
            raise
        why = str(exc)
        log.warning("backend auto: CLIPSeg %r could not be loaded, using SIMULATED perception instead "
                    "(test instrument; real camera frames will be rejected). Reason: %s", config.model, why)
        return _make_sim(config, f"auto: fell back to simulated because CLIPSeg {config.model!r} could not be loaded ({why})")


def weights_missing(model: str, env: Mapping[str, str] = os.environ) -> str | None:
    """Why CLIPSeg weights certainly cannot load here, found without importing torch; None when they may.

    `auto` falls back to the simulated perception when the weights are not on disk. Finding that
    out by trying to load them cost 10-25 s on a loaded 2-core host (torch and transformers
    imported for nothing) and a slow interpreter teardown after; a look at the folder, or at the
    local Hugging Face cache when the Hub may not be asked (HF_HUB_OFFLINE, which `up` sets for
    `auto`), answers in well under a second. Online, or with the files there, the real load decides.
    """
    path = Path(model).expanduser()
    if model.startswith((".", "/", "~")) or path.exists():
        if not path.is_dir():
            return f"CLIPSeg model {model!r}: no such local directory"
        if not (path / "config.json").is_file():
            return f"CLIPSeg model {model!r}: the directory has no config.json"
        return None
    if env.get("HF_HUB_OFFLINE", "").strip().lower() in ("", "0", "false"):
        return None  # the Hub may still have them
    try:
        from huggingface_hub import try_to_load_from_cache  # light: no torch
    except ImportError:
        return None  # no Hub client: the real load will say why
    if isinstance(try_to_load_from_cache(model, "config.json"), str):
        return None
    return (f"CLIPSeg model {model!r} is not in the local Hugging Face cache and HF_HUB_OFFLINE is set "
            f"(download it on a connected machine: hf download {model} --local-dir DIR, then --model DIR)")


def _make_clipseg(config: SegmenterConfig, reason: str) -> ClipSegFrameBackend:
    try:
        from .clipseg import ModelUnavailableError, load_clipseg  # lazy: torch, absent onboard
    except ImportError as exc:
        raise BackendUnavailableError(f"the CLIPSeg backend needs torch and transformers "
                                      f"(pip install 'dovesei[segmenter]'): {exc}") from exc
    try:
        model = load_clipseg(config.model, device=config.device, dtype=config.dtype, compile=config.compile,
                             threads=config.threads)
    except ModelUnavailableError as exc:
        raise BackendUnavailableError(str(exc)) from exc
    return ClipSegFrameBackend(model, reason)


def _make_sim(config: SegmenterConfig, reason: str) -> SimFrameBackend:
    model = SimPerception(profile_params(config.sim_profile, float(config.sim_noise)), seed=int(config.sim_seed))
    return SimFrameBackend(model, reason)


# --- the core -------------------------------------------------------------------------------


def prompt_set_from_msg(msg: PromptSetMsg) -> PromptSet:
    """The wire message as a validated PromptSet (PromptError, a ValueError, names the problem)."""
    return PromptSet(positive=msg.positive, negative=msg.negative, template=msg.template)


def to_wire(prob: np.ndarray, dtype: str) -> np.ndarray:
    """P(safe) float32 in [0, 1] as the heatmap's wire array (uint8 = round(P * 255), or float16)."""
    if dtype == "uint8":
        return (prob * np.float32(255.0) + np.float32(0.5)).astype(np.uint8)
    return prob.astype(np.float16)


def crop_probabilities(logits: np.ndarray, in_world: np.ndarray | None, prompts: PromptSet, n_never: int,
                       fusion: FusionConfig, side_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(P(safe), P(never)) at side_px from the logits of `crop_prompt_set(prompts, never)` on any
    square grid (CLIPSeg's 352, the simulated perception's coarser one): the landing prompts fused
    as every frame's are; the never prompts (the last `n_never`) against the landing positives,
    grouped (the landing negatives hold "people" and "vehicle" themselves). The box blurs are sized
    for CLIPSeg's 352 px grid and scaled to the logits' grid."""
    n_land, grid = prompts.n_prompts, logits.shape[-1]
    scale = grid / INPUT_PX
    blur_safe, blur_never = (max(1, int(round(b * scale))) for b in (fusion.blur_px, NEVER_BLUR_PX))
    prob_safe = fuse(logits[:n_land], prompts.n_positive, fusion.mode, fusion.temperature, blur_safe)
    prob_never = fuse(np.concatenate([logits[n_land:], logits[:prompts.n_positive]]), n_never, "grouped",
                      fusion.temperature, blur_never)
    if in_world is not None:
        prob_safe *= in_world  # unknown ground beyond the map is no landing place
    out = []
    for prob in (prob_safe, prob_never):
        if prob.shape != (side_px, side_px):
            prob = cv2.resize(prob, (side_px, side_px), interpolation=cv2.INTER_LINEAR)
        out.append(np.clip(prob, 0.0, 1.0, out=prob))
    return out[0], out[1]


class SegmenterCore:
    """Frames in, heatmaps out, with the current prompt set and counters of what happened.

    Not thread-safe (neither is CLIPSeg): one loop calls `process` and `set_prompts`.
    """

    def __init__(self, backend: object, config: SegmenterConfig) -> None:
        if not isinstance(config, SegmenterConfig):
            raise TypeError(f"config must be a SegmenterConfig, got {type(config).__name__}")
        self.config = config
        self.backend: FrameBackend = as_frame_backend(backend)
        self.fusion = config.fusion_config
        # What the heatmap's `fusion` field says: the mode, or "none" when nothing was fused.
        self.fusion_name = self.fusion.mode if self.backend.fuses else SIM_FUSION
        self.prompts: PromptSet = config.prompts
        self.backend.prepare(self.prompts)
        self.processed = 0
        self.processed_crops = 0
        self.rejected: Counter[str] = Counter()
        self.prompt_changes = 0

    def check_frame(self, frame: CameraFrame) -> None:
        """Raise FrameRejected when the frame's size is outside the configured limits."""
        height_px, width_px = frame.image_rgb.shape[:2]
        cfg = self.config
        if not (cfg.min_side_px <= min(height_px, width_px) and max(height_px, width_px) <= cfg.max_side_px):
            raise FrameRejected(REJECT_SIZE, f"{width_px}x{height_px} px outside {cfg.min_side_px}..{cfg.max_side_px} px "
                                             f"per side (vehicle {frame.vehicle_id}, seq {frame.seq})")
        if cfg.expected_size_px is not None and (height_px, width_px) != cfg.expected_size_px:
            exp_h, exp_w = cfg.expected_size_px
            raise FrameRejected(REJECT_SIZE, f"{width_px}x{height_px} px, expected {exp_w}x{exp_h} px "
                                             f"(vehicle {frame.vehicle_id}, seq {frame.seq})")

    def process(self, frame: CameraFrame) -> SafetyHeatmap:
        """The heatmap of one frame at the frame's size; FrameRejected (counted) for a bad frame."""
        if not isinstance(frame, CameraFrame):
            raise TypeError(f"process() takes a CameraFrame, got {type(frame).__name__}")
        try:
            self.check_frame(frame)
            t0 = time.perf_counter()
            prob = self.backend.safe_probability(frame, self.prompts, self.fusion)
            if self.config.prob_shift is not None:
                prob = shift_probability(prob, *self.config.prob_shift)
            wire = to_wire(prob, self.config.heatmap_dtype)
            inference_s = time.perf_counter() - t0
        except FrameRejected as exc:
            self.count_rejected(exc.reason)
            raise
        heatmap = SafetyHeatmap(
            vehicle_id=frame.vehicle_id,
            seq=frame.seq,
            stamp=frame.stamp,
            prob_safe=wire,
            alt_agl_m=frame.alt_agl_m,
            hfov_rad=frame.hfov_rad,
            backend=self.backend.name,
            simulated=self.backend.simulated,
            prompt_set_id=self.prompts.set_id,
            fusion=self.fusion_name,
            inference_s=inference_s,
        )
        self.processed += 1
        log.debug("frame %s/%d -> heatmap in %.4f s (%s)", frame.vehicle_id, frame.seq, inference_s, self.backend.name)
        return heatmap

    def process_crop(self, crop: CropFrame) -> CropHeatmap:
        """A close look: P(safe) with the landing prompts and P(never) (the never set against every
        landing prompt, grouped fusion) at the crop's size; FrameRejected (counted) for a bad crop."""
        if not isinstance(crop, CropFrame):
            raise TypeError(f"process_crop() takes a CropFrame, got {type(crop).__name__}")
        never = self.config.never
        try:
            side = crop.image_rgb.shape[0]
            if not self.config.min_side_px <= side <= self.config.max_side_px:
                raise FrameRejected(REJECT_SIZE, f"crop of {side} px outside {self.config.min_side_px}.."
                                                 f"{self.config.max_side_px} px (vehicle {crop.vehicle_id})")
            t0 = time.perf_counter()
            logits, in_world = self.backend.crop_logits(crop, crop_prompt_set(self.prompts, never))
            prob_safe, prob_never = crop_probabilities(logits, in_world, self.prompts, len(never), self.fusion, side)
            wire_safe, wire_never = to_wire(prob_safe, self.config.heatmap_dtype), to_wire(prob_never, self.config.heatmap_dtype)
            inference_s = time.perf_counter() - t0
        except FrameRejected as exc:
            self.count_rejected(exc.reason)
            raise
        self.processed_crops += 1
        return CropHeatmap(crop.vehicle_id, crop.request_seq, crop.frame_seq, crop.stamp, wire_safe, wire_never,
                           crop.centre_frd_m, crop.side_m, crop.alt_agl_m, self.backend.name, self.backend.simulated,
                           self.prompts.set_id, never_set_id(never), inference_s)

    def count_rejected(self, reason: str) -> None:
        """Count a rejection found outside `process` too (the service's decode and key checks)."""
        self.rejected[reason] += 1

    def set_prompts(self, msg: PromptSetMsg | PromptSet) -> bool:
        """Replace the prompt set; True when it changed. The backend rebuilds its text cache once.

        A set the backend cannot take raises PromptError (a ValueError) and the old set stays.
        """
        new = msg if isinstance(msg, PromptSet) else prompt_set_from_msg(msg)
        if new == self.prompts:
            return False
        self.backend.prepare(new)
        old_id, self.prompts = self.prompts.set_id, new
        self.prompt_changes += 1
        log.info("prompt set %s -> %s (%d positive, %d negative, template %r)", old_id, new.set_id,
                 new.n_positive, len(new.negative), new.template)
        return True

    def stats(self) -> Mapping[str, object]:
        """Counters for logs and reports."""
        return {"backend": self.backend.name, "processed": self.processed, "processed_crops": self.processed_crops,
                "rejected": dict(self.rejected),
                "prompt_set_id": self.prompts.set_id, "prompt_changes": self.prompt_changes}


__all__ = [
    "BACKENDS", "BackendUnavailableError", "ClipSegFrameBackend", "FrameBackend", "FrameRejected", "HEATMAP_DTYPES", "PromptError",
    "SegmenterConfig", "SegmenterCore", "SimFrameBackend", "as_frame_backend", "make_backend",
    "prompt_set_from_msg", "to_wire",
]
