"""msgpack codec for the wire messages; decoding is the trust boundary.

encode: message -> {"_schema", "_v", fields...} -> msgpack bytes. Numpy arrays travel as
{"dtype", "shape", "data"} (raw little-endian bytes) or, for image fields when asked,
{"jpeg": bytes} (a radio link to a ground station is not a bus). Nested records are maps.

decode: bytes -> message. Everything that can be wrong with a payload (not msgpack, not a map,
unknown schema, wrong version, missing/unknown/mistyped fields, array bytes not matching shape and
dtype, NaN/inf, numbers outside their field's range, oversized payloads, undecodable JPEG)
raises `ProtocolError` naming the key or schema and the problem; no other exception type leaves
`decode`. Raw arrays are decoded with `np.frombuffer` (no copy, read-only). A JPEG's dimensions
are read from its frame header before anything is decoded: a few hundred bytes can claim
16000x16000 px, and decoding that first costs close to a gigabyte.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, TypeVar

import cv2
import msgpack
import numpy as np

from dovesei.shared.errors import ProtocolError
from dovesei.shared.messages import MAX_IMAGE_SIDE_PX, SCHEMAS, FieldError, Message, Record, field_hints

DEFAULT_MAX_BYTES = 32 * 1024 * 1024  # a 4K raw frame is 25 MB; anything bigger is an attack or a bug
_WIRE_DTYPES = {"uint8", "uint16", "int16", "int32", "float16", "float32", "float64", "bool"}

M = TypeVar("M", bound=Message)


def encode(msg: Message, *, jpeg_quality: int | None = None) -> bytes:
    """Serialise a message; image fields are JPEG-compressed when `jpeg_quality` is given."""
    if not isinstance(msg, Message):
        raise TypeError(f"encode() takes a registered message, got {type(msg).__name__}")
    body = _record_to_wire(msg, jpeg_quality)
    body["_schema"], body["_v"] = msg.SCHEMA, msg.VERSION
    return msgpack.packb(body, use_bin_type=True)


def decode(data: bytes | bytearray | memoryview, expected: type[M] | None = None, *,
           key: str = "", max_bytes: int = DEFAULT_MAX_BYTES) -> M:
    """Parse and check a payload; `expected` pins the message type, `key` names the source in errors."""
    where = key or (expected.SCHEMA if expected is not None else "payload")
    if len(data) > max_bytes:
        raise ProtocolError(where, f"payload of {len(data)} bytes exceeds the {max_bytes}-byte limit")
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=max_bytes,
                               max_str_len=max_bytes, max_array_len=65536, max_map_len=4096)
    except Exception as exc:  # msgpack raises many types (ValueError, ExtraData, FormatError, ...)
        raise ProtocolError(where, f"not a msgpack payload ({type(exc).__name__}: {exc})") from None
    if not isinstance(body, dict):
        raise ProtocolError(where, f"expected a msgpack map, got {type(body).__name__}")
    schema, version = body.pop("_schema", None), body.pop("_v", None)
    cls = SCHEMAS.get(schema) if isinstance(schema, str) else None
    if cls is None:
        raise ProtocolError(where, f"unknown schema {schema!r}")
    where = f"{key} ({schema})" if key else schema
    if expected is not None and cls is not expected:
        raise ProtocolError(where, f"expected schema {expected.SCHEMA!r}")
    if version != cls.VERSION or isinstance(version, bool):
        raise ProtocolError(where, f"version {version!r} not supported (this build speaks {cls.VERSION})")
    try:
        return _record_from_wire(cls, body)
    except (FieldError, ValueError, TypeError, OverflowError) as exc:
        raise ProtocolError(where, str(exc)) from None


def _record_to_wire(rec: Record, jpeg_quality: int | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, hint in field_hints(type(rec)).items():
        out[name] = _value_to_wire(getattr(rec, name), rec, name, jpeg_quality)
    return out


def _value_to_wire(value: Any, rec: Record, name: str, jpeg_quality: int | None) -> Any:
    if isinstance(value, np.ndarray):
        spec = type(rec).ARRAYS[name]
        if spec.image and jpeg_quality is not None:
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(value, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
            if not ok:
                raise ValueError(f"JPEG encoding of field {name!r} failed")
            return {"jpeg": buf.tobytes()}
        arr = np.ascontiguousarray(value)
        if arr.dtype.byteorder == ">":
            arr = arr.astype(arr.dtype.newbyteorder("<"))
        return {"dtype": arr.dtype.name, "shape": list(arr.shape), "data": memoryview(arr).cast("B")}
    if isinstance(value, Record):
        return _record_to_wire(value, jpeg_quality)
    if isinstance(value, tuple):
        return [_value_to_wire(v, rec, name, jpeg_quality) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    return value


def _record_from_wire(cls: type, body: Any) -> Any:
    if not isinstance(body, dict):
        raise FieldError(f"{cls.__name__}: expected a map, got {type(body).__name__}")
    hints = field_hints(cls)
    unknown = set(body) - set(hints)
    if unknown:
        raise FieldError(f"{cls.__name__}: unknown fields {sorted(map(str, unknown))}")
    required = {f.name for f in dataclasses.fields(cls)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
    missing = required - set(body)
    if missing:
        raise FieldError(f"{cls.__name__}: missing fields {sorted(missing)}")
    kwargs = {name: _value_from_wire(body[name], hints[name], cls, name) for name in body}
    return cls(**kwargs)  # the record's own checks run here


def _value_from_wire(value: Any, hint: Any, cls: type, name: str) -> Any:
    origin = typing.get_origin(hint)
    if origin is typing.Union or type(hint).__name__ == "UnionType":
        if value is None:
            return None
        (inner,) = [a for a in typing.get_args(hint) if a is not type(None)]
        return _value_from_wire(value, inner, cls, name)
    if hint is np.ndarray:
        return _array_from_wire(value, cls, name)
    if dataclasses.is_dataclass(hint):
        return _record_from_wire(hint, value)
    if origin is tuple:
        if not isinstance(value, list):
            raise FieldError(f"field {name!r}: expected an array, got {type(value).__name__}")
        args = typing.get_args(hint)
        item_hint = args[0] if len(args) == 2 and args[1] is Ellipsis else None
        if item_hint is None and len(value) != len(args):
            raise FieldError(f"field {name!r}: {len(value)} items, expected {len(args)}")
        return tuple(_value_from_wire(v, item_hint or args[i], cls, f"{name}[{i}]") for i, v in enumerate(value))
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)  # msgpack keeps 3.0 as a float, but other encoders may send 3
    return value  # scalars are checked by the record itself


def _array_from_wire(value: Any, cls: type, name: str) -> np.ndarray:
    if not isinstance(value, dict):
        raise FieldError(f"field {name!r}: expected an array map, got {type(value).__name__}")
    if set(value) == {"jpeg"}:
        if not cls.ARRAYS[name].image:
            raise FieldError(f"field {name!r}: JPEG is only allowed for image fields")
        buf = value["jpeg"]
        if not isinstance(buf, bytes) or not buf:
            raise FieldError(f"field {name!r}: JPEG data must be non-empty bytes")
        height, width, _ = jpeg_header_size(buf, name)
        if not (1 <= height <= MAX_IMAGE_SIDE_PX and 1 <= width <= MAX_IMAGE_SIDE_PX):
            raise FieldError(f"field {name!r}: JPEG of {width}x{height} px outside 1..{MAX_IMAGE_SIDE_PX} px "
                             f"(refused before decoding)")
        if height * width * 3 > DEFAULT_MAX_BYTES:
            # A JPEG may not decode to more than a raw frame may carry.
            raise FieldError(f"field {name!r}: JPEG of {width}x{height} px decodes to more than "
                             f"{DEFAULT_MAX_BYTES} bytes (refused before decoding)")
        bgr = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None or bgr.shape[:2] != (height, width):
            raise FieldError(f"field {name!r}: undecodable JPEG ({len(buf)} bytes)")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if set(value) != {"dtype", "shape", "data"}:
        raise FieldError(f"field {name!r}: array map needs dtype, shape and data, got {sorted(map(str, value))}")
    dtype, shape, data = value["dtype"], value["shape"], value["data"]
    if not isinstance(dtype, str) or dtype not in _WIRE_DTYPES:
        raise FieldError(f"field {name!r}: dtype {dtype!r} not accepted")
    if (not isinstance(shape, list) or not 1 <= len(shape) <= 4
            or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= 65536 for s in shape)):
        raise FieldError(f"field {name!r}: bad shape {shape!r}")
    if not isinstance(data, bytes):
        raise FieldError(f"field {name!r}: data must be bytes, got {type(data).__name__}")
    dt = np.dtype(dtype).newbyteorder("<")
    expected = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    if len(data) != expected:
        raise FieldError(f"field {name!r}: {len(data)} bytes for shape {shape} {dtype} (expected {expected})")
    arr = np.frombuffer(data, dtype=dt).reshape(shape)
    return arr if dt.isnative else arr.astype(dt.newbyteorder("="))


# Start-of-frame markers (baseline, extended, progressive, lossless, arithmetic): they carry the
# image size. 0xC4 (DHT), 0xC8 (JPG) and 0xCC (DAC) share the range but are not frames.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_STANDALONE_MARKERS = frozenset(range(0xD0, 0xD8)) | {0x01}  # RSTn and TEM have no length field


def jpeg_header_size(buf: bytes, name: str = "image") -> tuple[int, int, int]:
    """(height, width, components) from a JPEG's frame header, without decoding any pixels.

    Walks the marker segments from SOI to the first start-of-frame; raises `FieldError` when the
    bytes are not a JPEG or end before a frame header (then there is nothing safe to decode).
    """
    if len(buf) < 4 or buf[0] != 0xFF or buf[1] != 0xD8:
        raise FieldError(f"field {name!r}: undecodable JPEG (no start-of-image marker)")
    i = 2
    while i + 4 <= len(buf):
        if buf[i] != 0xFF:
            raise FieldError(f"field {name!r}: undecodable JPEG (no marker at byte {i})")
        marker = buf[i + 1]
        if marker == 0xFF:  # fill byte before a marker
            i += 1
            continue
        if marker in _STANDALONE_MARKERS:
            i += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, or scan data before any frame header
            break
        length = (buf[i + 2] << 8) | buf[i + 3]
        if length < 2:
            raise FieldError(f"field {name!r}: undecodable JPEG (segment length {length} at byte {i})")
        if marker in _SOF_MARKERS:
            if i + 10 > len(buf):
                break
            height = (buf[i + 5] << 8) | buf[i + 6]
            width = (buf[i + 7] << 8) | buf[i + 8]
            return height, width, buf[i + 9]
        i += 2 + length
    raise FieldError(f"field {name!r}: undecodable JPEG (no frame header in {len(buf)} bytes)")


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*")
_TIFF_WIDTH, _TIFF_LENGTH = 256, 257  # the ImageWidth and ImageLength tags of the first IFD


def png_header_size(buf: bytes, name: str = "image") -> tuple[int, int]:
    """(height, width) from a PNG's IHDR chunk (bytes 16..24, big-endian), without decoding."""
    if len(buf) < 24 or not buf.startswith(_PNG_MAGIC) or buf[12:16] != b"IHDR":
        raise FieldError(f"field {name!r}: undecodable PNG (no IHDR header)")
    return int.from_bytes(buf[20:24], "big"), int.from_bytes(buf[16:20], "big")


def _tiff_header_size(buf: bytes, name: str) -> tuple[int, int]:
    """(height, width) from a classic TIFF's first image file directory."""
    order = "little" if buf[:2] == b"II" else "big"
    u16 = lambda at: int.from_bytes(buf[at:at + 2], order)  # noqa: E731 - two readers of one byte order
    u32 = lambda at: int.from_bytes(buf[at:at + 4], order)  # noqa: E731
    ifd = u32(4)
    if ifd + 2 > len(buf):
        raise FieldError(f"field {name!r}: undecodable TIFF (first directory at byte {ifd} of {len(buf)})")
    found: dict[int, int] = {}
    for i in range(u16(ifd)):
        at = ifd + 2 + 12 * i
        if at + 12 > len(buf):
            break
        tag, kind = u16(at), u16(at + 2)
        if tag in (_TIFF_WIDTH, _TIFF_LENGTH):
            found[tag] = u16(at + 8) if kind == 3 else u32(at + 8)  # SHORT or LONG, stored in the entry
    if len(found) != 2:
        raise FieldError(f"field {name!r}: undecodable TIFF (no width and length in its first directory)")
    return found[_TIFF_LENGTH], found[_TIFF_WIDTH]


def image_header_size(buf: bytes, name: str = "image") -> tuple[int, int]:
    """(height, width) of a JPEG, PNG, BMP or classic TIFF file from its header, without decoding.

    A few hundred bytes can claim 30000x30000 px: decoding first cost 68 s and 5.2 GB (a world's
    image.jpg). Raises `FieldError` for anything else (there is then no size to check first).
    """
    if buf[:2] == b"\xff\xd8":
        height, width, _ = jpeg_header_size(buf, name)
        return height, width
    if buf.startswith(_PNG_MAGIC):
        return png_header_size(buf, name)
    if buf[:2] == b"BM" and len(buf) >= 26:
        # BITMAPINFOHEADER: int32 width at 18, int32 height at 22 (negative: stored top-down).
        return abs(int.from_bytes(buf[22:26], "little", signed=True)), int.from_bytes(buf[18:22], "little", signed=True)
    if buf[:4] in _TIFF_MAGICS and len(buf) >= 8:
        return _tiff_header_size(buf, name)
    raise FieldError(f"field {name!r}: not a JPEG, PNG, BMP or TIFF image")
