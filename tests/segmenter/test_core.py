"""SegmenterCore without Zenoh: the heatmap contract, rejections, prompt changes, backend choice.

The simulated backend runs on tiny 64x64 frames; the CLIPSeg backend runs on a tiny random model
written by `build_random_clipseg` and opened through `load_clipseg`, the path real weights take.
"""

from __future__ import annotations

import logging
import subprocess
import sys

import numpy as np
import pytest

from dovesei.segmenter import clipseg
from dovesei.segmenter.core import (
    DEFAULT_MODEL, DTYPES, BackendUnavailableError, ClipSegFrameBackend, FrameRejected, SegmenterConfig, SegmenterCore, SimFrameBackend, make_backend, to_wire,
)
from dovesei.segmenter.prompts import REFERENCE_PROMPTS, PromptError, PromptSet
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import CameraFrame, ClassEntry, GroundTruth, PromptSetMsg, Stamp

CLASSES = (ClassEntry(1, "grass", True), ClassEntry(2, "road", False), ClassEntry(3, "roof_flat", False))
NEW_PROMPTS = PromptSetMsg(Stamp(0.0, "wall"), ("open field",), ("building", "road", "tree"), "photo of {}")


def make_frame(seq: int = 3, size_px: tuple[int, int] = (64, 64), truth: bool = True, vehicle: str = "uav1",
               seed: int = 0) -> CameraFrame:
    """A frame with a left half of grass (safe) and a right half of road/roof (unsafe)."""
    height_px, width_px = size_px
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (height_px, width_px, 3), dtype=np.uint8)
    labels = np.full((height_px, width_px), 2, np.uint8)
    labels[:, : width_px // 2] = 1
    labels[: height_px // 4, width_px // 2:] = 3
    gt = GroundTruth(labels, CLASSES) if truth else None
    return CameraFrame(vehicle, seq, Stamp(1.25 + seq, "sim"), image, 1.274, 87.5, sent_wall_s=0.0, truth=gt)


def sim_core(**overrides) -> SegmenterCore:
    config = SegmenterConfig(backend="sim", **overrides)
    return SegmenterCore(make_backend(config), config)


# --- simulated backend ------------------------------------------------------------------------


def test_sim_heatmap_contract() -> None:
    core = sim_core(sim_noise=1.0, sim_seed=4)
    frame = make_frame(seq=11, size_px=(48, 80))
    hm = core.process(frame)
    assert (hm.vehicle_id, hm.seq, hm.stamp) == (frame.vehicle_id, 11, frame.stamp)
    assert (hm.alt_agl_m, hm.hfov_rad) == (frame.alt_agl_m, frame.hfov_rad)
    assert hm.prob_safe.shape == (48, 80) and hm.prob_safe.dtype == np.uint8
    # The simulated backend makes prompt logits; the configured fusion runs after it, as after CLIPSeg.
    assert hm.backend == "simulated" and hm.simulated is True and hm.fusion == "grouped"
    assert hm.prompt_set_id == REFERENCE_PROMPTS.set_id
    assert 0.0 < hm.inference_s < 1.0 and hm.frame_to_segmenter_s == 0.0
    # Degraded, but the grass half still reads safer than the road half.
    prob = hm.probability()
    assert prob[:, :40].mean() > prob[:, 40:].mean() + 0.2
    assert core.processed == 1 and not core.rejected


def test_sim_clean_profile_reads_the_halves_apart_on_a_float16_wire() -> None:
    core = sim_core(sim_profile="clean", heatmap_dtype="float16")
    hm = core.process(make_frame())
    assert hm.prob_safe.dtype == np.float16
    prob = hm.probability()
    assert prob[:, :20].mean() > 0.8 and prob[20:, 44:].mean() < 0.2  # grass vs road, away from the seam


def test_sim_is_deterministic_per_frame_and_flickers_between_frames() -> None:
    a, b = sim_core(sim_seed=7), sim_core(sim_seed=7)
    f1, f2 = make_frame(seq=1), make_frame(seq=2)
    np.testing.assert_array_equal(a.process(f1).prob_safe, b.process(f1).prob_safe)
    assert not np.array_equal(a.process(f1).prob_safe, a.process(f2).prob_safe)


def test_sim_refuses_frames_without_truth_and_counts_them() -> None:
    core = sim_core()
    with pytest.raises(FrameRejected) as info:
        core.process(make_frame(truth=False))
    assert info.value.reason == "no_truth" and "ground-truth" in str(info.value)
    assert isinstance(info.value, ValueError)
    core.process(make_frame())  # the next good frame is served
    assert core.rejected == {"no_truth": 1} and core.processed == 1


def test_frames_outside_the_size_limits_are_rejected() -> None:
    core = sim_core(min_side_px=32, max_side_px=128)
    for size in ((16, 64), (64, 200)):
        with pytest.raises(FrameRejected, match="outside 32..128") as info:
            core.process(make_frame(size_px=size))
        assert info.value.reason == "size"
    fixed = sim_core(expected_size_px=(64, 64))
    with pytest.raises(FrameRejected, match="expected 64x64"):
        fixed.process(make_frame(size_px=(64, 48)))
    assert fixed.process(make_frame()).prob_safe.shape == (64, 64)
    assert core.rejected == {"size": 2} and fixed.rejected == {"size": 1}


def test_sim_prompt_change_changes_the_map_and_the_set_id() -> None:
    core = sim_core()
    frame = make_frame()
    before = core.process(frame)
    assert core.set_prompts(NEW_PROMPTS) is True
    after = core.process(frame)
    new_id = PromptSet(NEW_PROMPTS.positive, NEW_PROMPTS.negative, NEW_PROMPTS.template).set_id
    assert after.prompt_set_id == new_id != before.prompt_set_id
    assert not np.array_equal(before.prob_safe, after.prob_safe)  # the words decide, as with CLIPSeg
    assert core.set_prompts(NEW_PROMPTS) is False and core.prompt_changes == 1


def test_bad_prompt_set_is_refused_and_the_old_one_stays() -> None:
    core = sim_core()
    bad = PromptSetMsg(Stamp(0.0, "wall"), ("grass {x}",), ("road",), "{}")  # braces break str.format
    with pytest.raises(PromptError):
        core.set_prompts(bad)
    assert core.prompts == REFERENCE_PROMPTS


def test_config_rejects_bad_values_by_name() -> None:
    for kwargs, name in ((dict(backend="gpu"), "backend"), (dict(fusion="max"), "fusion"),
                         (dict(heatmap_dtype="float32"), "heatmap_dtype"), (dict(sim_noise=-1.0), "sim_noise"),
                         (dict(min_side_px=100, max_side_px=50), "side limits"),
                         (dict(expected_size_px=(64,)), "expected_size_px")):
        with pytest.raises(ConfigError, match=name):
            SegmenterConfig(**kwargs)


def test_core_wraps_a_raw_simulated_backend() -> None:
    from dovesei.segmenter.simulated import SimPerceptionParams, SimulatedBackend

    config = SegmenterConfig(backend="sim")
    raw = SegmenterCore(SimulatedBackend(SimPerceptionParams(noise=0.5), seed=2), config)
    made = SegmenterCore(make_backend(SegmenterConfig(backend="sim", sim_noise=0.5, sim_seed=2)), config)
    frame = make_frame()
    np.testing.assert_array_equal(raw.process(frame).prob_safe, made.process(frame).prob_safe)
    with pytest.raises(TypeError, match="not a segmenter backend"):
        SegmenterCore(object(), config)


def test_to_wire_rounds_to_nearest() -> None:
    prob = np.array([[0.0, 0.5, 1.0, 0.999]], np.float32)
    np.testing.assert_array_equal(to_wire(prob, "uint8"), [[0, 128, 255, 255]])


# --- backend choice -------------------------------------------------------------------------


def test_auto_falls_back_to_sim_when_the_model_dir_is_missing(tmp_path, caplog) -> None:
    missing = tmp_path / "no-such-model"
    config = SegmenterConfig(backend="auto", model=str(missing))
    with caplog.at_level(logging.WARNING, logger="dovesei.segmenter.core"):
        backend = make_backend(config)
    assert isinstance(backend, SimFrameBackend)
    assert "fell back to simulated" in backend.reason and str(missing) in backend.reason
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("SIMULATED" in m and str(missing) in m and "no such local directory" in m for m in warnings)
    hm = SegmenterCore(backend, config).process(make_frame())
    assert hm.backend == "simulated" and hm.simulated


def test_explicit_clipseg_with_missing_weights_raises(tmp_path) -> None:
    with pytest.raises(BackendUnavailableError, match="--model") as info:
        make_backend(SegmenterConfig(backend="clipseg", model=str(tmp_path / "absent")))
    assert isinstance(info.value.__cause__, clipseg.ModelUnavailableError)


def test_core_constants_mirror_the_clipseg_module() -> None:
    assert (DEFAULT_MODEL, DTYPES) == (clipseg.DEFAULT_MODEL, clipseg.DTYPES)


# --- CLIPSeg backend on a tiny random model -------------------------------------------------


@pytest.fixture(scope="module")
def tiny_model_dir(tiny_clipseg_dir) -> str:
    return str(tiny_clipseg_dir)


@pytest.fixture(scope="module")
def tiny_backend(tiny_model_dir) -> ClipSegFrameBackend:
    backend = make_backend(SegmenterConfig(backend="auto", model=tiny_model_dir, threads=1))
    assert isinstance(backend, ClipSegFrameBackend)  # auto takes CLIPSeg when the weights load
    return backend


def test_clipseg_heatmap_contract_and_equals_the_backend(tiny_backend) -> None:
    config = SegmenterConfig(backend="clipseg", model=tiny_backend.model.model_id)
    core = SegmenterCore(tiny_backend, config)
    frame = make_frame(seq=5, size_px=(96, 128), truth=False)  # a real camera frame: no truth needed
    hm = core.process(frame)
    assert hm.prob_safe.shape == (96, 128) and hm.prob_safe.dtype == np.uint8
    assert hm.backend == "clipseg" and hm.simulated is False and hm.fusion == "grouped"
    assert (hm.seq, hm.stamp, hm.alt_agl_m) == (5, frame.stamp, frame.alt_agl_m)
    assert hm.prompt_set_id == REFERENCE_PROMPTS.set_id and hm.inference_s > 0
    direct = tiny_backend.model.safe_probability(frame.image_rgb, REFERENCE_PROMPTS, "grouped")
    np.testing.assert_array_equal(hm.prob_safe, to_wire(direct, "uint8"))
    # The raw ClipSegBackend is wrapped the same way.
    np.testing.assert_array_equal(SegmenterCore(tiny_backend.model, config).process(frame).prob_safe, hm.prob_safe)


def test_clipseg_prompt_change_rebuilds_the_text_cache_once(tiny_backend) -> None:
    config = SegmenterConfig(backend="clipseg", model=tiny_backend.model.model_id, heatmap_dtype="float16")
    core = SegmenterCore(tiny_backend, config)
    frame = make_frame(seq=1, truth=False)
    before = core.process(frame)
    encodes = tiny_backend.model.text_encode_count
    core.set_prompts(NEW_PROMPTS)
    after = [core.process(make_frame(seq=s, truth=False)) for s in (1, 2)]
    assert tiny_backend.model.text_encode_count == encodes + 1
    assert after[0].prompt_set_id != before.prompt_set_id
    assert not np.array_equal(after[0].prob_safe, before.prob_safe)
    # The reference fusion is a different function of the same logits.
    ref = SegmenterCore(tiny_backend, SegmenterConfig(backend="clipseg", fusion="dovesei", heatmap_dtype="float16"))
    hm_ref = ref.process(frame)
    assert hm_ref.fusion == "dovesei" and not np.array_equal(hm_ref.prob_safe, before.prob_safe)


def test_importing_the_service_does_not_import_torch() -> None:
    # The onboard install has no torch: the sim backend and the service must work without it.
    code = "import sys, dovesei.segmenter.service; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0
