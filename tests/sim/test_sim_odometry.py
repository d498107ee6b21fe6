"""The sim as the onboard camera's visual odometry: in-process (`SimCore` with `odometry_rate_hz`),
over loopback Zenoh in lockstep (published before the state it goes with) and in external-pose mode
(views at the poses a controller publishes)."""

from __future__ import annotations

import numpy as np
import pytest

from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import Stamp, VehicleState, VisualOdometry
from dovesei.shared.visual_velocity import VisualVelocityConfig
from dovesei.sim.camera import CameraModel
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.odometry import SimOdometry
from dovesei.sim.service import build_parser, config_from_args
from dovesei.sim.starts import Start
from dovesei.sim.world import World
from tests.sim.test_sim_core import MID_Y_M, WEST_M, fly, split_world
from tests.sim.test_sim_service_zenoh import (
    VID, SimThread, StatePublisher, external_config, lockstep_config, pair,  # noqa: F401 - pair is a fixture
)

FORWARD = (4.0, 1.5, 2.0)  # forward, right, down (m/s): 40 m -> 20 m in 10 s


@pytest.fixture(scope="module")
def world() -> World:
    return split_world()


def test_sim_core_publishes_odometry_at_its_rate_and_it_measures_the_velocity(world: World) -> None:
    core = SimCore(world, Start(WEST_M, MID_Y_M, 40.0, yaw_rad=0.7),
                   SimConfig(vehicle_id=VID, odometry_rate_hz=10.0, time_limit_s=60.0))
    outs = fly(core, FORWARD)
    odo = [(o.state, o.odometry) for o in outs if o.odometry is not None]
    # One view per 0.1 s of sim time (every second 0.05 s step); the first has nothing to compare with.
    sim_s = outs[-1].state.stamp.t_s
    assert len(odo) == pytest.approx(sim_s / 0.1 - 1, abs=2)
    msgs = [m for _, m in odo]
    assert [m.frame_seq for m in msgs] == list(range(1, len(msgs) + 1))
    # Each view against the newest at least the altitude's baseline older (0.2 s at 40 m, 0.1 s at
    # 20 m: VisualVelocity), once the stream holds one that old.
    baseline = VisualVelocityConfig().baseline_s
    assert all(m.prev_frame_seq < m.frame_seq and m.dt_s == pytest.approx(0.1 * (m.frame_seq - m.prev_frame_seq))
               for m in msgs)
    assert all(baseline(m.alt_agl_m) - 1e-6 <= m.dt_s < baseline(m.alt_agl_m) + 0.1 for m in msgs[3:])
    assert all(m.stamp == s.stamp and m.alt_agl_m == s.alt_agl_m for s, m in odo)
    valid = [(s, m) for s, m in odo if m.valid]
    assert len(valid) >= 0.9 * len(odo)
    # Against the velocity the vehicle flew (the state is the truth under this config): the
    # horizontal error within 10 % of the speed for the median, 25 % for the worst tenth.
    errs = [np.linalg.norm(np.subtract(m.vel_body_frd_m_s[:2], s.vel_body_frd_m_s[:2])) /
            max(0.5, np.linalg.norm(s.vel_body_frd_m_s[:2])) for s, m in valid]
    assert np.median(errs) < 0.10 and np.percentile(errs, 90) < 0.25, (np.median(errs), np.percentile(errs, 90))


def test_without_odometry_the_episode_is_unchanged(world: World) -> None:
    start = Start(WEST_M, MID_Y_M, 30.0)
    plain = fly(SimCore(world, start, SimConfig(vehicle_id=VID)), FORWARD)
    with_odo = fly(SimCore(world, start, SimConfig(vehicle_id=VID, odometry_rate_hz=10.0)), FORWARD)
    assert all(o.odometry is None for o in plain)
    strip = lambda s: s.__class__(**{**s.__dict__, "sent_wall_s": 0.0})  # noqa: E731 - wall time differs
    assert [strip(o.state) for o in plain] == [strip(o.state) for o in with_odo]
    assert plain[-1].result.outcome == with_odo[-1].result.outcome


def test_a_gimballed_camera_is_tagged_level(world: World) -> None:
    # The body rolls 0.2 rad but the gimbal keeps the camera level: told the body's roll, the
    # estimator would remove a rotation the image never had (and read ~ alt x 0.2 / dt of motion).
    def states(roll: float):
        return [VehicleState(VID, k, Stamp(0.1 * k, "sim"), 40.0, (0.0, 0.0, 0.0), roll_rad=roll * (k > 0))
                for k in range(3)]

    def run(tag):
        odo = SimOdometry(world, CameraModel(), VID, 10.0)
        return [odo.observe(WEST_M, MID_Y_M, 40.0, 0.0, st, tag_roll_pitch_rad=tag) for st in states(0.2)][1:]
    level = run((0.0, 0.0))
    assert all(m.valid and np.linalg.norm(m.vel_body_frd_m_s) < 0.1 for m in level)
    assert all(not m.valid or np.linalg.norm(m.vel_body_frd_m_s) > 10.0 for m in run(None))


def test_odometry_flag(world: World) -> None:
    assert config_from_args(build_parser().parse_args(["--odometry-rate-hz", "10"])).sim.odometry_rate_hz == 10.0
    assert config_from_args(build_parser().parse_args([])).sim.odometry_rate_hz == 0.0
    with pytest.raises(ConfigError, match="odometry_rate_hz"):
        SimConfig(odometry_rate_hz=-1.0)


def test_lockstep_service_publishes_odometry_before_the_state(pair, world: World) -> None:
    from tests.sim.test_sim_core import command  # lazy: the lockstep answer helper of the core tests

    sim_session, rec = pair
    config = lockstep_config(sim=SimConfig(vehicle_id=VID, time_limit_s=30.0, odometry_rate_hz=10.0))
    with SimThread(sim_session, config, world) as sim:
        rec.announce()
        rec.until_result(lambda st: rec.send(command(st, (0.5, 0.0, 4.0))))
        sim.join()
    topics = [t for t, _ in rec.seen]
    odo = rec.of("odometry")
    assert odo and sim.stats.odometry_sent == len(odo)
    assert all(isinstance(m, VisualOdometry) and m.vehicle_id == VID for m in odo)
    # Each odometry message is followed by the state of the same step (same stamp).
    msgs = rec.seen
    for i, (t, m) in enumerate(msgs):
        if t == "odometry":
            nxt = msgs[i + 1]
            assert nxt[0] == "state" and nxt[1].stamp == m.stamp
    assert topics.count("odometry") >= 10


def test_external_pose_publishes_odometry_of_the_received_poses(pair, world: World) -> None:
    sim_session, rec = pair
    config = external_config(sim=SimConfig(vehicle_id=VID, odometry_rate_hz=10.0))
    with StatePublisher(rec.session) as _states, SimThread(sim_session, config, world) as sim:
        got: list[VisualOdometry] = []
        while len(got) < 5:
            topic, msg = rec.next()
            if topic == "odometry":
                got.append(msg)
        sim.stop.set()
    # A vehicle hovering where the controller says: valid, and no motion.
    assert all(m.stamp.clock == "vehicle" and m.alt_agl_m == pytest.approx(60.0) for m in got)
    assert sum(m.valid for m in got) >= 4
    assert all(np.linalg.norm(m.vel_body_frd_m_s) < 0.2 for m in got if m.valid)
    assert sim.stats.odometry_sent >= 5
