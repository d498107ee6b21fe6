"""CLIPSeg on ONNX Runtime: our own export of the split model, the vision encoder quantised to int8.

The export is of the same split the torch fast path runs (``clipseg.py``), at the fixed 352 px
input and batch 1:

    encoder.onnx   pixel_values (1, 3, 352, 352) -> reduced activations of the extract layers
                   (vision embeddings, encoder layers 0..max(extract_layers), decoder ``reduces``)
                   -> ONNX Runtime transformer optimizer (fused attention / layer norm / GELU)
                   -> dynamic int8 quantisation of the weights (activations quantised per run)
    decoder.onnx   reduced activations + text embeddings (P, projection) -> logits (P, 352, 352),
                   P a dynamic axis, kept in fp32 (small matrices, and the logits' last layers)

The text tower and the processor stay in torch (once per prompt set / cheap). The files are
written once per model into a cache folder named by a digest of the weights, so the next start
loads them in a second; ``OnnxClipSeg`` is a ``ClipSegBackend`` whose forward runs the two
sessions, so the checks, text cache, fusion and resize are the torch backend's own.

ONNX Runtime's worker threads spin after each run by default; on a CPU shared with the torch
text tower (and, on a ground station, other services) that steals the cores, so spinning is off.
Needs the ``onnx`` extra (onnxruntime, onnx). Imported only when this variant is built.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnxruntime.quantization import QuantType, quantize_dynamic

from .clipseg import ClipSegBackend

LOG = logging.getLogger(__name__)

EXPORT_VERSION = 1  # part of the cache key: bump when the exported graph changes
OPSET = 17
FRAME_PX = 352


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


def export_split(base: ClipSegBackend, out_dir: Path, *, optimize: bool = True) -> tuple[Path, Path]:
    """Write encoder_int8.onnx and decoder.onnx for ``base`` into ``out_dir``; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    encoder_fp32, encoder_int8, decoder = out_dir / "encoder.onnx", out_dir / "encoder_int8.onnx", out_dir / "decoder.onnx"
    n_out = len(base.extract_layers)
    start_s = time.perf_counter()
    pixel_values = torch.zeros(1, 3, FRAME_PX, FRAME_PX)
    # not inference_mode: the exporter traces through autograd-aware ops. The tracer's warnings
    # (shapes taken as constants) are expected: the graph is exported for the fixed 352 px input.
    with torch.no_grad(), warnings.catch_warnings():
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
    if optimize:
        from onnxruntime.transformers.optimizer import optimize_model

        vision = base._model.config.vision_config
        optimized = out_dir / "encoder_optimized.onnx"
        model = optimize_model(str(encoder_fp32), model_type="vit", num_heads=vision.num_attention_heads,
                               hidden_size=vision.hidden_size)
        model.save_model_to_file(str(optimized))
        to_quantize = optimized
    # The optimizer's fused nodes (com.microsoft domain) defeat the quantizer's shape inference;
    # every weight here is float32, so say so.
    quantize_dynamic(str(to_quantize), str(encoder_int8), weight_type=QuantType.QInt8,
                     extra_options={"DefaultTensorType": onnx.TensorProto.FLOAT})
    # Only the int8 encoder and the decoder are served; the fp32 intermediates are ~0.7 GB for rd64.
    for intermediate in {encoder_fp32, to_quantize}:
        intermediate.unlink(missing_ok=True)
    LOG.info("exported the split CLIPSeg to ONNX in %.1f s (%s)", time.perf_counter() - start_s, out_dir)
    return encoder_int8, decoder


def _session(path: Path, threads: int | None) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.intra_op_num_threads = threads or torch.get_num_threads()
    options.inter_op_num_threads = 1
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
        self._encoder = _session(encoder, threads)
        self._decoder = _session(decoder, threads)
        self._reduced_names = [o.name for o in self._encoder.get_outputs()]
        self._forward = self._forward_onnx

    def _forward_onnx(self, pixel_values: torch.Tensor, text_embeddings: torch.Tensor) -> torch.Tensor:
        logits = []
        text = text_embeddings.float().cpu().numpy()
        for frame in pixel_values.float().cpu().numpy():  # exported at batch 1
            reduced = self._encoder.run(None, {"pixel_values": frame[None]})
            feeds = dict(zip(self._reduced_names, reduced))
            feeds["text_embeddings"] = text
            logits.append(self._decoder.run(None, feeds)[0])
        return torch.from_numpy(np.stack(logits))
