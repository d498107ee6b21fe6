"""CLIPSeg variants, the decision gate and the picker, on the tiny random-weight model.

Which variants can run depends on this host; the tests never assume it: where a variant cannot
run (no native BF16, no GPU) the test asserts the refusal and its reason instead of skipping, and
where it can, it asserts the variant runs and passes the gate.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from dovesei.segmenter import backends, cpu_features, gate, picker
from dovesei.segmenter.backends import VariantUnavailable, build_variant
from dovesei.segmenter.clipseg import ClipSegBackend, load_clipseg
from dovesei.segmenter.core import BackendUnavailableError, SegmenterConfig
from dovesei.segmenter.fusion import FusionConfig
from dovesei.segmenter.prompts import REFERENCE_PROMPTS
from dovesei.segmenter.service import CLI, ServiceConfig, build_backend


@pytest.fixture(autouse=True)
def _offline(monkeypatch):
    import huggingface_hub.constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)


@pytest.fixture(scope="module")
def tiny_dir(tiny_clipseg_dir):
    return tiny_clipseg_dir


@pytest.fixture(scope="module")
def base(tiny_dir) -> ClipSegBackend:
    return load_clipseg(str(tiny_dir))


@pytest.fixture(scope="module")
def onnx_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("onnx-cache")


FRAMES = picker.calibration_frames(2, seed=1)
FUSION = FusionConfig()


# --- CPU flags --------------------------------------------------------------------------------


def test_bf16_is_native_only_with_the_flags_and_onednn_agreeing(tmp_path) -> None:
    with_bf16 = tmp_path / "a"
    with_bf16.write_text("processor\t: 0\nmodel name\t: Test CPU\nflags\t\t: fpu avx2 avx512f avx512_bf16 avx512_vnni\n")
    without = tmp_path / "b"
    without.write_text("processor\t: 0\nflags\t\t: fpu avx2 fma\n")
    flags = cpu_features.cpu_flags(with_bf16)
    assert "avx512_bf16" in flags and cpu_features.cpu_model(with_bf16) == "Test CPU"
    assert cpu_features.native_bf16(flags)[0]
    assert cpu_features.native_bf16(flags, onednn_bf16=True)[0]
    native, why = cpu_features.native_bf16(flags, onednn_bf16=False)
    assert not native and "oneDNN" in why
    native, why = cpu_features.native_bf16(cpu_features.cpu_flags(without))
    assert not native and "avx512_bf16" in why
    assert cpu_features.cpu_flags(tmp_path / "missing") == frozenset()


# --- the gate ---------------------------------------------------------------------------------


def test_gate_passes_equal_decisions_and_fails_a_moved_target() -> None:
    yy, xx = np.mgrid[0:100, 0:200]
    prob = np.exp(-((xx - 60.0) ** 2 + (yy - 50.0) ** 2) / 800.0).astype(np.float32)
    same = gate.gate([prob], [prob + 1e-4])
    assert same.passed and same.min_mask_iou == 1.0 and same.max_target_shift_frac == 0.0
    moved = np.roll(prob, 10, axis=1)  # 10 px of 200 = 5 % of the width
    result = gate.gate([prob], [moved])
    assert not result.passed and result.max_target_shift_frac == pytest.approx(0.05, abs=0.006)
    assert "FAILED" in result.describe()


def test_dynamic_threshold_keeps_about_the_best_tenth() -> None:
    prob = np.linspace(0.0, 0.6, 10000, dtype=np.float32).reshape(100, 100)
    mask = gate.dynamic_threshold_mask(prob)
    assert 0.10 <= mask.mean() < 0.12 and mask[-1, -1] and not mask[0, 0]
    assert not gate.dynamic_threshold_mask(np.zeros((10, 10), np.float32)).any()


def test_gate_mask_is_the_controllers_dynamic_threshold() -> None:
    from dovesei.controller.policies.dovesei.policy import DoveseiConfig, dynamic_threshold

    rng = np.random.default_rng(3)
    for scale in (1.0, 0.5, 0.05, 0.002):  # from easy frames to ones needing a low threshold, or none
        prob = (rng.random((60, 80)) ** 3 * scale).astype(np.float32)
        theirs = dynamic_threshold(prob, DoveseiConfig()).mask_u8
        ours = gate.dynamic_threshold_mask(prob)
        assert np.array_equal(ours, np.zeros_like(ours) if theirs is None else theirs > 0), scale


# --- variants ---------------------------------------------------------------------------------


def test_fp32_is_the_base_itself(base) -> None:
    assert build_variant("fp32", base) is base


def test_bf16_runs_only_where_the_cpu_has_native_bf16(base) -> None:
    native, why = backends.bf16_native()
    if native:
        model = build_variant("bf16", base)
        assert model.dtype == "bfloat16"
        _, ref = picker.measure(base, FRAMES, REFERENCE_PROMPTS, FUSION)
        _, got = picker.measure(model, FRAMES, REFERENCE_PROMPTS, FUSION)
        assert gate.gate(ref, got).min_mask_iou > 0.5
    else:
        with pytest.raises(VariantUnavailable, match="bf16 refused: the CPU has no native BF16"):
            build_variant("bf16", base)


def test_cuda_fp16_runs_on_a_gpu_and_is_refused_with_the_reason_without_one(base) -> None:
    ok, _ = backends.cuda_available()
    if ok:
        model = build_variant("cuda-fp16", base)
        _, ref = picker.measure(base, FRAMES, REFERENCE_PROMPTS, FUSION)
        _, got = picker.measure(model, FRAMES, REFERENCE_PROMPTS, FUSION)
        assert gate.gate(ref, got).passed
    else:
        with pytest.raises(VariantUnavailable, match=r"cuda-fp16 refused: no CUDA device \(torch.cuda.is_available"):
            build_variant("cuda-fp16", base)


def test_onnx_int8_is_exported_once_and_close_to_fp32(base, onnx_cache, caplog) -> None:
    from dovesei.segmenter.onnx_backend import OnnxClipSeg

    implementation = base._model.config.vision_config._attn_implementation
    model = OnnxClipSeg(base, cache_dir=onnx_cache, threads=1)
    # The export traced eager attention; the torch path gets its own implementation back.
    assert base._model.config.vision_config._attn_implementation == implementation
    exported = sorted(p.name for p in next(onnx_cache.iterdir()).iterdir())
    assert exported == ["decoder.onnx", "encoder_int8.onnx", "export.json"]  # the fp32 intermediates are removed
    # The optimizer's fusions fired in every encoder layer, and the fused attention was quantised.
    assert model.export["fused"]["Attention"] == base.encoder_depth
    assert model.export["fused"]["SkipLayerNormalization"] >= base.encoder_depth
    ops = model.export["encoder_int8_ops"]
    assert ops.get("QAttention") == base.encoder_depth and "Attention" not in ops and ops.get("MatMulInteger", 0) > 0
    assert "ConvInteger" not in ops  # the patch convolution stays fp32
    ref, got = base.logits(FRAMES[0], REFERENCE_PROMPTS), model.logits(FRAMES[0], REFERENCE_PROMPTS)
    assert got.shape == ref.shape == (REFERENCE_PROMPTS.n_prompts, 352, 352)
    # int8 weights: close, not equal (the gate judges whether it is close enough).
    assert np.abs(got - ref).max() < 0.1 * np.ptp(ref)
    assert np.abs(got - ref).max() > 0.0
    # A prompt set of another size goes through the same decoder (dynamic prompt axis).
    fewer = REFERENCE_PROMPTS.__class__(positive=("grass",), negative=("road",), template="{}")
    assert model.logits(FRAMES[0], fewer).shape == (2, 352, 352)
    caplog.set_level(logging.INFO, logger="dovesei.segmenter.onnx_backend")
    # Two threads decode the prompts in parallel calls: same logits, in prompt order.
    parallel = OnnxClipSeg(base, cache_dir=onnx_cache, threads=2)
    assert parallel._decoder_pool is not None and model._decoder_pool is None
    assert np.allclose(parallel.logits(FRAMES[0], REFERENCE_PROMPTS), got, atol=1e-4)
    assert any("ONNX export found" in r.getMessage() for r in caplog.records)


# --- the picker -------------------------------------------------------------------------------


def test_auto_times_every_runnable_variant_and_keeps_the_fastest_passing(base, onnx_cache, monkeypatch) -> None:
    monkeypatch.setattr("dovesei.segmenter.onnx_backend.default_cache_dir", lambda: onnx_cache)
    model, pick = picker.choose(base, "auto", REFERENCE_PROMPTS, FUSION, threads=1, frames=FRAMES, export=True)
    runnable, refused = backends.candidates(base, export=True)
    timed = {c.name: c for c in pick.timed}
    assert set(timed) | set(pick.refused) == set(backends.VARIANTS)
    assert set(timed) == set(runnable) - set(pick.refused)
    assert "onnx-int8" in timed  # installed here with the onnx extra
    assert timed["fp32"].gate.passed and timed["fp32"].gate.min_mask_iou == 1.0
    assert all(c.cpu_s_per_frame > 0 for c in pick.timed)  # the work, beside the wall time
    passing = [c for c in pick.timed if c.gate.passed]
    assert pick.chosen == min(passing, key=lambda c: c.s_per_frame).name
    assert model.dtype == {"fp32": "float32", "onnx-int8": "onnx-int8", "bf16": "bfloat16",
                           "cuda-fp16": "float16"}[pick.chosen]
    assert "picked by measurement" in pick.describe()
    for name, why in refused.items():
        assert pick.refused[name] == why


def test_auto_does_not_export_onnx_unasked(base, tmp_path, monkeypatch) -> None:
    monkeypatch.setattr("dovesei.segmenter.onnx_backend.default_cache_dir", lambda: tmp_path)
    _, refused = backends.candidates(base)
    assert "not exported yet" in refused["onnx-int8"] and "bench-segmenter" in refused["onnx-int8"]
    _, pick = picker.choose(base, "auto", REFERENCE_PROMPTS, FUSION, threads=1, frames=FRAMES[:1])
    assert "onnx-int8" not in {c.name for c in pick.timed} and not any(tmp_path.iterdir())


def test_a_pinned_variant_that_cannot_run_here_is_one_clear_error(tiny_dir) -> None:
    config = ServiceConfig(segmenter=SegmenterConfig(backend="clipseg", model=str(tiny_dir)), variant="cuda-fp16")
    if backends.cuda_available()[0]:
        assert build_backend(config).model.dtype == "float16"
    else:
        with pytest.raises(BackendUnavailableError, match="cuda-fp16 refused: no CUDA device"):
            build_backend(config)
    pinned = build_backend(ServiceConfig(segmenter=config.segmenter, variant="fp32"))
    assert "pinned" in pinned.reason and pinned.model.dtype == "float32"


def test_variant_flag_round_trips_and_refuses_unknown_names() -> None:
    config = CLI.from_args(CLI.build_parser().parse_args(["--variant", "onnx-int8"]))
    assert config.variant == "onnx-int8"
    assert CLI.from_args(CLI.build_parser().parse_args(CLI.to_argv(config))).variant == "onnx-int8"
    with pytest.raises(SystemExit):
        CLI.build_parser().parse_args(["--variant", "int4"])
