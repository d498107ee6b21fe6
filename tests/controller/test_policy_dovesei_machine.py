"""The `dovesei` state machine cycle by cycle: every transition, timer and output of REFERENCE.md.

The machine is driven directly with candidate errors in (halved) metres, so each test states the
exact inputs of each cycle. Velocities are (forward, right, up) as the machine returns them; the
policy's FRD conversion is tested in test_policy_dovesei.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.controller.policies.dovesei.config import DoveseiConfig, real_timing, reference_timing
from dovesei.shared import timing as shared_timing
from dovesei.controller.policies.dovesei.policy import DoveseiState as S
from dovesei.controller.policies.dovesei.policy import MachineOutput, StateMachine, conservative_gain

PRESETS = {"real": real_timing, "reference": reference_timing}


class Driver:
    """Feeds one cycle at a time; the clock advances by the preset's decision period unless a
    cycle gives its absolute time. `dt_s` (used by est) is always the nominal period."""

    def __init__(self, config: DoveseiConfig) -> None:
        self.cfg = config
        self.machine = StateMachine(config)
        self.t_s = 0.0

    def cycle(
        self,
        alt_m: float,
        err_m: tuple[float, float] = (0.0, 0.0),
        second_m: tuple[float, float] | None = None,
        *,
        depth_ok: bool = True,
        at_s: float | None = None,
    ) -> MachineOutput:
        rows = [err_m] + ([second_m] if second_m is not None else [])
        self.t_s = self.t_s + self.cfg.decision_period_s if at_s is None else at_s
        return self.machine.update(
            elapsed_s=self.t_s, dt_s=self.cfg.decision_period_s, alt_agl_m=alt_m,
            err_sorted_m=np.asarray(rows, dtype=float), depth_ok=depth_ok,
        )

    def warm_up(self) -> None:
        for _ in range(self.cfg.warm_up_cycles):
            out = self.cycle(100.0)
            assert out.state is S.SENSOR_ERROR


@pytest.fixture(params=sorted(PRESETS))
def drv(request: pytest.FixtureRequest) -> Driver:
    return Driver(PRESETS[request.param]())


def test_warm_up_is_five_sensor_error_cycles_with_zero_velocity(drv: Driver) -> None:
    for i in range(5):
        out = drv.cycle(100.0, (1.0, 0.0))  # a perfectly good candidate is ignored
        assert out.state is S.SENSOR_ERROR
        assert (out.vel_forward_m_s, out.vel_right_m_s, out.vel_up_m_s) == (0.0, 0.0, 0.0)
        assert drv.machine.cycles == i + 1
    assert drv.cycle(100.0, (1.0, 0.0)).state is S.AIMING


def test_searching_aiming_landing_landed_with_outputs(drv: Driver) -> None:
    drv.warm_up()
    # Far candidate at 100 m: not xy_ok (10 >= 2*2/cg=4), safe and descend_while_aiming -> SEARCHING.
    out = drv.cycle(100.0, (10.0, -2.0))
    assert out.state is S.SEARCHING
    assert out.vel_forward_m_s == pytest.approx(0.5 * 10.0)
    assert out.vel_right_m_s == pytest.approx(0.5 * -2.0)
    assert out.vel_up_m_s == 0.0
    assert drv.machine.int_x == 0.0 and drv.machine.int_y == 0.0  # neutralised
    # Close candidate: AIMING, gain 0.25, descends at 0.03 x alt while alt + est >= 55.
    out = drv.cycle(100.0, (1.0, 0.0))
    assert out.state is S.AIMING
    assert out.vel_forward_m_s == pytest.approx(0.25 * (1.0 + 1.0))  # x + int, int = 1 now
    assert out.vel_up_m_s == pytest.approx(-0.03 * 100.0)
    assert drv.machine.s_m_s == pytest.approx(3.0)
    # Below the aiming floor (alt + est < 55) and err < 2: LANDING at max(0.06 alt, 0.5) down.
    est_m = 3.0 * drv.cfg.decision_period_s / drv.cfg.timer_scale
    alt_m = 55.0 - est_m - 0.1
    out = drv.cycle(alt_m, (1.0, 0.5))
    assert out.state is S.LANDING
    assert out.vel_up_m_s == pytest.approx(-0.06 * alt_m)
    assert (out.vel_forward_m_s, out.vel_right_m_s) == (0.0, 0.0)  # integrator reset
    # LANDED once alt - est <= 5 m (est with s = 0.06 * alt of the previous cycle).
    est_m = 0.06 * alt_m * drv.cfg.decision_period_s / drv.cfg.timer_scale
    out = drv.cycle(5.0 + est_m, (1.0, 0.0))
    assert out.state is S.LANDED
    assert out.vel_up_m_s == 0.0


def test_landing_descent_floor_and_landed_boundary() -> None:
    drv = Driver(real_timing())
    drv.warm_up()
    drv.cycle(100.0, (0.5, 0.0))  # AIMING
    out = drv.cycle(8.0, (0.5, 0.0))  # alt + est < 55: LANDING
    assert out.state is S.LANDING
    assert out.vel_up_m_s == pytest.approx(-0.5)  # 0.06 * 8 = 0.48 < 0.5
    # est = 0.5 m/s * 0.5 s = 0.25 m: 5.26 - 0.25 > 5 keeps LANDING, 5.25 - 0.25 <= 5 lands.
    assert drv.cycle(5.26, (0.5, 0.0)).state is S.LANDING
    assert drv.cycle(5.25, (0.5, 0.0)).state is S.LANDED


def _latest_within(start_s: float, duration_s: float) -> float:
    """The latest float time t with t - start <= duration (the timers' strict test in floats)."""
    t_s = start_s + duration_s
    while t_s - start_s > duration_s:
        t_s = math.nextafter(t_s, -math.inf)
    return t_s


def test_waiting_give_up_restarting_then_searching_after_restart_time(drv: Driver) -> None:
    cfg = drv.cfg
    drv.warm_up()
    assert drv.cycle(60.0, (1.0, 0.0), at_s=6.0).state is S.AIMING
    # At 52 m (safe, alt + est < 55) with a far target: not landing, not aiming -> WAITING.
    out = drv.cycle(52.0, (30.0, 0.0), (5.0, -3.0), at_s=7.0)
    assert out.state is S.WAITING
    assert drv.machine.giveup_start_s == 7.0
    # The give-up test is strict: exactly 5 s (scaled: 0.25 s) later it is still WAITING.
    giveup_end_s = _latest_within(7.0, cfg.giveup_after_data_s)
    assert drv.cycle(52.0, (30.0, 0.0), (5.0, -3.0), at_s=giveup_end_s).state is S.WAITING
    # After it: RESTARTING towards the SECOND candidate, chosen once.
    restart_start_s = giveup_end_s + 0.5
    out = drv.cycle(52.0, (30.0, 0.0), (5.0, -3.0), at_s=restart_start_s)
    assert out.state is S.RESTARTING
    assert drv.machine.restart_dir_m == (5.0, -3.0)
    out = drv.cycle(52.0, (7.0, 7.0), (-9.0, 9.0))  # new candidates do not change the direction
    assert out.state is S.RESTARTING
    assert drv.machine.restart_dir_m == (5.0, -3.0)
    # Strict again: exactly 60 s (scaled: 3 s) of restarting keeps RESTARTING, later -> SEARCHING.
    restart_end_s = _latest_within(restart_start_s, cfg.restart_duration_data_s)
    assert drv.cycle(52.0, (30.0, 0.0), at_s=restart_end_s).state is S.RESTARTING
    out = drv.cycle(52.0, (30.0, 0.0), at_s=restart_end_s + 0.5)
    assert out.state is S.SEARCHING
    assert drv.machine.giveup_start_s is None and drv.machine.restart_start_s is None
    assert out.vel_forward_m_s == pytest.approx(0.5 * 30.0)


def test_a_long_gap_between_heatmaps_inflates_est_and_lands() -> None:
    # est = s * dt with dt the time since the previous cycle: a stalled segmenter (60 s) while
    # AIMING at 60 m (s = 1.8 m/s) predicts a 108 m descent, and the reference declares LANDED.
    cfg = real_timing()
    machine = StateMachine(cfg)
    for i in range(cfg.warm_up_cycles):
        machine.update(elapsed_s=0.5 * i, dt_s=0.5, alt_agl_m=100.0, err_sorted_m=np.zeros((1, 2)), depth_ok=True)
    machine.update(elapsed_s=3.0, dt_s=0.5, alt_agl_m=60.0, err_sorted_m=np.zeros((1, 2)), depth_ok=True)
    out = machine.update(elapsed_s=63.0, dt_s=60.0, alt_agl_m=60.0, err_sorted_m=np.zeros((1, 2)), depth_ok=True)
    assert out.state is S.LANDED


def test_timer_presets_scale_the_wall_clock_timers() -> None:
    ref, real = reference_timing(), real_timing()
    assert (ref.giveup_after_data_s, ref.restart_duration_data_s, ref.max_landing_time_data_s) == pytest.approx(
        (0.325, 3.9, 19.5))
    assert (real.giveup_after_data_s, real.restart_duration_data_s, real.max_landing_time_data_s) == (5.0, 60.0, 300.0)
    assert real.decision_period_s == 0.5


def test_one_reference_timing_for_sim_and_policy() -> None:
    """Issue 10: the policy decides at the sim's frame rate, and each decision is one of the
    reference's heatmap cycles (1/1.3 wall s), so est per decision is s / 1.3, not s."""
    for name, preset in PRESETS.items():
        assert preset().decision_period_s == shared_timing.timing(name).frame_period_s
    ref = reference_timing()
    assert 1.0 / ref.decision_period_s == pytest.approx(20.0)
    per_decision_ref_s = ref.decision_period_s / ref.timer_scale
    assert per_decision_ref_s == pytest.approx(1.0 / 1.3)
    drv = Driver(ref)
    drv.warm_up()
    out = drv.cycle(100.0, (0.0, 0.0))
    assert out.report.est_m == pytest.approx(3.0 / 1.3)


def test_give_up_below_safe_altitude_climbs_then_restarts_above_it(drv: Driver) -> None:
    drv.warm_up()
    drv.cycle(60.0, (1.0, 0.0))  # AIMING
    assert drv.cycle(52.0, (30.0, 0.0)).state is S.WAITING
    out = drv.cycle(45.0, (30.0, 0.0), at_s=drv.t_s + drv.cfg.giveup_after_data_s * 1.01)
    assert out.state is S.CLIMBING
    assert out.vel_up_m_s == 6.0  # commanded; the reference simulator clipped it to 5
    assert drv.cycle(49.9, (30.0, 0.0)).state is S.CLIMBING
    out = drv.cycle(50.0, (30.0, 0.0), (2.0, 1.0))
    assert out.state is S.RESTARTING
    assert drv.machine.restart_dir_m == (2.0, 1.0)


def test_waiting_lands_before_give_up_and_clears_the_timer(drv: Driver) -> None:
    drv.warm_up()
    drv.cycle(60.0, (1.0, 0.0))
    assert drv.cycle(52.0, (30.0, 0.0)).state is S.WAITING
    out = drv.cycle(52.0, (1.0, 1.0))  # is_landing: err < 2, below the aiming floor
    assert out.state is S.LANDING
    assert drv.machine.giveup_start_s is None


def test_landing_never_returns_to_aiming() -> None:
    drv = Driver(real_timing())
    drv.warm_up()
    drv.cycle(60.0, (1.0, 0.0))
    assert drv.cycle(53.0, (1.0, 0.0)).state is S.LANDING
    # err 3 m: xy_ok (< 4 m) but not is_landing (>= 2 m); LANDING may not become AIMING.
    out = drv.cycle(51.0, (3.0, 0.0))
    assert out.state is S.WAITING


def test_searching_persists_below_safe_altitude() -> None:
    drv = Driver(real_timing())
    drv.warm_up()
    assert drv.cycle(100.0, (30.0, 0.0)).state is S.SEARCHING
    out = drv.cycle(40.0, (30.0, 10.0))
    assert out.state is S.SEARCHING  # not WAITING: no give-up timer from SEARCHING
    assert drv.machine.giveup_start_s is None
    assert out.vel_forward_m_s == pytest.approx(15.0)


def test_non_finite_error_is_sensor_error_and_clears_the_give_up_timer(drv: Driver) -> None:
    drv.warm_up()
    drv.cycle(60.0, (1.0, 0.0))
    assert drv.cycle(52.0, (30.0, 0.0)).state is S.WAITING
    out = drv.cycle(math.nan, (math.nan, math.nan))
    assert out.state is S.SENSOR_ERROR
    assert drv.machine.giveup_start_s is None
    assert drv.machine.cycles == 6  # the reference counts every SENSOR_ERROR cycle


def test_failure_path_saturates_searching_and_feeds_a_restart() -> None:
    drv = Driver(real_timing())
    drv.warm_up()
    proj_100 = math.tan(math.radians(36.5)) * 100.0
    fail = (1000.0 * proj_100, 1000.0 * proj_100)
    out = drv.cycle(100.0, fail, depth_ok=False)
    assert out.state is S.SEARCHING  # safe and descend_while_aiming
    assert out.vel_forward_m_s == pytest.approx(0.5 * 1000.0 * proj_100)  # ~37 km/s: saturated
    # From AIMING at 52 m a failure is a miss (depth fails) -> WAITING; a restart begun on a
    # failure cycle takes the failure vector as its direction (one entry: no second candidate).
    drv.cycle(60.0, (1.0, 0.0))
    proj_52 = math.tan(math.radians(36.5)) * 52.0
    fail_52 = (1000.0 * proj_52, 1000.0 * proj_52)
    assert drv.cycle(52.0, fail_52, depth_ok=False).state is S.WAITING
    out = drv.cycle(52.0, fail_52, depth_ok=False, at_s=drv.t_s + 6.0)
    assert out.state is S.RESTARTING
    assert drv.machine.restart_dir_m == fail_52


def test_failure_path_never_lands_even_with_zero_error() -> None:
    drv = Driver(real_timing())
    drv.warm_up()
    drv.cycle(60.0, (1.0, 0.0))
    assert drv.cycle(52.0, (0.0, 0.0), depth_ok=False).state is S.WAITING


def test_integrator_accumulates_without_dt_clips_and_moves_the_zero_states() -> None:
    drv = Driver(real_timing())
    drv.warm_up()
    expected_int = [(0.4, -0.3), (0.8, -0.6), (1.0, -0.9), (1.0, -1.0)]
    for int_x, int_y in expected_int:
        out = drv.cycle(100.0, (0.4, -0.3))
        assert out.state is S.AIMING
        assert (drv.machine.int_x, drv.machine.int_y) == pytest.approx((int_x, int_y))
        assert out.vel_forward_m_s == pytest.approx(0.25 * (0.4 + int_x))
        assert out.vel_right_m_s == pytest.approx(0.25 * (-0.3 + int_y))
    # WAITING commands x = y = 0 but still moves at gain * int.
    out = drv.cycle(52.0, (30.0, 0.0))
    assert out.state is S.WAITING
    assert (out.vel_forward_m_s, out.vel_right_m_s, out.vel_up_m_s) == pytest.approx((0.25, -0.25, 0.0))
    # So does CLIMBING, and RESTARTING adds its direction to the integrator (clipped again).
    out = drv.cycle(45.0, (30.0, 0.0), at_s=drv.t_s + 5.5)
    assert out.state is S.CLIMBING
    assert (out.vel_forward_m_s, out.vel_right_m_s) == pytest.approx((0.25, -0.25))
    out = drv.cycle(55.0, (30.0, 0.0), (-0.5, 0.2))
    assert out.state is S.RESTARTING
    assert (drv.machine.int_x, drv.machine.int_y) == pytest.approx((0.5, -0.8))
    assert (out.vel_forward_m_s, out.vel_right_m_s) == pytest.approx((0.25 * (-0.5 + 0.5), 0.25 * (0.2 - 0.8)))
    # SENSOR_ERROR (non-finite input) also keeps moving at gain * int.
    out = drv.cycle(math.nan, (math.nan, math.nan))
    assert out.state is S.SENSOR_ERROR
    assert (out.vel_forward_m_s, out.vel_right_m_s) == pytest.approx((0.25 * 0.5, 0.25 * -0.8))


def test_restarting_keeps_the_last_gain_set() -> None:
    drv = Driver(real_timing())
    drv.warm_up()
    # Straight from warm-up to WAITING (SENSOR_ERROR is not SEARCHING): gain still the initial 0.5.
    assert drv.cycle(52.0, (30.0, 0.0)).state is S.WAITING
    out = drv.cycle(52.0, (30.0, 0.0), (2.0, 0.0), at_s=drv.t_s + 5.5)
    assert out.state is S.RESTARTING
    assert out.vel_forward_m_s == pytest.approx(0.5 * (2.0 + 1.0))  # int clipped to 1
    # After AIMING it is 0.25.
    drv2 = Driver(real_timing())
    drv2.warm_up()
    drv2.cycle(100.0, (0.0, 0.0))
    drv2.cycle(52.0, (30.0, 0.0))
    out = drv2.cycle(52.0, (30.0, 0.0), (2.0, 0.0), at_s=drv2.t_s + 5.5)
    assert out.state is S.RESTARTING
    assert out.vel_forward_m_s == pytest.approx(0.25 * (2.0 + 1.0))


def test_conservative_gain_law_and_its_effect_on_xy_ok() -> None:
    real, ref = real_timing(), reference_timing()
    assert conservative_gain(0.0, real) == 1.0
    assert conservative_gain(100.0, real) == pytest.approx(1.0 - math.exp(1.0 - 3.0))
    assert conservative_gain(150.0, real) == pytest.approx(1.0 - math.exp(-1.0))
    assert conservative_gain(300.0, real) == 0.5  # 1 - e^0 = 0, floored at 0.5
    assert conservative_gain(6.5, ref) == pytest.approx(conservative_gain(100.0, real))  # 6.5 s sim = 100 s wall
    # xy_ok = err < 4 / cg: a 6 m error is too far at the start but accepted once cg = 0.5.
    drv = Driver(real_timing())
    drv.warm_up()
    assert drv.cycle(100.0, (6.0, 0.0)).state is S.SEARCHING
    assert drv.cycle(100.0, (6.0, 0.0), at_s=250.0).state is S.AIMING


def _fly(config: DoveseiConfig, start_alt_m: float, cycles: int) -> list[tuple[S, float]]:
    """AIMING over a target 0.5 m away; the vehicle follows the vertical command on the data clock."""
    drv = Driver(config)
    drv.warm_up()
    alt_m, trace = start_alt_m, []
    for _ in range(cycles):
        out = drv.cycle(alt_m, (0.5, 0.0))
        trace.append((out.state, alt_m))
        alt_m += out.vel_up_m_s * config.decision_period_s
    return trace


def test_oscillation_quirk_between_52_and_55_m_in_reference_timing() -> None:
    trace = _fly(reference_timing(), 56.0, 150)
    states = [s for s, _ in trace]
    # LANDING -> SEARCHING -> AIMING -> LANDING repeats: est (s * dt on the wall clock, 20x the
    # real per-cycle descent) pushes alt + est back over 55 m after each LANDING cycle.
    loops = [i for i in range(len(states) - 3)
             if states[i:i + 4] == [S.LANDING, S.SEARCHING, S.AIMING, S.LANDING]]
    assert len(loops) >= 5
    assert all(52.0 <= trace[i][1] < 55.0 for i in loops)
    # Without the wall-clock dt in est, the same flight descends without oscillating.
    calm = [s for s, _ in _fly(reference_timing().replace(est_dt_on_reference_clock=False), 56.0, 150)]
    assert S.SEARCHING not in calm[calm.index(S.LANDING):]
