"""Values valid on the wire that no camera or multirotor produces: the controller refuses them,
counts them in one warning line each, and keeps serving (the fault probes of issue 26).

Core tests drive `ControllerCore` with the real policies; one test sends the probe through the
Zenoh service to show the loop survives it.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from dovesei.controller.core import ControllerConfig, ControllerCore, Mode
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import SafetyHeatmap, Stamp, VehicleState
from dovesei.controller.policies.base import Decision
from tests.controller.test_service_zenoh import start_service

CAMERA_HFOV_RAD = math.radians(73.0)  # the sim's and the reference's camera, the controller's default


def heatmap(seq: int, t_s: float, alt_m: float = 80.0, hfov_rad: float = CAMERA_HFOV_RAD,
            side_px: int = 352) -> SafetyHeatmap:
    prob = np.full((side_px, side_px), 200, np.uint8)
    prob[side_px // 3:side_px // 2, side_px // 3:side_px // 2] = 20
    return SafetyHeatmap("uav1", seq, Stamp(t_s, "sim"), prob, alt_m, hfov_rad, "simulated", True, "p", "f", 0.01)


def state(seq: int, t_s: float, alt_m: float = 80.0, await_seq: int = -1) -> VehicleState:
    return VehicleState("uav1", seq, Stamp(t_s, "sim"), alt_m, (0.0, 0.0, 0.0), await_frame_seq=await_seq)


@pytest.mark.parametrize("policy", ["clearance", "dovesei"])
@pytest.mark.parametrize(("what", "bad"), [
    ("hfov 1e-6", {"hfov_rad": 1e-6}),  # killed the controller: focus_radius_px 1477523.18
    ("hfov ~pi", {"hfov_rad": 3.14}),
    ("4096 px", {"side_px": 4096}),
    ("alt 0", {"alt_m": 0.0}),  # the paper's policy declared LANDED
    ("alt -999", {"alt_m": -999.0}),
])
def test_a_heatmap_no_camera_of_ours_sends_is_refused_and_the_loop_goes_on(policy: str, what: str, bad: dict,
                                                                           caplog) -> None:
    core = ControllerCore(ControllerConfig(lockstep=True, policy=policy))
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    core.tick(state(0, 0.05, await_seq=0))
    with caplog.at_level(logging.WARNING, logger="dovesei.controller.core"):
        assert core.on_heatmap(heatmap(1, 0.10, **bad), 0.0) is False
    refused = [r.getMessage() for r in caplog.records if "heatmap 1 refused" in r.getMessage()]
    assert len(refused) == 1 and "\n" not in refused[0], refused
    assert core.rejected["camera model"] == 1
    cmd, status = core.tick(state(1, 0.15, await_seq=1))  # it was never buffered: decided without it
    assert cmd.frame_seq == 0 and status.state not in ("LANDED", "HANDOVER")
    assert core.rejected["policy restarted"] == 0 and core.rejected["terminal above hand-over"] == 0
    core.on_heatmap(heatmap(2, 0.20), 0.0)  # the next honest heatmap is taken as ever
    cmd, _ = core.tick(state(2, 0.25, await_seq=2))
    assert cmd.frame_seq == 2


def test_the_camera_model_is_configurable_and_an_exact_size_can_be_required() -> None:
    core = ControllerCore(ControllerConfig(lockstep=True, camera_hfov_deg=58.0, camera_size_px=(352, 352)))
    assert core.on_heatmap(heatmap(0, 0.0, hfov_rad=math.radians(60.0)), 0.0)
    assert not core.on_heatmap(heatmap(1, 0.0, hfov_rad=math.radians(90.0)), 0.0)
    assert not core.on_heatmap(heatmap(2, 0.0, hfov_rad=math.radians(60.0), side_px=176), 0.0)
    assert core.rejected["camera model"] == 2
    for bad in ({"camera_hfov_deg": 0.0}, {"camera_size_px": (0, 352)}, {"max_vertical_speed_m_s": -1.0},
                {"handover_confirm_states": 0}):
        with pytest.raises(ConfigError):
            ControllerConfig(**bad)


def test_a_heatmap_captured_at_an_altitude_the_vehicle_never_had_is_refused() -> None:
    core = ControllerCore(ControllerConfig(lockstep=True, policy="dovesei"))
    for k in range(3):
        core.tick(state(k, 0.05 * k, alt_m=80.0))
    core.on_heatmap(heatmap(0, 0.05, alt_m=25.0), 0.0)  # the vehicle was at 80 m when it was captured
    cmd, _ = core.tick(state(3, 0.15, alt_m=80.0, await_seq=0))
    assert core.rejected["heatmap altitude"] == 1 and cmd.frame_seq == -1
    core.on_heatmap(heatmap(1, 0.10, alt_m=79.0), 0.0)  # within the altitude noise: taken
    cmd, _ = core.tick(state(4, 0.20, alt_m=80.0, await_seq=1))
    assert cmd.frame_seq == 1


@pytest.mark.parametrize("lockstep", [True, False])
def test_an_altitude_jump_no_multirotor_can_fly_is_refused_and_counted(lockstep: bool) -> None:
    config = ControllerConfig(lockstep=lockstep, policy="dovesei", timing="reference" if lockstep else "real")
    core = ControllerCore(config, mono=lambda: 0.0)
    wall = (lambda s: None) if lockstep else (lambda s: s)
    core.on_heatmap(heatmap(0, 10.0, alt_m=60.0), 0.0)
    core.tick(state(0, 10.0, alt_m=60.0, await_seq=0), wall_s=wall(0.0))
    # +100 m in 50 ms: refused, answered with a hold (a lockstep sim waits for an answer to every state).
    cmd, status = core.tick(state(1, 10.05, alt_m=160.0), wall_s=wall(0.05))
    assert core.rejected["altitude jump"] == 1 and "altitude 160.0 m" in status.reason
    assert cmd.state_seq == 1 and cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0) and status.watchdog == "hold"
    assert status.alt_agl_m == 60.0  # the altitude it holds to, not the refused one
    cmd, status = core.tick(state(2, 10.10, alt_m=59.8), wall_s=wall(0.1))  # the honest stream goes on
    assert cmd.state_seq == 2 and status.alt_agl_m == 59.8
    # A step that holds (an estimator reset, a rangefinder over a roof) is taken after 3 states.
    for k in (3, 4):
        _, status = core.tick(state(k, 10.10 + 0.05 * (k - 2), alt_m=30.0), wall_s=wall(0.1 + 0.05 * (k - 2)))
        assert "refused" in status.reason
    cmd, status = core.tick(state(5, 10.25, alt_m=30.0), wall_s=wall(0.25))
    assert cmd.state_seq == 5 and status.alt_agl_m == 30.0 and core.rejected["altitude jump"] == 3


class Landing:
    """A policy committed to landing, as the paper's is in LANDING."""

    name = "double"

    def step(self, obs):
        return Decision((0.0, 0.0, 1.0), 0.0, "LANDING", None, 10.0, 0.5, landing=True)

    def reset(self) -> None:
        pass


def test_one_forged_low_state_never_hands_over() -> None:
    core = ControllerCore(ControllerConfig(lockstep=True), policy=Landing())
    core.on_heatmap(heatmap(0, 0.0, alt_m=22.0), 0.0)
    core.tick(state(0, 0.05, alt_m=22.0, await_seq=0))
    # 19 m, plausible after 22 m: accepted as a state, but one sample is no altitude.
    cmd, status = core.tick(state(1, 0.10, alt_m=19.0))
    assert core.mode is Mode.OK and not cmd.handover and status.state == "LANDING"
    cmd, _ = core.tick(state(2, 0.15, alt_m=22.0))
    assert not cmd.handover
    # Nor does one low state re-ticked by a real-time loop while no newer state comes.
    rt = ControllerCore(ControllerConfig(lockstep=False, timing="real"), policy=Landing(), mono=lambda: 0.0)
    rt.on_heatmap(heatmap(0, 10.0, alt_m=22.0), 0.0)
    rt.tick(state(0, 10.0, alt_m=22.0), wall_s=0.0)
    low = state(1, 10.05, alt_m=19.0)
    for k in range(5):
        cmd, _ = rt.tick(low, wall_s=0.05 + 0.01 * k)
        assert not cmd.handover
    # A genuine descent holds below 20 m over several states: then it is the hand-over.
    for k, alt_m in enumerate((19.9, 19.8, 19.7), start=3):
        cmd, status = core.tick(state(k, 0.05 * (k + 1), alt_m=alt_m))
    assert core.mode is Mode.HANDOVER and cmd.handover and status.handover


def test_a_hostile_heatmap_through_the_service_is_refused_and_the_service_keeps_serving(zenoh_pair) -> None:
    # The refused heatmap is waited for until this wall deadline; honest ones arrive well within it.
    config = ControllerConfig(lockstep=True, policy="clearance", lockstep_heatmap_wait_s=3.0)
    for h, thread in start_service(zenoh_pair, config):
        h.put_heatmap(heatmap(0, 0.0))
        h.put_state(state(0, 0.05, await_seq=0))
        assert h.next_cmd().frame_seq == 0
        h.put_heatmap(heatmap(1, 0.10, hfov_rad=1e-6))  # valid on the wire
        h.put_state(state(1, 0.15, await_seq=1))
        cmd = h.next_cmd()
        assert cmd.state_seq == 1 and cmd.frame_seq == 0  # decided without it, not dead
        h.put_heatmap(heatmap(2, 0.20))
        h.put_state(state(2, 0.25, await_seq=2))
        cmd = h.next_cmd()
        assert cmd.state_seq == 2 and cmd.frame_seq == 2
        assert h.finish(thread).ticks == 3
        statuses = list(iter(h.statuses.poll, None))
        assert statuses and all(s.frame_seq != 1 for s in statuses)  # the probe never became a decision
