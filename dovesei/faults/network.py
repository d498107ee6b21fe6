"""The fault suite's network on loopback: a restartable router and a lossy relay between two routers.

    sim, controller, observers --> Router A ──Relay (drops, delays, duplicates)──> Router B <-- segmenter
                     (all Zenoh clients of their router)
                                                    camera, prompts  A -> B
                                                    heatmap          B -> A
                                                    liveliness of the segmenter mirrored on A

The relay works on Zenoh samples, not on TCP bytes: a dropped TCP segment is a broken link, while
what a radio link loses is whole messages. Each direction forwards only its own keys, so nothing
loops. Decisions come from a seeded generator, so one seed gives the same drop pattern.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import random
import threading
import time
from dataclasses import dataclass
from typing import Any

import zenoh

from dovesei.shared import keys
from dovesei.shared.zconfig import free_port, zenoh_config

log = logging.getLogger("dovesei.faults")


def client_config(endpoint: str) -> zenoh.Config:
    return zenoh_config(mode="client", connect=[endpoint], multicast_scouting=False, env={})


class Router:
    """A Zenoh router on 127.0.0.1 in this process; `restart(gap_s)` closes it and opens it again."""

    def __init__(self, port: int | None = None) -> None:
        self.port = port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self._session: Any = None
        self.open()

    def open(self) -> None:
        self._session = zenoh.open(zenoh_config(mode="router", listen=[self.endpoint], multicast_scouting=False,
                                                env={}))

    def close(self) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None

    def restart(self, gap_s: float, stop: threading.Event) -> None:
        """Down for `gap_s` (every client loses its link), then up on the same port."""
        self.close()
        stop.wait(gap_s)
        self.open()


@dataclass(frozen=True)
class LossProfile:
    """What the relay does to each forwarded sample (probabilities per sample)."""

    drop: float = 0.2
    duplicate: float = 0.05
    max_delay_s: float = 0.05  # uniform in [0, max_delay_s]: reorders samples too


@dataclass
class RelayCounts:
    forwarded: int = 0
    dropped: int = 0
    duplicated: int = 0


class Relay:
    """Forwards the segmenter's keys between router A (the rest) and router B (the segmenter)."""

    def __init__(self, a_endpoint: str, b_endpoint: str, vehicle_id: str, profile: LossProfile, seed: int) -> None:
        self.profile = profile
        self.counts: dict[str, RelayCounts] = {}
        self._rng = random.Random(seed)
        self._lock = threading.Lock()  # the generator and the counters are shared by Zenoh's threads
        self._queue: list[tuple[float, int, Any]] = []  # (due monotonic s, tiebreak, action)
        self._tiebreak = itertools.count()
        self._wake = threading.Condition(self._lock)
        self._closed = False
        self.a = zenoh.open(client_config(a_endpoint))
        self.b = zenoh.open(client_config(b_endpoint))
        self._subs: list[Any] = []
        self._tokens: dict[str, Any] = {}
        for topic, src, dst in (("camera", self.a, self.b), ("prompts", self.a, self.b), ("heatmap", self.b, self.a)):
            self.counts[topic] = RelayCounts()
            key = getattr(keys, topic)(vehicle_id)
            self._subs.append(src.declare_subscriber(key, self._forwarder(topic, dst, key)))
        # The sim waits for the segmenter's token and `up` watches it: mirror B's tokens onto A.
        self._subs.append(self.b.liveliness().declare_subscriber(keys.alive(vehicle_id, "*"), self._on_token,
                                                                 history=True))
        self._thread = threading.Thread(target=self._deliver, name="relay", daemon=True)
        self._thread.start()

    def _forwarder(self, topic: str, dst: Any, key: str):
        def on_sample(sample: Any) -> None:
            payload = sample.payload.to_bytes()
            with self._lock:
                c = self.counts[topic]
                if self._rng.random() < self.profile.drop:
                    c.dropped += 1
                    return
                copies = 2 if self._rng.random() < self.profile.duplicate else 1
                c.duplicated += copies - 1
                c.forwarded += 1
                now = time.monotonic()
                for _ in range(copies):
                    due = now + self._rng.uniform(0.0, self.profile.max_delay_s)
                    self._push(due, lambda: dst.put(key, payload))

        return on_sample

    def _on_token(self, sample: Any) -> None:
        # Liveliness is not lost by the radio model: it is the session's presence, which Zenoh keeps.
        key, put = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT

        def mirror() -> None:
            if put and key not in self._tokens:
                self._tokens[key] = self.a.liveliness().declare_token(key)
            elif not put and key in self._tokens:
                self._tokens.pop(key).undeclare()

        with self._lock:
            self._push(time.monotonic(), mirror)

    def _push(self, due: float, action: Any) -> None:
        """Queue an action for the delivery thread (called with the lock held)."""
        heapq.heappush(self._queue, (due, next(self._tiebreak), action))
        self._wake.notify()

    def _deliver(self) -> None:
        """Puts happen here, never in a callback (no Zenoh calls inside callbacks)."""
        while True:
            with self._lock:
                while not self._closed and (not self._queue or self._queue[0][0] > time.monotonic()):
                    timeout = self._queue[0][0] - time.monotonic() if self._queue else None
                    self._wake.wait(timeout)
                if self._closed:
                    return
                _, _, action = heapq.heappop(self._queue)
            action()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._wake.notify()
        self._thread.join(timeout=5)
        for sub in self._subs:
            sub.undeclare()
        for token in self._tokens.values():
            token.undeclare()
        self.b.close()
        self.a.close()

    def totals(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {t: vars(c).copy() for t, c in self.counts.items()}
