"""Well-formed but hostile input: absurd numbers, lying JPEG headers, floods, stamps from the future.

Each test is one probe of issue 13 that the decoder or the inbox must refuse: it fails on the code
before the fix (the probe succeeded there) and names what was refused.
"""

from __future__ import annotations

import dataclasses
import logging
import resource
import time
import typing

import cv2
import msgpack
import numpy as np
import pytest
import zenoh

from dovesei.shared import keys
from dovesei.shared.clock import REANCHOR_SAMPLES, Arrival, DataClock, StampBound, own_time
from dovesei.shared.codec import decode, encode, jpeg_header_size
from dovesei.shared.errors import ProtocolError
from dovesei.shared.lifecycle import FLOOD_DEPTH, MAX_REASONS, REJECT_STAMP, Inbox, RateLimitedLog, wait_until
from dovesei.shared.messages import (
    SCHEMAS, FieldError, PromptSetMsg, Record, SafetyHeatmap, Stamp, VehicleState, VelocityCommand, field_hints, field_range,
    replace,
)

from tests.shared.samples import sample_messages

BLOCK = zenoh.CongestionControl.BLOCK


def _tamper(msg, **fields) -> bytes:
    body = msgpack.unpackb(encode(msg), raw=False)
    body.update(fields)
    return msgpack.packb(body, use_bin_type=True)


# --- numeric ranges ---------------------------------------------------------------------------------


def _records(cls: type) -> list[type]:
    """A record class and every record class nested in its fields."""
    out = [cls]
    for hint in field_hints(cls).values():
        for t in (hint, *typing.get_args(hint), *(a for h in typing.get_args(hint) for a in typing.get_args(h))):
            if isinstance(t, type) and dataclasses.is_dataclass(t) and issubclass(t, Record) and t not in out:
                out += _records(t)
    return out


def _numeric(hint) -> bool:
    args = typing.get_args(hint)
    return hint in (int, float) or any(_numeric(a) for a in args if a is not type(None) and a is not Ellipsis)


@pytest.mark.parametrize("schema", sorted(SCHEMAS))
def test_every_numeric_field_of_every_message_has_a_range(schema: str) -> None:
    for cls in _records(SCHEMAS[schema]):
        for name, hint in field_hints(cls).items():
            if _numeric(hint):
                assert field_range(cls, name) is not None, f"{cls.__name__}.{name} has no range"


def test_altitude_of_1e300_is_refused_at_decode() -> None:
    heatmap = sample_messages()[2]
    with pytest.raises(ProtocolError, match=r"alt_agl_m.*1e\+300"):
        decode(_tamper(heatmap, alt_agl_m=1e300), SafetyHeatmap)


@pytest.mark.parametrize("index", range(len(sample_messages())))
def test_a_huge_value_in_any_numeric_field_is_refused(index: int) -> None:
    msg = sample_messages()[index]
    body = msgpack.unpackb(encode(msg), raw=False)
    tried = 0
    for name, hint in field_hints(type(msg)).items():
        if not _numeric(hint) or isinstance(body.get(name), dict):
            continue
        value = body[name]
        huge = [1e300] * len(value) if isinstance(value, list) else (2**62 + 1 if hint is int else 1e300)
        with pytest.raises(ProtocolError, match=name):
            decode(_tamper(msg, **{name: huge}))
        tried += 1
    stamp = dict(body["stamp"], t_s=1e300)  # nested records are bounded too
    with pytest.raises(ProtocolError, match="t_s"):
        decode(_tamper(msg, stamp=stamp))
    assert tried >= 1 or type(msg).__name__ == "PromptSetMsg"


def test_a_command_stamped_1e9_s_is_refused_at_decode() -> None:
    cmd = sample_messages()[4]
    with pytest.raises(ProtocolError, match="t_s"):
        decode(_tamper(cmd, stamp={"t_s": 1e9, "clock": "sim"}), VelocityCommand)


def test_a_negative_velocity_far_beyond_any_vehicle_is_refused_when_built() -> None:
    with pytest.raises(FieldError, match="vel_body_frd_m_s"):
        VelocityCommand("uav1", 0, Stamp(1.0, "sim"), (0.0, 0.0, -1e6))


# --- JPEG header ------------------------------------------------------------------------------------


def _lying_jpeg(height: int, width: int) -> bytes:
    """A small real JPEG whose frame header claims another size (what an attacker sends)."""
    ok, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 50])
    assert ok
    data = bytearray(buf.tobytes())
    i = 2
    while not 0xC0 <= data[i + 1] <= 0xC2:  # walk to the baseline/progressive frame header
        i += 2 + (data[i + 2] << 8 | data[i + 3])
    data[i + 5:i + 9] = bytes([height >> 8, height & 0xFF, width >> 8, width & 0xFF])
    return bytes(data)


def test_jpeg_header_size_reads_the_frame_header() -> None:
    for progressive in (0, 1):
        ok, buf = cv2.imencode(".jpg", np.zeros((24, 40, 3), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, progressive])
        assert jpeg_header_size(buf.tobytes()) == (24, 40, 3)
    with pytest.raises(FieldError, match="undecodable JPEG"):
        jpeg_header_size(b"\xff\xd8\xff\xe0\x00\x10JFIF")


def test_a_tiny_jpeg_claiming_16000_px_is_refused_before_decoding() -> None:
    frame = replace(sample_messages()[0], truth=None)
    bomb = _lying_jpeg(16000, 16000)
    assert len(bomb) < 1200 and jpeg_header_size(bomb)[:2] == (16000, 16000)
    payload = _tamper(frame, image_rgb={"jpeg": bomb})
    rss_before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with pytest.raises(ProtocolError, match="16000x16000 px.*refused before decoding"):
        decode(payload)
    assert time.perf_counter() - t0 < 0.05  # decoding it took 3 s
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before_kb < 50_000  # decoding it took 826 MB


# --- stamp bound --------------------------------------------------------------------------------------


def test_a_stamp_leading_the_receivers_own_clock_is_refused() -> None:
    clock = DataClock("sim")
    bound = StampBound(1.0, own=own_time(clock), own_clock="sim")
    assert bound.judge("uav1", Stamp(5.0, "sim"), bound.arrive()) is None  # no own time yet: nothing to judge by
    clock.observe(Stamp(10.0, "sim"))
    arrival = bound.arrive()
    assert bound.judge("uav1", Stamp(10.9, "sim"), arrival) is None
    assert bound.judge("uav1", Stamp(3.0, "sim"), arrival) is None  # the past is the receiver's call
    assert "leads the receiver's clock" in bound.judge("uav1", Stamp(40.0, "sim"), arrival)


def test_a_learnt_clock_refuses_the_future_and_cannot_be_ratcheted() -> None:
    bound = StampBound(1.0)  # the vehicle clock is learnt at (about) one second per second
    t0 = 1000.0
    assert bound.judge("uav1", Stamp(100.0, "vehicle"), Arrival(t0)) is None
    assert bound.judge("uav1", Stamp(100.05, "vehicle"), Arrival(t0 + 0.05)) is None
    assert bound.judge("uav1", Stamp(130.0, "vehicle"), Arrival(t0 + 0.06)) is not None  # 30 s ahead
    # A forger staying just inside the tolerance gains nothing: the anchor stays with honest samples.
    for k in range(1, 20):
        forged = 100.05 + 0.01 * k * 1.05 + 0.99
        assert bound.judge("uav1", Stamp(forged, "vehicle"), Arrival(t0 + 0.05 + 0.01 * k)) is None
    assert bound.judge("uav1", Stamp(102.5, "vehicle"), Arrival(t0 + 0.3)) is not None
    assert bound.judge("uav1", Stamp(100.3, "vehicle"), Arrival(t0 + 0.3)) is None  # honest keeps flowing
    # Another vehicle's clock is its own.
    assert bound.judge("uav2", Stamp(5000.0, "vehicle"), Arrival(t0 + 0.3)) is None


def test_a_backlog_after_an_outage_is_accepted_and_live_samples_keep_coming() -> None:
    bound = StampBound(1.0)
    for k in range(20):  # 5 Hz, honest, small latency
        assert bound.judge("uav1", Stamp(100.0 + 0.2 * k, "vehicle"), Arrival(10.0 + 0.2 * k + 0.01)) is None
    # A 3 s outage, then the link flushes its backlog within a few ms, oldest first, then live again.
    t_last, a_back = 100.0 + 0.2 * 19, 10.0 + 0.2 * 19 + 3.0
    for k in range(1, 16):
        assert bound.judge("uav1", Stamp(t_last + 0.2 * k, "vehicle"), Arrival(a_back + 0.001 * k)) is None
    assert bound.judge("uav1", Stamp(t_last + 3.2, "vehicle"), Arrival(a_back + 0.2)) is None
    # Longer than the learning window: the clock is learnt afresh from the flushed backlog.
    a_long = a_back + 0.2 + 30.0
    for k in range(1, 150):
        assert bound.judge("uav1", Stamp(t_last + 3.2 + 0.2 * k, "vehicle"), Arrival(a_long + 0.001 * k)) is None
    assert bound.judge("uav1", Stamp(t_last + 3.2 + 30.2, "vehicle"), Arrival(a_long + 0.2)) is None
    assert bound.judge("uav1", Stamp(t_last + 3.2 + 60.0, "vehicle"), Arrival(a_long + 2.0)) is not None


def test_an_old_first_stamp_cannot_make_fresh_frames_look_like_the_future() -> None:
    # The sim's slow first render: its first frame reaches the segmenter 3 s behind the vehicle's
    # clock, then fresh frames follow at 2 Hz. Was: refused for the whole 10 s learning window,
    # and `up` ended the flight "segmenter hung" after 8 s.
    bound = StampBound(1.0)
    assert bound.judge("uav1", Stamp(100.0, "vehicle"), Arrival(50.0)) is None  # old: the clock is ~103 s
    verdicts = [bound.judge("uav1", Stamp(103.0 + 0.5 * k, "vehicle"), Arrival(50.0 + 0.5 * k)) for k in range(1, 21)]
    refused = [v for v in verdicts if v is not None]
    assert refused and all("leads" in v for v in refused)
    assert len(refused) < REANCHOR_SAMPLES and verdicts[REANCHOR_SAMPLES - 1:] == [None] * (21 - REANCHOR_SAMPLES)
    # Re-anchored on the live clock: a stamp leading it is refused again.
    assert bound.judge("uav1", Stamp(140.0, "vehicle"), Arrival(60.1)) is not None


def test_a_steady_forged_stream_never_re_anchors_while_honest_samples_arrive() -> None:
    bound = StampBound(1.0)
    for k in range(100):  # 10 s: honest at 5 Hz, a forger 30 s ahead in step with it
        a_s = 10.0 + 0.2 * k
        assert bound.judge("uav1", Stamp(100.0 + 0.2 * k, "vehicle"), Arrival(a_s)) is None
        if k:
            assert bound.judge("uav1", Stamp(130.0 + 0.2 * k, "vehicle"), Arrival(a_s + 0.01)) is not None


def test_lockstep_sim_time_is_not_bounded_by_rate() -> None:
    bound = StampBound(1.0)
    assert bound.judge("uav1", Stamp(0.0, "sim"), Arrival(0.0)) is None
    assert bound.judge("uav1", Stamp(50.0, "sim"), Arrival(0.001)) is None  # a fast lockstep burst
    realtime = StampBound(1.0, rates={"sim": 1.05})
    assert realtime.judge("uav1", Stamp(0.0, "sim"), Arrival(0.0)) is None
    assert realtime.judge("uav1", Stamp(50.0, "sim"), Arrival(0.001)) is not None


def test_bad_bound_settings_are_refused() -> None:
    with pytest.raises(ValueError):
        StampBound(-1.0)
    with pytest.raises(ValueError):
        StampBound(1.0, own=lambda: 0.0)
    with pytest.raises(ValueError):
        StampBound(1.0, rates={"sim": 0.0})


# --- the inbox ----------------------------------------------------------------------------------------


def _garbage(heatmap: SafetyHeatmap, i: int) -> bytes:
    """Varied refusals: not msgpack, another schema, a NaN, an absurd altitude."""
    kind = i % 4
    if kind == 0:
        return bytes([0xC1]) + i.to_bytes(4, "little")
    if kind == 1:
        return encode(sample_messages()[1])
    if kind == 2:
        return _tamper(heatmap, hfov_rad=float("nan"))
    return _tamper(heatmap, alt_agl_m=1e300)


def _flush(a: zenoh.Session, b: zenoh.Session, marker_key: str) -> None:
    """Wait until everything `a` published before now has reached `b` (one link delivers in order)."""
    got = []
    sub = b.declare_subscriber(marker_key, lambda s: got.append(s))
    try:
        assert wait_until(lambda: (a.put(marker_key, b"m", congestion_control=BLOCK), bool(got))[1], 10.0)
    finally:
        sub.undeclare()


def _warm_up(a, inbox, key, msg) -> None:
    assert wait_until(lambda: (a.put(key, encode(msg)), inbox.poll() is not None)[1], 5.0)
    while inbox.recv(0.05) is not None:
        pass


def test_a_garbage_flood_never_evicts_the_newest_valid_sample(zenoh_pair, caplog) -> None:
    a, b = zenoh_pair
    key = keys.heatmap("uav1")
    heatmap = sample_messages()[2]
    n = 2000
    with Inbox(b, key, SafetyHeatmap, newest_only=True) as inbox:
        _warm_up(a, inbox, key, heatmap)
        rejected_before = sum(inbox.rejected.values())
        valid = replace(heatmap, seq=4242)
        caplog.set_level(logging.WARNING, logger="dovesei.shared.lifecycle")
        caplog.clear()
        a.put(key, encode(valid), congestion_control=BLOCK)
        for i in range(n):
            a.put(key, _garbage(heatmap, i), congestion_control=BLOCK)
        _flush(a, b, "dovesei/uav1/test_marker")
        got = inbox.poll()  # only now: the whole flood arrived after the valid sample
        assert got is not None and got.seq == 4242
        assert inbox.poll() is None
        assert sum(inbox.rejected.values()) - rejected_before == n  # every refusal counted, decode failures too
        # One line per kind of refusal, not one per message.
        assert len([r for r in caplog.records if "rejected on" in r.getMessage()]) <= 6


def test_a_garbage_flood_never_evicts_queued_commands(zenoh_pair) -> None:
    a, b = zenoh_pair
    key = keys.cmd("uav1")
    cmd = sample_messages()[4]
    heatmap = sample_messages()[2]
    with Inbox(b, key, VelocityCommand, newest_only=False, depth=16) as inbox:
        _warm_up(a, inbox, key, cmd)
        a.put(key, encode(replace(cmd, seq=1)), congestion_control=BLOCK)
        for i in range(FLOOD_DEPTH // 2):  # far more than the queue of 16 valid commands
            a.put(key, _garbage(heatmap, i), congestion_control=BLOCK)
        a.put(key, encode(replace(cmd, seq=2)), congestion_control=BLOCK)
        _flush(a, b, "dovesei/uav1/test_marker")
        assert [inbox.poll().seq, inbox.poll().seq] == [1, 2]
        assert inbox.poll() is None and inbox.dropped == 0


def test_a_heatmap_stamped_30_s_ahead_is_refused_and_honest_ones_keep_coming(zenoh_pair) -> None:
    a, b = zenoh_pair
    key = keys.heatmap("uav1")
    clock = DataClock("sim")  # the controller's clock, fed by the states it receives
    clock.observe(Stamp(12.5, "sim"))
    heatmap = sample_messages()[2]  # stamped 12.5 s
    bound = StampBound(1.0, own=own_time(clock), own_clock="sim")
    with Inbox(b, key, SafetyHeatmap, newest_only=False, stamps=bound) as inbox:
        _warm_up(a, inbox, key, heatmap)
        a.put(key, encode(replace(heatmap, seq=1, stamp=Stamp(42.5, "sim"))), congestion_control=BLOCK)
        a.put(key, encode(replace(heatmap, seq=2, stamp=Stamp(12.55, "sim"))), congestion_control=BLOCK)
        got = inbox.recv(5.0)
        assert got is not None and got.seq == 2
        assert inbox.rejected[REJECT_STAMP] == 1


def test_a_state_from_a_vehicle_clock_jumping_ahead_is_refused(zenoh_pair) -> None:
    a, b = zenoh_pair
    key = keys.state("uav1")
    state = replace(sample_messages()[1], stamp=Stamp(500.0, "vehicle"))
    with Inbox(b, key, VehicleState, newest_only=True) as inbox:
        _warm_up(a, inbox, key, state)
        a.put(key, encode(replace(state, seq=1, stamp=Stamp(530.0, "vehicle"))), congestion_control=BLOCK)
        _flush(a, b, "dovesei/uav1/test_marker")
        assert inbox.poll() is None and inbox.rejected[REJECT_STAMP] == 1
        assert inbox.stats()["rejected"][REJECT_STAMP] == 1


def test_a_flood_of_bad_prompts_logs_a_few_lines_not_one_per_message(zenoh_pair, caplog) -> None:
    a, b = zenoh_pair
    key = keys.prompts("uav1")
    prompts = sample_messages()[6]
    with Inbox(b, key, PromptSetMsg, newest_only=False) as inbox:
        _warm_up(a, inbox, key, prompts)
        caplog.set_level(logging.WARNING, logger="dovesei.shared.lifecycle")
        caplog.clear()
        for i in range(500):
            a.put(key, b"\xc1" if i % 2 else _tamper(prompts, template="no placeholder"), congestion_control=BLOCK)
        a.put(key, encode(replace(prompts, positive=("meadow",))), congestion_control=BLOCK)
        got = inbox.recv(5.0)
        assert got is not None and got.positive == ("meadow",)
        assert sum(inbox.rejected.values()) == 500
        assert len([r for r in caplog.records if "rejected on" in r.getMessage()]) <= 3


def test_a_sender_choosing_its_errors_cannot_grow_the_counters(zenoh_pair, caplog) -> None:
    a, b = zenoh_pair
    key = keys.state("uav1")
    state = sample_messages()[1]
    with Inbox(b, key, VehicleState, newest_only=False) as inbox:
        _warm_up(a, inbox, key, state)
        caplog.set_level(logging.WARNING, logger="dovesei.shared.lifecycle")
        caplog.clear()
        for i in range(300):  # every payload a different unknown schema, and numbers that differ
            a.put(key, msgpack.packb({"_schema": f"evil-{i}", "_v": 1}) if i % 2 else
                  _tamper(state, alt_agl_m=1e6 + i), congestion_control=BLOCK)
        a.put(key, encode(replace(state, seq=77)), congestion_control=BLOCK)
        got = inbox.recv(5.0)
        assert got is not None and got.seq == 77
        assert sum(inbox.rejected.values()) == 300 and len(inbox.rejected) <= MAX_REASONS + 1
        assert len([r for r in caplog.records if "rejected on" in r.getMessage()]) <= MAX_REASONS + 1


def test_rate_limited_log_says_the_first_of_each_kind_then_summarises(caplog) -> None:
    rl = RateLimitedLog(logging.getLogger("test.rl"), "rejected on k", interval_s=3600.0)
    caplog.set_level(logging.WARNING, logger="test.rl")
    for i in range(500):
        rl.warn("a" if i % 2 else "b", f"detail {i}")
    assert [r.getMessage() for r in caplog.records] == ["rejected on k: detail 0", "rejected on k: detail 1"]
    rl.flush(force=True)
    assert "498 more" in caplog.records[-1].getMessage()
