"""What a world class LOOKS like from the air, decided from its NAME alone.

The simulated perception never asks whether the judge counts a class as safe: it asks what the
ground looks like (a lawn, a grey flat roof, a dark pond) and lets the response table
(`responses.py`) say how strongly that look answers each prompt word. A class name becomes an
appearance mix (weights over `APPEARANCES`, summing to 1) by keywords on its words:

    "roof_pitched"                                -> pitched_roof 1.0
    "parking_lot"                                 -> parking 1.0
    "land (unpaved area)"                         -> bare_ground 1.0
    "vegetation (lawns and trees, not separated)" -> lawn 0.5, tree 0.5
    "unlabeled", "zz top"                         -> clutter 1.0 (a generic man-made jumble)

Words are lowercase letter runs with a trailing plural "s"/"es" also tried. A word of the
"dominant" table (pitched, parking, sport...) decides alone; otherwise every matching word votes
and the votes are averaged. The label 255 (outside the world, written by the sim's camera) is
the appearance `off_world`, never a class name.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

APPEARANCES: tuple[str, ...] = (
    "lawn", "sports_field", "bare_ground", "paved", "parking", "road", "flat_roof", "pitched_roof",
    "tree", "water", "vehicle", "person", "shadow", "clutter", "off_world",
)
INDEX: dict[str, int] = {name: i for i, name in enumerate(APPEARANCES)}
OFF_WORLD_LABEL = 255  # the camera's "outside the world" label (GroundTruth's contract)
UNKNOWN_APPEARANCE = "clutter"

# A word here fixes the appearance whatever else the name says ("roof_pitched" is not a flat roof,
# "parking_lot" not bare land, "sports_field" not an agricultural field).
_DOMINANT: dict[str, dict[str, float]] = {
    **{w: {"pitched_roof": 1.0} for w in ("pitched", "gable", "gabled", "tiled", "hip")},
    **{w: {"parking": 1.0} for w in ("parking", "carpark")},
    **{w: {"sports_field": 1.0} for w in ("sport", "sports", "stadium", "pitch", "court", "golf")},
    **{w: {"person": 1.0} for w in ("person", "people", "pedestrian", "crowd", "human")},
    **{w: {"vehicle": 1.0} for w in ("car", "vehicle", "truck", "bus", "van", "train", "boat", "automobile")},
    **{w: {"shadow": 1.0} for w in ("shadow", "shade")},
}
_VOTES: dict[str, dict[str, float]] = {
    **{w: {"lawn": 1.0} for w in ("grass", "lawn", "meadow", "garden", "turf", "park", "greenery", "pasture")},
    **{w: {"lawn": 0.5, "tree": 0.5} for w in ("vegetation", "vegetated", "green", "greenspace")},
    **{w: {"tree": 1.0} for w in ("tree", "forest", "wood", "woods", "woodland", "bush", "shrub", "hedge",
                                   "hedgerow", "canopy", "orchard", "palm")},
    **{w: {"water": 1.0} for w in ("water", "lake", "river", "pool", "sea", "pond", "canal", "ocean", "harbour",
                                    "harbor", "swimming", "marina", "fountain")},
    **{w: {"road": 1.0} for w in ("road", "street", "highway", "avenue", "motorway", "rail", "railway",
                                   "asphalt", "freeway", "lane")},
    **{w: {"paved": 1.0} for w in ("sidewalk", "pavement", "plaza", "square", "concrete", "paved", "courtyard",
                                    "pier", "quay", "promenade", "footpath", "path", "walkway")},
    **{w: {"bare_ground": 1.0} for w in ("soil", "land", "sand", "dirt", "gravel", "earth", "desert", "unpaved",
                                          "ground", "beach", "bare", "dune", "field", "farmland", "crop")},
    **{w: {"flat_roof": 1.0} for w in ("flat", "warehouse", "rooftop", "terrace", "industrial")},
    **{w: {"flat_roof": 0.8, "pitched_roof": 0.2} for w in ("roof", "building", "house", "shed", "garage",
                                                            "villa", "tower", "apartment")},
}


def _forms(name: str) -> list[str]:
    words = [w for w in re.split(r"[^a-z]+", name.lower()) if w]
    out: list[str] = []
    for w in words:
        out.append(w)
        # Plurals: "trees" -> "tree", "lawns" -> "lawn", "beaches" -> "beach".
        if w.endswith("es") and len(w) > 3:
            out.append(w[:-2])
        if w.endswith("s") and len(w) > 2:
            out.append(w[:-1])
    return out


def appearance_mix(class_name: str) -> dict[str, float]:
    """The appearance weights of a class name (summing to 1); unknown names are `clutter`."""
    if not isinstance(class_name, str):
        raise ValueError(f"class name must be a str, got {class_name!r}")
    forms = _forms(class_name)
    for form in forms:
        if form in _DOMINANT:
            return dict(_DOMINANT[form])
    votes: dict[str, float] = {}
    n = 0
    seen: set[str] = set()
    for form in forms:
        if form in _VOTES and form not in seen:
            seen.add(form)
            n += 1
            for app, w in _VOTES[form].items():
                votes[app] = votes.get(app, 0.0) + w
    if not n:
        return {UNKNOWN_APPEARANCE: 1.0}
    return {app: w / n for app, w in votes.items()}


def class_appearance_table(names: Mapping[int, str]) -> "list[tuple[int, dict[str, float]]]":
    """(id, mix) for every class id of a world, in id order (for logs and the LUT builder)."""
    return [(int(cid), appearance_mix(name)) for cid, name in sorted(names.items())]
