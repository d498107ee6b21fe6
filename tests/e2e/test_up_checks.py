"""`dovesei up` refuses bad input before any process starts, and judges what it sees.

Fast tests: the command line as a user types it (bad world, model directory, MAVLink URL, seed,
timing with a vehicle: exit 2, one line naming the flag, no traceback, no output folder left);
the exit codes; the watcher's calls on hung services and on episode results that are not the
sim's; the report's command count for a MAVLink vehicle and its nearest-time state labels.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dovesei.shared.codec import encode
from dovesei.shared.messages import CameraFrame, ControllerStatus, EpisodeResult, SafetyHeatmap, Stamp, VehicleState
from dovesei.shared.zconfig import free_port
from dovesei.up import EXIT_FAILED, EXIT_OK, EXIT_UNSAFE, UpOptions, build_report, exit_code
from dovesei.up.monitor import Monitor, Recorder, Sample
from dovesei.up.watch import (CpuHistory, Watcher, busy_through, process_cpu_s, result_is_consistent, stalled_service,
                               stream_owners)

REPO = Path(__file__).resolve().parents[2]
WORLD = "synthetic:size_m=400,seed=1"


def _up(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    return subprocess.run([sys.executable, "-m", "dovesei.cli", "up", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout_s, env=env)


@pytest.mark.parametrize("flags, names", [
    (["--world", "no/such/world"], "world 'no/such/world'"),
    (["--model", "no/such/dir"], "--model 'no/such/dir'"),
    (["--vehicle", "udpin:0.0.0.0"], "--vehicle-url 'udpin:0.0.0.0'"),  # --vehicle: the same flag
    (["--vehicle-url", "14550"], "--vehicle-url '14550'"),
    (["--vehicle-url", "serial:///dev/ttyACM0:921600"], "write the device and baud as /dev/ttyACM0,921600"),
    (["--vehicle-url", "/dev/dovesei-no-such-tty,921600"], "no such serial device /dev/dovesei-no-such-tty"),
    (["--vehicle", "udpin:127.0.0.1:14550", "--timing", "reference"], "--timing real"),
    (["--handover-action", "precland"], "--handover-action only applies with --vehicle-url"),
    (["--yaw-control", "autopilot"], "--yaw-control only applies with --vehicle-url"),
    (["--signing-key", "key"], "--signing-key only applies with --vehicle-url"),
    (["--autopilot-system-id", "1"], "--autopilot-system-id only applies with --vehicle-url"),
    (["--gnss-denied", "attitude"], "--gnss-denied only applies with --vehicle-url"),
    (["--vehicle-url", "udpin:127.0.0.1:14550", "--gnss-denied", "gps"], "--gnss-denied"),
    (["--vehicle-url", "udpin:127.0.0.1:14550", "--handover-action", "jump"], "--handover-action"),
    (["--vehicle-url", "udpin:127.0.0.1:14550", "--signing-key", "/no/such/key"], "--signing-key: MAVLink signing key"),
    (["--vehicle-url", "udpin:127.0.0.1:14550", "--autopilot-system-id", "0"], "--autopilot-system-id 0"),
    (["--seed", "-1"], "--seed -1"),
    (["--seed", "x"], "--seed"),
    (["--start", "1;2"], "--start '1;2'"),
    (["--policy", "nope"], "--policy 'nope'"),
    (["--noise", "-0.5"], "--noise"),
    (["--takeoff"], "--takeoff"),
    (["--connect", "nope"], "--connect 'nope'"),
    (["--stall-s", "0"], "--stall-s"),
])
def test_bad_input_is_one_line_naming_the_flag_before_anything_starts(tmp_path: Path, flags: list[str],
                                                                       names: str) -> None:
    out = tmp_path / "run"
    done = _up("--world", WORLD, "--out", str(out), *flags) if "--world" not in flags else _up("--out", str(out),
                                                                                               *flags)
    assert done.returncode == 2, done.stderr
    assert names in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert "started sim" not in done.stderr  # no service was started
    assert not out.exists(), "a failed up left its output folder behind"


def test_the_real_autopilot_flags_reach_the_controller_through_its_own_flags(tmp_path: Path) -> None:
    """--vehicle-url, --handover-action, --yaw-control, --signing-key and --autopilot-system-id become the
    controller's config, and its argv (from the controller's own table) parses back to it."""
    from dovesei.controller.service import CLI as CONTROLLER
    from dovesei.up.launch import child_commands, child_configs
    from dovesei.up.options import build_parser, options_from_args

    key = tmp_path / "signing.key"
    key.write_bytes(bytes(range(32)))
    options = options_from_args(build_parser().parse_args([
        "--vehicle", "udpout:127.0.0.1:14550", "--handover-action", "precland", "--yaw-control", "autopilot",
        "--signing-key", str(key), "--autopilot-system-id", "7", "--gnss-denied", "external-nav",
        "--out", str(tmp_path / "run")]))
    configs = child_configs(options, (100.0, 100.0, 60.0))
    c = configs.controller
    assert configs.sim.sim.odometry_rate_hz == 10.0  # the sim is the camera's visual odometry too
    assert (c.vehicle_url, c.handover_action, c.mavlink_yaw_control, c.mavlink_signing_key_file,
            c.mavlink_system_id, c.gnss_denied) == ("udpout:127.0.0.1:14550", "precland", "autopilot", str(key), 7,
                                                    "external-nav")
    argv = child_commands(options, configs, {"sim": 1, "segmenter": 2, "controller": 3, "monitor": 4},
                          tmp_path)["controller"]
    for flag, value in (("--vehicle-url", "udpout:127.0.0.1:14550"), ("--handover-action", "precland"),
                        ("--yaw-control", "autopilot"), ("--signing-key", str(key)), ("--autopilot-system-id", "7"),
                        ("--gnss-denied", "external-nav")):
        assert argv[argv.index(flag) + 1] == value, argv
    # Not given: the controller keeps its own defaults, and no flag is passed for them.
    plain = child_configs(options_from_args(build_parser().parse_args(["--vehicle-url", "udpout:127.0.0.1:14550"])),
                          (100.0, 100.0, 60.0)).controller
    assert (plain.handover_action, plain.mavlink_yaw_control, plain.mavlink_signing_key_file,
            plain.mavlink_system_id, plain.gnss_denied) == ("hold", "rate", None, None, "off")
    # The close look is on in `up` (its sim answers the crops) and off in a bare controller (nothing
    # may answer them), so it is the one flag `up` always passes.
    assert CONTROLLER.to_argv(plain) == ["--vehicle-url", "udpout:127.0.0.1:14550", "--close-look"]
    no_look = child_configs(options_from_args(build_parser().parse_args(
        ["--vehicle-url", "udpout:127.0.0.1:14550", "--no-close-look"])), (100.0, 100.0, 60.0)).controller
    assert CONTROLLER.to_argv(no_look) == ["--vehicle-url", "udpout:127.0.0.1:14550"]
    assert child_configs(options_from_args(build_parser().parse_args(["--vehicle-url", "udpout:127.0.0.1:14550"])),
                         (100.0, 100.0, 60.0)).sim.sim.odometry_rate_hz == 0.0


def test_health_refuses_bad_flags_in_one_line() -> None:
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    for flags, names in ((["--timeout-s", "-1"], "--timeout-s"), (["--connect", "nope"], "--connect 'nope'"),
                         (["--vehicle-id", "a/b"], "vehicle id 'a/b'")):
        done = subprocess.run([sys.executable, "-m", "dovesei.cli", "health", "--service", "sim", *flags], cwd=REPO,
                              capture_output=True, text=True, timeout=60, env=env)
        assert done.returncode == 2 and names in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_a_model_directory_without_weights_is_refused(tmp_path: Path) -> None:
    model = tmp_path / "model"
    model.mkdir()
    done = _up("--world", WORLD, "--model", str(model), "--out", str(tmp_path / "run"))
    assert done.returncode == 2 and "config.json" in done.stderr, done.stderr
    (model / "config.json").write_text("{}")
    done = _up("--world", WORLD, "--model", str(model), "--out", str(tmp_path / "run"))
    assert done.returncode == 2 and "no weights" in done.stderr, done.stderr
    assert not (tmp_path / "run").exists()


def test_a_taken_mavlink_port_is_refused_before_start(tmp_path: Path) -> None:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        done = _up("--world", WORLD, "--vehicle", f"udpin:127.0.0.1:{port}", "--out", str(tmp_path / "run"))
    assert done.returncode == 2 and f"cannot bind 127.0.0.1:{port}" in done.stderr, done.stderr
    assert not (tmp_path / "run").exists()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        free = free_port(socket.SOCK_DGRAM)  # the controller's port is free: only the sim's is taken
        done = _up("--world", WORLD, "--vehicle", f"udpin:127.0.0.1:{free}", "--sitl-truth", f"udpin:127.0.0.1:{port}",
                   "--out", str(tmp_path / "run"))
    assert done.returncode == 2 and f"--sitl-truth 'udpin:127.0.0.1:{port}': cannot bind" in done.stderr, done.stderr


# ---------------------------------------------------------------- exit codes and the report


def _result(outcome: str, x_m: float = 1.0, y_m: float = 2.0) -> EpisodeResult:
    return EpisodeResult("uav1", Stamp(5.0, "sim"), outcome, 5.0, 10.0, x_m, y_m, 20.0, ("grass",), detail="detail")


def _state(k: int, t_s: float, north_m: float = 0.0) -> VehicleState:
    return VehicleState("uav1", k, Stamp(t_s, "sim"), 50.0, (0.0, 0.0, 0.0), pos_valid=True,
                        pos_local_ned_m=(north_m, 0.0, -50.0))


def _status(k: int, t_s: float, state: str) -> ControllerStatus:
    return ControllerStatus("uav1", k, Stamp(t_s, "sim"), "dovesei", state, "ok", "", 0, 0.0, 10.0)


def _report(opts: UpOptions, rec: Recorder, stats: dict | None = None):
    return build_report(opts, rec, (1.0, 2.0, 100.0), 0.0, stats or {}, None, False, 1.0)


@pytest.mark.parametrize("outcome, code", [("safe", EXIT_OK), ("unsafe", EXIT_UNSAFE), ("timeout", EXIT_UNSAFE),
                                           ("out_of_world", EXIT_UNSAFE), ("error", EXIT_FAILED),
                                           ("not_judged", EXIT_UNSAFE)])
def test_exit_code_follows_the_judge(tmp_path: Path, outcome: str, code: int) -> None:
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.accept_result(_result(outcome), 0.0)
    report = _report(UpOptions(world=WORLD, out=tmp_path), rec)
    assert exit_code(report) == code and report.to_dict()["outcome"] == outcome


def test_a_mavlink_run_counts_the_setpoints_the_controller_sent(tmp_path: Path) -> None:
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    for k in range(4):
        rec.handle(Sample("status", 0.0, encode(_status(k, 0.05 * k, "HANDOVER" if k == 3 else "SEARCHING"))))
    opts = UpOptions(world=WORLD, out=tmp_path, vehicle_url="udpin:127.0.0.1:14550", timing="real")
    counts = _report(opts, rec, {"controller": {"commands_sent": 3269}}).to_dict()["counts"]
    assert counts["commands"] == 3269 and counts["commands_measured_by"] == "controller"
    # Without the controller's stats (it was killed): one command per status outside the hand-over.
    counts = _report(opts, rec).to_dict()["counts"]
    assert counts["commands"] == 3 and counts["commands_measured_by"] == "controller status"
    # A simulated vehicle: the commands seen on the cmd key.
    assert _report(UpOptions(world=WORLD, out=tmp_path), rec).counts.commands_measured_by == "monitor"


def test_states_take_the_label_of_the_nearest_status_not_an_exact_stamp() -> None:
    rec = Recorder((0.0, 0.0, 50.0), video=False)
    # The autopilot's states at 10 Hz; the controller's statuses 30 ms off them, changing state at 0.43 s.
    for k in range(8):
        rec.handle(Sample("state", 0.0, encode(_state(k, 0.1 * k))))
    for k in range(8):
        rec.handle(Sample("status", 0.0, encode(_status(k, 0.1 * k + 0.03, "AIMING" if k >= 4 else "SEARCHING"))))
    traj = rec.trajectory()
    assert traj["state"] == ["SEARCHING"] * 4 + ["AIMING"] * 4, traj["state"]


# ---------------------------------------------------------------- the watcher


class _Proc:
    def __init__(self, pid: int, running: bool = True) -> None:
        self.pid, self.running = pid, running
        self.returncode = None if running else 0

    def poll(self) -> int | None:
        return None if self.running else self.returncode


class _Children:
    def __init__(self, log_dir: Path, sim_running: bool) -> None:
        self.log_dir = log_dir
        self.procs = {"sim": _Proc(11, sim_running), "segmenter": _Proc(12), "controller": _Proc(13)}

    def exited(self) -> list[tuple[str, int]]:
        return [(n, p.returncode) for n, p in self.procs.items() if p.poll() is not None]

    def log_path(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"


class _Monitor:
    backlog = 0
    arrived: dict[str, float] = {}  # noqa: RUF012 - never written: a fake with nothing queued

    def drain(self, max_s: float = float("inf")) -> int:
        return 0


def test_a_backlog_is_drained_in_slices_so_a_ctrl_c_is_seen_at_once(tmp_path: Path) -> None:
    # Under load a lockstep flight queued messages faster than the recorder took them: one drain
    # of up to 10,000 kept `up` from its stop check for 24 s, and a Ctrl-C was lost until the end.
    from collections import deque  # noqa: PLC0415

    class SlowRecorder:
        def __init__(self) -> None:
            self.n = 0

        def handle(self, _sample: object) -> None:
            time.sleep(0.001)
            self.n += 1

    mon = Monitor.__new__(Monitor)  # the queue and the recorder, without a Zenoh session
    mon._queue, mon.recorder = deque(range(3000)), SlowRecorder()
    t0 = time.monotonic()
    n = mon.drain(max_s=0.05)
    assert 0 < n < 3000 and mon.backlog == 3000 - n and time.monotonic() - t0 < 1.0
    assert mon.drain() == 3000 - n and mon.backlog == 0  # the final drain takes everything

    class Backlogged(_Monitor):
        backlog = 5000  # never caught up: no exit is judged yet, and the stop still counts

        def __init__(self) -> None:
            self.arrived = {}

        def drain(self, max_s: float = float("inf")) -> int:
            time.sleep(min(max_s, 0.05))
            self.arrived.update(dict.fromkeys(("state", "status", "heatmap"), time.time()))  # all still coming
            return 50

    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.first_state_wall_s = time.time() - 600.0  # every stream long silent, were the backlog not there
    t0 = time.monotonic()
    end = Watcher(UpOptions(world=WORLD, out=tmp_path, stall_s=1.0), rec, Backlogged(),
                  _Children(tmp_path, sim_running=False), stop, t0, cpu_s=lambda pid: 1.0).run()
    assert end.interrupted and end.failure is None and time.monotonic() - t0 < 2.0


def test_a_hang_is_named_while_the_recording_runs_behind(tmp_path: Path) -> None:
    # A CI run beside two benches (load 6 on 2 cores): `up` recorded slower than the streams came,
    # its queue never emptied, and a stopped controller went unnamed for 300 s. Behind, silences
    # are judged on when each stream last arrived, queued or not.
    class Behind(_Monitor):
        backlog = 5000

        def __init__(self) -> None:
            now = time.time()
            self.arrived = {"state": now, "heatmap": now, "status": now - 2.0}  # the controller went quiet

        def drain(self, max_s: float = float("inf")) -> int:
            time.sleep(min(max_s, 0.02))
            self.arrived["state"] = self.arrived["heatmap"] = time.time()
            return 50

    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.first_state_wall_s = time.time() - 60.0
    rec.last_recv_wall_s.update(dict.fromkeys(("state", "status", "heatmap"), time.time() - 30.0))  # recorded: long ago
    t0 = time.monotonic()
    end = Watcher(UpOptions(world=WORLD, out=tmp_path, stall_s=1.0, after_failure_s=0.2), rec, Behind(),
                  _Children(tmp_path, sim_running=True), threading.Event(), t0, cpu_s=lambda pid: 1.0).run()
    assert end.failure is not None and end.failure.child == "controller", end.failure
    assert "controller (pid 13) hung: no status message for" in end.failure.message
    assert time.monotonic() - t0 < 5.0
    # A result among the arrivals ends the streams on purpose: no silence is judged while behind.
    quiet = Behind()
    quiet.arrived["episode"] = time.time()
    stop = threading.Event()
    threading.Timer(1.5, stop.set).start()
    end = Watcher(UpOptions(world=WORLD, out=tmp_path, stall_s=1.0), rec, quiet,
                  _Children(tmp_path, sim_running=True), stop, time.monotonic(), cpu_s=lambda pid: 1.0).run()
    assert end.interrupted and end.failure is None


def test_a_result_while_the_sim_keeps_flying_is_not_the_sims(tmp_path: Path) -> None:
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.handle(Sample("state", time.time(), encode(_state(0, 0.0))))
    rec.handle(Sample("episode", time.time(), encode(_result("safe"))))  # forged: the sim is still running
    stop = threading.Event()
    children = _Children(tmp_path, sim_running=True)
    watcher = Watcher(UpOptions(world=WORLD, out=tmp_path, stall_s=30.0), rec, _Monitor(), children, stop,
                      time.monotonic(), confirm_s=0.2)
    timer = threading.Timer(1.0, stop.set)
    timer.start()
    try:
        end = watcher.run()
    finally:
        timer.cancel()
    assert end.interrupted and rec.result is None and rec.results_refused == 1


def test_the_sims_result_is_taken_once_it_has_ended_its_run(tmp_path: Path) -> None:
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.handle(Sample("state", time.time(), encode(_state(0, 0.0))))
    # One far from where the vehicle was (refused), then the sim's own.
    rec.handle(Sample("episode", time.time(), encode(_result("safe", x_m=300.0))))
    rec.handle(Sample("episode", time.time(), encode(_result("unsafe"))))
    watcher = Watcher(UpOptions(world=WORLD, out=tmp_path), rec, _Monitor(), _Children(tmp_path, sim_running=False),
                      threading.Event(), time.monotonic())
    end = watcher.run()
    assert end.failure is None and rec.result is not None and rec.result.outcome == "unsafe"
    rec2 = Recorder((1.0, 2.0, 100.0), video=False)
    rec2.handle(Sample("state", time.time(), encode(_state(0, 0.0))))
    rec2.handle(Sample("episode", time.time(), encode(_result("safe", x_m=300.0))))
    stop = threading.Event()
    timer = threading.Timer(4.0, stop.set)
    timer.start()
    try:
        end = Watcher(UpOptions(world=WORLD, out=tmp_path), rec2, _Monitor(), _Children(tmp_path, sim_running=False),
                      stop, time.monotonic()).run()
    finally:
        timer.cancel()
    # Its only result did not match the flight: no result, and the sim's exit is the failure.
    assert rec2.result is None and rec2.results_refused == 1 and end.failure is not None
    assert end.failure.child == "sim"


def test_a_result_judged_at_the_sitl_truth_may_lie_where_the_estimate_drifted_from() -> None:
    # SITL external-nav: the judge had SIMSTATE's true pose 16.8 m from the EKF's last state.
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.handle(Sample("state", time.time(), encode(_state(0, 0.0))))
    drifted, forged = _result("safe", x_m=1.0 + 16.8), _result("safe", x_m=300.0)
    assert "16.8 m from the vehicle's last recorded state" in result_is_consistent(rec, drifted)
    assert result_is_consistent(rec, drifted, judged_at_truth=True) == ""
    assert "more than 100 m" in result_is_consistent(rec, forged, judged_at_truth=True)


def test_the_service_whose_stream_went_quiet_first_is_named() -> None:
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    owners = stream_owners(UpOptions(world=WORLD))
    assert owners == {"status": "controller", "heatmap": "segmenter", "state": "sim"}
    assert stalled_service(rec, owners, 1000.0, 5.0) is None  # before the episode: everything may still load
    rec.first_state_wall_s = 100.0
    rec.last_recv_wall_s = {"state": 200.0, "status": 199.0, "heatmap": 200.0}
    assert stalled_service(rec, owners, 203.0, 5.0) is None
    # A hung controller in lockstep: its status stops first, everything downstream follows.
    assert stalled_service(rec, owners, 205.0, 5.0) == ("controller", "status")
    rec.last_recv_wall_s = {"state": 210.0, "status": 210.0, "heatmap": 199.0}
    assert stalled_service(rec, owners, 210.0, 5.0) == ("segmenter", "heatmap")
    # A controller that hung after its status but before its command: in lockstep the sim waits
    # for that command and its state stream goes quiet first; the controller owes the answer.
    rec.last_recv_wall_s = {"state": 200.0, "status": 200.5, "heatmap": 200.2, "cmd": 199.9}
    assert stalled_service(rec, owners, 206.0, 5.0) == ("sim", "state")
    assert stalled_service(rec, owners, 206.0, 5.0, lockstep=True) == ("controller", "cmd")
    rec.last_recv_wall_s["cmd"] = 200.6  # the state was answered: the sim is the one that stopped
    assert stalled_service(rec, owners, 206.0, 5.0, lockstep=True) == ("sim", "state")
    # A vehicle: the controller publishes the states, the sim only frames.
    assert stream_owners(UpOptions(world=WORLD, vehicle_url="udpin:127.0.0.1:1", timing="real"))["camera"] == "sim"


def test_report_json_keeps_the_keys_readers_use(tmp_path: Path) -> None:
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.handle(Sample("state", 0.0, encode(_state(0, 0.0))))
    rec.accept_result(_result("safe"), 0.0)
    doc = json.loads(json.dumps(_report(UpOptions(world=WORLD, out=tmp_path), rec).to_dict()))
    for key in ("outcome", "detail", "judged", "sim_time_s", "path_length_m", "start", "final", "classes_found",
                "closest_unsafe_m", "world", "backend", "simulated", "segmenter_option", "noise", "policy", "timing",
                "seed", "mode", "vehicle", "vehicle_id", "safety_radius_m", "time_limit_s", "wall_time_s",
                "episode_wall_s", "latency_ms", "transport_overhead_ms", "zenoh_delivery_overhead_ms", "delivery_ms",
                "counts", "service_stats", "failure", "interrupted", "trajectory"):
        assert key in doc, key
    assert doc["outcome"] == "safe" and doc["judged"] is True and doc["final"] == {"x_m": 1.0, "y_m": 2.0,
                                                                                    "alt_m": 20.0}
    assert set(doc["latency_ms"]["policy"]) == {"p50", "p99", "n"}


def test_the_watcher_ends_the_run_naming_a_silent_service(tmp_path: Path) -> None:
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    now = time.time()
    for topic in ("state", "status"):
        rec.handle(Sample(topic, now, encode(_state(0, 0.0) if topic == "state" else _status(0, 0.0, "AIMING"))))
    rec.first_state_wall_s = now - 60.0
    rec.last_recv_wall_s["heatmap"] = now - 2.0  # the segmenter's last heatmap, then silence
    rec.handle(Sample("alive", now, b"segmenter", True))

    class _Fresh(_Monitor):
        def drain(self, max_s: float = float("inf")) -> int:  # the sim and the controller go on
            rec.last_recv_wall_s["state"] = rec.last_recv_wall_s["status"] = time.time()
            return 0

    t0 = time.monotonic()
    idle = lambda pid: 1.0  # noqa: E731 - no CPU used: stuck, not slow
    end = Watcher(UpOptions(world=WORLD, out=tmp_path, stall_s=1.0, after_failure_s=0.5), rec, _Fresh(),
                  _Children(tmp_path, sim_running=True), threading.Event(), t0, cpu_s=idle).run()
    assert end.failure is not None and end.failure.child == "segmenter" and end.failure.returncode is None
    assert "segmenter (pid 12) hung: no heatmap message for" in end.failure.message
    assert "still visible" in end.failure.message and "limit --stall-s 1)" in end.failure.message
    assert 0.5 <= time.monotonic() - t0 < 5.0  # found at once (the heatmap was already 2 s old) + 0.5 s after


def test_a_silent_service_still_computing_is_slow_not_hung_until_six_stalls(tmp_path: Path) -> None:
    # On an overloaded host one heatmap took 23 s of wall time: `up` called a working segmenter hung.
    rec = Recorder((1.0, 2.0, 100.0), video=False)
    rec.first_state_wall_s = time.time() - 60.0
    for topic in ("state", "status", "heatmap", "camera"):
        rec.last_recv_wall_s[topic] = time.time()
    t0 = time.monotonic()
    busy = lambda pid: time.monotonic() - t0 if pid == 12 else 1.0  # noqa: E731 - a whole core

    class _Fresh(_Monitor):
        def drain(self, max_s: float = float("inf")) -> int:  # everything but the segmenter goes on
            for topic in ("state", "status", "camera"):
                rec.last_recv_wall_s[topic] = time.time()
            return 0

    end = Watcher(UpOptions(world=WORLD, out=tmp_path, stall_s=0.5, after_failure_s=0.0), rec, _Fresh(),
                  _Children(tmp_path, sim_running=True), threading.Event(), t0, cpu_s=busy).run()
    silent = time.time() - rec.last_recv_wall_s["heatmap"]  # on the clock the watcher judges by
    assert end.failure is not None and end.failure.child == "segmenter"
    assert "6 x --stall-s 0.5, still computing" in end.failure.message
    assert 6 * 0.5 <= silent < 10.0  # not after 0.5 s: after six times that


def test_cpu_history_tells_the_cpu_used_over_a_silence() -> None:
    cpu = {1: 0.0}
    history = CpuHistory(lambda pid: cpu.get(pid))
    for t in range(5):
        cpu[1] = 0.2 * t
        history.sample({"segmenter": 1, "gone": 2}, 100.0 + t)
    cpu[1] = 1.0
    assert history.used_since("segmenter", 1, 101.5, 105.0) == pytest.approx((0.8, 4.0))  # from the sample at 101
    assert history.used_since("segmenter", 1, 90.0, 105.0) == pytest.approx((1.0, 5.0))  # from the oldest
    assert history.used_since("gone", 2, 103.0, 105.0) is None
    assert busy_through((0.6, 3.0)) and not busy_through((0.1, 3.0)) and not busy_through(None)
    assert not busy_through((0.4, 20.0))  # 2 % of a core over 20 s: idle polling, not work
    assert process_cpu_s(os.getpid()) is not None and process_cpu_s(2 ** 22 + 7) is None


def test_a_run_that_fails_before_writing_leaves_no_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import dovesei.up as up
    from dovesei.shared.errors import DoveseiError

    def no_session(*_args, **_kwargs) -> int:
        raise DoveseiError("the monitor's Zenoh session could not open")

    monkeypatch.setattr(up, "_fly", no_session)
    checked = (None, (1.0, 2.0, 100.0), None)  # what preflight would hand over; _fly never looks
    with pytest.raises(DoveseiError):
        up.run(UpOptions(world=WORLD, out=tmp_path / "new" / "run"), stop=threading.Event(), checked=checked)
    assert not (tmp_path / "new").exists()
    mine = tmp_path / "mine"  # a folder the user made stays, and stays as it was
    mine.mkdir()
    with pytest.raises(DoveseiError):
        up.run(UpOptions(world=WORLD, out=mine), stop=threading.Event(), checked=checked)
    assert mine.is_dir() and list(mine.iterdir()) == []


@pytest.mark.parametrize(("argv", "expected"), [
    ([], "reference"),
    (["--policy", "clearance"], "real"),  # its own true-second timers: the 78 sim s limit would cut it short
    (["--policy", "clearance", "--timing", "reference"], "reference"),  # an explicit choice stands
    (["--policy", "dovesei-nofocus"], "reference"),
])
def test_timing_default_follows_the_policy(argv: list[str], expected: str) -> None:
    from dovesei.up.options import build_parser, options_from_args  # lazy: only this test parses

    assert options_from_args(build_parser().parse_args(argv)).timing == expected


def test_a_heatmap_and_status_that_overtake_their_camera_frame_still_reach_the_video() -> None:
    rec = Recorder((0.0, 0.0, 50.0), video=True, video_period_s=0.5)
    img = np.zeros((64, 64, 3), np.uint8)
    prob = np.full((64, 64), 200, np.uint8)

    def heatmap(seq: int) -> bytes:
        return encode(SafetyHeatmap("uav1", seq, Stamp(0.5 * seq, "sim"), prob, 50.0, 1.2, "simulated", True,
                                    "p", "dovesei", 0.01))

    def status(seq: int) -> bytes:
        return encode(dataclasses.replace(_status(seq, 0.5 * seq + 0.1, "SEARCHING"), frame_seq=seq))

    def frame(seq: int) -> bytes:
        return encode(CameraFrame("uav1", seq, Stamp(0.5 * seq, "sim"), img, 1.2, 50.0))

    # Frame 0 in order; frame 1's heatmap and status arrive before the frame itself.
    for topic, payload in (("camera", frame(0)), ("heatmap", heatmap(0)), ("status", status(0)),
                           ("heatmap", heatmap(1)), ("status", status(1)), ("camera", frame(1))):
        rec.handle(Sample(topic, 0.0, payload))
    for seq in (0, 1):
        kept = rec.video_frames[seq]
        assert "prob" in kept and kept["status"].frame_seq == seq and "jpeg" in kept
    # A heatmap of a frame that already went by unkept is not held forever.
    rec.handle(Sample("heatmap", 0.0, heatmap(0)))
    assert 0 not in rec._early



def test_a_stopped_child_is_told_apart_from_a_running_one() -> None:
    import signal  # lazy: only this test signals a process

    from dovesei.up.watch import process_stopped  # lazy: only this test reads process states

    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert not process_stopped(proc.pid)
        os.kill(proc.pid, signal.SIGSTOP)
        deadline = time.monotonic() + 5.0
        while not process_stopped(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert process_stopped(proc.pid)
        os.kill(proc.pid, signal.SIGCONT)
    finally:
        proc.kill()
        proc.wait()
    assert not process_stopped(proc.pid)  # gone: nothing to read
