"""The CLIPSeg variants the segmenter can run, each built from the loaded fp32 backend.

    fp32        the torch fast path in float32: exact (the gate's reference), always a candidate
    bf16        torch in bfloat16: a candidate only where the CPU has native BF16 (``cpu_features``
                and oneDNN agree); elsewhere it is emulated and several times slower
    onnx-int8   ONNX Runtime, int8 vision encoder (``onnx_backend``; needs the ``onnx`` extra)
    cuda-fp16   torch on a CUDA GPU in float16: a candidate only when torch sees a GPU

`build_variant(name, base)` returns a ClipSegBackend-like model or raises VariantUnavailable
naming why (no BF16 flags, no GPU, onnxruntime not installed): asking for one explicitly gives
that message as the error, `candidates()` lists what can be timed here with the reasons for the
rest. Picking among them by measurement is ``picker.py``.
"""

from __future__ import annotations

import copy
import logging

import torch

from . import cpu_features
from .clipseg import ClipSegBackend
from .options import CLIPSEG_VARIANTS

LOG = logging.getLogger(__name__)

VARIANTS = CLIPSEG_VARIANTS[1:]  # without "auto", which is the picker's
REFERENCE_VARIANT = "fp32"


class VariantUnavailable(RuntimeError):
    """A variant that cannot run on this host; the text says why."""


def onednn_bf16() -> bool | None:
    """torch's own answer to 'does oneDNN have bf16 kernels for this CPU', None if it cannot say."""
    probe = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    try:
        return bool(probe()) if probe is not None else None
    except RuntimeError:
        return None


def bf16_native() -> tuple[bool, str]:
    return cpu_features.native_bf16(cpu_features.cpu_flags(), onednn_bf16())


def cuda_available() -> tuple[bool, str]:
    if not torch.cuda.is_available():
        return False, f"no CUDA device (torch.cuda.is_available() is False; torch {torch.__version__})"
    return True, f"CUDA device {torch.cuda.get_device_name(0)}"


def _torch_copy(base: ClipSegBackend, device: str, dtype: torch.dtype, dtype_name: str) -> ClipSegBackend:
    # A copy: the fp32 model stays the gate's reference (and the text tower of onnx-int8).
    model = copy.deepcopy(base._model).to(device=device, dtype=dtype)
    return ClipSegBackend(model, base._processor, model_id=base.model_id, device=device, dtype=dtype_name,
                          decoder_chunk=base.decoder_chunk)


def build_variant(name: str, base: ClipSegBackend, *, threads: int | None = None) -> ClipSegBackend:
    """The variant `name` of the loaded fp32 backend `base`; VariantUnavailable says why not."""
    if name not in VARIANTS:
        raise VariantUnavailable(f"unknown CLIPSeg variant {name!r}, expected one of {VARIANTS}")
    if name == "fp32":
        return base
    if base.device.type != "cpu" or base.dtype != "float32":
        raise VariantUnavailable(f"variants are built from an fp32 CPU model, got {base.device} {base.dtype}")
    if name == "bf16":
        native, why = bf16_native()
        if not native:
            raise VariantUnavailable(f"bf16 refused: the CPU has no native BF16 ({why}); it would be emulated")
        return _torch_copy(base, "cpu", torch.bfloat16, "bfloat16")
    if name == "cuda-fp16":
        ok, why = cuda_available()
        if not ok:
            raise VariantUnavailable(f"cuda-fp16 refused: {why}")
        return _torch_copy(base, "cuda", torch.float16, "float16")
    try:
        from .onnx_backend import OnnxClipSeg
    except ImportError as exc:
        raise VariantUnavailable(f"onnx-int8 refused: ONNX Runtime is not installed "
                                 f"(pip install 'dovesei[onnx]'): {exc}") from None
    return OnnxClipSeg(base, threads=threads)


def candidates(base: ClipSegBackend, *, export: bool = False) -> tuple[list[str], dict[str, str]]:
    """(variants that can run here, {variant: why not} for the others), without building any.

    onnx-int8 counts only once its export is cached, unless `export`: the one-time export takes
    about a minute on two cores, which a service start (watched by `dovesei up`'s start-up
    timeout) should not pay unasked; `dovesei bench-segmenter` and `--variant onnx-int8` export.
    """
    runnable, refused = ["fp32"], {}
    native, why = bf16_native()
    (runnable.append("bf16") if native else refused.__setitem__("bf16", f"no native BF16 ({why})"))
    ok, why = cuda_available()
    (runnable.append("cuda-fp16") if ok else refused.__setitem__("cuda-fp16", why))
    try:
        from . import onnx_backend
    except ImportError:
        refused["onnx-int8"] = "ONNX Runtime not installed (pip install 'dovesei[onnx]')"
    else:
        if export or onnx_backend.is_exported(base):
            runnable.append("onnx-int8")
        else:
            refused["onnx-int8"] = ("not exported yet for these weights (one-time, about a minute: run "
                                    "`dovesei bench-segmenter --model <weights>` or start once with --variant onnx-int8)")
    return runnable, refused
