"""Wire messages: frozen dataclasses with a schema name, a version and checked fields.

Data flows frame -> heatmap -> command:

    CameraFrame (sim or camera) --> SafetyHeatmap (segmenter) --> VelocityCommand (controller)
    VehicleState (sim or autopilot) ----------------------------^        ControllerStatus (controller)
    PromptSet (operator) --> segmenter            EpisodeResult (sim judge)

Every message carries a `Stamp` whose clock is named (sim time in simulation, the vehicle's clock
in flight, wall time otherwise) and the camera frame's sequence number travels downstream so
latency and staleness are measurable end to end. `sent_wall_s` is wall time at publication and is
used only to measure transport latency, never to decide anything.

Every field is checked when a message is built, by our code or by the codec, so a malformed
message cannot exist: types follow the annotations, floats are finite, arrays match an
`ArraySpec`. Units and frames are in the field names: FRD = body forward/right/down, NED =
north/east/down. Image up = body forward, image right = body right.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from dovesei.shared.errors import ConfigError
from dovesei.shared.validate import in_range

CLOCKS = ("sim", "wall", "vehicle")
MAX_STR_CHARS = 4096
MAX_SEQ_ITEMS = 256
MAX_IMAGE_SIDE_PX = 8192


# dtype -> (unsigned view, bit pattern of 1.0), for the [0, 1] range check.
_UNIT_BITS = {"float16": (np.uint16, 0x3C00), "float32": (np.uint32, 0x3F800000)}


class FieldError(ValueError):
    """A field of a message is missing, mistyped or out of range (the codec names the schema)."""


@dataclass(frozen=True)
class ArraySpec:
    """What an array field may hold: dtypes, number of dimensions, optional fixed channel count."""

    dtypes: tuple[str, ...]
    ndim: int
    channels: int | None = None  # required size of the last axis
    unit_range: bool = False  # float values must lie in [0, 1]
    image: bool = False  # may travel JPEG-compressed

    def check(self, name: str, arr: Any) -> None:
        if not isinstance(arr, np.ndarray):
            raise FieldError(f"field {name!r}: expected a numpy array, got {type(arr).__name__}")
        if arr.dtype.name not in self.dtypes:
            raise FieldError(f"field {name!r}: dtype {arr.dtype.name} not in {self.dtypes}")
        if arr.ndim != self.ndim:
            raise FieldError(f"field {name!r}: {arr.ndim} dimensions, expected {self.ndim}")
        if self.channels is not None and arr.shape[-1] != self.channels:
            raise FieldError(f"field {name!r}: last axis {arr.shape[-1]}, expected {self.channels}")
        if any(s < 1 or s > MAX_IMAGE_SIDE_PX for s in arr.shape[:2]):
            raise FieldError(f"field {name!r}: shape {arr.shape} outside 1..{MAX_IMAGE_SIDE_PX} px")
        if arr.dtype.kind == "f" and arr.size:
            if self.unit_range and arr.dtype.name in _UNIT_BITS:
                # IEEE floats in [+0, 1] are exactly the bit patterns <= that of 1.0; negatives, NaN
                # and inf all compare above it. One integer max, far faster than float compares.
                uint, one_bits = _UNIT_BITS[arr.dtype.name]
                ok = int(np.ascontiguousarray(arr).view(uint).max()) <= one_bits
            else:
                ok = bool(np.isfinite(arr).all())
            if not ok:
                raise FieldError(f"field {name!r}: values must be finite" + (" and in [0, 1]" if self.unit_range else ""))


Checker = Callable[[str, Any], None]

# Physical bounds of the numbers on the wire, wide enough for any real flight and narrow enough
# that no arithmetic downstream can overflow (a heatmap with alt_agl_m = 1e300 once crashed the
# controller). A record names its fields in `RANGES`; `_FIELD_RANGES` holds the defaults by field
# name, so a new message with a known field name is bounded without thinking about it.
ANGLE_RAD = (-2 * math.pi, 2 * math.pi)
SEQ = (-1, 2**62)
LATENCY_S = (-1e6, 1e6)  # cross-host wall differences can be negative when clocks disagree
_FIELD_RANGES: dict[str, tuple[float, float]] = {
    # Sim time, vehicle boot time (MAVLink's wraps at 49.7 days) or a process's monotonic clock:
    # three years of uptime is more than any of them; a command stamped 1e9 s never timed out.
    "t_s": (0.0, 1e8),
    "sent_wall_s": (0.0, 1e11),  # Unix time at publication; 0 = not set
    "seq": SEQ, "state_seq": SEQ, "frame_seq": SEQ, "await_frame_seq": SEQ,
    "alt_agl_m": (-1000.0, 100_000.0),
    "final_alt_m": (-1000.0, 100_000.0),
    "vel_body_frd_m_s": (-300.0, 300.0),
    "yaw_rate_rad_s": (-50.0, 50.0),
    "roll_rad": ANGLE_RAD, "pitch_rad": ANGLE_RAD, "yaw_rad": ANGLE_RAD,
    "hfov_rad": (0.0, math.pi),
    "pos_local_ned_m": (-1e7, 1e7),
    "inference_s": LATENCY_S, "frame_to_segmenter_s": LATENCY_S, "heatmap_to_controller_s": LATENCY_S,
    "policy_s": LATENCY_S,
    "heatmap_age_s": (-1.0, 1e9),
    "focus_radius_px": (0.0, 1e6), "target_row_px": (-1e6, 1e6), "target_col_px": (-1e6, 1e6),
    "threshold": (-1e6, 1e6),
    "sim_time_s": (0.0, 1e9), "path_length_m": (0.0, 1e9), "final_x_m": (-1e9, 1e9), "final_y_m": (-1e9, 1e9),
    "closest_unsafe_m": (0.0, 1e9),
}


def field_range(cls: type, name: str) -> tuple[float, float] | None:
    """The accepted [lo, hi] of a numeric field: the record's own `RANGES`, else the default by name."""
    own = getattr(cls, "RANGES", {})
    return own[name] if name in own else _FIELD_RANGES.get(name)


def _ranged(check: Checker, bounds: tuple[float, float], kind: type) -> Checker:
    lo, hi = bounds
    # A plain float (int) within finite bounds (within int64) passes every check at once: the
    # common case, as this runs for every field of every message.
    fast = kind if math.isfinite(lo) and math.isfinite(hi) and -(2**63) <= lo and hi < 2**63 else None

    def check_range(name: str, value: Any) -> None:
        if type(value) is fast and lo <= value <= hi:
            return
        check(name, value)
        if not lo <= value <= hi:  # cheap test first: this runs for every field of every message
            try:
                in_range(f"field {name!r}", value, lo, hi)
            except ConfigError as exc:
                raise FieldError(str(exc)) from None
    return check_range


def _check_float(name: str, value: Any) -> None:
    if type(value) is not float and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise FieldError(f"field {name!r}: expected a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise FieldError(f"field {name!r}: {value} is not finite")


def _check_int(name: str, value: Any) -> None:
    if type(value) is not int and (isinstance(value, bool) or not isinstance(value, (int, np.integer))):
        raise FieldError(f"field {name!r}: expected an integer, got {type(value).__name__}")
    if not -(2**63) <= int(value) < 2**63:
        raise FieldError(f"field {name!r}: integer {value} out of int64 range")


def _check_bool(name: str, value: Any) -> None:
    if not isinstance(value, bool):
        raise FieldError(f"field {name!r}: expected a boolean, got {type(value).__name__}")


def _check_str(name: str, value: Any) -> None:
    if not isinstance(value, str):
        raise FieldError(f"field {name!r}: expected a string, got {type(value).__name__}")
    if len(value) > MAX_STR_CHARS:
        raise FieldError(f"field {name!r}: string longer than {MAX_STR_CHARS} characters")


_SCALARS: dict[Any, Checker] = {float: _check_float, int: _check_int, bool: _check_bool, str: _check_str}


def _compile(hint: Any, owner: type, field_name: str) -> Checker:
    """A checker for one annotation, built once per record class (messages are built per tick)."""
    if hint in _SCALARS:
        bounds = field_range(owner, field_name) if hint in (int, float) else None
        return _SCALARS[hint] if bounds is None else _ranged(_SCALARS[hint], bounds, hint)
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        (inner,) = [a for a in typing.get_args(hint) if a is not type(None)]
        check_inner = _compile(inner, owner, field_name)

        def check_optional(name: str, value: Any) -> None:
            if value is not None:
                check_inner(name, value)
        return check_optional
    if hint is np.ndarray:
        return owner.ARRAYS[field_name].check
    if origin is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            check_item = _compile(args[0], owner, field_name)

            def check_seq(name: str, value: Any) -> None:
                if not isinstance(value, tuple):
                    raise FieldError(f"field {name!r}: expected a tuple, got {type(value).__name__}")
                if len(value) > MAX_SEQ_ITEMS:
                    raise FieldError(f"field {name!r}: more than {MAX_SEQ_ITEMS} items")
                for i, item in enumerate(value):
                    check_item(f"{name}[{i}]", item)
            return check_seq
        checks = [_compile(a, owner, field_name) for a in args]

        def check_fixed(name: str, value: Any) -> None:
            if not isinstance(value, tuple):
                raise FieldError(f"field {name!r}: expected a tuple, got {type(value).__name__}")
            if len(value) != len(checks):
                raise FieldError(f"field {name!r}: {len(value)} items, expected {len(checks)}")
            for i, (item, check) in enumerate(zip(value, checks)):
                check(f"{name}[{i}]", item)
        return check_fixed
    if dataclasses.is_dataclass(hint):
        def check_record(name: str, value: Any) -> None:
            if not isinstance(value, hint):
                raise FieldError(f"field {name!r}: expected {hint.__name__}, got {type(value).__name__}")
            # nested records checked themselves when built
        return check_record
    raise TypeError(f"{owner.__name__}.{field_name}: unsupported annotation {hint!r}")  # a bug in this module


_HINTS: dict[type, dict[str, Any]] = {}
_CHECKERS: dict[type, tuple[tuple[str, Checker], ...]] = {}


def field_hints(cls: type) -> dict[str, Any]:
    """Resolved annotations of a record's fields (cached: this runs for every message built)."""
    hints = _HINTS.get(cls)
    if hints is None:
        resolved = typing.get_type_hints(cls)
        hints = {f.name: resolved[f.name] for f in dataclasses.fields(cls)}
        _HINTS[cls] = hints
    return hints


def _checkers(cls: type) -> tuple[tuple[str, Checker], ...]:
    checks = _CHECKERS.get(cls)
    if checks is None:
        checks = tuple((name, _compile(hint, cls, name)) for name, hint in field_hints(cls).items())
        _CHECKERS[cls] = checks
    return checks


class Record:
    """Base of every wire record: checks all fields against their annotations when built."""

    ARRAYS: ClassVar[dict[str, ArraySpec]] = {}
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {}  # overrides of `_FIELD_RANGES` by field name

    def __post_init__(self) -> None:
        for name, check in _checkers(type(self)):
            check(name, getattr(self, name))
        self._check()

    def _check(self) -> None:
        """Cross-field checks of a record; override where there are any."""


# Registry of top-level messages by schema name; the codec dispatches on it.
SCHEMAS: dict[str, type[Message]] = {}


class Message(Record):
    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int]


def message(schema: str, version: int):
    """Class decorator: a frozen dataclass registered under `schema` at `version`."""

    def wrap(cls: type) -> type:
        cls = dataclass(frozen=True)(cls)
        cls.SCHEMA, cls.VERSION = schema, version
        if schema in SCHEMAS:
            raise TypeError(f"schema {schema!r} registered twice")
        SCHEMAS[schema] = cls
        return cls

    return wrap


@dataclass(frozen=True)
class Stamp(Record):
    """A time on a named clock: 'sim' (simulation seconds), 'vehicle' (autopilot boot), 'wall'."""

    t_s: float
    clock: str

    def _check(self) -> None:
        if self.clock not in CLOCKS:
            raise FieldError(f"field 'clock': {self.clock!r} is not one of {CLOCKS}")


@dataclass(frozen=True)
class ClassEntry(Record):
    """One class of a world's label map."""

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"id": (0, 254)}
    id: int
    name: str
    safe: bool

    def _check(self) -> None:
        if not 0 <= self.id <= 254:
            raise FieldError(f"field 'id': class id {self.id} outside 0..254 (255 marks outside the world)")


@dataclass(frozen=True)
class GroundTruth(Record):
    """Sim-only: the world's labels seen through the same camera (255 = outside the world)."""

    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"labels": ArraySpec(("uint8",), 2)}
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"centre_world_m": (-1e7, 1e7)}
    labels: np.ndarray
    classes: tuple[ClassEntry, ...]
    # The optical axis on the ground, world metres (x east, y north): the simulated perception
    # anchors its misreadings to the ground with it (the same ground misread the same way).
    centre_world_m: tuple[float, float] | None = None
    # The world's name: the simulated perception's per-world confusions and per-episode draws
    # are keyed by it ("" = unnamed: they are then the same for every world).
    world: str = ""


@message("dovesei.camera_frame", 1)
class CameraFrame(Message):
    """A nadir camera image with the vehicle's altitude and attitude at capture time."""

    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"image_rgb": ArraySpec(("uint8",), 3, channels=3, image=True)}
    vehicle_id: str
    seq: int
    stamp: Stamp
    image_rgb: np.ndarray  # (H, W, 3) RGB; image up = body forward
    hfov_rad: float
    alt_agl_m: float
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    sent_wall_s: float = 0.0
    truth: GroundTruth | None = None  # sim only; a real camera never has it

    def _check(self) -> None:
        if not 0.0 < self.hfov_rad < math.pi:
            raise FieldError(f"field 'hfov_rad': {self.hfov_rad} outside (0, pi)")
        if self.truth is not None and self.truth.labels.shape != self.image_rgb.shape[:2]:
            raise FieldError(
                f"field 'truth': labels {self.truth.labels.shape} differ from image {self.image_rgb.shape[:2]}"
            )


@message("dovesei.vehicle_state", 1)
class VehicleState(Message):
    """What the controller knows of the vehicle: altitude, velocity, attitude, mode."""

    vehicle_id: str
    seq: int
    stamp: Stamp
    alt_agl_m: float
    vel_body_frd_m_s: tuple[float, float, float]
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    armed: bool = True
    mode: str = ""
    pos_valid: bool = False  # the local position below is meaningful only when True
    pos_local_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Lockstep only: the controller must hold the heatmap of this frame before it decides this
    # tick (-1: nothing awaited). It is what makes a lockstep run independent of host speed.
    await_frame_seq: int = -1
    sent_wall_s: float = 0.0


@message("dovesei.visual_odometry", 1)
class VisualOdometry(Message):
    """The vehicle's ground velocity measured from two consecutive camera frames (onboard, no torch).

    `stamp` is the newer frame's capture stamp (the camera's clock); `prev_frame_seq`..`frame_seq`
    are the two frames compared. The velocity is in the body frame at the newer frame (rotation
    removed with the attitude, scaled by altitude and field of view): FRD of the full attitude
    `roll_rad`, `pitch_rad`, `yaw_rad` (ZYX, as MAVLink's ATTITUDE) that the newer frame was tagged
    with, so R(roll, pitch, yaw) @ vel gives NED. `quality` in [0, 1]: 0 means no estimate (low
    texture, blur, a bad altitude); an invalid estimate (`valid` False) has a zero velocity.
    `vel_var_m2_s2` is the variance per horizontal axis, what an EKF needs beside the value.
    """

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "quality": (0.0, 1.0), "vel_var_m2_s2": (0.0, 1e6), "dt_s": (0.0, 10.0), "prev_frame_seq": SEQ,
        "texture_share": (0.0, 1.0), "texture_offset": (-10.0, 10.0),
    }

    vehicle_id: str
    frame_seq: int
    prev_frame_seq: int
    stamp: Stamp
    vel_body_frd_m_s: tuple[float, float, float]
    vel_var_m2_s2: float
    quality: float
    valid: bool
    dt_s: float
    alt_agl_m: float
    sent_wall_s: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    # Where the newer frame's texture is, valid velocity or not: the share of its grid cells that
    # hold a trackable corner, and their centre on level ground in metres per metre of altitude,
    # (forward, right) of the heading (a coast at the left edge of a view over the sea: share
    # 0.2, offset (0, -0.6)). What a vehicle that lost its velocity over water flies towards.
    texture_share: float = 0.0
    texture_offset: tuple[float, float] = (0.0, 0.0)


@message("dovesei.safety_heatmap", 1)
class SafetyHeatmap(Message):
    """Per-pixel P(safe to land) for one camera frame; `seq` and `stamp` are the frame's."""

    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"prob_safe": ArraySpec(("uint8", "float16", "float32"), 2, unit_range=True)}
    vehicle_id: str
    seq: int
    stamp: Stamp
    prob_safe: np.ndarray  # uint8 means P * 255; float16/float32 are P itself
    alt_agl_m: float  # altitude when the frame was captured (the policy uses it, not the current one)
    hfov_rad: float
    backend: str  # "clipseg" or "simulated"
    simulated: bool
    prompt_set_id: str
    fusion: str
    inference_s: float
    frame_to_segmenter_s: float = 0.0
    sent_wall_s: float = 0.0

    def probability(self) -> np.ndarray:
        """P(safe) as float32 in [0, 1] whatever the wire dtype."""
        if self.prob_safe.dtype == np.uint8:
            return self.prob_safe.astype(np.float32) * np.float32(1.0 / 255.0)
        return self.prob_safe.astype(np.float32, copy=False)


@dataclass(frozen=True)
class StageLatency(Record):
    """Wall-clock seconds spent in each stage for the frame a command answers."""

    frame_to_segmenter_s: float
    inference_s: float
    heatmap_to_controller_s: float
    policy_s: float


@message("dovesei.velocity_command", 1)
class VelocityCommand(Message):
    """Body-frame FRD velocity and yaw rate: maps one-to-one onto MAVLink body-frame setpoints."""

    vehicle_id: str
    seq: int
    stamp: Stamp
    vel_body_frd_m_s: tuple[float, float, float]
    yaw_rate_rad_s: float = 0.0
    state_seq: int = -1  # the VehicleState tick this answers (lockstep pairs them)
    frame_seq: int = -1  # the frame whose heatmap produced it (-1: none yet)
    sent_wall_s: float = 0.0
    latency: StageLatency | None = None
    # The controller hands over here (short-range sensors / the autopilot's landing take over):
    # the only thing that ends a simulated episode as a landing (the judge never infers it from
    # the altitude alone, see dovesei.sim.judge).
    handover: bool = False


@message("dovesei.controller_status", 1)
class ControllerStatus(Message):
    """The controller's state for operators and reports; one per tick."""

    vehicle_id: str
    seq: int
    stamp: Stamp
    policy: str
    state: str
    watchdog: str  # "ok", "hold" (heatmap stale), "climb" (heatmap very stale), "state_stale"
    reason: str
    frame_seq: int
    heatmap_age_s: float  # -1 before the first heatmap
    focus_radius_px: float
    target_valid: bool = False
    target_row_px: float = 0.0
    target_col_px: float = 0.0
    threshold_valid: bool = False
    threshold: float = 0.0
    vel_body_frd_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    alt_agl_m: float = 0.0
    # Why the policy is in `state` (its last transition; `reason` is the watchdog's), and the spot
    # it chose in its own north/east frame, with clearance and confidence (policies with a map).
    policy_reason: str = ""
    spot_valid: bool = False
    spot_north_m: float = 0.0
    spot_east_m: float = 0.0
    spot_clearance_m: float = 0.0
    spot_confidence: float = 0.0
    handover: bool = False  # handed over (as the command's `handover`): what a judge ends an episode on
    # MAVLink navigation health (empty with the sim): which horizontal velocity the controller
    # trusts ("autopilot", "external-nav", "visual", "none"), whether GNSS and the autopilot's
    # position are lost, and why, in one line.
    nav_source: str = ""
    gnss_lost: bool = False
    position_lost: bool = False
    nav_reason: str = ""
    # The look that last confirmed the spot: the camera frame's seq and the spot's pixel in that
    # frame's heatmap (row down, col right), so a judge can map it to the ground with the frame's
    # own pose. Not valid for policies without a checked spot, or before a look confirmed one.
    confirmed_valid: bool = False
    confirmed_frame_seq: int = -1
    confirmed_row_px: float = 0.0
    confirmed_col_px: float = 0.0
    # The policy's last close look (issue 24): its verdict in one line ("clear: ...", "never set 2.1 m
    # from the spot ...", "look failed: ..."); empty for policies that do not look.
    look_verdict: str = ""

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "spot_north_m": (-1e7, 1e7), "spot_east_m": (-1e7, 1e7), "spot_clearance_m": (0.0, 1e6),
        "spot_confidence": (0.0, 1.0), "confirmed_frame_seq": SEQ,
        # Inside a frame of at most 8192 px a side (CameraModel's limit), with half a pixel of edge.
        "confirmed_row_px": (-0.5, 8191.5), "confirmed_col_px": (-0.5, 8191.5)}


@message("dovesei.prompt_set", 1)
class PromptSetMsg(Message):
    """Replace the segmenter's prompts at run time (what 'open vocabulary' buys an operator)."""

    stamp: Stamp
    positive: tuple[str, ...]
    negative: tuple[str, ...]
    template: str = "{}"

    def _check(self) -> None:
        if not self.positive or not self.negative:
            raise FieldError("fields 'positive' and 'negative' must each hold at least one prompt")
        if any(not p.strip() for p in self.positive + self.negative):
            raise FieldError("prompts must not be empty strings")
        if "{}" not in self.template:
            raise FieldError(f"field 'template': {self.template!r} has no '{{}}' placeholder")


# A close look (DESIGN.md 1, 5): a square of ground around a candidate spot, cut from the newest
# full-resolution camera frame onboard (only the crop crosses the link) and scored by the segmenter
# with the landing prompts and the "never" set. Geometry and limits: dovesei.shared.crop.
CROP_RANGES: dict[str, tuple[float, float]] = {
    "request_seq": SEQ, "centre_frd_m": (-1e4, 1e4), "side_m": (0.0, 1e4), "out_px": (1, MAX_IMAGE_SIDE_PX),
    "source_m_per_px": (0.0, 1e4), "never_p_max": (0.0, 1.0),
}


@message("dovesei.crop_request", 1)
class CropRequest(Message):
    """Ask the camera for a square of ground: its centre (forward, right metres from the point below
    the vehicle, heading-level body frame at the capture pose), its side in metres and the output
    side in pixels. `frame_seq` -1 asks for the newest full-resolution frame (a camera keeps only
    that one); `request_seq` comes back in the crop and its heatmap (correlation)."""

    RANGES: ClassVar[dict[str, tuple[float, float]]] = CROP_RANGES
    vehicle_id: str
    request_seq: int
    stamp: Stamp  # when asked, on the asker's data clock
    centre_frd_m: tuple[float, float]
    side_m: float
    out_px: int
    frame_seq: int = -1
    sent_wall_s: float = 0.0


@message("dovesei.crop", 1)
class CropFrame(Message):
    """The answer to a CropRequest: the crop (image up = body forward at capture) and the capture's
    tags (the frame's seq, stamp, altitude and attitude, as a CameraFrame carries them), the square
    actually cut, and the ground size of one source pixel at its centre (the detail really there)."""

    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"image_rgb": ArraySpec(("uint8",), 3, channels=3, image=True)}
    RANGES: ClassVar[dict[str, tuple[float, float]]] = CROP_RANGES
    vehicle_id: str
    request_seq: int
    frame_seq: int
    stamp: Stamp  # the capture's
    image_rgb: np.ndarray  # (out_px, out_px, 3) RGB
    centre_frd_m: tuple[float, float]
    side_m: float
    alt_agl_m: float
    source_m_per_px: float
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    sent_wall_s: float = 0.0
    truth: GroundTruth | None = None  # sim only: the crop's labels (centre_world_m = the square's centre)

    def _check(self) -> None:
        h, w = self.image_rgb.shape[:2]
        if h != w:
            raise FieldError(f"field 'image_rgb': a crop is square, got {w}x{h} px")
        if not self.side_m > 0.0 or not self.alt_agl_m > 0.0:
            raise FieldError(f"fields 'side_m' and 'alt_agl_m' must be > 0, got {self.side_m}, {self.alt_agl_m}")
        if self.truth is not None and self.truth.labels.shape != (h, w):
            raise FieldError(f"field 'truth': labels {self.truth.labels.shape} differ from the crop {(h, w)}")

    @property
    def hfov_rad(self) -> float:
        """The field of view of a nadir camera at the capture altitude that would see just this square."""
        return 2.0 * math.atan(self.side_m / (2.0 * self.alt_agl_m))

    @property
    def m_per_px(self) -> float:
        return self.side_m / self.image_rgb.shape[1]


_PROB_MAP = ArraySpec(("uint8", "float16", "float32"), 2, unit_range=True)


@message("dovesei.crop_heatmap", 1)
class CropHeatmap(Message):
    """A crop scored by the segmenter: P(safe) with the landing prompts and P(never) (people,
    vehicles, animals: anything of the "never" set), both at the crop's size."""

    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"prob_safe": _PROB_MAP, "prob_never": _PROB_MAP}
    RANGES: ClassVar[dict[str, tuple[float, float]]] = CROP_RANGES
    vehicle_id: str
    request_seq: int
    frame_seq: int
    stamp: Stamp  # the capture's
    prob_safe: np.ndarray  # uint8 = P * 255; float16/float32 = P
    prob_never: np.ndarray
    centre_frd_m: tuple[float, float]
    side_m: float
    alt_agl_m: float
    backend: str
    simulated: bool
    prompt_set_id: str
    never_set_id: str
    inference_s: float
    sent_wall_s: float = 0.0

    def _check(self) -> None:
        if self.prob_safe.shape != self.prob_never.shape:
            raise FieldError(f"fields 'prob_safe' {self.prob_safe.shape} and 'prob_never' {self.prob_never.shape} differ")

    def probabilities(self) -> tuple[np.ndarray, np.ndarray]:
        """(P(safe), P(never)) as float32 in [0, 1] whatever the wire dtype."""
        return tuple(a.astype(np.float32) * np.float32(1.0 / 255.0) if a.dtype == np.uint8
                     else a.astype(np.float32, copy=False) for a in (self.prob_safe, self.prob_never))


# "not_judged": the hand-over altitude was reached over a world without labels (tile worlds).
OUTCOMES = ("safe", "unsafe", "timeout", "out_of_world", "error", "not_judged")


@message("dovesei.episode_result", 1)
class EpisodeResult(Message):
    """The judge's verdict on one simulated episode."""

    vehicle_id: str
    stamp: Stamp
    outcome: str
    sim_time_s: float
    path_length_m: float
    final_x_m: float
    final_y_m: float
    final_alt_m: float
    classes_found: tuple[str, ...] = ()
    closest_unsafe_valid: bool = False
    closest_unsafe_m: float = 0.0
    detail: str = ""
    # The ground the policy last confirmed (its confirming look's spot pixel placed with that
    # frame's true pose) and, for an episode that reached the hand-over altitude, the true distance
    # from the hand-over point to it. Not valid for policies that confirm no spot.
    confirmed_valid: bool = False
    confirmed_x_m: float = 0.0
    confirmed_y_m: float = 0.0
    touchdown_error_valid: bool = False
    touchdown_error_m: float = 0.0
    # At the hand-over: the nearest person's and vehicle's footprint distance from the touchdown
    # point (not valid: none within the judge's search radius, or no hand-over), and whether one
    # was closer than its separation (the landing is then unsafe).
    nearest_person_valid: bool = False
    nearest_person_m: float = 0.0
    nearest_vehicle_valid: bool = False
    nearest_vehicle_m: float = 0.0
    separation_violated: bool = False

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "confirmed_x_m": (-1e9, 1e9), "confirmed_y_m": (-1e9, 1e9), "touchdown_error_m": (0.0, 1e9),
        "nearest_person_m": (0.0, 1e9), "nearest_vehicle_m": (0.0, 1e9)}

    def _check(self) -> None:
        if self.outcome not in OUTCOMES:
            raise FieldError(f"field 'outcome': {self.outcome!r} is not one of {OUTCOMES}")


def replace(msg: Record, **changes: Any) -> Any:
    """A copy of a record with some fields changed (checked again)."""
    return dataclasses.replace(msg, **changes)


__all__ = [
    "ArraySpec", "CameraFrame", "ClassEntry", "ControllerStatus", "CropFrame", "CropHeatmap", "CropRequest", "EpisodeResult", "FieldError",
    "GroundTruth", "Message", "VisualOdometry", "OUTCOMES", "PromptSetMsg", "Record", "SCHEMAS", "SafetyHeatmap",
    "StageLatency", "Stamp", "VehicleState", "VelocityCommand", "field_range", "replace",
]
