"""Who is about in a world: people walking and standing on walkable ground, cars driving on roads.

One set of placement rules for every world with a label map, synthetic or real (a world folder):
a class is walkable or drivable by the words of its NAME (`class_roles`), never by whether the
judge counts it safe. `populate(labels, gsd_m, class_names, seed, density)` returns an
`ObjectLayer` (`objects.py`) of

- walkers: a person on walkable ground with a straight path of 8-40 m ahead of it that stays on
  walkable ground (sampled every 0.5 m), walked back and forth at 1.0-1.5 m/s;
- standing people: the same, without the walk;
- cars: a car (4.2-4.8 x 1.75-1.9 m) on drivable ground, heading along the longest straight run
  of road through its point that its whole width fits on (16 headings tried), driven back and
  forth along it at 4-12 m/s (15-43 km/h). Parked cars belong to the world's own drawing;
- crowds (`Density.crowds_per_km2`): groups of 20-80 people around a point of plaza or lawn,
  a third of them milling about on short paths.

Counts are Poisson draws from densities per hectare of walkable or drivable ground; everything is
drawn from one generator seeded by (seed, a fixed tag), so a world's population is a function of
its labels and seed.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from dovesei.sim.objects import PERSON, VEHICLE, ObjectLayer, empty_layer

WALKABLE_WORDS = frozenset((
    "sidewalk", "pavement", "plaza", "square", "paved", "footpath", "path", "walkway", "promenade", "quay",
    "courtyard", "grass", "lawn", "park", "garden", "meadow", "sport", "sports", "field", "pitch", "soil", "land",
    "sand", "beach", "bare", "dirt", "gravel", "parking", "unpaved",
))
DRIVABLE_WORDS = frozenset(("road", "street", "highway", "avenue", "asphalt", "lane", "motorway", "carriageway"))
CROWD_WORDS = frozenset(("plaza", "square", "grass", "lawn", "park"))

WALK_SPEED_M_S = (1.0, 1.5)
DRIVE_SPEED_M_S = (4.0, 12.0)
PERSON_WIDTH_M = (0.45, 0.6)
CAR_LENGTH_M, CAR_WIDTH_M = (4.2, 4.8), (1.75, 1.9)
_STEP_M = 0.5  # path samples
_CLOTHES = ((30, 30, 35), (200, 40, 40), (40, 70, 160), (235, 235, 235), (230, 200, 40), (90, 90, 95),
            (150, 110, 80), (40, 140, 70), (210, 120, 160))
_CAR_COLOURS = ((232, 232, 230), (30, 30, 34), (118, 120, 124), (176, 178, 182), (40, 64, 120), (150, 30, 30),
                (44, 80, 52), (196, 180, 150))


@dataclass(frozen=True)
class Density:
    """How busy a world is: objects per hectare of walkable / drivable ground, crowds per km^2."""

    walkers_per_ha: float = 4.0
    standing_per_ha: float = 0.6
    cars_per_ha_road: float = 5.0
    crowds_per_km2: float = 0.0
    crowd_size: tuple[int, int] = (20, 80)


DEFAULT_DENSITY = Density()


def _words(name: str) -> set[str]:
    out = set()
    for w in re.split(r"[^a-z]+", name.lower()):
        if w:
            out |= {w, w[:-1] if w.endswith("s") else w}
    return out


def class_roles(class_names: Mapping[int, str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three 256-entry lookup tables over class ids: walkable, drivable, crowd ground (by name)."""
    walk, drive, crowd = (np.zeros(256, bool) for _ in range(3))
    for cid, name in class_names.items():
        words = _words(name)
        drive[cid] = bool(words & DRIVABLE_WORDS)
        walk[cid] = bool(words & WALKABLE_WORDS) and not drive[cid]
        crowd[cid] = bool(words & CROWD_WORDS) and walk[cid]
    return walk, drive, crowd


class _Ground:
    """Label lookups at world points (x east, y north); outside the map is no ground at all."""

    def __init__(self, labels: np.ndarray, gsd_m: float) -> None:
        self.labels, self.gsd_m = labels, gsd_m
        self.h, self.w = labels.shape

    def ids(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        row = self.h - 1 - np.floor(y_m / self.gsd_m).astype(np.int64)
        col = np.floor(x_m / self.gsd_m).astype(np.int64)
        inside = (row >= 0) & (row < self.h) & (col >= 0) & (col < self.w)
        out = np.full(np.shape(x_m), 255, np.uint8)
        out[inside] = self.labels[row[inside], col[inside]]
        return out

    def sample(self, rng: np.random.Generator, lut: np.ndarray, n: int) -> np.ndarray:
        """n world points (x, y) uniform over the ground where lut[id] holds (fewer if it is rare)."""
        got: list[np.ndarray] = []
        have = 0
        for _ in range(40):
            if have >= n:
                break
            xy = rng.uniform(0.0, 1.0, (max(4 * (n - have), 64), 2)) * (self.w * self.gsd_m, self.h * self.gsd_m)
            ok = xy[lut[self.ids(xy[:, 0], xy[:, 1])]]
            got.append(ok)
            have += len(ok)
        pts = np.concatenate(got) if got else np.zeros((0, 2))
        return pts[:n]

    def run_m(self, x_m: np.ndarray, y_m: np.ndarray, heading_rad: np.ndarray, lut: np.ndarray, max_m: float,
              half_width_m: float = 0.0) -> np.ndarray:
        """How far from each point along its heading the ground stays where lut holds (across the
        whole half-width), up to max_m, in steps of _STEP_M."""
        steps = np.arange(1, int(max_m / _STEP_M) + 1) * _STEP_M
        de, dn = np.sin(heading_rad)[:, None], np.cos(heading_rad)[:, None]
        ok = np.ones((len(x_m), len(steps)), bool)
        for off in ((0.0,) if half_width_m <= 0 else (-half_width_m, 0.0, half_width_m)):
            xs = x_m[:, None] + steps * de + off * dn
            ys = y_m[:, None] + steps * dn - off * de
            ok &= lut[self.ids(xs, ys)]
        first_bad = np.where(ok.all(axis=1), len(steps), np.argmin(ok, axis=1))
        return np.where(first_bad > 0, steps[np.maximum(first_bad - 1, 0)], 0.0)


def populate(labels: np.ndarray, gsd_m: float, class_names: Mapping[int, str], seed: int,
             density: Density = DEFAULT_DENSITY) -> ObjectLayer:
    """The walkers, standing people, crowds and driving cars of a labelled world (module docstring)."""
    walk, drive, crowd = class_roles(class_names)
    ground = _Ground(labels, gsd_m)
    rng = np.random.default_rng([int(seed), 0x9E0B1E])
    px_ha = gsd_m * gsd_m / 1e4
    counts = np.bincount(labels.ravel(), minlength=256)
    walk_ha, drive_ha = float(counts[walk].sum()) * px_ha, float(counts[drive].sum()) * px_ha
    rows: list[tuple] = []
    n_walk, n_stand = rng.poisson(density.walkers_per_ha * walk_ha), rng.poisson(density.standing_per_ha * walk_ha)
    if walk.any():
        rows += _people(ground, rng, ground.sample(rng, walk, n_walk + n_stand), walk, moving_share=None,
                        n_moving=n_walk)
    if density.crowds_per_km2 > 0 and crowd.any():
        world_km2 = labels.size * px_ha / 100.0
        for centre in ground.sample(rng, crowd, rng.poisson(density.crowds_per_km2 * world_km2)):
            size = int(rng.integers(density.crowd_size[0], density.crowd_size[1] + 1))
            spread = rng.uniform(3.0, 8.0)
            pts = centre + rng.normal(0.0, spread, (size, 2))
            pts = pts[walk[ground.ids(pts[:, 0], pts[:, 1])]]
            rows += _people(ground, rng, pts, walk, moving_share=1 / 3, max_path_m=12.0)
    if drive.any():
        rows += _cars(ground, rng, ground.sample(rng, drive, rng.poisson(density.cars_per_ha_road * drive_ha)), drive)
    return ObjectLayer.build(rows) if rows else empty_layer()


def _people(ground: _Ground, rng: np.random.Generator, pts: np.ndarray, walk: np.ndarray,
            moving_share: float | None, n_moving: int = 0, max_path_m: float = 40.0) -> list[tuple]:
    """Rows of people at the points: the first n_moving (or a moving_share of them) walk."""
    n = len(pts)
    if not n:
        return []
    moving = rng.random(n) < moving_share if moving_share is not None else np.arange(n) < n_moving
    heading = rng.uniform(-math.pi, math.pi, n)
    want = rng.uniform(8.0, max_path_m, n)
    path = np.minimum(ground.run_m(pts[:, 0], pts[:, 1], heading, walk, max_path_m, 0.3), want)
    moving &= path >= 2.0  # nowhere to walk: it stands
    path = np.where(moving, path, 0.0)
    speed = np.where(moving, rng.uniform(*WALK_SPEED_M_S, n), 0.0)
    phase = rng.uniform(0.0, 2.0, n) * path
    width = rng.uniform(*PERSON_WIDTH_M, n)
    colour = rng.integers(0, len(_CLOTHES), n)
    return [(PERSON, pts[i, 0], pts[i, 1], heading[i], speed[i], path[i], phase[i], width[i], width[i],
             _CLOTHES[colour[i]], False) for i in range(n)]


def _cars(ground: _Ground, rng: np.random.Generator, pts: np.ndarray, drive: np.ndarray) -> list[tuple]:
    """Rows of cars driving the longest straight run of road through each point (skipped under 15 m)."""
    n = len(pts)
    if not n:
        return []
    length, width = rng.uniform(*CAR_LENGTH_M, n), rng.uniform(*CAR_WIDTH_M, n)
    headings = np.linspace(0.0, math.pi, 16, endpoint=False)
    half = 0.5 * float(CAR_WIDTH_M[1]) + 0.2
    x = np.repeat(pts[:, 0], len(headings))
    y = np.repeat(pts[:, 1], len(headings))
    h = np.tile(headings, n)
    # The road's direction is where its centre line runs longest through the point; then the car's
    # whole width must fit along it (a point by the kerb has no room and drives nowhere).
    line = ground.run_m(x, y, h, drive, 150.0) + ground.run_m(x, y, h + math.pi, drive, 150.0)
    heading = headings[np.argmax(line.reshape(n, -1), axis=1)]
    ahead = ground.run_m(pts[:, 0], pts[:, 1], heading, drive, 150.0, half)
    back = ground.run_m(pts[:, 0], pts[:, 1], heading + math.pi, drive, 150.0, half)
    at_point = drive[ground.ids(pts[:, 0] + half * np.cos(heading), pts[:, 1] - half * np.sin(heading))] & \
        drive[ground.ids(pts[:, 0] - half * np.cos(heading), pts[:, 1] + half * np.sin(heading))]
    run = np.where(at_point, ahead + back, 0.0)
    speed = rng.uniform(*DRIVE_SPEED_M_S, n)
    flip = rng.random(n) < 0.5  # half of them start from the other end
    colour = rng.integers(0, len(_CAR_COLOURS), n)
    phase_u = rng.uniform(0.0, 2.0, n)
    rows = []
    for i in range(n):
        path = run[i] - length[i]
        if path < 15.0:
            continue
        de, dn = math.sin(heading[i]), math.cos(heading[i])
        # The path runs between the car's centre positions that keep it on the run.
        sx = pts[i, 0] - (back[i] - 0.5 * length[i]) * de
        sy = pts[i, 1] - (back[i] - 0.5 * length[i]) * dn
        hd = heading[i]
        if flip[i]:
            sx, sy, hd = sx + path * de, sy + path * dn, hd + math.pi
        rows.append((VEHICLE, sx, sy, hd, speed[i], path, phase_u[i] * path, length[i], width[i],
                     _CAR_COLOURS[colour[i]], False))
    return rows
