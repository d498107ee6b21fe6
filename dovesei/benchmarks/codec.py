"""`dovesei bench-codec`: encode/decode time of a 352x352 RGB frame and a 352x352 heatmap.

Prints one line per case (median and p90 over many runs, microseconds) and, with --json, one
JSON object on the last line.
"""

from __future__ import annotations

import json
import statistics
import time

import numpy as np

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.codec import decode, encode
from dovesei.shared.messages import CameraFrame, SafetyHeatmap, Stamp


def _time_us(fn, runs: int) -> tuple[float, float]:
    samples = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e6)
    samples.sort()
    return statistics.median(samples), samples[int(0.9 * (len(samples) - 1))]


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="dovesei bench-codec", description=__doc__)
    p.add_argument("--runs", type=int, default=2000)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    rng = np.random.default_rng(0)
    stamp = Stamp(0.0, "sim")
    frame = CameraFrame("uav1", 1, stamp, rng.integers(0, 255, (352, 352, 3), dtype=np.uint8), 1.274, 100.0)
    hm8 = SafetyHeatmap("uav1", 1, stamp, rng.integers(0, 255, (352, 352), dtype=np.uint8), 100.0, 1.274,
                        "simulated", True, "p", "grouped", 0.0)
    hm16 = SafetyHeatmap("uav1", 1, stamp, rng.random((352, 352)).astype(np.float16), 100.0, 1.274,
                         "simulated", True, "p", "grouped", 0.0)
    cases = {
        "frame_raw": (frame, None), "frame_jpeg90": (frame, 90), "heatmap_uint8": (hm8, None), "heatmap_float16": (hm16, None),
    }
    out: dict[str, dict[str, float]] = {}
    for name, (msg, q) in cases.items():
        data = encode(msg, jpeg_quality=q)
        runs = args.runs if q is None else max(50, args.runs // 10)
        enc = _time_us(lambda: encode(msg, jpeg_quality=q), runs)
        dec = _time_us(lambda: decode(data, type(msg)), runs)
        out[name] = {"bytes": len(data), "encode_us_p50": round(enc[0], 1), "encode_us_p90": round(enc[1], 1),
                     "decode_us_p50": round(dec[0], 1), "decode_us_p90": round(dec[1], 1), "runs": runs}
        print(f"{name:16s} {len(data):8d} B  encode p50 {enc[0]:8.1f} us  decode p50 {dec[0]:8.1f} us  ({runs} runs)")
    if args.json:
        print(json.dumps(out))
    return 0
