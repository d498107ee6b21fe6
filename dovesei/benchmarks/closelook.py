"""`dovesei bench-closelook`: how long a close look takes (a benchmark, not a timed test).

    crop_render_ms      the sim cutting a 352 px square of its world (image + labels) at the
                        newest frame's pose (SimCore.crop), median over --crops
    look_s              crop request -> CLIPSeg on the crop (landing + never prompts, one pass)
                        -> verdict (the largest P(never) inside the separation disk), median
                        over --looks, with torch on --threads threads

CLIPSeg is `--model` (a local directory), or without one a randomly initialised model of
CIDAS/clipseg-rd64-refined's architecture (the same compute: the weights do not change the time).
The last line is one JSON object with the medians and the load average beside them.
Targets (issue 24): crop_render_ms <= 5 at 352 px on one core; look_s <= 1 on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence

import cv2
import numpy as np

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.messages import CropRequest, Stamp
from dovesei.shared.mission import PERSON_SEPARATION_M, SAFETY_RADIUS_M
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.starts import generate_starts
from dovesei.sim.world import load_world

SIDE_M = 2.0 * (SAFETY_RADIUS_M + PERSON_SEPARATION_M + 1.0)  # the disk, the margin and a metre of slack


def _crop_core(world_spec: str, render_image: bool) -> SimCore:
    world = load_world(world_spec)
    start = generate_starts(world, 1, 0, alt_m=40.0)[0]
    core = SimCore(world, start, SimConfig(vehicle_profile="ideal", render_image=render_image,
                                           crop_limits=_unlimited()))
    core.reset()
    return core


def _unlimited():
    from dovesei.shared.crop import CropLimits

    return CropLimits(rate_hz=1e6, burst=1000)  # the benchmark asks back to back


def bench_crop_render(core: SimCore, n: int) -> list[float]:
    """Milliseconds per 352 px crop on one OpenCV thread, over n squares around the vehicle."""
    rng = np.random.default_rng(0)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        out = []
        for i in range(n):
            req = CropRequest(core.config.vehicle_id, i, Stamp(0.0, "sim"), tuple(rng.uniform(-8.0, 8.0, 2)), SIDE_M, 352)
            t0 = time.perf_counter()
            core.crop(req)
            out.append((time.perf_counter() - t0) * 1e3)
        return out
    finally:
        cv2.setNumThreads(threads)


def bench_look(core: SimCore, model_dir: str, threads: int, n: int) -> list[float]:
    """Seconds per close look: crop -> CLIPSeg (landing + never) -> the verdict's largest P(never)."""
    from dovesei.segmenter.core import SegmenterConfig, SegmenterCore, make_backend

    config = SegmenterConfig(backend="clipseg", model=model_dir, threads=threads)
    seg = SegmenterCore(make_backend(config), config)
    yy, xx = np.mgrid[0:352, 0:352]
    disk = np.hypot(yy - 175.5, xx - 175.5) * (SIDE_M / 352) <= SAFETY_RADIUS_M + PERSON_SEPARATION_M
    seg.process_crop(core.crop(CropRequest(core.config.vehicle_id, 0, Stamp(0.0, "sim"), (0.0, 0.0), SIDE_M, 352)))
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        crop = core.crop(CropRequest(core.config.vehicle_id, i + 1, Stamp(0.0, "sim"), (0.0, 0.0), SIDE_M, 352))
        _, never = seg.process_crop(crop).probabilities()
        float(never[disk].max())  # the verdict's figure
        out.append(time.perf_counter() - t0)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = OneLineParser(prog="dovesei bench-closelook", description=__doc__.splitlines()[0])
    p.add_argument("--world", default="synthetic", help="world spec (default the embedded synthetic city)")
    p.add_argument("--crops", type=int, default=500, help="crops rendered for the render median")
    p.add_argument("--looks", type=int, default=10, help="close looks for the look median (0: skip CLIPSeg)")
    p.add_argument("--threads", type=int, default=2, help="torch threads for CLIPSeg")
    p.add_argument("--model", help="CLIPSeg directory (default: random weights of the rd64-refined architecture)")
    args = p.parse_args(argv)
    render_ms = bench_crop_render(_crop_core(args.world, True), args.crops)
    result = {"crop_render_ms_median": round(statistics.median(render_ms), 3), "crops": args.crops,
              "crop_side_m": SIDE_M, "crop_px": 352}
    if args.looks > 0:
        with tempfile.TemporaryDirectory() as tmp:
            model = args.model
            if model is None:
                from dovesei.testing.random_model import build_random_clipseg

                model = str(build_random_clipseg(os.path.join(tmp, "rd64"), size="rd64", seed=0))
            look_s = bench_look(_crop_core(args.world, True), model, args.threads, args.looks)
        result.update(look_s_median=round(statistics.median(look_s), 3), looks=args.looks, threads=args.threads,
                      model=args.model or "random rd64-refined architecture")
    result["loadavg"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
