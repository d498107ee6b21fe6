"""Simulated perception: a CLIPSeg-like safe-probability map made from the sim's ground truth.

This backend is a TEST INSTRUMENT for the controller, never a perception system. The simulator
renders the world's label image through the camera (HxW uint8 class ids, 255 = outside the
world) and attaches it to each frame with the world's class table; this module turns those labels
into a per-pixel P(safe) (HxW float32 in [0, 1]) that is wrong the way CLIPSeg is wrong on aerial
images, so policies can be compared under realistic, repeatable perception errors. Frames without
truth labels (a real camera) are refused with `MissingTruthError`.

Data flow for one frame (every step is a knob of `SimPerceptionParams`, scaled by ``noise``):

    labels --class table--> perception group per id (keyword match on class NAMES, cached)
           --per-frame draws (seed, frame_seq)--> FrameEffects: group values jittered and pulled
             towards their confusion partners, gain/offset, optional flip blob
           --256-entry LUT--> P per pixel
           --area-downsample + Gaussian blur (ViT patch scale)--> work grid
           + slow correlated field (changes over a few frames) + fresh flicker field (every frame)
           --gain/offset around 0.5--> --invert inside the flip blob--> --bilinear upsample-->
           --clip to [0, 1]--> float32 HxW

With ``noise == 0`` the output is the clean label map: 1.0 on safe classes, 0.0 on unsafe ones,
``outside_prob`` outside the world; nothing random is applied. With ``noise == 1`` each group
reads at CLIPSeg's typical affinity (``affinity``) and the random effects have their nominal
strengths; above 1 the random effects grow further while the affinities stay at CLIPSeg's
(extrapolating them would rank flat roofs above grass, which no real segmenter does on average).

The reference's 15x15 box blur is NOT applied here: it belongs to the fusion of CLIPSeg prompt
logits (`fusion.py`). This backend models the model's own output, whose patch-scale smoothing is
the Gaussian blur above.

Determinism: the output depends only on (labels, classes, params, seed, frame_seq). Each random
stream is a fresh ``np.random.default_rng([seed, stream, index])``; nothing carries over between
calls, so frames can be rendered in any order, in any process, with identical bytes.
"""

from __future__ import annotations

import argparse
import logging
import math
import re
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from dovesei.shared.errors import ConfigError, DoveseiError

log = logging.getLogger(__name__)

OUTSIDE_ID = 255
# The input side of CLIPSeg: a 352x352 image cut into 16-pixel ViT patches, 22 across.
CLIPSEG_INPUT_PX = 352
CLIPSEG_PATCH_PX = 16

# Perception groups, in match priority order: the first group with a keyword among a class
# name's words wins ("roof_pitched" must beat "roof"; "parking" is its own word, not "park").
GROUP_KEYWORDS: tuple[tuple[str, frozenset[str]], ...] = (
    ("roof_pitched", frozenset({"pitched", "gable", "gabled", "tiled", "hip"})),
    ("person", frozenset({"person", "people", "pedestrian", "crowd", "human"})),
    ("car", frozenset({"car", "vehicle", "truck", "bus", "van", "train", "automobile"})),
    ("water", frozenset({"water", "lake", "river", "pool", "sea", "pond", "canal", "swimming"})),
    ("tree", frozenset({"tree", "forest", "wood", "woodland", "bush", "shrub", "hedge", "hedgerow"})),
    ("roof", frozenset({"roof", "rooftop", "building", "house", "warehouse", "shed", "garage", "flat"})),
    ("road", frozenset({"road", "street", "asphalt", "highway", "avenue", "lane", "motorway"})),
    ("paved", frozenset({"sidewalk", "pavement", "plaza", "square", "concrete", "parking", "paved", "courtyard"})),
    ("sports_field", frozenset({"sport", "field", "stadium", "pitch", "court"})),
    ("grass", frozenset({"grass", "lawn", "park", "vegetation", "meadow", "garden", "turf", "greenery"})),
    ("soil", frozenset({"soil", "land", "sand", "dirt", "gravel", "earth", "desert", "unpaved", "ground"})),
)
OTHER_GROUP = "other"
OUTSIDE_GROUP = "outside"
GROUPS: tuple[str, ...] = tuple(g for g, _ in GROUP_KEYWORDS) + (OTHER_GROUP,)

# CLIPSeg's typical P(safe) per group at noise 1 (reference prompts, aerial views). "other" is
# an unknown class name: it reads mildly unsafe, or mildly safe when the world calls it safe.
DEFAULT_AFFINITY: tuple[tuple[str, float], ...] = (
    ("grass", 0.8),
    ("sports_field", 0.8),
    ("soil", 0.65),
    ("paved", 0.6),
    ("road", 0.3),
    ("roof", 0.35),  # flat roofs look like concrete floors
    ("roof_pitched", 0.15),
    ("tree", 0.45),  # canopies look like grass from above
    ("water", 0.25),  # still water looks like shadow or dark ground
    ("person", 0.3),  # a few pixels, blurred into their surroundings
    ("car", 0.2),
    ("other", 0.3),
)
OTHER_SAFE_AFFINITY = 0.55

# Pairs a segmenter mixes up; each frame, each member is pulled a random fraction towards the other.
CONFUSION_PAIRS: tuple[tuple[str, str], ...] = (("roof", "paved"), ("tree", "grass"), ("water", "soil"))

# Random stream ids, so the draws of one effect never shift another's.
_STREAM_EFFECTS = 1
_STREAM_FLICKER_FIELD = 2
_STREAM_SLOW_FIELD = 3


class MissingTruthError(DoveseiError, ValueError):
    """A frame without the sim's ground-truth labels reached the simulated backend."""

    def __init__(self) -> None:
        super().__init__(
            "simulated perception needs the sim's ground-truth labels; this frame has none (a real camera?)"
        )


# The default noise: the level at which, on the default synthetic world under the reference-timing
# preset, `dovesei` vs `dovesei-nofocus` land closest to the paper's 29/50 vs 3/50 (measured with
# `dovesei calibrate`; the sweep and the check run are in docs/RESULTS.md).
CALIBRATED_NOISE = 0.55


@dataclass(frozen=True)
class SimPerceptionParams:
    """Knobs of the simulated perception. ``noise`` multiplies every strength below; 0 = clean labels.

    Probabilities are in [0, 1]; lengths are fractions of the image or of one ViT patch so the
    same params fit any camera resolution.
    """

    noise: float = CALIBRATED_NOISE
    """Overall error scale: 0 clean labels, 1 every effect at its CLIPSeg-like strength, up to 4."""
    affinity: tuple[tuple[str, float], ...] = DEFAULT_AFFINITY
    """(group, P(safe) at noise 1) pairs; groups not listed keep DEFAULT_AFFINITY."""
    other_safe_affinity: float = OTHER_SAFE_AFFINITY
    """P(safe) at noise 1 of an unrecognised class name that the world marks safe."""
    outside_prob: float = 0.2
    """P(safe) outside the world (label 255), at every noise level: unknown, so low-ish."""
    blur_sigma_patches: float = 0.5
    """Gaussian blur sigma in ViT patches (1 patch = image side / 22) at noise 1: the patch grid
    and the decoder's upsampling erase cars and people but keep roads and buildings."""
    field_amplitude: float = 0.15
    """Std of the slow spatially correlated error field at noise 1 (grid-node std)."""
    field_corr_frac: float = 0.2
    """Correlation length of both error fields as a fraction of the image width (grid spacing).
    0.2 is ~30 m seen from 100 m, a few ViT patches: shorter lengths paint object-sized fake
    blobs that hide the scene; longer ones become a mere slow bias across the frame."""
    field_period_frames: int = 8
    """Frames over which the slow field morphs into the next independent one."""
    flicker_amplitude: float = 0.06
    """Std of the per-frame independent correlated field at noise 1."""
    gain_jitter: float = 0.12
    """Std of the per-frame contrast gain around 0.5 (gain = 1 + N(0, this)) at noise 1."""
    offset_jitter: float = 0.05
    """Std of the per-frame global offset at noise 1."""
    group_jitter: float = 0.06
    """Std of the per-frame perturbation of each group's affinity at noise 1."""
    confusion_pull: float = 0.3
    """Max per-frame fraction by which a group moves towards its confusion partner at noise 1."""
    flip_prob: float = 0.1
    """Probability per frame of a region flip at noise 1 (scaled by noise, capped at 1)."""
    flip_area_frac: tuple[float, float] = (0.10, 0.30)
    """Range of the flipped blob's area as a fraction of the image."""
    flip_strength: float = 1.0
    """1 inverts P inside the blob (P -> 1 - P); 0.5 pulls it to 0.5; 0 disables the flip."""

    def __post_init__(self) -> None:
        for name, lo, hi in (
            ("noise", 0.0, 4.0),
            ("other_safe_affinity", 0.0, 1.0),
            ("outside_prob", 0.0, 1.0),
            ("blur_sigma_patches", 0.0, 4.0),
            ("field_amplitude", 0.0, 1.0),
            ("flicker_amplitude", 0.0, 1.0),
            ("gain_jitter", 0.0, 1.0),
            ("offset_jitter", 0.0, 1.0),
            ("group_jitter", 0.0, 0.5),
            ("confusion_pull", 0.0, 1.0),
            ("flip_prob", 0.0, 1.0),
            ("flip_strength", 0.0, 1.0),
        ):
            _check_range(name, getattr(self, name), lo, hi)
        _check_range("field_corr_frac", self.field_corr_frac, 0.02, 1.0)
        period = self.field_period_frames
        if isinstance(period, bool) or not isinstance(period, int) or period < 1:
            raise ConfigError(f"SimPerceptionParams.field_period_frames must be an int >= 1, got {period!r}")
        try:
            lo_frac, hi_frac = (float(v) for v in self.flip_area_frac)
        except (TypeError, ValueError):
            raise ConfigError(
                f"SimPerceptionParams.flip_area_frac must be a (min, max) pair, got {self.flip_area_frac!r}"
            ) from None
        if not 0.01 <= lo_frac <= hi_frac <= 0.5:
            raise ConfigError(
                "SimPerceptionParams.flip_area_frac must satisfy 0.01 <= min <= max <= 0.5, "
                f"got {self.flip_area_frac!r}"
            )
        seen: set[str] = set()
        for item in self.affinity:
            if not (isinstance(item, tuple) and len(item) == 2):
                raise ConfigError(f"SimPerceptionParams.affinity entries must be (group, p) pairs, got {item!r}")
            group, p = item
            if group not in GROUPS:
                raise ConfigError(f"SimPerceptionParams.affinity: unknown group {group!r}; groups are {GROUPS}")
            if group in seen:
                raise ConfigError(f"SimPerceptionParams.affinity: group {group!r} given twice")
            seen.add(group)
            _check_range(f"affinity[{group!r}]", p, 0.0, 1.0)

    def affinity_of(self, group: str) -> float:
        """P(safe) of a group at noise 1 (the override in ``affinity``, else the default)."""
        return {**dict(DEFAULT_AFFINITY), **dict(self.affinity)}[group]


def _check_range(name: str, value: object, lo: float, hi: float) -> None:
    # bool is an int subclass; a True here is a caller's mistake, not 1.0.
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"SimPerceptionParams.{name} must be a finite number, got {value!r}")
    if not lo <= value <= hi:
        raise ConfigError(f"SimPerceptionParams.{name} must be in [{lo}, {hi}], got {value}")


def perception_group(class_name: str) -> str:
    """The perception group of a class name, by keywords on its words ("bare_soil" -> "soil").

    Words are split on anything that is not a letter; a trailing plural "s"/"es" is ignored.
    Names that match nothing (e.g. "unlabeled") are ``"other"``.
    """
    words = [w for w in re.split(r"[^a-z]+", class_name.lower()) if w]
    forms: set[str] = set()
    for w in words:
        forms.add(w)
        # Plurals: "trees" -> "tree", "grasses" -> "grass" (and harmless stems such as "gras").
        if w.endswith("es"):
            forms.add(w[:-2])
        if w.endswith("s"):
            forms.add(w[:-1])
    for group, keywords in GROUP_KEYWORDS:
        if forms & keywords:
            return group
    return OTHER_GROUP


@dataclass(frozen=True)
class FlipBlob:
    """A region whose probabilities are inverted for one frame, in image-fraction coordinates."""

    centre_xy_frac: tuple[float, float]
    area_frac: float
    aspect: float  # x stretch over y stretch (area-preserving)
    angle_rad: float
    wobble: tuple[tuple[float, float], ...]  # (amplitude, phase_rad) of radial harmonics 2, 3, ...

    def mask(self, height_px: int, width_px: int) -> np.ndarray:
        """Soft mask (float32 HxW in [0, 1]) of the blob rasterised at the given size."""
        u = (np.arange(width_px, dtype=np.float32) + 0.5) / width_px - self.centre_xy_frac[0]
        v = (np.arange(height_px, dtype=np.float32) + 0.5) / height_px - self.centre_xy_frac[1]
        uu, vv = np.meshgrid(u, v)
        # Undo rotation, then stretch so the ellipse becomes a circle of radius `base`.
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        a = (c * uu + s * vv) / math.sqrt(self.aspect)
        b = (-s * uu + c * vv) * math.sqrt(self.aspect)
        rho = np.hypot(a, b)
        theta = np.arctan2(b, a)
        base = self._base_radius()
        radius = np.full_like(rho, base)
        for k, (amp, phase) in enumerate(self.wobble, start=2):
            radius += base * amp * np.cos(k * theta + phase)
        # A soft edge a few percent of the radius wide, so the flip has no hard seam.
        edge = 0.08
        return np.clip((1.0 - rho / radius) / edge + 0.5, 0.0, 1.0).astype(np.float32)

    def _base_radius(self) -> float:
        # Area of r(t) = R (1 + sum a_k cos(k t + p_k)) is pi R^2 (1 + sum a_k^2 / 2).
        return math.sqrt(self.area_frac / (math.pi * (1.0 + 0.5 * sum(a * a for a, _ in self.wobble))))


@dataclass(frozen=True)
class FrameEffects:
    """The random draws of one frame, before any pixel is touched (inspectable by tests)."""

    frame_seq: int
    group_affinity: Mapping[str, float] = field(repr=False)
    """Each group's P(safe) this frame at full CLIPSeg error (jittered and confused)."""
    gain: float
    offset: float
    flip: FlipBlob | None


@dataclass(frozen=True)
class _ClassTables:
    """Per-id lookup tables of one class table: clean value, group index, affinity at noise 1."""

    clean: np.ndarray  # (256,) float64: 1 safe, 0 unsafe/unknown, outside_prob at 255
    group_index: np.ndarray  # (256,) int: index into GROUPS, -1 for outside
    other_safe: np.ndarray  # (256,) bool: "other" classes the world marks safe


class SimulatedBackend:
    """Simulated CLIPSeg: ground-truth labels in, degraded P(safe) out. A test instrument only."""

    name = "simulated"

    def __init__(self, params: SimPerceptionParams = SimPerceptionParams(), seed: int = 0) -> None:
        if not isinstance(params, SimPerceptionParams):
            raise ConfigError(f"params must be SimPerceptionParams, got {type(params).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed must be a non-negative int, got {seed!r}")
        self.params = params
        self.seed = int(seed)
        self._affinity = np.array([params.affinity_of(g) for g in GROUPS], dtype=np.float64)
        self._pairs = [(GROUPS.index(a), GROUPS.index(b)) for a, b in CONFUSION_PAIRS]
        self._tables: dict[tuple, _ClassTables] = {}
        log.info(
            "simulated perception backend (test instrument, needs sim ground truth; never for a real camera): "
            "noise=%.2f seed=%d",
            params.noise,
            self.seed,
        )

    # --- per-frame random draws -------------------------------------------------------------

    def frame_effects(self, frame_seq: int) -> FrameEffects:
        """The random draws of frame ``frame_seq``: group affinities, gain/offset, flip blob.

        The same numbers of draws happen whatever the noise, so a frame at noise 2 is the frame at
        noise 1 with its errors scaled, not a different frame.
        """
        frame_seq = _check_seq(frame_seq)
        p = self.params
        rng = np.random.default_rng([self.seed, _STREAM_EFFECTS, frame_seq])
        jitter = rng.standard_normal(len(GROUPS))
        pulls = rng.random(2 * len(self._pairs))
        gain_z, offset_z = rng.standard_normal(2)
        flip_u = rng.random()
        blob_draws = rng.random(5 + 2 * 3)

        # Jitter per GROUP, not per pixel: CLIPSeg misjudges a whole material at once in a frame.
        values = np.clip(self._affinity + p.group_jitter * p.noise * jitter, 0.0, 1.0)
        confused = values.copy()
        for i, (a, b) in enumerate(self._pairs):
            # Each member of a confused pair slides towards the other one's look this frame.
            pull_max = min(1.0, p.confusion_pull * p.noise)
            confused[a] += pull_max * pulls[2 * i] * (values[b] - values[a])
            confused[b] += pull_max * pulls[2 * i + 1] * (values[a] - values[b])

        flip = None
        # Independent per frame: a flip lasts exactly one frame, as CLIPSeg's sudden misreadings do.
        if flip_u < min(1.0, p.flip_prob * p.noise) and p.flip_strength > 0.0:
            flip = self._flip_blob(blob_draws)
        return FrameEffects(
            frame_seq=frame_seq,
            group_affinity=dict(zip(GROUPS, (float(v) for v in confused))),
            gain=max(0.0, 1.0 + p.gain_jitter * p.noise * float(gain_z)),
            offset=p.offset_jitter * p.noise * float(offset_z),
            flip=flip,
        )

    def _flip_blob(self, u: np.ndarray) -> FlipBlob:
        lo, hi = self.params.flip_area_frac
        area = lo + (hi - lo) * float(u[0])
        aspect = math.exp((float(u[1]) - 0.5) * math.log(2.0))  # between 1/sqrt2 and sqrt2
        angle = math.pi * float(u[2])
        wobble = tuple((0.12 * float(u[5 + 2 * k]), 2 * math.pi * float(u[6 + 2 * k])) for k in range(3))
        blob = FlipBlob((0.5, 0.5), area, aspect, angle, wobble)
        # Keep the blob inside the image so its area is the drawn fraction: place the centre
        # anywhere its (stretched, wobbled) extent still fits.
        extent = blob._base_radius() * (1.0 + sum(a for a, _ in wobble)) * math.sqrt(max(aspect, 1.0 / aspect))
        span = max(0.0, 1.0 - 2.0 * extent)
        cx = 0.5 + span * (float(u[3]) - 0.5)
        cy = 0.5 + span * (float(u[4]) - 0.5)
        return FlipBlob((cx, cy), area, aspect, angle, wobble)

    # --- rendering ---------------------------------------------------------------------------

    def safe_probability(
        self,
        truth_labels: np.ndarray | None,
        classes: Mapping[int, tuple[str, bool]] | Iterable[object],
        frame_seq: int,
        out_size: tuple[int, int] | None = None,
    ) -> np.ndarray:
        """P(safe) per pixel (float32, in [0, 1]) of one frame.

        ``truth_labels``: HxW uint8 class ids seen by the camera (255 = outside the world); None
        raises `MissingTruthError`. ``classes``: id -> (name, safe), or an iterable of entries with
        ``id``, ``name`` and ``safe`` (the sim's ``ClassEntry``); ids absent from it are unsafe.
        ``out_size``: (height_px, width_px) of the output, numpy order; default the labels' size
        (labels are resized nearest-neighbour first, so the errors are drawn at the output size).
        """
        if truth_labels is None:
            raise MissingTruthError()
        labels = _check_labels(truth_labels)
        frame_seq = _check_seq(frame_seq)
        if out_size is not None:
            height_px, width_px = _check_size(out_size)
            if labels.shape != (height_px, width_px):
                labels = cv2.resize(labels, (width_px, height_px), interpolation=cv2.INTER_NEAREST)
        tables = self._tables_for(classes)
        p = self.params
        if p.noise == 0.0:
            # Clean labels: exact 0/1 (and outside_prob), no random stream touched.
            return cv2.LUT(labels, tables.clean.astype(np.float32))

        effects = self.frame_effects(frame_seq)
        lut = self._frame_lut(tables, effects)
        prob = cv2.LUT(labels, lut)
        prob = self._degrade(prob, effects)
        log.debug("simulated heatmap frame %d: gain %.3f offset %.3f flip %s", frame_seq, effects.gain,
                  effects.offset, effects.flip is not None)
        return prob

    def _frame_lut(self, tables: _ClassTables, effects: FrameEffects) -> np.ndarray:
        """Per-id P(safe) of this frame: clean value moved towards the group's affinity."""
        # Capped at 1: past CLIPSeg's affinities, more noise means more random error, not
        # systematically inverted classes (see the module docstring).
        weight = min(1.0, self.params.noise)
        group_values = np.array([effects.group_affinity[g] for g in GROUPS])
        affinity = group_values[np.maximum(tables.group_index, 0)]
        # Unknown-but-safe classes read mildly safe; shift by the frame's "other" jitter too.
        other_shift = group_values[GROUPS.index(OTHER_GROUP)] - self._affinity[GROUPS.index(OTHER_GROUP)]
        affinity = np.where(tables.other_safe, self.params.other_safe_affinity + other_shift, affinity)
        lut = tables.clean + weight * (affinity - tables.clean)
        lut[OUTSIDE_ID] = self.params.outside_prob  # unknown at every noise level
        return np.clip(lut, 0.0, 1.0).astype(np.float32)

    def _degrade(self, prob: np.ndarray, effects: FrameEffects) -> np.ndarray:
        """Blur, fields, flicker and flip on a coarse grid, then one upsample to full size."""
        p = self.params
        height_px, width_px = prob.shape
        # Blur sigma in pixels along each axis: CLIPSeg sees the frame as 22x22 patches whatever its size.
        patches_across = CLIPSEG_INPUT_PX / CLIPSEG_PATCH_PX
        sigma_x = p.blur_sigma_patches * p.noise * width_px / patches_across
        sigma_y = p.blur_sigma_patches * p.noise * height_px / patches_across
        # The output is smooth at the blur's scale, so work on a grid a few times coarser; a
        # power-of-two step divides common image sizes, which keeps OpenCV's area resize fast.
        step = 1
        while step < 8 and 2 * step <= min(sigma_x, sigma_y) / 2.0:
            step *= 2
        work_h, work_w = -(-height_px // step), -(-width_px // step)
        work = prob if step == 1 else cv2.resize(prob, (work_w, work_h), interpolation=cv2.INTER_AREA)
        # The area downsample already blurred by a box of `step` pixels (variance (step^2-1)/12).
        box_var = (step * step - 1) / 12.0
        sx = math.sqrt(max(sigma_x**2 - box_var, 0.0)) / step
        sy = math.sqrt(max(sigma_y**2 - box_var, 0.0)) / step
        if max(sx, sy) >= 0.3:
            work = cv2.GaussianBlur(work, (0, 0), sigmaX=max(sx, 1e-3), sigmaY=max(sy, 1e-3))

        # The error fields are drawn on a coarse node grid and interpolated (bicubic), which is
        # what makes them spatially correlated at a cost independent of the image size.
        field_grid = self._field_grid(effects.frame_seq, work_h / work_w)
        work = work + cv2.resize(field_grid, (work_w, work_h), interpolation=cv2.INTER_CUBIC)
        # Flicker of the whole map: contrast around 0.5 and a global shift.
        work = 0.5 + effects.gain * (work - 0.5) + effects.offset
        if effects.flip is not None:
            # Inverting after the noise makes the flipped region a mirror of the frame's own
            # estimate there, the way a misread region looks, rather than a flat patch.
            blob = effects.flip.mask(work_h, work_w)
            work = work + (p.flip_strength * blob) * (1.0 - 2.0 * work)
        if step > 1:
            work = cv2.resize(work, (width_px, height_px), interpolation=cv2.INTER_LINEAR)
        np.clip(work, 0.0, 1.0, out=work)
        return work.astype(np.float32, copy=False)

    def _field_grid(self, frame_seq: int, aspect_hw: float) -> np.ndarray:
        """Coarse grid of the summed error fields (slow morphing field + this frame's flicker)."""
        p = self.params
        # One node per correlation length, plus one so both image edges sit on a node.
        grid_w = math.ceil(1.0 / p.field_corr_frac) + 1
        grid_h = max(2, math.ceil(aspect_hw / p.field_corr_frac) + 1)
        shape = (grid_h, grid_w)
        # Slow field: blend two independent keyframe fields, variance-preserving, so the error
        # pattern drifts over `field_period_frames` instead of jumping every frame.
        key, phase = divmod(frame_seq, p.field_period_frames)
        w = phase / p.field_period_frames
        f0 = np.random.default_rng([self.seed, _STREAM_SLOW_FIELD, key]).standard_normal(shape)
        f1 = np.random.default_rng([self.seed, _STREAM_SLOW_FIELD, key + 1]).standard_normal(shape)
        slow = ((1.0 - w) * f0 + w * f1) / math.hypot(1.0 - w, w)
        fresh = np.random.default_rng([self.seed, _STREAM_FLICKER_FIELD, frame_seq]).standard_normal(shape)
        grid = p.noise * (p.field_amplitude * slow + p.flicker_amplitude * fresh)
        return grid.astype(np.float32)

    def _tables_for(self, classes: Mapping[int, tuple[str, bool]] | Iterable[object]) -> _ClassTables:
        entries = _class_entries(classes)
        key = tuple(sorted(entries.items()))
        tables = self._tables.get(key)
        if tables is None:
            if len(self._tables) >= 8:
                self._tables.clear()  # worlds rarely change; a tiny cache is enough
            tables = _build_tables(entries, self.params.outside_prob)
            self._tables[key] = tables
            log.info(
                "simulated perception class groups: %s",
                ", ".join(f"{i}:{n}->{GROUPS[tables.group_index[i]]}" for i, (n, _) in sorted(entries.items())),
            )
        return tables


def _class_entries(classes: Mapping[int, tuple[str, bool]] | Iterable[object]) -> dict[int, tuple[str, bool]]:
    """Normalise a class table to {id: (name, safe)}, accepting a mapping or ClassEntry-likes."""
    out: dict[int, tuple[str, bool]] = {}
    # The brief's form (a mapping) and the wire form (GroundTruth.classes, a tuple of ClassEntry)
    # both arrive here; duck typing keeps this module free of the message classes.
    if isinstance(classes, Mapping):
        items = list(classes.items())
    else:
        try:
            items = [(e.id, (e.name, e.safe)) for e in classes]  # type: ignore[attr-defined]
        except (AttributeError, TypeError):
            raise ValueError(
                "classes must map id -> (name, safe) or be entries with id, name and safe attributes"
            ) from None
    for class_id, entry in items:
        try:
            class_id = int(class_id)
            name, safe = entry if not isinstance(entry, Mapping) else (entry["name"], entry["safe"])
        except (TypeError, ValueError, KeyError):
            raise ValueError(f"classes[{class_id!r}] must be (name, safe), got {entry!r}") from None
        if not 0 <= class_id <= 254:
            raise ValueError(f"class id {class_id} outside 0..254 (255 marks outside the world)")
        if not isinstance(name, str):
            raise ValueError(f"classes[{class_id}] name must be a str, got {name!r}")
        out[class_id] = (name, bool(safe))
    return out


def _build_tables(entries: Mapping[int, tuple[str, bool]], outside_prob: float) -> _ClassTables:
    clean = np.zeros(256, dtype=np.float64)  # ids absent from the table count as unsafe
    group_index = np.full(256, GROUPS.index(OTHER_GROUP), dtype=np.int64)
    other_safe = np.zeros(256, dtype=bool)
    for class_id, (name, safe) in entries.items():
        group = perception_group(name)
        clean[class_id] = 1.0 if safe else 0.0
        group_index[class_id] = GROUPS.index(group)
        other_safe[class_id] = safe and group == OTHER_GROUP
    clean[OUTSIDE_ID] = outside_prob
    group_index[OUTSIDE_ID] = -1
    return _ClassTables(clean=clean, group_index=group_index, other_safe=other_safe)


def _check_labels(labels: object) -> np.ndarray:
    if not isinstance(labels, np.ndarray):
        raise ValueError(f"truth labels must be a numpy array, got {type(labels).__name__}")
    if labels.ndim != 2 or labels.shape[0] < 1 or labels.shape[1] < 1:
        raise ValueError(f"truth labels must be a non-empty HxW array, got shape {labels.shape}")
    if labels.dtype != np.uint8:
        # Other integer dtypes are accepted when they fit: a world folder's PNG may load as int32.
        if not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"truth labels must hold integer class ids, got dtype {labels.dtype}")
        if labels.min() < 0 or labels.max() > 255:
            raise ValueError(f"truth labels must be in 0..255, got {labels.min()}..{labels.max()}")
        labels = labels.astype(np.uint8)
    return np.ascontiguousarray(labels)


def _check_seq(frame_seq: object) -> int:
    if isinstance(frame_seq, bool) or not isinstance(frame_seq, (int, np.integer)) or frame_seq < 0:
        raise ValueError(f"frame_seq must be a non-negative int, got {frame_seq!r}")
    return int(frame_seq)


def _check_size(out_size: object) -> tuple[int, int]:
    try:
        height_px, width_px = (int(v) for v in out_size)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"out_size must be (height_px, width_px), got {out_size!r}") from None
    if height_px < 1 or width_px < 1:
        raise ValueError(f"out_size must be positive, got {out_size!r}")
    return height_px, width_px


# --- demo scene, benchmark, preview -----------------------------------------------------------

# The synthetic city's class table (id -> (name, safe)), used by the demo scene below.
DEMO_CLASSES: dict[int, tuple[str, bool]] = {
    1: ("roof_flat", False),
    2: ("roof_pitched", False),
    3: ("road", False),
    4: ("sidewalk", False),
    5: ("plaza", True),
    6: ("parking_lot", True),
    7: ("car", False),
    8: ("grass", True),
    9: ("sports_field", True),
    10: ("tree", False),
    11: ("water", False),
    12: ("bare_soil", True),
    13: ("person", False),
}


def demo_labels(size_px: int = CLIPSEG_INPUT_PX) -> np.ndarray:
    """A hand-made city block (ids of DEMO_CLASSES) as a nadir camera at ~100 m would see it.

    Drawn on a 352-pixel canvas (~0.42 m/px) and resized nearest-neighbour to ``size_px``; the
    right edge is outside the world (255) so the preview shows how that region reads.
    """
    lab = np.full((CLIPSEG_INPUT_PX, CLIPSEG_INPUT_PX), 4, dtype=np.uint8)  # sidewalk everywhere
    rect = cv2.rectangle
    rect(lab, (0, 150), (351, 174), 3, -1)  # east-west road, ~10 m wide
    rect(lab, (200, 0), (224, 351), 3, -1)  # north-south road
    # North-west block: a park with a pond and trees.
    rect(lab, (6, 6), (192, 142), 8, -1)
    cv2.ellipse(lab, (70, 60), (34, 22), 15, 0, 360, 11, -1)
    for cx, cy, r in ((130, 30, 11), (150, 45, 9), (165, 110, 12), (30, 120, 10), (120, 115, 8)):
        cv2.circle(lab, (cx, cy), r, 10, -1)
    rect(lab, (100, 70), (140, 95), 12, -1)  # bare soil patch
    # North-east block: buildings, flat and pitched roofs, and a plaza.
    rect(lab, (232, 6), (290, 70), 1, -1)
    rect(lab, (298, 6), (345, 40), 2, -1)
    rect(lab, (232, 80), (270, 142), 2, -1)
    rect(lab, (278, 50), (345, 142), 5, -1)
    rect(lab, (300, 70), (330, 100), 1, -1)
    # South-west block: a parking lot with cars, and a flat-roofed building.
    rect(lab, (6, 182), (110, 300), 6, -1)
    for col in range(12, 100, 14):
        for row in (190, 215, 265):
            rect(lab, (col, row), (col + 5, row + 10), 7, -1)
    rect(lab, (118, 182), (192, 345), 1, -1)
    # South-east block: a sports field, trees along it, people on it.
    rect(lab, (232, 182), (345, 300), 9, -1)
    for col in range(236, 345, 18):
        cv2.circle(lab, (col, 320), 8, 10, -1)
    for col, row in ((260, 220), (300, 250), (320, 200), (280, 270)):
        rect(lab, (col, row), (col + 1, row + 1), 13, -1)
    rect(lab, (6, 308), (110, 345), 12, -1)
    lab[:, 336:] = OUTSIDE_ID  # the world ends here
    if size_px != CLIPSEG_INPUT_PX:
        lab = cv2.resize(lab, (size_px, size_px), interpolation=cv2.INTER_NEAREST)
    return lab


def bench_hz(n: int = 200) -> float:
    """Heatmaps per second at 352x352, noise 1, on one OpenCV thread (the demo scene)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    labels = demo_labels()
    backend = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=0)
    # One OpenCV thread: the figure is per core (the controller and sim share the machine).
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for seq in range(5):  # warm the class tables and OpenCV's code paths
            backend.safe_probability(labels, DEMO_CLASSES, seq)
        t0 = time.perf_counter()
        for seq in range(n):
            backend.safe_probability(labels, DEMO_CLASSES, 1000 + seq)
        elapsed_s = time.perf_counter() - t0
    finally:
        cv2.setNumThreads(threads)
    return n / elapsed_s


# Colours (RGB) of the groups for the preview's stand-in camera frame.
_GROUP_RGB: dict[str, tuple[int, int, int]] = {
    "roof": (150, 150, 145),
    "roof_pitched": (160, 80, 60),
    "road": (70, 70, 75),
    "paved": (185, 180, 170),
    "sports_field": (90, 160, 80),
    "grass": (110, 150, 70),
    "tree": (40, 90, 40),
    "water": (40, 70, 90),
    "soil": (150, 120, 85),
    "person": (220, 40, 40),
    "car": (200, 200, 40),
    "other": (128, 0, 128),
}


def _frame_rgb(labels: np.ndarray, classes: Mapping[int, tuple[str, bool]]) -> np.ndarray:
    """A stand-in camera image coloured by group, with a little texture (preview only)."""
    lut = np.zeros((256, 3), dtype=np.uint8)
    lut[:] = _GROUP_RGB["other"]
    for class_id, (name, _) in _class_entries(classes).items():
        lut[class_id] = _GROUP_RGB[perception_group(name)]
    lut[OUTSIDE_ID] = (0, 0, 0)
    texture = np.random.default_rng(0).normal(0.0, 8.0, labels.shape + (1,))
    return np.clip(lut[labels] + texture, 0, 255).astype(np.uint8)


def _heat_rgb(prob: np.ndarray) -> np.ndarray:
    """P(safe) as RGB: red 0, yellow 0.5, green 1."""
    t = np.linspace(0.0, 1.0, 256)
    lut = np.stack([np.clip(2.0 - 2.0 * t, 0, 1), np.clip(2.0 * t, 0, 1), np.zeros_like(t)], axis=1)
    return (lut[np.round(prob * 255).astype(np.uint8)] * 230).astype(np.uint8)


def _titled(rgb: np.ndarray, title: str) -> np.ndarray:
    bar = np.full((24, rgb.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(bar, title, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, rgb])


def preview_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[str, bool]]]:
    """(image_rgb, labels, classes) of a 352x352 nadir view for the preview.

    A crop of a small generated synthetic city at 0.42 m/px (what the 73 deg camera sees from
    100 m), the crop with the most classes in it; the hand-made demo scene in stand-in colours
    when the sim package is not installed (the segmenter image may ship without it).
    """
    try:
        from dovesei.sim.synthetic import SYNTHETIC_CLASSES, SyntheticParams, generate_city
    except ImportError:
        log.info("dovesei.sim not importable: preview uses the hand-made demo scene")
        labels = demo_labels()
        return _frame_rgb(labels, DEMO_CLASSES), labels, dict(DEMO_CLASSES)
    image, labels = generate_city(SyntheticParams(seed=seed, size_m=400.0, gsd_m=0.42))
    side = CLIPSEG_INPUT_PX
    best, best_score = (0, 0), -1.0
    for row in range(0, labels.shape[0] - side + 1, 64):
        for col in range(0, labels.shape[1] - side + 1, 64):
            counts = np.bincount(labels[row:row + side, col:col + side].ravel(), minlength=256)
            # Classes with at least 0.3 % of the crop, ties broken towards balanced crops.
            score = float((counts > 0.003 * side * side).sum()) + 1.0 - counts.max() / (side * side)
            if score > best_score:
                best, best_score = (row, col), score
    row, col = best
    return (image[row:row + side, col:col + side].copy(), labels[row:row + side, col:col + side].copy(),
            dict(SYNTHETIC_CLASSES))


def render_noise_preview(
    path: str | Path,
    labels: np.ndarray | None = None,
    classes: Mapping[int, tuple[str, bool]] | None = None,
    seed: int = 0,
    image_rgb: np.ndarray | None = None,
) -> Path:
    """Write a PNG: a frame, its simulated heatmap at noise 0, 1, 2, and two consecutive frames at
    noise 1 where the second one has a region flip.

    Default scene: `preview_scene(seed)`. With ``labels`` (and their ``classes``) and no
    ``image_rgb``, the frame panel shows the labels in stand-in colours.
    """
    if labels is None:
        image_rgb, labels, classes = preview_scene(seed)
    elif classes is None:
        raise ValueError("render_noise_preview: labels given without their classes")
    labels = _check_labels(labels)
    if image_rgb is None:
        image_rgb, frame_title = _frame_rgb(labels, classes), "labels (stand-in colours)"
    else:
        frame_title = "camera frame (sim)"
        if image_rgb.shape != labels.shape + (3,):
            raise ValueError(f"image_rgb shape {image_rgb.shape} does not match labels {labels.shape}")
    panels = [_titled(image_rgb, frame_title)]
    for noise in (0.0, 1.0, 2.0):
        backend = SimulatedBackend(SimPerceptionParams(noise=noise), seed=seed)
        title = f"simulated P(safe), noise {noise:g}" + ("  (red 0 .. green 1)" if noise == 0 else "")
        panels.append(_titled(_heat_rgb(backend.safe_probability(labels, classes, 0)), title))
    # Two consecutive frames where the second flips a region, to show flicker plus a flip.
    backend = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=seed)
    # Draws only (no pixels) to find the pair; with flip_prob 0.1 it is within the first frames.
    seq = next(s for s in range(1, 10_000) if backend.frame_effects(s).flip and not backend.frame_effects(s - 1).flip)
    for s in (seq - 1, seq):
        note = " (region flip)" if backend.frame_effects(s).flip else ""
        panels.append(_titled(_heat_rgb(backend.safe_probability(labels, classes, s)), f"noise 1, frame {s}{note}"))
    gap = np.full((panels[0].shape[0], 6, 3), 255, dtype=np.uint8)
    rows = [np.hstack([panels[i], gap, panels[i + 1], gap, panels[i + 2]]) for i in (0, 3)]
    sheet = np.vstack([rows[0], np.full((6, rows[0].shape[1], 3), 255, np.uint8), rows[1]])
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write preview PNG {out}")
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m dovesei.segmenter.simulated {preview PATH | bench}``: picture or speed."""
    parser = argparse.ArgumentParser(description="Simulated perception (a test instrument): preview or benchmark.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    preview = sub.add_parser("preview", help="write a PNG of the heatmap at noise 0, 1, 2 and two consecutive frames")
    preview.add_argument("path")
    preview.add_argument("--seed", type=int, default=0)
    bench = sub.add_parser("bench", help="heatmaps per second at 352x352 on one core")
    bench.add_argument("--n", type=int, default=200)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.cmd == "preview":
        print(render_noise_preview(args.path, seed=args.seed))
    else:
        print(f"sim_backend_hz {bench_hz(args.n):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
