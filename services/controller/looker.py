"""Carrying out a policy's close looks: crop from the camera, score with the segmenter, hand back.

    Decision.look_request --ControllerCore--> CropRequest --Looker.submit
        --> camera (or sim) crop key: CropFrame --> segmenter segment key: CropHeatmap
        --> LookResult (or its refusal) --Looker.poll--> the next Observation.look

`Looker` is the two-method interface the core uses. `SyncLooker` answers in `submit` itself (the
lockstep sim waits for our command meanwhile, so a look costs no sim time and the same seed gives
the same flight in one process or three); `ThreadLooker` answers on a worker thread (real time:
the 20 Hz loop keeps commanding while a look is in flight; the policy holds meanwhile). Both take
`ask(request) -> (CropFrame, CropHeatmap)`; `zenoh_ask` builds it over the crop and segment
queryables; `seen(crop, heatmap)`, if given, gets every answered look (the service publishes it on
the look key for operators and reports; the policy itself gets the scores only). Every failure becomes a refusal text: a missing answer never becomes a verdict.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol

from dovesei.controller.policies.base import LookResult
from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.crop_server import ask_crop, query_one
from dovesei.shared.errors import DoveseiError, ProtocolError
from dovesei.shared.messages import CropFrame, CropHeatmap, CropRequest

log = logging.getLogger(__name__)

Ask = Callable[[CropRequest], tuple[CropFrame, CropHeatmap]]
CROP_TIMEOUT_S = 2.0
SEGMENT_TIMEOUT_S = 10.0  # CLIPSeg on a loaded ground station


class Looker(Protocol):
    def submit(self, req: CropRequest) -> None: ...

    def poll(self) -> LookResult | None:
        """The answer to the last submitted request, once; None while there is none."""
        ...


Seen = Callable[[CropFrame, CropHeatmap], None]  # what the looker saw, for operators (the look key)


def _answer(ask: Ask, req: CropRequest, seen: Seen | None = None) -> LookResult:
    try:
        crop, heatmap = ask(req)
    except DoveseiError as exc:  # CropRefused, FrameRejected-as-query-error, QueryFailed, ProtocolError
        return LookResult(req.request_seq, refusal=str(exc))
    if heatmap.request_seq != req.request_seq or heatmap.vehicle_id != req.vehicle_id:
        return LookResult(req.request_seq, refusal=f"answer to request {heatmap.request_seq} of "
                                                   f"{heatmap.vehicle_id!r}, asked {req.request_seq}")
    if heatmap.stamp.clock != req.stamp.clock:  # an answer stamped on another clock is not this look's
        return LookResult(req.request_seq, refusal=f"answer captured on the {heatmap.stamp.clock!r} clock, "
                                                   f"asked on {req.stamp.clock!r}")
    if seen is not None:
        seen(crop, heatmap)
    return LookResult(req.request_seq, heatmap=heatmap)  # the crop (with a sim's truth) stays here


class SyncLooker:
    """Answers in `submit` (lockstep and in-process episodes)."""

    def __init__(self, ask: Ask, seen: Seen | None = None) -> None:
        self._ask, self._seen, self._result = ask, seen, None

    def submit(self, req: CropRequest) -> None:
        self._result = _answer(self._ask, req, self._seen)

    def poll(self) -> LookResult | None:
        result, self._result = self._result, None
        return result


class ThreadLooker:
    """Answers on a worker thread, one request at a time (a new one while busy is refused)."""

    def __init__(self, ask: Ask, seen: Seen | None = None) -> None:
        self._ask, self._seen = ask, seen
        self._lock = threading.Lock()
        self._result: LookResult | None = None
        self._busy = False

    def submit(self, req: CropRequest) -> None:
        with self._lock:
            if self._busy:
                self._result = LookResult(req.request_seq, refusal="a close look is already in flight")
                return
            self._busy = True
        threading.Thread(target=self._run, args=(req,), name="close-look", daemon=True).start()

    def _run(self, req: CropRequest) -> None:
        result = _answer(self._ask, req, self._seen)
        with self._lock:
            self._result, self._busy = result, False

    def poll(self) -> LookResult | None:
        with self._lock:
            result, self._result = self._result, None
        return result


def zenoh_ask(session, *, crop_timeout_s: float = CROP_TIMEOUT_S, segment_timeout_s: float = SEGMENT_TIMEOUT_S) -> Ask:
    """Ask over Zenoh: the crop from the vehicle's camera, then its scores from the segmenter."""
    def ask(req: CropRequest) -> tuple[CropFrame, CropHeatmap]:
        crop = ask_crop(session, req, crop_timeout_s)
        key = keys.segment(req.vehicle_id)
        data = query_one(session, key, encode(crop, jpeg_quality=90), segment_timeout_s)
        try:
            return crop, decode(data, CropHeatmap, key=key)
        except ProtocolError as exc:
            raise DoveseiError(str(exc)) from None

    return ask
