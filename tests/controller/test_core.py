"""ControllerCore without Zenoh: hand-made heatmaps and states, a recording test-double policy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.controller.core import ControllerConfig, ControllerCore, ControllerInputError, JUMP_CONFIRM_STATES, Mode
from dovesei.controller.policies.base import Decision, Observation, PolicyInputError
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import SafetyHeatmap, Stamp, VehicleState

VEL_FRD = (1.0, -0.5, 2.0)  # what the double always commands: forward, left, descending


class RecordingPolicy:
    """Answers every heatmap with the same descending decision and remembers what it saw."""

    name = "double"

    def __init__(self, landing: bool = True) -> None:
        self.observations: list[Observation] = []
        self.resets = 0
        self.landing = landing  # committed to landing: a hand-over at 20 m is its to declare

    def step(self, obs: Observation) -> Decision:
        self.observations.append(obs)
        return Decision(VEL_FRD, 0.1, "AIMING", (10.0, 20.0), 123.0, 0.42, landing=self.landing)

    def reset(self) -> None:
        self.resets += 1
        self.observations.clear()


class HandsOver(RecordingPolicy):
    """Declares its hand-over at every step, whatever the altitude."""

    def step(self, obs: Observation) -> Decision:
        self.observations.append(obs)
        return Decision((0.0, 0.0, 0.0), 0.0, "HANDOVER", None, 0.0, None, landing=True)


def heatmap(seq: int, t_s: float, *, alt_m: float = 80.0, vehicle: str = "uav1", clock: str = "sim",
            sent_wall_s: float = 0.0) -> SafetyHeatmap:
    prob = np.full((16, 16), 51, np.uint8)  # 51 / 255 = 0.2
    return SafetyHeatmap(vehicle, seq, Stamp(t_s, clock), prob, alt_m, 1.2, "simulated", True, "p", "f",
                         inference_s=0.2, frame_to_segmenter_s=0.01, sent_wall_s=sent_wall_s)


def state(seq: int, t_s: float, *, alt_m: float = 80.0, await_seq: int = -1, vehicle: str = "uav1") -> VehicleState:
    return VehicleState(vehicle, seq, Stamp(t_s, "sim"), alt_m, (0.0, 0.0, 0.0), await_frame_seq=await_seq)


def make_core(**overrides: object) -> tuple[ControllerCore, RecordingPolicy]:
    policy = RecordingPolicy()
    return ControllerCore(ControllerConfig(**overrides), policy=policy), policy


def test_before_the_first_heatmap_it_holds_and_says_why() -> None:
    core, policy = make_core(lockstep=True)
    cmd, status = core.tick(state(0, 0.0))
    assert cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0) and cmd.frame_seq == -1 and cmd.latency is None
    assert cmd.state_seq == 0 and cmd.stamp == Stamp(0.0, "sim")
    assert status.watchdog == "hold" and "no heatmap" in status.reason
    assert status.state == "INIT" and status.heatmap_age_s == -1.0 and status.frame_seq == -1
    assert core.mode is Mode.NO_HEATMAP and not policy.observations


def test_a_command_and_a_status_every_tick_with_increasing_seq() -> None:
    core, _ = make_core(lockstep=True)
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    out = [core.tick(state(k, 0.05 * k, await_seq=0 if k == 1 else -1)) for k in range(6)]
    assert [cmd.seq for cmd, _ in out] == [1, 2, 3, 4, 5, 6]
    assert [cmd.state_seq for cmd, _ in out] == [0, 1, 2, 3, 4, 5]
    assert [status.seq for _, status in out] == [1, 2, 3, 4, 5, 6]
    # From the adopting tick on, the decision is sent every tick (fresh heatmap, watchdog ok).
    assert [cmd.vel_body_frd_m_s for cmd, _ in out[1:]] == [VEL_FRD] * 5


def test_lockstep_adopts_exactly_the_awaited_seq_and_never_an_early_one() -> None:
    core, policy = make_core(lockstep=True)
    for seq in (0, 1, 2):  # all arrive early
        assert core.on_heatmap(heatmap(seq, 0.05 * seq), 0.0)
    cmd, _ = core.tick(state(0, 0.05))  # nothing due yet
    assert cmd.frame_seq == -1 and not policy.observations
    cmd, status = core.tick(state(1, 0.10, await_seq=1))
    assert cmd.frame_seq == 1 and status.frame_seq == 1
    assert [o.t_s for o in policy.observations] == [0.05]  # seq 1's capture time, seq 2 unused
    assert not core.has_heatmap(0), "a seq older than the adopted one can never be due"
    assert core.has_heatmap(2)
    cmd, _ = core.tick(state(2, 0.15))  # await -1: keep the last decision, no policy step
    assert cmd.frame_seq == 1 and len(policy.observations) == 1
    cmd, _ = core.tick(state(3, 0.20, await_seq=2))
    assert cmd.frame_seq == 2 and len(policy.observations) == 2


def test_the_observation_says_how_long_after_its_capture_the_decision_is_flown() -> None:
    """`Observation.delay_s`: the state the decision is adopted at, less the heatmap's stamp (the
    pipeline's latency, 0.4 s in the bench's real timing)."""
    core, policy = make_core(lockstep=True)
    core.on_heatmap(heatmap(1, 10.0), 0.0)
    core.tick(state(0, 10.40, await_seq=1))
    core.on_heatmap(heatmap(2, 10.5), 0.0)
    core.tick(state(1, 10.95, await_seq=2))
    assert [round(o.delay_s, 6) for o in policy.observations] == [0.4, 0.45]


def test_lockstep_missing_awaited_heatmap_is_counted_and_the_last_decision_kept() -> None:
    core, policy = make_core(lockstep=True)
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    core.tick(state(0, 0.05, await_seq=0))
    cmd, _ = core.tick(state(1, 0.10, await_seq=1))  # never arrived
    assert cmd.frame_seq == 0 and cmd.vel_body_frd_m_s == VEL_FRD  # 0.1 s old: still fresh
    assert core.rejected["awaited heatmap missing"] == 1 and len(policy.observations) == 1


def test_real_time_keeps_the_newest_heatmap_by_capture_time() -> None:
    core, policy = make_core(lockstep=False)
    assert core.on_heatmap(heatmap(3, 0.3), 0.0)
    assert core.on_heatmap(heatmap(5, 0.5), 0.0)
    assert not core.on_heatmap(heatmap(4, 0.4), 0.0), "reordered older heatmap must not replace a newer one"
    cmd, _ = core.tick(state(10, 0.6), wall_s=0.0)
    assert cmd.frame_seq == 5 and [o.t_s for o in policy.observations] == [0.5]
    cmd, _ = core.tick(state(11, 0.65), wall_s=0.05)  # no new heatmap: no new policy step
    assert cmd.frame_seq == 5 and len(policy.observations) == 1


def test_observation_is_built_from_the_heatmap_not_the_current_state() -> None:
    core, policy = make_core(lockstep=True)
    core.on_heatmap(heatmap(0, 1.0, alt_m=93.5), 0.0)
    core.tick(state(0, 1.05, alt_m=90.0, await_seq=0))
    (obs,) = policy.observations
    assert obs.t_s == 1.0 and obs.alt_agl_m == 93.5 and obs.hfov_rad == 1.2
    assert obs.prob_safe.dtype == np.float32 and obs.prob_safe.shape == (16, 16)
    assert np.allclose(obs.prob_safe, 0.2)


def test_stage_latency_comes_from_the_heatmap_and_the_policy_timer() -> None:
    core, _ = make_core(lockstep=True)
    core.on_heatmap(heatmap(0, 0.0, sent_wall_s=1000.0), 1000.25)
    cmd, _ = core.tick(state(0, 0.05, await_seq=0))
    lat = cmd.latency
    assert lat is not None
    assert lat.inference_s == 0.2 and lat.frame_to_segmenter_s == 0.01
    assert lat.heatmap_to_controller_s == pytest.approx(0.25)
    assert 0.0 < lat.policy_s < 1.0


def test_status_carries_the_decision_and_the_watchdog_fields() -> None:
    core, _ = make_core(lockstep=True)
    core.on_heatmap(heatmap(4, 2.0), 0.0)
    _, status = core.tick(state(9, 2.3, alt_m=77.0, await_seq=4))
    assert status.policy == "double" and status.state == "AIMING" and status.watchdog == "ok"
    assert status.target_valid and (status.target_row_px, status.target_col_px) == (10.0, 20.0)
    assert status.focus_radius_px == 123.0 and status.threshold_valid and status.threshold == 0.42
    assert status.heatmap_age_s == pytest.approx(0.3) and status.frame_seq == 4
    assert status.vel_body_frd_m_s == VEL_FRD and status.alt_agl_m == 77.0
    assert status.stamp == Stamp(2.3, "sim") and status.reason


def test_handover_stops_commanding_with_hysteresis() -> None:
    core, _ = make_core(lockstep=True, handover_alt_m=20.0, handover_release_m=2.0)
    core.on_heatmap(heatmap(0, 0.0, alt_m=20.5), 0.0)
    cmd, status = core.tick(state(0, 0.05, alt_m=20.5, await_seq=0))
    assert status.state == "AIMING" and cmd.vel_body_frd_m_s == VEL_FRD
    for k in (1, 2):  # at the altitude: it must hold a few states before the hand-over
        cmd, status = core.tick(state(k, 0.05 + 0.05 * k, alt_m=20.0))
        assert status.state == "AIMING" and not cmd.handover
    cmd, status = core.tick(state(3, 0.20, alt_m=20.0))
    assert status.state == "HANDOVER" and cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0) and cmd.handover
    assert "hand-over" in status.reason and core.mode is Mode.HANDOVER
    _, status = core.tick(state(4, 0.25, alt_m=21.5))  # noise above 20 m: still handed over
    assert status.state == "HANDOVER"
    _, status = core.tick(state(5, 0.30, alt_m=22.5))  # clearly above: control resumes
    assert status.state == "AIMING"


def test_sinking_below_the_handover_altitude_without_the_policy_landing_is_no_handover() -> None:
    # Twice under `harsh` an aborted descent sank through 20 m and was taken for a landing.
    policy = RecordingPolicy(landing=False)
    core = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0), policy=policy)
    core.on_heatmap(heatmap(0, 0.0, alt_m=21.0), 0.0)
    cmd, status = core.tick(state(0, 0.05, alt_m=21.0, await_seq=0))
    assert not cmd.handover
    for k in range(1, 4):
        cmd, status = core.tick(state(k, 0.05 + 0.05 * k, alt_m=19.0))
        assert core.mode is Mode.OK and status.state == "AIMING" and not cmd.handover
        assert cmd.vel_body_frd_m_s == VEL_FRD  # still the policy's (it climbs back when it wants to)
    assert core.rejected["below hand-over, not landing"] == 1  # once per sink, not per tick
    # The policy commits: the very next tick is the hand-over, and the command says so.
    policy.landing = True  # the altitude has held for 3 states already: the next tick hands over
    core.on_heatmap(heatmap(1, 0.2, alt_m=19.0), 0.0)
    cmd, status = core.tick(state(4, 0.25, alt_m=19.0, await_seq=1))
    assert core.mode is Mode.HANDOVER and status.state == "HANDOVER" and cmd.handover
    assert cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0)


def test_a_noisy_baro_around_the_handover_altitude_is_one_sink_until_it_climbs_clear() -> None:
    """Back over 20 m and under it again is the same sink (harsh: 1 m of noise per state while a
    close look held the vehicle at 20 m logged every crossing); clear of the hand-over band it is
    a new one."""
    policy = RecordingPolicy(landing=False)
    core = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0), policy=policy)
    core.on_heatmap(heatmap(0, 0.0, alt_m=21.0), 0.0)
    core.tick(state(0, 0.05, alt_m=21.0, await_seq=0))
    for k, alt_m in enumerate((19.4, 20.6, 19.4, 21.5, 19.2), start=1):
        core.tick(state(k, 0.05 + 0.05 * k, alt_m=alt_m))
    assert core.rejected["below hand-over, not landing"] == 1
    for k, alt_m in enumerate((22.5, 21.0, 19.0), start=6):  # 2.5 m over: clear of the 2 m band
        core.tick(state(k, 0.05 + 0.05 * k, alt_m=alt_m))
    assert core.rejected["below hand-over, not landing"] == 2


def test_other_vehicles_and_other_clocks_are_refused() -> None:
    core, policy = make_core(lockstep=False)
    with pytest.raises(ControllerInputError, match="uav2"):
        core.tick(state(0, 0.0, vehicle="uav2"))
    assert not core.on_heatmap(heatmap(0, 0.0, vehicle="uav2"), 0.0)
    assert core.on_heatmap(heatmap(1, 0.0, clock="vehicle"), 0.0)
    cmd, _ = core.tick(state(1, 0.05), wall_s=0.0)
    assert cmd.frame_seq == -1 and not policy.observations
    assert core.rejected["other vehicle"] == 2 and core.rejected["clock mismatch"] == 1


def test_a_policy_refusal_is_counted_and_the_heatmap_not_adopted() -> None:
    class Refusing(RecordingPolicy):
        def step(self, obs: Observation) -> Decision:
            raise PolicyInputError("bad heatmap")

    core = ControllerCore(ControllerConfig(lockstep=True), policy=Refusing())
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    cmd, status = core.tick(state(0, 0.05, await_seq=0))
    assert cmd.frame_seq == -1 and status.watchdog == "hold"
    assert core.rejected["policy refused"] == 1


def test_data_time_going_back_starts_a_new_episode() -> None:
    core, policy = make_core(lockstep=True)
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    core.tick(state(0, 50.0, await_seq=0))
    core.on_heatmap(heatmap(0, 0.0), 0.0)  # the new episode's first frame, before its first state
    cmd, status = core.tick(state(0, 0.05, await_seq=0))
    assert policy.resets == 1
    assert cmd.frame_seq == 0 and status.heatmap_age_s == pytest.approx(0.05)


def test_real_wiring_builds_the_named_policy() -> None:
    core = ControllerCore(ControllerConfig(policy="dovesei-nofocus", timing="reference", lockstep=True))
    assert core.policy.name == "dovesei-nofocus"
    rng = np.random.default_rng(1)
    prob = rng.random((64, 64)).astype(np.float16)
    hm = SafetyHeatmap("uav1", 0, Stamp(0.0, "sim"), prob, 100.0, math.radians(73), "simulated", True, "p", "f", 0.0)
    core.on_heatmap(hm, 0.0)
    cmd, status = core.tick(state(0, 0.05, alt_m=100.0, await_seq=0))
    assert status.policy == "dovesei-nofocus" and status.frame_seq == 0 and status.watchdog == "ok"
    assert status.state == "SENSOR_ERROR"  # the reference's warm-up cycles
    assert cmd.latency is not None and cmd.latency.policy_s > 0


@pytest.mark.parametrize("overrides, match", [
    ({"heatmap_hold_after_s": 2.0, "heatmap_climb_after_s": 1.0}, "must exceed"),
    ({"handover_action": "explode"}, "handover_action"),
    ({"policy": "nope"}, "policy"),
    ({"timing": "fast"}, "timing"),
    ({"rate_hz": 0.0}, "rate_hz"),
    ({"rate_hz": math.nan}, "rate_hz"),
    ({"vehicle_id": "a/b"}, "vehicle id"),
    ({"search_alt_m": 10.0}, "search_alt_m"),
    ({"lockstep": True, "vehicle_url": "udpin:0.0.0.0:14550", "timing": "real"}, "lockstep"),
    ({"lockstep": False, "vehicle_url": "udpin:0.0.0.0:14550", "timing": "reference"}, "true seconds"),
    ({"policy_dt_max_s": 0.0}, "policy_dt_max_s"),
])
def test_config_validation_names_the_bad_value(overrides: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        ControllerConfig(**overrides)


# ---- faults in front of every policy (issue 13: clocks, policy errors, mid-air LANDED) --------


class Clock:
    """The controller's own monotonic clock, moved by the test."""

    def __init__(self) -> None:
        self.t_s = 100.0

    def __call__(self) -> float:
        return self.t_s


def test_a_policy_exception_is_caught_counted_and_the_vehicle_holds() -> None:
    class Crashing(RecordingPolicy):
        def step(self, obs: Observation) -> Decision:
            if len(self.observations) >= 1:
                raise ZeroDivisionError("bug in the policy")
            return super().step(obs)

    policy = Crashing()
    core = ControllerCore(ControllerConfig(lockstep=True), policy=policy)
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    cmd, status = core.tick(state(0, 0.05, await_seq=0))
    assert cmd.vel_body_frd_m_s == VEL_FRD
    core.on_heatmap(heatmap(1, 0.10), 0.0)
    cmd, status = core.tick(state(1, 0.15, await_seq=1))  # the policy raises: hold, not its last decision
    assert cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0) and status.watchdog == "hold"
    assert core.mode is Mode.POLICY_FAULT and "ZeroDivisionError" in status.reason
    assert core.policy_errors == 1 and core.rejected["policy error"] == 1


@pytest.mark.parametrize("terminal", ["LANDED", "HANDOVER"])
def test_landed_above_the_handover_altitude_is_refused(terminal: str) -> None:
    class Lands(RecordingPolicy):
        def step(self, obs: Observation) -> Decision:
            self.observations.append(obs)
            return Decision((0.0, 0.0, 0.0), 0.0, terminal, None, 0.0, None)

    core = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0), policy=Lands())
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    cmd, status = core.tick(state(0, 0.05, alt_m=93.0, await_seq=0))  # measured altitude: 93 m
    assert core.mode is Mode.POLICY_FAULT and status.watchdog == "hold"
    assert f"declared {terminal} at 93.0 m" in status.reason and cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0)
    core.tick(state(1, 0.07, alt_m=93.0))  # the same decision again: still refused, counted once
    assert core.rejected["terminal above hand-over"] == 1 and core.mode is Mode.POLICY_FAULT
    # At the hand-over altitude (reached 10 s later) it is the real thing, once the altitude holds.
    _, status = core.tick(state(2, 10.0, alt_m=19.5))
    assert core.mode is Mode.HOLD and "confirming" in status.reason
    core.tick(state(3, 10.05, alt_m=19.5))
    _, status = core.tick(state(4, 10.10, alt_m=19.5))
    assert core.mode is Mode.HANDOVER and status.state == "HANDOVER" and status.handover
    assert core.rejected["terminal above hand-over"] == 1 and core.rejected["policy restarted"] == 0


def test_a_handover_declared_under_baro_noise_is_confirmed_by_a_majority_while_sinking_not_refused() -> None:
    # Under `harsh` (baro noise 1 m a state) a policy handed over at 19.5 m, the next state read
    # 22.2 m: the single-state rule refused it, restarted the policy at 21 m, and it timed out.
    policy = HandsOver()
    core = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0, handover_release_m=2.0,
                                           handover_sink_m_s=0.3), policy=policy)
    core.on_heatmap(heatmap(0, 0.0, alt_m=19.5), 0.0)
    t_s, seen = 0.05, []
    for seq, alt_m in enumerate((19.5, 21.8, 19.4, 21.2, 20.6, 19.8, 19.1)):
        cmd, status = core.tick(state(seq, t_s, alt_m=alt_m, await_seq=0 if seq == 0 else -1))
        seen.append((core.mode, cmd.vel_body_frd_m_s[2], cmd.handover))
        t_s += 0.05
    modes = [m for m, _, _ in seen]
    assert Mode.POLICY_FAULT not in modes and core.rejected["terminal above hand-over"] == 0
    assert policy.resets == 0 and core.rejected["policy restarted"] == 0
    # Confirming: sinking at 0.3 m/s and no hand-over until 3 of the last 5 states read <= 20 m.
    assert seen[:6] == [(Mode.HOLD, 0.3, False)] * 6  # 19.8 m: 19.4 and 19.8 of the last 5, not yet
    assert seen[6][0] is Mode.HANDOVER and seen[6][2] and seen[6][1] == 0.0  # 19.1 m: 19.4, 19.8, 19.1
    assert "hand-over" in status.reason and status.handover


def test_a_handover_measured_on_a_low_heatmap_is_confirmed_under_a_drifted_baro_within_its_band() -> None:
    # harsh coast start 23 (the vehicle on the camera's velocity): the policy declared HANDOVER on
    # a heatmap captured at 19.1 m, the states around it read 21-23.8 m (a +2 m baro offset and 1 m
    # of noise): median 22.2 m, over the 2 m release band, so it was refused and the restarted
    # policy timed out at 20 m. Measured on its own heatmap at the altitude, it is confirmed.
    def fly(states: tuple[float, ...]) -> tuple[ControllerCore, HandsOver, list]:
        policy = HandsOver()
        core = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0, handover_release_m=2.0,
                                               handover_declared_band_m=4.0, handover_sink_m_s=0.3), policy=policy)
        core.on_heatmap(heatmap(0, 0.0, alt_m=19.1), 0.0)
        # The next heatmap (the same HANDOVER) was captured at 21.9 m: the declaration was at 19.1 m.
        core.on_heatmap(heatmap(1, 0.05, alt_m=21.9), 0.0)
        seen = []
        for seq, alt_m in enumerate(states):
            cmd, _ = core.tick(state(seq, 0.05 * (seq + 1), alt_m=alt_m, await_seq=seq if seq < 2 else -1))
            seen.append((core.mode, cmd.vel_body_frd_m_s[2], cmd.handover))
        return core, policy, seen

    core, policy, seen = fly((19.1, 21.9, 22.1, 23.8, 22.2, 22.4, 21.3, 19.6, 19.9, 19.4))
    assert Mode.POLICY_FAULT not in [m for m, _, _ in seen] and core.rejected["terminal above hand-over"] == 0
    assert seen[:9] == [(Mode.HOLD, 0.3, False)] * 9  # sinking while the states read above 20 m
    assert seen[9][0] is Mode.HANDOVER and seen[9][2]  # 19.6, 19.9, 19.4: three of the last five
    assert policy.resets == 0 and core.rejected["policy restarted"] == 0
    # Beyond the band (states 5-6 m above what the heatmap read) it is refused as before.
    core, _, seen = fly((25.5, 26.0, 25.8))
    assert seen[-1][0] is Mode.POLICY_FAULT and core.rejected["terminal above hand-over"] >= 1


def test_a_confirming_hold_flies_the_policys_horizontal_hold_while_it_sinks() -> None:
    # Without GNSS a zero command drifts at the estimate's bias: a policy that learnt the bias
    # holds with its opposite, and the controller flies that while the baro confirms the altitude
    # (harsh villas start 1 of 6 drifted 3.4 m onto a sidewalk during a 2.4 s confirmation).
    class HoldsAgainstBias(RecordingPolicy):
        def step(self, obs: Observation) -> Decision:
            self.observations.append(obs)
            return Decision((-0.25, 1.6, 0.0), 0.0, "HANDOVER", None, 0.0, None, landing=True)

    core = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0, handover_release_m=2.0,
                                           handover_sink_m_s=0.3), policy=HoldsAgainstBias())
    core.on_heatmap(heatmap(0, 0.0, alt_m=19.5), 0.0)
    cmds = [core.tick(state(seq, 0.05 * (seq + 1), alt_m=alt_m, await_seq=0 if seq == 0 else -1))[0]
            for seq, alt_m in enumerate((19.5, 21.8, 21.2, 20.6))]
    assert core.mode is Mode.HOLD
    assert [c.vel_body_frd_m_s for c in cmds] == [(-0.25, 1.6, 0.3)] * 4
    assert not any(c.handover for c in cmds)


def test_a_confirming_hold_never_sinks_far_below_the_altitude_and_a_lone_low_state_confirms_nothing() -> None:
    core = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0, handover_release_m=2.0),
                          policy=HandsOver())
    core.on_heatmap(heatmap(0, 0.0, alt_m=30.0), 0.0)
    core.tick(state(0, 0.05, alt_m=30.0, await_seq=0))
    assert core.mode is Mode.POLICY_FAULT  # 10 m above: refused as ever
    for seq, alt_m in enumerate((30.0, 19.0, 30.0, 30.0), start=1):  # one low state (a glitch, a forgery)
        core.tick(state(seq, 0.05 + 0.05 * seq, alt_m=alt_m))
        assert core.mode is not Mode.HANDOVER
    core2 = ControllerCore(ControllerConfig(lockstep=True, handover_alt_m=20.0, handover_release_m=2.0,
                                            handover_confirm_states=3), policy=HandsOver())
    core2.on_heatmap(heatmap(0, 0.0, alt_m=21.0), 0.0)
    # The baro drifted: the states read 21-22 m where the policy measured 19.9 m. The vehicle sinks
    # until they read 18 m at most, then holds: no hand-over on states above the altitude.
    cmds = [core2.tick(state(seq, 0.05 * (seq + 1), alt_m=alt_m, await_seq=0 if seq == 0 else -1))[0]
            for seq, alt_m in enumerate((21.0, 21.5, 20.5, 17.9, 21.9, 21.0))]
    assert [c.vel_body_frd_m_s[2] for c in cmds] == [0.3, 0.3, 0.3, 0.0, 0.3, 0.3]
    assert not any(c.handover for c in cmds) and core2.mode is Mode.HOLD


def test_the_policy_dt_is_capped_across_a_perception_gap() -> None:
    core, policy = make_core(lockstep=True, timing="real", policy_dt_max_s=1.0)  # 0.5 s periods: the 1 s cap rules
    for seq, t_s in enumerate((0.0, 0.5, 14.5, 15.0)):  # a 14 s gap between the 2nd and 3rd heatmap
        core.on_heatmap(heatmap(seq, t_s), 0.0)
        core.tick(state(seq, t_s + 0.05, await_seq=seq))
    assert [o.t_s for o in policy.observations] == pytest.approx([0.0, 0.5, 1.5, 2.0])


def realtime_core(clock: Clock) -> ControllerCore:
    """A real-time core on the test's clock, with a 1 s tolerance for stamps ahead of it."""
    return ControllerCore(ControllerConfig(lockstep=False, future_tolerance_s=1.0), policy=RecordingPolicy(),
                          mono=clock)


@pytest.mark.parametrize("jump_s", [-30.0, 30.0])
def test_a_state_clock_jump_never_resets_the_policy_mid_flight(jump_s: float) -> None:
    clock = Clock()
    core = realtime_core(clock)
    for k in range(5):
        clock.t_s += 0.5
        core.on_heatmap(heatmap(k, 100.0 + 0.5 * k), 0.0)
        core.tick(state(k, 100.05 + 0.5 * k), wall_s=clock.t_s)
    policy = core.policy
    steps = len(policy.observations)
    clock.t_s += 0.5
    t_s = 102.55 + jump_s
    if jump_s < 0:
        # Backwards: a lone past stamp is refused; the clock follows once 3 states agree.
        for _ in range(JUMP_CONFIRM_STATES - 1):
            with pytest.raises(ControllerInputError, match="behind the newest accepted"):
                core.tick(state(5, t_s), wall_s=clock.t_s)
            t_s, clock.t_s = t_s + 0.05, clock.t_s + 0.05
        assert core.rejected["state from the past"] == JUMP_CONFIRM_STATES - 1 and core.rejected["clock jump"] == 0
    try:
        cmd, status = core.tick(state(5, t_s), wall_s=clock.t_s)
    except ControllerInputError as exc:  # a forward jump beyond the tolerance is refused
        assert jump_s > 0 and "leads the controller's clock" in str(exc)
        assert core.rejected["state from the future"] == 1
    else:
        # Confirmed backwards: the policy is kept, the old timeline's decision dropped: hold until a new heatmap.
        # (Stale too here: these states come 0.5 s apart and the confirmation took two of them.)
        assert jump_s < 0 and core.mode in (Mode.NO_HEATMAP, Mode.STATE_STALE)
        assert cmd.vel_body_frd_m_s == (0.0, 0.0, 0.0)
        assert core.rejected["clock jump"] == 1
        clock.t_s += 0.5
        core.on_heatmap(heatmap(6, 103.0 + jump_s), 0.0)
        cmd, status = core.tick(state(6, 103.05 + jump_s), wall_s=clock.t_s)
        assert cmd.frame_seq == 6 and status.watchdog == "ok"
        assert policy.observations[-1].t_s > policy.observations[-2].t_s  # its clock never ran back
    assert policy.resets == 0 and len(policy.observations) >= steps


def test_past_states_among_genuine_ones_never_move_the_clock() -> None:
    # dovesei faults, clock-skew: a forger's state stamped 0 s, sent between genuine ones, once
    # re-anchored the clock there, and every genuine state after it was refused for good.
    clock = Clock()
    core = realtime_core(clock)
    for k in range(40):
        clock.t_s += 0.05
        core.on_heatmap(heatmap(k, 5.0 + 0.05 * k), 0.0)
        core.tick(state(k, 5.05 + 0.05 * k), wall_s=clock.t_s)
        if k % 2:
            with pytest.raises(ControllerInputError, match="behind the newest accepted"):
                core.tick(state(1000 + k, 0.0), wall_s=clock.t_s)
    assert core.rejected["state from the past"] == 20 and core.rejected["state from the future"] == 0
    assert core.rejected["clock jump"] == 0 and core.mode is Mode.OK


def test_a_heatmap_from_the_future_is_refused_and_honest_ones_still_adopted() -> None:
    clock = Clock()
    core = realtime_core(clock)
    core.tick(state(0, 10.0), wall_s=clock.t_s)
    assert not core.on_heatmap(heatmap(0, 40.0), 0.0)  # stamped 30 s ahead
    assert core.rejected["heatmap from the future"] == 1
    clock.t_s += 0.5
    assert core.on_heatmap(heatmap(1, 10.4), 0.0)  # an honest one is not "older than the newest"
    cmd, status = core.tick(state(1, 10.5), wall_s=clock.t_s)
    assert cmd.frame_seq == 1 and status.watchdog == "ok"


def test_a_turn_since_the_heatmap_turns_the_command_back_to_what_the_policy_meant() -> None:
    """Issue 26: an autopilot that yaws (WP_YAW_BEHAVIOR, drift) turned the body frame under a
    body-frame decision. The command keeps the direction the policy meant at its heatmap."""
    core, _ = make_core(lockstep=True)
    core.on_heatmap(heatmap(0, 0.0), 0.0)
    cmd, _ = core.tick(VehicleState("uav1", 0, Stamp(0.05, "sim"), 80.0, (0.0, 0.0, 0.0), yaw_rad=0.0,
                                    await_frame_seq=0))
    assert cmd.vel_body_frd_m_s == pytest.approx(VEL_FRD)
    # Turned 90 degrees right since: the policy's forward (north) is now the vehicle's left.
    cmd, _ = core.tick(VehicleState("uav1", 1, Stamp(0.10, "sim"), 80.0, (0.0, 0.0, 0.0), yaw_rad=math.pi / 2))
    fwd, right, down = cmd.vel_body_frd_m_s
    assert (fwd, right, down) == pytest.approx((VEL_FRD[1], -VEL_FRD[0], VEL_FRD[2]))
