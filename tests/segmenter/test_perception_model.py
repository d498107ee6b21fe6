"""The simulated perception v2 (sim_backend, appearance, responses): errors of CLIPSeg's kinds,
never the judge's safe flag."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dovesei.segmenter.appearance import INDEX as APPEARANCE_INDEX
from dovesei.segmenter.appearance import appearance_mix
from dovesei.segmenter.fusion import FusionConfig
from dovesei.segmenter.prompts import REFERENCE_PROMPTS, PromptSet
from dovesei.segmenter.responses import item_affinity, response_matrix
from dovesei.segmenter.sim_backend import PROFILES, SimPerception, View, profile_params
from dovesei.shared.errors import ConfigError

HFOV = math.radians(73.0)
CLASSES = {1: ("roof_flat", False), 2: ("road", False), 3: ("grass", True), 4: ("person", False),
           5: ("water", False), 6: ("sidewalk", False), 7: ("tree", False), 8: ("bare_soil", True)}
SOFTMAX = FusionConfig(mode="dovesei")


def _scene() -> np.ndarray:
    lab = np.full((352, 352), 3, np.uint8)
    lab[:, 150:180] = 2
    lab[20:140, 200:330] = 1
    lab[200:300, 20:120] = 5
    lab[200:260, 200:260] = 7
    lab[300:350, 200:340] = 8
    lab[150:170, :] = 6
    return lab


def _p(perception, labels, view, seq=0, prompts=REFERENCE_PROMPTS, fusion=SOFTMAX, classes=CLASSES):
    return perception.safe_probability(labels, classes, view, seq, prompts, fusion)


@pytest.mark.parametrize("profile", ["clean", "realistic", "harsh"])
def test_flipping_every_safe_flag_leaves_the_heatmap_bit_identical(profile: str) -> None:
    perception = SimPerception(profile_params(profile), seed=3)
    view = View((400.0, 300.0), 80.0, HFOV, 0.4)
    flipped = {cid: (name, not safe) for cid, (name, safe) in CLASSES.items()}
    a = _p(perception, _scene(), view, 7)
    b = _p(SimPerception(profile_params(profile), seed=3), _scene(), view, 7, classes=flipped)
    assert a.tobytes() == b.tobytes()


def test_the_frame_backend_ignores_the_wire_safe_flag() -> None:
    from dovesei.segmenter.core import SegmenterConfig, SegmenterCore, make_backend
    from dovesei.shared.messages import CameraFrame, ClassEntry, GroundTruth, Stamp

    def frame(flip: bool) -> CameraFrame:
        entries = tuple(ClassEntry(cid, name, safe != flip) for cid, (name, safe) in CLASSES.items())
        truth = GroundTruth(_scene(), entries, (120.0, 80.0))
        return CameraFrame("uav1", 4, Stamp(1.0, "sim"), np.zeros((352, 352, 3), np.uint8), HFOV, 90.0, truth=truth)

    config = SegmenterConfig(backend="sim", sim_profile="realistic", sim_seed=1)
    core = SegmenterCore(make_backend(config), config)
    assert core.process(frame(False)).prob_safe.tobytes() == core.process(frame(True)).prob_safe.tobytes()


def _errors(perception, clean, labels, view, seq):
    return (_p(perception, labels, view, seq) - _p(clean, labels, view, seq)).ravel()


def test_the_same_ground_is_misread_alike_across_frames_and_other_ground_is_not() -> None:
    # One material everywhere: every difference from the error-free reading is an error.
    labels = np.full((352, 352), 1, np.uint8)  # a grey flat roof as far as the camera sees
    realistic = SimPerception(profile_params("realistic"), seed=5)
    clean = SimPerception(profile_params("realistic", noise=0.0), seed=5)
    here = View((500.0, 500.0), 100.0, HFOV)
    nearby = View((500.4, 499.7), 100.0, HFOV)  # the next frame: 0.5 m of drift
    far = View((1500.0, -800.0), 100.0, HFOV)
    e0 = _errors(realistic, clean, labels, here, 10)
    e1 = _errors(realistic, clean, labels, nearby, 11)
    e_far = _errors(realistic, clean, labels, far, 12)
    assert e0.std() > 0.02  # there are errors to correlate
    assert np.corrcoef(e0, e1)[0, 1] > 0.7
    assert abs(np.corrcoef(e0, e_far)[0, 1]) < 0.4


def test_misreadings_follow_the_ground_when_the_camera_turns() -> None:
    # A heading change moves the ground in the image; the world field moves with it.
    labels = np.full((352, 352), 1, np.uint8)
    p = dataclasses.replace(profile_params("realistic"), flicker_logit=0.0, flicker_offset=0.0, context_global=0.0,
                            context_local=0.0)
    perception = SimPerception(p, seed=2)
    north = _p(perception, labels, View((300.0, 300.0), 100.0, HFOV, 0.0))
    east = _p(perception, labels, View((300.0, 300.0), 100.0, HFOV, math.pi / 2))
    # Heading east, image up is east and north is on the left: the north-up picture turned a
    # quarter counter-clockwise.
    inner = np.s_[40:-40, 40:-40]
    assert np.corrcoef(np.rot90(north, 1)[inner].ravel(), east[inner].ravel())[0, 1] > 0.8


def test_a_one_metre_object_is_invisible_at_100_m_and_visible_at_20_m() -> None:
    perception = SimPerception(profile_params("realistic", noise=0.0))
    lawn = np.full((352, 352), 3, np.uint8)
    drops = {}
    for alt_m in (100.0, 20.0):
        side_px = 1.0 / (2 * math.tan(HFOV / 2) * alt_m / 352)  # one metre in pixels
        half = max(1, int(round(side_px / 2)))
        with_person = lawn.copy()
        with_person[176 - half:176 + half, 176 - half:176 + half] = 4
        view = View((0.0, 0.0), alt_m, HFOV)
        drops[alt_m] = float((_p(perception, lawn, view) - _p(perception, with_person, view))[176, 176])
    assert drops[100.0] < 0.03
    assert drops[20.0] > 0.15


def test_changing_the_prompts_changes_the_map_as_the_words_say() -> None:
    perception = SimPerception(profile_params("realistic", noise=0.0))
    labels = _scene()
    view = View((0.0, 0.0), 100.0, HFOV)
    road = np.s_[60:120, 158:172]
    base = _p(perception, labels, view)
    # The user decides roads are fine: road words move from the negatives to the positives.
    negatives = tuple(n for n in REFERENCE_PROMPTS.negative if not n.startswith("road"))
    roads_ok = PromptSet(REFERENCE_PROMPTS.positive + ("road, street, avenue, highway, drive, lane",), negatives,
                         REFERENCE_PROMPTS.template)
    assert _p(perception, labels, view, prompts=roads_ok)[road].mean() > base[road].mean() + 0.2
    # Dropping the asphalt prompt lowers the road further; grass barely moves.
    no_asphalt = PromptSet(REFERENCE_PROMPTS.positive[:2], REFERENCE_PROMPTS.negative, REFERENCE_PROMPTS.template)
    changed = _p(perception, labels, view, prompts=no_asphalt)
    assert changed[road].mean() < base[road].mean() - 0.02
    assert not np.array_equal(changed, base)


def test_unknown_words_get_a_plausible_default() -> None:
    assert np.allclose(item_affinity("lawns"), item_affinity("lawn"))
    grassland = np.array(item_affinity("grassland"))
    assert int(np.argmax(grassland)) == int(np.argmax(item_affinity("grass")))
    nonsense = np.array(item_affinity("xyzzy quux"))
    assert nonsense.max() - nonsense[:-1].min() < 0.15  # flat: it resembles nothing
    prompts = PromptSet(("xyzzy quux",), ("florbnax",), "{}")
    prob = _p(SimPerception(profile_params("realistic")), _scene(), View((0.0, 0.0), 100.0, HFOV), prompts=prompts)
    assert np.isfinite(prob).all() and 0.0 <= prob.min() <= prob.max() <= 1.0
    assert response_matrix(prompts).shape == (15, 2)


@pytest.mark.parametrize("profile", ["clean", "realistic", "harsh"])
@pytest.mark.parametrize("mode", ["dovesei", "grouped"])
def test_off_world_reads_below_every_real_class(profile: str, mode: str) -> None:
    labels = _scene()
    labels[:, 260:] = 255
    prob = _p(SimPerception(profile_params(profile), seed=1), labels, View((0.0, 0.0), 100.0, HFOV), 3,
              fusion=FusionConfig(mode=mode))
    deep_off = prob[:, 300:]
    real = prob[:, :240]
    assert deep_off.max() < real.min() + 1e-6


def test_coarse_fusion_grid_matches_the_exact_path() -> None:
    exact = SimPerception(dataclasses.replace(profile_params("realistic"), fusion_grid_px=352), seed=4)
    fast = SimPerception(profile_params("realistic"), seed=4)
    view = View((10.0, 20.0), 60.0, HFOV, 1.0)
    for mode in ("dovesei", "grouped"):
        diff = np.abs(_p(exact, _scene(), view, 2, fusion=FusionConfig(mode=mode))
                      - _p(fast, _scene(), view, 2, fusion=FusionConfig(mode=mode)))
        assert diff.max() < 0.03


def test_output_is_a_pure_function_of_its_inputs() -> None:
    view = View((33.0, 44.0), 70.0, HFOV, 0.2)
    a = SimPerception(profile_params("harsh"), seed=9)
    b = SimPerception(profile_params("harsh"), seed=9)
    later = _p(a, _scene(), view, 5)
    _p(a, _scene(), view, 4)
    assert _p(b, _scene(), view, 5).tobytes() == later.tobytes()
    assert not np.array_equal(_p(b, _scene(), view, 6), later)  # flicker: frames differ a little


def test_frames_of_any_size_and_aspect() -> None:
    labels = np.full((240, 320), 3, np.uint8)
    prob = _p(SimPerception(profile_params("realistic")), labels, View((0.0, 0.0), 50.0, HFOV))
    assert prob.shape == (240, 320) and prob.dtype == np.float32


def test_class_names_map_to_appearances() -> None:
    assert appearance_mix("roof_pitched") == {"pitched_roof": 1.0}
    assert appearance_mix("parking_lot") == {"parking": 1.0}
    assert appearance_mix("land (unpaved area)") == {"bare_ground": 1.0}
    assert appearance_mix("vegetation (lawns and trees, not separated)") == {"lawn": 0.5, "tree": 0.5}
    assert appearance_mix("unlabeled") == {"clutter": 1.0}
    assert appearance_mix("sports_field") == {"sports_field": 1.0}


def test_profiles_and_bad_params() -> None:
    assert set(PROFILES) == {"clean", "realistic", "harsh"}
    assert profile_params("realistic", 2.0).noise == 2.0
    with pytest.raises(ConfigError, match="choose one of"):
        profile_params("noisy")
    with pytest.raises(ConfigError, match="noise"):
        profile_params("realistic", 9.0)
    with pytest.raises(ValueError, match="frame_seq"):
        SimPerception().safe_probability(_scene(), CLASSES, View(None, 50.0, HFOV), -1, REFERENCE_PROMPTS)


def _only(**errors) -> SimPerception:
    """The realistic profile with every error off except the named ones."""
    off = dict(confusion=0.0, context_local=0.0, context_global=0.0, flicker_logit=0.0, flicker_offset=0.0, shadow=0.0)
    return SimPerception(dataclasses.replace(profile_params("realistic"), **{**off, **errors}), seed=1)


def test_buildings_cast_shadows_on_one_side_fixed_in_the_world() -> None:
    labels = np.full((352, 352), 3, np.uint8)
    labels[136:216, 136:216] = 1  # a flat roof on a lawn
    shadow = APPEARANCE_INDEX["shadow"]
    perception = _only(shadow=0.5)
    north_up = perception.fractions(labels, CLASSES, View((0.0, 0.0), 40.0, HFOV, 0.0))[..., shadow]
    assert north_up.max() > 0.2  # some lawn lies in the roof's shadow
    assert north_up[17:27, 17:27].max() == 0.0  # not on the roof itself
    # Turning the camera turns the shadow with the ground: the sun stays where it is.
    turned = perception.fractions(labels, CLASSES, View((0.0, 0.0), 40.0, HFOV, math.pi))[..., shadow]
    assert np.allclose(np.rot90(north_up, 2), turned, atol=0.05)
    assert _only().fractions(labels, CLASSES, View((0.0, 0.0), 40.0, HFOV))[..., shadow].max() == 0.0


def test_a_patch_reads_differently_in_different_surroundings() -> None:
    def centre(surround: int) -> float:
        labels = np.full((352, 352), surround, np.uint8)
        labels[146:206, 146:206] = 6  # the same sidewalk patch
        prob = _only(context_local=0.25, context_global=0.12).safe_probability(
            labels, CLASSES, View((0.0, 0.0), 100.0, HFOV), 0, REFERENCE_PROMPTS, SOFTMAX)
        return float(prob[176, 176])

    assert centre(3) - centre(2) > 0.03  # among lawns it looks safer than among roads


def test_misreadings_drift_slowly_with_altitude() -> None:
    from dovesei.segmenter.sim_backend import world_field

    rng = np.random.default_rng(0)
    east, north = rng.uniform(-2000, 2000, 4000), rng.uniform(-2000, 2000, 4000)
    params = profile_params("realistic")
    at = {alt: world_field(east, north, alt, np.array([11]), params)[0] for alt in (100.0, 95.0, 25.0)}
    assert np.corrcoef(at[100.0], at[95.0])[0, 1] > 0.9  # a few metres of descent: the same misreading
    assert abs(np.corrcoef(at[100.0], at[25.0])[0, 1]) < 0.5  # two octaves lower: another one
