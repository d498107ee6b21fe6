"""Watching the services while the episode runs: the loop between start-up and the report.

    every few ms: drain the monitor, then in order
      - a result candidate on the episode key: accepted only once the sim has ended its run (its
        process exited right after) and the result agrees with the last recorded state; one
        that arrives while the sim keeps flying is not the sim's, and is refused and counted
      - a child that exited before the result: a failure naming it and its last log line
      - a stream gone silent for --stall-s wall seconds (status: controller, heatmap: segmenter,
        camera/state: sim): a failure naming the service whose stream went quiet FIRST (in
        lockstep one hang silences everything downstream of it), with its liveliness; a service
        that kept computing through the silence (its CPU time, from /proc) is slow, not hung, and
        gets SLOW_STALL_FACTOR times longer
      - nothing at all within the start-up timeout: a failure
    after a failure the others keep running for --after-failure-s, so the report shows how they
    reacted (the controller's watchdog holding), then `up` stops everything and exits 1.

A hung process keeps its pid and often its liveliness token (the Zenoh lease outlives short
stalls), so an exit alone would miss it: a 14 s segmenter hang once ended in a mid-air LANDED
with `up` reporting nothing.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from dovesei.shared.messages import EpisodeResult
from dovesei.shared.zconfig import ADDRESS_IN_USE
from dovesei.up.children import Children, describe_exit, last_error_line
from dovesei.up.launch import odometry_after_result_s
from dovesei.up.monitor import Monitor, Recorder
from dovesei.up.options import UpOptions
from dovesei.up.report import Failure

log = logging.getLogger("dovesei.up")

RESULT_AFTER_EXIT_S = 2.0  # a sim that exits right after publishing: give the result time to arrive
RESULT_CONFIRM_S = 10.0  # a result is the sim's only if the sim ends its run within this long after it
# A stream not heard yet gets this long beyond --stall-s: a model's first inference (warm-up), or
# the sim loading its world while a real vehicle's states already flow.
FIRST_MESSAGE_GRACE_S = 30.0
RESULT_POSITION_TOLERANCE_M = 10.0  # result's final position vs the last recorded state
RESULT_TRUTH_TOLERANCE_M = 100.0  # the same when the judge has the true pose and the states an estimate
DRAIN_SLICE_S = 0.05  # the watch loops hand the recorder at most this much work between their checks
# Waiting for an autopilot's landing after the hand-over: the hand-over altitude at this slowest
# descent (ArduCopter's LAND_SPEED is 0.5 m/s below LAND_ALT_LOW; a precision landing also moves
# over the spot first), plus a margin.
LANDING_MODES = ("LAND", "PRECLAND")
LANDING_MODE_GRACE_S = 10.0  # the adapter asks for LAND each second for 5 s
# A silent service that kept computing through its silence (at least this share of one core, and
# BUSY_MIN_CPU_S in all) is slow, not hung: on an overloaded host one heatmap took 23 s of wall
# time and `up` called a working segmenter hung. It is called hung only after SLOW_STALL_FACTOR
# times --stall-s. A stopped or deadlocked process uses no CPU and is named after --stall-s.
BUSY_CPU_FRACTION = 0.05
BUSY_MIN_CPU_S = 0.3
SLOW_STALL_FACTOR = 6.0
CPU_SAMPLE_S = 1.0  # how often each child's CPU time is read


@dataclass(frozen=True)
class WatchEnd:
    failure: Failure | None
    interrupted: bool


@dataclass(frozen=True)
class LandingWait:
    """How the wait for the autopilot's own landing ended."""

    landed: bool
    reason: str
    waited_s: float


def exits_seen(monitor: Monitor, children: Children) -> list[tuple[str, int]]:
    """The children that have exited, once the monitor has caught up with what they sent before
    (a sim exits right after its result, a controller after its last status: while those still
    wait in our queue, no exit is judged)."""
    return children.exited() if monitor.backlog == 0 else []


def wait_for_landing(rec: Recorder, monitor: Monitor, children: Children, stop: threading.Event,
                     timeout_s: float, stall_s: float, *, external_nav: bool = False) -> LandingWait:
    """After a 'land' or 'precland' hand-over: keep the controller running until the autopilot has landed.

    The controller is the one owner of the link and, for a precision landing, streams the spot
    as LANDING_TARGET: stopped at the hand-over (0.53 s after it on ArduCopter SITL), the target
    died before the autopilot's estimator had initialised and the vehicle landed blind. Landed
    means the autopilot reports itself disarmed (both autopilots disarm after a LAND). The wait
    also ends, unlanded, when the autopilot leaves its landing mode (a pilot took over), the
    controller exits, the states stop for `stall_s`, the operator stops `up`, or at `timeout_s`.

    With `external_nav` (`--gnss-denied external-nav`, any hand-over action) the autopilot's EKF
    flies on the camera's velocity that the controller streams from the sim's odometry: both must
    outlive the episode until the vehicle has landed and disarmed, whatever its mode (a pilot who
    takes over in LOITER needs that velocity too), or ArduCopter's EKF failsafe comes about 5 s
    after they stop (SITL). The wait then also ends when the sim (the odometry) exits.
    """
    t0 = time.monotonic()
    seen_landing_mode = False
    last_state_wall_s = time.time()
    count = len(rec.states)

    def end(landed: bool, reason: str) -> LandingWait:
        log.log(logging.INFO if landed else logging.WARNING, "landing: %s", reason)
        return LandingWait(landed, reason, round(time.monotonic() - t0, 3))

    log.info("hand-over done: waiting up to %.0f s for the autopilot to land (Ctrl-C ends the wait)", timeout_s)
    while True:
        monitor.drain(max_s=DRAIN_SLICE_S)
        now = time.monotonic()
        if len(rec.states) > count:
            count, last_state_wall_s = len(rec.states), time.time()
        state = rec.states[-1] if rec.states else None
        if state is not None:
            if not state.armed:
                return end(True, f"the autopilot disarmed in {state.mode or 'its mode'} after "
                                 f"{now - t0:.1f} s, at {state.alt_agl_m:.1f} m")
            if state.mode in LANDING_MODES:
                seen_landing_mode = True
            elif external_nav:
                pass  # whatever the mode, the EKF needs the camera's velocity until the motors stop
            elif seen_landing_mode or now - t0 > LANDING_MODE_GRACE_S:
                return end(False, f"the autopilot is in {state.mode or 'an unknown mode'}, not landing "
                                  "(a pilot or another station took over): not waiting")
        if stop.is_set():
            return end(False, "the operator ended the wait: the autopilot lands on its own, without our target")
        needed = ("controller", "sim") if external_nav else ("controller",)
        dead = [name for name, _ in exits_seen(monitor, children) if name in needed]
        if dead:
            what = "the camera's odometry (the sim)" if dead[0] == "sim" else "the controller"
            return end(False, f"{what} exited before the autopilot landed")
        if time.time() - last_state_wall_s > stall_s:
            return end(False, f"no vehicle state for {stall_s:g} s")
        if now - t0 > timeout_s:
            return end(False, f"not landed within {timeout_s:.0f} s: stopping (the autopilot goes on landing "
                              "on its own)")
        stop.wait(0.05)


def stream_owners(options: UpOptions) -> dict[str, str]:
    """Which service's liveness each watched stream proves."""
    owners = {"status": "controller", "heatmap": "segmenter"}
    if options.vehicle_url:
        # The controller publishes the autopilot's states; the sim (camera mode) only frames.
        owners["camera"] = "sim"
    else:
        owners["state"] = "sim"
    return owners


def stalled_service(rec: Recorder, owners: dict[str, str], now_wall_s: float, stall_s: float,
                    lockstep: bool = False, stopped: frozenset[str] = frozenset(),
                    heard: Mapping[str, float] | None = None) -> tuple[str, str] | None:
    """(service, stream) whose stream went silent first, once any watched stream is over `stall_s` old.

    Watching begins with the episode (the first state): before it every service may still load.
    `stopped` names services the kernel reports stopped: in lockstep one stopped process silences
    the others waiting for it and which stream falls silent first is a race, so a stopped one is
    named first (its oldest stream). `heard`: when each stream was last heard (wall s; default the
    recorder's valid messages).
    """
    if rec.first_state_wall_s is None:
        return None
    heard = rec.last_recv_wall_s if heard is None else heard
    ages: dict[str, float] = {}
    for topic in owners:
        last = heard.get(topic)
        if last is None:
            # Never heard: counted from the episode's start, with a warm-up allowance.
            last = rec.first_state_wall_s + FIRST_MESSAGE_GRACE_S
        ages[topic] = now_wall_s - last
    if not any(age > stall_s for age in ages.values()):
        return None
    own = {t: age for t, age in ages.items() if owners[t] in stopped}
    if own:
        topic = max(own, key=own.get)
        return owners[topic], topic
    topic = max(ages, key=ages.get)
    if lockstep and owners[topic] == "sim" and _owes_command(rec):
        # In lockstep the sim waits for the answer to its last state: a controller that hung after
        # its status but before its command silences the sim first, and is the one to name.
        return "controller", "cmd"
    return owners[topic], topic


def _proc_stat(pid: int) -> list[str] | None:
    """The fields of /proc/<pid>/stat after "(comm)" (comm may hold spaces and parentheses), the
    state first; None wherever that cannot be read (not Linux, the process gone)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            return f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def process_stopped(pid: int) -> bool:
    """True when the kernel says the process is stopped (SIGSTOP, a debugger): Linux /proc only;
    False wherever that cannot be read."""
    fields = _proc_stat(pid)
    return bool(fields) and fields[0] in ("T", "t")


def process_cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system, all threads) the process has used: Linux /proc only; None
    wherever that cannot be read."""
    fields = _proc_stat(pid)
    try:
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK") if fields else None
    except (IndexError, ValueError):
        return None


class CpuHistory:
    """Each child's CPU time, sampled about once a second: how much a silent service computed."""

    def __init__(self, read: Callable[[int], float | None] = process_cpu_s, keep_s: float = 600.0) -> None:
        self._read = read
        self._samples: dict[str, deque[tuple[float, float]]] = {}
        self._keep = max(2, int(keep_s / CPU_SAMPLE_S))
        self._last_wall_s = -math.inf

    def sample(self, pids: dict[str, int], now_wall_s: float) -> None:
        if now_wall_s - self._last_wall_s < CPU_SAMPLE_S:
            return
        self._last_wall_s = now_wall_s
        for name, pid in pids.items():
            cpu = self._read(pid)
            if cpu is not None:
                self._samples.setdefault(name, deque(maxlen=self._keep)).append((now_wall_s, cpu))

    def used_since(self, name: str, pid: int, since_wall_s: float, now_wall_s: float) -> tuple[float, float] | None:
        """(CPU seconds, wall seconds) from the newest sample at or before `since_wall_s` (else the
        oldest one) to a reading now (only asked while a stream is silent); None without a sample
        or a reading."""
        samples = self._samples.get(name)
        now_cpu = self._read(pid)
        if not samples or now_cpu is None:
            return None
        start = next((s for s in reversed(samples) if s[0] <= since_wall_s), samples[0])
        return now_cpu - start[1], now_wall_s - start[0]


def busy_through(used: tuple[float, float] | None) -> bool:
    """Did a service that used (CPU seconds, over wall seconds) of its silence keep computing?"""
    return used is not None and used[0] >= max(BUSY_MIN_CPU_S, BUSY_CPU_FRACTION * used[1])


def _owes_command(rec: Recorder) -> bool:
    """True when the newest state arrived after the newest command (nobody answered it yet)."""
    state_s, cmd_s = rec.last_recv_wall_s.get("state"), rec.last_recv_wall_s.get("cmd")
    return state_s is not None and (cmd_s is None or cmd_s < state_s)


def result_is_consistent(rec: Recorder, result: EpisodeResult, judged_at_truth: bool = False) -> str:
    """'' when the result agrees with the last recorded state, else why not.

    `judged_at_truth`: the sim judges at a true pose the recorded states do not carry (SITL's
    SIMSTATE, --sitl-truth) while the states are the autopilot's estimate, which drifts from it
    without GNSS (16.8 m at a SITL external-nav hand-over, up to 51 m on optical flow): the bound
    is then RESULT_TRUTH_TOLERANCE_M."""
    if not rec.states or not rec.states[-1].pos_valid:
        # A vehicle without a position (a GNSS-denied vehicle profile) reports dead reckoning,
        # which drifts from the judge's truth by design: nothing to compare it with.
        return ""
    x0, y0, _ = rec.start
    north_m, east_m, _ = rec.states[-1].pos_local_ned_m
    off_m = math.hypot(result.final_x_m - (x0 + east_m), result.final_y_m - (y0 + north_m))
    bound_m = RESULT_TRUTH_TOLERANCE_M if judged_at_truth else RESULT_POSITION_TOLERANCE_M
    if off_m > bound_m:
        return (f"its final position is {off_m:.1f} m from the vehicle's last recorded state "
                f"(more than {bound_m:g} m)")
    return ""


def port_collision(failure: Failure | None, rec: Recorder) -> str | None:
    """The service that died because its loopback listen port was taken before it could bind it,
    when nothing has flown yet (no vehicle state); else None. Such a start can be retried."""
    if failure is None or failure.child is None or failure.returncode is None or rec.states:
        return None
    return failure.child if ADDRESS_IN_USE in failure.last_line else None


def wait_for_takeoff(rec: Recorder, monitor: Monitor, children: Children, stop: threading.Event,
                     timeout_s: float) -> WatchEnd:
    """--takeoff: the controller arms and climbs before it steers; its first status says it is done.

    A takeoff the autopilot refuses ends the controller with the reason (its last log line).
    """
    deadline = time.monotonic() + timeout_s
    while rec.status_count == 0:
        monitor.drain(max_s=DRAIN_SLICE_S)
        if stop.is_set():
            return WatchEnd(None, True)
        dead = exits_seen(monitor, children)
        if dead:
            name, code = dead[0]
            line = last_error_line(children.log_path(name))
            return WatchEnd(Failure(name, code, line, f"{name} (pid {children.procs[name].pid}) {describe_exit(code)} "
                                                      f"during the takeoff; last log line: {line or '(empty log)'}"),
                            False)
        if time.monotonic() > deadline:
            alt = f"{rec.states[-1].alt_agl_m:.1f} m" if rec.states else "no vehicle state"
            return WatchEnd(Failure("controller", None, "", f"the takeoff did not end within {timeout_s:.0f} s "
                                                           f"(last: {alt})"), False)
        stop.wait(0.02)
    # The controller's first status answers its first tick after the climb: the mission starts there.
    rec.mission_start_t_s = min(rec.statuses) if rec.statuses else None
    log.info("takeoff done at %.1f m: starting the sim", rec.states[-1].alt_agl_m if rec.states else float("nan"))
    return WatchEnd(None, False)


class Watcher:
    """The loop's state: pending result candidates, the failure (if any) and its deadline."""

    def __init__(self, options: UpOptions, rec: Recorder, monitor: Monitor, children: Children,
                 stop: threading.Event, t0: float, confirm_s: float = RESULT_CONFIRM_S,
                 cpu_s: Callable[[int], float | None] = process_cpu_s) -> None:
        self.options, self.rec, self.monitor, self.children, self.stop = options, rec, monitor, children, stop
        self.cpu = CpuHistory(cpu_s)
        self._slow_warned: set[str] = set()
        self.t0, self.confirm_s = t0, confirm_s
        self.owners = stream_owners(options)
        self.failure: Failure | None = None
        self.failure_deadline = math.inf
        self._seen_candidates = 0
        self._confirm_by = math.inf  # monotonic deadline of the oldest pending candidate

    def run(self) -> WatchEnd:
        """Record until an accepted result, a failure (plus --after-failure-s) or a stop."""
        while True:
            self.monitor.drain(max_s=DRAIN_SLICE_S)
            if self._check_result():
                return WatchEnd(self.failure, False)
            if self.stop.is_set():
                return WatchEnd(self.failure, True)
            now = time.monotonic()
            # Exits and silences are judged on what the children sent before: only once our own
            # queue has caught up (a sim exits right after its result, which may still wait there).
            if self.failure is None and self.monitor.backlog == 0:
                # While a result waits for the sim to finish, its streams have ended on purpose.
                pending = bool(self.rec.result_candidates) and now < self._confirm_by
                self.failure = (self._check_exits() or (None if pending else self._check_stalls())
                                or self._check_startup(now))
            elif self.failure is None and "episode" not in self.monitor.arrived:
                # Behind (a loaded host records slower than the streams come): a queue that never
                # empties must not hide a hang, so silences are judged on when each stream was
                # last heard, queued or not, as long as no result (ending the streams) came in.
                self.failure = self._check_stalls(heard=self.monitor.arrived)
            if self.failure is not None and self.failure_deadline == math.inf:
                log.error("%s", self.failure.message)
                # The others keep running for a while so the report shows how they reacted.
                # Nothing to watch after a start that failed on a taken port: `up` retries it.
                after_s = (0.0 if self.failure.child in (None, "sim") or port_collision(self.failure, self.rec)
                           else self.options.after_failure_s)
                self.failure_deadline = now + after_s
            if now >= self.failure_deadline:
                return WatchEnd(self.failure, False)
            self.stop.wait(0.005)

    # -- the episode's result -----------------------------------------------------------------

    def _check_result(self) -> bool:
        """True once a candidate is accepted as the sim's."""
        candidates = self.rec.result_candidates
        if len(candidates) > self._seen_candidates:
            if self._confirm_by == math.inf:
                self._confirm_by = time.monotonic() + self.confirm_s
            self._seen_candidates = len(candidates)
        if not candidates:
            return False
        sim = self.children.procs.get("sim")
        # With --gnss-denied external-nav the sim ends its run by dropping its liveliness token with the
        # result and keeps only the camera's odometry going (the autopilot's EKF flies on it).
        tail = odometry_after_result_s(self.options) > 0 and self.rec.alive.get("sim") is False
        if sim is not None and sim.poll() is None and not tail:
            if time.monotonic() < self._confirm_by:
                return False
            log.warning("%d episode result(s) ignored: the sim kept running after them, so they are not the "
                        "sim's (anyone on the network can put on the episode key)", len(candidates))
            self.rec.results_refused += len(candidates)
            candidates.clear()
            self._seen_candidates, self._confirm_by = 0, math.inf
            return False
        # The sim has ended its run: the newest consistent candidate is its result.
        for result, recv_wall_s in reversed(candidates):
            why = result_is_consistent(self.rec, result, judged_at_truth=self.options.sitl_truth is not None)
            if not why:
                self.rec.results_refused += len(candidates) - 1
                self.rec.accept_result(result, recv_wall_s)
                log.info("episode result: %s after %.1f s of sim time (%s)", result.outcome, result.sim_time_s,
                         result.detail)
                return True
            log.warning("episode result %s refused: %s", result.outcome, why)
        self.rec.results_refused += len(candidates)
        candidates.clear()
        self._seen_candidates, self._confirm_by = 0, math.inf
        return False

    # -- failures -------------------------------------------------------------------------------

    def _check_exits(self) -> Failure | None:
        dead = self.children.exited()
        if not dead:
            return None
        name, code = dead[0]
        if name == "sim":
            # A sim that ended the episode publishes its result just before exiting (code 1 for an
            # 'error' ending, such as a silent controller): let the result arrive.
            deadline = time.monotonic() + RESULT_AFTER_EXIT_S
            while time.monotonic() < deadline:
                self.monitor.drain(max_s=DRAIN_SLICE_S)
                if self.rec.result_candidates:
                    return None  # _check_result takes it from here
                self.stop.wait(0.01)
        line = last_error_line(self.children.log_path(name))
        message = (f"{name} (pid {self.children.procs[name].pid}) {describe_exit(code)} before the episode ended; "
                   f"last log line: {line or '(empty log)'}")
        return Failure(name, code, line, message)

    def _check_stalls(self, heard: Mapping[str, float] | None = None) -> Failure | None:
        """A hung service's failure, judged on `heard` (`stalled_service`), else None."""
        now_wall = time.time()
        self.cpu.sample({n: p.pid for n, p in self.children.procs.items()}, now_wall)
        stopped = frozenset(n for n, proc in self.children.procs.items() if process_stopped(proc.pid))
        stall_s = self.options.stall_s
        heard = self.rec.last_recv_wall_s if heard is None else heard
        stalled = stalled_service(self.rec, self.owners, now_wall, stall_s,
                                  lockstep=self.options.lockstep, stopped=stopped, heard=heard)
        if stalled is None:
            self._slow_warned.clear()
            return None
        name, topic = stalled
        last = heard.get(topic)
        silent_s = now_wall - (last if last is not None else self.rec.first_state_wall_s + FIRST_MESSAGE_GRACE_S)
        # In lockstep everyone waits for the slowest, so anyone computing keeps the run alive.
        # A stopped process is named at once: nothing it waits for is slow.
        procs = self.children.procs
        computing = [] if stopped else [
            n for n in (procs if self.options.lockstep else (name,))
            if n in procs and busy_through(self.cpu.used_since(n, procs[n].pid, now_wall - silent_s, now_wall))]
        silent = f"no {topic} message for {silent_s:.1f} s" if last is not None else f"no {topic} message yet"
        if computing and silent_s < SLOW_STALL_FACTOR * stall_s:
            if name not in self._slow_warned:
                self._slow_warned.add(name)
                log.warning("%s slow, not hung: %s while %s kept computing (an overloaded host?); called hung "
                            "after %g s", name, silent, " and ".join(computing), SLOW_STALL_FACTOR * stall_s)
            return None
        token = {True: "its liveliness token is still visible: alive but stuck",
                 False: "its liveliness token was dropped (its Zenoh session is gone)", None: "no liveliness token seen"}[self.rec.alive.get(name)]
        proc = self.children.procs.get(name)
        pid = f" (pid {proc.pid})" if proc is not None else ""
        limit = (f"{SLOW_STALL_FACTOR:g} x --stall-s {stall_s:g}, still computing" if computing
                 else f"limit --stall-s {stall_s:g}")
        message = f"{name}{pid} hung: {silent} ({limit}); {token}"
        return Failure(name, None, last_error_line(self.children.log_path(name)), message)

    def _check_startup(self, now: float) -> Failure | None:
        rec = self.rec
        if rec.states or rec.status_count or now - self.t0 <= self.options.startup_timeout_s:
            return None
        return Failure(None, None, "", f"no vehicle state or controller status within "
                                       f"{self.options.startup_timeout_s:.0f} s of starting; see the logs in "
                                       f"{self.children.log_dir}")
