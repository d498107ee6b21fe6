"""Vehicle profiles: `ideal` is the sim as it always was; `realistic` reports an estimate, never the truth.

- ideal: episodes flown with it give the records captured from the code before profiles existed
  (the reference below was recorded at commit f3f3332 with the same jobs).
- realistic: every input of the controller and of the policy (state velocity, altitude,
  attitude; the frames' and heatmaps' altitude and attitude; the policy's Observation) differs
  from the sim's true pose at the same instant, and the frames are rendered tilted.
- the dynamics of a multirotor under ArduCopter: braking from 10 m/s in ~4.5 s, GUID_TIMEOUT's
  3 s of coasting, nose down to accelerate.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dovesei.bench import engines
from dovesei.episode import EpisodeSpec, build_cores
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import Stamp, VelocityCommand
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.dynamics import Pose, Vehicle, VehicleParams
from dovesei.sim.estimator import VEHICLE_PROFILES, vehicle_profile
from dovesei.sim.starts import Start
from dovesei.sim.world import load_world

WORLD = "synthetic:size_m=400,seed=1"

# Recorded with the code before vehicle profiles (commit f3f3332), `engines.run_job` of these jobs;
# since the judge ends an episode on the controller's hand-over (3 states at the altitude, then
# its command), 0.15 s later than the altitude crossing did: the same landing, 0.17 m lower. The
# clearance record is that of `clearance` since it lands where it checked (f7aefb9). Re-recorded
# for issue 24: people now walk and cars drive in every world (frames show them) and the simulated
# perception weighs a person or car by the tokens it covers. Before: dovesei 47.0 s, 87.956 m,
# landing at (290.224, 66.297); clearance 45.25 s, 80.455 m, at (290.721, 346.391). The same
# landings within 0.8 m. With the moving objects left out and the old constant salience the
# records were the old ones to the last digit (checked when re-recording). Re-recorded again for
# issue 25 and the close look: the realistic perception now draws a calibration and per-patch looks
# per episode (so `dovesei` read this seed's scene differently and took another safe spot, 52 m
# from the last one), and `clearance` holds at ~40 m for two clear close looks before descending
# (44.4 s -> 71.9 s, the same lawn within 4 m). Re-recorded for the scene thresholds' floor on the
# slack (level_slack_frac, c97402f): the re-checks of the footprint below pass more often, so the
# first descent went on to 39 m, where a close look saw the never set 3.9 m from the spot (P 0.40)
# and aborted it; the second spot, 8.3 m from the old landing, landed safe (71.9 s -> 126.35 s,
# nearest person 11.6 m). Re-recorded for the close look's blob rule and its 2-of-3 rejection: the
# first look at 42 m is clear, the next finds the never set 3.8 m away (P 0.40) and holds, the third
# again (P 0.51) and rejects the spot; the second spot lands safe 1.9 m from the last landing
# (126.35 s -> 126.7 s). Re-recorded when a close-look rejection stopped climbing back to the
# search altitude: the rejected first spot is followed at once by the next confirmed one from 42 m,
# which lands safe 9.0 m from the last landing (126.7 s -> 67.3 s). Re-recorded when the commands
# took off the velocity bias the registration learnt (small under `ideal`, from the registration's
# own noise): the same landing 0.45 m away, 0.55 s later. Re-recorded with the faster simulated
# perception (float32 after its cell counts and the like: P within 2.4e-7 of before), which steers
# this closed loop elsewhere on the same lawn: safe, 8.1 m from the last landing, 67.85 s -> 73.25 s.
# Re-recorded for the close look's walkers (a look every 0.5 s near the hand-over, which needs one
# at most ~1.1 s old, and a controller that stops the descent when the landing word runs out): the
# same landing 0.07 m away, 1.9 s later (73.25 s -> 75.15 s). Re-recorded when the landing word
# counted the delay until a decision is flown (it had run out before each renewal was flown, 0.275 s
# of every 0.5 s step, stopping the descent): the same landing 0.04 m away, 1.5 s sooner (75.15 s ->
# 73.65 s).
# Both profiles (none, ideal) must still agree.
REFERENCE = [
    ({"policy": "dovesei", "index": 1, "seed": 12, "timing": "reference", "time_limit_s": 60.0,
      "start": {"x_m": 266.718, "y_m": 133.498, "alt_m": 100.0}},
     {"outcome": "safe", "sim_time_s": 55.35, "path_length_m": 172.229, "max_range_m": 128.2,
      "final": {"x_m": 341.559, "y_m": 56.675, "alt_m": 19.783}}),
    ({"policy": "clearance", "index": 0, "seed": 11, "timing": "real", "time_limit_s": 150.0,
      "policy_config": {"scene_after_top_pass": False},  # a 400 m world: its scene is the first views
      "start": {"x_m": 230.274, "y_m": 296.129, "alt_m": 100.0}},
     {"outcome": "safe", "sim_time_s": 73.65, "path_length_m": 87.438, "max_range_m": 81.7,
      "final": {"x_m": 290.969, "y_m": 348.857, "alt_m": 19.797}}),
]


@pytest.mark.parametrize("job,want", REFERENCE, ids=[j["policy"] for j, _ in REFERENCE])
def test_ideal_reproduces_the_records_of_the_code_before_profiles(job: dict, want: dict) -> None:
    full = {"world": WORLD, "noise": None, "perception": "realistic", "prompts": None, **job}
    named = {**full, "vehicle_profile": "ideal"}
    # A job without the field (older benches) and one naming ideal become the same episode and the
    # same record fields: a record is a function of these and the world alone (`engines.run_job`), and
    # episodes are deterministic, so one flight of the two answers for both.
    start = Start(**job["start"])
    assert EpisodeSpec.from_job(full, start) == EpisodeSpec.from_job(named, start)
    assert EpisodeSpec.from_job(named, start).vehicle_profile == "ideal"
    assert engines.record_base(full) == engines.record_base(named)
    rec = engines.run_job(full)
    got = {k: rec[k] for k in want}
    assert got == want


def test_ideal_state_is_the_truth_and_frames_are_nadir() -> None:
    world = load_world(WORLD)
    core = SimCore(world, Start(200.0, 200.0, 60.0), SimConfig(vehicle_profile="ideal", timing="reference"))
    out = core.reset()
    for k in range(60):
        pose = core.true_pose()
        assert out.state.pos_valid and out.state.alt_agl_m == pose.alt_agl_m
        assert out.state.vel_body_frd_m_s == pose.vel_body_frd_m_s()
        if out.frame is not None:
            assert (out.frame.roll_rad, out.frame.pitch_rad) == (0.0, 0.0)
        out = core.step(VelocityCommand("uav1", k, out.state.stamp, (8.0 if k < 30 else 0.0, 0.0, 0.5),
                                        state_seq=out.state.seq))


def _truth_table(core: SimCore, table: dict) -> None:
    p = core.true_pose()
    table[round(core.t_s, 6)] = p


def test_realistic_no_controller_or_policy_input_equals_the_truth() -> None:
    """Fly a realistic episode with the bench's own cores, recording the truth of every step, and
    compare everything the controller and the policy were given with the truth of its instant."""
    world = load_world(WORLD)
    spec = EpisodeSpec(policy="clearance", start=Start(200.0, 200.0, 100.0), timing="real", seed=3,
                       time_limit_s=60.0, vehicle_profile="realistic")
    sim, seg, ctrl = build_cores(world, spec)
    observations = []
    policy_step = ctrl.policy.step

    def spy(obs):
        observations.append(obs)
        return policy_step(obs)

    ctrl.policy.step = spy
    truth: dict[float, Pose] = {}
    states, frames, heatmaps = [], [], {}
    out = sim.reset()
    pending = {}
    while out.result is None:
        _truth_table(sim, truth)
        states.append(out.state)
        if out.frame is not None:
            frames.append(out.frame)
            pending[out.frame.seq] = seg.process(out.frame)
            heatmaps[out.frame.seq] = pending[out.frame.seq]
        if out.state.await_frame_seq >= 0:
            ctrl.on_heatmap(pending.pop(out.state.await_frame_seq), 0.0)
        cmd, _status = ctrl.tick(out.state)
        out = sim.step(cmd)
    assert len(states) > 600 and len(frames) > 50 and len(observations) > 50

    def at(t_s: float) -> Pose:
        return truth[round(t_s, 6)]

    vel_err, alt_err, tilt = [], [], []
    for st in states:
        p = at(st.stamp.t_s)
        assert not st.pos_valid
        assert st.alt_agl_m != p.alt_agl_m
        assert st.vel_body_frd_m_s != p.vel_body_frd_m_s()
        assert st.vel_body_frd_m_s[:2] != pytest.approx(p.vel_body_frd_m_s()[:2], abs=1e-6)
        assert (st.roll_rad, st.pitch_rad, st.yaw_rad) != (p.roll_rad, p.pitch_rad, p.yaw_rad)
        assert st.yaw_rad != p.yaw_rad
        vel_err.append(np.subtract(st.vel_body_frd_m_s[:2], p.vel_body_frd_m_s()[:2]))
        alt_err.append(st.alt_agl_m - p.alt_agl_m)
    for fr in frames:
        p = at(fr.stamp.t_s)
        assert fr.alt_agl_m != p.alt_agl_m and heatmaps[fr.seq].alt_agl_m != p.alt_agl_m
        assert fr.roll_rad != p.roll_rad and fr.pitch_rad != p.pitch_rad and fr.yaw_rad != p.yaw_rad
        tilt.append(math.hypot(p.roll_rad, p.pitch_rad))
    for obs in observations:
        p = at(obs.t_s)
        assert obs.alt_agl_m != p.alt_agl_m
        assert (obs.roll_rad, obs.pitch_rad, obs.yaw_rad) != (p.roll_rad, p.pitch_rad, p.yaw_rad)
        assert obs.vel_est_body_frd_m_s != p.vel_body_frd_m_s()
    # The differences are an estimate's, not rounding: noise, bias, wind and latency add up to
    # more than a few centimetres per second, and the body tilts while it manoeuvres.
    assert float(np.sqrt(np.mean(np.square(vel_err)))) > 0.05
    assert max(abs(e) for e in alt_err) > 0.1
    assert max(tilt) > math.radians(3.0)


def test_realistic_frames_are_rendered_tilted_with_the_body() -> None:
    world = load_world(WORLD)
    core = SimCore(world, Start(200.0, 200.0, 80.0), SimConfig(vehicle_profile="realistic", timing="reference"))
    out = core.reset()
    tilted = None
    for k in range(40):  # accelerate forward: nose down
        out = core.step(VelocityCommand("uav1", k, out.state.stamp, (8.0, 0.0, 0.0), state_seq=out.state.seq))
        if out.frame is not None and core.true_pose().pitch_rad < -math.radians(5.0):
            tilted = out.frame, core.true_pose()
    assert tilted is not None
    frame, pose = tilted
    from dovesei.sim.camera import render
    # people and cars where they were when the frame was taken
    nadir, _, _ = render(world, pose.x_m, pose.y_m, pose.alt_agl_m, pose.yaw_rad, core.config.camera,
                         with_labels=False, t_s=pose.t_s)
    tilted_img, _, _ = render(world, pose.x_m, pose.y_m, pose.alt_agl_m, pose.yaw_rad, core.config.camera,
                              roll_rad=pose.roll_rad, pitch_rad=pose.pitch_rad, with_labels=False, t_s=pose.t_s)
    assert np.array_equal(frame.image_rgb, tilted_img) and not np.array_equal(frame.image_rgb, nadir)


DT_S = 0.05


def _fly(vehicle: Vehicle, seconds: float, cmd, cmd_t_s: float | None = None) -> None:
    """Step for `seconds`; the command is re-sent every step, or was sent once at `cmd_t_s`."""
    for _ in range(round(seconds / DT_S)):
        vehicle.step(DT_S, cmd, 0.0, vehicle.state.t_s if cmd_t_s is None else cmd_t_s)


def test_realistic_dynamics_brake_like_arducopter_and_coast_on_guid_timeout() -> None:
    params = dataclasses.replace(VEHICLE_PROFILES["realistic"].dynamics, gust_sigma_m_s=0.0, drift_sigma_m_s_sqrt_s=0.0)
    v = Vehicle(Pose(200.0, 200.0, 60.0), params)
    _fly(v, 8.0, (10.0, 0.0, 0.0))
    assert v.state.vel_ned_m_s[0] == pytest.approx(10.0, abs=0.05)
    t0, t_stop = v.state.t_s, None
    pitches = []
    while v.state.t_s - t0 < 10.0:
        v.step(DT_S, (0.0, 0.0, 0.0), 0.0, v.state.t_s)
        pitches.append(v.state.pitch_rad)
        if t_stop is None and v.state.vel_ned_m_s[0] < 0.1:
            t_stop = v.state.t_s - t0
    # ArduCopter SITL braked from 10 m/s in ~4.5 s (issue 23): 2.5 m/s^2 with a 5 m/s^3 jerk limit.
    assert t_stop is not None and 4.0 <= t_stop <= 5.2
    assert max(pitches) > math.radians(10.0)  # braking: nose up, 10-15 deg (issue 26)
    # GUID_TIMEOUT: a command that is no longer refreshed is flown for 3 s, then the vehicle brakes.
    v = Vehicle(Pose(200.0, 200.0, 60.0), params)
    _fly(v, 8.0, (10.0, 0.0, 0.0))
    sent_t_s = v.state.t_s
    _fly(v, 2.9, (10.0, 0.0, 0.0), cmd_t_s=sent_t_s)
    assert v.state.vel_ned_m_s[0] == pytest.approx(10.0, abs=0.05) and not v.last_command_stale
    _fly(v, 1.0, (10.0, 0.0, 0.0), cmd_t_s=sent_t_s)
    assert v.last_command_stale and v.state.vel_ned_m_s[0] < 9.0


def test_accelerating_forward_pitches_nose_down_and_right_rolls_right() -> None:
    v = Vehicle(Pose(200.0, 200.0, 60.0), VEHICLE_PROFILES["realistic"].dynamics)
    _fly(v, 0.5, (8.0, 0.0, 0.0))
    assert v.state.pitch_rad < -math.radians(3.0) and abs(v.state.roll_rad) < math.radians(1.0)
    v = Vehicle(Pose(200.0, 200.0, 60.0), VEHICLE_PROFILES["realistic"].dynamics)
    _fly(v, 0.5, (0.0, 8.0, 0.0))
    assert v.state.roll_rad > math.radians(3.0)


def test_profiles_are_checked_and_explicit_dynamics_win_over_the_profile() -> None:
    with pytest.raises(ConfigError, match="--vehicle-profile 'nosuch': choose one of ideal, realistic, harsh"):
        SimConfig(vehicle_profile="nosuch")
    with pytest.raises(ConfigError):
        vehicle_profile("nosuch")
    world = load_world(WORLD)
    core = SimCore(world, Start(200.0, 200.0, 60.0),
                   SimConfig(vehicle_profile="realistic", vehicle=VehicleParams(cmd_timeout_s=1.0)))
    core.reset()
    assert core.vehicle.params.cmd_timeout_s == 1.0 and core.vehicle.params.max_accel_h_m_s2 == 2.5
    core = SimCore(world, Start(200.0, 200.0, 60.0), SimConfig(vehicle_profile="realistic"))
    core.reset()
    assert core.vehicle.params.cmd_timeout_s == 3.0
    fresh = VelocityCommand("uav1", 0, Stamp(0.0, "sim"), (0.0, 0.0, 0.0))
    for _ in range(50):  # 2.5 s: a command that old is still fresh under GUID_TIMEOUT's 3 s
        core.step(None)
    assert core.is_fresh(fresh)


def test_the_estimate_repeats_per_seed_and_differs_between_seeds() -> None:
    world = load_world(WORLD)

    def states(seed: int) -> list:
        core = SimCore(world, Start(200.0, 200.0, 60.0), SimConfig(vehicle_profile="harsh", seed=seed))
        out, rows = core.reset(), []
        for k in range(40):
            out = core.step(VelocityCommand("uav1", k, out.state.stamp, (3.0, 1.0, 0.5), state_seq=out.state.seq))
            rows.append((out.state.alt_agl_m, out.state.vel_body_frd_m_s, out.state.yaw_rad, core.true_pose().x_m))
        return rows

    assert states(4) == states(4)
    assert states(4) != states(5)


# ---- the flags: bench, sweep, up, faults and the sim service all take --vehicle-profile ----


def test_bench_records_the_profile_and_the_start_altitude(tmp_path) -> None:
    from dovesei.bench import run_bench

    doc = run_bench(world_spec=WORLD, episodes=1, seed=2, policies=["clearance"], noise=None, timing="real",
                    time_limit_s=20.0, start_alt_m=40.0, jobs=1, out=tmp_path / "b", progress=False,
                    vehicle_profile="realistic")
    (ep,) = doc["episodes"]
    assert ep["vehicle_profile"] == "realistic" and ep["start"]["alt_m"] == 40.0
    assert doc["config"]["vehicle_profile"] == "realistic" and doc["config"]["start_alt_m"] == 40.0
    assert "vehicle profile `realistic`" in (tmp_path / "b" / "summary.md").read_text()
    # The track is the truth: it starts at the true start altitude, whatever the baro said.
    track = np.load(next((tmp_path / "b" / "tracks").rglob("*.npy")))
    assert track[0, 3] == pytest.approx(40.0, abs=1e-6)


@pytest.mark.parametrize("argv,needle", [
    (["--start-alt-m", "10"], "--start-alt-m must be a number of metres in [25, 200]"),
    (["--start-alt-m", "nan"], "--start-alt-m must be a number of metres in [25, 200]"),
    (["--vehicle-profile", "perfect"], "argument --vehicle-profile: invalid choice: 'perfect'"),
])
def test_bench_refuses_bad_profiles_and_altitudes_in_one_line(tmp_path, capsys, argv, needle) -> None:
    from dovesei.bench import main

    try:
        code = main(["--world", WORLD, "--episodes", "1", "--out", str(tmp_path / "b"), *argv])
    except SystemExit as exc:  # argparse's own refusal (one line: the bench's parser)
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1
    assert not (tmp_path / "b").exists()


def test_up_passes_the_profile_to_the_sim_child_and_checks_the_start_altitude() -> None:
    from dovesei.sim.service import CLI as SIM_CLI
    from dovesei.up.launch import child_configs
    from dovesei.up.options import UpOptions, build_parser, options_from_args

    options = options_from_args(build_parser().parse_args(["--vehicle-profile", "harsh", "--start-alt-m", "60"]))
    assert (options.vehicle_profile, options.start_alt_m) == ("harsh", 60.0)
    sim = child_configs(options, (100.0, 100.0, 60.0)).sim
    argv = SIM_CLI.to_argv(sim)
    assert argv[argv.index("--vehicle-profile") + 1] == "harsh"
    assert SIM_CLI.parse(argv).sim.vehicle_profile == "harsh"
    with pytest.raises(ConfigError, match="--vehicle-profile 'x'"):
        UpOptions(vehicle_profile="x")
    with pytest.raises(ConfigError, match=r"--start altitude must be a number of metres in \[25, 200\]"):
        UpOptions(start=(1.0, 1.0, 5.0))


def test_sweep_takes_the_profile_from_its_file_or_the_flag(tmp_path) -> None:
    from dovesei.sweep import build_parser, grid_from_doc

    base = {"worlds": [WORLD], "episodes": 1, "policies": ["dovesei"]}
    assert grid_from_doc(base).vehicle_profile == "ideal"
    assert grid_from_doc({**base, "vehicle_profile": "harsh", "start_alt_m": 60}).vehicle_profile == "harsh"
    with pytest.raises(ConfigError, match="sweep file: 'vehicle_profile' 'x'"):
        grid_from_doc({**base, "vehicle_profile": "x"})
    with pytest.raises(ConfigError, match="sweep file: 'start_alt_m' must be a number of metres"):
        grid_from_doc({**base, "start_alt_m": 500})
    assert build_parser().parse_args(["f.yaml", "--vehicle-profile", "realistic"]).vehicle_profile == "realistic"


def test_faults_fly_the_profile_asked_for() -> None:
    from dovesei.faults import build_parser

    assert build_parser().parse_args(["--vehicle-profile", "realistic"]).vehicle_profile == "realistic"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--vehicle-profile", "x"])


def test_without_a_profile_every_command_flies_the_timing_presets_default(tmp_path) -> None:
    from dovesei.bench import build_parser as bench_parser
    from dovesei.sim.estimator import default_vehicle_profile
    from dovesei.sweep import grid_from_doc
    from dovesei.up.options import UpOptions, build_parser, options_from_args

    # Real seconds fly the vehicle dovesei exists for; the paper's reproduction keeps its drone.
    assert (default_vehicle_profile("real"), default_vehicle_profile("reference")) == ("realistic", "ideal")
    for timing in ("reference", "real"):
        want = default_vehicle_profile(timing)
        assert want in VEHICLE_PROFILES
        assert UpOptions(timing=timing).sim_vehicle_profile == want
        assert UpOptions(timing=timing, vehicle_profile="harsh").sim_vehicle_profile == "harsh"
        opts = options_from_args(build_parser().parse_args(["--timing", timing]))
        assert opts.vehicle_profile is None and opts.sim_vehicle_profile == want
        assert grid_from_doc({"worlds": [WORLD], "timing": timing}).vehicle_profile == want
    assert bench_parser().parse_args([]).vehicle_profile is None


@pytest.mark.parametrize("name", ["realistic", "harsh"])
def test_the_reported_attitude_wanders_but_does_not_jump_between_frames(name: str) -> None:
    # An AHRS integrates gyros: its roll/pitch error drifts, it does not jump from one state to the
    # next. A jump of a few mrad between two frames 0.1 s apart is metres per second of false
    # visual velocity at 100 m (bench-odometry measured it), so the change must stay small while
    # the error itself still has the profile's spread.
    from dovesei.sim.estimator import Estimator
    params = VEHICLE_PROFILES[name].estimator
    est = Estimator(params, seed=3, dt_s=0.05)
    pose = Pose(0.0, 0.0, 80.0)
    errors = np.array([[e.roll_rad, e.pitch_rad] for e in (est.update(pose, (0.0, 0.0, 0.0)) for _ in range(24000))])
    change_0p1s = errors[2:] - errors[:-2]
    assert float(np.std(change_0p1s)) < 0.15 * params.attitude_noise_rad  # ~sqrt(2 x 0.1 / 30) = 0.08
    wander = errors - errors.mean(axis=0)
    assert float(np.std(wander)) > 0.3 * params.attitude_noise_rad  # it still wanders over minutes
