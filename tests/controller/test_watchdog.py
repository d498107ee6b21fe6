"""The controller's watchdog on the data clock: a toy vehicle flies the commands, heatmaps stop and
return, the vehicle state freezes. No Zenoh, no sleeps: time is the data's."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from dovesei.controller.core import ControllerConfig, ControllerCore, Mode
from dovesei.controller.policies.base import Decision, Observation
from dovesei.shared.messages import SafetyHeatmap, Stamp, VehicleState

DT_S = 0.05  # lockstep step = controller tick
DESCENT_M_S = 2.0
CORE_LOG = "dovesei.controller.core"


class DescendingPolicy:
    """Always descends straight down: any non-zero vertical command comes from the policy."""

    name = "descend"

    def step(self, obs: Observation) -> Decision:
        return Decision((0.0, 0.0, DESCENT_M_S), 0.0, "LANDING", None, 50.0, 0.5, landing=True)

    def reset(self) -> None:
        pass


class ToyFlight:
    """Lockstep loop in miniature: a vertical-only vehicle that follows the commanded speed."""

    def __init__(self, core: ControllerCore, alt_m: float = 100.0) -> None:
        self.core, self.alt_m, self.k, self.frame_seq = core, alt_m, 0, 0
        self.log: list[tuple[float, float, str, float]] = []  # (t_s, alt_m, watchdog mode, vel_down_m_s)

    @property
    def t_s(self) -> float:
        return self.k * DT_S

    def step(self, heatmap_ok: bool) -> None:
        """One tick: a heatmap captured one step ago becomes available when `heatmap_ok`."""
        await_seq = -1
        if heatmap_ok and self.k > 0:
            prob = np.full((8, 8), 0.9, np.float32)
            hm = SafetyHeatmap("uav1", self.frame_seq, Stamp(self.t_s - DT_S, "sim"), prob, self.alt_m, 1.27,
                               "simulated", True, "p", "f", 0.0)
            self.core.on_heatmap(hm, 0.0)
            await_seq, self.frame_seq = self.frame_seq, self.frame_seq + 1
        st = VehicleState("uav1", self.k, Stamp(self.t_s, "sim"), self.alt_m, (0.0, 0.0, 0.0),
                          await_frame_seq=await_seq)
        cmd, status = self.core.tick(st)
        self.status = status
        vel_down = cmd.vel_body_frd_m_s[2]
        self.log.append((self.t_s, self.alt_m, self.core.mode.value, vel_down))
        self.alt_m -= vel_down * DT_S
        self.k += 1

    def run_until(self, t_s: float, heatmap_ok: bool) -> None:
        while self.t_s < t_s - 1e-9:
            self.step(heatmap_ok)


def flight(alt_m: float = 100.0, **overrides: object) -> ToyFlight:
    config = ControllerConfig(lockstep=True, **overrides)
    return ToyFlight(ControllerCore(config, policy=DescendingPolicy()), alt_m)


def transitions(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == CORE_LOG and "watchdog" in r.getMessage()]


def test_segmenter_stops_mid_descent_hold_then_climb_then_resume(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger=CORE_LOG)
    f = flight()
    f.run_until(5.0, heatmap_ok=True)
    assert f.log[-1][2] == "ok" and f.log[-1][3] == DESCENT_M_S and f.alt_m < 95.0
    last_hm_t_s = f.t_s - 2 * DT_S  # the last heatmap adopted (captured one step before its tick)

    f.run_until(30.0, heatmap_ok=False)
    outage = [row for row in f.log if row[0] >= 5.0]
    # Descent stops at the first tick whose heatmap age exceeds 1.5 s, not one tick later.
    first_hold = next(row for row in outage if row[3] == 0.0)
    assert first_hold[0] == pytest.approx(last_hm_t_s + 1.5 + DT_S)
    assert all(row[3] == DESCENT_M_S for row in outage if row[0] - last_hm_t_s <= 1.5 + 1e-9)
    # Holding: zero velocity until the climb limit, altitude frozen.
    holding = [row for row in outage if 1.5 < row[0] - last_hm_t_s <= 10.0 + 1e-9]
    assert holding and all(row[2] == "hold" and row[3] == 0.0 for row in holding)
    assert max(r[1] for r in holding) - min(r[1] for r in holding) == 0.0
    # Climbing after 10 s: up (negative down), back towards the first altitude seen, no overshoot.
    climbing = [row for row in outage if row[0] - last_hm_t_s > 10.0 + 1e-9]
    assert climbing[0][2] == "climb" and climbing[0][3] < 0.0
    assert climbing[0][0] == pytest.approx(last_hm_t_s + 10.0 + DT_S)
    assert 99.0 < f.alt_m <= 100.0 and max(r[1] for r in f.log) <= 100.0
    assert abs(f.log[-1][3]) < 0.5, "near the search altitude the climb eases into a hold"

    # Heatmaps return: the policy's descent resumes on the very next tick that adopts one.
    f.step(heatmap_ok=True)
    assert f.log[-1][2] == "ok" and f.log[-1][3] == DESCENT_M_S

    # Each transition logged exactly once over ~500 ticks, with the limit that fired.
    msgs = transitions(caplog)
    modes = [m.split("watchdog ")[1].split(" at ")[0] for m in msgs]
    assert modes == ["start -> no_heatmap", "no_heatmap -> ok", "ok -> hold", "hold -> climb", "climb -> ok"]
    assert "older than 1.5 s" in msgs[2] and "older than 10 s" in msgs[3]


def test_a_configured_search_altitude_is_where_the_climb_goes() -> None:
    f = flight(45.0, search_alt_m=60.0, climb_speed_m_s=3.0)
    f.run_until(1.0, heatmap_ok=True)
    f.run_until(60.0, heatmap_ok=False)
    assert 59.0 < f.alt_m <= 60.0
    assert max(-row[3] for row in f.log) == pytest.approx(3.0), "climb speed capped at climb_speed_m_s"


def test_a_vehicle_above_the_search_altitude_is_never_told_to_descend_by_the_watchdog() -> None:
    f = flight(search_alt_m=50.0)
    f.run_until(1.0, heatmap_ok=True)
    f.run_until(20.0, heatmap_ok=False)
    assert all(row[3] <= 0.0 for row in f.log if row[2] in ("hold", "climb"))


def test_before_any_heatmap_the_vehicle_holds() -> None:
    f = flight()
    f.run_until(15.0, heatmap_ok=False)
    assert {row[2] for row in f.log} == {"no_heatmap"} and all(row[3] == 0.0 for row in f.log)


def test_stale_state_zeroes_the_command_then_recovers(caplog: pytest.LogCaptureFixture) -> None:
    """Real time: the loop's wall clock moves on while the vehicle's stamp stays put."""
    caplog.set_level(logging.INFO, logger=CORE_LOG)
    core = ControllerCore(ControllerConfig(lockstep=False, state_stale_after_s=0.5), policy=DescendingPolicy())
    prob = np.full((8, 8), 0.9, np.float32)
    core.on_heatmap(SafetyHeatmap("uav1", 0, Stamp(10.0, "sim"), prob, 80.0, 1.27, "simulated", True, "p", "f",
                                  0.0), 0.0)
    frozen = VehicleState("uav1", 7, Stamp(10.2, "sim"), 80.0, (0.0, 0.0, 0.0))
    velocities = []
    for tick in range(21):  # 1 s of wall time at 20 Hz, the same state every tick
        cmd, status = core.tick(frozen, wall_s=100.0 + 0.05 * tick)
        velocities.append((0.05 * tick, cmd.vel_body_frd_m_s[2], status.watchdog))
    assert all(v == DESCENT_M_S and w == "ok" for t, v, w in velocities if t <= 0.5 + 1e-9)
    assert all(v == 0.0 and w == "state_stale" for t, v, w in velocities if t > 0.5 + 1e-9)
    # A newer state brings the policy's command back at once.
    cmd, status = core.tick(VehicleState("uav1", 8, Stamp(10.25, "sim"), 80.0, (0.0, 0.0, 0.0)), wall_s=101.1)
    assert cmd.vel_body_frd_m_s[2] == DESCENT_M_S and status.watchdog == "ok"
    msgs = transitions(caplog)
    assert len(msgs) == 3 and "ok -> state_stale" in msgs[1] and "state_stale -> ok" in msgs[2]
    assert core.mode is Mode.OK


def test_lockstep_never_declares_the_state_stale() -> None:
    """Lockstep has no wall clock in its decisions: a slow host must not change the trajectory."""
    f = flight()
    f.run_until(3.0, heatmap_ok=True)
    assert "state_stale" not in {row[2] for row in f.log}


class WordPolicy(DescendingPolicy):
    """Descends, its landing word lasting `lasting_s` past each heatmap's capture (the close look's
    freshness, in miniature)."""

    def __init__(self, lasting_s: float) -> None:
        self.lasting_s = lasting_s

    def step(self, obs: Observation) -> Decision:
        return Decision((0.0, 0.0, DESCENT_M_S), 0.0, "LANDING", None, 50.0, 0.5, landing=True,
                        landing_until_s=obs.t_s + self.lasting_s)


def test_a_landing_word_that_runs_out_stops_the_descent_and_the_handover_until_renewed() -> None:
    """The policy's landing word has an end (`Decision.landing_until_s`): past it, between two of
    the policy's decisions, the controller stops the descent and does not hand over, whatever the
    altitude; a decision that renews it lets both go on. Heatmaps stop at 21 m (the word lasts 0.2 s
    past the last one), long before the heatmap watchdog's own hold."""
    core = ControllerCore(ControllerConfig(lockstep=True), policy=WordPolicy(0.2))
    toy = ToyFlight(core, alt_m=21.6)
    while toy.alt_m > 21.0:
        toy.step(heatmap_ok=True)
    stop_t = toy.t_s
    assert core.config.heatmap_hold_after_s > 0.6
    toy.run_until(stop_t + 0.6, heatmap_ok=False)
    late = [row for row in toy.log if row[0] > stop_t + 0.25]
    assert late and all(mode == "hold" and down <= 0.0 for _, _, mode, down in late), late
    assert min(alt for _, alt, _, _ in toy.log) > core.config.handover_alt_m
    assert "landing word ran out" in toy.status.reason
    toy.run_until(stop_t + 3.0, heatmap_ok=True)  # renewed: descends and hands over at 20 m
    assert toy.log[-1][2] == "handover"


def test_a_landing_word_that_is_not_a_finite_time_is_a_policy_fault() -> None:
    class Bad(WordPolicy):
        def step(self, obs: Observation) -> Decision:
            return Decision((0.0, 0.0, DESCENT_M_S), 0.0, "LANDING", None, 50.0, 0.5, landing=True,
                            landing_until_s=float("nan"))

    core = ControllerCore(ControllerConfig(lockstep=True), policy=Bad(0.0))
    toy = ToyFlight(core, alt_m=30.0)
    toy.run_until(0.5, heatmap_ok=True)
    assert core.mode is Mode.POLICY_FAULT and core.policy_errors > 0
    assert all(down <= 0.0 for _, _, _, down in toy.log)
