"""SimCore, the sim's pure core: frame schedule per timing preset, the await protocol, determinism,
and the three ways an episode ends (hand-over verdict, time limit, leaving the world) plus abort."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import Stamp, VehicleState, VelocityCommand, replace
from dovesei.shared.timing import timing
from dovesei.sim.core import SimConfig, SimCore, StepOut
from dovesei.sim.dynamics import VehicleParams
from dovesei.sim.starts import Start
from dovesei.sim.world import ClassInfo, World

GRASS, BUILDING = 1, 2
SPLIT_GSD_M = 0.5
SPLIT_SIDE_PX = 800  # a 400 m square world


def split_world() -> World:
    """400 m x 400 m: the west half grass (safe), the east half building (unsafe), textured so
    that every view differs (a seeded noise image: frames compare by bytes)."""
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (SPLIT_SIDE_PX, SPLIT_SIDE_PX, 3), dtype=np.uint8)
    labels = np.full((SPLIT_SIDE_PX, SPLIT_SIDE_PX), GRASS, np.uint8)
    labels[:, SPLIT_SIDE_PX // 2:] = BUILDING
    return World(image, labels, SPLIT_GSD_M, {GRASS: ClassInfo("grass", True), BUILDING: ClassInfo("building", False)},
                 "split")


WEST_M, EAST_M, MID_Y_M = 100.0, 300.0, 200.0  # over grass, over the building, the world's middle


@pytest.fixture(scope="module")
def world() -> World:
    return split_world()


HANDOVER_ALT_M = 20.0


def command(state: VehicleState, vel_frd_m_s: tuple[float, float, float], yaw_rate_rad_s: float = 0.0,
            landing: bool = True) -> VelocityCommand:
    """The answer a lockstep controller gives to `state`: it hands over at the hand-over altitude
    while its policy is `landing`."""
    return VelocityCommand(state.vehicle_id, state.seq, state.stamp, vel_frd_m_s, yaw_rate_rad_s, state_seq=state.seq,
                           handover=bool(landing and state.alt_agl_m <= HANDOVER_ALT_M))


def fly(core: SimCore, vel_frd_m_s: tuple[float, float, float], max_steps: int = 10_000,
        yaw_rate_rad_s: float = 0.0, landing: bool = True) -> list[StepOut]:
    """Run an episode under a constant command; every StepOut, the reset's first."""
    outs = [core.reset()]
    while outs[-1].result is None and len(outs) <= max_steps:
        outs.append(core.step(command(outs[-1].state, vel_frd_m_s, yaw_rate_rad_s, landing)))
    return outs


def test_reference_preset_renders_every_step_and_awaits_the_previous_frame(world: World) -> None:
    core = SimCore(world, Start(WEST_M, MID_Y_M, 60.0), SimConfig(timing="reference", time_limit_s=2.0))
    outs = fly(core, (0.0, 0.0, 0.0))
    assert outs[-1].result.outcome == "timeout"
    live = outs[:-1]  # the last step ends the episode: judged, no frame
    assert [o.frame.seq for o in live] == list(range(len(live)))
    assert [o.state.seq for o in outs] == list(range(len(outs)))
    # Latency 0.05 s = one step: state k awaits frame k - 1; nothing is due at step 0.
    assert [o.state.await_frame_seq for o in outs] == [-1] + list(range(len(outs) - 1))
    assert outs[-1].frame is None


def test_real_preset_frame_every_half_second_heatmap_due_latency_later(world: World) -> None:
    period_s, latency_s = timing("real").frame_period_s, timing("real").latency_s
    assert (period_s, latency_s) == (0.5, 0.4)  # the numbers the release flew with
    core = SimCore(world, Start(WEST_M, MID_Y_M, 60.0), SimConfig(timing="real", time_limit_s=3.0))
    outs = fly(core, (0.5, 0.0, 0.0))
    frames = {o.frame.seq: o.frame for o in outs if o.frame is not None}
    frame_steps = [o.state.seq for o in outs if o.frame is not None]
    assert frame_steps == [0, 10, 20, 30, 40, 50]  # 3 s at 2 Hz (none at the final, judged step)
    awaited = [(o.state.seq, o.state.await_frame_seq) for o in outs if o.state.await_frame_seq >= 0]
    assert awaited == [(8, 0), (18, 1), (28, 2), (38, 3), (48, 4), (58, 5)]
    by_seq = {o.state.seq: o.state for o in outs}
    for step, seq in awaited:
        # The awaited heatmap is of the frame captured exactly `latency` of sim time earlier.
        assert by_seq[step].stamp.t_s - frames[seq].stamp.t_s == pytest.approx(latency_s, abs=1e-9)
        assert frames[seq].stamp.t_s == pytest.approx(seq * period_s, abs=1e-9)


def test_overridden_period_and_latency(world: World) -> None:
    cfg = SimConfig(timing="real", frame_period_s=0.15, latency_s=0.10, time_limit_s=1.0)
    outs = fly(SimCore(world, Start(WEST_M, MID_Y_M, 60.0), cfg), (0.0, 0.0, 0.0))
    assert [o.state.seq for o in outs if o.frame is not None] == [0, 3, 6, 9, 12, 15, 18]
    assert [o.state.seq for o in outs if o.state.await_frame_seq >= 0] == [2, 5, 8, 11, 14, 17, 20]


def test_frames_carry_pose_and_truth_and_no_truth_option(world: World) -> None:
    out = SimCore(world, Start(WEST_M, MID_Y_M, 60.0, yaw_rad=0.4), SimConfig(seed=1)).reset()
    f = out.frame
    assert f.image_rgb.shape == (352, 352, 3) and f.alt_agl_m == 60.0 and f.yaw_rad == pytest.approx(0.4)
    assert f.hfov_rad == pytest.approx(math.radians(73.0)) and f.stamp == Stamp(0.0, "sim")
    assert set(np.unique(f.truth.labels)) == {GRASS}  # 89 m wide footprint, 100 m from the split
    assert {c.name for c in f.truth.classes} == {"grass", "building"}
    bare = SimCore(world, Start(WEST_M, MID_Y_M, 60.0), SimConfig(attach_truth=False)).reset()
    assert bare.frame.truth is None


def test_same_seed_same_trajectory_and_frames_different_seed_differs(world: World) -> None:
    gusty = VehicleParams(gust_sigma_m_s=1.0, drift_sigma_m_s_sqrt_s=0.3)

    def run(seed: int) -> list[StepOut]:
        core = SimCore(world, Start(WEST_M, MID_Y_M, 40.0), SimConfig(seed=seed, vehicle=gusty, time_limit_s=3.0))
        return fly(core, (1.0, 0.5, 0.2), yaw_rate_rad_s=0.2)

    a, b, c = run(7), run(7), run(8)
    assert len(a) == len(b)
    for oa, ob in zip(a, b):
        assert oa.state.pos_local_ned_m == ob.state.pos_local_ned_m and oa.state.yaw_rad == ob.state.yaw_rad
        assert (oa.frame is None) == (ob.frame is None)
        if oa.frame is not None:
            assert np.array_equal(oa.frame.image_rgb, ob.frame.image_rgb)
            assert np.array_equal(oa.frame.truth.labels, ob.frame.truth.labels)
    assert a[-1].result == b[-1].result
    assert a[-1].state.pos_local_ned_m != c[-1].state.pos_local_ned_m  # the gusts come from the seed


def test_handover_over_grass_is_safe_over_building_unsafe(world: World) -> None:
    safe = fly(SimCore(world, Start(WEST_M, MID_Y_M, 30.0), SimConfig()), (0.0, 0.0, 4.0))
    r = safe[-1].result
    assert r.outcome == "safe" and r.final_alt_m <= 20.0 and r.stamp.clock == "sim"
    assert r.final_x_m == pytest.approx(WEST_M) and r.classes_found == ("grass:1.000",)
    # 30 m -> 20 m at <= 4 m/s (3 m/s^2 ramp) takes a few seconds, not one step.
    assert 2.5 < r.sim_time_s < 5.0
    unsafe = fly(SimCore(world, Start(EAST_M, MID_Y_M, 30.0), SimConfig()), (0.0, 0.0, 4.0))[-1].result
    assert unsafe.outcome == "unsafe" and "building" in unsafe.classes_found[0]
    assert unsafe.closest_unsafe_valid and unsafe.closest_unsafe_m < SPLIT_GSD_M  # to the nearest pixel centre


def test_sinking_through_the_handover_altitude_without_a_handover_is_no_landing(world: World) -> None:
    # An aborted descent (the controller never says `handover`) sinks through 20 m over grass: the
    # episode goes on, and the vehicle that reaches the ground that way crashed, it did not land.
    outs = fly(SimCore(world, Start(WEST_M, MID_Y_M, 30.0), SimConfig()), (0.0, 0.0, 4.0), landing=False)
    below = [o for o in outs if o.state.alt_agl_m <= HANDOVER_ALT_M]
    assert len(below) > 20 and all(o.result is None for o in below[:-1])
    r = outs[-1].result
    assert r.outcome == "unsafe" and r.final_alt_m == pytest.approx(0.0, abs=0.11)
    assert "without a hand-over" in r.detail and r.classes_found == ()
    # The same descent handed over at 20 m is the safe landing.
    assert fly(SimCore(world, Start(WEST_M, MID_Y_M, 30.0), SimConfig()), (0.0, 0.0, 4.0))[-1].result.outcome == "safe"


def test_a_sink_below_the_handover_altitude_that_climbs_back_goes_on(world: World) -> None:
    core = SimCore(world, Start(WEST_M, MID_Y_M, 21.0), SimConfig(time_limit_s=6.0))
    outs = [core.reset()]
    while outs[-1].result is None:
        down = 4.0 if outs[-1].state.stamp.t_s < 1.5 else -2.0  # sink to ~17 m, then climb back
        outs.append(core.step(command(outs[-1].state, (0.0, 0.0, down), landing=False)))
    assert min(o.state.alt_agl_m for o in outs) < 19.0
    assert outs[-1].result.outcome == "timeout" and outs[-1].result.final_alt_m > HANDOVER_ALT_M


def test_time_limit_ends_a_hover_as_timeout(world: World) -> None:
    outs = fly(SimCore(world, Start(WEST_M, MID_Y_M, 50.0), SimConfig(time_limit_s=1.0)), (0.0, 0.0, 0.0))
    r = outs[-1].result
    assert r.outcome == "timeout" and r.sim_time_s == pytest.approx(1.0) and len(outs) == 21
    assert r.final_alt_m == pytest.approx(50.0) and "1 s" in r.detail
    with pytest.raises(RuntimeError, match="ended"):
        _ended_core(world).step(None)


def _ended_core(world: World) -> SimCore:
    core = SimCore(world, Start(WEST_M, MID_Y_M, 50.0), SimConfig(time_limit_s=0.05))
    fly(core, (0.0, 0.0, 0.0))
    return core


def test_leaving_the_world_ends_the_episode(world: World) -> None:
    # 20 m from the east edge, flying east (heading north, so east is body right) at 15 m/s.
    start = Start(world.width_m - 20.0, MID_Y_M, 60.0)
    outs = fly(SimCore(world, start, SimConfig()), (0.0, 15.0, 0.0))
    r = outs[-1].result
    assert r.outcome == "out_of_world" and r.final_x_m >= world.width_m
    assert r.path_length_m == pytest.approx(r.final_x_m - start.x_m, abs=0.01)
    assert outs[-1].frame is None


def test_no_command_brakes_after_the_vehicle_timeout(world: World) -> None:
    core = SimCore(world, Start(WEST_M, MID_Y_M, 60.0), SimConfig(time_limit_s=10.0))
    out = core.reset()
    for _ in range(20):  # 1 s of 3 m/s descent commands
        out = core.step(command(out.state, (0.0, 0.0, 3.0)))
    assert out.state.vel_body_frd_m_s[2] > 2.0
    for _ in range(60):  # then silence: None keeps the last command until it is 0.5 s old
        out = core.step(None)
    assert abs(out.state.vel_body_frd_m_s[2]) < 0.05


def test_a_command_not_fresh_on_the_sim_clock_is_dropped(world: World) -> None:
    core = SimCore(world, Start(WEST_M, MID_Y_M, 60.0), SimConfig(vehicle=VehicleParams(cmd_timeout_s=0.3)))
    out = core.reset()
    for _ in range(10):  # 0.5 s of sim time
        out = core.step(None)
    fresh = command(out.state, (3.0, 0.0, 0.0))
    old = replace(fresh, stamp=Stamp(out.state.stamp.t_s - 0.35, "sim"))  # older than the 0.3 s timeout
    ahead = replace(fresh, stamp=Stamp(out.state.stamp.t_s + 1.0, "sim"))  # a stamp from the future
    wall = replace(fresh, stamp=Stamp(out.state.stamp.t_s, "wall"))  # the right number on the wrong clock
    assert core.is_fresh(fresh) and not any(core.is_fresh(c) for c in (old, ahead, wall))
    for cmd in (old, ahead, wall):
        out = core.step(cmd)
    assert core.commands_dropped == 3 and out.state.vel_body_frd_m_s[0] == pytest.approx(0.0, abs=1e-9)
    out = core.step(command(out.state, (3.0, 0.0, 0.0)))
    assert core.commands_dropped == 3 and out.state.vel_body_frd_m_s[0] > 0.1  # a fresh one is flown


def test_lockstep_answers_are_never_dropped(world: World) -> None:
    # Every lockstep answer carries the stamp of its state: the freshness rule changes nothing there.
    for timing_name in ("reference", "real"):
        core = SimCore(world, Start(WEST_M, MID_Y_M, 30.0), SimConfig(timing=timing_name, time_limit_s=20.0))
        outs = fly(core, (0.5, 0.0, 3.0))
        assert outs[-1].result is not None and core.commands_dropped == 0


def test_abort_ends_as_error_and_keeps_a_verdict(world: World) -> None:
    core = SimCore(world, Start(WEST_M, MID_Y_M, 60.0), SimConfig())
    out = core.reset()
    out = core.step(command(out.state, (1.0, 0.0, 0.0)))
    r = core.abort("no command from the controller")
    assert r.outcome == "error" and r.detail == "no command from the controller" and core.result is r
    assert r.sim_time_s == pytest.approx(0.05)
    with pytest.raises(RuntimeError):
        core.step(None)
    ended = _ended_core(world)
    assert ended.abort("late").outcome == "timeout"


@pytest.mark.parametrize("bad, match", [
    (dict(timing="fast"), "timing"),
    (dict(frame_period_s=0.01), "shorter than the step"),
    (dict(latency_s=-1.0), "latency"),
    (dict(time_limit_s=0.0), "time_limit_s"),
])
def test_bad_config_is_refused(bad: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        SimConfig(**bad)
