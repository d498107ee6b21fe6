"""Service life: stop on signals, liveliness tokens, typed inboxes, waiting with a deadline.

Signal handlers only set a stop event so that `with` blocks close Zenoh sessions and
subscribers (an open Zenoh callback at interpreter exit hangs the process). Callbacks never do
work: subscribers hand raw samples over, and the service loop validates them through an `Inbox`
(decoded, its stamp not from the future on the receiver's clock)
before one can become the newest; it counts what it rejects and logs it rate-limited, so nothing
malformed reaches an algorithm, a flood cannot evict a valid sample, and the service keeps serving.
"""

from __future__ import annotations

import faulthandler
import json
import logging
import os
import re
import signal
import sys
import threading
import time
import typing
from collections import Counter, deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Generic, TypeVar

import zenoh

from dovesei.shared import keys
from dovesei.shared.clock import Arrival, StampBound
from dovesei.shared.codec import DEFAULT_MAX_BYTES, decode
from dovesei.shared.errors import ProtocolError
from dovesei.shared.messages import Message, Stamp

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)


def install_stop_handlers(stop: threading.Event | None = None) -> threading.Event:
    """SIGTERM and SIGINT set `stop` and do nothing else (main thread only).

    SIGUSR1 writes every thread's stack to stderr (the service's log under `up`) and the process
    goes on: what a process that does not stop is waiting for, without a debugger.
    """
    stop = stop or threading.Event()
    faulthandler.register(signal.SIGUSR1, all_threads=True)

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


class RateLimitedLog:
    """Warn at once about the first occurrence of each kind of event, then at most once per interval.

    A flood (garbage on a key, a sender with a skewed clock) must not become a flood of log lines:
    the first of each kind is logged with its detail, later ones are counted and summarised.
    """

    def __init__(self, logger: logging.Logger, what: str, interval_s: float = 10.0) -> None:
        self._log, self.what, self.interval_s = logger, what, interval_s
        self._seen: set[str] = set()
        self._suppressed: Counter[str] = Counter()
        self._last_summary_s = time.monotonic()

    def warn(self, kind: str, detail: str) -> None:
        if kind not in self._seen:
            self._seen.add(kind)
            self._log.warning("%s: %s", self.what, detail)
        else:
            self._suppressed[kind] += 1
        self.flush()

    def flush(self, force: bool = False) -> None:
        """Summarise what was suppressed, if the interval has passed (or `force`)."""
        now = time.monotonic()
        if self._suppressed and (force or now - self._last_summary_s >= self.interval_s):
            self._log.warning("%s: %d more in the last %.0f s (%s)", self.what, sum(self._suppressed.values()),
                              now - self._last_summary_s,
                              ", ".join(f"{k}: {n}" for k, n in self._suppressed.most_common(5)))
            self._suppressed.clear()
            self._last_summary_s = now


REJECT_STAMP = "stamp from the future"
REJECT_OVERFLOW = "arrived faster than validated"
# A newest-only inbox holds this many raw samples between two polls, so a flood of garbage is
# decoded and refused instead of pushing the last valid sample out (and bounded in bytes, so a
# flood of large payloads cannot take the memory instead).
FLOOD_DEPTH = 4096
MAX_REASONS = 32
_NUMBER_RE = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


class Inbox(Generic[M]):
    """A subscriber whose samples are validated in the caller's thread and counted when rejected.

    The Zenoh callback only hands the raw sample over (a deque and an event) with its arrival
    time: decoding, checking and logging happen in the service loop. A sample must pass decoding,
    the vehicle-id check (the id inside must be the key's) and the stamp bound (`StampBound`: not
    from the future on the receiver's clock) before it can be returned; whatever fails is counted
    in `rejected` by reason and logged rate-limited.

    `newest_only=True` returns only the newest *valid* sample: raw samples wait (up to
    `FLOOD_DEPTH`, and `4 x max_bytes`) and are validated newest first, so garbage arriving after
    a valid sample is refused and never displaces it; older samples behind a valid one are
    superseded undecoded (`superseded`). Otherwise a FIFO of `depth` valid samples keeps every
    message (commands, prompt changes); on overflow the oldest is dropped and counted. `wakeup`,
    an event shared by several inboxes, lets one loop sleep until any of them has something.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, expected: type[M], *, newest_only: bool,
                 depth: int = 256, max_bytes: int = DEFAULT_MAX_BYTES,
                 wakeup: threading.Event | None = None, stamps: StampBound | None = None) -> None:
        self.key_expr, self.expected, self.max_bytes = key_expr, expected, max_bytes
        self.newest_only = newest_only
        self.stamps = stamps if stamps is not None else StampBound()
        self.rejected: Counter[str] = Counter()
        self.received = 0
        self.dropped = 0  # valid messages lost to FIFO overflow (a flood overflowing: rejected[REJECT_OVERFLOW])
        self.superseded = 0  # newest-only: raw samples behind a newer valid one, never decoded
        self._reported_drops = 0
        self._reject_log = RateLimitedLog(log, f"rejected on {key_expr}")
        # (sample, arrival): stamped in the callback, so a transport-latency figure measures the
        # network and not how long the service loop took to get to the message, and a stamp is
        # judged against the receiver's clock when the sample landed.
        self._raw: deque[tuple[zenoh.Sample, float, Arrival, int]] = deque()
        self._raw_bytes = 0
        self._raw_limit = FLOOD_DEPTH if newest_only else max(FLOOD_DEPTH, depth)
        self._raw_byte_limit = 4 * max_bytes
        self._valid: deque[tuple[M, str, float]] = deque()
        self.last_recv_wall_s = 0.0  # arrival time of the message the last poll returned
        self._capacity = 1 if newest_only else max(1, depth)
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self._events = (self._ready,) if wakeup is None else (self._ready, wakeup)
        self._sub = session.declare_subscriber(key_expr, self._hand_off)

    def _hand_off(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: no decoding, no logging, no Zenoh calls.
        arrival, recv_wall_s, size = self.stamps.arrive(), time.time(), len(sample.payload)
        with self._lock:
            self._raw.append((sample, recv_wall_s, arrival, size))
            self._raw_bytes += size
            while len(self._raw) > self._raw_limit or (self._raw_bytes > self._raw_byte_limit and len(self._raw) > 1):
                self._raw_bytes -= self._raw.popleft()[3]
                self.rejected[REJECT_OVERFLOW] += 1
        for event in self._events:
            event.set()

    def _validate(self, sample: zenoh.Sample, arrival: Arrival) -> M | None:
        key = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes(), self.expected, key=key, max_bytes=self.max_bytes)
        except ProtocolError as exc:
            return self._reject(_reason(exc.problem), f"{key}: {exc.problem}")
        # Stamps are judged per vehicle: a ground segmenter serves vehicles whose clocks differ.
        # (A message whose vehicle id differs from its key's is the service's to count as foreign.)
        source = _vehicle_in(key)
        stamp = getattr(msg, "stamp", None)
        if isinstance(stamp, Stamp):
            refused = self.stamps.judge(source or key, stamp, arrival)
            if refused is not None:
                return self._reject(REJECT_STAMP, f"{key}: {refused}")
        self.received += 1
        return msg

    def _reject(self, reason: str, detail: str) -> None:
        with self._lock:  # the callback counts overflows into the same counter
            if reason not in self.rejected and len(self.rejected) >= MAX_REASONS:
                reason = "other"  # a sender choosing its errors must not grow the counter (or the log) without end
            self.rejected[reason] += 1
        self._reject_log.warn(reason, detail)
        return None

    def _drain(self) -> None:
        """Validate what has arrived; only valid samples reach `_valid`."""
        with self._lock:
            raw, self._raw, self._raw_bytes = self._raw, deque(), 0
        if self.newest_only:
            while raw:  # newest first: the first valid one wins, whatever garbage came after it
                sample, recv_wall_s, arrival, _ = raw.pop()
                msg = self._validate(sample, arrival)
                if msg is not None:
                    self.superseded += len(raw)
                    self._valid.clear()
                    self._valid.append((msg, str(sample.key_expr), recv_wall_s))
                    return
            return
        for sample, recv_wall_s, arrival, _ in raw:
            msg = self._validate(sample, arrival)
            if msg is not None:
                if len(self._valid) >= self._capacity:
                    self._valid.popleft()
                    self.dropped += 1
                self._valid.append((msg, str(sample.key_expr), recv_wall_s))

    def poll(self) -> M | None:
        """The next valid message if one is waiting, else None (never blocks)."""
        got = self.poll_keyed()
        return None if got is None else got[0]

    def poll_keyed(self) -> tuple[M, str] | None:
        """Like `poll`, with the concrete key it arrived on (whose frame, on a wildcard subscription)."""
        self._drain()
        self._reject_log.flush()
        if self.dropped != self._reported_drops:
            log.warning("%s: %d messages dropped (queue of %d full)", self.key_expr,
                        self.dropped - self._reported_drops, self._capacity)
            self._reported_drops = self.dropped
        if not self._valid:
            return None
        msg, key, recv_wall_s = self._valid.popleft()
        self.last_recv_wall_s = recv_wall_s
        return msg, key

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

    def stats(self) -> dict[str, Any]:
        """Counters for a service's `--stats-out`: what was accepted, refused (by reason), lost."""
        return {"received": self.received, "rejected": dict(self.rejected), "dropped": self.dropped,
                "superseded": self.superseded}

    def close(self) -> None:
        self._reject_log.flush(force=True)
        self._sub.undeclare()

    def __enter__(self) -> Inbox[M]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _reason(problem: str) -> str:
    """A reject's kind: the problem before any detail, numbers folded, so one flood is one kind."""
    return _NUMBER_RE.sub("N", problem.split(":")[0])[:60]


def _vehicle_in(key: str) -> str | None:
    """The vehicle chunk of a dovesei key (`dovesei/<vehicle>/...`), else None."""
    parts = key.split("/")
    return parts[1] if len(parts) >= 3 and parts[0] == keys.ROOT else None


def exit_process(code: int) -> typing.NoReturn:
    """End a service process once its work is done and saved, skipping the interpreter's teardown.

    A process that imported torch and transformers (the segmenter, even when `auto` falls back to
    the simulated perception) spent 2-5 s tearing the interpreter down after `main` returned
    (measured on 2 shared cores at load 8), so `dovesei up` counted it as ignoring SIGTERM and
    killed it after its 5 s grace in 2 of 6 runs. Call it only after every Zenoh session is closed
    and every file is written: atexit handlers do not run. Log handlers and the standard streams
    are flushed first, so no line is lost.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing left to save
            pass
    os._exit(code)
