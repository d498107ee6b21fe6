"""One fault scenario: a short `up`-like episode through a loopback router, one fault, the checks.

    Router A (+ Router B and the lossy Relay for `loss`) --> the three services as subprocesses
    (command lines from `dovesei.up.launch`, clients of the router) --> up's own Watcher and
    Recorder decide the report (exit code, the failure naming a service), exactly as in `up`
    --> an Observer session records every status, state, command and heatmap with its arrival
    --> the fault's script waits for the descent, injects, waits for recovery, ends the run
    --> check_run (dovesei.faults.checks): the safety rules, each failure one line in `violations`

The rules each run is held to are in `dovesei.faults.checks`.
"""

from __future__ import annotations

import logging
import os
import random
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from dovesei.faults.checks import Observer, check_run
from dovesei.faults.inject import SKEW_S, Intruder
from dovesei.faults.network import LossProfile, Relay, Router, client_config
from dovesei.up import exit_code, preflight
from dovesei.up.children import Children
from dovesei.up.launch import SERVICES, child_commands, child_env
from dovesei.up.monitor import Monitor, Recorder
from dovesei.up.options import UpOptions
from dovesei.up.report import build_report, read_stats
from dovesei.up.watch import Watcher

log = logging.getLogger("dovesei.faults")

WORLD = "synthetic:size_m=400,seed=1"  # generated in about a second, cached on disk after
START_ALT_M = 50.0
TRIGGER_MAX_S = 40.0  # wall seconds to wait for a descent before injecting anyway
RESUMED_FOR_S = 2.0  # `ok` on new heatmaps this long after the fault ends counts as resumed
RESUME_WINDOW_S = 12.0


@dataclass(frozen=True)
class Fault:
    """One fault: what to inject and what the report should say about it."""

    name: str
    text: str
    names: str | None  # the service the report must name as failed (None: the run must not fail)
    resumes: bool = True  # the fault ends, so the mission must resume
    relay: bool = False
    lockstep: bool = False  # the sim waits for every command (up's default); else real time as in flight
    heatmap_wait_s: float | None = None  # lockstep: the controller's wait for a due heatmap (None: its default)
    stall_s: float = 8.0
    after_failure_s: float = 8.0
    duration_s: float = 4.0


FAULTS: dict[str, Fault] = {f.name: f for f in (
    Fault("segmenter-kill", "SIGKILL the segmenter mid-descent", "segmenter", resumes=False, after_failure_s=4.0),
    Fault("segmenter-hang", "SIGSTOP the segmenter 4 s, then SIGCONT", "segmenter", stall_s=3.0),
    Fault("controller-hang", "SIGSTOP the controller 4 s, then SIGCONT", "controller", stall_s=3.0),
    # Lockstep, up's default: the hung service stops the sim's clock too (the mid-air LANDED).
    # 10 s with a 1 s heatmap wait: the controller decides blind every 0.25 s wall, data time reaches the hold.
    Fault("segmenter-hang-lockstep", "lockstep: SIGSTOP the segmenter 10 s, then SIGCONT", "segmenter",
          stall_s=3.0, after_failure_s=12.0, duration_s=10.0, lockstep=True, heatmap_wait_s=1.0),
    Fault("controller-hang-lockstep", "lockstep: SIGSTOP the controller 4 s, then SIGCONT", "controller",
          stall_s=3.0, lockstep=True),
    Fault("router-restart", "close the router 3 s, then open it on the same port", None, duration_s=3.0),
    Fault("loss", "a relay drops 10-30 % of camera/heatmap samples, delays <= 50 ms, duplicates 5 %", None,
          relay=True, duration_s=8.0),
    Fault("clock-skew", "forged heatmaps and states stamped 30 s ahead and behind, 10 Hz for 4 s", None),
    Fault("garbage", "random bytes and nonsense maps on heatmap and state, ~400/s for 4 s", None),
    Fault("forged", "forged descent commands (stamped 1e9, +5 s, -5 s), a forged 'safe' result, bad prompts", None),
)}


@dataclass
class Context:
    """What a fault's script can reach while the run goes on."""

    fault: Fault
    seed: int
    children: Children
    router: Router
    observer: Observer
    monitor: Monitor
    intruder: Intruder | None
    start: tuple[float, float, float]
    done: threading.Event  # the watcher ended the run (a result, or a failure's deadline)
    stop: threading.Event  # set by the script: the run has shown what it had to show
    fault_start_wall_s: float | None = None
    fault_end_wall_s: float | None = None
    notes: list[str] = field(default_factory=list)

    def drain(self) -> None:
        with self.observer.lock:
            self.monitor.drain()

    def wait(self, seconds: float) -> bool:
        """Drain for `seconds`; False when the run ended meanwhile."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.drain()
            if self.done.is_set():
                return False
            self.done.wait(min(0.02, max(0.0, deadline - time.monotonic())))
        return not self.done.is_set()

    def every(self, seconds: float, period_s: float, action: Callable[[], None]) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not self.done.is_set():
            self.drain()
            action()
            self.done.wait(period_s)

    def now_s(self) -> float:
        st = self.observer.last_state
        return st.stamp.t_s if st is not None else 0.0

    def alt_m(self) -> float:
        st = self.observer.last_state
        return st.alt_agl_m if st is not None else START_ALT_M

    def pid(self, name: str) -> int:
        return self.children.procs[name].pid


# ---- the faults' scripts: each runs from the trigger until the fault is over -------------------


def _pause(ctx: Context, name: str) -> None:
    os.kill(ctx.pid(name), signal.SIGSTOP)
    try:
        ctx.wait(ctx.fault.duration_s)
    finally:
        os.kill(ctx.pid(name), signal.SIGCONT)


def _kill(ctx: Context) -> None:
    os.kill(ctx.pid("segmenter"), signal.SIGKILL)
    ctx.wait(30.0)  # until the watcher's after-failure window ends the run


def _router(ctx: Context) -> None:
    ctx.router.restart(ctx.fault.duration_s, ctx.done)


def _skew(ctx: Context) -> None:
    intr = ctx.intruder

    def burst() -> None:
        now, alt = ctx.now_s(), ctx.alt_m()
        # Behind: a stamp the codec accepts (>= 0), else the decoder alone refuses it and the
        # controller's clock-jump handling is never probed.
        behind_s = -min(SKEW_S, now)
        intr.skewed_heatmap(now, SKEW_S, alt)
        intr.skewed_heatmap(now, behind_s, alt)
        intr.skewed_state(now, SKEW_S, alt)
        intr.skewed_state(now, behind_s, alt)

    ctx.every(ctx.fault.duration_s, 0.1, burst)


def _garbage(ctx: Context) -> None:
    intr = ctx.intruder

    def burst() -> None:
        for _ in range(4):
            intr.garbage("heatmap")
            intr.garbage("state")

    ctx.every(ctx.fault.duration_s, 0.02, burst)


def _forged(ctx: Context) -> None:
    intr = ctx.intruder
    intr.forged_result(ctx.observer.last_state, ctx.start)
    intr.bad_prompts()

    def burst() -> None:
        now = ctx.now_s()
        for stamp_s in (1e9, now + 5.0, now - 5.0):
            intr.forged_command(stamp_s)

    ctx.every(ctx.fault.duration_s, 0.02, burst)


def _loss(ctx: Context) -> None:
    ctx.wait(ctx.fault.duration_s)  # the relay has been lossy since the start


SCRIPTS: dict[str, Callable[[Context], None]] = {
    "segmenter-kill": _kill, "segmenter-hang": lambda c: _pause(c, "segmenter"),
    "segmenter-hang-lockstep": lambda c: _pause(c, "segmenter"),
    "controller-hang-lockstep": lambda c: _pause(c, "controller"),
    "controller-hang": lambda c: _pause(c, "controller"), "router-restart": _router, "loss": _loss,
    "clock-skew": _skew, "garbage": _garbage, "forged": _forged,
}


def _descending(ctx: Context) -> bool:
    st = ctx.observer.last_status
    return st is not None and st.watchdog == "ok" and st.vel_body_frd_m_s[2] > 0.3 and st.alt_agl_m > 28.0


def _script(ctx: Context) -> None:
    try:
        deadline = time.monotonic() + TRIGGER_MAX_S
        while not _descending(ctx) and time.monotonic() < deadline:
            if not ctx.wait(0.05):
                ctx.notes.append("the run ended before the fault was injected")
                return
        ctx.fault_start_wall_s = time.time()
        st = ctx.observer.last_status
        log.info("%s: injecting at t=%.2f s, alt %.1f m", ctx.fault.name, ctx.now_s(), ctx.alt_m())
        seq0 = st.frame_seq if st is not None else -1
        SCRIPTS[ctx.fault.name](ctx)
        ctx.fault_end_wall_s = time.time()
        if not ctx.fault.resumes:
            return
        # Resumed: `ok` on heatmaps newer than the one held at injection, for RESUMED_FOR_S.
        deadline = time.monotonic() + RESUME_WINDOW_S
        ok_since = None
        while time.monotonic() < deadline and not ctx.done.is_set():
            ctx.wait(0.05)
            # Only statuses that arrived after the fault count: the last one from before an outage
            # may still read `ok`.
            recv_s, st = ctx.observer.statuses[-1] if ctx.observer.statuses else (0.0, None)
            fresh = recv_s > max(ctx.fault_end_wall_s, time.time() - 0.5)  # and still arriving
            good = fresh and st is not None and (st.watchdog == "ok" or st.state == "HANDOVER") and st.frame_seq > seq0
            ok_since = (ok_since or time.monotonic()) if good else None
            if ok_since is not None and time.monotonic() - ok_since >= RESUMED_FOR_S:
                return
    except Exception as exc:  # noqa: BLE001 - a broken script must end the run and be reported, not hang it
        log.exception("fault script %s failed", ctx.fault.name)
        ctx.notes.append(f"fault script raised {type(exc).__name__}: {exc}")
    finally:
        ctx.stop.set()


# ---- running one scenario -----------------------------------------------------------------------


@dataclass(frozen=True)
class RunResult:
    fault: str
    seed: int
    exit_code: int
    outcome: str
    failure_child: str | None
    failure: str
    violations: tuple[str, ...]
    void: str | None  # why the run tested nothing: its fault was never injected (None: it was)
    unsafe: bool
    mid_air_handover: bool
    held: bool
    resumed: bool | None
    wall_s: float
    details: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        return {**{k: getattr(self, k) for k in self.__dataclass_fields__ if k != "details"}, **self.details,
                "violations": list(self.violations)}


def _retarget(argv: list[str], endpoint: str) -> list[str]:
    """The same command line with its Zenoh flags (always last, see launch.zenoh_flags) replaced."""
    i = argv.index("--mode")
    return [*argv[:i], "--mode", "client", "--connect", endpoint]


def run_scenario(fault: Fault, seed: int, out: Path, *, world: str = WORLD,
                 vehicle_profile: str | None = None) -> RunResult:
    t0 = time.monotonic()
    vid = "uav1"
    rng = random.Random(seed)
    router = Router()
    side = Router() if fault.relay else None
    relay = None
    if side is not None:
        relay = Relay(router.endpoint, side.endpoint, vid, LossProfile(drop=rng.uniform(0.1, 0.3)), seed)
    options = UpOptions(world=world, segmenter="sim", noise=0.0, start_seed=seed, start_alt_m=START_ALT_M, out=out,
                        realtime=not fault.lockstep, connect=(router.endpoint,), video=False, stall_s=fault.stall_s,
                        after_failure_s=fault.after_failure_s, heatmap_wait_s=fault.heatmap_wait_s,
                        startup_timeout_s=60.0, log_level="INFO", vehicle_profile=vehicle_profile)
    _, start, configs = preflight(options)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    (out / "stats").mkdir(exist_ok=True)
    commands = child_commands(options, configs, {n: 0 for n in (*SERVICES, "monitor")}, out)
    if side is not None:
        commands["segmenter"] = _retarget(commands["segmenter"], side.endpoint)
    session = zenoh.open(client_config(router.endpoint))
    intruder = Intruder(client_config(router.endpoint), vid, seed) if fault.name in ("clock-skew", "garbage",
                                                                                     "forged") else None
    rec = Recorder(start, video=False, vehicle_id=vid)
    observer = Observer(vid)
    children = Children(out / "logs")
    up_monitor = Monitor(session, vid, rec, with_camera=False)
    obs_monitor = Monitor(session, vid, observer, with_camera=False)
    done, stop = threading.Event(), threading.Event()
    ctx = Context(fault, seed, children, router, observer, obs_monitor, intruder, start, done, stop)
    script = threading.Thread(target=_script, args=(ctx,), name=f"fault-{fault.name}", daemon=True)
    end = None
    try:
        for name in SERVICES:
            children.start(name, commands[name], child_env(name, options))
        script.start()
        # A short confirmation window: a forged result must be seen refused within the run.
        end = Watcher(options, rec, up_monitor, children, stop, t0, confirm_s=3.0).run()
    finally:
        done.set()
        if script.is_alive():
            script.join(timeout=30)
        rec.expect_exits = True
        children.stop_all()
        up_monitor.drain()
        ctx.drain()
        up_monitor.close()
        obs_monitor.close()
        if intruder is not None:
            intruder.close()
        session.close()
        if relay is not None:
            relay.close()
        for r in (side, router):
            if r is not None:
                r.close()
    failure = end.failure if end is not None else None
    # Stopped by the suite once it had seen what it needed: 'interrupted' (130), as a Ctrl-C in up.
    interrupted = end is not None and end.interrupted
    report = build_report(options, rec, start, configs.noise, read_stats(out), failure, interrupted,
                          time.monotonic() - t0)
    code = exit_code(report)
    violations, facts = check_run(fault, observer, rec, failure, ctx.fault_start_wall_s, ctx.fault_end_wall_s)
    void = None
    if ctx.fault_start_wall_s is None:
        # Nothing was tested: not a violation of the fault's rules (the safety rules still count).
        void = "; ".join(ctx.notes) or "the fault was never injected"
        void += f" (the run ended {report.outcome})"
    else:
        violations += ctx.notes
    if relay is not None:
        facts["relay"] = relay.totals()
    if intruder is not None:
        facts["intruder_sent"] = intruder.sent
    mid_air = any(v.startswith("mid-air") for v in violations)
    unsafe = (any(v.startswith(("blind", "descent", "forged command")) for v in violations)
              or (rec.result is not None and rec.result.outcome == "unsafe"))
    return RunResult(fault.name, seed, code, report.outcome, failure.child if failure else None,
                     failure.message if failure else "", tuple(violations), void, unsafe, mid_air, facts["held"],
                     facts["resumed"], round(time.monotonic() - t0, 2), facts)
