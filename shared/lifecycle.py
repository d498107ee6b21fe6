"""Service life: stop on signals, liveliness tokens, typed inboxes, waiting with a deadline.

Signal handlers only set a stop event so that `with` blocks close Zenoh sessions and
subscribers (an open Zenoh callback at interpreter exit hangs the process). Callbacks never do
work: subscribers hand samples to a ring (newest wins) or a FIFO, and the service loop decodes
them through an `Inbox`, which counts and logs what it rejects so nothing malformed reaches an
algorithm and the service keeps serving.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Generic, TypeVar

import zenoh

from dovesei.shared import keys
from dovesei.shared.codec import DEFAULT_MAX_BYTES, decode
from dovesei.shared.errors import ProtocolError
from dovesei.shared.messages import Message

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)


def install_stop_handlers(stop: threading.Event | None = None) -> threading.Event:
    """SIGTERM and SIGINT set `stop` and do nothing else (main thread only)."""
    stop = stop or threading.Event()

    def _handler(signum: int, _frame: object) -> None:
        log.info("received %s, stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGTERM, _handler)
    signal.signal(signal.SIGINT, _handler)
    return stop


def write_stats(path: Path, stats: Mapping[str, Any]) -> None:
    """Write a service's counters as JSON at exit (`--stats-out`); a failure only warns.

    Written to a temporary file and renamed, so a reader never sees half a file.
    """
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(stats, default=_jsonable))
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("could not write the stats to %s: %s", path, exc)  # the service's work is unaffected


def _jsonable(value: Any) -> Any:
    if isinstance(value, (set, tuple, deque)):
        return list(value)
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.005,
               stop: threading.Event | None = None) -> bool:
    """Poll `predicate` until it holds (True) or the deadline passes (False)."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
            return False
        time.sleep(poll_s)


def declare_alive(session: zenoh.Session, vehicle: str, service: str) -> zenoh.LivelinessToken:
    """The token other services and `dovesei up` watch to know this service is up."""
    return session.liveliness().declare_token(keys.alive(vehicle, service))


def is_alive(session: zenoh.Session, vehicle: str, service: str, timeout_s: float = 1.0) -> bool:
    """Ask the network once whether a service's liveliness token exists."""
    replies = session.liveliness().get(keys.alive(vehicle, service), timeout=timeout_s)
    return any(r.ok is not None for r in replies)


class Inbox(Generic[M]):
    """A subscriber whose samples are decoded in the caller's thread and counted when rejected.

    The Zenoh callback only hands the raw sample over (a deque and an event): decoding, checking
    and logging happen in the service loop. `newest_only=True` keeps one sample: a slow consumer
    never builds a backlog. Otherwise a FIFO of `depth` samples keeps every message (commands,
    prompt changes); on overflow the oldest is dropped and counted. `wakeup`, an event shared by
    several inboxes, lets one loop sleep until any of them has something, with no polling delay.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, expected: type[M], *, newest_only: bool,
                 depth: int = 256, max_bytes: int = DEFAULT_MAX_BYTES,
                 wakeup: threading.Event | None = None) -> None:
        self.key_expr, self.expected, self.max_bytes = key_expr, expected, max_bytes
        self.rejected: Counter[str] = Counter()
        self.received = 0
        self.dropped = 0  # FIFO overflow (never in newest-only mode, where replacing is the point)
        self._reported_drops = 0
        # (sample, wall time of arrival): stamped in the callback, so a transport-latency figure
        # measures the network and not how long the service loop took to get to the message.
        self._pending: deque[tuple[zenoh.Sample, float]] = deque()
        self.last_recv_wall_s = 0.0  # arrival time of the message the last poll returned
        self._capacity = 1 if newest_only else max(1, depth)
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self._events = (self._ready,) if wakeup is None else (self._ready, wakeup)
        self._sub = session.declare_subscriber(key_expr, self._hand_off)

    def _hand_off(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: no decoding, no logging, no Zenoh calls.
        with self._lock:
            if len(self._pending) >= self._capacity:
                self._pending.popleft()
                if self._capacity > 1:
                    self.dropped += 1
            self._pending.append((sample, time.time()))
        for event in self._events:
            event.set()

    def _decode(self, sample: zenoh.Sample) -> M | None:
        key = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes(), self.expected, key=key, max_bytes=self.max_bytes)
        except ProtocolError as exc:
            self.rejected[exc.problem.split(":")[0][:60]] += 1
            log.warning("rejected message on %s: %s", key, exc.problem)
            return None
        self.received += 1
        return msg

    def poll(self) -> M | None:
        """The next valid message if one is waiting, else None (never blocks)."""
        got = self.poll_keyed()
        return None if got is None else got[0]

    def poll_keyed(self) -> tuple[M, str] | None:
        """Like `poll`, with the concrete key it arrived on (whose frame, on a wildcard subscription)."""
        if self.dropped != self._reported_drops:
            log.warning("%s: %d messages dropped (queue of %d full)", self.key_expr,
                        self.dropped - self._reported_drops, self._capacity)
            self._reported_drops = self.dropped
        while True:
            with self._lock:
                if not self._pending:
                    return None
                sample, recv_wall_s = self._pending.popleft()
            msg = self._decode(sample)
            if msg is not None:
                self.last_recv_wall_s = recv_wall_s
                return msg, str(sample.key_expr)

    def recv(self, timeout_s: float, stop: threading.Event | None = None) -> M | None:
        """Wait up to `timeout_s` for the next valid message (woken at once when one arrives)."""
        deadline = time.monotonic() + timeout_s
        while True:
            self._ready.clear()  # before polling: a sample arriving after this sets it again
            msg = self.poll()
            if msg is not None:
                return msg
            remaining = deadline - time.monotonic()
            if remaining <= 0 or (stop is not None and stop.is_set()):
                return None
            # Bounded so that a stop request is noticed within 50 ms.
            self._ready.wait(min(remaining, 0.05))

    def close(self) -> None:
        self._sub.undeclare()

    def __enter__(self) -> Inbox[M]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
