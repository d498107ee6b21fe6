"""Simulated perception backend: clean labels at noise 0, determinism, CLIPSeg-like degradations.

Pure numpy/OpenCV tests (no Zenoh, no torch). Label maps are the module's demo scene or small
hand-made arrays; statistical checks use fixed seeds and bounds many standard deviations wide.
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np
import pytest

from dovesei.segmenter.simulated import (
    DEMO_CLASSES,
    OUTSIDE_ID,
    MissingTruthError,
    SimPerceptionParams,
    SimulatedBackend,
    bench_hz,
    demo_labels,
    perception_group,
    render_noise_preview,
)
from dovesei.shared.errors import ConfigError

SAFE_IDS = [i for i, (_, safe) in DEMO_CLASSES.items() if safe]
DUBAI_CLASSES = {
    0: ("unlabeled", False),
    1: ("building", False),
    2: ("land (unpaved area)", True),
    3: ("road", False),
    4: ("vegetation", True),
    5: ("water", False),
}


@pytest.fixture(scope="module")
def labels() -> np.ndarray:
    return demo_labels()


def masks(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    safe = np.isin(labels, SAFE_IDS)
    return safe, ~safe & (labels != OUTSIDE_ID)


def test_noise_zero_is_exactly_the_clean_label_map(labels: np.ndarray) -> None:
    params = SimPerceptionParams(noise=0.0, outside_prob=0.2)
    backend = SimulatedBackend(params, seed=3)
    safe, unsafe = masks(labels)
    for seq in (0, 1, 99):
        prob = backend.safe_probability(labels, DEMO_CLASSES, seq)
        assert prob.dtype == np.float32 and prob.shape == labels.shape
        assert np.all(prob[safe] == 1.0)
        assert np.all(prob[unsafe] == 0.0)
        assert np.all(prob[labels == OUTSIDE_ID] == np.float32(0.2))


def test_noise_zero_with_out_size_resizes_labels_nearest(labels: np.ndarray) -> None:
    backend = SimulatedBackend(SimPerceptionParams(noise=0.0))
    prob = backend.safe_probability(labels, DEMO_CLASSES, 0, out_size=(120, 200))
    expected_labels = cv2.resize(labels, (200, 120), interpolation=cv2.INTER_NEAREST)
    assert prob.shape == (120, 200)
    assert np.array_equal(prob[np.isin(expected_labels, SAFE_IDS)], np.ones(np.isin(expected_labels, SAFE_IDS).sum()))


def test_ids_absent_from_the_class_table_count_as_unsafe() -> None:
    lab = np.array([[8, 42], [42, 8]], dtype=np.uint8)
    prob = SimulatedBackend(SimPerceptionParams(noise=0.0)).safe_probability(lab, DEMO_CLASSES, 0)
    assert prob.tolist() == [[1.0, 0.0], [0.0, 1.0]]


def test_same_inputs_give_identical_bytes_in_any_order(labels: np.ndarray) -> None:
    a = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=5)
    b = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=5)
    first = a.safe_probability(labels, DEMO_CLASSES, 7)
    # Rendering other frames in between must not change frame 7: nothing carries over.
    for seq in (3, 8, 100):
        b.safe_probability(labels, DEMO_CLASSES, seq)
    assert first.tobytes() == b.safe_probability(labels, DEMO_CLASSES, 7).tobytes()
    assert first.tobytes() == a.safe_probability(labels, DEMO_CLASSES, 7).tobytes()


def test_frames_and_seeds_differ_when_noisy(labels: np.ndarray) -> None:
    backend = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=5)
    f7 = backend.safe_probability(labels, DEMO_CLASSES, 7)
    f8 = backend.safe_probability(labels, DEMO_CLASSES, 8)
    other_seed = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=6).safe_probability(labels, DEMO_CLASSES, 7)
    assert np.abs(f7 - f8).mean() > 0.01
    assert np.abs(f7 - other_seed).mean() > 0.01


@pytest.mark.parametrize("noise", [0.3, 1.0, 2.0, 4.0])
def test_output_contract_float32_in_unit_range(labels: np.ndarray, noise: float) -> None:
    backend = SimulatedBackend(SimPerceptionParams(noise=noise), seed=1)
    for seq in range(6):
        prob = backend.safe_probability(labels, DEMO_CLASSES, seq, out_size=(240, 320))
        assert prob.dtype == np.float32 and prob.shape == (240, 320)
        assert np.isfinite(prob).all() and prob.min() >= 0.0 and prob.max() <= 1.0


def test_noise_one_is_discriminative_but_imperfect(labels: np.ndarray) -> None:
    backend = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=0)
    safe, unsafe = masks(labels)
    frames = [backend.safe_probability(labels, DEMO_CLASSES, seq) for seq in range(20)]
    mean_safe = float(np.mean([f[safe].mean() for f in frames]))
    mean_unsafe = float(np.mean([f[unsafe].mean() for f in frames]))
    assert mean_safe > mean_unsafe + 0.1
    # Not a clean map: safe ground is doubted and unsafe ground is sometimes trusted.
    assert mean_safe < 0.9 and mean_unsafe > 0.1


def test_more_noise_means_more_error(labels: np.ndarray) -> None:
    clean = SimulatedBackend(SimPerceptionParams(noise=0.0)).safe_probability(labels, DEMO_CLASSES, 0)
    inside = labels != OUTSIDE_ID
    errors = []
    for noise in (0.25, 1.0, 2.0):
        backend = SimulatedBackend(SimPerceptionParams(noise=noise, flip_prob=0.0), seed=2)
        errors.append(np.mean([np.abs(backend.safe_probability(labels, DEMO_CLASSES, s) - clean)[inside].mean()
                               for s in range(5)]))
    assert errors[0] < errors[1] < errors[2]


def test_class_confusions_follow_the_affinity_table() -> None:
    # One big patch per class, blur and fields off: each patch reads its group's affinity, jittered.
    ids = list(DEMO_CLASSES)
    lab = np.repeat(np.array(ids, dtype=np.uint8), 64)[None, :].repeat(8, axis=0)
    params = SimPerceptionParams(noise=1.0, blur_sigma_patches=0.0, field_amplitude=0.0, flicker_amplitude=0.0,
                                 gain_jitter=0.0, offset_jitter=0.0, flip_prob=0.0)
    backend = SimulatedBackend(params, seed=0)
    mean = np.mean([backend.safe_probability(lab, DEMO_CLASSES, s) for s in range(40)], axis=0)
    per_id = {i: float(mean[:, k * 64:(k + 1) * 64].mean()) for k, i in enumerate(ids)}
    name = {n: i for i, (n, _) in DEMO_CLASSES.items()}
    # Flat roofs read safer than pitched ones (concrete look-alike); trees safer than cars (grass look-alike).
    assert per_id[name["roof_flat"]] > per_id[name["roof_pitched"]] + 0.1
    assert per_id[name["tree"]] > per_id[name["car"]] + 0.1
    assert per_id[name["grass"]] > per_id[name["tree"]] + 0.15
    assert abs(per_id[name["grass"]] - 0.8) < 0.08


def test_flips_occur_at_the_expected_rate() -> None:
    n = 3000
    for noise, flip_prob in ((1.0, 0.1), (0.5, 0.1), (2.0, 0.2)):
        backend = SimulatedBackend(SimPerceptionParams(noise=noise, flip_prob=flip_prob), seed=11)
        rate = min(1.0, noise * flip_prob)
        count = sum(backend.frame_effects(s).flip is not None for s in range(n))
        # Binomial(n, rate): five standard deviations either side.
        sd = math.sqrt(n * rate * (1 - rate))
        assert abs(count - n * rate) < 5 * sd, (noise, count)
    quiet = SimulatedBackend(SimPerceptionParams(noise=0.0), seed=11)
    assert not any(quiet.frame_effects(s).flip for s in range(500))


def test_flip_blob_covers_the_configured_area_and_only_that_frame(labels: np.ndarray) -> None:
    params = SimPerceptionParams(noise=1.0)
    backend = SimulatedBackend(params, seed=4)
    no_flip = SimulatedBackend(SimPerceptionParams(noise=1.0, flip_strength=0.0), seed=4)
    flipped = [s for s in range(300) if backend.frame_effects(s).flip][:6]
    assert len(flipped) == 6
    for seq in flipped:
        blob = backend.frame_effects(seq).flip
        area_frac = float((blob.mask(256, 256) > 0.5).mean())
        assert 0.08 < area_frac < 0.33, area_frac
        changed = np.abs(backend.safe_probability(labels, DEMO_CLASSES, seq)
                         - no_flip.safe_probability(labels, DEMO_CLASSES, seq)) > 1e-6
        assert 0.05 < changed.mean() < 0.45
    unflipped = next(s for s in range(300) if not backend.frame_effects(s).flip)
    assert np.array_equal(backend.safe_probability(labels, DEMO_CLASSES, unflipped),
                          no_flip.safe_probability(labels, DEMO_CLASSES, unflipped))


def test_slow_field_makes_neighbouring_frames_more_alike_than_distant_ones(labels: np.ndarray) -> None:
    backend = SimulatedBackend(SimPerceptionParams(noise=1.0, flip_prob=0.0), seed=9)
    # The deterministic part (affinities and blur, no random effect) is the same every frame:
    # compare what is left.
    steady = SimulatedBackend(SimPerceptionParams(
        noise=1.0, flip_prob=0.0, field_amplitude=0.0, flicker_amplitude=0.0, gain_jitter=0.0,
        offset_jitter=0.0, group_jitter=0.0, confusion_pull=0.0)).safe_probability(labels, DEMO_CLASSES, 0)

    def err(seq: int) -> np.ndarray:
        return (backend.safe_probability(labels, DEMO_CLASSES, seq) - steady).ravel()

    near = np.mean([np.corrcoef(err(s), err(s + 1))[0, 1] for s in (0, 20, 40)])
    far = np.mean([np.corrcoef(err(s), err(s + 50))[0, 1] for s in (0, 20, 40)])
    assert near > far + 0.1


@pytest.mark.parametrize(
    ("name", "group"),
    [
        # The Dubai world folder's names.
        ("building", "roof"),
        ("land (unpaved area)", "soil"),
        ("road", "road"),
        ("vegetation", "grass"),
        ("water", "water"),
        ("unlabeled", "other"),
        # The synthetic city's names.
        ("roof_flat", "roof"),
        ("roof_pitched", "roof_pitched"),
        ("sidewalk", "paved"),
        ("plaza", "paved"),
        ("parking_lot", "paved"),
        ("car", "car"),
        ("grass", "grass"),
        ("sports_field", "sports_field"),
        ("tree", "tree"),
        ("bare_soil", "soil"),
        ("person", "person"),
        # Case, plurals and separators.
        ("Trees", "tree"),
        ("People", "person"),
        ("Asphalt-Road", "road"),
        ("helipad", "other"),
    ],
)
def test_class_names_map_to_perception_groups(name: str, group: str) -> None:
    assert perception_group(name) == group


def test_dubai_class_table_renders_and_ranks_safe_above_unsafe() -> None:
    lab = np.repeat(np.arange(6, dtype=np.uint8), 40)[None, :].repeat(40, axis=0)
    backend = SimulatedBackend(SimPerceptionParams(noise=1.0, blur_sigma_patches=0.2), seed=0)
    mean = np.mean([backend.safe_probability(lab, DUBAI_CLASSES, s) for s in range(20)], axis=0)
    col = {i: float(mean[:, i * 40 + 10:i * 40 + 30].mean()) for i in range(6)}
    assert min(col[2], col[4]) > max(col[0], col[1], col[3], col[5])


def test_class_entries_from_the_sim_message_work_like_a_mapping(labels: np.ndarray) -> None:
    from dovesei.shared.messages import ClassEntry

    entries = tuple(ClassEntry(id=i, name=n, safe=s) for i, (n, s) in DEMO_CLASSES.items())
    backend = SimulatedBackend(SimPerceptionParams(noise=1.0), seed=1)
    assert np.array_equal(backend.safe_probability(labels, entries, 4),
                          backend.safe_probability(labels, DEMO_CLASSES, 4))


def test_missing_truth_is_refused_with_a_clear_error() -> None:
    backend = SimulatedBackend()
    with pytest.raises(MissingTruthError, match="ground-truth labels.*real camera") as info:
        backend.safe_probability(None, DEMO_CLASSES, 0)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"noise": -0.1}, "noise"),
        ({"noise": float("nan")}, "noise"),
        ({"noise": True}, "noise"),
        ({"flip_prob": 1.5}, "flip_prob"),
        ({"blur_sigma_patches": -1.0}, "blur_sigma_patches"),
        ({"field_corr_frac": 0.0}, "field_corr_frac"),
        ({"field_period_frames": 0}, "field_period_frames"),
        ({"flip_area_frac": (0.3, 0.1)}, "flip_area_frac"),
        ({"affinity": (("lava", 0.1),)}, "affinity"),
        ({"affinity": (("grass", 1.2),)}, "affinity"),
        ({"outside_prob": 2.0}, "outside_prob"),
    ],
)
def test_bad_params_raise_naming_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        SimPerceptionParams(**kwargs)
    assert issubclass(ConfigError, ValueError)


def test_bad_call_arguments_raise_value_errors(labels: np.ndarray) -> None:
    backend = SimulatedBackend()
    with pytest.raises(ValueError, match="seed"):
        SimulatedBackend(seed=-1)
    with pytest.raises(ValueError, match="frame_seq"):
        backend.safe_probability(labels, DEMO_CLASSES, -1)
    with pytest.raises(ValueError, match="HxW"):
        backend.safe_probability(np.zeros((4, 4, 3), np.uint8), DEMO_CLASSES, 0)
    with pytest.raises(ValueError, match="integer class ids"):
        backend.safe_probability(np.zeros((4, 4), np.float32), DEMO_CLASSES, 0)
    with pytest.raises(ValueError, match="outside 0..254"):
        backend.safe_probability(labels, {255: ("road", False)}, 0)
    with pytest.raises(ValueError, match="out_size"):
        backend.safe_probability(labels, DEMO_CLASSES, 0, out_size=(0, 10))


def test_partial_affinity_override_keeps_the_other_defaults() -> None:
    params = SimPerceptionParams(affinity=(("grass", 0.9),))
    assert params.affinity_of("grass") == 0.9
    assert params.affinity_of("road") == 0.3


def test_backend_says_it_is_simulated(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="dovesei.segmenter.simulated"):
        backend = SimulatedBackend()
    assert backend.name == "simulated"
    assert "simulated" in caplog.text and "real camera" in caplog.text


def test_preview_png_and_bench_run(tmp_path) -> None:
    out = render_noise_preview(tmp_path / "preview.png", seed=0)
    sheet = cv2.imread(str(out))
    assert sheet is not None and sheet.shape[0] > 2 * 352 and sheet.shape[1] > 3 * 352
    assert bench_hz(n=3) > 0.0
