"""The `clearance` policy's thresholds, read off the scene instead of fixed in P.

CLIPSeg's absolute P moves with scene, light, season and prompt set (in PEACE the prompt wording
alone moved safe-zone identification from 57 % to 92 %); what a scene keeps is its order: landable
ground reads above the roofs, roads and water around it. So every threshold the policy applies
comes from the fused log-odds of its own map of the search area (the looks from high up, never
decayed), through three numbers:

    best     the highest mean over a clearance disk whose cells are all known: the best ground
             the scene has shown, at the size a landing needs (a mean over ~40 cells, so one
             noisy cell cannot set it)
    typical  the median cell: what most of the scene reads
    noise    how much a cell scatters from its neighbours (robust), for scenes of one class

    contrast = best - typical
    spot     a cell of the working map counts as safe at or above
             best - max(spot_frac x contrast, spot_z x that map's own per-cell noise,
                        level_slack_frac x (best - floor))
    gate     a disk's promise from high up must reach
             best - max(gate_frac x contrast, spot_z x noise, level_slack_frac x (best - floor))
    probes   the gate's level; during the top pass probe_now_frac instead of gate_frac

Below spot_z x noise of contrast the scene is one class (the best of 10^4 disks of one Gaussian
class stands ~4 sigma above its median): nothing in it reads better or worse than the rest, the
median is its level, and every threshold is the floor (the class is safe when it reads above
even odds; people and cars on it are still the dips the policy deepens).
    dips     deepened beyond dip_floor_frac x contrast

The last term keeps a scene of one material whose patches read a little apart (wet and dry sand,
gravel in the sand: a contrast of a few tenths) from being taken for two classes with a threshold
in the middle of the better one: a cell whose margin over even odds is within level_slack_frac of
the best disk's reads as confidently safe as the best does, whatever the contrast.

Each is a maximum, a median or a robust spread of the map, so a recalibration logit P' = a logit P
(a > 0) moves every threshold with the map and the decisions stay the same (up to the clip of
P at the wire's resolution); an offset b moves them too, except where a threshold is measured from
the floor (the floor itself, and the level_slack_frac term). The floor is log-odds 0 (P = 0.5):
when even the scene's level reads below it, the segmenter itself finds nothing in the scene more
likely safe than not, and nothing here is safe; no threshold is ever below it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.controller.policies.clearance.config import ClearanceConfig

NOTHING_SAFE = math.inf  # a threshold no log-odds meets


@dataclass(frozen=True)
class SceneLevels:
    """Thresholds in log-odds for one scene, and the levels they came from (for reports)."""

    gate_logit: float  # the promise from high up a spot needs
    probe_logit: float  # the promise an area needs to be probed
    probe_now_logit: float  # ... during the top pass
    dip_floor_logit: float  # dips shallower than this are the map's own ripple
    best_logit: float  # the best fully known disk's mean
    typical_logit: float  # the median known cell
    noise_logit: float  # the map's per-cell scatter
    cells: int  # how many known cells the levels were read from
    floor_logit: float = 0.0
    level_logit: float = -math.inf  # what safe ground reads here: the best, or the median of one class
    contrast_logit: float = 0.0  # best - typical (0: one class)

    @property
    def nothing_safe(self) -> bool:
        return math.isinf(self.gate_logit)

    def spot_for(self, noise_logit: float, cfg: ClearanceConfig) -> float:
        """The spot threshold for a map whose cells scatter by `noise_logit` (a low, fine map is
        noisier per cell than the smoothed looks from high up)."""
        if self.nothing_safe:
            return NOTHING_SAFE
        if self.contrast_logit <= 0.0:  # one class
            return self.floor_logit
        return below(self.level_logit, self.floor_logit, cfg.spot_frac * self.contrast_logit,
                     cfg.spot_z * noise_logit, cfg)


def below(top: float, floor: float, contrast_slack: float, noise_slack: float, cfg: ClearanceConfig) -> float:
    """A threshold under the level `top`: the widest of the contrast's and the noise's slack and
    level_slack_frac of the level's margin over the floor, never below the floor."""
    return max(floor, top - max(contrast_slack, noise_slack, cfg.level_slack_frac * (top - floor)))


def _nothing(cells: int, floor: float, best: float = -math.inf, typical: float = 0.0, noise: float = 0.0) -> SceneLevels:
    return SceneLevels(NOTHING_SAFE, NOTHING_SAFE, NOTHING_SAFE, 0.0, best, typical, noise, cells, floor)


def levels_from(mean: np.ndarray, known: np.ndarray, cfg: ClearanceConfig, cell_m: float) -> SceneLevels:
    """The scene's levels from a map of fused log-odds (`mean`, float32) and where it is known."""
    floor = cfg.scene_floor_logit
    cells = int(known.sum())
    r = max(1, int(round(cfg.required_clearance_m / cell_m)))
    if cells < (2 * r + 1) ** 2:  # too little seen to hold a single disk
        return _nothing(cells, floor)
    k = known.astype(np.float32)
    m = np.where(known, mean, np.float32(0.0)).astype(np.float32)
    size = (2 * r + 1, 2 * r + 1)
    num = cv2.blur(m, size, borderType=cv2.BORDER_CONSTANT)
    den = cv2.blur(k, size, borderType=cv2.BORDER_CONSTANT)
    full = den > 0.999  # every cell of the disk known (no unknown ground averaged in)
    if not full.any():
        return _nothing(cells, floor)
    best = float((num[full] / den[full]).max())
    # The median and the noise from every other row and column (a quarter of the cells: both are
    # robust statistics of thousands of cells, the best disk is not).
    typical = float(np.median(mean[::2, ::2][known[::2, ::2]]))
    noise = fine_noise(mean[::2, ::2], known[::2, ::2])
    spread = cfg.spot_z * noise
    contrast = best - typical
    top = best
    if contrast < spread:  # one class: its median is what it reads, the floor what it needs
        top, contrast, spread = typical, 0.0, math.inf
    if top < floor:
        return _nothing(cells, floor, best, typical, noise)

    def level(frac: float) -> float:
        return below(top, floor, frac * contrast, spread, cfg)

    gate = level(cfg.gate_frac)
    # A probe goes only where a spot could pass the gate: the probe threshold is the gate's.
    return SceneLevels(gate_logit=gate, probe_logit=gate, probe_now_logit=max(level(cfg.probe_now_frac), gate),
                       dip_floor_logit=cfg.dip_floor_frac * contrast, best_logit=best, typical_logit=typical,
                       noise_logit=noise, cells=cells, floor_logit=floor, level_logit=top, contrast_logit=contrast)


def fine_noise(mean: np.ndarray, known: np.ndarray) -> float:
    """How much known cells scatter from their neighbours, in log-odds: 1.4826 x the median absolute
    difference from the 3 x 3 mean (robust: edges between classes are few), 0 with too few cells.
    Scales with any recalibration a logit P + b."""
    k = known.astype(np.float32)
    num = cv2.blur(np.where(known, mean, np.float32(0.0)).astype(np.float32), (3, 3), borderType=cv2.BORDER_CONSTANT)
    den = cv2.blur(k, (3, 3), borderType=cv2.BORDER_CONSTANT)
    inner = known & (den > 0.999)
    if int(inner.sum()) < 16:
        return 0.0
    diff = mean[inner] - num[inner] / den[inner]
    # A cell differs from a 3 x 3 mean that includes it by 8/9 of its own deviation.
    return 1.4826 * float(np.median(np.abs(diff))) * 9.0 / 8.0


def map_levels(gmap, cfg: ClearanceConfig, stride: int = 2) -> SceneLevels:
    """The levels of a GroundMap's known cells (looks >= looks_min), every `stride`-th row and
    column (the levels move slowly; a quarter of a 750-cell map is plenty and four times cheaper)."""
    mean, known = known_mean(gmap, cfg, stride)
    return levels_from(mean, known, cfg, gmap.cell_m * stride)


def known_mean(gmap, cfg: ClearanceConfig, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A map's fused log-odds and where they are known (looks >= looks_min)."""
    looks = gmap.looks[::stride, ::stride]
    known = looks >= np.float32(cfg.looks_min)
    mean = np.divide(gmap.evidence[::stride, ::stride], looks, out=np.zeros(looks.shape, np.float32), where=known)
    return mean, known


def sigmoid(logit: float) -> float:
    """P for a log-odds threshold (1 for NOTHING_SAFE; 0 far below, where exp would overflow)."""
    if math.isinf(logit):
        return 1.0 if logit > 0 else 0.0
    if logit < -700.0:
        return 0.0
    return 1.0 / (1.0 + math.exp(-logit))
