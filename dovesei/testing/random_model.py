"""Random-weight CLIPSeg model directories, for tests and the speed benchmark.

Real weights cannot be downloaded on the team's machines, yet the backend must be exercised
through the very loading path users take with ``CIDAS/clipseg-rd64-refined``. This module writes
a complete model directory (``config.json`` + safetensors weights from
``CLIPSegForImageSegmentation.save_pretrained``, and the tokenizer and image-processor files from
``CLIPSegProcessor.save_pretrained``) that ``load_clipseg(model=<dir>)`` opens like a download.

Two sizes:
- ``tiny``: a few hundred kilobytes (hidden 32, 4 vision layers, 2 text layers) for unit tests;
  its extract layers stop before the last vision layer so the truncated encoder is exercised.
- ``rd64``: the real rd64-refined architecture (ViT-B/16 vision tower, 512-wide text tower,
  reduce_dim 64, extract layers 3/6/9, complex transposed convolution) with random weights: the
  same FLOPs as the real model, so it times like it, but its outputs mean nothing.

The tokenizer is a CLIP byte-level BPE over a small vocabulary written here: every printable
ASCII character (alone and word-final), plus a merge chain for each word of the reference prompts
and template, so those words become few tokens and unknown words fall back to characters; anything
outside printable ASCII becomes the unknown token.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from dovesei.segmenter.prompts import REFERENCE_PROMPTS

LOG = logging.getLogger(__name__)

MODEL_SIZES = ("tiny", "rd64")
IMAGE_SIZE_PX = 352
# The rd64 tokenizer ids must fit the real vocabulary size so the text tower has its real shape.
RD64_VOCAB_SIZE = 49408
BOS_TOKEN = "<|startoftext|>"
EOS_TOKEN = "<|endoftext|>"
WORD_END = "</w>"
# Normalisation of the CIDAS image processor (ImageNet mean/std, 352x352, bilinear).
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
PIL_BILINEAR = 2
# Spread (standard deviation) given to the random models' logits, close to real CLIPSeg's.
TARGET_LOGIT_STD = 4.0


def _vocabulary_words(extra_text: str = "") -> list[str]:
    """Words (CLIP pre-tokenizer pieces) of the reference prompts, template and extra text."""
    text = " ".join(REFERENCE_PROMPTS.texts()) + " " + extra_text
    # The same split CLIP's pre-tokenizer makes: letter runs, single digits, punctuation runs.
    pieces = re.findall(r"[A-Za-z]+|[0-9]|[^\sA-Za-z0-9]+", text.lower())
    return sorted(set(pieces))


def build_tokenizer_files(extra_text: str = "") -> tuple[dict[str, int], list[tuple[str, str]]]:
    """Vocabulary (token -> id) and ranked merges of the small CLIP BPE tokenizer."""
    vocab: dict[str, int] = {}

    def add(token: str) -> None:
        if token not in vocab:
            vocab[token] = len(vocab)

    # Printable ASCII maps to itself under CLIP's byte-to-unicode table, so these are the
    # base symbols; each exists as a word-internal and a word-final ("</w>") token.
    for code in range(33, 127):
        add(chr(code))
        add(chr(code) + WORD_END)
    merges: list[tuple[str, str]] = []
    seen_merges: set[tuple[str, str]] = set()
    for word in _vocabulary_words(extra_text):
        symbols = list(word[:-1]) + [word[-1] + WORD_END]
        # A left-to-right chain: ((w o) r) d</w>. Chains of different words may share or
        # pre-empt merges; BPE then yields a few sub-word tokens, which is still deterministic.
        merged = symbols[0]
        for symbol in symbols[1:]:
            pair = (merged, symbol)
            merged = merged + symbol
            add(merged)
            if pair not in seen_merges:
                seen_merges.add(pair)
                merges.append(pair)
    # CLIP puts the special tokens last, so end-of-text has the highest id (the legacy pooling
    # rule of some checkpoints takes the argmax id as the end of the sentence).
    add(BOS_TOKEN)
    add(EOS_TOKEN)
    return vocab, merges


def _tiny_config(vocab_size: int, bos_id: int, eos_id: int):
    from transformers import CLIPSegConfig, CLIPSegTextConfig, CLIPSegVisionConfig

    text = CLIPSegTextConfig(
        vocab_size=vocab_size,
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=2,
        max_position_embeddings=77,
        bos_token_id=bos_id,
        eos_token_id=eos_id,
        pad_token_id=eos_id,
    )
    vision = CLIPSegVisionConfig(
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=4,
        num_attention_heads=2,
        image_size=IMAGE_SIZE_PX,
        patch_size=16,
    )
    # extract_layers (0, 2) of 4: index 0 checks the hidden-state offset (layer outputs, not
    # embeddings) and stopping at 2 checks that the fast path skips the last layer.
    return CLIPSegConfig(
        text_config=text.to_dict(),
        vision_config=vision.to_dict(),
        projection_dim=16,
        extract_layers=[0, 2],
        reduce_dim=16,
        decoder_num_attention_heads=2,
        decoder_intermediate_size=32,
        conditional_layer=0,
        use_complex_transposed_convolution=True,
    )


def _rd64_config(bos_id: int, eos_id: int):
    """The architecture of CIDAS/clipseg-rd64-refined (CLIP ViT-B/16 + rd64 refined decoder)."""
    from transformers import CLIPSegConfig, CLIPSegTextConfig, CLIPSegVisionConfig

    text = CLIPSegTextConfig(
        vocab_size=RD64_VOCAB_SIZE,
        hidden_size=512,
        intermediate_size=2048,
        num_hidden_layers=12,
        num_attention_heads=8,
        max_position_embeddings=77,
        hidden_act="quick_gelu",
        bos_token_id=bos_id,
        eos_token_id=eos_id,
        pad_token_id=eos_id,
    )
    vision = CLIPSegVisionConfig(
        hidden_size=768,
        intermediate_size=3072,
        num_hidden_layers=12,
        num_attention_heads=12,
        image_size=224,  # CLIP's pre-training size; 352 inputs interpolate the position table
        patch_size=16,
        hidden_act="quick_gelu",
    )
    return CLIPSegConfig(
        text_config=text.to_dict(),
        vision_config=vision.to_dict(),
        projection_dim=512,
        extract_layers=[3, 6, 9],
        reduce_dim=64,
        decoder_num_attention_heads=4,
        decoder_intermediate_size=2048,
        conditional_layer=0,
        use_complex_transposed_convolution=True,
    )


def _calibrate_logit_scale(model, tokenizer) -> None:
    """Scale the last upsampling layer so logits have the spread of real CLIPSeg outputs.

    Random initialisation yields logits in the hundreds or thousands, which saturates any
    softmax and makes absolute error figures meaningless; real rd64-refined logits span roughly
    -20..10. One forward on a random image (seeded by the caller) sets the scale.
    """
    import torch

    head = model.decoder.transposed_convolution
    last = head[-1] if isinstance(head, torch.nn.Sequential) else head
    tokens = tokenizer(list(REFERENCE_PROMPTS.texts()[:2]), padding=True, return_tensors="pt")
    pixel_values = torch.randn(2, 3, IMAGE_SIZE_PX, IMAGE_SIZE_PX)
    with torch.no_grad():
        logits = model(pixel_values=pixel_values, **tokens).logits
        scale = TARGET_LOGIT_STD / float(logits.std())
        last.weight.mul_(scale)
        last.bias.mul_(scale)


def build_random_clipseg(out_dir: str | Path, size: str = "tiny", seed: int = 0) -> Path:
    """Write a random-weight CLIPSeg model + processor directory and return its path.

    Deterministic for a given ``seed``; the global torch RNG is left as it was.
    """
    if size not in MODEL_SIZES:
        raise ValueError(f"size: unknown model size {size!r}, expected one of {MODEL_SIZES}")
    import torch
    from transformers import CLIPSegForImageSegmentation, CLIPSegProcessor, CLIPTokenizer
    from transformers.models.vit.image_processing_pil_vit import ViTImageProcessorPil

    out_path = Path(out_dir)
    out_path.mkdir(parents=True, exist_ok=True)
    vocab, merges = build_tokenizer_files()
    bos_id, eos_id = vocab[BOS_TOKEN], vocab[EOS_TOKEN]
    config = _tiny_config(len(vocab), bos_id, eos_id) if size == "tiny" else _rd64_config(bos_id, eos_id)
    tokenizer = CLIPTokenizer(vocab=vocab, merges=merges, model_max_length=77)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = CLIPSegForImageSegmentation(config).eval()
        _calibrate_logit_scale(model, tokenizer)
    model.save_pretrained(out_path)

    image_processor = ViTImageProcessorPil(
        do_resize=True,
        size={"height": IMAGE_SIZE_PX, "width": IMAGE_SIZE_PX},
        resample=PIL_BILINEAR,
        do_rescale=True,
        rescale_factor=1 / 255,
        do_normalize=True,
        image_mean=list(IMAGENET_MEAN),
        image_std=list(IMAGENET_STD),
    )
    CLIPSegProcessor(image_processor=image_processor, tokenizer=tokenizer).save_pretrained(out_path)
    LOG.info("wrote random %s CLIPSeg (seed %d, %d tokens) to %s", size, seed, len(vocab), out_path)
    return out_path
