"""The codec round-trips every message and rejects each kind of bad payload with ProtocolError."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import ProtocolError
from dovesei.shared.messages import (
    SCHEMAS, CameraFrame, FieldError, SafetyHeatmap, Stamp, VehicleState, VelocityCommand,
)

from tests.shared.samples import sample_messages


def _assert_same(a, b) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            assert va.dtype == vb.dtype and np.array_equal(va, vb)
        elif dataclasses.is_dataclass(va):
            _assert_same(va, vb)
        else:
            assert va == vb, f.name


@pytest.mark.parametrize("msg", sample_messages(), ids=lambda m: type(m).__name__)
def test_round_trip_every_message(msg) -> None:
    back = decode(encode(msg), type(msg))
    _assert_same(msg, back)


def test_all_schemas_have_a_sample() -> None:
    assert {type(m) for m in sample_messages()} == set(SCHEMAS.values())


def test_raw_arrays_decode_without_copy() -> None:
    frame = sample_messages()[0]
    back = decode(encode(frame), CameraFrame)
    # np.frombuffer over the payload: a read-only view, not an owned copy.
    assert not back.image_rgb.flags.writeable and back.image_rgb.base is not None


def test_jpeg_frames_round_trip_approximately() -> None:
    frame = dataclasses.replace(sample_messages(64)[0], image_rgb=np.full((64, 64, 3), (40, 160, 90), np.uint8),
                                truth=None)
    data = encode(frame, jpeg_quality=90)
    back = decode(data, CameraFrame)
    assert len(data) < frame.image_rgb.nbytes
    assert np.abs(back.image_rgb.astype(int) - frame.image_rgb).max() <= 4


def _tamper(msg, **fields) -> bytes:
    body = msgpack.unpackb(encode(msg), raw=False)
    for k, v in fields.items():
        if v is KeyError:
            del body[k]
        else:
            body[k] = v
    return msgpack.packb(body, use_bin_type=True)


STATE = sample_messages()[1]
HEATMAP = sample_messages()[2]


@pytest.mark.parametrize("payload, expected_words", [
    (b"\xc1\xc1garbage", "not a msgpack"),
    (msgpack.packb([1, 2, 3]), "expected a msgpack map"),
    (_tamper(STATE, _schema="dovesei.nope"), "unknown schema"),
    (_tamper(STATE, _v=99), "version 99"),
    (_tamper(STATE, alt_agl_m=KeyError), "missing fields ['alt_agl_m']"),
    (_tamper(STATE, alt_agl_m="high"), "'alt_agl_m': expected a number"),
    (_tamper(STATE, alt_agl_m=float("nan")), "'alt_agl_m': nan is not finite"),
    (_tamper(STATE, alt_agl_m=float("inf")), "not finite"),
    (_tamper(STATE, seq=True), "'seq': expected an integer"),
    (_tamper(STATE, vel_body_frd_m_s=[1.0, 2.0]), "2 items, expected 3"),
    (_tamper(STATE, surprise=1), "unknown fields ['surprise']"),
    (_tamper(STATE, stamp={"t_s": 1.0, "clock": "martian"}), "'clock'"),
    (_tamper(HEATMAP, prob_safe={"dtype": "float16", "shape": [32, 32], "data": b"\x00" * 10}), "10 bytes for shape"),
    (_tamper(HEATMAP, prob_safe={"dtype": "object", "shape": [2], "data": b"\x00" * 16}), "dtype 'object'"),
    (_tamper(HEATMAP, prob_safe={"dtype": "float32", "shape": [2, 2], "data": np.full(4, np.nan, np.float32).tobytes()}),
     "finite and in [0, 1]"),
    (_tamper(HEATMAP, prob_safe={"dtype": "float32", "shape": [4], "data": np.zeros(4, np.float32).tobytes()}),
     "1 dimensions, expected 2"),
    (_tamper(HEATMAP, prob_safe={"jpeg": b"\xff\xd8"}), "JPEG is only allowed for image fields"),
])
def test_bad_payloads_raise_protocol_error_naming_the_problem(payload: bytes, expected_words: str) -> None:
    with pytest.raises(ProtocolError) as err:
        decode(payload, key="dovesei/uav1/state")
    assert expected_words in str(err.value)
    assert "dovesei/uav1/state" in str(err.value)


def test_undecodable_jpeg_is_rejected() -> None:
    frame = sample_messages()[0]
    data = _tamper(frame, image_rgb={"jpeg": b"\xff\xd8\xff\xe0 not really a jpeg"}, truth=None)
    with pytest.raises(ProtocolError, match="undecodable JPEG"):
        decode(data, CameraFrame)


def test_wrong_expected_schema_is_rejected() -> None:
    with pytest.raises(ProtocolError, match="expected schema 'dovesei.velocity_command'"):
        decode(encode(STATE), VelocityCommand)


def test_oversized_payload_is_rejected_before_parsing() -> None:
    with pytest.raises(ProtocolError, match="exceeds the 1000-byte limit"):
        decode(encode(sample_messages()[0]), max_bytes=1000)


def test_construction_checks_fields_too() -> None:
    with pytest.raises(FieldError, match="'alt_agl_m'"):
        VehicleState("uav1", 1, Stamp(0.0, "sim"), float("nan"), (0.0, 0.0, 0.0))
    with pytest.raises(FieldError, match="hfov_rad"):
        CameraFrame("uav1", 1, Stamp(0.0, "sim"), np.zeros((4, 4, 3), np.uint8), 4.0, 10.0)
    with pytest.raises(FieldError, match="prob_safe"):
        SafetyHeatmap("uav1", 1, Stamp(0.0, "sim"), np.full((4, 4), 2.0, np.float32), 10.0, 1.0,
                      "simulated", True, "x", "grouped", 0.0)


def test_uint8_heatmap_probability_scale() -> None:
    hm = dataclasses.replace(HEATMAP, prob_safe=np.array([[0, 255]], np.uint8))
    assert np.allclose(hm.probability(), [[0.0, 1.0]])


@pytest.mark.parametrize("dtype", ["float16", "float32"])
@pytest.mark.parametrize("bad", [-0.25, 1.0001, float("inf"), float("-inf"), float("nan")])
def test_probability_range_check_catches_every_bad_float(dtype: str, bad: float) -> None:
    arr = np.full((3, 3), 0.5, dtype)
    arr[1, 2] = bad
    if dtype == "float16" and bad == 1.0001:
        arr[1, 2] = np.float16(1.001)  # 1.0001 rounds to 1.0 in half precision
    with pytest.raises(FieldError, match="in \\[0, 1\\]"):
        SafetyHeatmap("uav1", 1, Stamp(0.0, "sim"), arr, 10.0, 1.0, "simulated", True, "x", "grouped", 0.0)
    arr[1, 2] = 1.0
    SafetyHeatmap("uav1", 1, Stamp(0.0, "sim"), arr, 10.0, 1.0, "simulated", True, "x", "grouped", 0.0)
