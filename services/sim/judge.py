"""The automatic judge: decides from the world's label map whether a landing spot is safe.

The paper judged landings by eye; here the label map does it. Two pieces:

- `judge_landing(world, x_m, y_m)` looks at the ground disk of the safety radius under the
  vehicle (pixels whose centre lies within the radius, at least the pixel under the vehicle):
  `safe` when at most `tolerance_frac` of it is unsafe (label anti-aliasing along class
  boundaries), else `unsafe`. Pixels outside the world count as unsafe: nobody vouches for them.
  Classes named like people (`zero_tolerance_names`) get no tolerance at all: a person is 1-2
  pixels at 0.25 m/px, under the 1 % allowance of a 2 m disk (~200 pixels), and landing on one is
  the worst failure there is. It also reports the classes in the disk and the distance from the
  landing point to the closest unsafe pixel (within `search_radius_m`).
- `disk_safe_map(world)` is that rule at every pixel at once, and `nearest_safe_m` the distance
  from a point to the nearest pixel where a landing would be judged safe (how far a perfect
  lander would have had to fly: the bench's ceiling).
- `EpisodeJudge` watches vehicle states during an episode and ends it: `out_of_world` when the
  vehicle leaves the image, the landing verdict when the controller hands over (its command says
  `handover`, which it sends only at/below the hand-over altitude with the policy landing),
  `timeout` when the sim-time limit runs out. It accumulates the horizontal path length.

  The altitude alone never makes a landing: twice under `harsh` a descent the policy had already
  aborted sank through the hand-over altitude on inertia and was scored "safe". Such an
  uncommanded sink goes on (the policy climbs back, or the time runs out); a vehicle that reaches the ground without a
  hand-over (`GROUND_CONTACT_M`) ends `unsafe`, "on the ground without a hand-over": an
  unplanned touchdown is a crash, wherever it happens. A caller with no word from the controller
  (`handover=None`) gets the altitude crossing, the paper's rule. It also keeps the ground the
  policy last confirmed (`confirm`, placed by the sim from the confirming frame's true pose): at
  the hand-over, `touchdown_error_m` is the true distance from the hand-over point to it (None
  for a policy that confirmed nothing).

Separation (DESIGN.md 1, issue 24): besides the disk, a landing is `unsafe` when a person is within
`person_separation_m` (3 m) or a vehicle within `vehicle_separation_m` (5 m) of the touchdown point
at the hand-over. Distances are to the object's footprint (a person's disc, a car's rectangle) at
the hand-over's episode time, from the world's people and vehicles (`World.population`, some of
them walking and driving) and from labelled pixels of classes named like them (a world folder's own
cars), whichever is nearer. A separation of 0 turns that rule off; a person or vehicle in the disk
itself stays unsafe. Every verdict carries the nearest person's and vehicle's distance.

Which classes are safe belongs to the world (`World.classes`); nothing here knows class ids.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from dovesei.shared.errors import DoveseiError
from dovesei.shared.mission import HANDOVER_ALT_M, PERSON_SEPARATION_M, SAFETY_RADIUS_M, VEHICLE_SEPARATION_M
from dovesei.shared.validate import is_number
from dovesei.sim.dynamics import Pose
from dovesei.sim.world import CANOPY_CLASS_NAME, World

OUTSIDE_WORLD_NAME = "outside the world"
DEFAULT_ZERO_TOLERANCE_NAMES = ("person", "people", "pedestrian", "human")
VEHICLE_NAMES = ("car", "vehicle", "truck", "bus", "van", "automobile")
TOLERANCE_FRAC = 0.01  # unsafe share of the disk forgiven (label anti-aliasing along edges)
SEARCH_RADIUS_M = 50.0  # how far `closest_unsafe_m` looks
GROUND_CONTACT_M = 0.1  # true altitude at which an un-handed-over vehicle has hit the ground
NO_HANDOVER_REASON = "on the ground without a hand-over (an uncommanded descent)"
# How near a crown counts as "beside the trees" in the canopy figures (`canopy_figures`): a crown's
# radius and a little, the distance the earlier canopy tables of docs/RESULTS.md used.
CANOPY_NEAR_M = 5.0


class JudgeError(DoveseiError, ValueError):
    """The judge cannot decide: no label map, or bad parameters."""


@dataclass(frozen=True)
class ClassFraction:
    """One class found in the landing disk and the fraction of the disk's pixels it covers."""

    name: str
    fraction: float
    safe: bool


@dataclass(frozen=True)
class Verdict:
    """The judge's decision on one landing point."""

    outcome: str  # "safe" or "unsafe"
    x_m: float
    y_m: float
    safety_radius_m: float
    disk_px: int
    unsafe_frac: float
    classes: tuple[ClassFraction, ...]  # largest fraction first
    closest_unsafe_m: float | None  # None: no unsafe pixel within the search radius
    reason: str
    # Footprint distances from the touchdown point at the hand-over (None: none within the search radius).
    nearest_person_m: float | None = None
    nearest_vehicle_m: float | None = None
    separation_violated: bool = False  # a person or vehicle closer than its separation

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def judge_landing(
    world: World,
    x_m: float,
    y_m: float,
    safety_radius_m: float = SAFETY_RADIUS_M,
    tolerance_frac: float = TOLERANCE_FRAC,
    search_radius_m: float = SEARCH_RADIUS_M,
    zero_tolerance_names: tuple[str, ...] = DEFAULT_ZERO_TOLERANCE_NAMES,
    *,
    t_s: float = 0.0,
    person_separation_m: float = PERSON_SEPARATION_M,
    vehicle_separation_m: float = VEHICLE_SEPARATION_M,
) -> Verdict:
    """Judge a landing at world point (x_m, y_m) from the world's label map, its people and vehicles
    where they are at t_s (seconds since the episode began), and the separations (0: rule off)."""
    if world.labels is None:
        raise JudgeError(f"world {world.name!r} has no label map: landings on it cannot be judged")
    if not (is_number(x_m) and is_number(y_m)):
        raise JudgeError(f"landing point must be finite, got ({x_m!r}, {y_m!r})")
    if not (is_number(safety_radius_m) and safety_radius_m >= 0):
        raise JudgeError(f"safety_radius_m must be finite and >= 0, got {safety_radius_m!r}")
    if not 0.0 <= tolerance_frac < 1.0:
        raise JudgeError(f"tolerance_frac must be in [0, 1), got {tolerance_frac!r}")
    check_separations(person_separation_m, vehicle_separation_m)

    ids, inside = _disk_labels(world, x_m, y_m, safety_radius_m)
    n = int(ids.size)  # never 0: the pixel under the vehicle always belongs to the disk
    n_outside = int((~inside).sum())
    counts = np.bincount(ids[inside], minlength=256)
    # safe_lut already treats ids missing from the world's classes as unsafe.
    unsafe_px = n_outside + int(counts[~world.safe_lut].sum())
    found: list[ClassFraction] = []
    critical: list[str] = []
    never = _zero_tolerance_ids(world, zero_tolerance_names)
    for cid in np.flatnonzero(counts):
        info = world.classes.get(int(cid))
        name = info.name if info is not None else f"unknown id {int(cid)}"
        safe = bool(world.safe_lut[cid])
        found.append(ClassFraction(name, float(counts[cid] / n), safe))
        if int(cid) in never:
            critical.append(name)
    if n_outside:
        found.append(ClassFraction(OUTSIDE_WORLD_NAME, n_outside / n, False))
    found.sort(key=lambda c: (-c.fraction, c.name))

    unsafe_frac = unsafe_px / n
    person_m, vehicle_m = nearest_objects_m(world, x_m, y_m, t_s, search_radius_m, zero_tolerance_names)
    too_close = []
    # A separation rule, or (with that rule off) the disk itself: nobody may be under the vehicle.
    for what, dist, sep in (("person", person_m, person_separation_m), ("vehicle", vehicle_m, vehicle_separation_m)):
        if dist is not None and dist < max(sep, safety_radius_m if what == "person" or sep == 0 else 0.0):
            too_close.append(f"a {what} {dist:.1f} m from the touchdown" + (f" (separation {sep:g} m)" if sep else ""))
    violated = any(d is not None and sep > 0 and d < sep
                   for d, sep in ((person_m, person_separation_m), (vehicle_m, vehicle_separation_m)))
    share = f"{unsafe_frac:.1%} of the disk is unsafe (tolerance {tolerance_frac:.1%})"
    if critical:
        outcome, reason = "unsafe", f"{', '.join(critical)} in the disk (no tolerance for them)"
    elif unsafe_frac > tolerance_frac:
        outcome, reason = "unsafe", share
    else:
        outcome, reason = "safe", share
    if too_close:
        outcome, reason = "unsafe", "; ".join([*too_close, reason])
    return Verdict(
        outcome=outcome, x_m=float(x_m), y_m=float(y_m), safety_radius_m=float(safety_radius_m),
        disk_px=n, unsafe_frac=float(unsafe_frac), classes=tuple(found),
        closest_unsafe_m=closest_unsafe_m(world, x_m, y_m, search_radius_m), reason=reason,
        nearest_person_m=person_m, nearest_vehicle_m=vehicle_m, separation_violated=violated,
    )


def canopy_figures(world: World, x_m: float, y_m: float, safety_radius_m: float = SAFETY_RADIUS_M,
                   search_radius_m: float = SEARCH_RADIUS_M) -> dict[str, float | None] | None:
    """Where a landing stands against the tree crowns the world's image shows, on a world whose
    labels lump open ground with canopy (a class marked `canopy_from_image`, e.g. Dubai's
    "vegetation (lawns and trees, not separated)"); None on other worlds.

    `lumped`: the share of the disk on such a class (the judge's labels); `in_disk`: the share the
    image shows as canopy (`World.perceived`, the rule the simulated camera sees by); `nearest_m`:
    the distance to the nearest canopy pixel centre (None: none within search_radius_m). A figure
    beside the verdict, never part of it: the judge keeps the world's labels, so a landing on open
    lawn under such a class stays unsafe and these figures say how open the lawn was.
    """
    if world.labels is None:
        raise JudgeError(f"world {world.name!r} has no label map")
    if not (is_number(x_m) and is_number(y_m)):
        raise JudgeError(f"landing point must be finite, got ({x_m!r}, {y_m!r})")
    lumped_ids = [c for c, info in world.classes.items() if info.canopy_from_image]
    if not lumped_ids:
        return None
    seen = world.perceived()  # the same grid as the world's, its lumped classes split by the image
    crown_ids = [c for c, info in seen.classes.items() if info.name == CANOPY_CLASS_NAME]
    rr, cc, inside = _disk_pixels(world, x_m, y_m, safety_radius_m)
    rr, cc, n = rr[inside], cc[inside], rr.size  # pixels beyond the world count in the disk, as no class
    nearest = _nearest_m(seen, lambda rs, cs: np.isin(seen.labels[rs, cs], crown_ids), x_m, y_m, search_radius_m)
    return {"lumped": round(float(np.count_nonzero(np.isin(world.labels[rr, cc], lumped_ids))) / n, 3),
            "in_disk": round(float(np.count_nonzero(np.isin(seen.labels[rr, cc], crown_ids))) / n, 3),
            "nearest_m": None if nearest is None else round(float(nearest), 2)}


def check_separations(person_separation_m: object, vehicle_separation_m: object) -> None:
    """JudgeError (one line) unless both separations are finite and >= 0 (0 turns a rule off)."""
    for name, value in (("person_separation_m", person_separation_m), ("vehicle_separation_m", vehicle_separation_m)):
        if not (is_number(value) and value >= 0):
            raise JudgeError(f"{name} must be a finite number of metres >= 0 (0 turns the rule off), got {value!r}")


def nearest_objects_m(world: World, x_m: float, y_m: float, t_s: float = 0.0,
                      search_radius_m: float = SEARCH_RADIUS_M,
                      person_names: tuple[str, ...] = DEFAULT_ZERO_TOLERANCE_NAMES) -> tuple[float | None, float | None]:
    """(nearest person, nearest vehicle): footprint distance from the point at t_s, from the world's
    population and from labelled pixels of classes named like them; None when none is within
    search_radius_m."""
    person, vehicle = world.population.nearest_m(x_m, y_m, t_s) if world.population is not None else (None, None)
    out = []
    for dist, ids in ((person, _zero_tolerance_ids(world, person_names)), (vehicle, _vehicle_ids(world))):
        ids = np.array(sorted(ids), np.uint8)
        if ids.size:
            labelled = _nearest_m(world, lambda rs, cs: np.isin(world.labels[rs, cs], ids), x_m, y_m, search_radius_m)
            if labelled is not None:
                dist = labelled if dist is None else min(dist, labelled)
        out.append(float(dist) if dist is not None and dist <= search_radius_m else None)
    return out[0], out[1]


def _zero_tolerance_ids(world: World, names: tuple[str, ...]) -> set[int]:
    """The unsafe classes never forgiven in a disk, matched by name: the world says what is
    unsafe, the judge only says what is never forgiven."""
    return {cid for cid, c in world.classes.items() if not c.safe and any(w in c.name.lower() for w in names)}


def _pixel_window(world: World, x_m: float, y_m: float, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices (possibly outside the image) of pixels within radius_m of the point."""
    row_c, col_c = world.world_to_pixel(x_m, y_m)
    r_px = radius_m / world.gsd_m
    # A square of candidate pixels around the point; callers cut the disk or the image out of it.
    rows = np.arange(math.floor(row_c - r_px), math.ceil(row_c + r_px) + 1)
    cols = np.arange(math.floor(col_c - r_px), math.ceil(col_c + r_px) + 1)
    return rows, cols


def _disk_labels(world: World, x_m: float, y_m: float, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Label ids of the disk's pixels (0 where outside) and which of them lie inside the world."""
    rr, cc, inside = _disk_pixels(world, x_m, y_m, radius_m)
    ids = np.zeros(rr.shape, dtype=np.uint8)  # placeholder ids where outside; `inside` tells them apart
    ids[inside] = world.labels[rr[inside], cc[inside]]
    return ids, inside


def _disk_pixels(world: World, x_m: float, y_m: float, radius_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, cols) of the disk's pixels, some perhaps beyond the image, and which lie inside it."""
    rows, cols = _pixel_window(world, x_m, y_m, radius_m)
    row_c, col_c = world.world_to_pixel(x_m, y_m)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    in_disk = ((rr - row_c) ** 2 + (cc - col_c) ** 2) * world.gsd_m**2 <= radius_m**2
    # The pixel under the vehicle always counts, even for a radius smaller than half a pixel.
    centre_row, centre_col = world.pixel_index(x_m, y_m)
    in_disk |= (rr == centre_row) & (cc == centre_col)
    rr, cc = rr[in_disk], cc[in_disk]
    return rr, cc, (rr >= 0) & (rr < world.height_px) & (cc >= 0) & (cc < world.width_px)


def _nearest_m(world: World, select, x_m: float, y_m: float, radius_m: float) -> float | None:
    """Distance from the point to the nearest pixel centre that `select(rows, cols)` (slices of
    the image) marks True, within radius_m (None: none that close)."""
    rows, cols = _pixel_window(world, x_m, y_m, radius_m)
    r0, r1 = max(int(rows[0]), 0), min(int(rows[-1]) + 1, world.height_px)
    c0, c1 = max(int(cols[0]), 0), min(int(cols[-1]) + 1, world.width_px)
    if r1 <= r0 or c1 <= c0:
        return None
    r_idx, c_idx = np.nonzero(select(slice(r0, r1), slice(c0, c1)))
    if r_idx.size == 0:
        return None
    px, py = world.pixel_to_world(r_idx + r0, c_idx + c0)
    best = float(np.sqrt(((px - x_m) ** 2 + (py - y_m) ** 2).min()))
    # The window is a square: its corners reach beyond the radius.
    return best if best <= radius_m else None


def closest_unsafe_m(world: World, x_m: float, y_m: float, search_radius_m: float = SEARCH_RADIUS_M) -> float | None:
    """Distance from the point to the nearest unsafe pixel centre within the radius (None if none).

    Only labelled pixels count: the world's edge is not an obstacle here.
    """
    if world.labels is None:
        raise JudgeError(f"world {world.name!r} has no label map")
    return _nearest_m(world, lambda rs, cs: ~world.safe_lut[world.labels[rs, cs]], x_m, y_m, search_radius_m)


def disk_safe_map(world: World, radius_m: float = SAFETY_RADIUS_M, tolerance_frac: float = TOLERANCE_FRAC,
                  zero_tolerance_names: tuple[str, ...] = DEFAULT_ZERO_TOLERANCE_NAMES,
                  person_separation_m: float = PERSON_SEPARATION_M,
                  vehicle_separation_m: float = VEHICLE_SEPARATION_M) -> np.ndarray:
    """uint8 map over the world: 1 where `judge_landing` would say "safe" at the pixel's centre.

    The same rule at every pixel at once: at most `tolerance_frac` of the disk unsafe, no person
    in it at all, beyond the world's edge is unsafe (the part of the disk that hangs outside
    counts against it), and no labelled person or vehicle pixel within its separation (pixels at
    exactly the separation count as too close: the map is never less strict than the judge).
    The world's moving people and cars are not in it: they are nowhere in particular.
    """
    if world.labels is None:
        raise JudgeError(f"world {world.name!r} has no label map: landings on it cannot be judged")
    r_px = radius_m / world.gsd_m
    n = int(math.ceil(r_px))
    yy, xx = np.mgrid[-n:n + 1, -n:n + 1]
    disk = ((xx * xx + yy * yy) <= r_px * r_px).astype(np.float32)
    disk /= disk.sum()
    # 1.0 per unsafe label (OpenCV's lookup: a few times numpy's indexing over a world's pixels),
    # framed by n pixels of 1.0: beyond the world's edge is unsafe, so one filtering counts the
    # part of the disk that hangs outside with the rest.
    labels = np.ascontiguousarray(world.labels)  # OpenCV takes no reversed or strided view
    unsafe = cv2.LUT(labels, (~world.safe_lut).astype(np.float32))
    framed = cv2.copyMakeBorder(unsafe, n, n, n, n, cv2.BORDER_CONSTANT, value=1.0)
    del unsafe
    unsafe_frac = cv2.filter2D(framed, -1, disk, borderType=cv2.BORDER_CONSTANT)[n:-n, n:-n]
    del framed
    ok = unsafe_frac <= tolerance_frac + 1e-6
    del unsafe_frac
    for ids, keep_m in ((_zero_tolerance_ids(world, zero_tolerance_names), max(radius_m, person_separation_m)),
                        (_vehicle_ids(world), vehicle_separation_m)):
        if ids and keep_m > 0:
            lut = np.zeros(256, np.uint8)
            lut[sorted(ids)] = 1
            near = cv2.LUT(labels, lut)
            k = int(math.ceil(keep_m / world.gsd_m))
            yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
            kernel = ((xx * xx + yy * yy) * world.gsd_m ** 2 <= keep_m * keep_m).astype(np.uint8)
            ok &= cv2.dilate(near, kernel, borderType=cv2.BORDER_CONSTANT) == 0
    return ok.astype(np.uint8)


def _vehicle_ids(world: World) -> set[int]:
    """Unsafe classes named as vehicles by a whole word ("car", not "carpark")."""
    return {cid for cid, c in world.classes.items()
            if not c.safe and set(re.split(r"[^a-z]+", c.name.lower())) & set(VEHICLE_NAMES)}


def nearest_safe_m(world: World, safe_map: np.ndarray, x_m: float, y_m: float, within_m: float) -> float | None:
    """Distance from the point to the nearest pixel of `safe_map` (from `disk_safe_map`) that is
    1, looking no farther than `within_m` (None: none that close).

    Squares of growing size around the point, so the usual answer (safe ground a few metres away)
    never lists the millions of safe pixels of a wide window.
    """
    radius = min(25.0, within_m)
    while True:
        found = _nearest_m(world, lambda rs, cs: safe_map[rs, cs], x_m, y_m, radius)
        if found is not None or radius >= within_m:
            return found
        radius = min(4.0 * radius, within_m)


class EpisodeJudge:
    """Ends an episode: out of world, hand-over altitude reached (judged landing) or time limit."""

    def __init__(
        self,
        world: World,
        handover_alt_m: float = HANDOVER_ALT_M,
        time_limit_s: float = 1200.0,
        safety_radius_m: float = SAFETY_RADIUS_M,
        tolerance_frac: float = TOLERANCE_FRAC,
        search_radius_m: float = SEARCH_RADIUS_M,
        person_separation_m: float = PERSON_SEPARATION_M,
        vehicle_separation_m: float = VEHICLE_SEPARATION_M,
    ) -> None:
        # A world without labels (tiles, paper-paris) is flown to the hand-over altitude, the time
        # limit or its edge like any other, but its landings end "not_judged": nothing says safe.
        if not (is_number(handover_alt_m) and handover_alt_m >= 0 and is_number(time_limit_s) and time_limit_s > 0):
            raise JudgeError(f"need handover_alt_m >= 0 and time_limit_s > 0, got {handover_alt_m}, {time_limit_s}")
        self.world = world
        self.handover_alt_m = handover_alt_m
        self.time_limit_s = time_limit_s
        self.safety_radius_m = safety_radius_m
        self.tolerance_frac = tolerance_frac
        self.search_radius_m = search_radius_m
        check_separations(person_separation_m, vehicle_separation_m)
        self.person_separation_m, self.vehicle_separation_m = float(person_separation_m), float(vehicle_separation_m)
        self.outcome: str | None = None  # "safe", "unsafe", "timeout", "out_of_world", "not_judged" once ended
        self.verdict: Verdict | None = None  # set when the controller handed over
        self.crashed = False  # reached the ground without a hand-over (outcome "unsafe", no verdict)
        self.path_length_m = 0.0  # horizontal, summed over the states checked
        self.start_t_s: float | None = None
        self.last_state: Pose | None = None
        self.confirmed_xy_m: tuple[float, float] | None = None  # the ground the policy last confirmed
        self.touchdown_error_m: float | None = None  # set with the landing verdict, when confirmed

    def confirm(self, xy_m: tuple[float, float] | None) -> None:
        """The ground the policy last confirmed (world metres), or None when it is not known;
        frozen once the episode has ended."""
        if self.outcome is None:
            self.confirmed_xy_m = xy_m

    @property
    def sim_time_s(self) -> float:
        if self.last_state is None or self.start_t_s is None:
            return 0.0
        return self.last_state.t_s - self.start_t_s

    def check(self, state: Pose, handover: bool | None = None) -> str | None:
        """Feed the newest state and whether the controller has handed over (None: no word from
        it, the altitude crossing decides); returns the outcome once the episode has ended (then
        always the same)."""
        if self.outcome is not None:
            return self.outcome
        if self.last_state is None:
            self.start_t_s = state.t_s
        else:
            self.path_length_m += math.hypot(state.x_m - self.last_state.x_m, state.y_m - self.last_state.y_m)
        self.last_state = state
        # Order matters: a vehicle outside the image cannot be judged, and reaching the hand-over
        # altitude on the last tick still counts as a landing.
        landed = state.alt_agl_m <= self.handover_alt_m if handover is None else handover
        if not self.world.contains(state.x_m, state.y_m):
            self.outcome = "out_of_world"
        elif landed and self.world.labels is None:
            self.outcome = "not_judged"
        elif landed:
            # People and cars where they are at the hand-over, on the episode's clock.
            self.verdict = judge_landing(self.world, state.x_m, state.y_m, self.safety_radius_m,
                                         self.tolerance_frac, self.search_radius_m, t_s=self.sim_time_s,
                                         person_separation_m=self.person_separation_m,
                                         vehicle_separation_m=self.vehicle_separation_m)
            self.outcome = self.verdict.outcome
            if self.confirmed_xy_m is not None:
                self.touchdown_error_m = math.hypot(state.x_m - self.confirmed_xy_m[0],
                                                    state.y_m - self.confirmed_xy_m[1])
        elif state.alt_agl_m <= GROUND_CONTACT_M:
            self.outcome, self.crashed = "unsafe", True
        elif self.sim_time_s >= self.time_limit_s:
            self.outcome = "timeout"
        return self.outcome

    def summary(self) -> dict[str, Any]:
        """JSON-ready record of the episode so far (outcome None while it runs)."""
        st = self.last_state
        return {
            "outcome": self.outcome,
            "sim_time_s": self.sim_time_s,
            "path_length_m": self.path_length_m,
            "final_x_m": st.x_m if st else None,
            "final_y_m": st.y_m if st else None,
            "final_alt_m": st.alt_agl_m if st else None,
            "verdict": self.verdict.to_dict() if self.verdict else None,
            "crashed": self.crashed,
            "confirmed_xy_m": self.confirmed_xy_m,
            "touchdown_error_m": self.touchdown_error_m,
        }
