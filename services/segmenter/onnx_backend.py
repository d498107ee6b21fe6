"""CLIPSeg on ONNX Runtime: our own export of the split model, the vision encoder quantised to int8.

The export is of the same split the torch fast path runs (``clipseg.py``), at the fixed 352 px
input and batch 1:

    encoder.onnx   pixel_values (1, 3, 352, 352) -> reduced activations of the extract layers
                   (vision embeddings, encoder layers 0..max(extract_layers), decoder ``reduces``)
                   -> ONNX Runtime's basic graph passes (constant folding) without MatMulAddFusion
                   -> the transformer optimizer (model type ``clip``): fused Attention,
                      SkipLayerNormalization and QuickGelu nodes
                   -> dynamic int8 quantisation of the weights of MatMul and Attention
                      (QAttention, then DynamicQuantizeMatMul at session start), per channel, with
                      7-bit weights; activations quantised per run; LayerNorm, softmax, GELU and
                      the patch convolution stay fp32
    decoder.onnx   reduced activations + text embeddings (P, projection) -> logits (P, 352, 352),
                   P a dynamic axis, kept in fp32 (small matrices, and the logits' last layers)

Why each step (measured on 2 AVX2 cores of an AMD EPYC, loaded, ratios in one run):
- The attention is traced in its eager form (``_eager_attention``): the SDPA form exports a
  pattern the optimizer does not recognise, and so does the ``vit`` model type. ORT's
  MatMulAddFusion, which the optimizer runs first by default (its ``opt_level`` 1), turns every
  3-D Linear into Reshape-Gemm-Reshape and hides the pattern too. Together they took the encoder
  from 0 to 10 fused Attention nodes of 10. `export.json` in the cache folder keeps the fused
  and quantised node counts, and the export logs a warning when attention did not fuse.
- 7-bit weights (``reduce_range``): without VNNI, ORT's AVX2 u8s8 kernel adds pairs of u8 x s8
  products in int16 (vpmaddubsw), which saturates with 8-bit weights; the encoder's outputs
  differed from fp32 by 10.0 % of their range with 8-bit weights, 4.6 % with 7-bit, 2.5 % with
  7-bit per channel and the patch convolution left in fp32, at the same speed (~0.72 CPU s).
- The decoder runs one prompt per call (`DECODER_PROMPTS_PER_RUN`): its 485 x 2048 MLP
  activations then stay in cache; 0.28 CPU s per frame of 13 prompts against 0.38 all at once.
  The prompts run on parallel single-threaded calls (one per thread) rather than one call
  after another on two threads: the decoder's ops are small, and splitting each across threads
  cost a synchronisation per op (0.37 -> 0.33 s wall, 0.38 -> 0.33 CPU s, 14 rounds, loaded).
  An int8 decoder (MatMul weights, per channel, 7-bit) saved 0.03 of 0.27 CPU s but moved
  logits by 2.1 % of their range, and a decoder exported for a fixed single prompt (its shape
  arithmetic folded) ran no faster: neither is done.
- Not faster here: MatMulNBits weight-only int8/int4 (2-3x slower than DynamicQuantizeMatMul on
  a 485 x 768 x 3072 MLP), torch's own dynamic int8 Linear (fbgemm; the encoder took 2x the CPU
  time of this one), ORT fp32 with the same fusions (1.14 CPU s for the encoder vs 0.72 int8).
  The int8 kernel itself is the limit: DynamicQuantizeMatMul ran ~1.8x the fp32 MatMul's rate.

The text tower and the processor stay in torch (once per prompt set / cheap). The files are
written once per model into a cache folder named by a digest of the weights, so the next start
loads them in a second; ``OnnxClipSeg`` is a ``ClipSegBackend`` whose forward runs the two
sessions, so the checks, text cache, fusion and resize are the torch backend's own.

ONNX Runtime's worker threads spin after each run by default; on a CPU shared with the torch
text tower (and, on a ground station, other services) that steals the cores, so spinning is off
(with the machine loaded, spinning made the encoder 0.93 s against 0.72 s).
Needs the ``onnx`` extra (onnxruntime, onnx). Imported only when this variant is built.
"""

from __future__ import annotations

import collections
import concurrent.futures
import hashlib
import json
import logging
import os
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnxruntime.quantization import QuantType, quantize_dynamic

from .clipseg import ClipSegBackend

LOG = logging.getLogger(__name__)

EXPORT_VERSION = 2  # part of the cache key: bump when the exported graph changes
OPSET = 17
FRAME_PX = 352
DECODER_PROMPTS_PER_RUN = 1  # see the module docstring
# Ops whose weights are quantised: QAttention and DynamicQuantizeMatMul have AVX2 int8 kernels;
# the patch embedding's ConvInteger was slower than the fp32 convolution and less exact.
QUANTIZED_OPS = ("MatMul", "Attention")
FUSED_OPS = ("Attention", "SkipLayerNormalization", "QuickGelu")
EXPORT_INFO = "export.json"


def default_cache_dir() -> Path:
    """Where exports are kept: $XDG_CACHE_HOME/dovesei/onnx (default ~/.cache/dovesei/onnx)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "dovesei" / "onnx"


def weights_digest(base: ClipSegBackend) -> str:
    """A digest of the model's weights and split: same digest, same exported graphs."""
    digest = hashlib.sha256(f"v{EXPORT_VERSION} ort{ort.__version__} {base.extract_layers}".encode())
    for name, tensor in base._model.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().float().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


class _Encoder(torch.nn.Module):
    def __init__(self, base: ClipSegBackend) -> None:
        super().__init__()
        self.base = base
        self.model = base._model  # registered, so export sees the parameters

    def forward(self, pixel_values: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.base._reduce(self.base._encode_image(pixel_values)))


class _Decoder(torch.nn.Module):
    def __init__(self, base: ClipSegBackend) -> None:
        super().__init__()
        self.base = base
        self.model = base._model

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        *reduced, text_embeddings = inputs
        return self.base._decode(list(reduced), text_embeddings)[0]


def op_counts(path: Path) -> dict[str, int]:
    """How many nodes of each op type the ONNX graph at ``path`` has, most frequent first."""
    graph = onnx.load(str(path), load_external_data=False).graph
    return dict(collections.Counter(node.op_type for node in graph.node).most_common())


@contextmanager
def _eager_attention(model) -> Iterator[None]:
    """Trace the attention as explicit MatMul/Softmax (the pattern the optimizer fuses), then put
    back the implementation the torch path runs with."""
    configs = [model.config, *(getattr(model.config, name, None) for name in ("text_config", "vision_config"))]
    saved = [(config, config._attn_implementation) for config in configs if config is not None]
    model.config._attn_implementation = "eager"  # the setter recurses into the sub-configs
    try:
        yield
    finally:
        for config, implementation in saved:  # parent first: its setter would overwrite the children
            config._attn_implementation = implementation


def _fold_without_matmul_add(source: Path, target: Path) -> None:
    """ORT's basic passes (constant folding of the traced shape arithmetic), minus MatMulAddFusion."""
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    options.optimized_model_filepath = str(target)
    ort.InferenceSession(str(source), options, providers=["CPUExecutionProvider"],
                         disabled_optimizers=["MatMulAddFusion"])


class _QuantizerChatter(logging.Filter):
    """Drops the quantizer's per-tensor INFO lines (it logs on the root logger, ~90 per export)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.name == "root" and record.levelno <= logging.INFO and "onnxruntime" in record.pathname)


def export_split(base: ClipSegBackend, out_dir: Path, *, optimize: bool = True) -> tuple[Path, Path]:
    """Write encoder_int8.onnx and decoder.onnx for ``base`` into ``out_dir``; returns their paths.

    Also writes ``export.json``: the fused and quantised node counts and the export time."""
    out_dir.mkdir(parents=True, exist_ok=True)
    encoder_fp32, encoder_int8, decoder = out_dir / "encoder.onnx", out_dir / "encoder_int8.onnx", out_dir / "decoder.onnx"
    n_out = len(base.extract_layers)
    start_s = time.perf_counter()
    pixel_values = torch.zeros(1, 3, FRAME_PX, FRAME_PX)
    # not inference_mode: the exporter traces through autograd-aware ops. The tracer's warnings
    # (shapes taken as constants) are expected: the graph is exported for the fixed 352 px input.
    with torch.no_grad(), warnings.catch_warnings(), _eager_attention(base._model):
        warnings.simplefilter("ignore")
        reduced = _Encoder(base)(pixel_values)
        text = torch.zeros(2, base._model.config.projection_dim)
        torch.onnx.export(_Encoder(base), (pixel_values,), str(encoder_fp32), dynamo=False, opset_version=OPSET,
                          input_names=["pixel_values"], output_names=[f"reduced{i}" for i in range(n_out)])
        torch.onnx.export(_Decoder(base), (*reduced, text), str(decoder), dynamo=False, opset_version=OPSET,
                          input_names=[*(f"reduced{i}" for i in range(n_out)), "text_embeddings"],
                          output_names=["logits"], dynamic_axes={"text_embeddings": {0: "prompts"},
                                                                 "logits": {0: "prompts"}})
    to_quantize = encoder_fp32
    folded, optimized = out_dir / "encoder_folded.onnx", out_dir / "encoder_optimized.onnx"
    fused: dict[str, int] = {}
    if optimize:
        from onnxruntime.transformers.optimizer import optimize_model

        _fold_without_matmul_add(encoder_fp32, folded)
        vision = base._model.config.vision_config
        # opt_level 0: the basic passes ran above, without the MatMulAddFusion that hides attention.
        model = optimize_model(str(folded), model_type="clip", num_heads=vision.num_attention_heads,
                               hidden_size=vision.hidden_size, opt_level=0)
        model.save_model_to_file(str(optimized))
        to_quantize = optimized
        statistics = model.get_fused_operator_statistics()
        fused = {op: int(statistics.get(op, 0)) for op in FUSED_OPS}
        if fused["Attention"] < base.encoder_depth:
            LOG.warning("ONNX export: attention fused in %d of %d encoder layers (the rest run unfused, slower)",
                        fused["Attention"], base.encoder_depth)
    # The optimizer's fused nodes (com.microsoft domain) defeat the quantizer's shape inference;
    # every weight here is float32, so say so.
    chatter = _QuantizerChatter()
    logging.getLogger().addFilter(chatter)
    try:
        quantize_dynamic(str(to_quantize), str(encoder_int8), weight_type=QuantType.QInt8, per_channel=True,
                         reduce_range=True, op_types_to_quantize=list(QUANTIZED_OPS),
                         extra_options={"DefaultTensorType": onnx.TensorProto.FLOAT})
    finally:
        logging.getLogger().removeFilter(chatter)
    # Only the int8 encoder and the decoder are served; the fp32 intermediates are ~0.7 GB for rd64.
    for intermediate in {encoder_fp32, folded, to_quantize}:
        intermediate.unlink(missing_ok=True)
    export_s = time.perf_counter() - start_s
    info = {"export_version": EXPORT_VERSION, "export_s": round(export_s, 1), "encoder_layers": base.encoder_depth,
            "fused": fused, "encoder_int8_ops": op_counts(encoder_int8)}
    (out_dir / EXPORT_INFO).write_text(json.dumps(info, indent=1) + "\n")
    LOG.info("exported the split CLIPSeg to ONNX in %.1f s (%s): fused %s", export_s, out_dir, fused)
    return encoder_int8, decoder


def export_info(folder: Path) -> dict[str, object]:
    """The ``export.json`` of an export folder ({} when missing or unreadable: an older export)."""
    try:
        return json.loads((folder / EXPORT_INFO).read_text())
    except (OSError, ValueError):
        return {}


def _session(path: Path, threads: int | None) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.intra_op_num_threads = threads or torch.get_num_threads()
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def export_folder(base: ClipSegBackend, cache_dir: Path | None = None) -> Path:
    return (cache_dir or default_cache_dir()) / weights_digest(base)


def is_exported(base: ClipSegBackend, cache_dir: Path | None = None) -> bool:
    """True when the export of these weights is in the cache (building the variant is then quick)."""
    folder = export_folder(base, cache_dir)
    return (folder / "encoder_int8.onnx").is_file() and (folder / "decoder.onnx").is_file()


class OnnxClipSeg(ClipSegBackend):
    """The ONNX int8 variant of a loaded fp32 ``ClipSegBackend`` (shares its torch model for texts)."""

    def __init__(self, base: ClipSegBackend, *, cache_dir: Path | None = None, threads: int | None = None) -> None:
        super().__init__(base._model, base._processor, model_id=base.model_id, device="cpu", dtype="float32")
        self.dtype = "onnx-int8"  # what describe() and the heatmap logs name
        folder = export_folder(base, cache_dir)
        encoder, decoder = folder / "encoder_int8.onnx", folder / "decoder.onnx"
        if encoder.is_file() and decoder.is_file():
            LOG.info("ONNX export found in %s", folder)
        else:
            encoder, decoder = export_split(base, folder)
        self.export = export_info(folder)
        n_threads = threads or torch.get_num_threads()
        self._encoder = _session(encoder, n_threads)
        self._decoder = _session(decoder, 1)  # parallel across prompts instead (module docstring)
        self._decoder_pool = (concurrent.futures.ThreadPoolExecutor(n_threads, thread_name_prefix="onnx-decoder")
                              if n_threads > 1 else None)
        self._reduced_names = [o.name for o in self._encoder.get_outputs()]
        self._forward = self._forward_onnx

    def _forward_onnx(self, pixel_values: torch.Tensor, text_embeddings: torch.Tensor) -> torch.Tensor:
        logits = []
        text = text_embeddings.float().cpu().numpy()
        step = DECODER_PROMPTS_PER_RUN
        for frame in pixel_values.float().cpu().numpy():  # exported at batch 1
            reduced = dict(zip(self._reduced_names, self._encoder.run(None, {"pixel_values": frame[None]})))

            def decode(start: int, reduced: dict[str, np.ndarray] = reduced) -> np.ndarray:
                return self._decoder.run(None, {**reduced, "text_embeddings": text[start : start + step]})[0]

            starts = range(0, len(text), step)
            # ONNX Runtime releases the GIL in run(), so the calls use the cores in parallel.
            per_prompt = list(self._decoder_pool.map(decode, starts) if self._decoder_pool else map(decode, starts))
            logits.append(np.concatenate(per_prompt))
        return torch.from_numpy(np.stack(logits))
