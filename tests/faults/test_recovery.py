"""What the fault suite found in the controller's core, pinned without Zenoh: a perception gap under the
`reference` preset, a terminal decision refused in mid-air, and the clock anchor across an outage."""

from __future__ import annotations

import numpy as np

from dovesei.controller.core import DT_CAP_PERIODS, ControllerConfig, ControllerCore, ControllerInputError, Mode
from dovesei.controller.policies.base import Decision, Observation
from dovesei.shared.messages import SafetyHeatmap, Stamp, VehicleState
from dovesei.shared.timing import timing


def heatmap(seq: int, t_s: float, alt_m: float) -> SafetyHeatmap:
    prob = np.full((88, 88), 255, np.uint8)  # all safe: the dovesei policy aims, then descends
    return SafetyHeatmap("uav1", seq, Stamp(t_s, "sim"), prob, alt_m, 1.274, "simulated", True, "p", "f", 0.01)


def state(seq: int, t_s: float, alt_m: float, await_seq: int = -1) -> VehicleState:
    return VehicleState("uav1", seq, Stamp(t_s, "sim"), alt_m, (0.0, 0.0, 0.0), await_frame_seq=await_seq)


def test_a_4_s_perception_gap_under_reference_timing_never_lands_the_dovesei_policy_in_mid_air() -> None:
    """Was: the gap, capped at 1 s = 15 reference seconds, made the descent estimate 40 m: LANDED at 45 m."""
    core = ControllerCore(ControllerConfig(lockstep=True, timing="reference", policy="dovesei"))
    alt_m, t_s, seq = 60.0, 0.0, 0
    states: list[str] = []
    for k in range(300):
        if k == 160:
            t_s += 4.0  # the segmenter hung for 4 s of sim time
        core.on_heatmap(heatmap(seq, t_s, alt_m), 0.0)
        cmd, status = core.tick(state(seq, t_s + 0.05, alt_m, await_seq=seq))
        states.append(status.state)
        alt_m = max(21.0, alt_m - 0.05 * cmd.vel_body_frd_m_s[2])
        t_s += 0.05
        seq += 1
    assert states[159] == "LANDING", "the policy never descended before the gap (the test is not probing anything)"
    assert "LANDED" not in states and core.rejected["terminal above hand-over"] == 0
    assert core.mode is Mode.OK


def test_the_policy_step_is_capped_at_two_nominal_periods_of_the_preset() -> None:
    for name in ("reference", "real"):
        cap_s = min(1.0, DT_CAP_PERIODS * timing(name).decision_period_s)
        seen: list[float] = []

        class Records:
            name = "double"

            def step(self, obs: Observation) -> Decision:
                seen.append(obs.t_s)
                return Decision((0.0, 0.0, 1.0), 0.0, "AIMING", None, 0.0, None)

            def reset(self) -> None:
                pass

        core = ControllerCore(ControllerConfig(lockstep=True, timing=name), policy=Records())
        for seq, t_s in enumerate((0.0, 30.0)):
            core.on_heatmap(heatmap(seq, t_s, 80.0), 0.0)
            core.tick(state(seq, t_s + 0.01, 80.0, await_seq=seq))
        assert seen[1] - seen[0] == cap_s, name


class LandsOnce:
    """Declares LANDED on its 2nd step (a policy fooled by a gap), then steers again after a reset."""

    name = "double"

    def __init__(self) -> None:
        self.steps, self.resets = 0, 0

    def step(self, obs: Observation) -> Decision:
        self.steps += 1
        landed = self.steps == 2
        return Decision((0.0, 0.0, 0.0 if landed else 1.0), 0.0, "LANDED" if landed else "LANDING", None, 0.0,
                        None)

    def reset(self) -> None:
        self.resets += 1
        self.steps = 0


def test_a_terminal_decision_refused_in_mid_air_restarts_the_policy_and_the_mission_resumes() -> None:
    policy = LandsOnce()
    core = ControllerCore(ControllerConfig(lockstep=True), policy=policy)
    modes = []
    for seq in range(4):
        core.on_heatmap(heatmap(seq, 0.05 * seq, 60.0), 0.0)
        cmd, status = core.tick(state(seq, 0.05 * seq + 0.01, 60.0, await_seq=seq))
        modes.append((core.mode, status.state, cmd.vel_body_frd_m_s[2]))
    assert modes[1] == (Mode.POLICY_FAULT, "LANDED", 0.0), "the mid-air LANDED is refused and the vehicle holds"
    assert policy.resets == 1 and core.rejected["policy restarted"] == 1
    assert modes[2][0] is Mode.OK and modes[2][2] > 0.0, "after the restart the policy steers again"


def test_an_outage_does_not_make_every_later_state_look_early() -> None:
    """Was: re-ticking the last state through an outage re-anchored its old stamp to 'now'."""
    now = [0.0]
    core = ControllerCore(ControllerConfig(lockstep=False, timing="reference"), mono=lambda: now[0])
    for k in range(20):  # on time: the vehicle clock and the controller's advance together
        now[0] = 0.05 * k
        core.on_heatmap(heatmap(k, 0.05 * k, 50.0), now[0])
        core.tick(state(k, 0.05 * k, 50.0), wall_s=now[0])
    last = state(19, 0.95, 50.0)
    for k in range(60):  # a 3 s outage: the loop keeps ticking on the newest state it has
        now[0] = 1.0 + 0.05 * k
        core.tick(last, wall_s=now[0])
    assert core.mode is Mode.STATE_STALE
    now[0] = 4.0
    try:
        core.tick(state(80, 4.0, 50.0), wall_s=now[0])  # the vehicle's clock ran on meanwhile
    except ControllerInputError as exc:
        raise AssertionError(f"an on-time state after the outage was refused: {exc}") from None
    assert core.rejected["state from the future"] == 0


class WindsUp:
    """A policy whose integrator runs away: its command would not even pass the message's own checks."""

    name = "double"

    def step(self, obs: Observation) -> Decision:
        return Decision((18497.8, 0.0, 1.0), 0.0, "RESTARTING", None, 0.0, None)

    def reset(self) -> None:
        pass


def test_a_runaway_policy_command_holds_instead_of_ending_the_loop() -> None:
    core = ControllerCore(ControllerConfig(lockstep=True), policy=WindsUp())
    core.on_heatmap(heatmap(0, 0.0, 60.0), 0.0)
    cmd, status = core.tick(state(0, 0.01, 60.0, await_seq=0))  # raised FieldError before
    assert core.mode is Mode.POLICY_FAULT and cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0)
    assert "policy commanded" in status.reason and core.policy_errors == 1


def test_after_a_hang_of_its_own_the_controller_resynchronises_on_live_states() -> None:
    """Was: the backlog came first, anchored a 4 s old stamp to 'now', and every live state was refused."""
    now = [0.0]
    core = ControllerCore(ControllerConfig(lockstep=False, timing="reference"), mono=lambda: now[0])
    for k in range(20):
        now[0] = 0.05 * k
        core.tick(state(k, 0.05 * k, 50.0), wall_s=now[0])
    now[0] = 5.0  # SIGSTOP for 4 s: the first state polled after SIGCONT is from the backlog
    core.tick(state(21, 1.05, 50.0), wall_s=now[0])
    refused, accepted = 0, 0
    for k in range(40):  # then the live ones, 4 s ahead of that stale anchor
        now[0] = 5.05 + 0.05 * k
        try:
            core.tick(state(100 + k, 5.05 + 0.05 * k, 50.0), wall_s=now[0])
            accepted += 1
        except ControllerInputError:
            refused += 1
            assert accepted == 0, "once re-synchronised, live states are never refused again"
    assert accepted > 25 and refused <= 11, (accepted, refused)  # within state_stale_after_s (0.5 s) + a tick


def test_a_gap_in_the_states_does_not_let_a_forged_lead_set_the_clock() -> None:
    """Was: after 0.5 s without an accepted state, the next state re-synchronised the clock whatever its
    stamp, so a forger's state 30 s ahead (a loaded host pausing the genuine ones) made its matching
    forged heatmaps fresh."""
    now = [0.0]
    core = ControllerCore(ControllerConfig(lockstep=False, timing="real"), mono=lambda: now[0])
    for k in range(20):
        now[0] = 0.05 * k
        core.tick(state(k, 0.05 * k, 50.0), wall_s=now[0])
    now[0] = 2.0  # the genuine states paused for a second
    try:
        core.tick(state(900, 2.0 + 30.0, 50.0), wall_s=now[0])
        raise AssertionError("a state 30 s ahead of every projection was accepted after a gap")
    except ControllerInputError:
        pass
    assert core.rejected["state from the future"] == 1
    core.tick(state(40, 2.0, 50.0), wall_s=now[0])  # the genuine clock goes on being accepted
