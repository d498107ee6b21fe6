"""CLIPSeg backend: camera frame + prompt set -> per-prompt logits -> per-pixel P(safe).

The stock way to run CLIPSeg on P prompts (what the reference did) is one
``CLIPSegForImageSegmentation`` forward on P copies of the image: the ViT-B/16 vision tower runs
P times on the same pixels, all 12 layers deep, and the text tower re-encodes every prompt on
every frame. This backend computes the same numbers with much less work:

    image (H, W, 3) uint8
      -> processor (resize to 352 x 352, normalise)              once per frame
      -> vision embeddings + pre-layernorm + encoder layers 0..max(extract_layers)
         (the decoder reads only those layer outputs; the deeper layers and the pooled head
         are never computed)                                     once per frame
      -> decoder: ``reduces[i](activation)`` once per frame, then FiLM with every prompt's
         text embedding and the decoder layers for all P prompts as one batch
      -> logits (P, 352, 352)
    prompts -> tokenizer -> text tower -> projection              once per prompt set (cached)

``safe_probability`` fuses the logits (see ``fusion.py``) and resizes the result bilinearly back
to the input frame's size. The decoder modules and encoder layers are the model's own, called in
the stock order, so fp32 results equal the stock forward to float rounding (batched matrix
products may round differently; tests hold them to 1e-4).

The decoder head's two stride-4 transposed convolutions run as matrix products (their output
blocks do not overlap), and the decoder takes the prompts a few at a time (DEFAULT_DECODER_CHUNK).

Measured on 2 shared Cascade Lake cores (``dovesei bench-segmenter --random-weights``, rd64
architecture, 13 prompts): fast path 0.61-0.64 s/frame vs 9-15 s for the stock forward, max
|diff| 1.2e-5 on a logit range of 35. This CPU has no bf16 or AMX instructions: bfloat16 ran
3-10x slower than float32 and differs from the fp32 stock forward by 0.41 logits (1.2 % of the
range). torch.compile took 70-106 s to compile and was not faster (two runs, both with other
jobs on the machine). Both stay options for GPUs and bf16-capable CPUs; the default is
float32, eager.
The service runs this backend, or a variant built from it (bf16 with native BF16, ONNX Runtime
int8, CUDA fp16: ``backends.py``), picked at start by measurement behind a decision gate
(``picker.py``, ``gate.py``).

Nothing is loaded at import: ``load_clipseg`` is the factory. It takes a Hub id or a local
directory through the same ``from_pretrained`` calls, so real weights and the random-weight
directories of ``random_model.py`` follow one path.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from .fusion import FusionConfig, fuse_with
from .options import DEFAULT_MODEL, DTYPES
from .prompts import PromptError, PromptSet

LOG = logging.getLogger(__name__)

# Prompts per decoder batch. The decoder MLP expands 64 -> 2048 channels on 485 tokens per
# prompt: 13 prompts at once make a 51 MB activation that streams through memory, 4 at a time
# stays in cache. Measured on 2 Cascade Lake cores: 0.19 s (4) vs 0.34 s (all 13) per frame.
DEFAULT_DECODER_CHUNK = 4
# Frame sides outside this range are refused before they reach the processor.
MIN_IMAGE_SIDE_PX = 8
MAX_IMAGE_SIDE_PX = 8192


class ModelUnavailableError(RuntimeError):
    """The CLIPSeg weights or processor files could not be found or opened."""


class ImageError(ValueError):
    """A frame is not an (H, W, 3) uint8 RGB image of a usable size."""


def _looks_like_path(model: str) -> bool:
    """True for explicit paths and for anything that exists on disk; Hub ids are "owner/name"."""
    return model.startswith((".", "/", "~")) or Path(model).expanduser().exists()


def _unavailable_message(model: str, reason: str) -> str:
    offline = os.environ.get("HF_HUB_OFFLINE", "") not in ("", "0", "false", "False")
    return (
        f"CLIPSeg model {model!r} is not available: {reason}. "
        f"It was looked for as a local directory and as a Hugging Face Hub model id in the local cache. "
        f"This machine may be offline (HF_HUB_OFFLINE={'1' if offline else 'unset'}; without network the "
        f"weights can only come from the cache or a local directory). On a connected machine run "
        f"`huggingface-cli download {DEFAULT_MODEL} --local-dir /path/to/clipseg-rd64-refined`, copy that "
        f"directory here and pass `--model /path/to/clipseg-rd64-refined`."
    )


def _check_image(image_rgb: np.ndarray, where: str = "image_rgb") -> np.ndarray:
    if not isinstance(image_rgb, np.ndarray):
        raise ImageError(f"{where}: expected a numpy array, got {type(image_rgb).__name__}")
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise ImageError(f"{where}: expected shape (H, W, 3), got {image_rgb.shape}")
    if image_rgb.dtype != np.uint8:
        raise ImageError(f"{where}: expected dtype uint8, got {image_rgb.dtype}")
    height_px, width_px = image_rgb.shape[:2]
    if not (MIN_IMAGE_SIDE_PX <= min(height_px, width_px) and max(height_px, width_px) <= MAX_IMAGE_SIDE_PX):
        raise ImageError(
            f"{where}: size {width_px}x{height_px} px outside [{MIN_IMAGE_SIDE_PX}, {MAX_IMAGE_SIDE_PX}] per side"
        )
    return image_rgb


def _is_block_upsampler(head) -> bool:
    """True for the rd64-refined head: Conv3x3, ReLU, ConvT(k=s), ReLU, ConvT(k=s) to 1 channel,
    whose transposed convolutions can run as matrix products (see ``_upsample_matmul``)."""
    if not isinstance(head, torch.nn.Sequential) or len(head) != 5:
        return False
    upsamplers = (head[2], head[4])
    return (
        isinstance(head[0], torch.nn.Conv2d)
        and isinstance(head[1], torch.nn.ReLU)
        and isinstance(head[3], torch.nn.ReLU)
        and all(
            isinstance(up, torch.nn.ConvTranspose2d)
            and up.kernel_size[0] == up.kernel_size[1] == up.stride[0] == up.stride[1]
            and up.padding == (0, 0)
            and up.output_padding == (0, 0)
            and up.dilation == (1, 1)
            and up.groups == 1
            and up.bias is not None
            for up in upsamplers
        )
        and head[4].out_channels == 1
    )


@dataclass
class _TextCache:
    prompts: PromptSet
    embeddings: torch.Tensor  # (P, projection_dim), on the model's device and dtype


class ClipSegBackend:
    """CLIPSeg with a shared vision pass and cached text embeddings (see the module docstring).

    Build it with ``load_clipseg``. Not thread-safe: one backend serves one inference loop.
    """

    name = "clipseg"

    def __init__(
        self,
        model,
        processor,
        *,
        model_id: str,
        device: str,
        dtype: str,
        compile: bool = False,
        decoder_chunk: int | None = DEFAULT_DECODER_CHUNK,
    ) -> None:
        self.model_id = model_id
        self.device = torch.device(device)
        self.dtype = dtype
        self._torch_dtype = getattr(torch, dtype)
        self._model = model.eval()
        self._processor = processor
        config = model.config
        n_vision_layers = config.vision_config.num_hidden_layers
        self.extract_layers = tuple(int(i) for i in config.extract_layers)
        if not self.extract_layers or not all(0 <= i < n_vision_layers for i in self.extract_layers):
            raise ModelUnavailableError(
                f"CLIPSeg model {model_id!r} has extract_layers {self.extract_layers} outside its "
                f"{n_vision_layers} vision layers"
            )
        # The decoder reads the outputs of the extract layers only, so deeper layers are skipped.
        self.vision_layers = n_vision_layers
        self.encoder_depth = max(self.extract_layers) + 1
        self.max_text_tokens = int(config.text_config.max_position_embeddings)
        self._text_cache: _TextCache | None = None
        # How many times prompt texts went through the text tower; tests check the cache with it.
        self.text_encode_count = 0
        # Prompts per decoder batch (None: all at once); a speed knob only, results are the same.
        self.decoder_chunk = decoder_chunk
        self._upsample_as_matmul = _is_block_upsampler(model.decoder.transposed_convolution)
        self._forward = self._forward_eager
        if compile:
            # Static shapes: a new batch size or prompt count recompiles once, then is reused.
            self._forward = torch.compile(self._forward_eager, dynamic=False)
        LOG.info(
            "CLIPSeg %s on %s (%s%s): vision encoder %d of %d layers, extract layers %s",
            model_id,
            self.device,
            dtype,
            ", torch.compile" if compile else "",
            self.encoder_depth,
            n_vision_layers,
            list(self.extract_layers),
        )

    # -- inputs ---------------------------------------------------------------------------------

    def _pixel_values(self, images: Sequence[np.ndarray]) -> torch.Tensor:
        batch = self._processor.image_processor(
            images=list(images), return_tensors="pt", input_data_format="channels_last"
        )
        return batch["pixel_values"].to(self.device, self._torch_dtype)

    def text_embeddings(self, prompts: PromptSet) -> torch.Tensor:
        """Projected text embeddings (P, projection_dim) of ``prompts.texts()``, cached per set."""
        if not isinstance(prompts, PromptSet):
            raise PromptError(f"prompts: expected a PromptSet, got {type(prompts).__name__}")
        cache = self._text_cache
        if cache is not None and cache.prompts == prompts:
            return cache.embeddings
        tokens = self._processor.tokenizer(list(prompts.texts()), padding=True, return_tensors="pt")
        n_tokens = tokens["input_ids"].shape[1]
        if n_tokens > self.max_text_tokens:
            raise PromptError(
                f"prompts: a templated prompt is {n_tokens} tokens long, the text encoder takes at most "
                f"{self.max_text_tokens}; shorten the prompt or the template"
            )
        with torch.inference_mode():
            embeddings = self._model.clip.get_text_features(
                input_ids=tokens["input_ids"].to(self.device),
                attention_mask=tokens["attention_mask"].to(self.device),
            ).pooler_output
        self.text_encode_count += 1
        self._text_cache = _TextCache(prompts=prompts, embeddings=embeddings)
        LOG.info("text embeddings rebuilt for prompt set %s (%d prompts)", prompts.set_id, prompts.n_prompts)
        return embeddings

    # -- the fast forward -----------------------------------------------------------------------

    def _encode_image(self, pixel_values: torch.Tensor) -> list[torch.Tensor]:
        """Outputs of the extract layers, in ``extract_layers`` order, each (N, tokens, hidden).

        Same as ``vision_model(..., output_hidden_states=True).hidden_states[i + 1]``: index 0
        of the stock hidden states is the pre-layernormed embedding, index i + 1 the output of
        encoder layer i (no post-layernorm; that only feeds the pooled head).
        """
        vision = self._model.clip.vision_model
        hidden = vision.embeddings(pixel_values, interpolate_pos_encoding=True)
        hidden = vision.pre_layrnorm(hidden)
        wanted = set(self.extract_layers)
        layer_outputs: dict[int, torch.Tensor] = {}
        for index in range(self.encoder_depth):
            hidden = vision.encoder.layers[index](hidden, None)
            if index in wanted:
                layer_outputs[index] = hidden
        return [layer_outputs[i] for i in self.extract_layers]

    def _reduce(self, activations: list[torch.Tensor]) -> list[torch.Tensor]:
        """The decoder's ``reduces`` projections (hidden -> reduce_dim), deepest layer first.

        They do not depend on the prompt, so they run once per frame, not once per prompt.
        """
        decoder = self._model.decoder
        return [reduce(activation) for activation, reduce in zip(activations[::-1], decoder.reduces)]

    def _decode(self, reduced: list[torch.Tensor], text_embeddings: torch.Tensor) -> torch.Tensor:
        """Logits (N, P, 352, 352) from the reduced activations (N, tokens, R) and P text embeddings.

        Mirrors ``CLIPSegDecoder.forward`` with the batch split as (frame, prompt): tensors that
        do not depend on the prompt yet (before FiLM) keep a prompt axis of 1 and broadcast.
        """
        decoder = self._model.decoder
        n_frames = reduced[0].shape[0]
        n_prompts = text_embeddings.shape[0]
        # (1, P, 1, R): broadcast over frames and tokens, like the stock (T, B, R) permute.
        film_mul = decoder.film_mul(text_embeddings)[None, :, None, :]
        film_add = decoder.film_add(text_embeddings)[None, :, None, :]
        output = None  # (N, 1 before FiLM or P after, tokens, reduce_dim)
        for index, (frame_term, layer) in enumerate(zip(reduced, decoder.layers)):
            frame_term = frame_term[:, None]
            output = frame_term if output is None else frame_term + output
            if index == decoder.conditional_layer:
                output = film_mul * output + film_add
            n_group, n_tokens, reduce_dim = output.shape[1:]
            output = layer(output.reshape(n_frames * n_group, n_tokens, reduce_dim), None)
            output = output.reshape(n_frames, n_group, n_tokens, reduce_dim)
        if output.shape[1] != n_prompts:
            # Only when FiLM never ran (conditional_layer beyond the decoder depth).
            output = output.expand(n_frames, n_prompts, *output.shape[2:])
        n_tokens, reduce_dim = output.shape[2:]
        # Drop the class token, then tokens -> a square patch grid for the transposed convolutions.
        grid = output.reshape(n_frames * n_prompts, n_tokens, reduce_dim)[:, 1:, :].transpose(1, 2)
        # int(): under ONNX tracing shapes are tensors; the grid side is fixed by the 352 px input.
        side = math.isqrt(int(n_tokens) - 1)
        grid = grid.reshape(n_frames * n_prompts, reduce_dim, side, side)
        if self._upsample_as_matmul:
            logits = self._upsample_matmul(grid)
        else:
            logits = decoder.transposed_convolution(grid).squeeze(1)
        return logits.reshape(n_frames, n_prompts, *logits.shape[1:])

    def _upsample_matmul(self, grid: torch.Tensor) -> torch.Tensor:
        """The complex transposed-convolution head, (B, R, s, s) -> (B, 16 s, 16 s).

        Conv3x3 + ReLU runs as the stock module. The two ConvTranspose2d have stride equal to
        their kernel, so their output blocks do not overlap: each input pixel's channel vector
        times a (C_in, k*k*C_out) matrix gives its k x k output block. One matrix product plus a
        block rearrangement, channels last, is several times faster on CPU than the generic
        transposed-convolution kernel and sums the same products.
        """
        head = self._model.decoder.transposed_convolution
        conv3x3, relu, upsample_1, _, upsample_2 = head
        hidden = relu(conv3x3(grid)).permute(0, 2, 3, 1)  # (B, s, s, C) channels last
        for upsample in (upsample_1, upsample_2):
            n_batch, height, width, c_in = hidden.shape
            kernel = upsample.kernel_size[0]
            c_out = upsample.out_channels
            # ConvTranspose2d weight is (C_in, C_out, kh, kw); reorder columns as (kh, kw, C_out).
            weight = upsample.weight.permute(0, 2, 3, 1).reshape(c_in, kernel * kernel * c_out)
            blocks = torch.matmul(hidden, weight).reshape(n_batch, height, width, kernel, kernel, c_out)
            hidden = blocks.permute(0, 1, 3, 2, 4, 5).reshape(n_batch, height * kernel, width * kernel, c_out)
            hidden = hidden + upsample.bias
            if upsample is upsample_1:
                hidden = torch.relu(hidden)
        return hidden[..., 0]

    def _forward_eager(self, pixel_values: torch.Tensor, text_embeddings: torch.Tensor) -> torch.Tensor:
        reduced = self._reduce(self._encode_image(pixel_values))
        n_prompts = text_embeddings.shape[0]
        chunk = self.decoder_chunk or n_prompts
        if chunk >= n_prompts:
            return self._decode(reduced, text_embeddings)
        # Smaller decoder batches keep the (prompts x tokens x 2048) MLP activations in cache.
        parts = [self._decode(reduced, text_embeddings[s : s + chunk]) for s in range(0, n_prompts, chunk)]
        return torch.cat(parts, dim=1)

    def logits_batch(self, images: Sequence[np.ndarray], prompts: PromptSet) -> np.ndarray:
        """Logits (N, P, 352, 352) float32 for N frames, prompts in ``prompts.texts()`` order."""
        if isinstance(images, np.ndarray) or len(images) == 0:
            raise ImageError("images: expected a non-empty sequence of (H, W, 3) uint8 arrays")
        checked = [_check_image(image, f"images[{i}]") for i, image in enumerate(images)]
        text_embeddings = self.text_embeddings(prompts)
        pixel_values = self._pixel_values(checked)
        with torch.inference_mode():
            logits = self._forward(pixel_values, text_embeddings)
        return logits.float().cpu().numpy()

    def logits(self, image_rgb: np.ndarray, prompts: PromptSet) -> np.ndarray:
        """Logits (P, 352, 352) float32 for one frame."""
        return self.logits_batch([image_rgb], prompts)[0]

    def safe_probability(
        self, image_rgb: np.ndarray, prompts: PromptSet, fusion: FusionConfig | str = FusionConfig()
    ) -> np.ndarray:
        """P(safe) (H, W) float32 in [0, 1] at the input frame's size."""
        config = FusionConfig(mode=fusion) if isinstance(fusion, str) else fusion
        prob_model_px = fuse_with(self.logits(image_rgb, prompts), prompts.n_positive, config)
        height_px, width_px = image_rgb.shape[:2]
        if (height_px, width_px) == prob_model_px.shape:
            return prob_model_px
        # Bilinear, as the reference's cv2.resize actually ran (its INTER_AREA sat in the dst slot).
        prob = cv2.resize(prob_model_px, (width_px, height_px), interpolation=cv2.INTER_LINEAR)
        return np.clip(prob, 0.0, 1.0, out=prob)

    # -- the stock forward, for equivalence tests and the benchmark ------------------------------

    def reference_logits(self, image_rgb: np.ndarray, prompts: PromptSet) -> np.ndarray:
        """Logits (P, 352, 352) the way the reference computed them: one stock forward on P
        copies of the frame, every prompt re-tokenised and re-encoded. Slow on purpose."""
        _check_image(image_rgb)
        texts = list(prompts.texts())
        inputs = self._processor(text=texts, images=[image_rgb] * len(texts), padding=True, return_tensors="pt")
        inputs = {key: value.to(self.device) for key, value in inputs.items()}
        with torch.inference_mode():
            logits = self._model(**inputs).logits
        return logits.float().cpu().numpy().reshape(len(texts), *logits.shape[-2:])


def load_clipseg(
    model: str = DEFAULT_MODEL,
    device: str = "cpu",
    dtype: str = "float32",
    compile: bool = False,
    threads: int | None = None,
    decoder_chunk: int | None = DEFAULT_DECODER_CHUNK,
) -> ClipSegBackend:
    """Load CLIPSeg weights and processor (Hub id or local directory) into a ClipSegBackend.

    ``threads`` sets torch's intra-op thread count for the whole process (None leaves torch's
    default). ``decoder_chunk`` is how many prompts the decoder runs per batch (None: all; a
    speed knob with the same results, see DEFAULT_DECODER_CHUNK). Raises ModelUnavailableError
    when the files cannot be found or opened, ValueError on a bad option.
    """
    from transformers import CLIPSegForImageSegmentation, CLIPSegProcessor

    if dtype not in DTYPES:
        raise ValueError(f"dtype: expected one of {DTYPES}, got {dtype!r}")
    try:
        torch_device = torch.device(device)
    except RuntimeError as exc:
        raise ValueError(f"device: {exc}") from exc
    for name, value in (("threads", threads), ("decoder_chunk", decoder_chunk)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name}: expected None or an integer >= 1, got {value!r}")
    if threads is not None:
        torch.set_num_threads(threads)
    model = str(model)
    if _looks_like_path(model) and not Path(model).expanduser().is_dir():
        # A path that does not exist would otherwise be reported as an invalid Hub id.
        raise ModelUnavailableError(_unavailable_message(model, "no such local directory"))
    source = str(Path(model).expanduser()) if _looks_like_path(model) else model
    try:
        processor = CLIPSegProcessor.from_pretrained(source)
        net = CLIPSegForImageSegmentation.from_pretrained(source, dtype=getattr(torch, dtype))
    except (OSError, ValueError) as exc:
        # transformers reports missing files and offline misses as OSError, bad ids as ValueError.
        raise ModelUnavailableError(_unavailable_message(model, f"{type(exc).__name__}: {exc}")) from exc
    net.to(torch_device)
    LOG.info(
        "loaded CLIPSeg from %s; torch %s, %d intra-op threads", source, torch.__version__, torch.get_num_threads()
    )
    return ClipSegBackend(
        net,
        processor,
        model_id=model,
        device=str(torch_device),
        dtype=dtype,
        compile=compile,
        decoder_chunk=decoder_chunk,
    )
