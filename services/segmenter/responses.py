"""How strongly each appearance answers each prompt: the simulated CLIPSeg's text side.

CLIPSeg scores a prompt such as "grass, dead grass, backyard, lawn" against each image patch.
Here a prompt is split on commas into items; each item gets an affinity in [0, 1] for every
appearance of `appearance.APPEARANCES`, and the prompt's affinity is a soft mean of its items
(a comma list embeds roughly as the mean of its parts, with the best-matching part weighing
more). The logit of prompt p for a patch of pure appearance a is ``logit_scale * affinity[a, p]``;
the perception model mixes these per patch (`sim_backend.py`).

An item is looked up, in order: as a whole ("dead grass", "swimming pool"; hyphens and case
ignored), then word by word (the mean of the known words' rows, so "rocky beach" averages the
two), then by spelling similarity to a known word (character trigrams: "lawns" -> "lawn",
"grassland" -> "grass"), shrunk towards a neutral row by how weak the match is. A word that
resembles nothing gets the neutral row, which every appearance answers weakly and about equally:
CLIPSeg's logits for an unrelated word are low and flat.

The template ("aerial view, drone footage photo of {}, ...") is shared by every prompt of a set
and shifts all logits alike, which neither fusion sees; it is not modelled.
"""

from __future__ import annotations

import re
from functools import lru_cache

import numpy as np

from .appearance import APPEARANCES, INDEX
from .prompts import PromptSet

BASE_AFFINITY = 0.12  # what an appearance not named in a row answers
NEUTRAL_AFFINITY = 0.18  # the row of a word that resembles nothing known
OFF_WORLD_BASE = 0.03  # black frame beyond the map: answers almost nothing
MIN_TRIGRAM_SIMILARITY = 0.35
ITEM_SHARPNESS = 4.0  # soft mean over a prompt's items: 0 = plain mean, large = max

# Affinity rows: item -> {appearance: affinity}; appearances not named get BASE_AFFINITY.
# Read as "how much does an aerial patch of this look resemble the word" (CLIP similarity).
_A = dict
WORDS: dict[str, dict[str, float]] = {
    # the reference's positive prompts
    "grass": _A(lawn=0.95, sports_field=0.8, tree=0.45, bare_ground=0.3, shadow=0.2),
    "dead grass": _A(lawn=0.75, bare_ground=0.7, sports_field=0.5, tree=0.25),
    "backyard": _A(lawn=0.7, paved=0.45, pitched_roof=0.4, tree=0.4, bare_ground=0.35, clutter=0.4, flat_roof=0.3),
    "frontyard": _A(lawn=0.65, paved=0.45, pitched_roof=0.4, tree=0.35, road=0.3, clutter=0.35),
    "courtyard": _A(paved=0.75, lawn=0.45, flat_roof=0.45, bare_ground=0.35, clutter=0.35),
    "lawn": _A(lawn=0.95, sports_field=0.8, tree=0.35, bare_ground=0.25),
    "sports field": _A(sports_field=0.95, lawn=0.75, bare_ground=0.35, paved=0.35, parking=0.3),
    "park": _A(lawn=0.8, tree=0.7, sports_field=0.6, parking=0.35, paved=0.35, water=0.3),
    "open area": _A(bare_ground=0.75, lawn=0.6, sports_field=0.6, paved=0.6, parking=0.55, flat_roof=0.4, road=0.3),
    "open space": _A(bare_ground=0.75, lawn=0.6, sports_field=0.6, paved=0.55, parking=0.5, flat_roof=0.35, road=0.3),
    "agricultural land": _A(bare_ground=0.75, lawn=0.7, sports_field=0.4, tree=0.35),
    "parking lot": _A(parking=0.95, paved=0.7, road=0.7, vehicle=0.6, flat_roof=0.45),
    "sidewalk": _A(paved=0.9, road=0.55, parking=0.5, person=0.4, flat_roof=0.35),
    "gravel": _A(bare_ground=0.8, paved=0.55, parking=0.5, flat_roof=0.45, road=0.4),
    "dirt": _A(bare_ground=0.9, lawn=0.3, road=0.3),
    "sand": _A(bare_ground=0.95, paved=0.45, water=0.3, flat_roof=0.3),
    "concrete floor": _A(paved=0.9, flat_roof=0.7, parking=0.65, road=0.55, bare_ground=0.4),
    "asphalt": _A(road=0.9, parking=0.9, paved=0.55, flat_roof=0.5, shadow=0.45, water=0.3),
    # the reference's negative prompts
    "building": _A(flat_roof=0.85, pitched_roof=0.85, clutter=0.5, paved=0.3, vehicle=0.2),
    "house": _A(pitched_roof=0.9, flat_roof=0.6, clutter=0.4),
    "apartment building": _A(flat_roof=0.85, pitched_roof=0.55, clutter=0.4),
    "warehouse": _A(flat_roof=0.9, pitched_roof=0.4, paved=0.4, parking=0.35),
    "shed": _A(pitched_roof=0.7, flat_roof=0.6, clutter=0.5, vehicle=0.3),
    "garage": _A(flat_roof=0.7, pitched_roof=0.6, vehicle=0.5, parking=0.5, paved=0.4),
    "roof": _A(flat_roof=0.9, pitched_roof=0.95, paved=0.35, clutter=0.4),
    "rooftop": _A(flat_roof=0.9, pitched_roof=0.85, paved=0.4),
    "terrace": _A(flat_roof=0.75, paved=0.7, pitched_roof=0.4, lawn=0.3),
    "shelter": _A(flat_roof=0.6, pitched_roof=0.6, clutter=0.5, tree=0.3),
    "dome": _A(flat_roof=0.4, pitched_roof=0.5, clutter=0.3, tree=0.35),
    "canopy": _A(tree=0.85, flat_roof=0.45, pitched_roof=0.4, clutter=0.3, lawn=0.35),
    "ceiling": _A(flat_roof=0.6, shadow=0.5, off_world=0.5, paved=0.4),
    "tree": _A(tree=0.95, lawn=0.45, sports_field=0.2, shadow=0.3),
    "bare tree": _A(tree=0.8, bare_ground=0.45, lawn=0.3),
    "tree during autumn": _A(tree=0.85, bare_ground=0.4, pitched_roof=0.35),
    "bush": _A(tree=0.85, lawn=0.55),
    "tall plant": _A(tree=0.8, lawn=0.5),
    "water": _A(water=0.95, shadow=0.5, road=0.3, off_world=0.4),
    "lake": _A(water=0.95, shadow=0.4, lawn=0.2),
    "river": _A(water=0.95, road=0.3, shadow=0.4),
    "swimming pool": _A(water=0.9, paved=0.4, flat_roof=0.3),
    "people": _A(person=0.9, clutter=0.3, paved=0.35),
    "crowd": _A(person=0.95, clutter=0.4, paved=0.3, vehicle=0.3),
    "vehicle": _A(vehicle=0.95, parking=0.5, road=0.5),
    "car": _A(vehicle=0.95, parking=0.55, road=0.5),
    "train": _A(vehicle=0.75, road=0.5, flat_roof=0.4),
    "lamp post": _A(clutter=0.4, road=0.35, paved=0.35, person=0.3, vehicle=0.2),
    "transmission line": _A(clutter=0.4, road=0.3, bare_ground=0.3),
    "fence": _A(clutter=0.5, paved=0.35, lawn=0.3, road=0.3, tree=0.3),
    "wall": _A(flat_roof=0.55, pitched_roof=0.4, clutter=0.5, paved=0.45),
    "hedgerow": _A(tree=0.85, lawn=0.6),
    "road": _A(road=0.95, parking=0.75, paved=0.55, vehicle=0.5, shadow=0.35),
    "street": _A(road=0.9, parking=0.6, paved=0.6, vehicle=0.5),
    "avenue": _A(road=0.85, paved=0.5, tree=0.4, vehicle=0.45),
    "highway": _A(road=0.95, vehicle=0.5, parking=0.5),
    "drive": _A(road=0.75, parking=0.6, paved=0.5, vehicle=0.45),
    "lane": _A(road=0.8, paved=0.5, parking=0.5),
    "stairs": _A(paved=0.55, flat_roof=0.5, clutter=0.5, pitched_roof=0.4),
    "steps": _A(paved=0.5, flat_roof=0.45, clutter=0.45),
    "footsteps": _A(paved=0.4, bare_ground=0.45, clutter=0.35),
    # words a user is likely to try
    "field": _A(sports_field=0.75, lawn=0.75, bare_ground=0.65),
    "meadow": _A(lawn=0.9, sports_field=0.6, bare_ground=0.4, tree=0.35),
    "beach": _A(bare_ground=0.85, water=0.5, paved=0.35),
    "desert": _A(bare_ground=0.9, paved=0.3, flat_roof=0.25),
    "soil": _A(bare_ground=0.9, lawn=0.3),
    "ground": _A(bare_ground=0.7, paved=0.55, lawn=0.5, parking=0.45, road=0.4),
    "plaza": _A(paved=0.9, flat_roof=0.6, parking=0.5, road=0.4),
    "square": _A(paved=0.8, flat_roof=0.55, parking=0.45),
    "pavement": _A(paved=0.9, road=0.6, parking=0.55, flat_roof=0.4),
    "concrete": _A(paved=0.85, flat_roof=0.75, parking=0.6, road=0.5),
    "forest": _A(tree=0.95, lawn=0.4),
    "pond": _A(water=0.9, shadow=0.4, lawn=0.3),
    "sea": _A(water=0.95, shadow=0.3),
    "pool": _A(water=0.85, paved=0.35),
    "truck": _A(vehicle=0.9, road=0.5, parking=0.45, flat_roof=0.3),
    "bus": _A(vehicle=0.9, road=0.55, flat_roof=0.35),
    "person": _A(person=0.95, paved=0.3, clutter=0.3),
    "pedestrian": _A(person=0.9, paved=0.4, road=0.3),
    "shadow": _A(shadow=0.9, water=0.45, road=0.4, tree=0.3),
    "shade": _A(shadow=0.85, tree=0.45, water=0.35),
    "runway": _A(road=0.85, parking=0.6, paved=0.6),
    "helipad": _A(paved=0.7, flat_roof=0.65, parking=0.5),
    "bridge": _A(road=0.7, water=0.4, flat_roof=0.35),
    "construction site": _A(bare_ground=0.65, clutter=0.6, vehicle=0.35, paved=0.35),
}


def _normalise(item: str) -> str:
    return " ".join(w for w in re.split(r"[^a-z0-9]+", item.lower()) if w)


def _row(affinities: dict[str, float]) -> np.ndarray:
    row = np.full(len(APPEARANCES), BASE_AFFINITY)
    row[INDEX["off_world"]] = OFF_WORLD_BASE
    row[INDEX["clutter"]] = max(BASE_AFFINITY, 0.25)  # a jumble looks a little like everything
    for app, a in affinities.items():
        row[INDEX[app]] = a
    return row


_ROWS: dict[str, np.ndarray] = {_normalise(k): _row(v) for k, v in WORDS.items()}
_NEUTRAL = np.full(len(APPEARANCES), NEUTRAL_AFFINITY)
_NEUTRAL[INDEX["off_world"]] = OFF_WORLD_BASE


def _trigrams(word: str) -> set[str]:
    padded = f"  {word} "
    return {padded[i:i + 3] for i in range(len(padded) - 2)}


_SINGLE_WORDS: dict[str, set[str]] = {k: _trigrams(k) for k in _ROWS if " " not in k}


def _plural_forms(word: str) -> list[str]:
    forms = [word]
    if word.endswith("es") and len(word) > 3:
        forms.append(word[:-2])
    if word.endswith("s") and len(word) > 2:
        forms.append(word[:-1])
    return forms


def _word_row(word: str) -> tuple[np.ndarray, float]:
    """(row, confidence in [0, 1]) of one word: exact, plural, or nearest by trigrams."""
    for form in _plural_forms(word):
        if form in _ROWS:
            return _ROWS[form], 1.0
    grams = _trigrams(word)
    best, best_sim = None, 0.0
    for known, known_grams in _SINGLE_WORDS.items():
        sim = len(grams & known_grams) / len(grams | known_grams)
        if sim > best_sim or (sim == best_sim and best is not None and known < best):
            best, best_sim = known, sim
    if best is None or best_sim < MIN_TRIGRAM_SIMILARITY:
        return _NEUTRAL, 0.0
    return _ROWS[best], best_sim


@lru_cache(maxsize=1024)
def item_affinity(item: str) -> tuple[float, ...]:
    """Affinity of each appearance (APPEARANCES order) to one comma-separated prompt item."""
    key = _normalise(item)
    if key in _ROWS:
        return tuple(float(v) for v in _ROWS[key])
    words = key.split()
    if not words:
        return tuple(float(v) for v in _NEUTRAL)
    rows, weights = [], []
    for word in words:
        row, conf = _word_row(word)
        if conf > 0.0:
            rows.append(_NEUTRAL + conf * (row - _NEUTRAL))
            weights.append(conf)
    if not rows:
        return tuple(float(v) for v in _NEUTRAL)
    # Function words ("of", "during") match nothing and drop out; known words share the item.
    mixed = np.average(np.stack(rows), axis=0, weights=weights)
    return tuple(float(v) for v in mixed)


def prompt_affinity(prompt: str, sharpness: float = ITEM_SHARPNESS) -> np.ndarray:
    """Affinity of each appearance to a whole prompt: soft mean of its comma-separated items."""
    items = [s for s in (part.strip() for part in prompt.split(",")) if s]
    if not items:
        return _NEUTRAL.copy()
    table = np.array([item_affinity(s) for s in items])  # (items, A)
    if sharpness <= 0.0:
        return table.mean(axis=0)
    peak = table.max(axis=0)
    return peak + np.log(np.exp(sharpness * (table - peak)).mean(axis=0)) / sharpness


def response_matrix(prompts: PromptSet, sharpness: float = ITEM_SHARPNESS) -> np.ndarray:
    """(A, P) affinities of every appearance to every prompt of the set, positives first."""
    cols = [prompt_affinity(p, sharpness) for p in prompts.positive + prompts.negative]
    return np.stack(cols, axis=1)


def describe_item(item: str) -> str:
    """How an item was understood (for logs): its three strongest appearances."""
    aff = np.array(item_affinity(item))
    top = np.argsort(-aff)[:3]
    return ", ".join(f"{APPEARANCES[i]} {aff[i]:.2f}" for i in top)


__all__ = ["WORDS", "describe_item", "item_affinity", "prompt_affinity", "response_matrix"]
