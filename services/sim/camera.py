"""The downward camera: renders what a nadir pinhole camera sees of a `World` from a pose.

Data flow: pose (x_m, y_m, alt_agl_m, yaw_rad) + `CameraModel` -> one affine map from output
pixels to world pixels -> `cv2.warpAffine` on the world image and on the world labels ->
(image_rgb, labels, valid_mask). The image is read from the level of a half-octave pyramid
closest to the needed scale (each level is an area average, so this is area resampling at a
fraction of its cost): nearest lookup when the residual scale is within a quarter octave of 1,
bilinear when the view magnifies the world (low altitude) or when asked for. Labels are always
sampled nearest from full resolution: class ids must never be blended.

Geometry: the camera is fixed to the body looking along body down; image up = body forward, image
right = body right; yaw_rad is the heading (0 = north, +pi/2 = east, NED convention). Level
(roll = pitch = 0, or a gimbal) the ground footprint's half-width is tan(hfov / 2) * alt_agl_m and
spans width_px / 2 pixels, so every output pixel covers 2 * tan(hfov / 2) * alt / width_px metres;
pixels are square, and the map from output to world pixels is affine (`cv2.warpAffine`). Tilted
(roll_rad, pitch_rad FRD, aerospace ZYX order: yaw, then pitch, then roll) each pixel's ray is
rotated by the attitude and cut with the flat ground, a homography (`cv2.warpPerspective`): nose up
(pitch > 0) moves the view forward, right wing down (roll > 0) moves it left, and the footprint
becomes a trapezoid. A tilt that puts any corner ray at or above the horizon is a CameraError. Output pixels whose centre falls
outside the world get label 255 (OUT_OF_WORLD_LABEL), valid_mask False and the flat neutral grey
of unknown ground (OUT_OF_WORLD_RGB): the world never wraps.

The pyramid is built lazily (only the levels an altitude needs), once per world, and cached in
a weak dictionary so it dies with the world.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
import weakref
from dataclasses import dataclass

import cv2
import numpy as np

from dovesei.shared import footprint
from dovesei.shared.footprint import tilt_rotation
from dovesei.shared.errors import DoveseiError
from dovesei.shared.validate import is_number
from dovesei.sim.world import OUT_OF_WORLD_LABEL, World

log = logging.getLogger(__name__)

# Beyond the map the ground is unknown: a flat neutral grey with no texture, so a segmenter finds
# nothing there to read as a surface (and the label is OUT_OF_WORLD_LABEL, which every simulated
# perception profile reads as unsafe).
OUT_OF_WORLD_RGB = (128, 128, 128)


class CameraError(DoveseiError, ValueError):
    """A camera model or pose that cannot be rendered (bad size, FOV, altitude)."""


@dataclass(frozen=True)
class CameraModel:
    """A square-pixel nadir pinhole camera; the defaults are the reference's (352 px, 73 deg)."""

    width_px: int = 352
    height_px: int = 352
    hfov_deg: float = footprint.REFERENCE_HFOV_DEG

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 8192:
                raise CameraError(f"CameraModel.{name} must be an integer in 1..8192, got {value!r}")
        if not (is_number(self.hfov_deg) and 0.0 < self.hfov_deg < 180.0):
            raise CameraError(f"CameraModel.hfov_deg must be in (0, 180), got {self.hfov_deg!r}")

    @property
    def hfov_rad(self) -> float:
        return math.radians(self.hfov_deg)

    def half_width_m(self, alt_agl_m: float) -> float:
        """Half the ground footprint's width (across the image's columns) at an altitude."""
        return footprint.half_width_m(alt_agl_m, self.hfov_rad)

    def half_height_m(self, alt_agl_m: float) -> float:
        """Half the footprint's height (along the image's rows); pixels are square."""
        return self.half_width_m(alt_agl_m) * self.height_px / self.width_px

    def metres_per_px(self, alt_agl_m: float) -> float:
        """Ground size of one output pixel at an altitude."""
        return footprint.metres_per_px(alt_agl_m, self.hfov_rad, self.width_px)


class _Pyramid:
    """Lazily built half-octave RGBA levels of one world's image (level j is ~2^(j/2) times smaller).

    Half-octave steps keep the residual scale of the final warp within [0.84, 1.19], where a
    nearest-neighbour lookup on an area-averaged level is nearly as good as area resampling.
    Levels carry a padding alpha channel because OpenCV warps 4-channel uint8 images about twice
    as fast as 3-channel ones (measured: ~0.57 vs ~1.0 ms bilinear per 352x352 frame, one core).
    """

    def __init__(self, image_rgb: np.ndarray) -> None:
        self._image_rgb = image_rgb
        self._levels: list[np.ndarray] = []
        # Per level: (scale_x, offset_x, scale_y, offset_y) with c0 = scale * cL + offset in pixel
        # coordinates whose integers are pixel centres (col for x, row for y).
        self._geometry: list[tuple[float, float, float, float]] = []
        self._lock = threading.Lock()  # a service may render from more than one thread
        self.build_s = 0.0  # wall seconds spent building levels so far (reported by benchmarks)

    def level(self, index: int) -> tuple[np.ndarray, tuple[float, float, float, float]]:
        """Level min(index, deepest useful one), built on demand, and its geometry."""
        with self._lock:
            while len(self._levels) <= index:
                t0 = time.perf_counter()
                if not self._levels:
                    self._levels.append(cv2.cvtColor(self._image_rgb, cv2.COLOR_RGB2RGBA))
                    self._geometry.append((1.0, 0.0, 1.0, 0.0))
                else:
                    # Even levels halve the level two below exactly (cheap, and geometry stays exact
                    # after cropping to even size); odd levels shrink the one below by sqrt(2) from
                    # the nearest even level, so only level 1 pays OpenCV's slow non-integer area path.
                    j = len(self._levels)
                    parent = j - 2 if j >= 2 else 0
                    prev = self._levels[parent]
                    if j % 2 == 0:
                        h, w = prev.shape[0] // 2, prev.shape[1] // 2
                        prev = prev[: 2 * h, : 2 * w]
                    else:
                        h, w = round(prev.shape[0] / math.sqrt(2.0)), round(prev.shape[1] / math.sqrt(2.0))
                    if h < 8 or w < 8:
                        break  # too small to be useful; the caller keeps the last level
                    self._levels.append(cv2.resize(prev, (w, h), interpolation=cv2.INTER_AREA))
                    # A resize maps child centre c to parent (c + 0.5) * r - 0.5, r = parent / child size.
                    sx, ox, sy, oy = self._geometry[parent]
                    rx, ry = prev.shape[1] / w, prev.shape[0] / h
                    self._geometry.append((sx * rx, sx * (0.5 * rx - 0.5) + ox, sy * ry, sy * (0.5 * ry - 0.5) + oy))
                self._levels[-1].flags.writeable = False
                self.build_s += time.perf_counter() - t0
                log.info("camera pyramid level %d: %dx%d px, %.0f MB, built in %.2f s", len(self._levels) - 1,
                         self._levels[-1].shape[1], self._levels[-1].shape[0], self._levels[-1].nbytes / 1e6,
                         time.perf_counter() - t0)
            top = min(index, len(self._levels) - 1)
            return self._levels[top], self._geometry[top]


_PYRAMIDS: "weakref.WeakKeyDictionary[World, _Pyramid]" = weakref.WeakKeyDictionary()
_PYRAMIDS_LOCK = threading.Lock()


def _pyramid(world: World) -> _Pyramid:
    with _PYRAMIDS_LOCK:
        pyr = _PYRAMIDS.get(world)
        if pyr is None:
            pyr = _PYRAMIDS[world] = _Pyramid(world.image_rgb)
        return pyr


def pixel_to_world_affine(
    world: World, x_m: float, y_m: float, alt_agl_m: float, yaw_rad: float, cam: CameraModel
) -> np.ndarray:
    """2x3 matrix taking output pixel (col, row) to world pixel (col, row), centres at integers."""
    k = cam.metres_per_px(alt_agl_m) / world.gsd_m  # world pixels per output pixel
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    cu, cv_ = (cam.width_px - 1) / 2.0, (cam.height_px - 1) / 2.0  # optical axis, between pixels if even
    col0 = x_m / world.gsd_m - 0.5  # world pixel under the camera
    row0 = world.height_px - y_m / world.gsd_m - 0.5
    # An output offset (du right, dv down) is body (forward = -dv, right = du) times the pixel size;
    # rotated by the heading, east = c*right + s*forward and north = c*forward - s*right. World
    # columns grow east and rows grow south, so col = col0 + k(c du - s dv), row = row0 + k(s du + c dv).
    return np.array(
        [
            [k * c, -k * s, col0 - k * c * cu + k * s * cv_],
            [k * s, k * c, row0 - k * s * cu - k * c * cv_],
        ],
        dtype=np.float64,
    )


# The steepest corner ray a tilted render accepts: cos of 85 deg from straight down. Beyond it the
# footprint runs to the horizon (and a homography would wrap the sky onto the ground).
_MIN_RAY_DOWN = math.cos(math.radians(85.0))


def pixel_to_world_homography(
    world: World, x_m: float, y_m: float, alt_agl_m: float, yaw_rad: float, roll_rad: float, pitch_rad: float,
    cam: CameraModel,
) -> np.ndarray:
    """3x3 matrix taking output pixel (col, row, 1) to world pixel (col, row) in homogeneous form.

    Pixel -> body ray (forward = -(row - cv) / f, right = (col - cu) / f, down = 1) -> heading-level
    ray L by the tilt -> ground point (forward, right) = alt * (L_f, L_r) / L_d -> world pixel by the
    heading, exactly as `pixel_to_world_affine` for a level camera (which this equals at zero tilt).
    """
    f_px = footprint.focal_px(cam.width_px, cam.hfov_rad)
    cu, cv_ = (cam.width_px - 1) / 2.0, (cam.height_px - 1) / 2.0
    ray = np.array([[0.0, -1.0 / f_px, cv_ / f_px],
                    [1.0 / f_px, 0.0, -cu / f_px],
                    [0.0, 0.0, 1.0]], dtype=np.float64)
    level = tilt_rotation(roll_rad, pitch_rad) @ ray
    w, h = cam.width_px, cam.height_px
    corners = level @ np.array([[0, w - 1, 0, w - 1], [0, 0, h - 1, h - 1], [1, 1, 1, 1]], dtype=np.float64)
    if np.min(corners[2] / np.linalg.norm(corners, axis=0)) <= _MIN_RAY_DOWN:
        raise CameraError(f"tilt roll {math.degrees(roll_rad):.1f} deg, pitch {math.degrees(pitch_rad):.1f} deg "
                          f"puts the {cam.hfov_deg:g} deg view within 5 deg of the horizon: not renderable")
    a = alt_agl_m / world.gsd_m
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    col0 = x_m / world.gsd_m - 0.5
    row0 = world.height_px - y_m / world.gsd_m - 0.5
    # East = c*right + s*forward, north = c*forward - s*right (as in the affine map); world columns
    # grow east and rows south, and everything is divided by the ray's down component L_d.
    to_world = np.array([[a * s, a * c, col0],
                         [-a * c, a * s, row0],
                         [0.0, 0.0, 1.0]], dtype=np.float64)
    return to_world @ level


def optical_axis_ground_m(x_m: float, y_m: float, alt_agl_m: float, yaw_rad: float, roll_rad: float = 0.0,
                          pitch_rad: float = 0.0) -> tuple[float, float]:
    """Where the camera's optical axis meets flat ground (world metres, x east, y north)."""
    fwd, right, down = tilt_rotation(roll_rad, pitch_rad) @ np.array([0.0, 0.0, 1.0])
    fwd_m, right_m = alt_agl_m * fwd / down, alt_agl_m * right / down
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return x_m + c * right_m + s * fwd_m, y_m + c * fwd_m - s * right_m


def ground_point_m(x_m: float, y_m: float, alt_agl_m: float, yaw_rad: float, row_px: float, col_px: float,
                   cam: CameraModel, roll_rad: float = 0.0, pitch_rad: float = 0.0) -> tuple[float, float]:
    """World (x_m east, y_m north) of the flat ground an output pixel (row, col; integers at pixel
    centres) shows from this pose: the renderer's own ray (`pixel_to_world_homography`), in metres,
    for the judge to place what a policy saw in a frame."""
    f_px = footprint.focal_px(cam.width_px, cam.hfov_rad)
    body = np.array([-(row_px - (cam.height_px - 1) / 2.0) / f_px, (col_px - (cam.width_px - 1) / 2.0) / f_px, 1.0])
    fwd, right, down = tilt_rotation(roll_rad, pitch_rad) @ body
    if down <= _MIN_RAY_DOWN:
        raise CameraError(f"pixel ({row_px:.1f}, {col_px:.1f}) looks within 5 deg of the horizon: no ground point")
    fwd_m, right_m = alt_agl_m * fwd / down, alt_agl_m * right / down
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return x_m + c * right_m + s * fwd_m, y_m + c * fwd_m - s * right_m


def _level_affine(m0: np.ndarray, geometry: tuple[float, float, float, float]) -> np.ndarray:
    # Output pixel -> level-0 pixel (m0), then level 0 -> level: cL = (c0 - offset) / scale.
    # Works for a 2x3 affine and a 3x3 homography alike (only the first two rows change).
    sx, ox, sy, oy = geometry
    m = m0.copy()
    m[0] = (m0[0] - m0[-1] * ox) / sx if m0.shape[0] == 3 else (m0[0] - [0.0, 0.0, ox]) / sx
    m[1] = (m0[1] - m0[-1] * oy) / sy if m0.shape[0] == 3 else (m0[1] - [0.0, 0.0, oy]) / sy
    return m


NEAREST_MIN_SCALE = 2.0 ** -0.25  # below this residual scale the warp magnifies: bilinear is needed

# Ground detail (`render(..., ground_detail=True)`, the sim's odometry views): a world's texture
# holds nothing finer than its own pixel (Dubai's orthophoto 1 m, the synthetic worlds 0.25 m), so
# a view that magnifies it (0.09 m per pixel at 20 m, 320 px) is a smooth blur in which the
# camera's visual velocity finds no corners, where a real camera at 20 m sees sand ripples,
# gravel, grass tufts and paving joints. A modelling choice, not a measured value: a faint
# periodic texture fixed to the ground, sd DETAIL_SD_GREY grey levels at 0.2-0.8 m wavelengths,
# faded in as the view magnifies the world (none at 1 world pixel per view pixel or coarser, full
# at 4x magnification), and never on water (reflections and waves move: a camera must not find a
# ground velocity there).
DETAIL_GSD_M = 0.05
DETAIL_SIDE_PX = 512  # the texture repeats every 25.6 m
DETAIL_SD_GREY = 6.0
DETAIL_WAVELENGTHS_PX = (4, 8, 16)
WATER_WORDS = ("water", "sea", "ocean", "lake", "river", "pond", "pool", "canal", "harbour", "harbor")


def render(
    world: World,
    x_m: float,
    y_m: float,
    alt_agl_m: float,
    yaw_rad: float,
    cam: CameraModel = CameraModel(),
    *,
    roll_rad: float = 0.0,
    pitch_rad: float = 0.0,
    with_labels: bool = True,
    with_image: bool = True,
    interpolation: str = "auto",
    t_s: float = 0.0,
    ground_detail: bool = False,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray]:
    """The camera's view: (image_rgb HxWx3 uint8, labels HxW uint8 or None, valid_mask HxW bool).

    roll_rad and pitch_rad tilt the body-fixed camera (both 0: the nadir view of a level vehicle or
    a gimbal, by the affine map); any tilt renders the perspective view of the tilted pinhole.

    labels is None when the world has none or with_labels is False (labels cost ~25 % of a frame);
    image is None with with_image=False (a consumer of the labels alone skips the costly warp).
    t_s: the time (seconds since the episode began) at which the world's people and cars are
    drawn (`World.population`, at the view's own resolution). interpolation "auto" reads the half-octave pyramid level closest to the needed scale with a
    nearest lookup (the level already averaged the right area) and switches to bilinear where the
    view magnifies the world (low altitude); "linear" is bilinear at every scale: softer, and
    ~1.4x slower over an episode's mix of altitudes (measured with bench_render).
    ground_detail: add the faint texture finer than the world's own pixel where the view magnifies
    it (DETAIL_SD_GREY above; the image only, labels untouched).
    """
    if not (is_number(alt_agl_m) and alt_agl_m > 0.0):
        raise CameraError(f"alt_agl_m must be finite and > 0 to render, got {alt_agl_m!r}")
    if not (is_number(x_m) and is_number(y_m) and is_number(yaw_rad) and is_number(roll_rad)
            and is_number(pitch_rad)):
        raise CameraError(f"pose must be finite, got x_m={x_m!r} y_m={y_m!r} yaw_rad={yaw_rad!r} "
                          f"roll_rad={roll_rad!r} pitch_rad={pitch_rad!r}")
    if interpolation not in ("auto", "linear"):
        raise CameraError(f"interpolation must be 'auto' or 'linear', got {interpolation!r}")
    size = (cam.width_px, cam.height_px)
    if roll_rad == 0.0 and pitch_rad == 0.0:
        m0 = pixel_to_world_affine(world, x_m, y_m, alt_agl_m, yaw_rad, cam)
        k = cam.metres_per_px(alt_agl_m) / world.gsd_m  # world pixels per output pixel
        warp = cv2.warpAffine
    else:
        m0 = pixel_to_world_homography(world, x_m, y_m, alt_agl_m, yaw_rad, roll_rad, pitch_rad, cam)
        # The pyramid level follows the scale on the optical axis (slant range = alt / cos(tilt));
        # the far edge of a strongly tilted view is then slightly aliased, the near edge soft.
        k = cam.metres_per_px(alt_agl_m / float(tilt_rotation(roll_rad, pitch_rad)[2, 2])) / world.gsd_m
        warp = cv2.warpPerspective
    # Border pixels are replicated (cheaper than a constant border in OpenCV's warp) and then
    # overwritten from the analytic mask below.
    image = None
    if with_image:
        src, geometry = _pyramid(world).level(_level_index(k))
        nearest = interpolation == "auto" and k / geometry[0] >= NEAREST_MIN_SCALE
        rgba = warp(src, _level_affine(m0, geometry), size,
                    flags=(cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_REPLICATE)
        image = cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB)
    labels = None
    if world.labels is not None and with_labels:
        labels = warp(world.labels, m0, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=OUT_OF_WORLD_LABEL)
    if ground_detail and image is not None and k < 1.0:
        _add_ground_detail(image, world, m0, k, labels)
    if world.population is not None and (image is not None or labels is not None):
        # People and cars at this view's own resolution; those the texture already holds (baked)
        # only when the view is finer than the texture (k < 1 world pixel per output pixel), and
        # into the image only: their labels are the world's own, sampled above like all ground.
        world.population.draw(image, labels, world_m_to_output_px(world, m0), t_s, skip_baked=k >= 1.0,
                              baked_labels=False)
    valid = _valid_mask(world, m0, cam)
    if valid is None:
        valid = np.ones((cam.height_px, cam.width_px), dtype=bool)
    else:
        # One source of truth for "outside": the analytic mask, not each warp's own border rounding.
        if image is not None:
            image[~valid] = OUT_OF_WORLD_RGB
        if labels is not None:
            labels[~valid] = OUT_OF_WORLD_LABEL
    return image, labels, valid


@functools.cache
def _detail_texture() -> np.ndarray:
    """The periodic detail texture (DETAIL_SIDE_PX square, float32, mean 0, sd 1, read-only), built once."""
    rng = np.random.default_rng(20261206)
    side = DETAIL_SIDE_PX
    out = np.zeros((side, side), np.float32)
    for wavelength in DETAIL_WAVELENGTHS_PX:
        n = side // wavelength
        coarse = np.tile(rng.standard_normal((n, n)).astype(np.float32), (3, 3))
        # Upsampled from three periods and cut from the middle: seamless where it repeats.
        out += cv2.resize(coarse, (3 * side, 3 * side), interpolation=cv2.INTER_CUBIC)[side:2 * side, side:2 * side]
    out -= out.mean()
    out /= out.std()
    out.flags.writeable = False
    return out


def _water_ids(world: World) -> list[int]:
    """The world's water classes (by name: WATER_WORDS), which get no ground detail."""
    return [cid for cid, info in world.classes.items() if any(word in info.name.lower() for word in WATER_WORDS)]


def _add_ground_detail(image: np.ndarray, world: World, m0: np.ndarray, k: float, labels: np.ndarray | None) -> None:
    """`render`'s ground detail, in place: the texture fixed to the world, faded in with the view's
    magnification 1 / k, none on water classes (`labels`: the view's, when rendered)."""
    fade = min(1.0, math.log2(1.0 / k) / 2.0)
    if fade <= 0.0:
        return
    h, w = image.shape[:2]
    affine = m0.shape[0] == 2
    warp = cv2.warpAffine if affine else cv2.warpPerspective
    # Output pixel -> world pixel (m0) -> detail pixel, the translation brought within one period
    # of the texture (it repeats) so the warp's fixed-point coordinates stay small.
    m = np.vstack([m0, [0.0, 0.0, 1.0]]) if affine else m0.astype(np.float64)
    m[:2] *= world.gsd_m / DETAIL_GSD_M
    centre = m @ np.array([w / 2.0, h / 2.0, 1.0])
    for axis in (0, 1):
        m[axis] -= math.floor(centre[axis] / centre[2] / DETAIL_SIDE_PX) * DETAIL_SIDE_PX * m[2]
    detail = warp(_detail_texture(), m[:2] if affine else m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                  borderMode=cv2.BORDER_WRAP)
    detail *= np.float32(fade * DETAIL_SD_GREY)
    water = _water_ids(world) if world.labels is not None else []
    if water:
        if labels is None:  # the view's labels were not asked for: only the water needs them
            labels = warp(world.labels, m0, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=OUT_OF_WORLD_LABEL)
        detail[np.isin(labels, water)] = 0.0
    out = image.astype(np.float32)
    out += detail[..., None]
    np.clip(out, 0.0, 255.0, out=out)
    image[...] = out.astype(np.uint8)


def world_m_to_output_px(world: World, m0: np.ndarray) -> np.ndarray:
    """3x3 map from world metres (x east, y north, 1) to output pixels (col, row, w), the inverse of
    a view's output -> world pixel map m0 (2x3 affine or 3x3 homography) composed with the world's
    metres -> pixel scale: what `objects.ObjectLayer.draw` takes."""
    m = np.vstack([m0, [0.0, 0.0, 1.0]]) if m0.shape[0] == 2 else m0
    g = world.gsd_m
    metres_to_px = np.array([[1.0 / g, 0.0, -0.5], [0.0, -1.0 / g, world.height_px - 0.5], [0.0, 0.0, 1.0]])
    return np.linalg.inv(m) @ metres_to_px


# The virtual camera a ground square is rendered through: a level nadir camera whose footprint is
# the square (any field of view gives the same affine map; this one keeps `render`'s checks happy).
_SQUARE_HFOV_DEG = 73.0


def render_ground_square(world: World, centre_x_m: float, centre_y_m: float, yaw_rad: float, side_m: float,
                         out_px: int, *, with_image: bool = True, with_labels: bool = True,
                         t_s: float = 0.0) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray]:
    """A square of the world `side_m` wide centred on (x east, y north), image up along the heading
    `yaw_rad`, at `out_px` a side: what a close-look crop shows, people and cars where they are at
    `t_s` (seconds since the episode began) drawn at the crop's resolution. Same outputs as `render`."""
    if not (is_number(side_m) and side_m > 0.0):
        raise CameraError(f"side_m must be finite and > 0, got {side_m!r}")
    cam = CameraModel(out_px, out_px, _SQUARE_HFOV_DEG)
    alt_m = side_m / footprint.width_m(1.0, cam.hfov_rad)  # the altitude whose footprint is the square
    return render(world, centre_x_m, centre_y_m, alt_m, yaw_rad, cam, with_image=with_image, with_labels=with_labels,
                  t_s=t_s)


def _level_index(k: float) -> int:
    """The half-octave level whose scale is closest (in log terms) to k world pixels per output pixel."""
    return max(0, int(round(2.0 * math.log2(k)))) if k > 1.0 else 0


def _valid_mask(world: World, m0: np.ndarray, cam: CameraModel) -> np.ndarray | None:
    """Pixels whose centre maps inside the world; None (all valid) in the common fully-inside case.

    m0 is the 2x3 affine map of a level camera or the 3x3 homography of a tilted one.
    """
    w, h = cam.width_px, cam.height_px
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], dtype=np.float64)
    cc = corners @ m0.T  # (4, 2) world (col, row), or (4, 3) homogeneous
    if m0.shape[0] == 3:
        cc = cc[:, :2] / cc[:, 2:]
    lo, hi_c, hi_r = -0.5, world.width_px - 0.5, world.height_px - 0.5
    # Affine, or a homography with the whole view below the horizon (checked when it was built):
    # straight lines stay straight and the image is convex, so the corners bound every pixel centre.
    if cc[:, 0].min() >= lo and cc[:, 0].max() < hi_c and cc[:, 1].min() >= lo and cc[:, 1].max() < hi_r:
        return None
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    col = m0[0, 0] * u + m0[0, 1] * v + m0[0, 2]
    row = m0[1, 0] * u + m0[1, 1] * v + m0[1, 2]
    if m0.shape[0] == 3:
        den = m0[2, 0] * u + m0[2, 1] * v + m0[2, 2]
        col, row = col / den, row / den
    return (col >= lo) & (col < hi_c) & (row >= lo) & (row < hi_r)


def bench_render(world: World, n: int = 2000, cam: CameraModel = CameraModel(), seed: int = 0,
                 poses: str = "trajectory", clock: str = "wall", **render_options: object) -> float:
    """Renders per second on one OpenCV thread over n seeded poses (pyramid built beforehand).

    poses="trajectory": descents from 100 m to 20 m at a random heading, drifting ~0.5 m per frame,
    as an episode renders them (consecutive frames share cache lines); poses="random": every
    frame anywhere in the world at 20-100 m and any yaw (cold caches: a pessimistic bound).
    clock="wall" counts wall seconds, clock="cpu" this thread's CPU seconds (robust when other
    processes share the machine). render_options go to `render` (with_labels, interpolation).
    """
    if n < 1 or poses not in ("trajectory", "random") or clock not in ("wall", "cpu"):
        raise ValueError(f"bench_render: need n >= 1, poses trajectory|random, clock wall|cpu; got {n}, {poses}, {clock}")
    rng = np.random.default_rng(seed)
    if poses == "random":
        table = np.column_stack([
            rng.uniform(0.0, world.width_m, n), rng.uniform(0.0, world.height_m, n),
            rng.uniform(20.0, 100.0, n), rng.uniform(-math.pi, math.pi, n),
        ])
    else:
        per_path = 100
        starts = rng.uniform(0.1, 0.9, (n // per_path + 1, 3))  # away from the edges, as episodes start
        rows = []
        for i in range(n):
            sx, sy, syaw = starts[i // per_path]
            j = i % per_path
            rows.append((sx * world.width_m + 0.5 * j, sy * world.height_m + 0.3 * j,
                         100.0 - 80.0 * j / (per_path - 1), (syaw - 0.5) * 2.0 * math.pi))
        table = np.array(rows)
    prebuild_pyramid(world, cam, 100.0)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # the target is per core; OpenCV would otherwise spread warps over all
    timer = time.perf_counter if clock == "wall" else time.thread_time
    try:
        t0 = timer()
        for x_m, y_m, alt_m, yaw in table:
            render(world, float(x_m), float(y_m), float(alt_m), float(yaw), cam, **render_options)
        elapsed_s = timer() - t0
    finally:
        cv2.setNumThreads(threads)
    return n / elapsed_s


def prebuild_pyramid(world: World, cam: CameraModel = CameraModel(), max_alt_m: float = 100.0) -> float:
    """Build every pyramid level up to what max_alt_m needs; returns the total build seconds so far."""
    pyr = _pyramid(world)
    pyr.level(_level_index(cam.metres_per_px(max_alt_m) / world.gsd_m))
    return pyr.build_s
