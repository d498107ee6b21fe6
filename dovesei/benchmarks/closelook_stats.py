"""How the close look's finding rule does on simulated crops: people it misses, clear ground it fires on.

Per world and perception profile, `--crops` squares (alternately one with a person within 3.5 m of
its centre and one of clear safe ground, nothing within 6 m) and `--vehicle-crops` squares with a
car within the judge's 5 m of their centre (the centre's own safety disk on safe ground, nobody
within 6 m), each looked at `--looks` times as the policy does while it holds (a fresh request each, the vehicle within +-0.5 m, heading at random),
at 22, 30 or 40 m. Every look is the real path: the sim cuts the crop with the people drawn at the
crop's resolution, the simulated perception scores it, `verdict()` of the policy judges it.

Figures per profile: looks at people that found nothing, people the gate would have let the
descent past (two clear looks in a row), the same for cars, clear looks that fired, clear squares
whose gate opened.
Perception seeds start at `--seed-base` and go up by one per square: the reported benches use
episode seeds 0-33, so this refuses a base below 100 (what is chosen here is checked elsewhere).
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Sequence

import numpy as np

from dovesei.controller.policies.clearance.closelook import CloseLookConfig, verdict
from dovesei.segmenter.core import SegmenterConfig, SegmenterCore, make_backend
from dovesei.segmenter.simulated import PROFILE_NAMES
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.crop import CropRefused
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import CropRequest, Stamp
from dovesei.sim.core import SimConfig, SimCore
from dovesei.shared.mission import SAFETY_RADIUS_M, VEHICLE_SEPARATION_M
from dovesei.sim.objects import PERSON, VEHICLE
from dovesei.sim.starts import Start
from dovesei.sim.world import World, load_world

DEFAULT_WORLDS = ("synthetic:style=villas,seed=2", "synthetic:style=coast,seed=4", "synthetic:style=desert,seed=3",
                  "synthetic:style=downtown,seed=1")
MIN_SEED_BASE = 100  # the reported benches' episode seeds are 0-33
LOOK_ALTS_M = (22.0, 30.0, 40.0)
PERSON_WITHIN_M = 3.5
CLEAR_BEYOND_M = 6.0


def _safe_codes(world: World) -> np.ndarray:
    return np.array([k for k, c in world.classes.items() if c.safe])


def _on_safe_ground(world: World, safe: np.ndarray, x_m: float, y_m: float, half_m: float) -> bool:
    """Is the square of half side `half_m` around the point all safe ground (and inside the world)?"""
    half_px = int(round(half_m / world.gsd_m))
    row, col = (int(v) for v in world.world_to_pixel(x_m, y_m))
    labels = world.labels[row - half_px:row + half_px + 1, col - half_px:col + half_px + 1]
    return labels.shape == (2 * half_px + 1,) * 2 and bool(np.isin(labels, safe).all())


def _beside(at, j: int, rng: np.random.Generator, lo_m: float, hi_m: float) -> tuple[float, float]:
    """A point lo_m-hi_m from object j's centre, in a random direction."""
    r, a = rng.uniform(lo_m, hi_m), rng.uniform(0.0, 2.0 * math.pi)
    return float(at.x_m[j]) + r * math.cos(a), float(at.y_m[j]) + r * math.sin(a)


def _square(world: World, rng: np.random.Generator, person: bool, side_m: float) -> tuple[float, float, float] | None:
    """A square's centre (east, north) on safe ground and its nearest person's distance, or None."""
    layer = world.population.layer
    safe = _safe_codes(world)
    people = np.flatnonzero(layer.kind == PERSON)
    if person and people.size == 0:
        return None
    at = layer.at(0.0)
    for _ in range(3000):
        if person:
            cx, cy = _beside(at, int(rng.choice(people)), rng, 0.5, PERSON_WITHIN_M)
        else:
            cx, cy = rng.uniform(50.0, world.width_m - 50.0), rng.uniform(50.0, world.height_m - 50.0)
        if not _on_safe_ground(world, safe, cx, cy, side_m / 2):
            continue  # a spot the map could have chosen: safe ground all over the square
        d = layer.distances_m(cx, cy, 0.0)
        nearest = float(d[people].min(initial=math.inf))
        if person and nearest <= PERSON_WITHIN_M:
            return cx, cy, nearest
        if not person and float(d.min(initial=math.inf)) >= CLEAR_BEYOND_M:
            return cx, cy, nearest
    return None


def _vehicle_square(world: World, rng: np.random.Generator) -> tuple[float, float, float] | None:
    """A square's centre (east, north) with a car within VEHICLE_SEPARATION_M of it, the centre's
    safety disk on safe ground and no person within CLEAR_BEYOND_M, and the car's distance; or None."""
    layer = world.population.layer
    safe = _safe_codes(world)
    cars, people = np.flatnonzero(layer.kind == VEHICLE), layer.kind == PERSON
    if cars.size == 0:
        return None
    at = layer.at(0.0)
    for _ in range(3000):
        cx, cy = _beside(at, int(rng.choice(cars)), rng, 2.0, VEHICLE_SEPARATION_M)
        if not _on_safe_ground(world, safe, cx, cy, SAFETY_RADIUS_M):
            continue
        d = layer.distances_m(cx, cy, 0.0)
        nearest_car = float(d[cars].min())
        if nearest_car <= VEHICLE_SEPARATION_M and float(d[people].min(initial=math.inf)) >= CLEAR_BEYOND_M:
            return cx, cy, nearest_car
    return None


def looks_of(world: World, profile: str, squares: int, looks: int, seed_base: int,
             cfg: CloseLookConfig = CloseLookConfig(), vehicles: bool = False, margin_m: float | None = None,
             out_px: int | None = None) -> list[dict]:
    """One record per square: person or clear (or, with `vehicles`, a car near it), distance to the
    nearest person (car), one verdict per look. The looks' margin is `margin_m` (the config's by
    default), their square twice that, asked at `out_px` (the config's by default)."""
    margin = cfg.margin_m if margin_m is None else margin_m
    side = 2.0 * margin
    out_px = cfg.out_px if out_px is None else out_px
    rng = np.random.default_rng([seed_base, 53 if vehicles else 47])
    out = []
    for i in range(squares):
        person = not vehicles and i % 2 == 0
        found = _vehicle_square(world, rng) if vehicles else _square(world, rng, person, side)
        if found is None:
            continue
        cx, cy, nearest = found
        seg_cfg = SegmenterConfig(backend="sim", sim_profile=profile, sim_seed=seed_base + i)
        seg = SegmenterCore(make_backend(seg_cfg), seg_cfg)
        alt = float(rng.choice(LOOK_ALTS_M))
        fired = []
        for k in range(looks):
            dx, dy = rng.uniform(-0.5, 0.5, 2)
            core = SimCore(world, Start(cx + dx, cy + dy, alt, float(rng.uniform(-math.pi, math.pi))),
                           SimConfig(vehicle_profile="ideal"))
            core.reset()
            try:
                crop = core.crop(CropRequest("uav1", k + 1, Stamp(0.0, "sim"), (0.0, 0.0), side, out_px))
            except CropRefused:
                continue
            _, never = seg.process_crop(crop).probabilities()
            fired.append(not verdict(never, side, cfg, margin_m=margin).clear)
        out.append({"person": person, "vehicle": vehicles, f"nearest_{'vehicle' if vehicles else 'person'}_m":
                    round(nearest, 2), "alt_m": alt, "fired": fired})
    return out


def _gate_opens(fired: list[bool]) -> bool:
    return any(not a and not b for a, b in zip(fired, fired[1:]))


def summarise(records: list[dict]) -> dict:
    people = [r for r in records if r["person"]]
    cars = [r for r in records if r["vehicle"]]
    clear = [r for r in records if not r["person"] and not r["vehicle"]]
    return {"person_squares": len(people), "person_looks": sum(len(r["fired"]) for r in people),
            "person_looks_missed": sum(f is False for r in people for f in r["fired"]),
            "person_gate_opened": sum(_gate_opens(r["fired"]) for r in people),
            "clear_squares": len(clear), "clear_looks": sum(len(r["fired"]) for r in clear),
            "clear_looks_fired": sum(f is True for r in clear for f in r["fired"]),
            "clear_gate_opened": sum(_gate_opens(r["fired"]) for r in clear),
            "vehicle_squares": len(cars), "vehicle_looks": sum(len(r["fired"]) for r in cars),
            "vehicle_looks_missed": sum(f is False for r in cars for f in r["fired"]),
            "vehicle_gate_opened": sum(_gate_opens(r["fired"]) for r in cars)}


def main(argv: Sequence[str] | None = None) -> int:
    p = OneLineParser(prog="dovesei closelook-stats", description=__doc__.splitlines()[0])
    p.add_argument("--world", action="append", default=None,
                   help=f"world spec, repeatable (default: {', '.join(DEFAULT_WORLDS)})")
    p.add_argument("--profile", default="realistic,harsh", help="simulated perception profiles, comma-separated")
    p.add_argument("--crops", type=int, default=30, help="squares per world and profile (half with a person)")
    p.add_argument("--vehicle-crops", type=int, default=20,
                   help="squares per world and profile with a car within 5 m of the centre (0: none)")
    p.add_argument("--looks", type=int, default=4, help="looks at each square")
    p.add_argument("--seed-base", type=int, default=200, help=f"first perception seed (>= {MIN_SEED_BASE})")
    p.add_argument("--margin-m", type=float, default=None,
                   help=f"the looks' margin, their square twice it (default {CloseLookConfig().margin_m:g}: the descent's "
                        "looks; the final looks of a bench flight: 5.7, the cap)")
    p.add_argument("--out-px", type=int, default=None,
                   help=f"the crops' size (default {CloseLookConfig().out_px}, as the policy asks)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    args = p.parse_args(argv)
    profiles = [s.strip() for s in args.profile.split(",") if s.strip()]
    for name in profiles:
        if name not in PROFILE_NAMES:
            raise ConfigError(f"--profile {name!r}: choose from {', '.join(PROFILE_NAMES)}")
    if not profiles:
        raise ConfigError("--profile: name at least one profile")
    if args.seed_base < MIN_SEED_BASE:
        raise ConfigError(f"--seed-base {args.seed_base}: use {MIN_SEED_BASE} or more (the reported benches use "
                          "episode seeds 0-33)")
    for flag, value, low in (("--crops", args.crops, 1), ("--looks", args.looks, 1),
                             ("--vehicle-crops", args.vehicle_crops, 0)):
        if not low <= value <= 10_000:
            raise ConfigError(f"{flag} {value}: expected {low}..10000")
    cfg = CloseLookConfig()
    margin = cfg.margin_m if args.margin_m is None else args.margin_m
    if not (math.isfinite(margin) and cfg.margin_m / 4 <= margin <= 4 * cfg.margin_m):
        raise ConfigError(f"--margin-m {args.margin_m}: expected {cfg.margin_m / 4:g}..{4 * cfg.margin_m:g} m")
    out_px = cfg.out_px if args.out_px is None else args.out_px
    if not 32 <= out_px <= 1024:
        raise ConfigError(f"--out-px {args.out_px}: expected 32..1024")
    worlds = {spec: load_world(spec) for spec in (args.world or DEFAULT_WORLDS)}
    result = {"worlds": list(worlds), "crops": args.crops, "vehicle_crops": args.vehicle_crops, "looks": args.looks,
              "seed_base": args.seed_base, "margin_m": margin, "side_m": 2.0 * margin, "out_px": out_px, "profiles": {}}
    for name in profiles:
        records = [r for w in worlds.values()
                   for r in looks_of(w, name, args.crops, args.looks, args.seed_base, margin_m=margin, out_px=out_px)]
        if args.vehicle_crops:
            records += [r for w in worlds.values()
                        for r in looks_of(w, name, args.vehicle_crops, args.looks, args.seed_base, vehicles=True,
                                          margin_m=margin, out_px=out_px)]
        result["profiles"][name] = summarise(records)
    result["loadavg"] = [round(v, 2) for v in os.getloadavg()]
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"close-look rule on simulated crops: {len(worlds)} worlds, {args.crops} squares each "
          f"(+{args.vehicle_crops} with a car), {args.looks} looks, "
          f"seeds from {args.seed_base}, {2.0 * margin:g} m squares at {out_px} px")
    for name, s in result["profiles"].items():
        print(f"  {name:10s} people: {s['person_looks_missed']}/{s['person_looks']} looks missed, gate opened on "
              f"{s['person_gate_opened']}/{s['person_squares']} | clear: {s['clear_looks_fired']}/{s['clear_looks']} "
              f"looks fired, gate opened on {s['clear_gate_opened']}/{s['clear_squares']} | cars: "
              f"{s['vehicle_looks_missed']}/{s['vehicle_looks']} looks missed, gate opened on "
              f"{s['vehicle_gate_opened']}/{s['vehicle_squares']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
