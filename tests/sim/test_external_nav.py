"""A sim vehicle whose autopilot fuses the camera's visual velocity (`SimConfig.external_nav`, the
bench's `--gnss-denied external-nav`): what it takes off, what it leaves, and that it fuses only
what the camera measured well."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dovesei.bench import make_grid
from dovesei.bench.engines import record_base
from dovesei.bench.run import load_worlds, plan_jobs, summary_markdown
from dovesei import episode
from dovesei.controller.core import ControllerCore
from dovesei.controller.policies.base import Decision, Observation
from dovesei.episode import BENCH_ODOMETRY_HZ, BENCH_ODOMETRY_WIDTH_PX, EpisodeSpec, build_cores, run_episode
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import ControllerStatus, Stamp, VisualOdometry
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.dynamics import DynamicsError, Pose, Vehicle, VehicleParams
from dovesei.sim.starts import Start
from dovesei.sim.world import ClassInfo, World
from tests.controller.test_watchdog import DescendingPolicy
from tests.sim.test_sim_core import MID_Y_M, fly, split_world

DT_S = 0.05


def _hover(vehicle: Vehicle, seconds: float, cmd=(0.0, 0.0, 0.0), fuse_every: int = 0) -> None:
    """Fly a constant command; every `fuse_every` steps fuse the TRUE ground velocity (an exact camera)."""
    for k in range(int(round(seconds / DT_S))):
        vehicle.step(DT_S, cmd, 0.0, vehicle.state.t_s)
        if fuse_every and k % fuse_every == 0:
            vehicle.fuse_ground_velocity(vehicle.state.vel_ned_m_s[:2], fuse_every * DT_S, 1.0)


def test_an_exact_ground_velocity_takes_off_the_wind_and_the_scale_error() -> None:
    params = VehicleParams(wind_ned_m_s=(1.0, -0.5, 0.0), scale_error=0.08)
    drifting = Vehicle(Pose(0.0, 0.0, 50.0), params)
    _hover(drifting, 30.0)
    assert math.hypot(*drifting.state.vel_ned_m_s[:2]) == pytest.approx(math.hypot(1.0, 0.5), rel=1e-6)
    fused = Vehicle(Pose(0.0, 0.0, 50.0), params)
    _hover(fused, 30.0, fuse_every=2)
    # Hovering: the ground velocity is gone, the correction is the wind.
    assert math.hypot(*fused.state.vel_ned_m_s[:2]) < 0.02
    assert fused.nav_correction_ned_m_s[:2] == pytest.approx((1.0, -0.5), abs=0.02)
    # Cruising north at 5 m/s: the 8 % scale error is taken off too.
    _hover(fused, 30.0, cmd=(5.0, 0.0, 0.0), fuse_every=2)
    assert fused.state.vel_ned_m_s[0] == pytest.approx(5.0, abs=0.05)
    assert fused.state.vel_ned_m_s[1] == pytest.approx(0.0, abs=0.05)


def test_a_vehicle_that_never_fuses_flies_exactly_as_before() -> None:
    params = VehicleParams(wind_ned_m_s=(0.3, 0.2, 0.0), gust_sigma_m_s=0.4, drift_sigma_m_s_sqrt_s=0.02)
    a, b = Vehicle(Pose(0.0, 0.0, 50.0), params, seed=4), Vehicle(Pose(0.0, 0.0, 50.0), params, seed=4)
    _hover(a, 20.0, cmd=(3.0, 1.0, 0.0))
    _hover(b, 20.0, cmd=(3.0, 1.0, 0.0))
    assert a.state == b.state and b.nav_correction_ned_m_s == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("args", [((float("nan"), 0.0), 0.1, 1.0), ((1.0,), 0.1, 1.0), ((0.0, 0.0), 0.0, 1.0),
                                  ((0.0, 0.0), 0.1, -1.0)])
def test_bad_fusion_inputs_are_refused(args) -> None:
    v = Vehicle(Pose(0.0, 0.0, 50.0))
    with pytest.raises(DynamicsError):
        v.fuse_ground_velocity(*args)
    assert v.nav_correction_ned_m_s == (0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def world() -> World:
    return split_world()


def _drift(world: World, external_nav: bool, seconds: float = 60.0, profile: str = "harsh") -> tuple[float, float, int]:
    """Hover a `profile` vehicle at 40 m over the world's middle: (true drift from the start, error
    of the dead-reckoned position against the truth, samples fused)."""
    start = Start(200.0, MID_Y_M, 40.0)
    core = SimCore(world, start, SimConfig(vehicle_profile=profile, seed=5, time_limit_s=seconds,
                                           odometry_rate_hz=10.0 if external_nav else 0.0, external_nav=external_nav))
    outs = fly(core, (0.0, 0.0, 0.0), landing=False)
    pose = core.true_pose()
    north, east = pose.y_m - start.y_m, pose.x_m - start.x_m
    est = outs[-1].state.pos_local_ned_m
    return math.hypot(north, east), math.hypot(est[0] - north, est[1] - east), core.fused


def test_a_harsh_vehicle_on_the_cameras_velocity_stays_where_it_believes_it_is(world: World) -> None:
    drift_off, err_off, fused_off = _drift(world, False)
    drift_on, err_on, fused_on = _drift(world, True)
    assert fused_off == 0 and fused_on >= 0.9 * 60.0 * 10.0
    # harsh: ~1 m/s of unseen wind plus gusts and a drifting bias carry it tens of metres a minute.
    assert drift_off > 30.0 and err_off > 30.0
    assert drift_on < 0.2 * drift_off and err_on < 0.2 * err_off, (drift_off, drift_on, err_off, err_on)


def test_a_camera_that_sees_nothing_is_never_fused() -> None:
    # Calm open water: no corners (and no ground detail: water never gets any), every odometry
    # sample invalid; the flight is the one without fusion.
    blank = World(np.full((800, 800, 3), 128, np.uint8), np.ones((800, 800), np.uint8), 0.5,
                  {1: ClassInfo("sea", False)}, "blank")
    start = Start(200.0, 200.0, 40.0)
    cores = [SimCore(blank, start, SimConfig(vehicle_profile="realistic", seed=2, time_limit_s=20.0,
                                             odometry_rate_hz=10.0, external_nav=on)) for on in (False, True)]
    outs = [fly(core, (2.0, 0.0, 0.0), landing=False) for core in cores]
    assert cores[1].fused == 0
    assert any(o.odometry is not None and not o.odometry.valid for o in outs[1])
    assert cores[0].true_pose() == cores[1].true_pose()


@pytest.mark.parametrize("changes,needle", [
    (dict(external_nav=True), "needs odometry_rate_hz > 0"),
    (dict(external_nav=True, odometry_rate_hz=10.0, vehicle_profile="ideal"), "reports the truth"),
    (dict(odometry_rate_hz=10.0, odometry_width_px=16), "odometry_width_px"),
    (dict(odometry_rate_hz=10.0, odometry_width_px=4000), "odometry_width_px"),
    (dict(external_nav_tau_s=0.0), "external_nav_tau_s"),
    (dict(external_nav_min_quality=1.5), "external_nav_min_quality"),
    (dict(external_nav_max_var_m2_s2=0.0), "external_nav_max_var_m2_s2"),
])
def test_bad_external_nav_settings_are_named(changes: dict, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        SimConfig(**{"vehicle_profile": "realistic", **changes})


def test_the_bench_flies_and_records_a_vehicle_on_the_cameras_velocity(tmp_path) -> None:
    kw = dict(world_spec="synthetic:style=desert,seed=3", episodes=1, seed=0, policies=("clearance",), noise=None,
              timing="real", time_limit_s=60.0, start_alt_m=100.0, start_margin_m=50.0, vehicle_profile="harsh")
    off, on = make_grid(**kw), make_grid(**kw, gnss_denied="external-nav")
    # Off, the settings (and so their hash) are those of benches before the flag: they resume.
    assert "gnss_denied" not in off.config() and on.config()["gnss_denied"] == "external-nav"
    worlds = load_worlds(list(on.worlds))
    (job,) = plan_jobs(on, worlds, tmp_path)
    (job_off,) = plan_jobs(off, worlds, tmp_path)
    assert record_base(job)["gnss_denied"] == "external-nav" and "gnss_denied" not in record_base(job_off)
    spec = EpisodeSpec.from_job(job, Start(**job["start"]))
    assert spec.external_nav and not EpisodeSpec.from_job(job_off, Start(**job_off["start"])).external_nav
    sim, _seg, _ctrl = build_cores(worlds[job["world"]], spec)
    assert (sim.config.external_nav, sim.config.odometry_rate_hz, sim.config.odometry_width_px) == \
        (True, BENCH_ODOMETRY_HZ, BENCH_ODOMETRY_WIDTH_PX)
    assert sim.config.odometry_camera.width_px == BENCH_ODOMETRY_WIDTH_PX
    assert "on the camera's visual velocity" in summary_markdown({"config": on.config(), "summary": {}})
    assert "visual velocity" not in summary_markdown({"config": off.config(), "summary": {}})
    with pytest.raises(ConfigError, match="--gnss-denied external-nav needs a vehicle"):
        make_grid(**{**kw, "vehicle_profile": "ideal"}, gnss_denied="external-nav")
    with pytest.raises(ConfigError, match="--gnss-denied"):
        make_grid(**kw, gnss_denied="attitude")



def test_overlapping_samples_weigh_the_time_between_them_and_noisy_ones_are_not_fused(world: World) -> None:
    # From high up each sample spans 0.5 s but they come every 0.1 s: the autopilot weighs each by
    # the time since the one before (else the same motion counted five times); a sample over the
    # controller's variance limit is one its adapter never sends, so the EKF never sees it.
    core = SimCore(world, Start(200.0, MID_Y_M, 100.0), SimConfig(vehicle_profile="realistic", seed=2,
                                                                  odometry_rate_hz=10.0, external_nav=True))
    core.reset()

    def sample(k: int, var: float = 0.2) -> VisualOdometry:
        return VisualOdometry("uav1", k + 5, k, Stamp(1.0 + 0.1 * k, "sim"), (2.0, 0.0, 0.0), var, 0.9, True, 0.5, 100.0)

    core._fuse(sample(0))
    first = core.vehicle.nav_correction_ned_m_s[0]
    core._fuse(sample(1, var=1.5))  # too noisy: not fused
    assert core.fused == 1 and core.vehicle.nav_correction_ned_m_s[0] == first
    core._fuse(sample(2))
    # Nothing moved in between, so the innovation is the same each time: the first sample pulls
    # by its 0.5 s / tau, the second by the 0.2 s since the first (not by its own 0.5 s again).
    second = core.vehicle.nav_correction_ned_m_s[0] - first
    assert abs(first) > 0.1 and second / first == pytest.approx(0.2 / 0.5)
    assert core.fused == 2


def test_the_bench_controller_descends_only_on_a_trusted_visual_velocity(monkeypatch) -> None:
    # As on a real autopilot without GNSS (`VisualNav`): the controller may descend only while the
    # camera's velocity is good. Over calm water it never is: the vehicle holds at its altitude
    # (a hold, its reason saying why) until the time runs out; over textured ground the same
    # policy, perception and vehicle hand over at 20 m.
    real_build = episode.build_cores

    def build(world, spec, **kw):
        sim, seg, ctrl = real_build(world, spec, **kw)
        ctrl.policy = DescendingPolicy()  # straight down, always landing: any hold is the controller's
        return sim, seg, ctrl

    monkeypatch.setattr(episode, "build_cores", build)
    textured = split_world()
    blank = World(np.full_like(textured.image_rgb, 128), np.ones_like(textured.labels), textured.gsd_m,
                  {1: ClassInfo("water", False)}, "water")
    spec = EpisodeSpec(policy="clearance", start=Start(100.0, MID_Y_M, 40.0), timing="real", seed=1,
                       time_limit_s=40.0, vehicle_profile="realistic", external_nav=True)
    runs = {}
    for name, world in (("blank", blank), ("textured", textured)):
        statuses: list = []
        rec = run_episode(world, spec, record=lambda m: statuses.append(m) if isinstance(m, ControllerStatus) else None)
        held = [s for s in statuses if s.watchdog == "hold" and s.reason.startswith("no trusted velocity source")]
        runs[name] = (rec.result.outcome, float(rec.track[:, 3].min()), len(held) / len(statuses), held)
    outcome, lowest_m, held_frac, held = runs["blank"]
    assert outcome == "timeout" and lowest_m > 38.0 and held_frac > 0.9
    assert "visual velocity" in held[-1].reason
    outcome, lowest_m, held_frac, _ = runs["textured"]
    assert outcome == "safe" and lowest_m < 21.0 and held_frac < 0.1


class EastPolicy:
    """Flies east at 4 m/s at its altitude for ever, never landing: any turn back is the controller's."""

    name = "east"

    def step(self, obs: Observation) -> Decision:
        return Decision((0.0, 4.0, 0.0), 0.0, "SEARCH", None, 50.0, 0.5)

    def reset(self) -> None:
        pass


def _shore_world() -> World:
    """The split world's textured west half; calm water (flat, no detail) from x = 200 m east."""
    land = split_world()
    image, labels = land.image_rgb.copy(), land.labels.copy()
    half = image.shape[1] // 2
    image[:, half:] = 128
    labels[:, half:] = 3
    classes = {**land.classes, 3: ClassInfo("water", False)}
    return World(image, labels, land.gsd_m, classes, "shore")


def test_a_vehicle_that_flies_out_over_water_flies_back_to_where_the_camera_measures(monkeypatch) -> None:
    # GNSS lost, the autopilot on the camera's velocity, a policy that flies east over the sea.
    # Past the shore the camera measures nothing: the controller stops following the policy and
    # flies back towards the shore until the velocity is trusted again, then follows it again (out,
    # back: it stays at the shore). With the retreat off it holds out at sea, where a hold drifts.
    real_build = episode.build_cores
    retreat_s: list[float] = []

    def build(world, spec, **kw):
        sim, seg, ctrl = real_build(world, spec, **kw)
        config = dataclasses.replace(ctrl.config, nav_retreat_max_s=retreat_s[0])
        return sim, seg, ControllerCore(config, policy=EastPolicy())

    monkeypatch.setattr(episode, "build_cores", build)
    world = _shore_world()
    spec = EpisodeSpec(policy="clearance", start=Start(150.0, MID_Y_M, 40.0), timing="real", seed=1,
                       time_limit_s=90.0, vehicle_profile="realistic", external_nav=True)
    runs = {}
    for max_s in (20.0, 0.0):
        retreat_s[:] = [max_s]
        statuses: list = []
        rec = run_episode(world, spec, record=lambda m: statuses.append(m) if isinstance(m, ControllerStatus) else None)
        blind = [s.reason.startswith("no trusted velocity source") for s in statuses]
        flying = blind.index(False)  # the first samples come after the first state
        lost = flying + blind[flying:].index(True)
        late = [b for s, b in zip(statuses, blind) if s.stamp.t_s > 45.0]  # the second half of the flight
        runs[max_s] = (float(rec.track[:, 1].max()), float(rec.track[-1, 1]), 1.0 - sum(late) / len(late),
                       statuses[lost:], float(rec.track[:, 3].min()))
    far_m, end_m, trusted_frac, after, lowest_m = runs[20.0]
    # Back by any of the controller's ways: towards the shore in view, on the way it was last
    # seen, or back the way it came.
    ways = ("flying towards the ground the camera can measure", "flying on towards the ground the camera measured",
            "flying back over the ground the camera measured")
    assert any(w in s.reason for s in after for w in ways), {s.reason.split("; ")[-1] for s in after}
    assert trusted_frac > 0.2 and end_m < 200.0 + 40.0 and far_m < 200.0 + 50.0, runs[20.0][:3]
    assert lowest_m > 39.0  # never a descent on the way back
    far0_m, end0_m, trusted0_frac, _after, _ = runs[0.0]
    assert trusted0_frac == 0.0 and end0_m > 200.0 + 20.0, runs[0.0][:3]
