"""`dovesei bench-odometry`: the visual velocity's speed per frame and its error against the truth.

Speed: a descent over a suite world rendered at 640x480 (RGB, as a camera delivers it), each
frame prepared and compared with the one before (`dovesei.shared.visual_velocity`) on one OpenCV
thread; per-frame CPU time of this thread (robust when other processes share the host) and wall
time, median and 95th percentile. Target: <= 10 ms per frame.

Error: on every world of the suite, frame pairs as far apart as the camera's stream compares them
(`pair_dt_s`: its 10 Hz frames, the newest at least the altitude's baseline back, 0.1 s at 20 m to
0.5 s at 100 m; `VisualVelocityConfig.baseline_s`) rendered with the
sim's camera (`dovesei.sim.camera.render`, bilinear, as the sim's odometry views) along straight
segments with a known velocity: at each altitude and horizontal speed, `--pairs` pairs at seeded
positions (inside the world, away from its edge), random heading and direction of travel, a yaw
rate up to 0.3 rad/s and a climb or sink up to 1 m/s. With `--tilt` (the default both are run) the
body-fixed camera is rolled and pitched up to 15 deg, changing by up to 0.3 rad/s between the two
frames. With `--noise ideal` the estimator is told the true altitude and attitude and sees the
rendered pixels (the estimator's own error); with `realistic` (both are run by default) each frame
gets sensor noise (sigma 2 grey levels), an altitude reading off by 1 % (sigma, each frame) and
roll, pitch and yaw tags off by 0.5, 0.5 and 1 mrad (sigma, each frame: gyro-integrated attitude
and a time-tag mismatch). Reported: the fraction of pairs flagged invalid, over the valid ones
the horizontal error |v_est - v_true| (both brought to the level frame) in % of the speed (median,
95th percentile) or in m/s at speed 0, and how often the error lies within the estimate's own 95 %
circle (2.45 sd of the per-axis variance): an EKF fuses the value with that variance.

Flights (`--flight-s`, 60 s by default, 0 = skip): on every world, one in-process `SimCore`
episode per vehicle profile (`ideal`, `realistic`, `harsh`) with the sim's odometry at 10 Hz, flown by a
scripted pilot (speeds 0-8 m/s in changing directions, turns, a 1 m/s descent from 100 m): the
views are rendered at the true pose tilted with the body, the estimator is told what the profile's
autopilot reports (its delayed, noisy attitude, heading error and baro altitude). Each odometry
message is turned to north/east with the attitude it carries, as an EKF would, and compared with
the true displacement over the interval it spans: median and 95th percentile error in % of the speed
(pairs above 1 m/s), in m/s below, the invalid fraction, and the share of samples the controller's
gate (`OdometryGate`'s default limits: quality >= 0.5, variance <= 1 m^2/s^2) would refuse.

The last line printed is one JSON object with every figure (`--json` prints only that line).
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import statistics
import sys
import time
import zlib
from collections.abc import Sequence

import cv2
import numpy as np

from dovesei.controller.gnss_denied import OdometryGate
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import footprint
from dovesei.shared.visual_velocity import FrameMeta, VisualVelocityConfig, estimate, prepare, rotation_body_to_level
from dovesei.shared.messages import VehicleState, VelocityCommand
from dovesei.sim.camera import CameraError, CameraModel, prebuild_pyramid, render
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.starts import Start
from dovesei.sim.suite import suite
from dovesei.sim.world import World, WorldError, load_world

log = logging.getLogger(__name__)

DT_S = 0.1  # the camera service's and the sim's odometry rate, 10 Hz
ALTITUDES_M = (20.0, 40.0, 60.0, 80.0, 100.0)
SPEEDS_M_S = (0.0, 2.0, 5.0, 10.0)
MAX_YAW_RATE_RAD_S = 0.3
MAX_CLIMB_M_S = 1.0
MAX_TILT_RAD = math.radians(15.0)
MAX_TILT_RATE_RAD_S = 0.3
# `realistic`: what a real camera and autopilot add (sigma per frame): sensor noise, a baro or
# rangefinder altitude, the attitude the frame is tagged with.
NOISE_GREY = 2.0
ALT_REL_SIGMA = 0.01
ROLL_PITCH_SIGMA_RAD = 0.0005
YAW_SIGMA_RAD = 0.001


def _percentile(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def bench_speed(world: World, frames: int, seed: int) -> dict:
    """Per-frame time at 640x480 on one OpenCV thread, over a descent drifting across the world.

    The frames are rendered first; only the estimator is timed."""
    cam = CameraModel(640, 480, footprint.REFERENCE_HFOV_DEG)
    prebuild_pyramid(world, cam, 100.0)
    rng = np.random.default_rng(seed)
    x0, y0 = rng.uniform(0.3, 0.7) * world.width_m, rng.uniform(0.3, 0.7) * world.height_m
    images, metas = [], []
    for k in range(frames + 1):
        alt = max(20.0, 100.0 - 0.2 * k)  # 2 m/s down, 4 m/s east, 3 m/s north, turning 0.2 rad/s
        yaw = 0.5 + 0.02 * k
        images.append(render(world, x0 + 0.4 * k, y0 + 0.3 * k, alt, yaw, cam, with_labels=False,
                             interpolation="linear", ground_detail=True)[0])
        metas.append(FrameMeta(k, k * DT_S, alt, cam.hfov_rad, 0.0, 0.0, yaw))
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # the target is per core
    cpu_ms, wall_ms, valid = [], [], 0
    try:
        prev = prepare(images[0], metas[0])
        for image, meta in zip(images[1:], metas[1:]):
            c0, w0 = time.thread_time(), time.perf_counter()
            new = prepare(image, meta)
            est = estimate(prev, new)
            cpu_ms.append((time.thread_time() - c0) * 1e3)
            wall_ms.append((time.perf_counter() - w0) * 1e3)
            valid += est.valid
            prev = new
    finally:
        cv2.setNumThreads(threads)
    return {"frames": frames, "size": "640x480", "world": world.name, "valid_fraction": round(valid / frames, 3),
            "cpu_ms_median": round(statistics.median(cpu_ms), 3), "cpu_ms_p95": round(_percentile(cpu_ms, 95), 3),
            "wall_ms_median": round(statistics.median(wall_ms), 3), "wall_ms_p95": round(_percentile(wall_ms, 95), 3)}


def pair_dt_s(alt_m: float, config: VisualVelocityConfig = VisualVelocityConfig()) -> float:
    """The interval the camera's stream compares frames over at this altitude: the newest frame at
    least the baseline back among frames DT_S apart (`VisualVelocity.update`)."""
    baseline_s = config.baseline_s(alt_m)
    return DT_S * max(1, math.ceil(baseline_s / DT_S - 1e-6))


def _pair(world: World, cam: CameraModel, rng: np.random.Generator, alt_m: float, speed_m_s: float, tilt: bool,
          config: VisualVelocityConfig, noise: np.random.Generator | None) -> tuple[bool, float, float, float] | None:
    """(valid, horizontal error m/s, speed m/s, sd per axis m/s) of one pair, or None when a view
    falls outside the world."""
    margin = 1.5 * alt_m + 20.0  # the whole footprint inside the world, tilted or not
    if world.width_m < 2 * margin or world.height_m < 2 * margin:
        return None
    dt_s = pair_dt_s(alt_m, config)
    x0, y0 = rng.uniform(margin, world.width_m - margin), rng.uniform(margin, world.height_m - margin)
    course, yaw0 = rng.uniform(-math.pi, math.pi, 2)
    vn, ve = speed_m_s * math.cos(course), speed_m_s * math.sin(course)
    vd = rng.uniform(-MAX_CLIMB_M_S, MAX_CLIMB_M_S)
    yaw1 = yaw0 + rng.uniform(-MAX_YAW_RATE_RAD_S, MAX_YAW_RATE_RAD_S) * dt_s
    if tilt:
        roll0, pitch0 = rng.uniform(-MAX_TILT_RAD, MAX_TILT_RAD, 2)
        roll1, pitch1 = (np.array([roll0, pitch0]) + rng.uniform(-1, 1, 2) * MAX_TILT_RATE_RAD_S * dt_s).tolist()
    else:
        roll0 = pitch0 = roll1 = pitch1 = 0.0
    alt1 = alt_m - vd * dt_s
    # World x is east, y north.
    x1, y1 = x0 + ve * dt_s, y0 + vn * dt_s
    try:
        a = render(world, x0, y0, alt_m, yaw0, cam, roll_rad=roll0, pitch_rad=pitch0, with_labels=False,
                   interpolation="linear", ground_detail=True)[0]
        b = render(world, x1, y1, alt1, yaw1, cam, roll_rad=roll1, pitch_rad=pitch1, with_labels=False,
                   interpolation="linear", ground_detail=True)[0]
    except CameraError:
        return None
    if noise is not None:
        a, b = (np.clip(x + noise.normal(0.0, NOISE_GREY, x.shape), 0, 255).astype(np.uint8) for x in (a, b))
        tags = [(alt * (1 + noise.normal(0, ALT_REL_SIGMA)), r + noise.normal(0, ROLL_PITCH_SIGMA_RAD),
                 p + noise.normal(0, ROLL_PITCH_SIGMA_RAD), y + noise.normal(0, YAW_SIGMA_RAD))
                for alt, r, p, y in ((alt_m, roll0, pitch0, yaw0), (alt1, roll1, pitch1, yaw1))]
    else:
        tags = [(alt_m, roll0, pitch0, yaw0), (alt1, roll1, pitch1, yaw1)]
    m0 = FrameMeta(0, 0.0, tags[0][0], cam.hfov_rad, *(float(v) for v in tags[0][1:]))
    m1 = FrameMeta(1, dt_s, tags[1][0], cam.hfov_rad, *(float(v) for v in tags[1][1:]))
    est = estimate(prepare(a, m0, config), prepare(b, m1, config), config)
    if not est.valid:
        return False, 0.0, speed_m_s, 0.0
    # Both in the level frame of the newer heading (what an EKF fuses as north/east after its yaw).
    level = rotation_body_to_level(roll1, pitch1, 0.0) @ np.array(est.vel_body_frd_m_s)
    c, s = math.cos(yaw1), math.sin(yaw1)
    truth_fwd, truth_right = c * vn + s * ve, -s * vn + c * ve
    return (True, float(math.hypot(level[0] - truth_fwd, level[1] - truth_right)), speed_m_s,
            math.sqrt(est.vel_var_m2_s2))


def _summary(rows: list[tuple[bool, float, float, float]]) -> dict:
    n = len(rows)
    valid = [(err, v, sd) for ok, err, v, sd in rows if ok]
    moving = [100.0 * err / v for err, v, _ in valid if v > 0]
    still = [err for err, v, _ in valid if v == 0]
    # A 2-D Gaussian error with this sd per axis lies within 2.45 sd 95 % of the time.
    within = sum(err <= 2.45 * sd for err, _, sd in valid)
    return {"pairs": n, "invalid_fraction": round(1 - len(valid) / n, 3) if n else None,
            "err_pct_median": _r(_percentile(moving, 50)), "err_pct_p95": _r(_percentile(moving, 95)),
            "err_m_s_at_rest_median": _r(_percentile(still, 50)), "err_m_s_at_rest_p95": _r(_percentile(still, 95)),
            "within_own_95pct": round(within / len(valid), 3) if valid else None}


def _r(value: float | None) -> float | None:
    return None if value is None else round(value, 2)


def bench_error(worlds: dict[str, World], pairs: int, seed: int, tilts: Sequence[bool], noises: Sequence[str],
                cam: CameraModel = CameraModel()) -> dict:
    """The error tables: per world, tilt and noise, and per altitude x speed over all worlds."""
    config = VisualVelocityConfig()
    out: dict = {"camera": f"{cam.width_px}x{cam.height_px} {cam.hfov_deg:g} deg", "dt_s": DT_S,
                 "pair_dt_s": {f"{alt:g}": round(pair_dt_s(alt, config), 3) for alt in ALTITUDES_M},
                 "pairs_per_cell": pairs, "per_world": {}, "per_cell": {}}
    for noise, tilt in itertools.product(noises, tilts):
        tag = f"{'tilted' if tilt else 'level'} camera, {noise}"
        everything: list[tuple[bool, float, float, float]] = []
        cells: dict[str, list] = {}
        for spec, world in worlds.items():
            prebuild_pyramid(world, cam, 100.0)
            # The same poses on any host, with or without noise (its draws come from another stream).
            rng = np.random.default_rng([seed, int(tilt), zlib.crc32(spec.encode())])
            noise_rng = np.random.default_rng([seed, int(tilt), zlib.crc32(spec.encode()), 1])
            rows = []
            for alt, speed in itertools.product(ALTITUDES_M, SPEEDS_M_S):
                for _ in range(pairs):
                    r = _pair(world, cam, rng, alt, speed, tilt, config, noise_rng if noise == "realistic" else None)
                    if r is not None:
                        rows.append(r)
                        cells.setdefault(f"{alt:g} m, {speed:g} m/s", []).append(r)
            everything += rows
            out["per_world"].setdefault(tag, {})[spec] = _summary(rows)
        out["per_world"][tag]["all"] = _summary(everything)
        out["per_cell"][tag] = {k: _summary(v) for k, v in cells.items()}
    return out


# The scripted pilot of the flights: (seconds, forward, right, down m/s, yaw rate rad/s), repeated.
PILOT_LEGS = ((8.0, 5.0, 0.0, 1.0, 0.0), (6.0, 8.0, 2.0, 1.0, 0.2), (5.0, 0.0, 0.0, 1.0, 0.0),
              (8.0, -3.0, 4.0, 1.0, -0.3), (6.0, 2.0, -6.0, 1.0, 0.0), (4.0, 0.0, 0.0, 0.0, 0.5))


def _pilot(state: VehicleState, t_s: float) -> VelocityCommand:
    period = sum(leg[0] for leg in PILOT_LEGS)
    t = t_s % period
    for dur, fwd, right, down, yaw_rate in PILOT_LEGS:
        if t < dur:
            break
        t -= dur
    return VelocityCommand(state.vehicle_id, state.seq, state.stamp, (fwd, right, down), yaw_rate,
                           state_seq=state.seq)


def bench_flights(worlds: dict[str, World], flight_s: float, profiles: Sequence[str], seed: int) -> dict:
    """Odometry against the truth along scripted flights, per profile and world."""
    out: dict = {"flight_s": flight_s, "per_profile": {}}
    gate = OdometryGate()  # the controller's default limits: what it would fly on
    for profile in profiles:
        table: dict = {}
        every: list[tuple[bool, float, float, float, bool]] = []
        for spec, world in worlds.items():
            start = Start(world.width_m / 2, world.height_m / 2, 100.0, yaw_rad=0.3)
            core = SimCore(world, start, SimConfig(vehicle_id="bench", vehicle_profile=profile, odometry_rate_hz=10.0,
                                                   time_limit_s=flight_s, attach_truth=False, render_image=False,
                                                   seed=seed, handover_alt_m=5.0))
            out_step = core.reset()
            truth: dict[float, tuple[float, float]] = {}
            rows = []
            while out_step.result is None:
                pose = core.true_pose()
                truth[round(out_step.state.stamp.t_s, 6)] = (pose.x_m, pose.y_m)
                odo = out_step.odometry
                if odo is not None:
                    t1, t0 = round(odo.stamp.t_s, 6), round(odo.stamp.t_s - odo.dt_s, 6)
                    if t0 in truth:
                        (x0, y0), (x1, y1) = truth[t0], truth[t1]
                        vn, ve = (y1 - y0) / odo.dt_s, (x1 - x0) / odo.dt_s
                        speed = math.hypot(vn, ve)
                        if not odo.valid:
                            rows.append((False, 0.0, speed, 0.0, False))
                        else:
                            ned = rotation_body_to_level(odo.roll_rad, odo.pitch_rad, odo.yaw_rad) @ \
                                np.array(odo.vel_body_frd_m_s)
                            rows.append((True, math.hypot(ned[0] - vn, ned[1] - ve), speed,
                                         math.sqrt(odo.vel_var_m2_s2), gate.sample_good(odo)))
                out_step = core.step(_pilot(out_step.state, out_step.state.stamp.t_s))
            every += rows
            table[spec] = _flight_summary(rows)
        table["all"] = _flight_summary(every)
        out["per_profile"][profile] = table
    return out


def _flight_summary(rows: list[tuple[bool, float, float, float, bool]]) -> dict:
    valid = [(err, v, sd) for ok, err, v, sd, _good in rows if ok]
    moving = [100.0 * err / v for err, v, _ in valid if v >= 1.0]
    slow = [err for err, v, _ in valid if v < 1.0]
    within = sum(err <= 2.45 * sd for err, _, sd in valid)  # as in _summary
    return {"samples": len(rows), "invalid_fraction": round(1 - len(valid) / len(rows), 3) if rows else None,
            "err_pct_median": _r(_percentile(moving, 50)), "err_pct_p95": _r(_percentile(moving, 95)),
            "err_m_s_slow_median": _r(_percentile(slow, 50)), "err_m_s_slow_p95": _r(_percentile(slow, 95)),
            "within_own_95pct": round(within / len(valid), 3) if valid else None,
            "sd_m_s_median": _r(_percentile([sd for _, _, sd in valid], 50)),
            # the share of samples the controller's gate (default limits) would not fly on
            "refused_fraction": round(1 - sum(good for *_, good in rows) / len(rows), 3) if rows else None}


def _print_flights(flights: dict) -> None:
    def fmt(v: float | None, width: int = 7) -> str:
        return f"{'-':>{width}s}" if v is None else f"{v:{width}.2f}"
    for profile, table in flights["per_profile"].items():
        print(f"\nflights, {profile} vehicle profile ({flights['flight_s']:g} s each, odometry at 10 Hz vs the true "
              "displacement; % of speed above 1 m/s, m/s below)")
        print(f"{'':34s} {'samples':>7s} {'invalid':>8s} {'med %':>7s} {'p95 %':>7s} {'slow med':>9s} {'slow p95':>9s} "
              f"{'in 95%':>7s} {'sd med':>7s} {'refused':>8s}")
        for spec, s in table.items():
            within = "-" if s["within_own_95pct"] is None else f"{100 * s['within_own_95pct']:.0f}%"
            refused = "-" if s["refused_fraction"] is None else f"{100 * s['refused_fraction']:.1f}%"
            print(f"{spec:34s} {s['samples']:7d} {100 * s['invalid_fraction']:7.1f}% {fmt(s['err_pct_median'])} "
                  f"{fmt(s['err_pct_p95'])} {fmt(s['err_m_s_slow_median'], 9)} {fmt(s['err_m_s_slow_p95'], 9)} "
                  f"{within:>7s} {fmt(s['sd_m_s_median'])} {refused:>8s}")


def _print_tables(speed: dict, error: dict) -> None:
    print(f"speed at {speed['size']} ({speed['frames']} frames, {speed['world']}), one OpenCV thread: "
          f"CPU {speed['cpu_ms_median']:.2f} ms median, {speed['cpu_ms_p95']:.2f} ms p95; "
          f"wall {speed['wall_ms_median']:.2f} / {speed['wall_ms_p95']:.2f} ms")

    def fmt(v: float | None, width: int = 7) -> str:
        return f"{'-':>{width}s}" if v is None else f"{v:{width}.2f}"

    def row(name: str, s: dict) -> str:
        within = "-" if s["within_own_95pct"] is None else f"{100 * s['within_own_95pct']:.0f}%"
        return (f"{name:34s} {s['pairs']:5d} {100 * s['invalid_fraction']:7.1f}% {fmt(s['err_pct_median'])} "
                f"{fmt(s['err_pct_p95'])} {fmt(s['err_m_s_at_rest_median'], 9)} {fmt(s['err_m_s_at_rest_p95'], 9)} "
                f"{within:>7s}")

    header = (f"{'':34s} {'pairs':>5s} {'invalid':>8s} {'med %':>7s} {'p95 %':>7s} {'rest med':>9s} {'rest p95':>9s} "
              f"{'in 95%':>7s}")
    for tag, table in error["per_world"].items():
        spans = ", ".join(f"{dt:g} s at {alt} m" for alt, dt in error["pair_dt_s"].items())
        print(f"\n{tag} ({error['camera']}, frames {error['dt_s']:g} s apart compared over {spans}; "
              "error in % of speed over the valid pairs, m/s at rest; in 95%: within the estimate's own 95 % circle)")
        print(header)
        for spec, s in table.items():
            print(row(spec, s))
        for cell, s in error["per_cell"][tag].items():
            print(row("  " + cell, s))


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="dovesei bench-odometry", description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="default", help="world suite whose every world is measured")
    p.add_argument("--world", action="append", help="measure these worlds instead of a suite (repeatable)")
    p.add_argument("--pairs", type=int, default=10, help="frame pairs per world, altitude and speed")
    p.add_argument("--frames", type=int, default=300, help="frames timed for the speed figure")
    p.add_argument("--tilt", choices=("both", "on", "off"), default="both",
                   help="body-fixed camera rolled and pitched (on), level (off) or both")
    p.add_argument("--noise", choices=("both", "ideal", "realistic"), default="both",
                   help="true tags and clean pixels (ideal), sensor noise and tag errors (realistic), or both")
    p.add_argument("--flight-s", type=float, default=60.0,
                   help="seconds of scripted flight per world and vehicle profile (0 = skip the flights)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip-error", action="store_true", help="only the speed figure")
    p.add_argument("--json", action="store_true", help="print only the JSON line")
    args = p.parse_args(argv)
    if args.pairs < 1 or args.frames < 10 or not 0.0 <= args.flight_s <= 3600.0:
        p.error("--pairs must be >= 1, --frames >= 10 and --flight-s in 0..3600")
    logging.basicConfig(level=logging.WARNING)
    specs = tuple(args.world) if args.world else suite(args.suite)
    try:
        worlds = {spec: load_world(spec) for spec in specs}
    except WorldError as exc:
        print(f"dovesei bench-odometry: {exc}", file=sys.stderr)
        return 2
    speed = bench_speed(next(iter(worlds.values())), args.frames, args.seed)
    tilts = {"both": (False, True), "on": (True,), "off": (False,)}[args.tilt]
    noises = ("ideal", "realistic") if args.noise == "both" else (args.noise,)
    error = {} if args.skip_error else bench_error(worlds, args.pairs, args.seed, tilts, noises)
    flights = bench_flights(worlds, args.flight_s, ("ideal", "realistic", "harsh"), args.seed) \
        if args.flight_s > 0 and not args.skip_error else {}
    if not args.json:
        if error:
            _print_tables(speed, error)
        else:
            print(json.dumps(speed))
        if flights:
            _print_flights(flights)
    print(json.dumps({"speed": speed, "error": error, "flights": flights}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
