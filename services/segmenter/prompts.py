"""Prompt sets for the open-vocabulary segmenter.

A prompt set is what the user says "safe" and "unsafe" look like: a tuple of positive prompts
(places to land on), a tuple of negative prompts (everything else) and a template that wraps
each prompt into a sentence for the text encoder. It is configuration: the service builds one
from its config file or from a prompts message received at run time, the CLIPSeg backend turns
``texts()`` into cached text embeddings keyed by ``set_id``, and heatmaps carry ``set_id`` so a
consumer knows which vocabulary produced them.

Data flow:  config / wire message -> PromptSet (validated here) -> texts() -> text encoder
                                                             \\-> set_id -> heatmap metadata

The class is pure (no torch, no I/O) so the controller side and the message codec can build and
compare prompt sets without the segmenter's heavy dependencies.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field

# Bounds keep a hostile or mistaken prompts message from making the text encoder allocate
# without limit. CLIP's text encoder sees at most 77 tokens, so a few hundred characters is
# already more than it can use; the backend checks the token count exactly.
MAX_PROMPTS_PER_GROUP = 32
MAX_PROMPT_CHARS = 200
MAX_TEMPLATE_CHARS = 300
SET_ID_HEX_CHARS = 12


class PromptError(ValueError):
    """A prompt set is malformed; the message names the offending field."""


def _as_prompt_tuple(field_name: str, values: Sequence[str]) -> tuple[str, ...]:
    """Validate one prompt group and return it as a tuple of stripped strings."""
    if isinstance(values, str):
        # A bare string would otherwise be iterated character by character.
        raise PromptError(f"{field_name}: expected a sequence of strings, got a single string {values!r}")
    try:
        items = tuple(values)
    except TypeError as exc:
        raise PromptError(f"{field_name}: expected a sequence of strings, got {type(values).__name__}") from exc
    if not items:
        raise PromptError(f"{field_name}: needs at least one prompt")
    if len(items) > MAX_PROMPTS_PER_GROUP:
        raise PromptError(f"{field_name}: {len(items)} prompts, at most {MAX_PROMPTS_PER_GROUP} allowed")
    cleaned = []
    for index, item in enumerate(items):
        if not isinstance(item, str):
            raise PromptError(f"{field_name}[{index}]: expected a string, got {type(item).__name__}")
        text = item.strip()
        if not text:
            raise PromptError(f"{field_name}[{index}]: empty prompt")
        if len(text) > MAX_PROMPT_CHARS:
            raise PromptError(f"{field_name}[{index}]: {len(text)} characters, at most {MAX_PROMPT_CHARS} allowed")
        if "{" in text or "}" in text:
            # Braces would be interpreted by str.format when the template is applied.
            raise PromptError(f"{field_name}[{index}]: braces are not allowed in a prompt: {text!r}")
        cleaned.append(text)
    return tuple(cleaned)


def _check_template(template: str) -> str:
    if not isinstance(template, str):
        raise PromptError(f"template: expected a string, got {type(template).__name__}")
    if len(template) > MAX_TEMPLATE_CHARS:
        raise PromptError(f"template: {len(template)} characters, at most {MAX_TEMPLATE_CHARS} allowed")
    # Exactly one "{}" and no other brace, so str.format (what the reference used) can neither
    # fail nor pick up stray fields.
    if template.count("{}") != 1 or template.count("{") != 1 or template.count("}") != 1:
        raise PromptError(f"template: must contain exactly one '{{}}' placeholder and no other braces: {template!r}")
    return template


@dataclass(frozen=True)
class PromptSet:
    """Positive and negative prompts plus the template that turns each into a sentence.

    Lists are accepted and stored as tuples; surrounding whitespace is stripped. ``texts()``
    lists the positives first, which is the order the fusion functions expect.
    """

    positive: tuple[str, ...]
    negative: tuple[str, ...]
    template: str = "{}"
    set_id: str = field(init=False, compare=False)

    def __post_init__(self) -> None:
        # frozen=True forbids plain assignment; normalising in place keeps the constructor the
        # single entry point (wire messages and config both call it).
        object.__setattr__(self, "positive", _as_prompt_tuple("positive", self.positive))
        object.__setattr__(self, "negative", _as_prompt_tuple("negative", self.negative))
        object.__setattr__(self, "template", _check_template(self.template))
        canonical = json.dumps(
            {"positive": list(self.positive), "negative": list(self.negative), "template": self.template},
            ensure_ascii=False,
            separators=(",", ":"),
        )
        digest = hashlib.sha256(canonical.encode("utf-8")).hexdigest()
        object.__setattr__(self, "set_id", digest[:SET_ID_HEX_CHARS])

    @property
    def n_positive(self) -> int:
        return len(self.positive)

    @property
    def n_prompts(self) -> int:
        return len(self.positive) + len(self.negative)

    def texts(self) -> tuple[str, ...]:
        """Template-formatted sentences, positives first then negatives."""
        return tuple(self.template.format(p) for p in self.positive + self.negative)


# The reference's aerial prompts and template, verbatim (see docs/REFERENCE.md).
REFERENCE_TEMPLATE = "aerial view, drone footage photo of {}, shade, shadows, low resolution"
REFERENCE_POSITIVE = (
    "grass, dead grass, backyard, frontyard, courtyard, lawn",
    "sports-field, park, open-area, open-space, agricultural land",
    "parking lot, sidewalk, gravel, dirt, sand, concrete floor, asphalt",
)
REFERENCE_NEGATIVE = (
    "building, house, apartment-building, warehouse, shed, garage",
    "roof, rooftop, terrace, shelter, dome, canopy, ceiling",
    "tree, bare tree, tree during autumn, bush, tall-plant",
    "water, lake, river, swimming pool",
    "people, crowd",
    "vehicle, car, train",
    "lamp-post, transmission-line",
    "fence, wall, hedgerow",
    "road, street, avenue, highway, drive, lane",
    "stairs, steps, footsteps",
)
REFERENCE_PROMPTS = PromptSet(positive=REFERENCE_POSITIVE, negative=REFERENCE_NEGATIVE, template=REFERENCE_TEMPLATE)


# What a close look must never land near (DESIGN.md 5): scored on crops against every landing
# prompt; any pixel where they win is kept clear by the separation margin. Each prompt one group of
# synonyms, as the reference writes its negatives.
NEVER_PROMPTS = (
    "people, person, pedestrian, crowd",
    "car, vehicle, truck, bus, van",
    "bicycle, motorcycle, scooter",
    "animal, dog, horse, cow",
)


def never_prompts(values: Sequence[str]) -> tuple[str, ...]:
    """A validated "never" prompt tuple (the same rules as a prompt group; PromptError names the problem)."""
    return _as_prompt_tuple("never", values)


def crop_prompt_set(prompts: PromptSet, never: tuple[str, ...]) -> PromptSet:
    """The landing prompts with the never set appended to the negatives: one model pass scores both
    (the landing fusion then reads the first `prompts.n_prompts` logits, the never fusion the rest)."""
    return PromptSet(positive=prompts.positive, negative=prompts.negative + never, template=prompts.template)


def never_set_id(never: tuple[str, ...]) -> str:
    """A short id of a never set, as `PromptSet.set_id` for the landing prompts."""
    canonical = json.dumps(list(never), ensure_ascii=False, separators=(",", ":"))
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:SET_ID_HEX_CHARS]
