"""Simulated CLIPSeg: one logit map per prompt from the sim's truth labels, wrong the way CLIPSeg is.

A TEST INSTRUMENT for comparing landing policies, never a perception system: it needs the sim's
ground-truth label image (frames without it are refused) and it never reads which classes the
judge counts safe, only their NAMES (`appearance.py`). Its output is what CLIPSeg's is, a stack
of prompt logits, and the same fusion (`fusion.py`, reference softmax or grouped) turns it into
P(safe), so changing the prompts changes the map through the response table (`responses.py`).

Data flow for one frame (labels resized to CLIPSeg's 352x352 input, as CLIPSeg resizes frames):

    labels --class names--> appearance mix per class (cached per class table)
           + shadows: roofs/trees/cars cast a shadow away from the episode's sun (world direction,
             turning ~15 deg an hour with the frame's time) on lower ground
      --8x8-pixel cells--> appearance fractions on a 44x44 grid; a person or a car weighs by how
        many tokens it covers (the resolution curve, `object_gain`): its area alone under one
        token, up to 3x its area across several
      --per-patch looks, fixed on the GROUND--> an atypical patch of a class reads partly as its
        other looks (INSTANCE_LOOKS: dry lawn -> soil, stained concrete -> asphalt, wet sand ->
        pavement) where a seeded field over (east, north) keyed by (seed, world) is high
      --Gaussian ~1 token--> detail under one token (1/22 of the view: ~6.7 m at 100 m, ~1.3 m
        at 20 m) is diluted into its surroundings
      --confusions anchored in WORLD metres--> each appearance is read partly as a partner
        (grey flat roof -> plaza, dark pond -> asphalt, lawn -> sports field) where a seeded
        value-noise field over (east, north, log2 altitude) is high: the same ground is misread
        the same way frame after frame and drifts as the altitude changes (a close look's crop
        is read at the altitude whose 73 deg view is its square, `crop_view_of`: the same square
        reads alike from any height); how often and towards which partner is the WORLD's own (a
        log-normal draw per world around CONFUSIONS)
      --context--> each cell pulled towards its neighbourhood and towards the whole view
      --responses--> logits = f * logit_scale * G @ R (R: appearance x prompt affinities), the
        positives + o: the episode's calibration (f, o), drawn per (seed, world)
      + flicker: a small smooth per-frame field and per-prompt offsets (seed, frame_seq)
      --fusion (softmax or grouped) on an 88x88 grid, box blur at 352--> P(safe)
      --x fraction of the cell inside the world--> off-world reads 0, below any real class
      --bilinear--> frame size

Variation between episodes and worlds, and where the ranges come from. The statistics we have of
real CLIPSeg on this task are the authors' logs of the reference pipeline (the dynamic threshold's
median 0.51, lowered below 0.85 on 99.8 % of frames) and PEACE (prompt wording alone moved safe-zone
identification from 57 % to 92 %: CLIPSeg's absolute levels are not a property of the ground).

- logit scale factor f, uniform in 1 +- 0.2 (`realistic`; 1 +- 0.3 `harsh`): with every other
  draw held, `logit_scale` 4, 5 and 6 give a frame-weighted median threshold of 0.47, 0.53 and
  0.59 (the test's six worlds, seeds 1-2, not the reported 0), all within the authors' 0.51 +- 0.1,
  so a calibration anywhere from 4 to 6 is as consistent with their logs as the mean.
- positive offset o, uniform in +-0.4 logit (`harsh` +-0.6): under both fusions it moves
  logit P(safe) by o exactly, so +-0.4 moves the authors' median threshold 0.51 to 0.41-0.61,
  the band the perception-stats test holds the suite to; `harsh` goes past it on purpose.
- per-patch looks: up to 50 % (`harsh` 70 %) of a patch read as its other looks, on a 25 m
  lattice (a lawn, a lot, a roof), half the area atypical at all: judgement, not a statistic;
  the test holds perception-stats inside the authors' band with it on.
- world confusion tables: log-normal sigma 0.5 (`harsh` 0.7) on each class's partner weights,
  half that on its strength (capped at 0.95): CLIPSeg's misreadings follow the imagery (PEACE's
  scenes needed different prompts), so each world gets its own.
- sun elevation 45 +- 20 deg per episode (`harsh` +- 25), azimuth uniform: mid-morning to
  mid-afternoon at mid latitudes.

`clean` has none of it. ``noise`` scales every spread (0: none). `dovesei perception-stats` and
tests/segmenter/test_perception_variation.py check the result against the statistics above.

Determinism: the output is a pure function of (labels, class names, view, prompts, params,
seed, frame_seq); every random draw comes from a hash or a fresh generator keyed by them (the
world's name through crc32, never Python's salted str hash).

Speed: the per-frame path reads each label pixel through lookup tables built once per world
(`_Classes`: codes ordered so that "casts at least this tall" is a code range), casts all
shadows as one running maximum of caster codes, counts (cell row, cell column, code) in one
OpenCV histogram of 8-bit images, weighs objects from their own pixels alone (not their box),
evaluates both octaves of a world field in one pass over the 16 x 16 field points and keeps the
hashed value-noise lattice around the view from frame to frame (`_lattice`: a pure function of
lattice point, height and key; a table per height and spacing with a row per key, so a field that
comes into view hashes only its own row; least recently used out). It is float32 from the cell
counts on, keeps every matrix product under OpenBLAS's one-thread size (`_rows_product`: threads
cost a loaded machine's CPU several times what they save) and hands the fusion its prompt planes
through OpenCV's transpose; tests/segmenter/test_perception_variation.py holds it equal to the
plain formulas. The process keeps the memory a frame frees for the next (`heap.keep_freed_memory`):
glibc would hand much of it back and page-fault it in again, frame after frame.
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import logging
import math
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.shared import footprint, heap, validate
from dovesei.shared.errors import ConfigError

from .appearance import APPEARANCES, INDEX, OFF_WORLD_LABEL, appearance_mix
from .fusion import FusionConfig, blur_prob, fuse
from .prompts import PromptSet
from .responses import ITEM_SHARPNESS, response_matrix

log = logging.getLogger(__name__)

INPUT_PX = 352  # CLIPSeg's input side
CELL_SIZES_PX = (1, 2, 4, 8)  # 8 = half a 16-pixel ViT patch: appearance fractions on 44x44
FIELD_GRID = 16  # world-anchored fields are evaluated on 16x16 points across the view
A = len(APPEARANCES)

# Who is misread as whom, and how often relative to the others (rows need not sum to 1).
CONFUSIONS: dict[str, dict[str, float]] = {
    "flat_roof": {"paved": 0.6, "parking": 0.2, "bare_ground": 0.2},
    "pitched_roof": {"flat_roof": 0.5, "bare_ground": 0.3, "paved": 0.2},
    "road": {"parking": 0.5, "paved": 0.5},
    "paved": {"road": 0.3, "flat_roof": 0.4, "bare_ground": 0.3},
    "parking": {"road": 0.6, "paved": 0.4},
    "lawn": {"sports_field": 0.5, "tree": 0.3, "bare_ground": 0.2},
    "sports_field": {"lawn": 0.7, "paved": 0.3},
    "bare_ground": {"paved": 0.5, "lawn": 0.2, "flat_roof": 0.3},
    "tree": {"lawn": 0.7, "shadow": 0.3},
    "water": {"road": 0.5, "shadow": 0.3, "lawn": 0.2},
    "vehicle": {"road": 0.5, "flat_roof": 0.5},
    "person": {"paved": 0.6, "lawn": 0.4},
    "shadow": {"water": 0.4, "road": 0.6},
    "clutter": {"paved": 0.3, "flat_roof": 0.4, "bare_ground": 0.3},
}
# Height of what casts a shadow (m); the sun's elevation turns it into a length on the ground.
CASTER_HEIGHT_M: dict[str, float] = {"flat_roof": 9.0, "pitched_roof": 7.0, "tree": 5.0, "vehicle": 1.5}

# The resolution curve of objects (people, vehicles): how strongly one connected object answers,
# as a multiple of its area, against how many CLIPSeg tokens it covers (16 x 16 px of the 352 px
# input, a ViT-B/16 patch):
#
#     gain(n) = 1 + (OBJECT_GAIN_MAX - 1) * n^2 / (n^2 + OBJECT_HALF_TOKENS^2),  n = area_px / 256
#
#     n (tokens)  0.004 (a person at 100 m: 1 px)   0.1 (a person at 20 m)   0.5   1     2     4 (a car at 20 m)
#     gain        1.00                               1.02                     1.4   2.0   2.6   2.9
#
# Assumption (no per-object statistics of CLIPSeg were measured here): a patch embedding describes
# what fills most of its 16 px; an object much smaller than a patch only shifts the patch's colour
# and texture statistics in proportion to its area, so it is a dip of its area share and no more
# (issue 24: a person under one token at 100 m read as ~0.02 in P, inside the ripple). An object
# spanning a token or more is recognised as such, and CLIPSeg's upsampled 22 x 22 blobs outgrow
# the objects they find, so across several tokens it answers up to OBJECT_GAIN_MAX times its area
# (after the token blur that gives a blob about a token wider than the object). Monotone in n.
OBJECT_APPEARANCES = ("person", "vehicle")
OBJECT_GAIN_MAX = 3.0
OBJECT_HALF_TOKENS = 1.0
TOKEN_PX = 16


def object_gain(tokens: np.ndarray | float) -> np.ndarray:
    """The resolution curve: an object's response per unit of area against the tokens it covers."""
    n2 = np.square(np.asarray(tokens, np.float64))
    return 1.0 + (OBJECT_GAIN_MAX - 1.0) * n2 / (n2 + OBJECT_HALF_TOKENS ** 2)
# A class's other looks, patch by patch: a dry or dead lawn reads partly as bare soil, stained or
# weathered concrete as asphalt, wet sand as pavement, a gravel or green roof as ground. Which
# patches look atypical is fixed on the ground for an episode over a world (season, rain, the
# day's light), the same at every altitude; how they split is this table.
INSTANCE_LOOKS: dict[str, dict[str, float]] = {
    "lawn": {"bare_ground": 0.7, "tree": 0.3},
    "sports_field": {"bare_ground": 0.6, "lawn": 0.4},
    "bare_ground": {"paved": 0.5, "road": 0.3, "water": 0.2},
    "paved": {"road": 0.6, "bare_ground": 0.4},
    "parking": {"paved": 0.6, "road": 0.4},
    "road": {"paved": 0.6, "parking": 0.4},
    "flat_roof": {"paved": 0.5, "bare_ground": 0.3, "lawn": 0.2},
    "pitched_roof": {"flat_roof": 0.6, "bare_ground": 0.4},
    "tree": {"lawn": 0.5, "bare_ground": 0.5},
    "water": {"road": 0.6, "lawn": 0.4},
}
SUN_RATE_RAD_S = 2.0 * math.pi / 86400.0  # the sun's azimuth turns about 15 degrees an hour


@dataclass(frozen=True)
class PerceptionParams:
    """One profile of the simulated perception; ``noise`` scales every error strength in it."""

    name: str = "realistic"
    noise: float = 1.0
    """0: no confusions, context, flicker or shadows (the response table and token grid stay)."""
    logit_scale: float = 5.0
    """Logit per unit of affinity: CLIPSeg's spread between a matching and an unrelated prompt."""
    item_sharpness: float = ITEM_SHARPNESS
    confusion: float = 0.8
    """Largest share of an appearance read as its partners where the world field is high."""
    confusion_onset: float = 0.3
    """Field value (in its std) where misreading starts; it is full at onset + 1."""
    field_length_m: float = 20.0
    """Lattice spacing of the world fields; a second octave at 0.4 x this adds texture."""
    field_octaves_per_doubling: float = 0.7
    """How fast the misreading changes with altitude: lattice units per altitude doubling."""
    context_local: float = 0.25
    context_sigma_px: float = 24.0
    """Neighbourhood of the local context, Gaussian sigma in input pixels (1.5 tokens)."""
    context_global: float = 0.12
    flicker_logit: float = 0.2
    """Std (logits) of the smooth per-frame field, per prompt."""
    flicker_offset: float = 0.1
    """Std (logits) of each prompt's per-frame offset over the whole view."""
    shadow: float = 0.5
    """Share of a shadowed patch that reads as shadow."""
    sun_elevation_deg: float = 45.0
    """Mean sun elevation; each episode's is drawn uniform in +- `sun_elevation_spread_deg` of it."""
    sun_elevation_spread_deg: float = 20.0
    calibration_scale_spread: float = 0.2
    """Per-episode calibration: `logit_scale` times a factor drawn uniform in 1 +- this."""
    calibration_offset_logit: float = 0.4
    """Per-episode calibration: every positive prompt's logit moved by a draw uniform in +- this,
    which moves logit P(safe) by the same amount under either fusion."""
    instance_variation: float = 0.5
    """Largest share of a patch read as its class's other looks (dry grass, stained concrete...)."""
    instance_length_m: float = 25.0
    """Lattice spacing of the per-patch appearance field: about one lawn, lot or roof."""
    world_confusion_spread: float = 0.5
    """Log-normal sigma of each world's confusion partner weights and per-class confusion strength."""
    cell_px: int = 8
    """Side of the cells the appearance is counted on, input pixels (8: half a ViT token)."""
    token_sigma_px: float = 4.4
    """Token footprint, Gaussian sigma in input pixels (with the 8-px cells, about a 16-px box)."""
    fusion_grid_px: int = 88
    """Grid the fusion runs on before the upsample to 352 (352 = CLIPSeg's own output grid)."""

    def __post_init__(self) -> None:
        checks = {"noise": (0.0, 4.0), "logit_scale": (0.1, 50.0), "item_sharpness": (0.0, 50.0),
                  "confusion": (0.0, 0.95), "confusion_onset": (-3.0, 3.0), "field_length_m": (1.0, 1000.0),
                  "field_octaves_per_doubling": (0.0, 5.0), "context_local": (0.0, 0.6),
                  "context_sigma_px": (1.0, 200.0), "context_global": (0.0, 0.4), "flicker_logit": (0.0, 5.0),
                  "flicker_offset": (0.0, 5.0), "shadow": (0.0, 1.0), "sun_elevation_deg": (10.0, 90.0),
                  "sun_elevation_spread_deg": (0.0, 40.0), "calibration_scale_spread": (0.0, 0.6),
                  "calibration_offset_logit": (0.0, 3.0), "instance_variation": (0.0, 0.95),
                  "instance_length_m": (1.0, 1000.0), "world_confusion_spread": (0.0, 2.0),
                  "token_sigma_px": (0.0, 40.0)}
        for key, (lo, hi) in checks.items():
            validate.in_range(f"perception {self.name}: {key}", getattr(self, key), lo, hi)
        if self.cell_px not in CELL_SIZES_PX:
            raise ConfigError(f"perception {self.name}: cell_px must be one of {CELL_SIZES_PX}, got {self.cell_px!r}")
        if self.fusion_grid_px not in (44, 88, 176, 352):
            raise ConfigError(f"perception {self.name}: fusion_grid_px must be 44, 88, 176 or 352, "
                              f"got {self.fusion_grid_px!r}")

    def scaled(self) -> dict[str, float]:
        """The error strengths after ``noise`` (capped where a share must stay below 1)."""
        n = self.noise
        local, glob = self.context_local * n, self.context_global * n
        if local + glob > 0.8:  # a cell must keep most of its own look
            local, glob = 0.8 * local / (local + glob), 0.8 * glob / (local + glob)
        return {"confusion": min(0.95, self.confusion * n), "context_local": local, "context_global": glob,
                "flicker_logit": self.flicker_logit * n, "flicker_offset": self.flicker_offset * n,
                "shadow": min(1.0, self.shadow * n), "sun_elevation_spread_deg": self.sun_elevation_spread_deg * n,
                "calibration_scale_spread": min(0.9, self.calibration_scale_spread * n),
                "calibration_offset_logit": self.calibration_offset_logit * n,
                "instance_variation": min(0.95, self.instance_variation * n),
                "world_confusion_spread": self.world_confusion_spread * n}


# The profiles: `realistic` is calibrated on threshold statistics of the authors' logs and on
# PEACE's 57 % (see dovesei.perception_stats), on seeds apart from the reported ones.
PROFILES: dict[str, PerceptionParams] = {
    # clean: every error off, 2-px cells (no token grid) and confident logits: what the prompts
    # say about each appearance, nothing else.
    "clean": PerceptionParams(name="clean", logit_scale=15.0, cell_px=2, token_sigma_px=0.0, confusion=0.0,
                              context_local=0.0, context_global=0.0, flicker_logit=0.0, flicker_offset=0.0,
                              shadow=0.0, sun_elevation_spread_deg=0.0, calibration_scale_spread=0.0,
                              calibration_offset_logit=0.0, instance_variation=0.0, world_confusion_spread=0.0),
    "realistic": PerceptionParams(name="realistic"),
    "harsh": PerceptionParams(name="harsh", confusion=0.95, confusion_onset=-0.2, context_local=0.35,
                              context_global=0.2, flicker_logit=0.4, flicker_offset=0.2, shadow=0.7,
                              sun_elevation_spread_deg=25.0, calibration_scale_spread=0.3,
                              calibration_offset_logit=0.6, instance_variation=0.7, world_confusion_spread=0.7),
}
DEFAULT_PROFILE = "realistic"


def profile_params(name: str = DEFAULT_PROFILE, noise: float = 1.0) -> PerceptionParams:
    """The named profile at a noise scale (ConfigError naming the choices for a bad name)."""
    if name not in PROFILES:
        raise ConfigError(f"perception profile {name!r}: choose one of {', '.join(PROFILES)}")
    return dataclasses.replace(PROFILES[name], noise=noise)


@dataclass(frozen=True)
class View:
    """Where the camera looks: its optical axis on the ground (world metres, x east, y north;
    None when the frame does not say, and the world fields are then anchored to the image),
    altitude, horizontal FOV and heading (0 north, +pi/2 east)."""

    centre_world_m: tuple[float, float] | None
    alt_agl_m: float
    hfov_rad: float
    yaw_rad: float = 0.0
    world: str = ""
    """Which world (the sim's name for it): its confusions and per-episode draws are its own."""
    time_s: float = 0.0
    """The frame's time (sim seconds): the sun, and so the shadows, move with it."""


# --- seeded value noise in world coordinates ------------------------------------------------

_M1, _M2, _M3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)


def _hash_unit(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Uniform [-1, 1) from integer lattice coordinates and keys (splitmix64 finaliser).

    ``key`` is an int64 array broadcast against the coordinates (one key per field)."""
    with np.errstate(over="ignore"):
        h = (ix.astype(np.uint64) * _M1) ^ (iy.astype(np.uint64) * _M2) ^ (iz.astype(np.uint64) * _M3)
        h = h ^ ((key.astype(np.uint64) + np.uint64(0x632BE59BD9B4E019)) * _M2)  # broadcasts to (keys, points)
        h ^= h >> np.uint64(30)
        h *= _M2
        h ^= h >> np.uint64(27)
        h *= _M3
        h ^= h >> np.uint64(31)
    return (h >> np.uint64(11)).astype(np.float64) * (2.0 / 2.0**53) - 1.0


def _smoothstep(t: np.ndarray | float) -> np.ndarray | float:
    """3t^2 - 2t^3: the lattice weights' easing, flat at 0 and 1."""
    return t * t * (3.0 - 2.0 * t)


def _noise_octaves(x: np.ndarray, y: np.ndarray,
                   octaves: Sequence[tuple[float, float, np.ndarray, float]]) -> np.ndarray:
    """A sum of octaves of smooth noise on a unit lattice (trilinear with smoothstep weights) at
    points (x, y), one field per key: octave (length, z, keys, amplitude) reads the lattice at
    (x / length, y / length, z) with its own keys (as many as every other octave's) and adds
    amplitude x it. (len(keys),) + x.shape; one octave of amplitude 1 is about uniform in [-1, 1]."""
    n_octaves, n_keys, n = len(octaves), len(octaves[0][2]), x.size
    # Every octave's x and y as the rows of one array: each step below is one numpy call for all
    # (written into arrays made for them: np.stack costs as much as a few such steps).
    lengths = np.array([length for length, _, _, _ in octaves])[:, None]
    xy = np.empty((n_octaves, 2, n))  # (octave, axis, points)
    np.divide(x.reshape(-1), lengths, out=xy[:, 0])
    np.divide(y.reshape(-1), lengths, out=xy[:, 1])
    fxy = np.floor(xy)
    txy, ixy = _smoothstep(xy - fxy), fxy.astype(np.int64)
    lows, highs = ixy.min(axis=2).tolist(), ixy.max(axis=2).tolist()
    # corners: (octave, keys, 4, points), (dx, dy) = (0, 0), (1, 0), (0, 1), (1, 1).
    corners = np.empty((n_octaves, n_keys, 4, n))
    for o, ((length, z, keys, _), (ix, iy), (x0, y0), (x1, y1)) in enumerate(zip(octaves, ixy, lows, highs)):
        iz = math.floor(z)
        tz = _smoothstep(z - iz)
        nx, ny = x1 - x0 + 2, y1 - y0 + 2
        if nx * ny <= 8 * n:
            # Neighbouring points share corners (a view's 16 x 16 points cover about 10 x 10 lattice
            # cells): blend the two heights on the lattice around the points, then gather. At a whole
            # height (a ground field's first octave) the upper layer weighs 0 and the blend is the
            # lower layer itself, to the bit (hash values are never -0.0).
            window = (length, x0, y0, nx, ny)
            plane = _lattice(keys, iz, *window)
            if tz != 0.0:
                plane = (1.0 - tz) * plane + tz * _lattice(keys, iz + 1, *window)
            plane = plane.reshape(n_keys, -1)
            np.take(plane, ((iy - y0) * nx + (ix - x0))[None, :] + np.array([[0], [1], [nx], [nx + 1]]), axis=1,
                    out=corners[o], mode="clip")  # in range: "clip" only spares take a buffered copy
        else:
            # Points spread thinly over a large box: hash each point's own corners.
            key = keys[:, None]
            for c, (dx, dy) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
                corners[o, :, c] = ((1.0 - tz) * _hash_unit(ix + dx, iy + dy, np.int64(iz), key)
                                    + tz * _hash_unit(ix + dx, iy + dy, np.int64(iz + 1), key))
    w = np.empty((2,) + txy.shape)  # (d, octave, axis, points): the weight of the corner at +d along x, y
    np.subtract(1.0, txy, out=w[0])
    w[1] = txy
    w[:, :, 1] *= np.array([amplitude for _, _, _, amplitude in octaves])[:, None]
    weights = (w[:, None, :, 1] * w[None, :, :, 0]).reshape(4, n_octaves, n)
    return np.einsum("okcp,cop->kp", corners, weights).reshape((n_keys,) + x.shape)


# The hashed lattice is a pure function of (point, height, key), so it is kept across frames. Each
# height of each lattice spacing (a layer) keeps the region the view last needed, widened by a
# margin and snapped to whole blocks of lattice cells, with one row per key asked of it: the next
# views of a flight (which move a little) read it again, and a field that comes into view (the
# confusions in view change from frame to frame) hashes only its own row. A descent reads the same
# layers again as the height passes a whole lattice unit (a layer is one height, not a pair).
# The least recently used layer goes first (the dict's order is the order of use).
_LATTICE_BLOCK = 8
_LATTICE_MARGIN = 4
_LATTICE_CACHE_ENTRIES = 16
_LATTICE_CACHE_BYTES = 16 << 20
_LATTICE_PICKS = 64  # key arrays a layer remembers the rows of


@dataclass(frozen=True)
class _LatticeLayer:
    """One cached layer: hash values (keys, rows, columns) from lattice point (x0, y0). Replaced, not
    changed, when a key comes in: another thread may be reading it."""

    x0: int
    y0: int
    table: np.ndarray
    row_of: dict[int, int]  # key -> its index along the table's first axis
    # The indices of each key array asked for (by its bytes): a slice where they are consecutive
    # (a layer's first keys, and the same keys again: a view, no copy), else an index array.
    picks: dict[bytes, slice | np.ndarray] = dataclasses.field(default_factory=dict)


_lattice_cache: dict[tuple[float, int], _LatticeLayer] = {}


def _lattice(keys: np.ndarray, iz: int, spacing: float, x0: int, y0: int, nx: int, ny: int) -> np.ndarray:
    """(len(keys), ny, nx) hash values at lattice points (x0 + i, y0 + j, iz), read-only (often a view
    of the cache); ``spacing`` names the lattice (the fields of one spacing read about the same region)."""
    entry = (spacing, iz)
    layer = _lattice_cache.pop(entry, None)  # put back below as the most recently used
    if layer is None or not (layer.x0 <= x0 and layer.y0 <= y0 and x0 + nx <= layer.x0 + layer.table.shape[2]
                             and y0 + ny <= layer.y0 + layer.table.shape[1]):
        b, m = _LATTICE_BLOCK, _LATTICE_MARGIN
        rx, ry = (x0 - m) // b * b, (y0 - m) // b * b
        width, height = -(-(x0 + nx + m) // b) * b - rx, -(-(y0 + ny + m) // b) * b - ry
        layer = _LatticeLayer(rx, ry, np.empty((0, height, width)), {})
    pick = layer.picks.get(keys.tobytes())
    if pick is None:
        wanted = keys.tolist()
        new = [k for k in dict.fromkeys(wanted) if k not in layer.row_of]
        if new:
            _, height, width = layer.table.shape
            gx = np.arange(layer.x0, layer.x0 + width, dtype=np.int64)
            gy = np.arange(layer.y0, layer.y0 + height, dtype=np.int64)
            added = _hash_unit(gx[None, None, :], gy[None, :, None], np.int64(iz),
                               np.array(new, np.int64)[:, None, None])
            row_of = dict(layer.row_of)
            row_of.update((k, layer.table.shape[0] + i) for i, k in enumerate(new))
            table = np.concatenate([layer.table, added])
            table.flags.writeable = False
            layer = _LatticeLayer(layer.x0, layer.y0, table, row_of)
        rows = [layer.row_of[k] for k in wanted]
        pick = (slice(rows[0], rows[-1] + 1) if rows and rows == list(range(rows[0], rows[0] + len(rows)))
                else np.array(rows, np.intp))
        if len(layer.picks) >= _LATTICE_PICKS:
            layer.picks.clear()
        layer.picks[keys.tobytes()] = pick
        # Copies of the cache's contents: another thread may change it meanwhile.
        while (kept := list(_lattice_cache.values())) and (
                len(kept) >= _LATTICE_CACHE_ENTRIES or sum(t.table.nbytes for t in kept) > _LATTICE_CACHE_BYTES):
            _lattice_cache.pop(next(iter(_lattice_cache), None), None)
    _lattice_cache[entry] = layer
    return layer.table[pick, y0 - layer.y0:y0 - layer.y0 + ny, x0 - layer.x0:x0 - layer.x0 + nx]


# Two octaves of trilinear value noise have a std of about 0.33 (measured over 10^6 points);
# dividing by it makes `confusion_onset` read in standard deviations.
_FIELD_STD = 0.33


def world_field(east_m: np.ndarray, north_m: np.ndarray, alt_m: float, keys: np.ndarray,
                params: PerceptionParams) -> np.ndarray:
    """Seeded smooth fields over the ground and log-altitude, about unit std: (len(keys),) + east_m.shape."""
    z = math.log2(max(alt_m, 0.5)) * params.field_octaves_per_doubling
    return _field(east_m, north_m, z, keys, params.field_length_m)


def ground_field(east_m: np.ndarray, north_m: np.ndarray, keys: np.ndarray, length_m: float) -> np.ndarray:
    """`world_field` fixed on the ground (the same at every altitude): what the ground itself looks like."""
    return _field(east_m, north_m, 0.0, keys, length_m)


def _field(east_m: np.ndarray, north_m: np.ndarray, z: float, keys: np.ndarray, length: float) -> np.ndarray:
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    return _noise_octaves(east_m, north_m, ((length, z, keys, 0.75 / _FIELD_STD),
                                            (0.4 * length, z + 17.3, keys + 7, 0.45 / _FIELD_STD)))


# --- one episode over one world ---------------------------------------------------------------


def world_key(world: str) -> int:
    """A stable integer for a world's name (Python's own str hash changes between processes)."""
    return zlib.crc32(world.encode("utf-8"))


@dataclass(frozen=True)
class EpisodeDraw:
    """What one episode over one world gets; a pure function of (profile, seed, world).

    The calibration and the sun are drawn per (seed, world); the confusion table per world alone
    (the same imagery misleads alike in every episode; where it does is the seeded field's business).
    """

    logit_scale_factor: float
    positive_offset_logit: float
    sun_azimuth_rad: float  # at time 0; it turns at SUN_RATE_RAD_S
    sun_elevation_deg: float
    confusion: tuple[tuple[int, int, float], ...]  # (appearance, partner, share weight)


def episode_draw(params: PerceptionParams, seed: int, world: str) -> EpisodeDraw:
    """The per-episode calibration, sun and per-world confusions (see PerceptionParams)."""
    s = params.scaled()
    wk = world_key(world)
    rng = np.random.default_rng([seed, wk, 23])
    factor = 1.0 + rng.uniform(-1.0, 1.0) * s["calibration_scale_spread"]
    offset = rng.uniform(-1.0, 1.0) * s["calibration_offset_logit"]
    azimuth = rng.uniform(0.0, 2.0 * math.pi)
    elevation = float(np.clip(params.sun_elevation_deg + rng.uniform(-1.0, 1.0) * s["sun_elevation_spread_deg"],
                              10.0, 90.0))
    world_rng = np.random.default_rng([wk, 29])
    spread = s["world_confusion_spread"]
    pairs = []
    for a, partners in CONFUSIONS.items():
        # Each world misreads each class more or less often (capped: a cell keeps some of its look)
        # and towards its partners in its own proportions.
        strength = min(math.exp(0.5 * spread * world_rng.standard_normal()), 0.95 / max(s["confusion"], 1e-9))
        weights = {b: w * math.exp(spread * world_rng.standard_normal()) for b, w in partners.items()}
        total = sum(weights.values())
        pairs += [(INDEX[a], INDEX[b], strength * w / total) for b, w in weights.items()]
    return EpisodeDraw(float(factor), float(offset), float(azimuth), elevation, tuple(pairs))


def _field_keys(seed: int, world: str, ids: Iterable[int], tag: int = 0) -> np.ndarray:
    """Keys of the seeded fields: one per id, distinct per seed, world and use (tag)."""
    base = seed * 1_000_003 + (world_key(world) % 999_983) * 4099 + tag * 50_021
    return np.array([base + i for i in ids], dtype=np.int64)


# --- the model ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Classes:
    """A world's class table as the per-frame path needs it, built once per table.

    Label ids with the same appearance mix are interchangeable for the perception, so each is
    given the code of its distinct mix row: the frame's labels become codes with one lookup
    (`code_lut`), and the appearance fractions come from one histogram of (cell, code, shadowed).
    Codes are ordered by (off-world first, caster rank, mix row), so "at least rank r tall" is
    "code >= the rank's first code", read on the code image directly.
    """

    mix: np.ndarray  # (256, A) appearance weights per label id (255 = off_world)
    height_m: np.ndarray  # (256,) caster height per label id
    code_lut: np.ndarray  # (256,) uint8 (uint16 past 128 codes): label id -> code of its distinct mix row
    code_mix: np.ndarray  # (K, A) the mix of each code
    rank_first_code: np.ndarray  # (R + 2,) first code of each caster rank (rank 0 casts nothing; [R+1] = K)
    object_lut: np.ndarray  # (256,) uint8 per label id: bit i set when it is mostly OBJECT_APPEARANCES[i]
    rank_height_m: np.ndarray  # (R + 1,) height of each rank, [0] = 0


def _class_names(classes: Mapping[int, object] | Iterable[object]) -> dict[int, str]:
    """{id: name} from a mapping id -> (name, safe) / name, or entries with .id and .name.

    Only the names are kept: the judge's safe flag never enters the perception.
    """
    out: dict[int, str] = {}
    if isinstance(classes, Mapping):
        items = [(cid, e if isinstance(e, str) else (e[0] if isinstance(e, tuple) else getattr(e, "name", e)))
                 for cid, e in classes.items()]
    else:
        try:
            items = [(e.id, e.name) for e in classes]  # type: ignore[attr-defined]
        except (AttributeError, TypeError):
            raise ValueError("classes must map id -> name or (name, ...), or be entries with id and name") from None
    for cid, name in items:
        if isinstance(cid, bool) or not isinstance(cid, (int, np.integer)) or not 0 <= int(cid) <= 254:
            raise ValueError(f"class id {cid!r} must be an integer in 0..254 (255 marks outside the world)")
        if not isinstance(name, str):
            raise ValueError(f"class {cid} name must be a str, got {name!r}")
        out[int(cid)] = name
    return out


def _build_classes(names: Mapping[int, str]) -> _Classes:
    mix = np.zeros((256, A))
    mix[:, INDEX["clutter"]] = 1.0  # ids missing from the table: something, nobody says what
    for cid, name in names.items():
        mix[cid] = 0.0
        for app, w in appearance_mix(name).items():
            mix[cid, INDEX[app]] = w
    mix[OFF_WORLD_LABEL] = 0.0
    mix[OFF_WORLD_LABEL, INDEX["off_world"]] = 1.0
    heights = np.zeros(A)
    for app, h in CASTER_HEIGHT_M.items():
        heights[INDEX[app]] = h
    height_m = mix @ heights
    # Heights under half a metre cast nothing (a lawn's mix may carry a little tree).
    rank_height_m = np.concatenate([[0.0], np.unique(height_m[height_m > 0.5])])
    rank = np.searchsorted(rank_height_m, np.where(height_m > 0.5, height_m, 0.0))
    # Codes ordered by (off-world first, caster rank, mix row): "at least rank r" is a code range.
    rows = np.concatenate([(np.arange(256) != OFF_WORLD_LABEL)[:, None], rank[:, None], mix], axis=1)
    uniq, code = np.unique(rows, axis=0, return_inverse=True)
    rank_first = np.searchsorted(uniq[:, 1], np.arange(rank_height_m.size + 1), side="left")
    rank_first[0] = 1  # code 0 is off-world, never lit nor shaded
    objects = np.zeros(256, np.uint8)
    for i, app in enumerate(OBJECT_APPEARANCES):
        objects |= (mix[:, INDEX[app]] >= 0.5).astype(np.uint8) << i
    code = code.reshape(-1).astype(np.uint8 if 2 * uniq.shape[0] <= 256 else np.uint16)
    return _Classes(mix=mix, height_m=height_m, code_lut=code, code_mix=uniq[:, 2:],
                    rank_first_code=rank_first.astype(np.int64), rank_height_m=rank_height_m, object_lut=objects)


class SimPerception:
    """Truth labels + view + prompts -> prompt logits and P(safe), CLIPSeg-like. Test instrument."""

    def __init__(self, params: PerceptionParams = PROFILES[DEFAULT_PROFILE], seed: int = 0) -> None:
        if not isinstance(params, PerceptionParams):
            raise ConfigError(f"params must be PerceptionParams, got {type(params).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed must be a non-negative int, got {seed!r}")
        self.params, self.seed = params, int(seed)
        # Each frame allocates and frees a few MB of arrays: without this, glibc gives much of it
        # back to the system and page-faults it in again the next frame (a quarter of the CPU or more).
        heap.keep_freed_memory()
        self._strength = params.scaled()
        self._classes: dict[tuple, _Classes] = {}
        self._responses: dict[str, np.ndarray] = {}
        self._draws: dict[str, EpisodeDraw] = {}
        self.grid = INPUT_PX // params.cell_px
        # Each input pixel's cell row and column (8-bit images, as OpenCV's histogram counts them).
        cell_of = (np.arange(INPUT_PX) // params.cell_px).astype(np.uint8)
        self._cell_row = np.ascontiguousarray(np.broadcast_to(cell_of[:, None], (INPUT_PX, INPUT_PX)))
        self._cell_col = np.ascontiguousarray(np.broadcast_to(cell_of[None, :], (INPUT_PX, INPUT_PX)))

    def describe(self) -> str:
        return f"SIMULATED perception profile={self.params.name} noise={self.params.noise:g} seed={self.seed}"

    def draw(self, world: str = "") -> EpisodeDraw:
        """This episode's calibration, sun and confusions over `world` (cached)."""
        d = self._draws.get(world)
        if d is None:
            if len(self._draws) >= 16:
                self._draws.clear()
            d = self._draws[world] = episode_draw(self.params, self.seed, world)
            log.info("simulated perception over %r, seed %d: logit scale x%.3f, positive offset %+.3f logit, "
                     "sun elevation %.0f deg", world, self.seed, d.logit_scale_factor, d.positive_offset_logit,
                     d.sun_elevation_deg)
        return d

    def responses(self, prompts: PromptSet) -> np.ndarray:
        """(A, P) logits of a pure patch of each appearance for each prompt (cached per set)."""
        r = self._responses.get(prompts.set_id)
        if r is None:
            if len(self._responses) >= 16:
                self._responses.clear()
            r = self.params.logit_scale * response_matrix(prompts, self.params.item_sharpness)
            self._responses[prompts.set_id] = r
        return r

    def _tables(self, classes: Mapping[int, object] | Iterable[object]) -> _Classes:
        names = _class_names(classes)
        key = tuple(sorted(names.items()))
        tables = self._classes.get(key)
        if tables is None:
            if len(self._classes) >= 8:
                self._classes.clear()
            tables = self._classes[key] = _build_classes(names)
            log.info("simulated perception appearances: %s", "; ".join(
                f"{cid}:{name}->" + "+".join(f"{APPEARANCES[j]}" for j in np.flatnonzero(tables.mix[cid] > 0))
                for cid, name in sorted(names.items())))
        return tables

    # --- one frame ---------------------------------------------------------------------

    def fractions(self, labels: np.ndarray, classes: Mapping[int, object] | Iterable[object],
                  view: View) -> np.ndarray:
        """(grid, grid, A) appearance fractions per cell, shadows included, before any error."""
        return self._fractions(_input_labels(labels), self._tables(classes), view, labels.shape)

    def _fractions(self, lab: np.ndarray, tables: _Classes, view: View, frame_shape: tuple[int, int],
                   dtype: type = np.float64) -> np.ndarray:
        """`fractions` of input labels (352 x 352 uint8) with their class tables, in ``dtype``."""
        k = tables.code_mix.shape[0]
        # Each pixel's code (its class's mix row, + k when shadowed), then one histogram per cell.
        code = cv2.LUT(lab, tables.code_lut) if tables.code_lut.dtype == np.uint8 else tables.code_lut[lab]
        if self._strength["shadow"] > 0:
            cv2.add(code, k, dst=code, mask=self._shadow_mask(code, tables, view, frame_shape))
        n_cells = self.grid * self.grid
        shadow_mix = (1.0 - self._strength["shadow"]) * tables.code_mix
        shadow_mix[:, INDEX["shadow"]] += self._strength["shadow"]
        mix = np.concatenate([tables.code_mix, shadow_mix])  # (2k, A): lit codes, then shaded
        if n_cells * 2 * k > 1 << 18:
            # Fine cells (the clean profile's 2 px): count only the codes in view, not a mostly
            # empty (cells x every code) table.
            if code.dtype == np.uint8:  # OpenCV's histogram and lookup: several times numpy's speed
                present = np.flatnonzero(cv2.calcHist([code], [0], None, [2 * k], [0, 2 * k]).reshape(-1))
                remap = np.zeros(256, np.uint8)
                remap[present] = np.arange(present.size)
                code = cv2.LUT(code, remap)
            else:
                present = np.flatnonzero(np.bincount(code.reshape(-1), minlength=2 * k))
                remap = np.zeros(2 * k, np.uint8 if present.size <= 256 else code.dtype)
                remap[present] = np.arange(present.size)
                code = remap[code]
            mix = mix[present]
        m, grid = mix.shape[0], self.grid
        if code.dtype == np.uint8:
            # OpenCV counts 8-bit images through lookup tables: ~1.4x numpy's bincount of a
            # (cell, code) key, and exact (float32 counts of at most 352 x 352).
            counts = cv2.calcHist([self._cell_row, self._cell_col, code], [0, 1, 2], None, [grid, grid, m],
                                  [0, grid, 0, grid, 0, m])
        else:  # more than 256 codes in view
            cell = self._cell_row.astype(np.intp) * grid + self._cell_col
            counts = np.bincount((cell * m + code).reshape(-1), minlength=n_cells * m)
        frac = _rows_product(counts.reshape(n_cells, m), mix.astype(dtype, copy=False))
        frac /= dtype(self.params.cell_px ** 2)
        return frac.reshape(grid, grid, A)

    def logits(self, labels: np.ndarray, classes: Mapping[int, object] | Iterable[object], view: View,
               frame_seq: int, prompts: PromptSet) -> tuple[np.ndarray, np.ndarray]:
        """(P, grid, grid) prompt logits and the (grid, grid) in-world share of each cell."""
        out, in_world = self._logits_hwp(labels, classes, view, frame_seq, prompts)
        return np.ascontiguousarray(out.transpose(2, 0, 1)), in_world

    def _logits_hwp(self, labels: np.ndarray, classes: Mapping[int, object] | Iterable[object], view: View,
                    frame_seq: int, prompts: PromptSet) -> tuple[np.ndarray, np.ndarray]:
        """`logits` with the prompt axis last (grid, grid, P), as OpenCV resizes it."""
        frame_seq = _check_seq(frame_seq)
        draw = self.draw(view.world)
        lab, tables = _input_labels(labels), self._tables(classes)
        # float32 from the counts on: float64 would only carry digits the float32 logits drop.
        g = self._fractions(lab, tables, view, labels.shape, np.float32)
        in_world = 1.0 - g[..., INDEX["off_world"]]
        self._weigh_objects(g, lab, tables)
        g /= np.maximum(cv2.reduce(g.reshape(-1, A), 1, cv2.REDUCE_SUM).reshape(self.grid, self.grid, 1), 1e-12)
        s = self._strength
        if s["instance_variation"] > 0 or s["confusion"] > 0:
            points = self.cell_world_m(view, FIELD_GRID, labels.shape)  # where the world fields are read
        if s["instance_variation"] > 0:
            g = self._instance_looks(g, view, points)
        if self.params.token_sigma_px > 0:
            sigma = self.params.token_sigma_px / self.params.cell_px
            g = cv2.GaussianBlur(g, (0, 0), sigma)
        if s["confusion"] > 0:
            g = self._confuse(g, view, points, draw)
        if s["context_local"] > 0 or s["context_global"] > 0:
            near = cv2.GaussianBlur(g, (0, 0), self.params.context_sigma_px / self.params.cell_px)
            # In place: g is this frame's own array by now.
            near *= np.float32(s["context_local"])
            near += np.float32(s["context_global"]) * _over_cells(g, cv2.REDUCE_AVG)
            g *= np.float32(1.0 - s["context_local"] - s["context_global"])
            g += near
        grid = self.grid
        # The episode's calibration: all logits scaled alike (in the response table), the positives
        # moved against the rest (with the flicker's per-prompt offsets, one pass over the logits).
        responses = self.responses(prompts) * draw.logit_scale_factor
        out = _rows_product(g.reshape(-1, A), responses.astype(np.float32)).reshape(grid, grid, -1)
        offset = np.zeros(out.shape[2])
        offset[:prompts.n_positive] = draw.positive_offset_logit
        if s["flicker_logit"] > 0 or s["flicker_offset"] > 0:
            rng = np.random.default_rng([self.seed, 11, frame_seq])
            n_p = out.shape[2]
            field = rng.standard_normal((6, 6, n_p)).astype(np.float32) * s["flicker_logit"]
            out += cv2.resize(field, (grid, grid), interpolation=cv2.INTER_CUBIC).reshape(grid, grid, n_p)
            offset += rng.standard_normal(n_p) * s["flicker_offset"]
        if offset.any():
            out += offset.astype(np.float32)
        return out, in_world

    def safe_probability(self, labels: np.ndarray, classes: Mapping[int, object] | Iterable[object], view: View,
                         frame_seq: int, prompts: PromptSet, fusion: FusionConfig = FusionConfig(),
                         out_size: tuple[int, int] | None = None) -> np.ndarray:
        """P(safe) float32 in [0, 1] at ``out_size`` (height, width; default the labels' size)."""
        logits, in_world = self._logits_hwp(labels, classes, view, frame_seq, prompts)
        grid = max(self.params.fusion_grid_px, self.grid)
        if grid != self.grid:
            logits = cv2.resize(logits, (grid, grid), interpolation=cv2.INTER_LINEAR).reshape(grid, grid, -1)
        # The fusion reads prompt planes: OpenCV's transpose of (pixels, P) is ~4x numpy's copy.
        up = cv2.transpose(logits.reshape(grid * grid, -1)).reshape(-1, grid, grid)
        if grid == INPUT_PX:
            prob = fuse(up, prompts.n_positive, fusion.mode, fusion.temperature, fusion.blur_px)
        else:
            # Fuse on the coarse grid, then upsample and box-blur at CLIPSeg's 352: the logits are
            # smooth below a token, so this is the exact path to within ~0.01 at a tenth of its cost.
            prob = fuse(up, prompts.n_positive, fusion.mode, fusion.temperature, 1)
            prob = blur_prob(cv2.resize(prob, (INPUT_PX, INPUT_PX), interpolation=cv2.INTER_LINEAR), fusion.blur_px)
        if in_world.min() < 1.0:  # most frames lie wholly inside the world: nothing to scale
            prob *= cv2.resize(in_world, (INPUT_PX, INPUT_PX), interpolation=cv2.INTER_LINEAR)
        height_px, width_px = labels.shape if out_size is None else out_size
        if (height_px, width_px) != prob.shape:
            prob = cv2.resize(prob, (int(width_px), int(height_px)), interpolation=cv2.INTER_LINEAR)
        return _clip_unit(prob, out=prob)

    def _weigh_objects(self, frac: np.ndarray, lab: np.ndarray, tables: _Classes) -> None:
        """Weighs person and vehicle appearances in ``frac`` (grid, grid, A), in place: in a cell
        with object pixels by the mean `object_gain` of those pixels (each connected object by its
        own size in tokens of the 352 px input), elsewhere by 1."""
        if not tables.object_lut.any():
            return
        objects = cv2.LUT(lab, tables.object_lut)
        # Components only within the box of the object pixels (often a small part of the view).
        bx, by, bw, bh = cv2.boundingRect(objects)
        n_cells, cell_px = self.grid * self.grid, self.params.cell_px
        for i, app in enumerate(OBJECT_APPEARANCES):
            mask = cv2.bitwise_and(objects[by:by + bh, bx:bx + bw], 1 << i)
            x0, y0, w, h = cv2.boundingRect(mask)
            if not w:
                continue
            mask = mask[y0:y0 + h, x0:x0 + w]
            n, comp = cv2.connectedComponents(mask, connectivity=8)
            # Only the object pixels (a few % of the box) are read from here on, in the raster
            # order findNonZero lists them in, so the sums add in the same order as over the box.
            xs, ys = cv2.findNonZero(mask).reshape(-1, 2).T
            comp_on = comp[ys, xs]
            # Each component's area from its pixels (OpenCV's stats cost 4x the labelling).
            gain = object_gain(np.bincount(comp_on, minlength=n) / float(TOKEN_PX * TOKEN_PX))
            cells = (ys + (by + y0)) // cell_px * self.grid + (xs + (bx + x0)) // cell_px
            total = np.bincount(cells, weights=gain[comp_on], minlength=n_cells)
            count = np.bincount(cells, minlength=n_cells)
            hit = np.flatnonzero(count)  # the cells with object pixels; the others keep their weight
            frac.reshape(n_cells, A)[hit, INDEX[app]] *= total[hit] / count[hit]

    # --- errors ------------------------------------------------------------------------

    def cell_world_m(self, view: View, n: int, frame_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """World (east, north) of an n x n grid of points spread like cell centres over the view."""
        height_px, width_px = frame_shape
        half_w_m = footprint.half_width_m(view.alt_agl_m, view.hfov_rad)
        half_h_m = half_w_m * height_px / width_px
        u = (np.arange(n) + 0.5) / n * 2.0 - 1.0  # -1 left/top .. +1 right/bottom
        right, forward = (u * half_w_m)[None, :], (-u * half_h_m)[:, None]  # broadcast to n x n below
        c, s = math.cos(view.yaw_rad), math.sin(view.yaw_rad)
        cx, cy = view.centre_world_m if view.centre_world_m is not None else (0.0, 0.0)
        return cx + c * right + s * forward, cy + c * forward - s * right

    def _confuse(self, g: np.ndarray, view: View, points: tuple[np.ndarray, np.ndarray],
                 draw: EpisodeDraw) -> np.ndarray:
        """Each appearance read partly as its partners where the world's seeded field is high;
        ``points``: the (east, north) of the FIELD_GRID points (`cell_world_m`)."""
        top = _over_cells(g, cv2.REDUCE_MAX)
        # Only appearances in view need their fields (not in view: nothing to misread).
        pairs = [(a, b, w) for a, b, w in draw.confusion if top[a] >= 0.02]
        if not pairs:
            return g.copy()
        keys = _field_keys(self.seed, view.world, (a * 97 + b for a, b, _ in pairs))
        z = world_field(*points, view.alt_agl_m, keys, self.params)
        pick, move = _move_tables(tuple((i, a, b, w) for i, (a, b, w) in enumerate(pairs)), len(pairs))
        return _moved(g, self._on_grid(z - self.params.confusion_onset), pick,
                      np.float32(self._strength["confusion"]) * move)

    def _instance_looks(self, g: np.ndarray, view: View, points: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Atypical patches read partly as their class's other looks (INSTANCE_LOOKS), fixed on the ground;
        ``points`` as in `_confuse`."""
        top = _over_cells(g, cv2.REDUCE_MAX)
        sources = [a for a in INSTANCE_LOOKS if top[INDEX[a]] >= 0.02]
        if not sources:
            return g
        # One field per class (how atypical each patch of it is); its looks share the moved part.
        z = ground_field(*points, _field_keys(self.seed, view.world, (INDEX[a] for a in sources), tag=1),
                         self.params.instance_length_m)
        pick, move = _move_tables(tuple((i, INDEX[a], INDEX[b], w) for i, a in enumerate(sources)
                                        for b, w in INSTANCE_LOOKS[a].items()), len(sources))
        return _moved(g, self._on_grid(z), pick, np.float32(self._strength["instance_variation"]) * move)

    def _on_grid(self, z: np.ndarray) -> np.ndarray:
        """(n, F, F) fields at FIELD_GRID points -> (grid, grid, n) float32 on the cells."""
        n, f = z.shape[0], z.shape[1]
        z = cv2.transpose(z.reshape(n, -1).astype(np.float32)).reshape(f, f, n)  # OpenCV's: ~4x numpy's copy
        return cv2.resize(z, (self.grid, self.grid), interpolation=cv2.INTER_LINEAR).reshape(self.grid, self.grid, -1)

    def _shadow_mask(self, code: np.ndarray, tables: _Classes, view: View,
                     frame_shape: tuple[int, int]) -> np.ndarray:
        """Input pixels in the shadow of something taller (uint8 255, else 0), sun fixed in the world.

        Each caster height in view (a rank: a range of codes) throws every pixel at least that tall
        half and all of its shadow length away from the sun, onto in-world ground lower than it: a
        pixel is shaded where the tallest rank whose shadow reaches it is above its own, that is
        where that rank's first code is above the pixel's code.
        """
        first = tables.rank_first_code.tolist()
        top = cv2.minMaxLoc(code)[1]
        ranks = range(1, bisect.bisect_right(first, top))  # those with a code <= top
        # Pixels at least each rank tall, as the rank's first code (0 elsewhere), and how many.
        casters = [cv2.threshold(code, first[r] - 1.0, first[r], cv2.THRESH_BINARY)[1] for r in ranks]
        at_least = [cv2.countNonZero(c) for c in casters] + [0]
        reach = np.zeros_like(code)  # the first code of the tallest rank whose shadow reaches each pixel
        frame_h, frame_w = frame_shape
        m_per_px_x = footprint.metres_per_px(view.alt_agl_m, view.hfov_rad, INPUT_PX)
        m_per_px_y = m_per_px_x * frame_h / frame_w
        # Shadows fall away from the sun; world (east, north) -> image (right, forward).
        draw = self.draw(view.world)
        azimuth = draw.sun_azimuth_rad + SUN_RATE_RAD_S * view.time_s
        east, north = -math.sin(azimuth), -math.cos(azimuth)
        c, s = math.cos(view.yaw_rad), math.sin(view.yaw_rad)
        right, forward = c * east - s * north, s * east + c * north
        per_m = 1.0 / math.tan(math.radians(draw.sun_elevation_deg))
        for r in ranks:
            # Only heights in view cast: a rank with no pixel of its own adds no shadow length.
            if at_least[r - 1] == at_least[r]:
                continue
            length_m = float(tables.rank_height_m[r]) * per_m
            for frac in (0.5, 1.0):
                dx = int(round(right * length_m * frac / m_per_px_x))
                dy = int(round(-forward * length_m * frac / m_per_px_y))
                _max_shifted(reach, casters[r - 1], dx, dy)
        # 255 where shaded (OpenCV's mask): reached by a taller rank, and in the world (code 0 is off it).
        return cv2.bitwise_and(cv2.compare(reach, code, cv2.CMP_GT), cv2.compare(code, 0, cv2.CMP_NE))


def _clip_unit(a: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """clip(a, 0, 1) of a 2-D float32 array with OpenCV's thresholds (exact; a few times faster
    than np.clip at these sizes), into ``out`` (``a`` itself for in place; None: a new array)."""
    out = cv2.threshold(a, 1.0, 1.0, cv2.THRESH_TRUNC, dst=out)[1]
    return cv2.threshold(out, 0.0, 0.0, cv2.THRESH_TOZERO, dst=out)[1]


def _moved(g: np.ndarray, excess: np.ndarray, pick: np.ndarray, move: np.ndarray) -> np.ndarray:
    """g (float32) with part of each field's source appearance handed to its partners.

    Per field (a channel of ``excess``) and cell, clip(excess, 0, 1) of the source's fraction
    moves as the field's row of ``move`` says; every field reads the same g, so that is two float32
    products: with ``pick`` (the source columns) and with ``move`` (`_move_tables`), added to g.
    """
    share = _clip_unit(excess.reshape(excess.shape[0], -1)).reshape(excess.shape)
    share *= g @ pick
    return g + share @ move


@functools.lru_cache(maxsize=64)
def _move_tables(moves: tuple[tuple[int, int, int, float], ...], n_fields: int) -> tuple[np.ndarray, np.ndarray]:
    """Read-only float32 tables of moves (field, source, partner, weight), all of a field's moves
    from one source: (A, fields) with 1 at each field's source (a product with it picks the source
    columns: exact, and faster than indexing the short last axis) and (fields, A) with each move's
    weight at its partner and taken from its source."""
    pick = np.zeros((A, n_fields), np.float32)
    move = np.zeros((n_fields, A), np.float32)
    for field, source, partner, weight in moves:
        pick[source, field] = 1.0
        move[field, source] -= weight
        move[field, partner] += weight
    pick.flags.writeable = move.flags.writeable = False
    return pick, move


# OpenBLAS spreads a product of 2^19 multiply-adds (rows x inner x columns) or more over threads,
# which costs several times the CPU time it saves (the perception is budgeted one core): measured
# over 44 x 44 cells, (cells x 38 codes) @ (38 codes x 15 appearances) took 0.7-4 ms of CPU on a
# loaded machine in one block, 77 us in blocks under 2^19 (a world with many classes has that many
# codes; the clean profile has 176 x 176 cells).
_PRODUCT_MACS = 1 << 19


def _rows_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b in b's dtype, for a 2-D ``a`` of many rows, taken a block of rows at a time, each block
    small enough to stay on one thread (`_PRODUCT_MACS`)."""
    out = np.empty((a.shape[0], b.shape[1]), b.dtype)
    rows = max(1, (_PRODUCT_MACS - 1) // (a.shape[1] * b.shape[1]))
    for i in range(0, a.shape[0], rows):
        np.matmul(a[i:i + rows].astype(b.dtype, copy=False), b, out=out[i:i + rows])
    return out


def _over_cells(g: np.ndarray, op: int) -> np.ndarray:
    """(A,) the max or mean (``op``: cv2.REDUCE_MAX, REDUCE_AVG) of a (grid, grid, A) map over its
    cells; OpenCV's reduce, as numpy's is several times slower over a short last axis."""
    return cv2.reduce(g.reshape(-1, g.shape[2]), 0, op).reshape(-1)


def _max_shifted(out: np.ndarray, img: np.ndarray, dx: int, dy: int) -> None:
    """out = max(out, img moved by dx right, dy down), in place; nothing moves in at the edges."""
    h, w = img.shape
    if abs(dx) >= w or abs(dy) >= h:
        return
    dst = (slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0)))
    src = (slice(max(-dy, 0), h - max(dy, 0)), slice(max(-dx, 0), w - max(dx, 0)))
    cv2.max(out[dst], img[src], dst=out[dst])


def _input_labels(labels: object) -> np.ndarray:
    if not isinstance(labels, np.ndarray):
        raise ValueError(f"truth labels must be a numpy array, got {type(labels).__name__}")
    if labels.ndim != 2 or min(labels.shape) < 1:
        raise ValueError(f"truth labels must be a non-empty HxW array, got shape {labels.shape}")
    if labels.dtype != np.uint8:
        if not np.issubdtype(labels.dtype, np.integer) or labels.min() < 0 or labels.max() > 255:
            raise ValueError(f"truth labels must hold class ids in 0..255, got dtype {labels.dtype}")
        labels = labels.astype(np.uint8)
    if labels.shape != (INPUT_PX, INPUT_PX):
        # CLIPSeg resizes every frame to 352x352 whatever its aspect; labels must not be blended.
        labels = cv2.resize(labels, (INPUT_PX, INPUT_PX), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(labels)


def _check_seq(frame_seq: object) -> int:
    if isinstance(frame_seq, bool) or not isinstance(frame_seq, (int, np.integer)) or frame_seq < 0:
        raise ValueError(f"frame_seq must be a non-negative int, got {frame_seq!r}")
    return int(frame_seq)
