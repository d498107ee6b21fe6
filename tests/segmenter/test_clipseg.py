"""CLIPSeg backend against the stock transformers forward, on a tiny random model.

The tiny model directory is written once per session by ``build_random_clipseg`` and opened with
``load_clipseg``, the same call users make with the real weights. Offline: HF_HUB_OFFLINE is
forced on for the whole module.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dovesei.segmenter.clipseg import (
    ClipSegBackend,
    ImageError,
    ModelUnavailableError,
    load_clipseg,
)
from dovesei.segmenter.fusion import FusionConfig
from dovesei.segmenter.prompts import REFERENCE_PROMPTS, PromptError, PromptSet

# fp32 fast path vs stock forward; the tiny model's logits have a spread of ~4.
LOGIT_ATOL = 1e-4


@pytest.fixture(autouse=True)
def _offline(monkeypatch):
    import huggingface_hub.constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    # huggingface_hub reads the variable once at import; patch the parsed value too.
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)


@pytest.fixture(scope="module")
def tiny_dir(tiny_clipseg_dir):
    return tiny_clipseg_dir


@pytest.fixture(scope="module")
def backend(tiny_dir) -> ClipSegBackend:
    return load_clipseg(str(tiny_dir))


def _frame(seed: int, height_px: int = 240, width_px: int = 320) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # Smooth blobs rather than white noise, so resizing and patches see structure.
    small = rng.integers(0, 256, size=(6, 8, 3), dtype=np.uint8)
    return cv2.resize(small, (width_px, height_px), interpolation=cv2.INTER_CUBIC)


SMALL_PROMPTS = PromptSet(positive=["grass", "park"], negative=["building", "road", "water"], template="photo of {}")


def test_fast_path_equals_stock_forward(backend):
    image = _frame(1)
    fast = backend.logits(image, REFERENCE_PROMPTS)
    stock = backend.reference_logits(image, REFERENCE_PROMPTS)
    assert fast.shape == (13, 352, 352) and fast.dtype == np.float32
    assert np.abs(stock).max() > 1.0  # the comparison is not between two near-zero maps
    np.testing.assert_allclose(fast, stock, atol=LOGIT_ATOL, rtol=0)
    # Prompts do produce different maps (the comparison would be weak otherwise).
    assert np.abs(fast[0] - fast[1]).max() > 1e-2


def test_decoder_chunking_does_not_change_logits(backend):
    image = _frame(2)
    stock = backend.reference_logits(image, REFERENCE_PROMPTS)
    default_chunk = backend.decoder_chunk
    try:
        for chunk in (None, 1, 5):  # all at once, one by one, uneven split of 13
            backend.decoder_chunk = chunk
            np.testing.assert_allclose(backend.logits(image, REFERENCE_PROMPTS), stock, atol=LOGIT_ATOL, rtol=0)
    finally:
        backend.decoder_chunk = default_chunk


def test_vision_encoder_stops_at_the_deepest_extract_layer(backend):
    layers = backend._model.clip.vision_model.encoder.layers
    assert backend.extract_layers == (0, 2) and len(layers) == 4
    calls = {"last": 0}
    handle = layers[3].register_forward_hook(lambda *_: calls.__setitem__("last", calls["last"] + 1))
    try:
        backend.logits(_frame(3), SMALL_PROMPTS)
        assert calls["last"] == 0
        backend.reference_logits(_frame(3), SMALL_PROMPTS)
        assert calls["last"] == 1  # the stock forward runs it, once on the batch
    finally:
        handle.remove()


def test_batch_of_two_frames_equals_two_single_calls(backend):
    frames = [_frame(4), _frame(5)]
    batch = backend.logits_batch(frames, SMALL_PROMPTS)
    assert batch.shape == (2, SMALL_PROMPTS.n_prompts, 352, 352)
    for index, frame in enumerate(frames):
        np.testing.assert_allclose(batch[index], backend.logits(frame, SMALL_PROMPTS), atol=LOGIT_ATOL, rtol=0)
    assert np.abs(batch[0] - batch[1]).max() > 1e-2


def test_text_cache_is_rebuilt_once_per_prompt_change(backend):
    image = _frame(6)
    first = backend.logits(image, SMALL_PROMPTS)
    count = backend.text_encode_count
    backend.logits(image, SMALL_PROMPTS)
    backend.logits(_frame(7), SMALL_PROMPTS)
    assert backend.text_encode_count == count  # same set: cached
    # An equal set built anew (e.g. decoded from a message) hits the cache as well.
    rebuilt = PromptSet(positive=["grass", "park"], negative=["building", "road", "water"], template="photo of {}")
    backend.logits(image, rebuilt)
    assert backend.text_encode_count == count

    changed = PromptSet(positive=["grass", "park"], negative=["building", "road", "fence"], template="photo of {}")
    second = backend.logits(image, changed)
    assert backend.text_encode_count == count + 1
    backend.logits(image, changed)
    assert backend.text_encode_count == count + 1
    # The changed negative changes its own map, the unchanged prompts keep theirs.
    assert np.abs(second[4] - first[4]).max() > 1e-2
    np.testing.assert_allclose(second[:4], first[:4], atol=LOGIT_ATOL, rtol=0)


@pytest.mark.parametrize("mode", ["grouped", "dovesei"])
def test_safe_probability_contract_at_non_model_size(backend, mode):
    image = _frame(8, height_px=240, width_px=320)
    prob = backend.safe_probability(image, REFERENCE_PROMPTS, FusionConfig(mode=mode))
    assert prob.shape == (240, 320)
    assert prob.dtype == np.float32
    assert np.isfinite(prob).all()
    assert prob.min() >= 0.0 and prob.max() <= 1.0
    assert prob.max() - prob.min() > 1e-4  # not a constant map


def test_safe_probability_at_model_size_is_not_resized(backend):
    image = _frame(9, height_px=352, width_px=352)
    prob = backend.safe_probability(image, SMALL_PROMPTS, "dovesei")
    assert prob.shape == (352, 352)


def test_bfloat16_is_close_to_float32_stock(tiny_dir, backend):
    bf16 = load_clipseg(str(tiny_dir), dtype="bfloat16")
    image = _frame(10)
    stock = backend.reference_logits(image, REFERENCE_PROMPTS)
    fast_bf16 = bf16.logits(image, REFERENCE_PROMPTS)
    assert fast_bf16.dtype == np.float32
    error = np.abs(fast_bf16 - stock).max()
    # bf16 keeps 8 mantissa bits; a few percent of the logit range is expected, not more.
    assert 0 < error < 0.1 * np.ptp(stock)


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((240, 320), np.uint8),
        np.zeros((240, 320, 4), np.uint8),
        np.zeros((240, 320, 3), np.float32),
        np.zeros((4, 320, 3), np.uint8),
        "not an image",
    ],
)
def test_bad_frames_raise_image_error(backend, bad):
    with pytest.raises(ImageError):
        backend.logits(bad, SMALL_PROMPTS)


def test_empty_batch_raises_image_error(backend):
    with pytest.raises(ImageError, match="non-empty"):
        backend.logits_batch([], SMALL_PROMPTS)


def test_prompt_longer_than_text_encoder_raises(backend):
    # Unknown words fall back to characters: 40 x "zq" is 80 tokens in 119 characters.
    long_prompt = PromptSet(positive=[" ".join(["zq"] * 40)], negative=["road"], template="{}")
    with pytest.raises(PromptError, match="77"):
        backend.logits(_frame(11), long_prompt)


def test_bad_options_raise_value_error(tiny_dir):
    with pytest.raises(ValueError, match="dtype"):
        load_clipseg(str(tiny_dir), dtype="float16")
    with pytest.raises(ValueError, match="threads"):
        load_clipseg(str(tiny_dir), threads=0)


def _assert_helpful(message: str, looked_for: str) -> None:
    assert looked_for in message
    assert "offline" in message and "HF_HUB_OFFLINE" in message
    assert "--model /path/to/" in message
    assert "huggingface-cli download CIDAS/clipseg-rd64-refined --local-dir" in message


def test_missing_local_directory_names_it_and_explains(tmp_path):
    missing = str(tmp_path / "no-such-model")
    with pytest.raises(ModelUnavailableError) as info:
        load_clipseg(missing)
    _assert_helpful(str(info.value), missing)


def test_unknown_hub_id_offline_names_it_and_explains():
    with pytest.raises(ModelUnavailableError) as info:
        load_clipseg("nobody-here/no-such-clipseg-model")
    _assert_helpful(str(info.value), "nobody-here/no-such-clipseg-model")


def test_directory_without_weights_is_unavailable(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelUnavailableError, match="empty"):
        load_clipseg(str(tmp_path / "empty"))



def test_bench_smoke_prints_one_json_record(capsys, monkeypatch, tmp_path):
    import json

    from dovesei.benchmarks.segmenter import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # the ONNX export goes there, not to ~/.cache
    code = main(["--random-weights", "--size", "tiny", "--json", "--repeats", "1", "--reference-repeats", "1",
                 "--views", "2", "--fair-s", "4"])
    assert code == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    fairness = record["fairness"]  # the four-vehicle figure (test_fair.py holds it to 25 % +/- 5 %)
    assert set(fairness["per_vehicle"]) == {"uav1", "uav2", "uav3", "uav4"} and fairness["served_hz_total"] > 0
    assert sum(f["share"] for f in fairness["per_vehicle"].values()) == pytest.approx(1.0)
    for key in ("prompts", "threads", "reference_s_per_frame", "fast_s_per_frame", "speedup", "fast_hz",
                "max_abs_diff_vs_reference", "peak_rss_mb", "sim_backend_hz"):
        assert key in record
    assert record["prompts"] == 13
    assert record["max_abs_diff_vs_reference"] < LOGIT_ATOL
    assert record["speedup"] == pytest.approx(record["reference_s_per_frame"] / record["fast_s_per_frame"])
    # Every variant this host can run is timed and gated on the sim worlds' camera views; the
    # rest are named with the reason; the picked one passes the gate and is the fastest that does.
    backends, refused = record["backends"], record["backends_refused"]
    assert set(backends) | set(refused) == {"fp32", "bf16", "onnx-int8", "cuda-fp16"}
    assert backends["fp32"]["gate"]["passed"] and backends["fp32"]["gate"]["min_mask_iou"] == 1.0
    assert record["gate_views"] == 2 and record["gate"] == backends[record["picked"]]["gate"]
    passing = {name: b["s_per_frame"] for name, b in backends.items() if b["gate"]["passed"]}
    assert record["picked"] == min(passing, key=passing.get)
    assert record["picked_speedup"] == pytest.approx(record["reference_s_per_frame"] / record["picked_s_per_frame"])
    assert record["picked_speedup_cpu_time"] == pytest.approx(
        record["reference_cpu_s_per_frame"] / record["picked_cpu_s_per_frame"])
    for figures in backends.values():
        assert figures["cpu_s_per_frame"] > 0
        assert figures["speedup_vs_stock"] == pytest.approx(record["reference_s_per_frame"] / figures["s_per_frame"])
    if "onnx-int8" in backends:  # installed here with the onnx extra: the export says which fusions fired
        assert record["onnx_export"]["fused"]["Attention"] == record["onnx_export"]["encoder_layers"]
    assert isinstance(record["cpu"]["flags"], list) and isinstance(record["cpu"]["native_bf16"], bool)


def test_bench_refuses_a_missing_model_with_exit_code_2(tmp_path, capsys):
    from dovesei.benchmarks.segmenter import main

    assert main(["--model", str(tmp_path / "absent")]) == 2
    assert "not available" in capsys.readouterr().err


def test_rd64_random_config_is_the_real_architecture():
    from dovesei.testing.random_model import RD64_VOCAB_SIZE, _rd64_config, build_tokenizer_files

    vocab, _ = build_tokenizer_files()
    config = _rd64_config(vocab["<|startoftext|>"], vocab["<|endoftext|>"])
    vision, text = config.vision_config, config.text_config
    assert (vision.hidden_size, vision.num_hidden_layers, vision.num_attention_heads) == (768, 12, 12)
    assert (vision.patch_size, vision.intermediate_size) == (16, 3072)
    assert (text.hidden_size, text.num_hidden_layers, text.num_attention_heads) == (512, 12, 8)
    assert text.vocab_size == RD64_VOCAB_SIZE
    assert config.projection_dim == 512 and config.reduce_dim == 64
    assert list(config.extract_layers) == [3, 6, 9]
    assert config.use_complex_transposed_convolution and config.conditional_layer == 0
    assert (config.decoder_num_attention_heads, config.decoder_intermediate_size) == (4, 2048)
    assert max(vocab.values()) < RD64_VOCAB_SIZE
