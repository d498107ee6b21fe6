"""Real in-process Zenoh sessions on loopback: pub/sub of every message, a queryable, liveliness."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.lifecycle import Inbox, declare_alive, is_alive, wait_until
from dovesei.shared.messages import CameraFrame, SafetyHeatmap, Stamp, VehicleState, replace

from tests.shared.samples import sample_messages


def test_pub_sub_round_trip_of_every_message(zenoh_pair) -> None:
    a, b = zenoh_pair
    msgs = sample_messages()
    got: list = []
    sub = b.declare_subscriber("dovesei/uav1/test", zenoh.handlers.FifoChannel(64))
    try:
        # Publish until the subscription has propagated, then every message once.
        assert wait_until(lambda: (a.put("dovesei/uav1/test", b"ping"), sub.try_recv() is not None)[1], 5.0)
        for m in msgs:
            a.put("dovesei/uav1/test", encode(m))
        assert wait_until(lambda: (got.append(s) if (s := sub.try_recv()) is not None else None,
                                   len([g for g in got if g.payload.to_bytes() != b"ping"]) >= len(msgs))[1], 5.0)
    finally:
        sub.undeclare()
    decoded = [decode(s.payload.to_bytes()) for s in got if s.payload.to_bytes() != b"ping"]
    assert [type(d) for d in decoded] == [type(m) for m in msgs]
    assert decoded[1] == msgs[1]  # a record without arrays compares equal field by field


def test_inbox_rejects_and_counts_bad_payloads_then_keeps_serving(zenoh_pair) -> None:
    a, b = zenoh_pair
    key = keys.state("uav1")
    good = sample_messages()[1]
    with Inbox(b, key, VehicleState, newest_only=False) as inbox:
        assert wait_until(lambda: (a.put(key, encode(good)), inbox.poll() is not None)[1], 5.0)
        a.put(key, b"\x00garbage")
        a.put(key, encode(sample_messages()[0]))  # a camera frame on the state key
        last = replace(good, seq=999)
        a.put(key, encode(last))
        # Warm-up copies may still be queued ahead (FIFO): read up to the marker.
        got = []
        assert wait_until(lambda: (m := inbox.recv(0.1)) is not None and got.append(m) is None and m.seq == 999, 5.0)
        assert got[-1] == last
        assert sum(inbox.rejected.values()) == 2


def test_newest_only_inbox_never_builds_a_backlog(zenoh_pair) -> None:
    a, b = zenoh_pair
    key = keys.state("uav1")
    base = sample_messages()[1]
    with Inbox(b, key, VehicleState, newest_only=True) as inbox:
        assert wait_until(lambda: (a.put(key, encode(base)), inbox.poll() is not None)[1], 5.0)
        for seq in range(100, 150):
            a.put(key, encode(VehicleState("uav1", seq, base.stamp, 50.0, (0.0, 0.0, 0.0))))
        newest: list[int] = []
        assert wait_until(lambda: (m := inbox.poll()) is not None and newest.append(m.seq) is None and m.seq == 149,
                          5.0)
        # The ring keeps one sample: at most a few intermediate ones were seen, never all 50.
        assert len(newest) < 50 and inbox.poll() is None


def test_queryable_request_reply(zenoh_pair) -> None:
    a, b = zenoh_pair
    frame = sample_messages()[0]
    stop = threading.Event()
    queryable = a.declare_queryable(keys.segment(keys.ANY_VEHICLE), zenoh.handlers.FifoChannel(8))

    def serve() -> None:
        while not stop.is_set():
            q = queryable.try_recv()
            if q is None:
                stop.wait(0.002)
                continue
            req = decode(q.payload.to_bytes(), CameraFrame)
            reply = SafetyHeatmap(req.vehicle_id, req.seq, req.stamp, np.zeros(req.image_rgb.shape[:2], np.uint8),
                                  req.alt_agl_m, req.hfov_rad, "simulated", True, "p", "grouped", 0.0)
            q.reply(q.key_expr, encode(reply))
            q.drop()

    server = threading.Thread(target=serve)
    server.start()
    try:
        replies: list = []

        def ask() -> bool:
            replies.extend(r for r in b.get(keys.segment("uav1"), payload=encode(frame), timeout=1.0) if r.ok)
            return bool(replies)

        assert wait_until(ask, 10.0)  # the queryable's declaration may still be propagating
        hm = decode(replies[0].ok.payload.to_bytes(), SafetyHeatmap)
        assert hm.seq == frame.seq and hm.prob_safe.shape == frame.image_rgb.shape[:2]
    finally:
        stop.set()
        server.join()
        queryable.undeclare()


def test_liveliness_token_appears_and_disappears(zenoh_pair) -> None:
    a, b = zenoh_pair
    assert not is_alive(b, "uav1", "segmenter", timeout_s=0.3)
    token = declare_alive(a, "uav1", "segmenter")
    assert wait_until(lambda: is_alive(b, "uav1", "segmenter", timeout_s=0.3), 5.0)
    token.undeclare()
    assert wait_until(lambda: not is_alive(b, "uav1", "segmenter", timeout_s=0.3), 5.0)


def test_stamp_clock_is_part_of_the_contract() -> None:
    with pytest.raises(ValueError):
        Stamp(0.0, "gps")


def test_a_query_nobody_serves_says_so_at_once_and_wait_served_sees_a_queryable_arrive(zenoh_pair) -> None:
    from dovesei.shared.crop_server import QueryFailed, query_one, wait_served

    a, b = zenoh_pair
    key = keys.segment("uav9")
    t0 = time.monotonic()
    with pytest.raises(QueryFailed, match="nobody serves it"):
        query_one(b, key, b"", 20.0)
    assert time.monotonic() - t0 < 10.0  # Zenoh ended it: not a 20 s wait
    assert not wait_served(b, key, 0.2)
    queryable = a.declare_queryable(key)
    try:
        assert wait_served(b, key, 10.0)
    finally:
        queryable.undeclare()
