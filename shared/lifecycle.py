"""Service life: stop on signals, liveliness tokens, typed inboxes, waiting with a deadline.

Signal handlers only set a stop event so that `with` blocks close Zenoh sessions and
subscribers (an open Zenoh callback at interpreter exit hangs the process). Callbacks never do
work: subscribers hand samples to a ring (newest wins) or a FIFO, and the service loop decodes
them through an `Inbox`, which counts and logs what it rejects so nothing malformed reaches an
algorithm and the service keeps serving.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Generic, TypeVar

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

    `newest_only=True` keeps one sample (RingChannel(1)): a slow consumer never builds a backlog.
    Otherwise a FIFO of `depth` samples keeps every message (commands, prompt changes).
    """

    def __init__(self, session: zenoh.Session, key_expr: str, expected: type[M], *, newest_only: bool,
                 depth: int = 256, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        handler = zenoh.handlers.RingChannel(1) if newest_only else zenoh.handlers.FifoChannel(depth)
        self.key_expr, self.expected, self.max_bytes = key_expr, expected, max_bytes
        self.rejected: Counter[str] = Counter()
        self.received = 0
        self._sub = session.declare_subscriber(key_expr, handler)

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
        while True:
            sample = self._sub.try_recv()
            if sample is None:
                return None
            msg = self._decode(sample)
            if msg is not None:
                return msg, str(sample.key_expr)

    def recv(self, timeout_s: float, stop: threading.Event | None = None) -> M | None:
        """Wait up to `timeout_s` for the next valid message."""
        deadline = time.monotonic() + timeout_s
        while True:
            msg = self.poll()
            if msg is not None:
                return msg
            remaining = deadline - time.monotonic()
            if remaining <= 0 or (stop is not None and stop.is_set()):
                return None
            time.sleep(min(0.001, remaining))

    def close(self) -> None:
        self._sub.undeclare()

    def __enter__(self) -> Inbox[M]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
