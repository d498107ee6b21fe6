"""`dovesei up`: fly one episode with the three services as separate OS processes on Zenoh.

    dovesei up ──starts──> dovesei.sim.service         (camera frames, vehicle states, judge)
               ──starts──> dovesei.segmenter.service   (heatmaps)
               ──starts──> dovesei.controller.service  (velocity commands, status)
               ──monitor session──> records states, statuses, commands, heatmaps, a subsample
                                    of the camera frames, liveliness and the EpisodeResult
               ──at the end──> <out>/report.json, trajectory.png, episode.mp4
                               <out>/logs/<service>.log (each child's output), stats/<service>.json
                               (from services with --stats-out), pids.json (written at start)

The package, by concern: `options` (flags, typed options, every check made before a process
starts), `launch` (each service's command line and Zenoh wiring), `children` (the processes),
`monitor` (what `up` sees on Zenoh), `watch` (dead, hung or silent services; whose result to
believe), `report` (the typed run report and its pictures). This module runs them in order.

`up` never steps anything itself: the sim runs the episode (lockstep by default, so the trajectory
equals `dovesei.episode.run_episode` for the same spec) and `up` watches the keys like any
operator would. With `--vehicle URL` a real autopilot flies instead of the simulated vehicle, in
true seconds (the `real` timing preset): the controller is the one process that opens the MAVLink
link and publishes the autopilot's state; the sim renders the world at that state (its local
origin placed at --start) and judges there.

With `--handover-action land` or `precland`, `up` keeps the controller running after the judged
hand-over until the autopilot has landed and disarmed (bounded; `watch.wait_for_landing`): the
autopilot lands on its own, and a precision landing needs the controller's LANDING_TARGET stream
to touchdown. With `--gnss-denied external-nav` (any hand-over action) the sim's odometry and the
controller's stream of it to the autopilot's EKF go on the same way, until the autopilot disarms
(or the bound): stopped at the hand-over, ArduCopter's EKF failsafe took over ~5 s later. The
report's `landing` section says how that wait ended.

Exit codes: 0 landed safely; 3 the episode ran but ended unsafe, timed out or left the world;
1 an error (a service died or hung, takeoff refused, an 'error' ending); 2 bad usage (flags, world,
model directory, MAVLink URL: one line, before any process starts and before the output folder
exists); 130 interrupted (SIGINT/SIGTERM stop every child the same way).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import os
import shutil
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from dovesei.replay import up_recorder
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.lifecycle import install_stop_handlers
from dovesei.shared.mavurl import check_serial_device
from dovesei.shared.zconfig import SessionError, free_port, open_session, zenoh_config
from dovesei.sim.world import WorldError, load_world
from dovesei.up.children import Children, describe_exit, last_error_line
from dovesei.up.launch import (
    SERVICES, ChildConfigs, check_endpoint_free, check_link_owners, child_commands, child_configs, child_env,
    landing_timeout_s, zenoh_flags,
)
from dovesei.up.monitor import Monitor, Recorder, Sample
from dovesei.up.options import (
    UpOptions, build_parser, check_policy, options_from_args, parse_mavlink_url, parse_start, resolve_start,
)
from dovesei.up.report import RunReport, build_report, read_stats, write_outputs
from dovesei.up.watch import (
    RESULT_AFTER_EXIT_S, LandingWait, Watcher, WatchEnd, port_collision, wait_for_landing,
    wait_for_takeoff,
)

__all__ = ["SERVICES", "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "EXIT_UNSAFE", "EXIT_INTERRUPTED", "Recorder",
           "Sample", "UpOptions", "build_report", "child_commands", "last_error_line", "main",
           "parse_start", "run", "zenoh_flags"]

log = logging.getLogger("dovesei.up")

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_UNSAFE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
TAKEOFF_CLIMB_M_S = 1.0  # slowest climb rate allowed for when waiting for --takeoff (ArduCopter's default is 2.5)
TAKEOFF_MARGIN_S = 30.0
START_ATTEMPTS = 3  # starts on freshly picked ports when one was taken before a service bound it


def exit_code(report: RunReport) -> int:
    if report.failure is not None:
        return EXIT_FAILED
    if report.interrupted:
        return EXIT_INTERRUPTED
    if report.outcome == "safe":
        return EXIT_OK
    if report.outcome == "not_judged":  # reached the hand-over altitude; nothing says it was safe
        return EXIT_UNSAFE
    return EXIT_UNSAFE if report.episode.judged else EXIT_FAILED


def preflight(options: UpOptions) -> tuple[object, tuple[float, float, float], ChildConfigs]:
    """Everything that can be wrong before a process starts: policy, world, start, the link's endpoint."""
    check_policy(options.policy)
    if options.out.exists() and not options.out.is_dir():
        raise ConfigError(f"--out {str(options.out)!r} is a file; give a folder for the report")
    if options.connect:
        zenoh_config(mode="client", connect=options.connect, env={})  # names a malformed --connect
    if options.vehicle_url:
        link = parse_mavlink_url(options.vehicle_url)
        check_serial_device(link)
        check_endpoint_free(link)
    if options.sitl_truth:
        check_endpoint_free(parse_mavlink_url(options.sitl_truth, "--sitl-truth"), "--sitl-truth")
    world = load_world(options.world)
    if world.labels is None and options.segmenter == "sim":
        raise ConfigError(f"world {options.world!r} has no labels for the simulated perception to read: "
                          "fly it with --segmenter clipseg")
    start = resolve_start(world, options)
    configs = child_configs(options, start, world)  # each service's own checks, now rather than in a child
    # The ports do not change which links the command lines open: placeholders suffice here.
    check_link_owners(child_commands(options, configs, {n: 0 for n in (*SERVICES, "monitor")}, options.out))
    return world, start, configs


def claim_folder(base: Path) -> Path:
    """A new folder named `base`, or `base`-2, -3, ... when taken: mkdir is atomic, so two runs
    started in the same second (the default name has one-second resolution) never share one."""
    base.parent.mkdir(parents=True, exist_ok=True)
    for n in itertools.count(1):
        path = base if n == 1 else base.with_name(f"{base.name}-{n}")
        try:
            path.mkdir()
        except FileExistsError:
            continue
        return path
    raise AssertionError("unreachable")


def _remove_if_empty(out: Path, created: list[Path]) -> None:
    """A failed run leaves no empty folder behind: remove the folders this run made if they hold no file."""
    if out.is_dir() and not any(p.is_file() for p in out.rglob("*")):
        for folder in sorted(created, key=lambda p: len(p.parts), reverse=True):
            shutil.rmtree(folder, ignore_errors=True)


def run(options: UpOptions, *, stop: threading.Event,
        checked: tuple[object, tuple[float, float, float], ChildConfigs] | None = None) -> int:
    """Fly one episode; writes the report folder and returns the exit code.

    `checked` is what `preflight(options)` returned (it runs here when not given).
    """
    t0 = time.monotonic()
    world, start, configs = preflight(options) if checked is None else checked
    created = [p for p in (*reversed(options.out.parents), options.out) if not p.exists()]
    if options.out_unique:
        options = dataclasses.replace(options, out=claim_folder(options.out), out_unique=False)
        created.append(options.out)
    out = options.out
    created += [p for p in (out, out / "logs", out / "stats") if not p.exists() and p not in created]
    (out / "logs").mkdir(parents=True, exist_ok=True)
    (out / "stats").mkdir(exist_ok=True)
    try:
        return _fly(options, world, start, configs, stop, t0)
    finally:
        _remove_if_empty(out, created)


def _fly(options: UpOptions, world: object, start: tuple[float, float, float], configs: ChildConfigs,
         stop: threading.Event, t0: float) -> int:
    out = options.out
    noise = configs.noise
    log.info("world %s (%.0f x %.0f m), start (%.1f, %.1f) m at %.0f m, policy %s, %s timing, %s, segmenter %s",
             options.world, world.width_m, world.height_m, *start, options.policy, options.timing,
             "lockstep" if options.lockstep else "real time", options.segmenter)
    if options.vehicle_url and options.segmenter == "sim":
        log.warning("--segmenter sim with --vehicle: heatmaps come from the world's labels at the autopilot's "
                    "pose, not from a model")
    if options.segmenter != "sim" and options.lockstep and options.timing == "reference":
        log.warning("a model segmenter in lockstep with reference timing runs one inference per 0.05 s of sim "
                    "time; --timing real needs ten times fewer")
    rec = Recorder(start, video=options.video, vehicle_id=options.vehicle_id)
    taps = _open_taps(options, configs, start, world)
    rec.taps = [tap.write for tap in taps]
    session, monitor_port = _open_monitor_session(options)
    children = Children(out / "logs")
    monitor = None
    landing: LandingWait | None = None
    try:
        # Subscribed before any child starts: the first state the sim publishes is recorded.
        monitor = Monitor(session, options.vehicle_id, rec,
                          with_camera=options.video or bool(options.vehicle_url) or bool(taps))
        for attempt in range(1, START_ATTEMPTS + 1):
            # Picked now, bound by the children a moment later: another process may take a port in
            # between (1 run in 6 under load). Such a start is retried on new ports, never flown.
            ports = {**{name: free_port() for name in SERVICES}, "monitor": monitor_port}
            end = _start_and_watch(options, configs, start, rec, monitor, children,
                                   child_commands(options, configs, ports, out), stop, t0)
            taken = port_collision(end.failure, rec)
            if taken is None or attempt == START_ATTEMPTS:
                break
            log.warning("%s could not listen on port %d (another process took it after `up` picked it): "
                        "restarting the services on new ports (attempt %d of %d)", taken, ports[taken],
                        attempt + 1, START_ATTEMPTS)
            children.stop_all()
            children = Children(out / "logs")
            rec.alive.clear()
        if rec.result is not None:
            # external-nav: the sim's odometry goes on after the result (the autopilot's EKF flies on it).
            external_nav = configs.sim.odometry_after_result_s > 0
            if not external_nav:
                # The sim ends its run once the result is out: a signal now would only cut its shutdown.
                children.wait_exit("sim", RESULT_AFTER_EXIT_S)
            # Give the controller's hand-over statuses a moment to arrive after the sim's result.
            if options.vehicle_url and (external_nav or configs.controller.handover_action in ("land", "precland")) \
                    and _handover_reported(rec, monitor, stop):
                # The autopilot lands on its own from here, and for a precision landing on the
                # target the controller streams: both must outlive the judged episode; with
                # external-nav so must the camera's velocity, whatever the hand-over action.
                landing = wait_for_landing(rec, monitor, children, stop,
                                           landing_timeout_s(configs.controller.handover_alt_m), options.stall_s,
                                           external_nav=external_nav)
    finally:
        rec.expect_exits = True
        codes = children.stop_all()
        if monitor is not None:
            monitor.drain()
            monitor.close()
        session.close()
        for tap in taps:
            tap.close()
    log.info("children stopped: %s", ", ".join(f"{n} {describe_exit(c)}" for n, c in codes.items()))

    report = build_report(options, rec, start, noise, read_stats(out), end.failure, end.interrupted,
                          time.monotonic() - t0, landing=landing, handover_action=configs.controller.handover_action)
    report = write_outputs(world, report, rec, out, options.video)
    log.info("report: %s (%s)", out / "report.json", ", ".join(report.files.values()))
    code = exit_code(report)
    if end.failure is not None:
        print(f"dovesei up: {end.failure.message}", file=sys.stderr)
    elif end.interrupted:
        print("dovesei up: interrupted; every service stopped", file=sys.stderr)
    else:
        t = report.timing
        print(f"{report.outcome}: {report.episode.detail} ({report.episode.sim_time_s:.1f} s sim in "
              f"{t.episode_wall_s or t.wall_time_s:.1f} s wall, path {report.episode.path_length_m:.0f} m, "
              f"{report.perception_text()}); transport overhead p50 {t.transport_overhead.p50_ms} ms")
    return code


def _open_monitor_session(options: UpOptions) -> tuple[zenoh.Session, int]:
    """`up`'s own Zenoh session and the loopback port it listens on (0 with --connect).

    Opened in this process, so a port taken between picking and binding is seen at once and
    another one is picked.
    """
    if options.connect:
        return open_session(zenoh_config(mode="client", connect=options.connect, env={})), 0
    for attempt in range(1, START_ATTEMPTS + 1):
        port = free_port()
        try:
            return open_session(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"],
                                             multicast_scouting=False, env={})), port
        except SessionError as exc:
            if not exc.address_in_use or attempt == START_ATTEMPTS:
                raise
            log.info("monitor port %d was taken before it could be bound: picking another", port)
    raise AssertionError("unreachable")


def _start_and_watch(options: UpOptions, configs: ChildConfigs, start: tuple[float, float, float], rec: Recorder,
                     monitor: Monitor, children: Children, commands: dict[str, list[str]], stop: threading.Event,
                     t0: float) -> WatchEnd:
    """Start the services (the controller's takeoff first, when asked) and watch the episode."""
    end = WatchEnd(None, False)
    if options.takeoff:
        # The sim would judge the climb as a landing: it starts once the controller steers.
        _start(children, ("segmenter", "controller"), commands, options)
        end = wait_for_takeoff(rec, monitor, children, stop, configs.controller.takeoff_ready_timeout_s
                               + start[2] / TAKEOFF_CLIMB_M_S + TAKEOFF_MARGIN_S)
        if port_collision(end.failure, rec) is not None:
            return end
        rec.first_state_wall_s = None  # the episode begins after the climb
    if end.failure is None and not end.interrupted:
        _start(children, [n for n in SERVICES if n not in children.procs], commands, options)
        end = Watcher(options, rec, monitor, children, stop, t0).run()
    return end


def _handover_reported(rec: Recorder, monitor: Monitor, stop: threading.Event, within_s: float = 2.0) -> bool:
    """True once the controller has reported its hand-over (a timeout or out-of-world ending has none)."""
    deadline = time.monotonic() + within_s
    while not rec.handover_seen and time.monotonic() < deadline and not stop.is_set():
        monitor.drain()
        stop.wait(0.02)
    return rec.handover_seen


def _open_taps(options: UpOptions, configs: ChildConfigs, start: tuple[float, float, float], world: object) -> list:
    """What sees every message besides the report: the flight recording and the live view."""
    taps: list = []
    # The view first: when its extra is missing nothing has been opened yet.
    if options.view or options.rrd:
        try:
            from dovesei.view import LiveView  # lazy: rerun-sdk is the optional extra 'view'
        except ImportError as exc:
            raise ConfigError(f"--view/--rrd need the extra 'view' (pip install 'dovesei[view]'): {exc}") from None
        taps.append(LiveView(world, start, spawn=options.view, rrd=options.rrd, vehicle_id=options.vehicle_id))
    if options.record:
        taps.append(up_recorder(options.out, configs, options, start))
        log.info("recording the flight to %s", taps[-1].path)
    return taps


def _start(children: Children, names: Sequence[str], commands: dict[str, list[str]], options: UpOptions) -> None:
    for name in names:
        children.start(name, commands[name], child_env(name, options))
    # Rewritten after each batch: tests and operators find every child's pid here.
    pids = {"up": os.getpid(), **{n: p.pid for n, p in children.procs.items()}}
    (options.out / "pids.json").write_text(json.dumps(pids))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = install_stop_handlers()
    try:
        options = options_from_args(args)
        checked = preflight(options)
    except (ConfigError, WorldError) as exc:  # bad flags, or a world, model, link or start that cannot be used
        print(f"dovesei up: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        return run(options, stop=stop, checked=checked)
    except DoveseiError as exc:  # could not run: a service's start or the monitor's Zenoh session failed
        print(f"dovesei up: {exc}", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
