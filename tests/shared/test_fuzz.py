"""Thousands of random and mutated payloads at every decoder: only ProtocolError may come out."""

from __future__ import annotations

import msgpack
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import ProtocolError
from dovesei.shared.messages import SCHEMAS

from tests.shared.samples import sample_messages

VALID = [encode(m) for m in sample_messages(8)]
TYPES = [None, *SCHEMAS.values()]
FUZZ = settings(max_examples=2500, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)

# msgpack-shaped values, including the types the codec special-cases.
leaf = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=True),
                 st.text(max_size=20), st.binary(max_size=64))
wire_value = st.recursive(leaf, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                         st.dictionaries(st.text(max_size=10), inner, max_size=5)),
                          max_leaves=20)


def _decode_only_protocol_errors(data: bytes, expected) -> None:
    try:
        decode(data, expected, key="fuzz")
    except ProtocolError:
        pass  # the one allowed failure; any other exception fails the test


@FUZZ
@given(data=st.binary(max_size=512), which=st.sampled_from(TYPES))
def test_random_bytes(data: bytes, which) -> None:
    _decode_only_protocol_errors(data, which)


@FUZZ
@given(base=st.sampled_from(VALID), flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=8),
       cut=st.integers(0, 10**6), which=st.sampled_from(TYPES))
def test_mutated_valid_payloads(base: bytes, flips, cut: int, which) -> None:
    data = bytearray(base)
    for pos, byte in flips:
        data[pos % len(data)] = byte
    if cut % 3 == 0:
        data = data[: cut % len(data)]
    _decode_only_protocol_errors(bytes(data), which)


@FUZZ
@given(base=st.sampled_from(VALID), field_pick=st.integers(0, 100), value=wire_value, which=st.sampled_from(TYPES))
def test_structurally_mutated_fields(base: bytes, field_pick: int, value, which) -> None:
    body = msgpack.unpackb(base, raw=False)
    names = sorted(body)
    body[names[field_pick % len(names)]] = value
    try:
        data = msgpack.packb(body, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        return  # hypothesis produced something msgpack itself cannot pack
    _decode_only_protocol_errors(data, which)


@FUZZ
@given(body=st.dictionaries(st.text(max_size=12), wire_value, max_size=8), schema=st.sampled_from(sorted(SCHEMAS)))
def test_random_maps_with_a_real_schema(body, schema: str) -> None:
    body["_schema"], body["_v"] = schema, 1
    try:
        data = msgpack.packb(body, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        return
    _decode_only_protocol_errors(data, None)
