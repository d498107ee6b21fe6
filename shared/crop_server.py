"""The `dovesei/<vehicle>/crop` queryable, served on its own thread by the camera or the sim.

    query (CropRequest, msgpack) --decode (the trust boundary)--> answer(request) --> CropFrame
      --encode (the crop as JPEG)--> reply on the crop key
    anything refused (undecodable, CropRefused, a render error) --> reply_err("crop refused: ...")

The Zenoh handler only queues the query (a FIFO of QUERY_DEPTH; more waiting than that are
dropped by Zenoh and their askers time out); the thread decodes, answers and replies, so a slow
crop never blocks a Zenoh thread, and a crash of one answer is a refusal, never a dead service.
`answer` must be safe to call from this thread while the owner's loop runs (the camera and the
sim read one snapshot of their newest frame, replaced whole).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable

import zenoh

from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import DoveseiError, ProtocolError
from dovesei.shared.lifecycle import RateLimitedLog
from dovesei.shared.messages import CropFrame, CropRequest

log = logging.getLogger(__name__)

QUERY_DEPTH = 8
CROP_JPEG_QUALITY = 90  # a 352 px crop at q90 is ~30-60 kB: fine over a radio link
_POLL_S = 0.005
MAX_REQUEST_BYTES = 4096  # a CropRequest is ~150 bytes


class QueryFailed(DoveseiError, RuntimeError):
    """A query got no usable answer: refused (the answerer's reason), undecodable, or none in time."""


def query_one(session: zenoh.Session, key: str, payload: bytes, timeout_s: float) -> bytes:
    """The first reply's payload to a query on `key`; QueryFailed with the answerer's error text, or
    saying nobody answered within `timeout_s`, or that nobody serves `key` at all (Zenoh ends a query
    at once when no queryable it knows of matches: one just declared may still be propagating)."""
    t0 = time.monotonic()
    replies = session.get(key, payload=payload, timeout=timeout_s)
    for reply in replies:
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        raise QueryFailed(f"{key}: {reply.err.payload.to_string()}")
    waited_s = time.monotonic() - t0
    if waited_s < 0.5 * timeout_s:
        raise QueryFailed(f"{key}: nobody serves it (no answer, ended after {waited_s:.2f} s of {timeout_s:g} s)")
    raise QueryFailed(f"{key}: no answer within {timeout_s:g} s (is the camera / sim serving it?)")


def wait_served(session: zenoh.Session, key: str, timeout_s: float) -> bool:
    """Whether a queryable on `key` became known to `session` within `timeout_s` (a query sent before
    that gets no answer at all)."""
    querier = session.declare_querier(key)
    try:
        deadline = time.monotonic() + timeout_s
        while not querier.matching_status.matching:
            if time.monotonic() > deadline:
                return False
            time.sleep(_POLL_S)
        return True
    finally:
        querier.undeclare()


def ask_crop(session: zenoh.Session, req: CropRequest, timeout_s: float) -> CropFrame:
    """A crop from the vehicle's camera (or the sim); QueryFailed when refused or unanswered."""
    key = keys.crop(req.vehicle_id)
    data = query_one(session, key, encode(req), timeout_s)
    try:
        return decode(data, CropFrame, key=key)
    except ProtocolError as exc:
        raise QueryFailed(str(exc)) from None


class CropServer:
    """Answers crop queries for one vehicle until `close()`; counts what it answered and refused."""

    def __init__(self, session: zenoh.Session, vehicle_id: str, answer: Callable[[CropRequest], CropFrame], *,
                 jpeg_quality: int = CROP_JPEG_QUALITY) -> None:
        self.vehicle_id, self._answer, self.jpeg_quality = vehicle_id, answer, jpeg_quality
        self.key = keys.crop(vehicle_id)
        self.answered = 0
        self.refused: Counter[str] = Counter()
        self._log = RateLimitedLog(log, f"crop refusals on {self.key}")
        self._stop = threading.Event()
        self._queryable = session.declare_queryable(self.key, zenoh.handlers.FifoChannel(QUERY_DEPTH))
        self._thread = threading.Thread(target=self._run, name=f"crop-{vehicle_id}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            query = self._queryable.try_recv()
            if query is None:
                self._stop.wait(_POLL_S)
                continue
            try:
                self._serve(query)
            finally:
                query.drop()  # finalises the query: the asker's get() ends now, not at its timeout

    def _serve(self, query: zenoh.Query) -> None:
        t0 = time.perf_counter()
        try:
            if query.payload is None:
                raise ProtocolError(self.key, "a crop query must carry an encoded CropRequest")
            req = decode(query.payload.to_bytes(), CropRequest, key=self.key, max_bytes=MAX_REQUEST_BYTES)
            crop = self._answer(req)
            query.reply(self.key, encode(crop, jpeg_quality=self.jpeg_quality))
        except DoveseiError as exc:  # ProtocolError, CropRefused, CameraError: the asker's problem, said once
            kind = type(exc).__name__
            self.refused[kind] += 1
            self._log.warn(kind, str(exc))
            query.reply_err(f"crop refused: {exc}")
            return
        except Exception as exc:  # noqa: BLE001 - a bug in one answer must not kill the server
            self.refused["internal"] += 1
            log.exception("crop query on %s failed", self.key)
            query.reply_err(f"crop refused: internal error ({type(exc).__name__}: {exc})")
            return
        self.answered += 1
        log.debug("crop %d (frame %d, %.1f m over %d px) answered in %.1f ms", req.request_seq, crop.frame_seq,
                  req.side_m, req.out_px, (time.perf_counter() - t0) * 1e3)

    def stats(self) -> dict[str, object]:
        return {"crops_answered": self.answered, "crops_refused": dict(self.refused)}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._queryable.undeclare()
        self._log.flush(force=True)
