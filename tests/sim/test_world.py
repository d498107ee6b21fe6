"""World model and world-folder loading: coordinates, safe_lut, and a clear error per broken input."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import dovesei.sim
from dovesei.shared.codec import image_header_size
from dovesei.shared.messages import FieldError
from dovesei.sim.world import WORLD_ALIASES, ClassInfo, World, WorldError, load_world, shipped_world

# The CC0 Dubai tile ships inside the package (package data), found from the installed module.
DUBAI = Path(dovesei.sim.__file__).parent / "worlds" / "dubai-tile8-004"


def small_world(h: int = 4, w: int = 6, gsd_m: float = 0.5) -> World:
    labels = np.zeros((h, w), np.uint8)
    labels[0, :] = 1
    return World(np.zeros((h, w, 3), np.uint8), labels, gsd_m,
                 {0: ClassInfo("grass", True), 1: ClassInfo("road", False)}, "small")


def write_folder(folder: Path, image: np.ndarray, labels: np.ndarray, meta: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "image.png"), image[:, :, ::-1])
    cv2.imwrite(str(folder / "labels.png"), labels)
    (folder / "world.json").write_text(json.dumps(meta))
    return folder


GOOD_META = {"gsd_m": 0.5, "image": "image.png", "labels": "labels.png",
             "classes": {"0": {"name": "grass", "safe": True}, "1": {"name": "road", "safe": False}}}


@pytest.fixture()
def good_folder(tmp_path: Path) -> Path:
    image = np.random.default_rng(0).integers(0, 255, (20, 30, 3), dtype=np.uint8)
    labels = np.zeros((20, 30), np.uint8)
    labels[5:10, 5:10] = 1
    return write_folder(tmp_path / "w", image, labels, GOOD_META)


def test_coordinates_round_trip_and_bottom_origin() -> None:
    world = small_world()
    assert world.width_m == 3.0 and world.height_m == 2.0
    # Pixel (row 0, col 0) is the top-left: north-west corner, so y is near the top (height).
    assert world.pixel_to_world(0, 0) == (0.25, 1.75)
    assert world.pixel_to_world(3, 5) == (2.75, 0.25)
    assert world.world_to_pixel(2.75, 0.25) == (3.0, 5.0)
    assert world.pixel_index(0.01, 0.01) == (3, 0)  # bottom-left pixel
    assert world.pixel_index(2.99, 1.99) == (0, 5)
    rows, cols = world.world_to_pixel(np.array([0.25, 1.25]), np.array([1.75, 0.75]))
    np.testing.assert_allclose(rows, [0.0, 2.0])
    np.testing.assert_allclose(cols, [0.0, 2.0])
    assert world.contains(0.0, 0.0) and not world.contains(3.0, 1.0) and not world.contains(1.0, -0.01)


def test_safe_lut_unlisted_ids_are_unsafe() -> None:
    lut = small_world().safe_lut
    assert lut.shape == (256,) and lut.dtype == bool
    assert lut[0] and not lut[1] and not lut[2:].any()


def test_world_arrays_become_read_only() -> None:
    world = small_world()
    with pytest.raises(ValueError):
        world.image_rgb[0, 0, 0] = 1


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"gsd_m": 0.0}, "gsd_m"),
        ({"gsd_m": float("nan")}, "gsd_m"),
        ({"labels": np.zeros((3, 6), np.uint8)}, "differ in size"),
        ({"image_rgb": np.zeros((4, 6), np.uint8)}, "image_rgb"),
        ({"classes": {255: ClassInfo("x", True)}}, "0..254"),
    ],
)
def test_world_rejects_bad_fields(kwargs: dict, match: str) -> None:
    base = dict(image_rgb=np.zeros((4, 6, 3), np.uint8), labels=np.zeros((4, 6), np.uint8), gsd_m=1.0,
                classes={0: ClassInfo("grass", True)}, name="t")
    base.update(kwargs)
    with pytest.raises(WorldError, match=match):
        World(**base)


def test_dubai_world_loads_with_its_classes() -> None:
    world = load_world(str(DUBAI))
    assert world.name == "dubai-tile8-004"
    assert world.image_rgb.shape == (1480, 2149, 3) and world.labels.shape == (1480, 2149)
    assert world.gsd_m == 1.0
    assert set(np.unique(world.labels)) == {1, 2, 3, 4, 5}
    assert world.classes[2] == ClassInfo("land (unpaved area)", True)
    assert [cid for cid in range(256) if world.safe_lut[cid]] == [2]
    # The same folder named through its world.json loads the same world.
    assert load_world(str(DUBAI / "world.json")).labels.shape == world.labels.shape


def test_good_folder_and_rgb_label_png_with_equal_channels(good_folder: Path) -> None:
    world = load_world(str(good_folder))
    assert world.labels[7, 7] == 1 and world.labels[0, 0] == 0
    grey = cv2.imread(str(good_folder / "labels.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(good_folder / "labels.png"), cv2.merge([grey, grey, grey]))
    np.testing.assert_array_equal(load_world(str(good_folder)).labels, world.labels)


def test_missing_world_json(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(WorldError, match="missing world.json"):
        load_world(str(tmp_path / "empty"))
    with pytest.raises(WorldError, match="no such folder"):
        load_world(str(tmp_path / "nowhere"))


@pytest.mark.parametrize("missing", ["image.png", "labels.png"])
def test_missing_image_or_labels_names_the_file(good_folder: Path, missing: str) -> None:
    (good_folder / missing).unlink()
    with pytest.raises(WorldError, match=missing):
        load_world(str(good_folder))


def test_unreadable_image(good_folder: Path) -> None:
    (good_folder / "image.png").write_bytes(b"not a png")
    with pytest.raises(WorldError, match="image.png.*unreadable"):
        load_world(str(good_folder))


def _claiming(encoded: bytes, side_px: int) -> bytes:
    """A small real JPEG or PNG whose header claims side_px x side_px (what the probes sent)."""
    buf = bytearray(encoded)
    if buf.startswith(b"\x89PNG"):
        buf[16:24] = side_px.to_bytes(4, "big") * 2  # IHDR width, height
        return bytes(buf)
    sof = next(i for i in range(2, len(buf) - 1) if buf[i] == 0xFF and buf[i + 1] in (0xC0, 0xC1, 0xC2))
    buf[sof + 5:sof + 9] = side_px.to_bytes(2, "big") * 2  # SOF height, width
    return bytes(buf)


@pytest.mark.parametrize(("name", "ext"), [("image", ".jpg"), ("labels", ".png")])
def test_a_world_image_claiming_30000_px_is_refused_before_decoding(good_folder: Path, name: str, ext: str) -> None:
    # Was: a 631-byte image.jpg claiming 30000x30000 px took 68 s and 5.2 GB to decode, a labels.png
    # 19 s and 1.8 GB; the header alone says it is no world.
    pixels = np.zeros((8, 8, 3) if name == "image" else (8, 8), np.uint8)
    probe = _claiming(cv2.imencode(ext, pixels)[1].tobytes(), 30000)
    assert len(probe) < 1000
    (good_folder / f"{name}{ext}").write_bytes(probe)
    meta = {**GOOD_META, name: f"{name}{ext}"}
    (good_folder / "world.json").write_text(json.dumps(meta))
    t0 = time.perf_counter()
    with pytest.raises(WorldError, match=rf"{name}{ext}.*30000x30000 px, outside 1..16384 px.*before decoding"):
        load_world(str(good_folder))
    assert time.perf_counter() - t0 < 5.0  # no decode: well under a second on an idle host


def test_header_sizes_of_every_world_format_match_the_decoded_image() -> None:
    image = np.random.default_rng(1).integers(0, 255, (13, 21, 3), dtype=np.uint8)
    for ext in (".jpg", ".png", ".bmp", ".tif"):
        buf = cv2.imencode(ext, image)[1].tobytes()
        assert image_header_size(buf) == (13, 21), ext
    with pytest.raises(FieldError, match="not a JPEG, PNG, BMP or TIFF"):
        image_header_size(b"GIF89a....")


def test_label_size_mismatch(good_folder: Path) -> None:
    cv2.imwrite(str(good_folder / "labels.png"), np.zeros((21, 30), np.uint8))
    with pytest.raises(WorldError, match=r"labels.png.*30x21.*image.png.*30x20"):
        load_world(str(good_folder))


def test_colour_label_image_refused(good_folder: Path) -> None:
    colour = np.zeros((20, 30, 3), np.uint8)
    colour[:, :, 2] = 1
    cv2.imwrite(str(good_folder / "labels.png"), colour)
    with pytest.raises(WorldError, match="one channel"):
        load_world(str(good_folder))


def test_unknown_label_id_is_named(good_folder: Path) -> None:
    labels = cv2.imread(str(good_folder / "labels.png"), cv2.IMREAD_GRAYSCALE)
    labels[0, 0], labels[1, 1] = 7, 9
    cv2.imwrite(str(good_folder / "labels.png"), labels)
    with pytest.raises(WorldError, match=r"label ids \[7, 9\].*absent from 'classes'"):
        load_world(str(good_folder))


@pytest.mark.parametrize("gsd", [None, "0.5", 0, -1.0, "nan", True])
def test_bad_gsd(good_folder: Path, gsd: object) -> None:
    meta = dict(GOOD_META)
    if gsd is None:
        del meta["gsd_m"]
    else:
        meta["gsd_m"] = float("nan") if gsd == "nan" else gsd
    (good_folder / "world.json").write_text(json.dumps(meta))  # json writes NaN as a bare NaN
    with pytest.raises(WorldError, match="gsd_m"):
        load_world(str(good_folder))


@pytest.mark.parametrize(
    "classes, match",
    [
        ([], "'classes' must be"),
        ({"x": {"name": "a", "safe": True}}, "integer class id"),
        ({"0": {"name": "a", "safe": "yes"}, "1": {"name": "b", "safe": False}}, "'safe' must be true or false"),
        ({"0": {"safe": True}, "1": {"name": "b", "safe": False}}, "'name'"),
        ({"0": {"name": "a", "safe": True}, "300": {"name": "b", "safe": False}}, "0..254"),
    ],
)
def test_malformed_classes(good_folder: Path, classes: object, match: str) -> None:
    (good_folder / "world.json").write_text(json.dumps(dict(GOOD_META, classes=classes)))
    with pytest.raises(WorldError, match=match):
        load_world(str(good_folder))


def test_broken_json_names_the_file(good_folder: Path) -> None:
    (good_folder / "world.json").write_text("{ not json")
    with pytest.raises(WorldError, match="world.json.*JSON"):
        load_world(str(good_folder))


def test_dubai_copy_with_a_class_removed(tmp_path: Path) -> None:
    copy = tmp_path / "dubai"
    shutil.copytree(DUBAI, copy)
    meta = json.loads((copy / "world.json").read_text())
    del meta["classes"]["5"]
    (copy / "world.json").write_text(json.dumps(meta))
    with pytest.raises(WorldError, match=r"label ids \[5\]"):
        load_world(str(copy))


def test_bad_spec_strings() -> None:
    with pytest.raises(WorldError, match="empty world spec"):
        load_world("  ")
    with pytest.raises(WorldError, match="synthetic"):
        load_world("synthetic:seed=abc")


def test_synthetic_spec_goes_through_the_generator(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("DOVESEI_CACHE", str(tmp_path))  # never touch the user's cache
    world = load_world("synthetic:seed=1,size_m=200,gsd_m=0.5")
    assert world.image_rgb.shape == (400, 400, 3) and world.gsd_m == 0.5
    assert world.classes[13] == ClassInfo("person", False) and world.classes[8] == ClassInfo("grass", True)
    assert set(np.unique(world.labels)) <= set(world.classes)
    again = load_world("synthetic:seed=1,size_m=200,gsd_m=0.5")  # from the disk cache this time
    np.testing.assert_array_equal(again.image_rgb, world.image_rgb)


def test_the_dubai_alias_names_the_shipped_folder() -> None:
    assert shipped_world("dubai") == DUBAI and WORLD_ALIASES["dubai"] == DUBAI.name
    assert load_world(" dubai ").name == "dubai-tile8-004"
    with pytest.raises(WorldError, match="known: dubai"):
        shipped_world("atlantis")
