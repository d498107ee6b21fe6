"""Worlds the simulator flies over: an orthoimage, an optional per-pixel class map and a scale.

A `World` is the immutable bundle every other sim module reads: the camera samples its image and
labels, the judge reads its labels and `safe_lut`, the start generator reads its extent.
`load_world(spec)` is the one factory that turns a user's `--world` value into a `World`:

    "synthetic[:seed=N,...]"        -> synthetic.parse_spec + synthetic.load_or_generate (cached)
    "dubai" (a name in WORLD_ALIASES) -> the world folder shipped in `worlds/` beside this module
    "tiles:<url template>[,k=v...]" -> tiles.load_tile_world (web map tiles, no labels)
    "paper-paris[:start=K,...]"     -> paris.load_paper_paris (the paper's IGN orthophotos, no labels)
    "<folder>" or ".../world.json"  -> world.json + image + labels (DESIGN.md section 8)

World frame (metres, used by the whole simulator): x_m points east from the image's left edge,
y_m points north from the image's BOTTOM edge, so the centre of pixel (row, col) is at
x_m = (col + 0.5) * gsd_m, y_m = (H - row - 0.5) * gsd_m. The image's top is north.

Label id 255 is reserved: the camera writes it where a view leaves the world. Ids a world does not
list in `classes` count as unsafe; a world folder whose label image uses an unlisted id is
refused at load time, because that is nearly always a mapping mistake rather than intent.

Worlds without labels (tiles, paper-paris) can be flown but never judged: `require_judged(spec)`
refuses them from the spec alone (before any download) for the commands that judge.
"""

from __future__ import annotations

import json
import zlib
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dovesei.shared.codec import image_header_size
from dovesei.shared.errors import ConfigError, DoveseiError
from dovesei.shared.messages import FieldError
from dovesei.shared.validate import positive
from dovesei.sim.synthetic import generate as synthetic
from dovesei.sim.objects import Population
from dovesei.sim.populate import DEFAULT_DENSITY, populate

log = logging.getLogger(__name__)

OUT_OF_WORLD_LABEL = 255  # written by the camera outside the world; never a class id

# A world image may be this large (a synthetic world's limit too; 16384^2 RGB is 805 MB decoded).
MAX_WORLD_SIDE_PX = 16384
MAX_WORLD_FILE_BYTES = 2 * 1024**3

# The world folders shipped inside the package (package data), and the short names users type.
WORLDS_DIR = Path(__file__).resolve().parent / "worlds"
WORLD_ALIASES = {"dubai": "dubai-tile8-004"}


def shipped_world(name: str) -> Path:
    """The folder of a world shipped with the package, by alias ('dubai') or folder name."""
    folder = WORLDS_DIR / WORLD_ALIASES.get(name, name)
    if not (folder / "world.json").is_file():
        known = ", ".join(sorted({*WORLD_ALIASES, *(d.name for d in WORLDS_DIR.iterdir() if d.is_dir())}))
        raise WorldError(f"no shipped world {name!r} (known: {known})")
    return folder


class WorldError(DoveseiError, ValueError):
    """A world that cannot be loaded or built: names the file or field and what was wrong."""


@dataclass(frozen=True)
class ClassInfo:
    """One class of a label map: its name and whether landing on it is acceptable."""

    name: str
    safe: bool
    # A coarse class that lumps open ground with tree canopy ("vegetation (lawns and trees, not
    # separated)"): a camera sees the crowns, so the simulated perception reads the class split
    # by the world's image (`World.perceived`); the judge keeps the class as it is.
    canopy_from_image: bool = False


# What a class with canopy_from_image looks like to the perception, in its two parts (names the
# appearance table reads: `segmenter.appearance`).
CANOPY_CLASS_NAME = "trees (canopy seen in the image)"
OPEN_CLASS_NAME = "lawn (open vegetation between the crowns)"
# Canopy in an orthophoto: crowns and their shadows are darker than the ground around them. A
# pixel is canopy where its brightness (HSV value, blurred over CANOPY_BLUR_M) is under
# CANOPY_DARKER x the median brightness within CANOPY_CONTEXT_M; the mask is then grown by
# CANOPY_GROW_M to take in a crown's sunlit side. Chosen by eye on the Dubai tile (docs/RESULTS.md,
# 7 Dec: the overlay of the mask on the photo), before any flight over the result: 11 % of its
# "vegetation" reads as canopy before growing.
CANOPY_DARKER = 0.7
CANOPY_CONTEXT_M = 30.0
CANOPY_BLUR_M = 1.0
CANOPY_GROW_M = 1.0


# eq=False: field-wise equality on numpy arrays is ill-defined, and identity hashing lets the
# camera cache image pyramids per world in a WeakKeyDictionary.
@dataclass(frozen=True, eq=False)
class World:
    """An orthoimage (RGB, top = north) with optional class labels and its ground sampling distance."""

    image_rgb: np.ndarray  # (H, W, 3) uint8
    labels: np.ndarray | None  # (H, W) uint8 class ids, None when the source has no labels (tiles)
    gsd_m: float  # metres per pixel, same along both axes
    classes: Mapping[int, ClassInfo]
    name: str
    home_xy_m: tuple[float, float] | None = None
    """Where a preset built around one start puts it (world metres); None: the starts are drawn."""
    population: Population | None = None
    """The people and vehicles about (`objects.py`): drawn by every renderer at its own resolution,
    measured by the judge; None for a world nobody populated (no labels to place them by)."""

    def __post_init__(self) -> None:
        img = self.image_rgb
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise WorldError(f"world {self.name!r}: image_rgb must be an (H, W, 3) uint8 array, got {_describe(img)}")
        if img.shape[0] < 1 or img.shape[1] < 1:
            raise WorldError(f"world {self.name!r}: image_rgb is empty {img.shape}")
        if self.labels is not None:
            lab = self.labels
            if not isinstance(lab, np.ndarray) or lab.dtype != np.uint8 or lab.ndim != 2:
                raise WorldError(f"world {self.name!r}: labels must be an (H, W) uint8 array, got {_describe(lab)}")
            if lab.shape != img.shape[:2]:
                raise WorldError(f"world {self.name!r}: labels {lab.shape} differ in size from image {img.shape[:2]}")
        _check_gsd(self.gsd_m, f"world {self.name!r}: gsd_m")
        if self.home_xy_m is not None:
            home = self.home_xy_m
            if (not isinstance(home, tuple) or len(home) != 2 or not all(math.isfinite(float(v)) for v in home)
                    or not self.contains(float(home[0]), float(home[1]))):
                raise WorldError(f"world {self.name!r}: home_xy_m must be a finite (x, y) on the image, got {home!r}")
        if self.population is not None:
            pop = self.population
            if not isinstance(pop, Population) or any(i not in self.classes for i in pop.label_ids):
                raise WorldError(f"world {self.name!r}: population must be a Population whose label ids are classes "
                                 "of the world")
        for cid, info in self.classes.items():
            if not isinstance(cid, int) or isinstance(cid, bool) or not 0 <= cid <= 254:
                raise WorldError(
                    f"world {self.name!r}: class id {cid!r} must be an integer in 0..254 "
                    f"({OUT_OF_WORLD_LABEL} marks outside the world)"
                )
            if not isinstance(info, ClassInfo):
                raise WorldError(f"world {self.name!r}: class {cid} must be a ClassInfo, got {type(info).__name__}")
        # Frozen in spirit too: the camera caches pyramids built from these arrays, so an in-place
        # edit after construction would silently desynchronise them.
        img.flags.writeable = False
        if self.labels is not None:
            self.labels.flags.writeable = False

    def perceived(self) -> "World":
        """The world as a camera-based segmenter sees it (built once per world): classes marked
        `canopy_from_image` split by the image into their canopy and their open ground, as two new
        classes (CANOPY_CLASS_NAME, OPEN_CLASS_NAME) with the class's safe flag; everything else,
        the image and the people, as they are. The perception and the frames' truth read this; the
        judge reads the world itself. Worlds with no such class are their own perceived world."""
        return self._perceived_world

    @cached_property
    def _perceived_world(self) -> "World":
        return _perceived(self)

    @property
    def height_px(self) -> int:
        return int(self.image_rgb.shape[0])

    @property
    def width_px(self) -> int:
        return int(self.image_rgb.shape[1])

    @property
    def width_m(self) -> float:
        return self.width_px * self.gsd_m

    @property
    def height_m(self) -> float:
        return self.height_px * self.gsd_m

    @cached_property
    def safe_lut(self) -> np.ndarray:
        """256 booleans indexed by label id: True only for ids listed in `classes` as safe."""
        lut = np.zeros(256, dtype=bool)
        for cid, info in self.classes.items():
            lut[cid] = info.safe
        lut.flags.writeable = False
        return lut

    def contains(self, x_m: float, y_m: float) -> bool:
        """True when the world point lies on the image (edges: left/bottom inclusive)."""
        return 0.0 <= x_m < self.width_m and 0.0 <= y_m < self.height_m

    def world_to_pixel(self, x_m: Any, y_m: Any) -> tuple[Any, Any]:
        """World metres -> continuous (row, col) pixel coordinates, integers at pixel centres.

        Works on scalars and numpy arrays; round to get the index of the pixel holding the point.
        """
        col = np.asarray(x_m, dtype=np.float64) / self.gsd_m - 0.5
        row = self.height_px - np.asarray(y_m, dtype=np.float64) / self.gsd_m - 0.5
        return _unwrap(row), _unwrap(col)

    def pixel_to_world(self, row: Any, col: Any) -> tuple[Any, Any]:
        """Continuous (row, col) pixel coordinates (integers at centres) -> world (x_m, y_m)."""
        x_m = (np.asarray(col, dtype=np.float64) + 0.5) * self.gsd_m
        y_m = (self.height_px - np.asarray(row, dtype=np.float64) - 0.5) * self.gsd_m
        return _unwrap(x_m), _unwrap(y_m)

    def pixel_index(self, x_m: float, y_m: float) -> tuple[int, int]:
        """(row, col) of the pixel containing a world point (may lie outside the image)."""
        return self.height_px - 1 - math.floor(y_m / self.gsd_m), math.floor(x_m / self.gsd_m)


def _unwrap(a: np.ndarray) -> Any:
    # Scalars in, Python floats out: callers mixing math and numpy should not get 0-d arrays.
    return float(a) if a.ndim == 0 else a


def _describe(a: Any) -> str:
    if isinstance(a, np.ndarray):
        return f"{a.dtype} array of shape {a.shape}"
    return type(a).__name__


def _check_gsd(gsd_m: Any, what: str) -> float:
    try:
        return positive(f"{what} (metres per pixel)", gsd_m)
    except ConfigError as exc:
        raise WorldError(str(exc)) from None


def unjudged_reason(spec: str) -> str | None:
    """Why the world a spec names can never be judged (it has no labels), or None; no I/O."""
    spec = spec.strip()
    if spec == "paper-paris" or spec.startswith("paper-paris:"):
        return ("world 'paper-paris' (IGN orthophotos) has no labels, so nothing flown on it can be judged: "
                "fly it with CLIPSeg, dovesei up --world paper-paris --segmenter clipseg")
    if spec.startswith("tiles:"):
        return ("a tiles: world has no labels, so nothing flown on it can be judged: "
                "fly it with CLIPSeg, dovesei up --segmenter clipseg")
    return None


def require_judged(spec: str) -> None:
    """WorldError (one line) for a command that judges what it flies, given a world without labels."""
    reason = unjudged_reason(spec)
    if reason is not None:
        raise WorldError(reason)


def load_world(spec: str) -> World:
    """Build the world a `--world` value names (see the module docstring for the forms)."""
    spec = spec.strip()  # specs often arrive from shells and config files with stray spaces
    if not spec:
        raise WorldError("empty world spec: use 'synthetic[:seed=N]', 'tiles:<url>,...', "
                         f"{', '.join(repr(a) for a in WORLD_ALIASES)} or a world folder")
    if spec == "synthetic" or spec.startswith("synthetic:"):
        return _load_synthetic(spec)
    if spec == "paper-paris" or spec.startswith("paper-paris:"):
        from dovesei.sim.paris import load_paper_paris  # lazy: import cycle through tiles

        return load_paper_paris(spec)
    if spec.startswith("tiles:"):
        # tiles imports this module (World, WorldError), and it pulls urllib and tile caching
        # that other worlds never need.
        from dovesei.sim.tiles import load_tile_world  # lazy: import cycle with tiles

        return load_tile_world(spec)
    if spec in WORLD_ALIASES:
        return load_world_folder(shipped_world(spec))
    return load_world_folder(Path(spec))


def _load_synthetic(spec: str) -> World:
    try:
        params = synthetic.parse_spec(spec)
    except synthetic.SyntheticWorldError as exc:
        raise WorldError(str(exc)) from exc  # load_world callers handle one error type
    gen = synthetic.load_or_generate_world(params)
    classes = {int(cid): ClassInfo(name, bool(safe)) for cid, (name, safe) in synthetic.SYNTHETIC_CLASSES.items()}
    # The people and cars the generator drew stand where it drew them; the others walk and drive by
    # the rules every labelled world is populated with, at the style's density.
    about = populate(gen.labels, float(params.gsd_m), {c: i.name for c, i in classes.items()}, int(params.seed),
                     synthetic.STYLE_DENSITY.get(params.style, DEFAULT_DENSITY))
    population = Population(gen.baked.concat(about), (synthetic.PERSON, synthetic.CAR), gen.shadow_per_m)
    world = World(gen.image, gen.labels, float(params.gsd_m), classes, name=spec, population=population)
    _check_label_ids(world.labels, classes, f"synthetic world {spec!r}")
    return world


def load_world_folder(folder: Path) -> World:
    """Load a world folder (or its world.json directly): gsd_m, image, labels, classes."""
    folder = folder.expanduser()
    # Accept the folder or its world.json: users tab-complete to either.
    meta_path = folder if folder.is_file() else folder / "world.json"
    if not meta_path.is_file():
        if not folder.exists():
            raise WorldError(f"world {str(folder)!r}: no such folder (nor a known world spec)")
        raise WorldError(f"world folder {str(folder)!r}: missing world.json")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise WorldError(f"{meta_path}: not readable JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise WorldError(f"{meta_path}: top level must be an object, got {type(meta).__name__}")
    if "gsd_m" not in meta:
        raise WorldError(f"{meta_path}: field 'gsd_m' is missing (metres per pixel)")
    gsd_m = _check_gsd(meta["gsd_m"], f"{meta_path}: field 'gsd_m'")
    classes = _parse_classes(meta.get("classes"), meta_path)
    base = meta_path.parent
    # Cheap metadata checks come first so a typo is reported before seconds of image decoding.
    image_rgb = _read_image(_file_field(meta, "image", meta_path, base))
    labels = _read_labels(_file_field(meta, "labels", meta_path, base))
    if labels.shape != image_rgb.shape[:2]:
        raise WorldError(
            f"{meta_path}: label image {meta['labels']!r} is {labels.shape[1]}x{labels.shape[0]} px "
            f"but image {meta['image']!r} is {image_rgb.shape[1]}x{image_rgb.shape[0]} px"
        )
    _check_label_ids(labels, classes, f"{meta_path}: label image {meta['labels']!r}")
    classes, population = _populated(labels, gsd_m, classes, base.name)
    world = World(image_rgb, labels, gsd_m, classes, name=base.name, population=population)
    log.info(
        "world %s: %dx%d px at %.3f m/px (%.0f x %.0f m), %d classes",
        world.name, world.width_px, world.height_px, gsd_m, world.width_m, world.height_m, len(classes),
    )
    return world


def canopy_mask(image_rgb: np.ndarray, gsd_m: float) -> np.ndarray:
    """Where an orthophoto shows tree canopy (bool, the image's size): the CANOPY_* rule above."""
    value = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2HSV)[..., 2].astype(np.float32)
    value = cv2.GaussianBlur(value, (0, 0), max(0.5, CANOPY_BLUR_M / gsd_m))
    side = min(255, int(round(CANOPY_CONTEXT_M / gsd_m)) | 1)  # OpenCV's median takes odd sides, 255 at most on 8 bits
    context = cv2.medianBlur(np.clip(value, 0.0, 255.0).astype(np.uint8), side).astype(np.float32)
    dark = (value < CANOPY_DARKER * context).astype(np.uint8)
    grow = max(1, int(round(CANOPY_GROW_M / gsd_m)))
    return cv2.dilate(dark, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))).astype(bool)


def _perceived(world: World) -> World:
    flagged = sorted(cid for cid, info in world.classes.items() if info.canopy_from_image)
    if not flagged or world.labels is None:
        return world
    free = [cid for cid in range(1, OUT_OF_WORLD_LABEL) if cid not in world.classes]
    if len(free) < 2 * len(flagged):
        raise WorldError(f"world {world.name!r}: no free class ids left to split {len(flagged)} canopy classes")
    canopy = canopy_mask(world.image_rgb, world.gsd_m)
    looks = world.labels.copy()
    classes = dict(world.classes)
    for k, cid in enumerate(flagged):
        tree_id, open_id = free[2 * k], free[2 * k + 1]
        mask = world.labels == cid
        looks[mask & canopy] = tree_id
        looks[mask & ~canopy] = open_id
        safe = world.classes[cid].safe
        classes[tree_id], classes[open_id] = ClassInfo(CANOPY_CLASS_NAME, safe), ClassInfo(OPEN_CLASS_NAME, safe)
    return World(world.image_rgb, looks, world.gsd_m, classes, name=world.name, home_xy_m=world.home_xy_m,
                 population=world.population)


def _populated(labels: np.ndarray, gsd_m: float, classes: dict[int, ClassInfo], name: str
               ) -> tuple[dict[int, ClassInfo], Population | None]:
    """People and cars placed by `populate` on a labelled world's walkable and drivable classes,
    seeded by the world's name. A world whose classes name no person or car gets them as new
    unsafe classes (the highest free ids), so frames can label what is drawn."""
    layer = populate(labels, gsd_m, {c: i.name for c, i in classes.items()}, zlib.crc32(name.encode()), DEFAULT_DENSITY)
    if not len(layer):
        return classes, None
    classes = dict(classes)
    ids = []
    for wanted in ("person", "car"):
        found = [c for c, i in sorted(classes.items()) if wanted in i.name.lower().split()]
        if found:
            ids.append(found[0])
        else:
            free = max(c for c in range(255) if c not in classes)
            classes[free] = ClassInfo(wanted, False)
            ids.append(free)
    return classes, Population(layer, (ids[0], ids[1]))


def _file_field(meta: dict, key: str, meta_path: Path, base: Path) -> Path:
    value = meta.get(key)
    if not isinstance(value, str) or not value:
        raise WorldError(f"{meta_path}: field {key!r} must name a file next to world.json, got {value!r}")
    path = base / value
    if not path.is_file():
        raise WorldError(f"{meta_path}: field {key!r}: file {str(path)!r} does not exist")
    return path


def _parse_classes(raw: Any, meta_path: Path) -> dict[int, ClassInfo]:
    if not isinstance(raw, dict) or not raw:
        raise WorldError(f"{meta_path}: field 'classes' must be a non-empty object {{\"<id>\": {{\"name\", \"safe\"}}}}")
    classes: dict[int, ClassInfo] = {}
    for key, entry in raw.items():
        where = f"{meta_path}: classes[{key!r}]"
        try:
            cid = int(key)
        except ValueError:
            raise WorldError(f"{where}: the key must be an integer class id") from None
        if not 0 <= cid <= 254:
            raise WorldError(f"{where}: class id must be in 0..254 ({OUT_OF_WORLD_LABEL} marks outside the world)")
        if not isinstance(entry, dict):
            raise WorldError(f"{where}: must be an object with 'name' and 'safe'")
        name, safe = entry.get("name"), entry.get("safe")
        if not isinstance(name, str) or not name.strip():
            raise WorldError(f"{where}: 'name' must be a non-empty string, got {name!r}")
        # A string "false" would be truthy: only real JSON booleans decide safety.
        if not isinstance(safe, bool):
            raise WorldError(f"{where}: 'safe' must be true or false, got {safe!r}")
        if cid in classes:
            raise WorldError(f"{where}: class id {cid} is listed twice")
        canopy = entry.get("canopy_from_image", False)
        if not isinstance(canopy, bool):
            raise WorldError(f"{where}: 'canopy_from_image' must be true or false, got {canopy!r}")
        classes[cid] = ClassInfo(name.strip(), safe, canopy)
    return classes


def _read_checked(path: Path, what: str, flags: int) -> np.ndarray:
    """Decode an image file once its header says its size is one a world can have.

    The size comes first: a 631-byte image.jpg claiming 30000x30000 px cost 68 s and 5.2 GB to
    decode, a 1 MB labels.png of the same size 19 s and 1.8 GB.
    """
    try:
        if path.stat().st_size > MAX_WORLD_FILE_BYTES:
            raise WorldError(f"{what} {str(path)!r}: {path.stat().st_size} bytes, more than "
                             f"{MAX_WORLD_FILE_BYTES} a world file may have")
        buf = path.read_bytes()
    except OSError as exc:
        raise WorldError(f"{what} {str(path)!r}: unreadable ({exc.strerror or exc})") from None
    try:
        height, width = image_header_size(buf, what)
    except FieldError as exc:
        raise WorldError(f"{what} {str(path)!r}: unreadable ({exc})") from None
    if not (1 <= height <= MAX_WORLD_SIDE_PX and 1 <= width <= MAX_WORLD_SIDE_PX):
        raise WorldError(f"{what} {str(path)!r}: {width}x{height} px, outside 1..{MAX_WORLD_SIDE_PX} px a side "
                         f"(refused before decoding)")
    image = cv2.imdecode(np.frombuffer(buf, np.uint8), flags)
    # Sorted: OpenCV turns a JPEG by its EXIF orientation, which swaps the two sides.
    if image is None or sorted(image.shape[:2]) != sorted((height, width)):
        raise WorldError(f"{what} {str(path)!r}: unreadable (its {width}x{height} px could not be decoded)")
    return image


def _read_image(path: Path) -> np.ndarray:
    # IMREAD_COLOR turns grey and RGBA files into 3-channel 8-bit BGR, which is what we want.
    bgr = _read_checked(path, "image", cv2.IMREAD_COLOR)
    return np.ascontiguousarray(bgr[:, :, ::-1])


def _read_labels(path: Path) -> np.ndarray:
    raw = _read_checked(path, "label image", cv2.IMREAD_UNCHANGED)
    if raw.dtype != np.uint8:
        raise WorldError(f"label image {str(path)!r}: must be 8-bit class ids, got {raw.dtype}")
    if raw.ndim == 3:
        # Many tools save grey masks as RGB(A); accept that only when the colour channels agree.
        if raw.shape[2] < 3:
            raise WorldError(f"label image {str(path)!r}: must be one channel of class ids, got {raw.shape[2]} channels")
        colour = raw[:, :, :3]
        if not (np.array_equal(colour[:, :, 0], colour[:, :, 1]) and np.array_equal(colour[:, :, 0], colour[:, :, 2])):
            raise WorldError(
                f"label image {str(path)!r}: must be one channel of class ids, got {raw.shape[2]} channels "
                "that differ (a colour mask? map its colours to ids first)"
            )
        raw = np.ascontiguousarray(colour[:, :, 0])
    return raw


def _check_label_ids(labels: np.ndarray, classes: Mapping[int, ClassInfo], what: str) -> None:
    # bincount over the whole map is one fast pass (~0.1 s for 6400^2); np.unique would sort it.
    present = np.flatnonzero(np.bincount(labels.ravel(), minlength=256))
    unknown = [int(i) for i in present if int(i) not in classes]
    if unknown:
        raise WorldError(
            f"{what}: label ids {unknown} are used in the image but absent from 'classes' "
            f"(listed: {sorted(classes)})"
        )
