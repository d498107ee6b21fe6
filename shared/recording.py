"""Flight recordings in MCAP: what a service saw, in a file robotics tools open and `replay` reads.

    message --to_json()--> /dovesei/<topic>  (JSON, JSON-schema generated from the dataclass)
       |  images ---------> /camera/image, /heatmap/image, /sim/labels  (foxglove.CompressedImage)
       v
    FlightRecorder.write(msg) --mcap Writer (zstd chunks)--> recording.mcap
    FlightRecording(path).messages() <-- mcap reader <-- recording.mcap --> the codec's own checks

Every message keeps its wire form on a JSON channel (floats survive JSON exactly), so reading back
rebuilds the same dataclass through `dovesei.shared.codec.decode`: a recording is an input like a
Zenoh sample and passes the same trust boundary. Image arrays live on image channels that
Foxglove and Lichtblick display (the `foxglove.CompressedImage` JSON schema: base64 data); the
JSON message names that channel and the MCAP `sequence` of both records is the frame's seq, so a
reader pairs them without guessing by time. The camera image is JPEG (what a radio link carries;
replaying CLIPSeg on it is replaying what a ground station saw); heatmaps (uint8 = P*255) and the
sim's label images are PNG, lossless, so a replayed policy sees exactly what the live one saw.
Float heatmaps also travel as raw base64 inside the JSON message, for the same reason.

log_time is the message's own stamp (the data's clock, DESIGN 4): playback follows the vehicle's
time; publish_time is the recorder's wall clock at arrival. A service on a real drone uses the
same class (the camera service, the controller): this module needs only numpy, OpenCV and `mcap`.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import threading
import time
import typing
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np
from mcap.records import Channel, Footer, Header, Metadata
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import ConfigError, DoveseiError, ProtocolError
from dovesei.shared.messages import (
    SCHEMAS, CameraFrame, ControllerStatus, CropFrame, CropHeatmap, EpisodeResult, Message, PromptSetMsg, SafetyHeatmap, VehicleState,
    VelocityCommand, VisualOdometry, field_hints,
)

PROFILE = "dovesei"
TOPICS: dict[type, str] = {
    VehicleState: "/dovesei/state", VelocityCommand: "/dovesei/cmd", ControllerStatus: "/dovesei/status",
    SafetyHeatmap: "/dovesei/heatmap", CameraFrame: "/dovesei/camera", EpisodeResult: "/dovesei/episode",
    PromptSetMsg: "/dovesei/prompts", VisualOdometry: "/dovesei/odometry",
    CropFrame: "/dovesei/look/crop", CropHeatmap: "/dovesei/look/heatmap",
}
CAMERA_IMAGE_TOPIC = "/camera/image"
HEATMAP_IMAGE_TOPIC = "/heatmap/image"
LABELS_IMAGE_TOPIC = "/sim/labels"
IMAGE_TOPICS = (CAMERA_IMAGE_TOPIC, HEATMAP_IMAGE_TOPIC, LABELS_IMAGE_TOPIC)
MCAP_MAGIC = b"\x89MCAP0\r\n"
JPEG_QUALITY = 90

# The schema Foxglove and Lichtblick show as an image (their published foxglove.CompressedImage).
COMPRESSED_IMAGE_SCHEMA = {
    "title": "foxglove.CompressedImage", "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                       "nsec": {"type": "integer", "minimum": 0}}},
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}


class RecordingError(DoveseiError):
    """A recording that cannot be read or written (not MCAP, not ours, a broken message)."""


def json_schema(cls: type) -> dict[str, Any]:
    """The JSON schema of a message's JSON form, generated from its dataclass (one source of truth)."""
    props = {name: _hint_schema(hint) for name, hint in field_hints(cls).items()}
    required = [f.name for f in dataclasses.fields(cls)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    out: dict[str, Any] = {"type": "object", "properties": props, "required": required}
    if getattr(cls, "SCHEMA", None):
        out.update(title=f"dovesei.{cls.SCHEMA}", description=f"{cls.__doc__ or ''}".strip().split("\n")[0],
                   version=cls.VERSION)
        out["properties"]["_schema"] = {"type": "string", "const": cls.SCHEMA}
        out["properties"]["_v"] = {"type": "integer", "const": cls.VERSION}
    return out


def _hint_schema(hint: Any) -> dict[str, Any]:
    origin = typing.get_origin(hint)
    if origin is typing.Union or type(hint).__name__ == "UnionType":
        inner = [a for a in typing.get_args(hint) if a is not type(None)]
        return {"anyOf": [_hint_schema(inner[0]), {"type": "null"}]}
    if hint is np.ndarray:
        return {"type": "object", "description": "an array: {image_topic, format} (the image channel with this "
                "message's sequence) or {dtype, shape, base64} (raw little-endian bytes)"}
    if dataclasses.is_dataclass(hint):
        return json_schema(hint)
    if origin is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": _hint_schema(args[0])}
        return {"type": "array", "items": [_hint_schema(a) for a in args], "minItems": len(args),
                "maxItems": len(args)}
    return {"type": {float: "number", int: "integer", str: "string", bool: "boolean"}.get(hint, "string")}


def _stamp_ns(msg: Message) -> int:
    stamp = getattr(msg, "stamp", None)
    return max(0, int(round(stamp.t_s * 1e9))) if stamp is not None else 0


class FlightRecorder:
    """Writes messages to an MCAP file; thread-safe, so Zenoh threads or a loop may call `write`."""

    def __init__(self, path: str | Path, *, metadata: dict[str, dict[str, str]] | None = None) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close(); the writer owns it until then
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="dovesei")
        self._channels: dict[str, int] = {}
        self._lock = threading.Lock()
        self.count = 0
        for name, data in (metadata or {}).items():
            self.add_metadata(name, data)

    def __enter__(self) -> FlightRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_metadata(self, name: str, data: dict[str, Any]) -> None:
        """A named metadata record; values that are not strings are stored as JSON."""
        with self._lock:
            self._writer.add_metadata(name, {str(k): v if isinstance(v, str) else json.dumps(v)
                                             for k, v in data.items()})

    def _channel(self, topic: str, schema: dict[str, Any]) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._writer.register_schema(name=schema["title"], encoding="jsonschema",
                                               data=json.dumps(schema).encode())
            cid = self._writer.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            self._channels[topic] = cid
        return cid

    def write(self, msg: Message, recv_wall_s: float | None = None) -> None:
        """Record one message (its images on their image channels, with the same sequence)."""
        topic = TOPICS.get(type(msg))
        if topic is None:
            raise RecordingError(f"no recording channel for {type(msg).__name__}")
        log_ns = _stamp_ns(msg)
        pub_ns = int((time.time() if recv_wall_s is None else recv_wall_s) * 1e9)
        seq = int(getattr(msg, "seq", 0)) & 0xFFFFFFFF
        body, images = to_json(msg)
        with self._lock:
            for image_topic, fmt, data in images:
                self._writer.add_message(self._channel(image_topic, COMPRESSED_IMAGE_SCHEMA), log_ns,
                                         _compressed_image(log_ns, fmt, data), pub_ns, seq)
            self._writer.add_message(self._channel(topic, json_schema(type(msg))), log_ns,
                                     json.dumps(body, separators=(",", ":")).encode(), pub_ns, seq)
            self.count += 1

    def close(self) -> None:
        with self._lock:
            if self._file.closed:
                return
            self._writer.finish()
            self._file.close()


def _compressed_image(log_ns: int, fmt: str, data: bytes) -> bytes:
    return json.dumps({"timestamp": {"sec": log_ns // 1_000_000_000, "nsec": log_ns % 1_000_000_000},
                       "frame_id": "camera", "format": fmt, "data": base64.b64encode(data).decode()}).encode()


def to_json(msg: Message) -> tuple[dict[str, Any], list[tuple[str, str, bytes]]]:
    """A message's wire form as JSON, and its images as (image topic, format, bytes)."""
    wire = msgpack.unpackb(encode(msg), raw=False)
    images: list[tuple[str, str, bytes]] = []
    if isinstance(msg, CameraFrame):
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(msg.image_rgb, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        images.append((CAMERA_IMAGE_TOPIC, "jpeg", buf.tobytes()))
        wire["image_rgb"] = {"image_topic": CAMERA_IMAGE_TOPIC, "format": "jpeg"}
        if msg.truth is not None:
            images.append((LABELS_IMAGE_TOPIC, "png", _png(msg.truth.labels)))
            wire["truth"]["labels"] = {"image_topic": LABELS_IMAGE_TOPIC, "format": "png"}
    elif isinstance(msg, SafetyHeatmap):
        prob = np.asarray(msg.prob_safe)
        if prob.dtype == np.uint8:
            images.append((HEATMAP_IMAGE_TOPIC, "png", _png(prob)))
            wire["prob_safe"] = {"image_topic": HEATMAP_IMAGE_TOPIC, "format": "png"}
        else:  # float P: exact bytes in the message, and a picture of it for the viewers
            images.append((HEATMAP_IMAGE_TOPIC, "png", _png(np.round(np.clip(prob, 0, 1) * 255).astype(np.uint8))))
    return _jsonable(wire), images


def _png(arr: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise RecordingError(f"PNG encoding of a {arr.shape} {arr.dtype} array failed")
    return buf.tobytes()


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        if set(value) == {"dtype", "shape", "data"}:
            return {"dtype": value["dtype"], "shape": value["shape"], "base64": base64.b64encode(value["data"]).decode()}
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    if isinstance(value, bytes):
        return base64.b64encode(value).decode()
    return value


class FlightRecording:
    """Reads a recording back: metadata, and the messages as the codec's checked dataclasses.

    The file is read as a stream, record after record, never through its summary: a recording cut
    anywhere (a crash, a power loss: even only the last 100 bytes, the footer) still gives every
    message written before the cut. `complete` says whether the file ended properly; after
    `messages()` has run, `recovered` counts the messages it gave and `cut` says where and why the
    stream stopped (None for a complete file).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"recording {self.path}: no such file")
        self.size_bytes = self.path.stat().st_size
        self.recovered = 0
        self.cut: str | None = None
        self.profile = ""
        self.metadata: dict[str, dict[str, str]] = {}
        self.complete = False
        with open(self.path, "rb") as f:
            if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise RecordingError(f"recording {self.path}: not a readable MCAP file (no MCAP magic at its start)")
        # Chunks are skipped, not decompressed: metadata sits outside them.
        for record in self._records(emit_chunks=True):
            if isinstance(record, Header):
                self.profile = record.profile
            elif isinstance(record, Metadata):
                self.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Footer):
                self.complete = True
        self.cut = None  # the scan's own cut is reported again by messages(), with what it recovered

    def _records(self, *, emit_chunks: bool) -> Iterator[Any]:
        """The file's records in order, up to the end or the cut (then `cut` says where)."""
        with open(self.path, "rb") as f:
            stream = StreamReader(f, emit_chunks=emit_chunks)
            try:
                yield from stream.records
            except Exception as exc:  # noqa: BLE001 - the mcap and zstd readers raise many types at a cut
                self.cut = (f"a broken or unfinished record near byte {f.tell()} of {self.size_bytes} "
                            f"({type(exc).__name__}{': ' + str(exc) if str(exc) else ''})")

    def describe(self) -> str:
        """One line on what was read: complete, or cut and how much came back."""
        if self.cut is None:
            return f"recording {self.path}: {self.recovered} messages"
        return (f"recording {self.path} is cut ({self.cut}): recovered the {self.recovered} messages "
                f"written before the cut")

    def meta(self, name: str) -> dict[str, Any]:
        """A metadata record with its JSON values parsed back."""
        out: dict[str, Any] = {}
        for k, v in self.metadata.get(name, {}).items():
            try:
                out[k] = json.loads(v)
            except ValueError:
                out[k] = v
        return out

    def messages(self, types: Iterable[type] | None = None) -> Iterator[tuple[float, Message]]:
        """(arrival wall s, message) in file order (the order the recorder saw them), up to the cut."""
        wanted = {TOPICS[t] for t in (types or TOPICS)}
        want_images = TOPICS[CameraFrame] in wanted or TOPICS[SafetyHeatmap] in wanted
        images: dict[tuple[str, int], bytes] = {}  # written just before their message: held until it comes
        channels: dict[int, str] = {}
        self.recovered, self.cut = 0, None
        for rec in self._records(emit_chunks=False):
            if isinstance(rec, Channel):
                channels[rec.id] = rec.topic
                continue
            if not isinstance(rec, McapMessage):
                continue
            topic = channels.get(rec.channel_id)
            if topic is None:
                continue
            try:
                if topic not in wanted:
                    if want_images and topic in IMAGE_TOPICS:
                        images[(topic, rec.sequence)] = base64.b64decode(json.loads(rec.data)["data"])
                    continue
                body = json.loads(rec.data)
                msg = from_json(body, lambda image_topic, seq=rec.sequence: images.pop((image_topic, seq)))
            except (ValueError, KeyError, TypeError) as exc:
                raise RecordingError(f"recording {self.path}: broken {topic} message "
                                     f"(sequence {rec.sequence}): {type(exc).__name__}: {exc}") from None
            except ProtocolError as exc:
                raise RecordingError(f"recording {self.path}: {topic}: {exc}") from None
            self.recovered += 1
            yield rec.publish_time / 1e9, msg


def from_json(body: dict[str, Any], image: Any) -> Message:
    """The message a JSON form describes, through the codec's checks; `image(topic)` gives image bytes."""
    schema = body.get("_schema")
    if schema not in SCHEMAS:
        raise ValueError(f"unknown schema {schema!r}")
    wire = _from_jsonable(body, image)
    return decode(msgpack.packb(wire, use_bin_type=True), SCHEMAS[schema], key="recording")


def _from_jsonable(value: Any, image: Any) -> Any:
    if isinstance(value, dict):
        if set(value) == {"image_topic", "format"}:
            data = image(value["image_topic"])
            if value["format"] == "jpeg":
                return {"jpeg": data}  # the codec checks and decodes it, size first
            arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if arr is None:
                raise ValueError(f"undecodable PNG on {value['image_topic']}")
            return {"dtype": arr.dtype.name, "shape": list(arr.shape), "data": arr.tobytes()}
        if set(value) == {"dtype", "shape", "base64"}:
            return {"dtype": value["dtype"], "shape": value["shape"], "data": base64.b64decode(value["base64"])}
        return {k: _from_jsonable(v, image) for k, v in value.items()}
    if isinstance(value, list):
        return [_from_jsonable(v, image) for v in value]
    return value


RECORDING_NAME = "recording.mcap"  # what `dovesei up` writes in its report folder


def find_recording(target: str | Path) -> Path:
    """The recording a user means: an .mcap file as given, or the one in a report folder.

    `dovesei view` and `dovesei replay` both take either, so a report folder printed by `up` can be
    pasted into each. In a folder, `recording.mcap` wins; otherwise the folder's only .mcap (a replay
    folder holds replay.mcap). A target that holds no recording is the user's error: ConfigError.
    """
    path = Path(target)
    if path.is_dir():
        if (path / RECORDING_NAME).is_file():
            return path / RECORDING_NAME
        found = sorted(p for p in path.glob("*.mcap") if p.is_file())
        if len(found) == 1:
            return found[0]
        what = f"{len(found)} .mcap files ({', '.join(p.name for p in found)})" if found else "no .mcap file"
        raise ConfigError(f"{path}: no recording: a folder without {RECORDING_NAME} and with {what}; "
                          "give the recording's path")
    if not path.is_file():
        raise ConfigError(f"{path}: no recording, no such file or folder (give a report folder with "
                          f"{RECORDING_NAME}, or an .mcap file)")
    return path
