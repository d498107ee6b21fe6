"""`dovesei perception-stats`: the simulated perception's statistics, comparable to real CLIPSeg's.

The figures the authors' logs and PEACE give for the reference pipeline with real CLIPSeg, and
that the `realistic` profile is calibrated against (never against landing success counts):

- `median_threshold`: median over frames of the reference's dynamic threshold (authors: 0.51);
- `lowered_fraction`: share of frames whose threshold went below 0.85 (authors: 99.8 %);
  frames where even 0.0085 leaves < 10 % of pixels count as lowered (the service failed);
- `target_precision`: share of single-frame target pixels (P above the dynamic threshold) whose
  2 m ground disk is truly safe, judged with the world's safe flags and the judge's 1 %
  tolerance (PEACE: DOVESEI's prompts found a safe landing zone 57 % of the time);
- `core_precision`: share of frames whose mask's deepest pixel (farthest from the mask's edge,
  where the reference aims) has a truly safe disk: PEACE's per-image reading of the same thing;
- `oracle_precision` (a ceiling, judge side): the same figure for a map made of the judge's own
  flags (1 safe, 0 unsafe) through the same blur and threshold;
- `below_floor_fraction` (judge side): share of frames whose truly disk-safe share of the view is
  under the threshold loop's 10 % floor. On such a frame any map that does not fail the loop puts
  target pixels on unsafe ground, however right it is about each class;
- `frame_agreement`: mean IoU of the target masks of consecutive frames (the camera drifting
  0.2 m per frame at 100 m), i.e. how much of the map's choice survives one frame;
- `separability` (judge side): median over frames of the area under the ROC curve of P between
  the view's disk-safe ground and the rest (0.5: P says nothing about it; 1: some threshold
  separates them exactly), on frames where each side covers at least `SEPARABILITY_MIN_SHARE` of
  the view. No threshold, blur or policy enters it: it bounds what any policy can read from one
  map, whatever it does with the levels.

Why even `clean` stays under the judge's flags (measured on the default suite, seed 0): the
reference's 15-px box blur (6.3 m at 100 m) and its 10 % floor cap the oracle itself at 0.88
(37 % of the frames have under 10 % disk-safe ground: 85 % of Dubai's, 40-50 % of downtown's,
the villas' and the coast's); and the reference prompts name "sidewalk" and "asphalt" as places to land while the
synthetic judge counts sidewalks unsafe, and Dubai's "vegetation (lawns and trees, not
separated)" is half lawn by its own name but unsafe to its judge. A perception that answers the
prompts faithfully is penalised for both; that is the prompts' and labels' error, not its own.

All at 100 m over seeded starts, with the reference prompts, the reference fusion (softmax) and
the dynamic threshold of `dovesei.controller.policies.dovesei`. This side is the JUDGE and may
read the safe flags; the perception under test never does.

    worlds --starts (seeded)--> views at 100 m, a short drift per start
           --sim render (labels + pose)--> SimPerception --fusion "dovesei"--> P(safe)
           --dynamic threshold--> target mask --world disk-safe map--> precision, agreement
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from dovesei.controller.policies.dovesei.policy import DoveseiConfig, dynamic_threshold
from dovesei.segmenter.fusion import FusionConfig, blur_prob
from dovesei.segmenter.prompts import REFERENCE_PROMPTS
from dovesei.segmenter.sim_backend import (
    DEFAULT_PROFILE, PROFILES, PerceptionParams, SimPerception, View, profile_params,
)
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.sim.camera import CameraModel, pixel_to_world_affine, render
from dovesei.sim.judge import disk_safe_map
from dovesei.sim.starts import generate_starts
from dovesei.sim.suite import suite
from dovesei.sim.world import World, load_world, require_judged

log = logging.getLogger(__name__)

ALT_M = 100.0
DRIFT_M_PER_FRAME = 0.2
SEPARABILITY_MIN_SHARE = 0.02  # a frame's AUC needs this share of the view on each side
SEPARABILITY_STRIDE = 4  # every 4th pixel each way: P's detail is a 16 px token, this keeps 5 a token


@dataclass(frozen=True)
class WorldStats:
    world: str
    frames: int
    median_threshold: float
    lowered_fraction: float
    failed_fraction: float
    target_precision: float
    core_precision: float
    oracle_precision: float
    below_floor_fraction: float
    frame_agreement: float
    separability: float = float("nan")


def roc_auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """P(a random positive scores above a random negative), ties counting half (Mann-Whitney U)."""
    if positive.size == 0 or negative.size == 0:
        raise ValueError("roc_auc needs at least one positive and one negative score")
    scores = np.concatenate([positive.ravel(), negative.ravel()]).astype(np.float64)
    values, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    # Average rank of each distinct value (1-based): ties share the mean of their ranks.
    ends = np.cumsum(counts)
    ranks = (ends - (counts - 1) / 2.0)[inverse]
    n_pos = positive.size
    u = ranks[:n_pos].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * negative.size))


def default_worlds() -> list[str]:
    """The repository's world suite (`dovesei.sim.suite.DEFAULT_SUITE`)."""
    return list(suite("default"))


def _view_disk_safe(world: World, safe_map: np.ndarray, x_m: float, y_m: float, cam: CameraModel) -> np.ndarray:
    m0 = pixel_to_world_affine(world, x_m, y_m, ALT_M, 0.0, cam)
    return cv2.warpAffine(safe_map, m0, (cam.width_px, cam.height_px), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def world_stats(world: World, params: PerceptionParams, n_starts: int, frames_per_start: int, seed: int) -> WorldStats:
    """The statistics of one world under one perception profile (see the module docstring)."""
    cam = CameraModel()
    perception = SimPerception(params, seed=seed)
    seen = world.perceived()  # what the camera sees; the judge's disk map below reads the world itself
    names = {cid: c.name for cid, c in seen.classes.items()}  # names only: the flag stays here
    fusion = FusionConfig(mode="dovesei")
    policy_cfg = DoveseiConfig()
    safe_map = disk_safe_map(world)
    rng = np.random.default_rng([seed, 5])
    thresholds, agreements, aucs = [], [], []
    lowered = failed = 0
    target_px = target_safe = 0
    cores = cores_safe = 0
    oracle_px = oracle_safe = 0
    below_floor = 0
    safe_lut = seen.safe_lut.astype(np.float32)  # the sub-classes carry their class's flag
    for i, start in enumerate(generate_starts(world, n_starts, seed, ALT_M, cam)):
        heading = rng.uniform(0.0, 2.0 * math.pi)
        prev = None
        for k in range(frames_per_start):
            x_m = start.x_m + k * DRIFT_M_PER_FRAME * math.sin(heading)
            y_m = start.y_m + k * DRIFT_M_PER_FRAME * math.cos(heading)
            _, labels, _ = render(seen, x_m, y_m, ALT_M, 0.0, cam, with_image=False)
            view = View((x_m, y_m), ALT_M, cam.hfov_rad, 0.0, world.name)
            prob = perception.safe_probability(labels, names, view, i * 1000 + k, REFERENCE_PROMPTS, fusion)
            truth = _view_disk_safe(world, safe_map, x_m, y_m, cam)
            step = SEPARABILITY_STRIDE
            p_s, t_s = prob[::step, ::step], truth[::step, ::step]
            if SEPARABILITY_MIN_SHARE <= t_s.mean() <= 1.0 - SEPARABILITY_MIN_SHARE:
                aucs.append(roc_auc(p_s[t_s], p_s[~t_s]))
            below_floor += float(np.count_nonzero(truth)) / truth.size < policy_cfg.seg_min_safe_fraction
            # The ceiling: the judge's own class flags as P (1 safe, 0 unsafe), the same box blur
            # and threshold. What no perception can beat at 100 m with this pipeline.
            oracle = dynamic_threshold(blur_prob(safe_lut[labels], fusion.blur_px), policy_cfg)
            if oracle.mask_u8 is not None:
                oracle_px += int(np.count_nonzero(oracle.mask_u8))
                oracle_safe += int(np.count_nonzero((oracle.mask_u8 > 0) & truth))
            res = dynamic_threshold(prob, policy_cfg)
            if res.threshold is None:
                failed += 1
                lowered += 1
                prev = None
                continue
            thresholds.append(res.threshold)
            lowered += res.threshold < policy_cfg.seg_threshold_start
            mask = res.mask_u8 > 0
            target_px += int(mask.sum())
            target_safe += int((mask & truth).sum())
            # The mask's deepest pixel (farthest from its edge), where a policy would aim.
            dist = cv2.distanceTransform(res.mask_u8, cv2.DIST_L2, 3)
            cores += 1
            cores_safe += bool(truth.flat[int(np.argmax(dist))])
            if prev is not None:
                # The drift moves the ground under the camera by < 0.5 px: compare pixel for pixel.
                agreements.append(float((mask & prev).sum()) / max(1, int((mask | prev).sum())))
            prev = mask
    frames = n_starts * frames_per_start
    return WorldStats(
        world=world.name, frames=frames,
        median_threshold=float(np.median(thresholds)) if thresholds else float("nan"),
        lowered_fraction=lowered / frames, failed_fraction=failed / frames,
        target_precision=target_safe / target_px if target_px else float("nan"),
        core_precision=cores_safe / cores if cores else float("nan"),
        oracle_precision=oracle_safe / oracle_px if oracle_px else float("nan"),
        below_floor_fraction=below_floor / frames,
        frame_agreement=float(np.mean(agreements)) if agreements else float("nan"),
        separability=float(np.median(aucs)) if aucs else float("nan"))


def suite_stats(worlds: list[str], profile: str = DEFAULT_PROFILE, noise: float = 1.0, n_starts: int = 40,
                frames_per_start: int = 3, seed: int = 0) -> dict:
    """Per-world statistics and their frame-weighted means over the worlds."""
    per_world = []
    for spec in worlds:
        require_judged(spec)
    for spec in worlds:
        world = load_world(spec)
        stats = world_stats(world, profile_params(profile, noise), n_starts, frames_per_start, seed)
        log.info("%s", stats)
        per_world.append(stats)
    frames = sum(s.frames for s in per_world)

    def mean(key: str) -> float:
        vals = [(getattr(s, key), s.frames) for s in per_world if not math.isnan(getattr(s, key))]
        return sum(v * f for v, f in vals) / sum(f for _, f in vals) if vals else float("nan")

    return {"perception": profile, "noise": noise, "seed": seed, "starts_per_world": n_starts,
            "frames_per_start": frames_per_start, "alt_m": ALT_M, "prompts": "reference", "fusion": "dovesei",
            "frames": frames, "median_threshold": mean("median_threshold"), "lowered_fraction": mean("lowered_fraction"),
            "failed_fraction": mean("failed_fraction"), "target_precision": mean("target_precision"),
            "core_precision": mean("core_precision"), "oracle_precision": mean("oracle_precision"),
            "below_floor_fraction": mean("below_floor_fraction"),
            "frame_agreement": mean("frame_agreement"), "separability": mean("separability"), "worlds": [asdict(s) for s in per_world]}


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei perception-stats", description=__doc__.split("\n\n")[0])
    p.add_argument("--perception", default=DEFAULT_PROFILE, choices=sorted(PROFILES),
                   help=f"simulated perception profile (default {DEFAULT_PROFILE})")
    p.add_argument("--noise", type=float, default=1.0, help="error scale within the profile (default 1)")
    p.add_argument("--world", action="append", default=None,
                   help="world spec (repeatable; default: the world suite)")
    p.add_argument("--suite", default=None, help="a named world suite instead of --world (default suite: 'default')")
    p.add_argument("--starts", type=int, default=40, help="seeded starts per world (default 40)")
    p.add_argument("--frames", type=int, default=3, help="consecutive frames per start (default 3, >= 2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the starts and of the perception")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.starts < 1 or args.frames < 2 or args.seed < 0:
        print("dovesei perception-stats: --starts must be >= 1, --frames >= 2 and --seed >= 0", file=sys.stderr)
        return 2
    try:
        if args.suite is not None and args.world:
            raise ConfigError("give --world or --suite, not both")
        worlds = list(suite(args.suite)) if args.suite is not None else (args.world or default_worlds())
        out = suite_stats(worlds, args.perception, args.noise, args.starts, args.frames,
                          args.seed)
    except (DoveseiError, ValueError) as exc:
        print(f"dovesei perception-stats: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out))
    else:
        for w in out["worlds"]:
            print(f"{w['world']:<40} median thr {w['median_threshold']:.3f}  lowered {w['lowered_fraction']:.3f}  "
                  f"precision {w['target_precision']:.3f}  core {w['core_precision']:.3f}  oracle {w['oracle_precision']:.3f}  "
                  f"below floor {w['below_floor_fraction']:.3f}  agreement {w['frame_agreement']:.3f}  "
                  f"separability {w['separability']:.3f}")
        print(f"{'ALL':<40} median thr {out['median_threshold']:.3f}  lowered {out['lowered_fraction']:.3f}  "
              f"precision {out['target_precision']:.3f}  core {out['core_precision']:.3f}  oracle {out['oracle_precision']:.3f}  "
              f"below floor {out['below_floor_fraction']:.3f}  agreement {out['frame_agreement']:.3f}  "
              f"separability {out['separability']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["WorldStats", "default_worlds", "roc_auc", "suite_stats", "world_stats"]
