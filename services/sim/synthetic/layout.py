"""Layout of a synthetic city: the road grid, the blocks between roads (one kind each), the river.

Everything here is geometry and random choices, drawn from the layout stream of the seed; nothing is
painted. `layout` returns the road lines, the blocks and which block owns each grid cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dovesei.sim.synthetic.canvas import uni
from dovesei.sim.synthetic.classes import ROOF_FLAT, ROOF_PITCHED, WATER


@dataclass
class Road:
    centre_m: float
    width_m: float
    avenue: bool
    parking_lanes: bool


@dataclass
class Block:
    x0: float  # outer edge of the sidewalk ring (= kerb line), metres
    y0: float
    x1: float
    y1: float
    sidewalk_m: float
    kind: str = ""
    cells: list[tuple[int, int]] = field(default_factory=list)

    @property
    def inner(self) -> tuple[float, float, float, float]:
        s = self.sidewalk_m
        return self.x0 + s, self.y0 + s, self.x1 - s, self.y1 - s


@dataclass(frozen=True)
class BlockFrame:
    """Block-local axes: u along the block's long side, v across it from one street front."""

    x0: float
    y0: float
    x1: float
    y1: float
    along_x: bool
    flip_v: bool = False

    @property
    def length(self) -> float:
        return (self.x1 - self.x0) if self.along_x else (self.y1 - self.y0)

    @property
    def depth(self) -> float:
        return (self.y1 - self.y0) if self.along_x else (self.x1 - self.x0)

    def pt(self, u: float, v: float) -> tuple[float, float]:
        if self.flip_v:
            v = self.depth - v
        return (self.x0 + u, self.y0 + v) if self.along_x else (self.x0 + v, self.y0 + u)

    def rect(self, u0, v0, u1, v1) -> tuple[float, float, float, float]:
        (ax, ay), (bx, by) = self.pt(u0, v0), self.pt(u1, v1)
        return min(ax, bx), min(ay, by), max(ax, bx), max(ay, by)

    def v_angle(self) -> float:
        """World angle of the +v direction (away from this frame's street front)."""
        (ax, ay), (bx, by) = self.pt(0, 0), self.pt(0, 1)
        return math.atan2(by - ay, bx - ax)

    def flipped(self) -> "BlockFrame":
        return BlockFrame(self.x0, self.y0, self.x1, self.y1, self.along_x, not self.flip_v)


_KIND_WEIGHTS = {"residential": 0.27, "apartments": 0.22, "commercial": 0.21, "park": 0.055,
                 "sports": 0.025, "parking": 0.06, "plaza": 0.045, "water": 0.025,
                 "construction": 0.03}


@dataclass(frozen=True)
class CityStyle:
    """What makes one kind of city: how often each block kind is drawn, how far apart the streets
    run (metres between kerbs, along the two axes), and how often a river crosses it. The
    defaults are the original city; other styles only change these numbers, so they share every
    drawing routine and the default city's random draws stay exactly what they were."""

    kind_weights: tuple[tuple[str, float], ...] = tuple(_KIND_WEIGHTS.items())
    spacing_long_m: tuple[float, float] = (75, 150)
    spacing_short_m: tuple[float, float] = (55, 110)
    no_river_chance: float = 0.45


CITY = CityStyle()
# Trees scattered at random are dropped where their trunk would stand in these.
NO_TREES = {WATER, ROOF_FLAT, ROOF_PITCHED, 0}
_REQUIRED_KINDS = ["residential", "apartments", "commercial", "park", "sports", "parking",
                   "plaza", "water", "construction"]


def _road_lines(rng, size_m: float, spacing_m: tuple[float, float]) -> list[Road]:
    def new_road() -> Road:
        avenue = rng.random() < 0.2
        parking = (not avenue) and rng.random() < 0.5
        width = uni(rng, 17, 21) if avenue else 2 * uni(rng, 3.0, 3.4) + (4.4 if parking else 0)
        return Road(0.0, width, avenue, parking)

    roads = []
    road = new_road()
    road.centre_m = -uni(rng, 5, 40)
    while True:
        roads.append(road)
        if road.centre_m > size_m + 5:
            return roads
        nxt = new_road()
        nxt.centre_m = road.centre_m + road.width_m / 2 + uni(rng, *spacing_m) + nxt.width_m / 2
        road = nxt


@dataclass
class River:
    pts_m: np.ndarray  # centreline
    width_m: float
    bank_m: float


def make_river(rng, size_m: float, style: CityStyle = CITY) -> River | None:
    if size_m < 700 or rng.random() < style.no_river_chance:
        return None
    t = np.arange(-60.0, size_m + 60.0, 8.0)
    base = uni(rng, 0.3, 0.7) * size_m
    off = np.zeros_like(t)
    for amp, lam in ((uni(rng, 40, 110), uni(rng, 700, 1600)),
                     (uni(rng, 10, 30), uni(rng, 200, 400))):
        off += amp * np.sin(2 * math.pi * t / lam + uni(rng, 0, 2 * math.pi))
    pts = np.stack([t, base + off], 1) if rng.random() < 0.5 else np.stack([base + off, t], 1)
    return River(pts, uni(rng, 24, 42), uni(rng, 5, 9))


def make_layout(rng, size_m: float, river: River | None, style: CityStyle = CITY
                ) -> tuple[list[Road], list[Road], list[Block], dict[tuple[int, int], int]]:
    """Road grid lines along x and y, the blocks between them, and which block owns each grid
    cell (a merged block owns two, and the street between them is not drawn)."""
    if rng.random() < 0.5:
        sx, sy = style.spacing_long_m, style.spacing_short_m
    else:
        sx, sy = style.spacing_short_m, style.spacing_long_m
    xr, yr = _road_lines(rng, size_m, sx), _road_lines(rng, size_m, sy)
    nx, ny = len(xr) - 1, len(yr) - 1

    def cell_rect(i0, j0, i1, j1):
        return (xr[i0].centre_m + xr[i0].width_m / 2, yr[j0].centre_m + yr[j0].width_m / 2,
                xr[i1 + 1].centre_m - xr[i1 + 1].width_m / 2,
                yr[j1 + 1].centre_m - yr[j1 + 1].width_m / 2)

    riverside: set[tuple[int, int]] = set()
    if river is not None:
        reach = river.width_m / 2 + river.bank_m + 2
        for i in range(nx):
            for j in range(ny):
                x0, y0, x1, y1 = cell_rect(i, j, i, j)
                dx = np.maximum(np.maximum(x0 - river.pts_m[:, 0], river.pts_m[:, 0] - x1), 0)
                dy = np.maximum(np.maximum(y0 - river.pts_m[:, 1], river.pts_m[:, 1] - y1), 0)
                if np.min(np.hypot(dx, dy)) < reach:
                    riverside.add((i, j))

    owner: dict[tuple[int, int], int] = {}
    blocks: list[Block] = []

    def add(i0, j0, i1, j1, kind):
        x0, y0, x1, y1 = cell_rect(i0, j0, i1, j1)
        b = Block(x0, y0, x1, y1, uni(rng, 2.2, 4.0), kind,
                  [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)])
        for c in b.cells:
            owner[c] = len(blocks)
        blocks.append(b)

    order = [(i, j) for i in range(nx) for j in range(ny)]
    rng.shuffle(order)
    # Big blocks first: two cells merged (the street between them disappears) make room for a
    # running track, a large park or a mall.
    for i, j in order:
        if (i, j) in owner or (i, j) in riverside or rng.random() > 0.05:
            continue
        di, dj = (1, 0) if rng.random() < 0.5 else (0, 1)
        other = (i + di, j + dj)
        if other[0] >= nx or other[1] >= ny or other in owner or other in riverside:
            continue
        kind = str(rng.choice(["sports", "park", "commercial", "apartments", "parking"],
                              p=[0.15, 0.2, 0.3, 0.25, 0.1]))
        add(i, j, other[0], other[1], kind)
    singles = [c for c in order if c not in owner]
    kinds = [k for k, _ in style.kind_weights]
    p = np.array([w for _, w in style.kind_weights])
    assigned = [str(k) for k in rng.choice(kinds, size=len(singles), p=p / p.sum())]
    # Make sure every kind (hence every class) exists: overwrite the first few draws.
    inner = [n for n, c in enumerate(singles) if c not in riverside]
    if len(inner) >= 2 * len(_REQUIRED_KINDS):
        for n, kind in zip(inner, _REQUIRED_KINDS):
            assigned[n] = kind
    for (i, j), kind in zip(singles, assigned):
        add(i, j, i, j, "riverside" if (i, j) in riverside else kind)
    return xr, yr, blocks, owner
