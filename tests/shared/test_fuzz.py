"""Thousands of random and mutated payloads at every decoder: only ProtocolError may come out."""

from __future__ import annotations

from collections import Counter

import msgpack
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import ProtocolError
from dovesei.shared.messages import SCHEMAS, field_hints

from tests.shared.samples import sample_messages

VALID = [encode(m) for m in sample_messages(8)]
TYPES = [None, *SCHEMAS.values()]

# msgpack-shaped values, including the types the codec special-cases.
leaf = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=True),
                 st.text(max_size=20), st.binary(max_size=64))
wire_value = st.recursive(leaf, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                         st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                          max_leaves=8)


MIN_DECODED_PER_TEST = 800  # four tests: at least 3,200 payloads decoded per run
# Some drawn values cannot be packed by msgpack (integers past 64 bits) and are not decoded.
# The runs are derandomized (the same payloads every run), and nearly all their cost is hypothesis
# drawing nested values, not decoding: 1000 each kept the suite's budget (3000 cost ~80 CPU s).
EXAMPLES_PER_TEST = 1000
DECODED: Counter[str] = Counter()  # payloads decoded per fuzz target, checked by each test


def _decode_only_protocol_errors(data: bytes, expected, target: str) -> None:
    DECODED[target] += 1
    try:
        decode(data, expected, key="fuzz")
    except ProtocolError:
        pass  # the one allowed failure; any other exception fails the test


def _run(target) -> None:
    """Run a hypothesis target and check it really decoded its share of payloads."""
    DECODED[target.__name__] = 0
    target()
    assert DECODED[target.__name__] >= MIN_DECODED_PER_TEST, DECODED


# Derandomized: CI runs the same payloads every time; a failure reproduces.
FUZZ = settings(max_examples=EXAMPLES_PER_TEST, deadline=None, suppress_health_check=list(HealthCheck),
                derandomize=True, database=None)


@FUZZ
@given(data=st.binary(max_size=512), which=st.sampled_from(TYPES))
def fuzz_random_bytes(data: bytes, which) -> None:
    _decode_only_protocol_errors(data, which, "fuzz_random_bytes")


@FUZZ
@given(base=st.sampled_from(VALID), flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=8),
       cut=st.integers(0, 10**6), which=st.sampled_from(TYPES))
def fuzz_mutated_valid_payloads(base: bytes, flips, cut: int, which) -> None:
    data = bytearray(base)
    for pos, byte in flips:
        data[pos % len(data)] = byte
    if cut % 3 == 0:
        data = data[: cut % len(data)]
    _decode_only_protocol_errors(bytes(data), which, "fuzz_mutated_valid_payloads")


@FUZZ
@given(base=st.sampled_from(VALID), field_pick=st.integers(0, 100), value=wire_value, which=st.sampled_from(TYPES))
def fuzz_structurally_mutated_fields(base: bytes, field_pick: int, value, which) -> None:
    body = msgpack.unpackb(base, raw=False)
    names = sorted(body)
    body[names[field_pick % len(names)]] = value
    try:
        data = msgpack.packb(body, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        return  # hypothesis produced something msgpack itself cannot pack
    _decode_only_protocol_errors(data, which, "fuzz_structurally_mutated_fields")


@FUZZ
@given(extra=st.dictionaries(st.text(max_size=12), wire_value, max_size=3), schema=st.sampled_from(sorted(SCHEMAS)),
       real_fields=st.lists(st.tuples(st.integers(0, 100), wire_value), max_size=4))
def fuzz_random_maps_with_a_real_schema(extra, schema: str, real_fields) -> None:
    # Real field names with random values reach deeper into the checks than random names alone.
    names = sorted(field_hints(SCHEMAS[schema]))
    body = dict(extra)
    for pick, value in real_fields:
        body[names[pick % len(names)]] = value
    body["_schema"], body["_v"] = schema, 1
    try:
        data = msgpack.packb(body, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        return
    _decode_only_protocol_errors(data, None, "fuzz_random_maps_with_a_real_schema")


def test_random_bytes() -> None:
    _run(fuzz_random_bytes)


def test_mutated_valid_payloads() -> None:
    _run(fuzz_mutated_valid_payloads)


def test_structurally_mutated_fields() -> None:
    _run(fuzz_structurally_mutated_fields)


def test_random_maps_with_a_real_schema() -> None:
    _run(fuzz_random_maps_with_a_real_schema)
