"""Loop-jitter benchmark of the real-time controller: how late its 20 Hz ticks run.

    python -m dovesei.benchmarks.loop [--duration-s 30] [--heatmap-hz 2] [--json]

Two Zenoh peers on loopback. On one, a fake world publishes VehicleState at the loop rate (its
altitude follows the newest command) and a fake segmenter publishes 352x352 heatmaps at 2 Hz (a
real CLIPSeg's rate); the controller service (`run`, real-time mode, the real policy) runs on the
other. The world runs in a child process by default, as sim and segmenter do when deployed.
Measured per tick against the absolute schedule t0 + k x period:

    wake lateness     when the loop woke up (the jitter of the schedule itself)
    publish lateness  when the command had been sent (adds the policy's compute on heatmap ticks)

Target: p99 wake lateness <= 5 ms. `--world thread` puts the world in the controller's process
instead: its Python work then competes with the loop for the GIL (a pessimistic figure).
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import queue
import statistics
import sys
import threading
from typing import Any

import cv2
import numpy as np
import zenoh

from dovesei.controller.core import ControllerConfig
from dovesei.controller.policies.registry import policy_names
from dovesei.controller.service import RunStats, run
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import footprint, keys
from dovesei.shared.clock import WallClock, wall_time_s
from dovesei.shared.codec import encode
from dovesei.shared.lifecycle import Inbox, is_alive, wait_until
from dovesei.shared.messages import SafetyHeatmap, Stamp, VehicleState, VelocityCommand
from dovesei.shared.zconfig import free_port, loopback_config

log = logging.getLogger(__name__)
VEHICLE = "bench"
HFOV_RAD = footprint.REFERENCE_HFOV_RAD




def _heatmaps(count: int, size_px: int, seed: int) -> list[np.ndarray]:
    """Smooth random P(safe) fields as uint8 (CLIPSeg-like blobs), one per published frame."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        field = cv2.GaussianBlur(rng.random((size_px, size_px)).astype(np.float32), (0, 0), size_px / 30.0)
        field = (field - field.min()) / max(float(np.ptp(field)), 1e-6)
        out.append((field * 255.0).astype(np.uint8))
    return out


class FakeWorld:
    """Vehicle states at `rate_hz` and heatmaps at `heatmap_hz`, both on a wall-clock schedule."""

    def __init__(self, session: zenoh.Session, *, rate_hz: float, heatmap_hz: float, size_px: int) -> None:
        self.session, self.rate_hz, self.heatmap_hz = session, rate_hz, heatmap_hz
        # Precomputed so the world's own work stays small and regular.
        self.maps = _heatmaps(8, size_px, seed=0)
        self.cmds: Inbox[VelocityCommand] = Inbox(session, keys.cmd(VEHICLE), VelocityCommand, newest_only=False)
        self.policy_s: list[float] = []
        self.commands = 0

    def run(self, stop: threading.Event) -> None:
        clock = WallClock()
        period_s = 1.0 / self.rate_hz
        frames_every = max(1, round(self.rate_hz / self.heatmap_hz))
        alt_m, vel_down_m_s, k, frame_seq, last_frame = 100.0, 0.0, 0, 0, -1
        while clock.sleep_until(k * period_s, stop):
            t_s = clock.now_s()
            # Fly the newest command; each new frame's policy time comes back on the command.
            while (cmd := self.cmds.poll()) is not None:
                self.commands += 1
                vel_down_m_s = cmd.vel_body_frd_m_s[2]
                if cmd.latency is not None and cmd.frame_seq != last_frame:
                    self.policy_s.append(cmd.latency.policy_s)
                    last_frame = cmd.frame_seq
            alt_m = min(max(alt_m - vel_down_m_s * period_s, 25.0), 120.0)  # stay above the hand-over
            # The data clock is the world's wall time since start, as a real-time sim would stamp.
            if k % frames_every == 0:
                hm = SafetyHeatmap(VEHICLE, frame_seq, Stamp(t_s, "sim"), self.maps[frame_seq % len(self.maps)],
                                   alt_m, float(HFOV_RAD), "simulated", True, "bench", "bench", 0.0,
                                   sent_wall_s=wall_time_s())
                self.session.put(keys.heatmap(VEHICLE), encode(hm))
                frame_seq += 1
            st = VehicleState(VEHICLE, k, Stamp(t_s, "sim"), alt_m, (0.0, 0.0, vel_down_m_s), sent_wall_s=wall_time_s())
            self.session.put(keys.state(VEHICLE), encode(st))
            k += 1

    def close(self) -> None:
        self.cmds.close()


def _percentile_ms(values_s: list[float], q: float) -> float:
    """Nearest-rank percentile in milliseconds."""
    ordered = sorted(values_s)
    index = min(len(ordered) - 1, max(0, int(round(q / 100.0 * (len(ordered) - 1)))))
    return ordered[index] * 1e3


def _world_process(port: int, rate_hz: float, heatmap_hz: float, size_px: int, ready: Any, stop: Any,
                   out: Any) -> None:
    """The fake world on its own Zenoh session, as sim and segmenter would be.

    Runs in a child process or a thread: `ready`/`stop` are multiprocessing or threading events
    (same wait/is_set/set interface) and `out` a queue receiving (commands, policy seconds).
    """
    commands, policy_s = 0, []
    with zenoh.open(loopback_config(connect_ports=[port])) as session:
        world = FakeWorld(session, rate_hz=rate_hz, heatmap_hz=heatmap_hz, size_px=size_px)
        try:
            if wait_until(lambda: is_alive(session, VEHICLE, "controller", 0.5), 20.0):
                ready.set()
                world.run(stop)
                commands, policy_s = world.commands, world.policy_s
        finally:
            world.close()
    out.put((commands, policy_s))


def bench(*, duration_s: float, rate_hz: float, heatmap_hz: float, size_px: int, policy: str,
          world_in_process: bool) -> dict[str, object]:
    port = free_port()
    config = ControllerConfig(vehicle_id=VEHICLE, policy=policy, timing="real", lockstep=False, rate_hz=rate_hz)
    stop_service = threading.Event()
    result: dict[str, RunStats] = {}
    if world_in_process:
        # Same process: the world's Python work competes with the loop for the GIL.
        ready, stop_world, out = threading.Event(), threading.Event(), queue.Queue()
        world: Any = threading.Thread(target=_world_process, name="world",
                                      args=(port, rate_hz, heatmap_hz, size_px, ready, stop_world, out))
    else:
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter: no inherited Zenoh state
        ready, stop_world, out = ctx.Event(), ctx.Event(), ctx.Queue()
        world = ctx.Process(target=_world_process, name="world",
                            args=(port, rate_hz, heatmap_hz, size_px, ready, stop_world, out))
    world_result = None
    with zenoh.open(loopback_config(listen_port=port)) as controller_session:
        service = threading.Thread(target=lambda: result.update(stats=run(controller_session, config=config,
                                                                          stop=stop_service)),
                                   name="controller")
        # The controller's `run`, as `main` calls it, in a thread of this process.
        service.start()
        # Everything after the service started is inside the try: the session must outlive it.
        try:
            world.start()
            if ready.wait(30.0):
                # The benchmark's length, counted from the first published state.
                stop_service.wait(duration_s)
        finally:
            stop_service.set()
            service.join()
            stop_world.set()
            if world.ident is not None:  # started
                try:
                    world_result = out.get(timeout=30.0)
                except queue.Empty:
                    pass
                world.join(30.0)
    if "stats" not in result:
        raise RuntimeError("the controller service failed; see the log above")
    if world_result is None:
        raise RuntimeError("the fake world did not report; see the log above")
    commands, policy_s = world_result
    stats = result["stats"]
    # Ticks before the first state are not sampled: they command nothing.
    wake, publish = list(stats.wake_lateness_s), list(stats.publish_lateness_s)
    if not wake:
        raise RuntimeError("the controller never ticked: no vehicle state reached it")
    return {
        "rate_hz": rate_hz, "heatmap_hz": heatmap_hz, "size_px": size_px, "policy": policy,
        "world": "thread" if world_in_process else "process",
        "duration_s": duration_s, "ticks": stats.ticks, "missed_ticks": stats.missed_ticks,
        "heatmaps_received": stats.heatmaps_received, "commands_received": commands,
        "wake_lateness_p50_ms": _percentile_ms(wake, 50), "wake_lateness_p99_ms": _percentile_ms(wake, 99),
        "wake_lateness_max_ms": max(wake) * 1e3,
        "publish_lateness_p50_ms": _percentile_ms(publish, 50),
        "publish_lateness_p99_ms": _percentile_ms(publish, 99), "publish_lateness_max_ms": max(publish) * 1e3,
        "policy_median_ms": statistics.median(policy_s) * 1e3 if policy_s else None,
        "target_p99_ms": 5.0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="dovesei bench-loop", description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=30.0)
    parser.add_argument("--rate-hz", type=float, default=20.0)
    parser.add_argument("--heatmap-hz", type=float, default=2.0)
    parser.add_argument("--size", type=int, default=352, help="heatmap side in pixels")
    parser.add_argument("--policy", default="dovesei", choices=policy_names())
    parser.add_argument("--world", choices=["process", "thread"], default="process",
                        help="run the fake sim + segmenter in a child process (as deployed, default) or in a "
                             "thread of this process (its Python work then competes for the GIL)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    if args.duration_s <= 0 or args.rate_hz <= 0 or args.heatmap_hz <= 0 or args.size < 8:
        parser.error("--duration-s, --rate-hz and --heatmap-hz must be > 0, --size >= 8")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    res = bench(duration_s=args.duration_s, rate_hz=args.rate_hz, heatmap_hz=args.heatmap_hz,
                size_px=args.size, policy=args.policy, world_in_process=args.world == "thread")
    if args.json:
        print(json.dumps(res))
    else:
        r = res
        print(f"controller loop at {r['rate_hz']:g} Hz, heatmaps at {r['heatmap_hz']:g} Hz "
              f"({r['size_px']} px, policy {r['policy']}), world in a {r['world']}: "
              f"{r['ticks']} ticks, {r['missed_ticks']} missed")
        for what in ("wake", "publish"):
            print(f"  {what + ' lateness':<17} p50 {r[what + '_lateness_p50_ms']:.3f} ms  "
                  f"p99 {r[what + '_lateness_p99_ms']:.3f} ms  max {r[what + '_lateness_max_ms']:.3f} ms")
        print(f"  target: wake p99 <= {r['target_p99_ms']:g} ms; policy median "
              f"{r['policy_median_ms'] or float('nan'):.3f} ms per heatmap")
    return 0


if __name__ == "__main__":
    sys.exit(main())
