"""`dovesei bench-sim`: how fast the simulator renders and steps (a benchmark, not a timed test).

Measures, on one OpenCV thread (`cv2.setNumThreads(1)`: the targets are per core):

    world load / generation s, pyramid build s      the one-off costs before the first frame
    render_fps        352x352 views (image + labels, as the sim renders them) per wall second,
                      median over batches; each batch is one descent 100 m -> 20 m drifting
                      across the world, the way an episode moves (render_fps_cpu: the same per
                      CPU second of this thread, robust when other processes share the host)
    realtime_factor   sim seconds per wall second of a lockstep episode flown in-process by
                      SimCore.step with a trivial policy (constant drift, turn and descent), no
                      perception (so no ground-truth labels attached: nobody reads them), frames
                      rendered at the `reference` preset's rate (every step);
                      realtime_factor_real_timing is the same at the `real` preset (2 Hz frames)
    zenoh_realtime_factor  the same episode through the Zenoh service in lockstep: `run()` on one
                      in-process loopback peer, a trivial controller answering each state on another

The last line printed is one JSON object with all of these (`--json` prints only that line).
Targets on a 2-core machine: render_fps >= 1000, realtime_factor >= 200.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import statistics
import sys
import threading
import time
from collections.abc import Sequence

import cv2

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.messages import VehicleState, VelocityCommand
from dovesei.sim.camera import CameraModel, prebuild_pyramid, render
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.estimator import VEHICLE_PROFILE_NAMES
from dovesei.sim.starts import Start, generate_starts
from dovesei.sim.world import World, WorldError, load_world
from dovesei.shared.zconfig import free_port

log = logging.getLogger(__name__)

VEHICLE_ID = "bench"
# The trivial policy: 1 m/s forward while turning at 0.1 rad/s (a 10 m circle, so the vehicle
# stays inside any world) and sinking at 0.5 m/s (100 m -> 20 m in about 160 s).
TRIVIAL_VEL_FRD_M_S = (1.0, 0.0, 0.5)
TRIVIAL_YAW_RATE_RAD_S = 0.1


def trivial_command(state: VehicleState) -> VelocityCommand:
    """The trivial policy's answer to a state (lockstep: it names the state it answers)."""
    return VelocityCommand(state.vehicle_id, state.seq, state.stamp, TRIVIAL_VEL_FRD_M_S, TRIVIAL_YAW_RATE_RAD_S,
                           state_seq=state.seq)


def bench_starts(world: World, n: int, seed: int, cam: CameraModel) -> list[Start]:
    """Seeded 100 m starts; a world too small for a 100 m footprint gets its centre (the bench still runs)."""
    try:
        return generate_starts(world, n, seed, alt_m=100.0, cam=cam)
    except WorldError:
        log.warning("world %s is too small for 100 m starts: benchmarking from its centre", world.name)
        return [Start(world.width_m / 2.0, world.height_m / 2.0, 100.0)] * n


def measure_render(world: World, starts: Sequence[Start], frames: int, cam: CameraModel, roll_rad: float = 0.0,
                   pitch_rad: float = 0.0) -> tuple[list[float], list[float]]:
    """(wall fps, CPU fps) per batch; batch i descends from starts[i] while drifting and turning
    (a tilt renders the body-fixed camera's perspective view instead of the nadir one)."""
    wall_fps, cpu_fps = [], []
    for i, s in enumerate(starts):
        yaw0 = 2.0 * math.pi * i / len(starts)
        # Precomputed poses: the loop below times render() and nothing else.
        poses = [(s.x_m + 0.4 * j * math.cos(yaw0), s.y_m + 0.4 * j * math.sin(yaw0),
                  100.0 - 80.0 * j / max(frames - 1, 1), yaw0 + 0.01 * j) for j in range(frames)]
        w0, c0 = time.perf_counter(), time.thread_time()
        for x_m, y_m, alt_m, yaw_rad in poses:
            render(world, x_m, y_m, alt_m, yaw_rad, cam, roll_rad=roll_rad, pitch_rad=pitch_rad)
        wall_fps.append(frames / (time.perf_counter() - w0))
        cpu_fps.append(frames / max(time.thread_time() - c0, 1e-9))
    return wall_fps, cpu_fps


def measure_episode(world: World, start: Start, timing: str, episode_s: float, seed: int,
                    vehicle_profile: str = "ideal") -> dict[str, float]:
    """Fly the trivial policy in-process for `episode_s` of sim time; rates per wall second."""
    core = SimCore(world, start, SimConfig(vehicle_id=VEHICLE_ID, timing=timing, time_limit_s=episode_s, seed=seed,
                                           attach_truth=False, vehicle_profile=vehicle_profile))
    frames = steps = 0
    w0, c0 = time.perf_counter(), time.thread_time()
    out = core.reset()
    while out.result is None:
        frames += out.frame is not None
        out = core.step(trivial_command(out.state))
        steps += 1
    wall_s, cpu_s = time.perf_counter() - w0, max(time.thread_time() - c0, 1e-9)
    sim_s = out.result.sim_time_s
    return {"realtime_factor": sim_s / wall_s, "realtime_factor_cpu": sim_s / cpu_s, "steps_per_s": steps / wall_s,
            "frames": frames, "sim_s": sim_s, "outcome": out.result.outcome}




def measure_zenoh_episode(world: World, start: Start, episode_s: float, seed: int) -> float:
    """Sim seconds per wall second of the lockstep service with a trivial controller, both in-process."""
    import zenoh  # only this measurement needs the network stack

    from dovesei.shared import keys
    from dovesei.shared.codec import encode
    from dovesei.shared.lifecycle import Inbox, declare_alive, wait_until
    from dovesei.shared.zconfig import loopback_config
    from dovesei.sim.service import SimServiceConfig, run

    port = free_port()
    config = SimServiceConfig(sim=SimConfig(vehicle_id=VEHICLE_ID, time_limit_s=episode_s, seed=seed,
                                            attach_truth=False),
                              start_xy_alt_m=(start.x_m, start.y_m, start.alt_m), wait_for=("controller",),
                              wait_timeout_s=10.0, cmd_timeout_s=10.0)
    stop = threading.Event()
    first_state_s: list[float] = []
    with zenoh.open(loopback_config(listen_port=port)) as sim_session, \
            zenoh.open(loopback_config(connect_ports=[port])) as ctrl_session:
        if not wait_until(lambda: any(True for _ in sim_session.info.peers_zid()), 10.0):
            raise RuntimeError("the two in-process Zenoh peers did not connect")

        def controller() -> None:
            with Inbox(ctrl_session, keys.state(VEHICLE_ID), VehicleState, newest_only=False) as states:
                pub = ctrl_session.declare_publisher(keys.cmd(VEHICLE_ID))
                token = declare_alive(ctrl_session, VEHICLE_ID, "controller")  # after the subscriber
                try:
                    while not stop.is_set():
                        state = states.recv(0.2, stop)
                        if state is not None:
                            if not first_state_s:
                                first_state_s.append(time.perf_counter())
                            pub.put(encode(trivial_command(state)))
                finally:
                    token.undeclare()
                    pub.undeclare()

        thread = threading.Thread(target=controller, name="bench-controller", daemon=True)
        thread.start()
        try:
            result = run(sim_session, config=config, stop=threading.Event(), world=world)
            end_s = time.perf_counter()
        finally:
            stop.set()
            thread.join(5.0)
    if result is None or result.outcome == "error" or not first_state_s:
        raise RuntimeError(f"the Zenoh episode did not complete: {result}")
    # From the first state (after the liveliness wait) to the result: the stepping alone.
    return result.sim_time_s / (end_s - first_state_s[0])


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei bench-sim", description=__doc__.splitlines()[0])
    p.add_argument("--world", default="synthetic", help="synthetic[:seed=N,...] or a world folder (default: synthetic)")
    p.add_argument("--json", action="store_true", help="print only the JSON line")
    p.add_argument("--batches", type=int, default=5, help="render batches (the median is reported)")
    p.add_argument("--frames", type=int, default=400, help="frames per render batch")
    p.add_argument("--episode-s", type=float, default=120.0, help="sim seconds of the in-process episode")
    p.add_argument("--zenoh-episode-s", type=float, default=20.0, help="sim seconds of the Zenoh episode (0: skip)")
    p.add_argument("--seed", type=int, default=0, help="seed of the start positions")
    p.add_argument("--vehicle-profile", default="ideal", choices=VEHICLE_PROFILE_NAMES,
                   help="vehicle profile of the in-process episodes (default: ideal; realistic adds the estimate "
                        "and renders tilted)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.batches < 1 or args.frames < 1 or not args.episode_s > 0 or args.zenoh_episode_s < 0:
        print("dovesei bench-sim: --batches, --frames and --episode-s must be > 0", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        report = _measure(args)
    except (WorldError, RuntimeError) as exc:
        print(f"dovesei bench-sim: {exc}", file=sys.stderr)
        return 1
    finally:
        cv2.setNumThreads(threads)
    if not args.json:
        print(f"world {report['world']}: {report['world_px'][0]}x{report['world_px'][1]} px at {report['gsd_m']} m/px, "
              f"loaded in {report['world_load_s']:.2f} s, pyramid {report['pyramid_build_s']:.2f} s")
        print(f"render: {report['render_fps']:.0f} fps wall, {report['render_fps_cpu']:.0f} fps CPU (median of "
              f"{args.batches} x {args.frames} frames, one thread; target >= 1000)")
        print(f"lockstep episode in-process: x{report['realtime_factor']:.0f} real time at reference timing "
              f"(x{report['realtime_factor_cpu']:.0f} per CPU second; target >= 200), "
              f"x{report['realtime_factor_real_timing']:.0f} at real timing "
              f"(x{report['realtime_factor_real_timing_cpu']:.0f} per CPU second)")
        if report["zenoh_realtime_factor"] is not None:
            print(f"lockstep episode over in-process Zenoh: x{report['zenoh_realtime_factor']:.1f} real time")
    print(json.dumps(report))
    return 0


def _measure(args: argparse.Namespace) -> dict:
    cam = CameraModel()
    t0 = time.perf_counter()
    world = load_world(args.world)
    world_load_s = time.perf_counter() - t0
    pyramid_build_s = prebuild_pyramid(world, cam, 100.0)
    starts = bench_starts(world, max(args.batches, 1), args.seed, cam)
    wall_fps, cpu_fps = measure_render(world, starts, args.frames, cam)
    # A braking body-fixed camera: 12 deg nose up, 4 deg of roll (the perspective warp).
    tilted_fps, _ = measure_render(world, starts, args.frames, cam, math.radians(4.0), math.radians(12.0))
    ref = measure_episode(world, starts[0], "reference", args.episode_s, args.seed, args.vehicle_profile)
    real = measure_episode(world, starts[0], "real", args.episode_s, args.seed, args.vehicle_profile)
    zenoh_rtf = measure_zenoh_episode(world, starts[0], args.zenoh_episode_s, args.seed) if args.zenoh_episode_s else None
    return {
        "world": world.name, "world_px": [world.width_px, world.height_px], "gsd_m": world.gsd_m,
        "world_load_s": round(world_load_s, 3), "pyramid_build_s": round(pyramid_build_s, 3),
        "frame_px": [cam.width_px, cam.height_px],
        "render_fps": round(statistics.median(wall_fps), 1), "render_fps_cpu": round(statistics.median(cpu_fps), 1),
        "render_fps_batches": [round(f, 1) for f in wall_fps],
        "render_fps_tilted": round(statistics.median(tilted_fps), 1), "vehicle_profile": args.vehicle_profile,
        "realtime_factor": round(ref["realtime_factor"], 2), "realtime_factor_cpu": round(ref["realtime_factor_cpu"], 2),
        "steps_per_s": round(ref["steps_per_s"], 1), "episode_sim_s": ref["sim_s"], "episode_frames": ref["frames"],
        "realtime_factor_real_timing": round(real["realtime_factor"], 2),
        "realtime_factor_real_timing_cpu": round(real["realtime_factor_cpu"], 2),
        "zenoh_realtime_factor": None if zenoh_rtf is None else round(zenoh_rtf, 2),
        "cpus": os.cpu_count(), "opencv_threads": 1,
    }


if __name__ == "__main__":
    sys.exit(main())
