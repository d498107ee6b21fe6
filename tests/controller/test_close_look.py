"""The close look in flight (issue 24): `clearance` looks at its spot at full resolution before it
commits, and keeps looking while it descends.

Episodes are flown in-process (`dovesei.episode.run_episode`: the sim cuts each crop from its world
with the people drawn at the crop's resolution, the simulated perception scores it) over a small
world: roofs all round one 40 m lawn. The flight without anyone shows where the policy lands; then a
person stands there, or walks through it; the policy never reads where they are.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.looker import SyncLooker
from dovesei.controller.policies.base import Decision, LookResult, Observation, SpotReport
from dovesei.controller.policies.registry import make_policy
from dovesei.controller.policies.clearance.closelook import CloseLookConfig, CloseLookPolicy, verdict
from dovesei.episode import EpisodeSpec, run_episode
from dovesei.shared.messages import ControllerStatus, CropFrame, CropHeatmap, CropRequest, Stamp, VehicleState
from dovesei.shared.errors import ConfigError
from dovesei.shared.mission import VEHICLE_SEPARATION_M
from dovesei.sim.camera import CameraModel
from dovesei.sim.objects import PERSON, ObjectLayer, Population
from dovesei.sim.starts import Start
from dovesei.sim.world import ClassInfo, World

GSD_M = 0.25
SIDE_M = 200.0
LAWN_M = 40.0
CENTRE = (SIDE_M / 2, SIDE_M / 2)
GRASS, ROOF, PERSON_ID, CAR_ID = 1, 2, 3, 4


def lawn_world(people: list[tuple]) -> World:
    """Flat roofs all round a 40 m lawn in the middle; `people` as ObjectLayer rows."""
    n = int(SIDE_M / GSD_M)
    labels = np.full((n, n), ROOF, np.uint8)
    lo, hi = int((SIDE_M - LAWN_M) / 2 / GSD_M), int((SIDE_M + LAWN_M) / 2 / GSD_M)
    labels[lo:hi, lo:hi] = GRASS
    image = np.zeros((n, n, 3), np.uint8)
    image[labels == ROOF] = (150, 150, 155)
    image[labels == GRASS] = (70, 130, 60)
    classes = {GRASS: ClassInfo("grass", True), ROOF: ClassInfo("roof_flat", False),
               PERSON_ID: ClassInfo("person", False), CAR_ID: ClassInfo("car", False)}
    return World(image, labels, GSD_M, classes, "lawn",
                 population=Population(ObjectLayer.build(people), (PERSON_ID, CAR_ID)))


def person(x_m: float, y_m: float, *, heading_rad: float = 0.0, speed_m_s: float = 0.0, path_m: float = 0.0,
           phase_m: float = 0.0) -> tuple:
    return (PERSON, x_m, y_m, heading_rad, speed_m_s, path_m, phase_m, 0.5, 0.5, (200, 40, 40), False)


# A 100 m world: the scene is the first views, not a top pass that would fly off it.
SMALL_WORLD = (("scene_after_top_pass", False),)


def fly(world: World, *, close_look: bool = True, time_limit_s: float = 400.0) -> tuple[list, object]:
    statuses: list[ControllerStatus] = []
    looks: list = []

    def record(msg) -> None:
        if isinstance(msg, ControllerStatus):
            statuses.append(msg)
        elif isinstance(msg, (CropFrame, CropHeatmap)):
            looks.append(msg)

    spec = EpisodeSpec(policy="clearance", start=Start(*CENTRE, 100.0), timing="real", perception="realistic",
                       vehicle_profile="ideal", time_limit_s=time_limit_s, close_look=close_look,
                       policy_config=SMALL_WORLD)
    rec = run_episode(world, spec, record=record)
    return statuses, looks, rec


@pytest.fixture(scope="module")
def clear_flight():
    """The flight over the empty lawn: it lands, every look clear; where it lands is the spot."""
    return fly(lawn_world([]))


def test_without_a_person_the_close_look_clears_the_spot_and_it_lands(clear_flight) -> None:
    statuses, looks, rec = clear_flight
    assert rec.result.outcome == "safe", rec.result.detail
    verdicts = [s.look_verdict for s in statuses if s.look_verdict]
    assert verdicts and all(v.startswith("clear") for v in verdicts)
    crops = [m for m in looks if isinstance(m, CropFrame)]
    assert len(crops) >= 3  # the first at the look altitude, then during the last descent
    first_look = next(s for s in statuses if s.look_verdict)
    assert first_look.alt_agl_m >= 38.0


def test_people_under_one_token_at_100_m_are_found_by_the_close_look_at_40_m() -> None:
    # People standing 5 m apart all over the lawn: wherever the spot is, one of them is within
    # 3.6 m of it, inside the look's margin; at 100 m each is ~1.2 px, far under a 16 px token.
    assert 0.5 / CameraModel().metres_per_px(100.0) < 2.0
    lo, hi = CENTRE[0] - LAWN_M / 2 + 2.5, CENTRE[0] + LAWN_M / 2 - 2.5
    grid = np.arange(lo, hi + 0.01, 5.0)
    people = [person(x + 0.3, y - 0.2) for x in grid for y in grid]
    statuses, looks, rec = fly(lawn_world(people), time_limit_s=300.0)
    found = [s for s in statuses if s.look_verdict.startswith("never set")]
    assert found, "no close look found anyone"
    assert found[0].alt_agl_m >= 38.0  # seen from the look altitude, before committing below it
    assert any("close look: never set" in s.policy_reason for s in statuses), "the spot was not rejected"
    cleared_below = False
    for s in statuses:  # below the look altitude only after a look cleared the spot it was over
        cleared_below = cleared_below or s.look_verdict.startswith("clear")
        assert s.alt_agl_m >= 38.0 or cleared_below
    # It never handed over within 3 m of anyone.
    layer = lawn_world(people).population.layer
    if rec.result.outcome == "safe":
        assert layer.nearest_m(rec.result.final_x_m, rec.result.final_y_m, rec.result.sim_time_s, PERSON) > 3.0


def test_a_person_walking_into_the_disk_during_the_last_descent_makes_it_wait_or_abort(clear_flight) -> None:
    statuses0, _, rec0 = clear_flight
    spot = (rec0.result.final_x_m, rec0.result.final_y_m)
    first_look_s = next(s.stamp.t_s for s in statuses0 if s.look_verdict)
    # A walker on a 30 m east-west path through the spot at 1.2 m/s: 12 m or more away while the
    # vehicle looks from 40 m, at the spot a few seconds into the last descent.
    at_spot_s = first_look_s + 6.0
    walker = person(spot[0] - 15.0, spot[1] + 0.3, heading_rad=math.pi / 2, speed_m_s=1.2, path_m=30.0,
                    phase_m=15.0 - 1.2 * at_spot_s)
    layer = lawn_world([walker]).population.layer
    assert layer.nearest_m(*spot, first_look_s, PERSON) > 6.0 and layer.nearest_m(*spot, at_spot_s, PERSON) < 0.5
    statuses, looks, rec = fly(lawn_world([walker]))
    stopped = [s for s in statuses if "waiting for the never set" in s.policy_reason
               or "close look: never set" in s.policy_reason]
    assert stopped, "the walker never stopped the descent"
    assert min(s.alt_agl_m for s in stopped) < 39.0  # during the last descent, not at the first look
    if rec.result.outcome == "safe":
        assert layer.nearest_m(rec.result.final_x_m, rec.result.final_y_m, rec.result.sim_time_s, PERSON) > 3.0


def test_no_answer_means_no_descent_below_the_look_altitude() -> None:
    """A controller whose looks all fail (no camera): the policy holds at the gate, never lower."""
    from dovesei.episode import build_cores

    world = lawn_world([])
    spec = EpisodeSpec(policy="clearance", start=Start(*CENTRE, 100.0), timing="real", perception="realistic",
                       vehicle_profile="ideal", time_limit_s=200.0, policy_config=SMALL_WORLD)
    sim, seg, ctrl = build_cores(world, spec)

    def refuse(req):
        from dovesei.shared.crop import CropRefused
        raise CropRefused("camera unplugged")

    ctrl.looker = SyncLooker(refuse)
    out = sim.reset()
    lowest = math.inf
    pending = {}
    failures = []
    while out.result is None:
        if out.frame is not None:
            pending[out.frame.seq] = seg.process(out.frame)
        if out.state.await_frame_seq >= 0:
            ctrl.on_heatmap(pending.pop(out.state.await_frame_seq), 0.0)
        cmd, status = ctrl.tick(out.state)
        failures += [status.look_verdict] if status.look_verdict.startswith("look failed") else []
        lowest = min(lowest, sim.true_pose().alt_agl_m)
        out = sim.step(cmd)
    assert failures and "camera unplugged" in failures[-1]
    assert lowest > 38.0 and out.result.outcome != "safe"


def test_the_verdict_measures_from_the_square_centre() -> None:
    cfg = CloseLookConfig()
    never = np.zeros((352, 352), np.float32)
    assert verdict(never, cfg.side_m, cfg).clear
    m_per_px = cfg.side_m / 352
    row = int(round(175.5 - 2.0 / m_per_px))  # 2 m forward of the spot
    never[row - 3:row + 3, 173:179] = 0.9
    v = verdict(never, cfg.side_m, cfg)
    # The blob detector's answer spreads about its scale around what it finds: the finding may sit
    # up to ~0.25 m nearer the spot than the object's edge, never further (the margin errs safe).
    assert not v.clear and 2.0 - 0.3 <= v.nearest_m <= 2.0 + 0.05 and v.p_max == pytest.approx(0.9)


def test_something_broad_counts_out_to_the_vehicle_separation_a_blob_only_within_the_person_margin() -> None:
    # A car (read at even odds or above) whose near corner is 4.5 m from the spot: past
    # the person margin (4 m), inside the vehicles' 5 m. A person-sized faint blob as far out is not
    # a finding (people need 3 m; the margin has 1 m for the landing's own error).
    cfg = CloseLookConfig()
    assert cfg.margin_m < 4.5 < VEHICLE_SEPARATION_M < cfg.broad_margin_m
    n = 352
    m_per_px = cfg.side_m / n
    yy, xx = (np.mgrid[0:n, 0:n] - 175.5) * m_per_px  # metres from the spot
    # The car's near corner on the diagonal; the square (4 m half side) shows the piece of it inside.
    car = np.where((xx >= 4.5 * math.cos(math.pi / 4)) & (yy >= 4.5 * math.sin(math.pi / 4)), 0.7, 0.02)
    v = verdict(car.astype(np.float32), cfg.side_m, cfg)
    assert not v.clear and 4.3 <= v.nearest_m <= 4.6 and "something broad" in v.text(cfg.margin_m)
    person = np.full((n, n), 0.04, np.float32)
    blob = np.hypot(xx - 4.5 * math.cos(math.pi / 4), yy - 4.5 * math.sin(math.pi / 4)) <= 0.25
    person[blob] = 0.15  # under never_p_min: found only as a blob
    v = verdict(person, cfg.side_m, cfg)
    assert v.clear and v.nearest_m is not None and v.nearest_m > cfg.margin_m
    # The same blob inside the margin is found.
    person = np.full((n, n), 0.04, np.float32)
    person[np.hypot(xx - 2.0, yy) <= 0.25] = 0.15
    assert not verdict(person, cfg.side_m, cfg).clear
    # A broad margin narrower than the person margin is refused, in one line naming it.
    with pytest.raises(ConfigError, match="broad_margin_m"):
        CloseLookConfig(broad_margin_m=cfg.margin_m - 1.0)


def test_a_faint_person_stands_out_as_a_blob_and_broad_swells_are_not_findings() -> None:
    """A person the segmenter half-confuses with the lawn (P(never) 0.15 over a lawn reading 0.04, a
    token-wide blob, far under never_p_min) is found by how they stand out of their surroundings. A
    broad swell of the map (1.5 log-odds over 2 m: calibration, context), ground reading 0.2 or 0.35
    everywhere, are clear; something broad at even odds or above (a car) is a finding."""
    cfg = CloseLookConfig()
    n = 352
    m_per_px = cfg.side_m / n
    rng = np.random.default_rng(3)
    base = rng.normal(-3.2, 0.1, (n, n))
    yy, xx = (np.mgrid[0:n, 0:n] - 175.5) * m_per_px  # metres from the spot (rows: behind +)

    def prob(odds: np.ndarray) -> np.ndarray:
        return (1.0 / (1.0 + np.exp(-odds))).astype(np.float32)

    assert verdict(prob(base), cfg.side_m, cfg).clear
    swell = base + 1.5 * np.exp(-((yy + 1.0) ** 2 + (xx - 1.0) ** 2) / (2 * 1.0 ** 2))
    assert verdict(prob(swell), cfg.side_m, cfg).clear and prob(swell).max() < 0.25
    assert verdict(np.full((n, n), 0.2, np.float32), cfg.side_m, cfg).clear
    assert verdict(np.full((n, n), 0.35, np.float32), cfg.side_m, cfg).clear
    # A person 2.5 m behind the spot: 0.5 m across, blurred by about a token (0.36 m at this scale).
    disc = (np.hypot(yy - 2.5, xx) <= 0.25).astype(np.float32)
    blurred = cv2.GaussianBlur(disc, (0, 0), 0.15 / m_per_px)
    rise = math.log(0.15 / 0.85) + 3.2
    person = base + rise * blurred / blurred.max()
    v = verdict(prob(person), cfg.side_m, cfg)
    assert not v.clear and v.nearest_m == pytest.approx(2.5 - 0.25, abs=0.3) and 0.12 < v.p_max < cfg.never_p_min
    # The same person in the square's corner, 4.8 m from the spot: outside the margin, no finding.
    corner = cv2.GaussianBlur((np.hypot(yy - 3.4, xx - 3.4) <= 0.25).astype(np.float32), (0, 0), 0.15 / m_per_px)
    assert verdict(prob(base + rise * corner / corner.max()), cfg.side_m, cfg).clear
    # A car: 2 x 4 m at P 0.6, its near edge 3 m to the side.
    car = base.copy()
    car[(np.abs(yy) <= 2.0) & (xx >= 3.0) & (xx <= 5.0)] = math.log(0.6 / 0.4)
    v = verdict(prob(car), cfg.side_m, cfg)
    assert not v.clear and v.nearest_m == pytest.approx(3.0, abs=0.3)


def test_the_broad_level_follows_the_flights_baseline_within_its_bounds() -> None:
    """Something broad must stand baseline_k_logit above the flight's baseline (never above
    never_p_max); a blob is found whatever the baseline."""
    cfg = CloseLookConfig()
    n = 352
    m = cfg.side_m / n
    yy, xx = (np.mgrid[0:n, 0:n] - (n - 1) / 2.0) * m

    def prob(lg: np.ndarray) -> np.ndarray:
        return (1.0 / (1.0 + np.exp(-lg))).astype(np.float32)

    def swell_of(peak_p: float) -> np.ndarray:  # a swell 1.5 m wide at the spot, too broad for a blob
        low = math.log(0.05 / 0.95)
        return prob(low + (math.log(peak_p / (1 - peak_p)) - low) * np.exp(-(yy ** 2 + xx ** 2) / (2 * 1.5 ** 2)))

    swell = swell_of(0.45)  # over never_p_min
    assert not verdict(swell, cfg.side_m, cfg).clear
    low = math.log(0.05 / 0.95)
    assert not verdict(swell, cfg.side_m, cfg, baseline_logit=low).clear  # a low baseline: 0.4 stands
    high = math.log(0.3 / 0.7)  # a flight whose looks read P(never) 0.3 everywhere
    v = verdict(swell, cfg.side_m, cfg, baseline_logit=high)
    assert v.clear and v.broad_p == pytest.approx(cfg.never_p_max)
    assert "broad from P 0.60 on this flight" in v.text(cfg.margin_m)  # the status says why it is clear
    assert "on this flight" not in verdict(swell, cfg.side_m, cfg, baseline_logit=low).text(cfg.margin_m)
    assert not verdict(swell_of(0.65), cfg.side_m, cfg, baseline_logit=5.0).clear  # over never_p_max: found
    person = prob(high + 1.0 * np.exp(-(yy ** 2 + (xx - 1.0) ** 2) / (2 * 0.2 ** 2)))  # a faint blob, 1 m aside
    v = verdict(person, cfg.side_m, cfg, baseline_logit=high)
    assert not v.clear and v.nearest_m == pytest.approx(1.0, abs=0.3)


def _flat_answer(seq: int, p: float, centre_frd_m: tuple[float, float] = (0.0, 0.0)) -> LookResult:
    never = np.full((352, 352), p, np.float32)
    heat = CropHeatmap("uav1", seq, seq, Stamp(float(seq), "sim"), never, never, centre_frd_m, 8.0, 41.0, "simulated",
                       True, "p", "n", 0.01)
    return LookResult(seq, heat)


def test_the_baseline_is_read_from_looks_at_other_ground_only() -> None:
    """The spot's own looks never set its bar (what is there would raise it); looks at ground
    farther than a square's side do, once baseline_looks of them were scored."""
    cfg = CloseLookConfig()

    class _Moving(_Descending):
        spot = (10.0, 5.0)

        def step(self, obs: Observation) -> Decision:
            n, e = self.spot
            s = SpotReport(n, e, 6.0, 1.0, 0.9, 0.0, est_north_m=n, est_east_m=e)
            return Decision((0.0, 0.0, 1.0), 0.0, "DESCEND", None, 0.0, None, spot=s, landing=True)

    inner = _Moving()
    gate = CloseLookPolicy(inner)
    t = 0.0

    def look_once(seq: int, p: float) -> None:  # ask (a step), then the answer half a second later
        nonlocal t
        t += 1.0
        assert gate.step(Observation(t_s=t, alt_agl_m=41.0, prob_safe=None)).look_request is not None
        gate.step(Observation(t_s=t + 0.5, alt_agl_m=41.0, prob_safe=None, look=_flat_answer(seq, p)))

    for seq in range(1, 6):  # five looks at the spot itself, P(never) 0.3 all over
        look_once(seq, 0.3)
    assert gate.looks == 5 and gate.baseline_logit(inner.spot) is None
    for k in range(cfg.baseline_looks):  # looks at other spots, each a square's side and more away
        inner.spot = (10.0 + 2.0 * cfg.side_m * (k + 1), 5.0)
        look_once(10 + k, 0.1)
    base = gate.baseline_logit((10.0, 5.0))
    assert base == pytest.approx(math.log(0.1 / 0.9), abs=0.02)
    # The last spot's own look is not in its own baseline: the first spot's five and the other two are.
    assert gate.baseline_logit(inner.spot) == pytest.approx(math.log(0.3 / 0.7), abs=0.02)


class _Descending:
    """An inner policy descending onto one spot at 41 m; it records the spots the gate rejects."""

    name = "stub"
    config = None

    def __init__(self) -> None:
        self.rejected: list[str] = []

    def reset(self) -> None:
        self.rejected = []

    def map_view(self) -> dict:
        return {}

    def step(self, obs: Observation) -> Decision:
        spot = SpotReport(10.0, 5.0, 6.0, 1.0, 0.9, 0.0, est_north_m=10.0, est_east_m=5.0)
        return Decision((0.0, 0.0, 1.0), 0.0, "DESCEND", None, 0.0, None, spot=spot, landing=True)

    def reject_target(self, t_s: float, alt_m: float, why: str) -> None:
        self.rejected.append(why)


def _answer(seq: int, found: bool) -> LookResult:
    never = np.full((352, 352), 0.03, np.float32)
    if found:
        never[100:120, 170:190] = 0.8  # something 1.7 m ahead of the spot
    heat = CropHeatmap("uav1", seq, seq, Stamp(float(seq), "sim"), never, never, (0.0, 0.0), 8.0, 41.0, "simulated",
                       True, "p", "n", 0.01)
    return LookResult(seq, heat)


@pytest.mark.parametrize("pattern, rejected_at", [
    ("FCC", None),  # one finding holds the descent; it is not a verdict on the spot
    ("FCF", 2),  # found again within three looks: rejected
    ("FF", 1),
    ("CFCCFC", None),  # never twice within three looks
    ("CCF", None),  # past the gate (two clear looks): the last descent waits
])
def test_a_spot_is_rejected_when_found_again_not_on_one_look(pattern: str, rejected_at: int | None) -> None:
    inner = _Descending()
    gate = CloseLookPolicy(inner)
    obs = Observation(t_s=0.0, alt_agl_m=41.0, prob_safe=None)
    d = gate.step(obs)
    assert d.look_request is not None and d.vel_body_frd_m_s[2] <= 0.0  # holds and asks before any look
    for i, ch in enumerate(pattern):
        d = gate.step(Observation(t_s=1.0 + i, alt_agl_m=41.0, prob_safe=None, look=_answer(i + 1, ch == "F")))
        if rejected_at is not None and i >= rejected_at:
            break
        assert not inner.rejected, (pattern, i)
        if ch == "F":
            assert d.vel_body_frd_m_s[2] <= 0.0 and "never set" in d.look_verdict  # a finding holds
    if rejected_at is None:
        assert not inner.rejected
    else:
        assert len(inner.rejected) == 1 and "found in 2 of the last" in inner.rejected[0]


def _past_the_gate() -> tuple[_Descending, CloseLookPolicy]:
    """A gate over the stub's spot, opened by two clear looks at 40 m (t = 1 and 2 s)."""
    inner = _Descending()
    gate = CloseLookPolicy(inner)
    gate.step(Observation(t_s=0.0, alt_agl_m=41.0, prob_safe=None))
    for i in (1, 2):
        gate.step(Observation(t_s=float(i), alt_agl_m=40.0, prob_safe=None, look=_answer(i, False)))
    return inner, gate


def test_a_wait_that_does_not_end_rejects_the_spot_even_between_findings() -> None:
    """After a finding in the last descent the gate waits for resume_looks clear looks in a row; a
    wait past wait_s rejects the spot though no new finding came (clear looks of a spot that kept
    moving never made a streak: a harsh crowded flight waited 600 s so)."""
    cfg, inner, gate = CloseLookConfig(), *_past_the_gate()
    gate.step(Observation(t_s=3.0, alt_agl_m=30.0, prob_safe=None, look=_answer(3, True)))  # past the gate: waits
    t = 3.0
    while t < 3.0 + cfg.wait_s - 0.5:
        t += 0.5
        d = gate.step(Observation(t_s=t, alt_agl_m=30.0, prob_safe=None))  # no answers: no streak
        assert not inner.rejected and d.vel_body_frd_m_s[2] <= 0.0
    gate.step(Observation(t_s=3.0 + cfg.wait_s + 0.5, alt_agl_m=30.0, prob_safe=None))
    assert len(inner.rejected) == 1 and f"within {cfg.wait_s:g} s of a finding" in inner.rejected[0]


def test_findings_that_keep_coming_back_reject_the_spot() -> None:
    """Past the gate a finding waits and resume_looks clear looks end the wait; a finding on the same
    ground again more than wait_s after the first one rejects the spot (a crowd walking past, or a
    false finding flickering: each wait restarting held a harsh crowded flight for 600 s)."""
    cfg, inner, gate = CloseLookConfig(), *_past_the_gate()
    seq, t = 3, 2.0
    first_finding_s = None
    while not inner.rejected and t < 3.0 * cfg.wait_s:
        for found in (True,) + (False,) * cfg.resume_looks:  # each wait ends, then it is found again
            t += 1.5
            gate.step(Observation(t_s=t, alt_agl_m=30.0, prob_safe=None, look=_answer(seq, found)))
            seq += 1
            first_finding_s = t if found and first_finding_s is None else first_finding_s
            if inner.rejected:
                break
    assert len(inner.rejected) == 1 and "after the first finding there" in inner.rejected[0]
    assert cfg.wait_s < t - first_finding_s <= cfg.wait_s + 1.5 * (cfg.resume_looks + 1)


def test_the_gate_withholds_the_inner_policys_handover_until_a_fresh_clear_look() -> None:
    """An altitude hold sags through the hand-over altitude while the gate waits on a finding (a
    shifted crowded flight handed over 1.5 m from a person this way): the inner policy is told the
    hand-over is withheld whenever the spot has no fresh clear look, and released by one."""
    inner = _Descending()
    inner.handover_withheld = ""
    gate = CloseLookPolicy(inner)
    gate.step(Observation(t_s=0.0, alt_agl_m=41.0, prob_safe=None))
    assert inner.handover_withheld == "close look: no clear look of the spot"
    gate.step(Observation(t_s=1.0, alt_agl_m=40.0, prob_safe=None, look=_answer(1, False)))
    gate.step(Observation(t_s=2.0, alt_agl_m=39.0, prob_safe=None, look=_answer(2, False)))
    gate.step(Observation(t_s=3.0, alt_agl_m=38.0, prob_safe=None, look=_answer(3, False)))
    assert inner.handover_withheld == ""  # two clear looks in a row, the last one fresh
    gate.step(Observation(t_s=4.0, alt_agl_m=20.5, prob_safe=None, look=_answer(4, True)))
    gate.step(Observation(t_s=4.5, alt_agl_m=20.1, prob_safe=None))
    assert "waiting" in inner.handover_withheld  # the last descent found something: no hand-over
    for i in range(5, 9):
        gate.step(Observation(t_s=float(i), alt_agl_m=20.0, prob_safe=None, look=_answer(i, False)))
    assert inner.handover_withheld == ""  # resume_looks clear looks, the last captured 1 s ago: released
    gate.step(Observation(t_s=8.0 + CloseLookConfig().fresh_max_s + 0.5, alt_agl_m=20.0, prob_safe=None))
    assert inner.handover_withheld == "close look: no fresh clear look"


class _Handing(_Descending):
    """The stub descending onto its spot that declares HANDOVER at 20 m when the gate lets it, and
    records what takes it back."""

    def __init__(self) -> None:
        super().__init__()
        self.handover_withheld = ""
        self.state = "DESCEND"
        self.withdrawn: list[str] = []

    def step(self, obs: Observation) -> Decision:
        if self.state == "DESCEND" and obs.alt_agl_m <= 20.0 and not self.handover_withheld:
            self.state = "HANDOVER"
        d = super().step(obs)
        return dataclasses.replace(d, state=self.state, vel_body_frd_m_s=(0.0, 0.0, 0.0))

    def withdraw_handover(self, t_s: float, alt_m: float, why: str) -> None:
        if self.state == "HANDOVER":
            self.state = "DESCEND"
            self.withdrawn.append(why)


def _handing_over() -> tuple[_Handing, CloseLookPolicy]:
    """The gate opened by two clear looks (answered at t = 1 and 2 s, asked a second before), the
    stub declaring HANDOVER at 20 m with the second one, captured a fresh 1 s before."""
    inner = _Handing()
    gate = CloseLookPolicy(inner)
    gate.step(Observation(t_s=0.0, alt_agl_m=41.0, prob_safe=None))
    gate.step(Observation(t_s=1.0, alt_agl_m=40.0, prob_safe=None, look=_answer(1, False)))
    assert gate.step(Observation(t_s=2.0, alt_agl_m=20.0, prob_safe=None, look=_answer(2, False))).state == "HANDOVER"
    return inner, gate


def test_a_declared_handover_keeps_looking_and_is_taken_back_when_someone_walks_in() -> None:
    """While the controller confirms a declared hand-over (seconds on a noisy baro) the looks go
    on; one that finds the never set inside the margin takes the hand-over back, and it is declared
    again only once resume_looks clear looks say the margin is clear (harsh Dubai start 8: a walker
    came from 6.8 m to 1.8 m of the touchdown in the 4 s a hand-over took to confirm, unlooked at)."""
    cfg, (inner, gate) = CloseLookConfig(), _handing_over()
    seq, t = 3, 2.0
    asked = 0
    for _ in range(3):  # the hand-over is being confirmed: clear looks keep it, new ones are asked
        t += cfg.look_period_s
        d = gate.step(Observation(t_s=t, alt_agl_m=20.0, prob_safe=None, look=_answer(seq, False)))
        seq += 1
        asked += d.look_request is not None
        assert d.state == "HANDOVER"
    assert asked >= 2
    t += cfg.look_period_s
    d = gate.step(Observation(t_s=t, alt_agl_m=20.0, prob_safe=None, look=_answer(seq, True)))
    seq += 1
    assert d.state == "DESCEND" and d.vel_body_frd_m_s[2] <= 0.0
    assert inner.withdrawn == ["close look: waiting for the never set to clear the margin"]
    for k in range(cfg.resume_looks):
        t += cfg.look_period_s
        d = gate.step(Observation(t_s=t, alt_agl_m=20.0, prob_safe=None, look=_answer(seq, False)))
        seq += 1
        assert d.state == ("HANDOVER" if k == cfg.resume_looks - 1 else "DESCEND"), k
    assert not inner.rejected


def test_a_declared_handover_without_a_fresh_look_is_taken_back() -> None:
    """Looks that stop being answered during the confirmation leave no fresh clear look: the
    hand-over is taken back rather than completed on a look older than fresh_max_s."""
    cfg, (inner, gate) = CloseLookConfig(), _handing_over()
    d = gate.step(Observation(t_s=2.0 + cfg.fresh_max_s + 0.1, alt_agl_m=20.0, prob_safe=None))
    assert d.state == "DESCEND" and inner.withdrawn == ["close look: no fresh clear look"]


def test_near_the_handover_looks_come_every_final_period_and_the_landing_word_ends_with_the_look() -> None:
    """Walkers: within final_gate_m of the hand-over the gate looks every final_look_period_s (not
    look_period_s), and each decision's landing word ends fresh_s after the newest clear look was
    asked (the controller hands over between the policy's steps, never on a look gone stale)."""
    cfg = CloseLookConfig()
    assert cfg.final_look_period_s < cfg.look_period_s
    inner = _Descending()
    inner.handover_withheld = ""
    gate = CloseLookPolicy(inner)
    gate.step(Observation(t_s=0.0, alt_agl_m=41.0, prob_safe=None))  # asks look 1
    d = gate.step(Observation(t_s=1.0, alt_agl_m=40.0, prob_safe=None, look=_answer(1, False)))  # asks look 2
    assert d.landing_until_s is None  # above the final band: the word lasts until the next decision
    gate.step(Observation(t_s=2.0, alt_agl_m=21.0, prob_safe=None, look=_answer(2, False)))  # asks look 3
    assert inner.handover_withheld == ""
    asks, t, seq = [], 2.0, 3
    while t < 6.0:  # steps every 0.25 s, each look answered at the next step
        t += 0.25
        look = _answer(seq, False) if gate._asked is not None else None
        seq += look is not None
        d = gate.step(Observation(t_s=t, alt_agl_m=21.0, prob_safe=None, look=look))
        if d.look_request is not None:
            asks.append(t)
        assert inner.handover_withheld == "", t  # always a clear look fresh enough
        assert d.landing and d.landing_until_s == gate._clear.t_s + gate.fresh_limit_s and d.landing_until_s > t
    assert gate.fresh_limit_s == cfg.fresh_s  # answers a 0.25 s step after the ask: fresh_s itself
    gaps = np.diff(asks)
    assert len(asks) >= 7 and gaps.max() <= cfg.final_look_period_s + 1e-9, asks


def test_a_look_answered_on_another_clock_is_refused() -> None:
    """The hand-over's freshness reads the crop's capture stamp: an answer stamped on a clock other
    than the request's is refused (one line naming both), never compared across clocks."""
    never = np.full((352, 352), 0.03, np.float32)
    heat = CropHeatmap("uav1", 1, 1, Stamp(5.0, "wall"), never, never, (0.0, 0.0), 8.0, 20.0, "simulated", True,
                       "p", "n", 0.01)
    looker = SyncLooker(lambda req: (None, heat))
    looker.submit(CropRequest("uav1", 1, Stamp(5.0, "sim"), (0.0, 0.0), 8.0, 352))
    result = looker.poll()
    assert not result.ok and result.refusal == "answer captured on the 'wall' clock, asked on 'sim'"


def test_the_freshness_a_handover_needs_follows_the_looks_own_lag_within_its_bounds() -> None:
    """A look cannot be younger than its answer's lag plus the step until the next decision: the
    limit is that (x 1.25 on the step), never under fresh_s (walkers) nor over fresh_max_s (beyond
    it a slow segmenter means holding, as before)."""
    cfg = CloseLookConfig()

    def limit_after(step_s: float, lag_steps: int, delay_s: float = 0.0) -> float:
        inner = _Descending()
        inner.handover_withheld = ""
        gate = CloseLookPolicy(inner)
        t = 0.0
        gate.step(Observation(t_s=t, alt_agl_m=41.0, prob_safe=None, delay_s=delay_s))  # asks look 1 at t = 0
        for _ in range(lag_steps):
            t += step_s
            gate.step(Observation(t_s=t, alt_agl_m=40.0, prob_safe=None, delay_s=delay_s))
        gate.step(Observation(t_s=t + step_s, alt_agl_m=40.0, prob_safe=None, look=_answer(1, False),
                              delay_s=delay_s))
        return gate.fresh_limit_s

    assert limit_after(0.25, 0) == cfg.fresh_s  # answered a step later: 0.25 + 0.31 s, under fresh_s
    assert limit_after(1.0, 0) == pytest.approx(1.0 + 1.25)  # a segmenter at 1 Hz
    assert limit_after(1.0, 4) == cfg.fresh_max_s  # answered after 5 s: capped
    assert limit_after(0.5, 0) == pytest.approx(cfg.fresh_s + 0.125)  # the bench's 2 Hz: 0.5 + 0.625 s
    # ... flown 0.4 s after each heatmap's capture (the bench's real timing): that much longer.
    assert limit_after(0.5, 0, 0.4) == pytest.approx(0.5 + 0.4 + 0.625)
    assert limit_after(0.5, 0, 100.0) == cfg.fresh_max_s  # a long one is bounded
    assert limit_after(0.5, 0, math.inf) == pytest.approx(cfg.fresh_s + 0.125)  # no number: never a longer word


def test_the_landing_word_outlasts_the_step_until_its_renewal_is_flown() -> None:
    """In the final band each decision is flown `delay` after its heatmap's stamp, so its landing
    word must last until the next decision is flown, or the descent and the hand-over's confirmation
    stop every step. The bench's timing: steps every 0.5 s, looks answered at the next step,
    decisions flown 0.4 s after the stamp (a word of 1.125 s ran out 0.275 s of every 0.5 s)."""
    for alts in ((21.0,), (21.0, 24.5)):  # steady, and a noisy baro crossing the band's edge (23 m)
        inner = _Descending()
        inner.handover_withheld = ""
        gate = CloseLookPolicy(inner)
        step, delay = 0.5, 0.4
        gate.step(Observation(t_s=0.0, alt_agl_m=41.0, prob_safe=None, delay_s=delay))
        gate.step(Observation(t_s=0.5, alt_agl_m=40.0, prob_safe=None, look=_answer(1, False), delay_s=delay))
        words, t, seq, k = [], 0.5, 2, 0
        while t < 8.0:
            t, k = t + step, k + 1
            look = _answer(seq, False) if gate._asked is not None else None
            seq += look is not None
            d = gate.step(Observation(t_s=t, alt_agl_m=alts[k % len(alts)], prob_safe=None, look=look,
                                      delay_s=delay))
            words.append((t, d.landing_until_s))
        assert sum(until is not None for _, until in words) >= 7, alts
        for (t_now, until), (t_next, _) in zip(words, words[1:]):
            # Still valid when the next decision is flown.
            assert until is None or until >= t_next + delay, (alts, t_now, until, t_next)


def _answer_side(seq: int, side_m: float, found_at_m: float | None) -> LookResult:
    """A look over a square of `side_m` with a person-sized finding `found_at_m` ahead of the spot."""
    n = 352
    never = np.full((n, n), 0.03, np.float32)
    if found_at_m is not None:
        row = int(round((n - 1) / 2 - found_at_m * n / side_m))
        never[row - 10:row + 10, 166:186] = 0.8
    heat = CropHeatmap("uav1", seq, seq, Stamp(float(seq), "sim"), never, never, (0.0, 0.0), side_m, 21.0,
                       "simulated", True, "p", "n", 0.01)
    return LookResult(seq, heat)


def test_the_looks_that_hand_over_reach_as_far_as_a_walker_goes_before_the_hand_over() -> None:
    """Within final_gate_m of the hand-over a look's square reaches margin + walk_m_s x the
    freshness limit: someone 5 m from the spot, outside the 4 m margin but able to walk inside it
    by the hand-over (coast start 22: a walker came from 4.7 m to 3.26 m), holds the hand-over;
    above the band the square stays 2 x margin."""
    cfg = CloseLookConfig()
    inner = _Descending()
    inner.handover_withheld = ""
    gate = CloseLookPolicy(inner)
    d = gate.step(Observation(t_s=0.0, alt_agl_m=41.0, prob_safe=None))
    assert d.look_request.side_m == pytest.approx(2 * cfg.margin_m)  # 8 m above the band
    gate.step(Observation(t_s=1.0, alt_agl_m=40.0, prob_safe=None, look=_answer_side(1, 8.0, None)))
    d = gate.step(Observation(t_s=2.0, alt_agl_m=21.0, prob_safe=None, look=_answer_side(2, 8.0, None)))
    reach = min(cfg.final_margin_max_m, cfg.margin_m + cfg.walk_m_s * gate.fresh_limit_s)
    assert gate.final_margin_m == pytest.approx(reach) and reach > cfg.margin_m + 1.0
    assert d.look_request is not None and d.look_request.side_m == pytest.approx(2 * reach)
    assert inner.handover_withheld == ""
    # Someone 5 m ahead: inside the final margin, a finding; the hand-over waits.
    d = gate.step(Observation(t_s=2.5, alt_agl_m=21.0, prob_safe=None, look=_answer_side(3, 2 * reach, 5.0)))
    assert "never set 4." in gate._verdict and f"margin {reach:.1f} m" in gate._verdict, gate._verdict
    assert inner.handover_withheld == "close look: waiting for the never set to clear the margin"
    assert not d.landing and d.vel_body_frd_m_s[2] <= 0.0
    # An 8 m look (as before the band) would not have seen them at all: outside its square.
    assert cfg.side_m / 2 < 4.7
