"""Classes of the synthetic worlds: their ids, which are safe, and the colours and textures they are drawn with.

The ids are fixed (other tools and stored results refer to them). The palettes are flat base colours;
the texture tables say how strongly each class is modulated by grain, mid-scale and coarse noise and
how its tint drifts across a patch field (applied by `render`).
"""

from __future__ import annotations

import numpy as np


ROOF_FLAT, ROOF_PITCHED, ROAD, SIDEWALK, PLAZA, PARKING_LOT, CAR = 1, 2, 3, 4, 5, 6, 7
GRASS, SPORTS_FIELD, TREE, WATER, BARE_SOIL, PERSON = 8, 9, 10, 11, 12, 13

# id -> (name, safe to land on). Fixed: other tools and stored results refer to these ids.
SYNTHETIC_CLASSES: dict[int, tuple[str, bool]] = {
    ROOF_FLAT: ("roof_flat", False),
    ROOF_PITCHED: ("roof_pitched", False),
    ROAD: ("road", False),
    SIDEWALK: ("sidewalk", False),
    PLAZA: ("plaza", True),
    PARKING_LOT: ("parking_lot", True),
    CAR: ("car", False),
    GRASS: ("grass", True),
    SPORTS_FIELD: ("sports_field", True),
    TREE: ("tree", False),
    WATER: ("water", False),
    BARE_SOIL: ("bare_soil", True),
    PERSON: ("person", False),
}

RGB = tuple[int, int, int]

# Palettes (RGB). Base colours are flat; the texture pass adds grain, patches and shadows.

PAL_ASPHALT = (82, 84, 86)
PAL_LOT_ASPHALT = (96, 96, 95)
PAL_PAINT = (228, 228, 222)
PAL_SIDEWALK = (168, 164, 156)
PAL_GRASS = [(98, 128, 62), (88, 122, 58), (106, 130, 66), (84, 116, 56), (112, 128, 70)]
PAL_TREE = [(50, 76, 40), (58, 86, 44), (45, 68, 42), (66, 92, 48), (40, 60, 46), (72, 90, 52)]
PAL_ROOF_PITCHED = [  # (colour, weight): clay tiles dominate, then slate, metal, concrete tiles
    ((176, 88, 62), 4.0), ((158, 76, 56), 3.0), ((128, 78, 60), 2.0), ((74, 76, 82), 2.5),
    ((138, 142, 146), 1.2), ((140, 58, 52), 0.7), ((78, 104, 90), 0.5), ((110, 104, 98), 1.5),
]
PAL_ROOF_FLAT = [
    ((168, 166, 160), 3.0), ((184, 178, 166), 2.0), ((92, 92, 95), 2.0), ((214, 214, 210), 1.5),
    ((132, 132, 134), 2.0), ((150, 140, 126), 1.0),
]
PAL_CAR = [
    ((232, 232, 230), 24), ((30, 30, 34), 18), ((118, 120, 124), 16), ((176, 178, 182), 13),
    ((40, 64, 120), 9), ((150, 30, 30), 7), ((44, 80, 52), 3), ((196, 180, 150), 4),
    ((220, 180, 40), 2), ((90, 50, 40), 4),
]
PAL_CLOTHES = [(30, 30, 35), (200, 40, 40), (40, 70, 160), (235, 235, 235), (230, 200, 40),
               (90, 90, 95), (150, 110, 80), (40, 140, 70)]
PAL_WATER_POND = (52, 74, 72)
PAL_WATER_RIVER = (58, 82, 92)
PAL_WATER_POOL = (96, 186, 206)
PAL_SOIL = (150, 122, 92)

# Texture amplitudes per class: grain (per pixel), mid (~0.75 m), coarse (~5-15 m) relative
# luminance modulation, and an RGB tint driven by a ~30-60 m patch field (dry grass, stains).
TEX_GRAIN = {ROOF_FLAT: .035, ROOF_PITCHED: .05, ROAD: .05, SIDEWALK: .04, PLAZA: .04,
             PARKING_LOT: .05, CAR: .015, GRASS: .06, SPORTS_FIELD: .04, TREE: .08,
             WATER: .015, BARE_SOIL: .08, PERSON: 0.0}
TEX_MID = {ROOF_FLAT: .03, ROOF_PITCHED: .06, ROAD: .03, SIDEWALK: .03, PLAZA: .03,
           PARKING_LOT: .03, CAR: 0.0, GRASS: .09, SPORTS_FIELD: .03, TREE: .26,
           WATER: .02, BARE_SOIL: .09, PERSON: 0.0}
TEX_COARSE = {ROOF_FLAT: .06, ROOF_PITCHED: .04, ROAD: .07, SIDEWALK: .05, PLAZA: .05,
              PARKING_LOT: .07, CAR: 0.0, GRASS: .12, SPORTS_FIELD: .04, TREE: .10,
              WATER: .06, BARE_SOIL: .14, PERSON: 0.0}
TEX_TINT = {GRASS: (34, 18, 4), BARE_SOIL: (18, 12, 6), TREE: (10, 8, 0), ROAD: (6, 6, 6),
            ROOF_FLAT: (-8, -8, -6), WATER: (-6, 4, 0), PARKING_LOT: (6, 6, 6)}
# Shadowed surfaces get the bluish sky light only: per-channel factor.
SHADOW_RGB = np.array([0.42, 0.46, 0.56], np.float32)
