"""The segmenter as a Zenoh service (entry point `dovesei-segmenter`).

    dovesei/<vehicle>/camera   CameraFrame  --subscriber (newest wins; FIFO in --lockstep)--+
    dovesei/*/segment          CameraFrame  --queryable (request-reply)---------------------+--> SegmenterCore
    dovesei/<vehicle>/prompts  PromptSetMsg --subscriber (FIFO: every change applied once)--+
                                                                                            |
    dovesei/<vehicle>/heatmap  SafetyHeatmap <--publisher (streamed frames) <---------------+
    query reply                SafetyHeatmap, or an error reply naming the reason
    dovesei/<vehicle>/alive/segmenter  liveliness token

One loop thread does all the work (CLIPSeg is not thread-safe and a second inference thread
would only compete for the same cores): Zenoh callbacks just fill channels, and the loop takes,
in turn, every pending prompt change, one query and one frame. With `--all-vehicles` the keys use
the `*` chunk and the vehicle id of the sample's key says whose frame it is. In real-time mode the
camera channel holds one frame, so a slow model always works on the newest frame and never
builds a backlog; in lockstep mode every frame is answered in order, because the controller
waits for the heatmap of a named frame.

Bad input never stops the service: undecodable payloads (garbage, broken JPEG) are counted by
the inbox, frames the core refuses (size, no ground truth for the simulated backend, key naming
another vehicle) are counted by reason; each is logged at WARNING with the reason.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import ConfigError, DoveseiError, ProtocolError
from dovesei.shared.lifecycle import Inbox, declare_alive, install_stop_handlers, write_stats
from dovesei.shared.messages import CameraFrame, PromptSetMsg, SafetyHeatmap, replace
from dovesei.shared.zconfig import add_zenoh_args, zenoh_config_from_args

from .core import (
    BACKENDS, DEFAULT_MODEL, DTYPES, HEATMAP_DTYPES, REJECT_VEHICLE, FrameBackend, FrameRejected, SegmenterConfig, SegmenterCore,
    make_backend,
)
from .fusion import FUSION_MODES
from .prompts import REFERENCE_PROMPTS, PromptError, PromptSet

log = logging.getLogger(__name__)

SERVICE = "segmenter"
LOCKSTEP_FRAME_DEPTH = 64  # frames queued in lockstep; the sim waits on us, so a few suffice
QUERY_DEPTH = 16
IDLE_WAIT_S = 0.002  # longest idle sleep: frames and prompts wake the loop, queries are polled
REJECT_DECODE = "decode"  # payloads the codec refused (garbage, broken JPEG, wrong schema)


@dataclass(frozen=True)
class ServiceConfig:
    """Transport settings around a SegmenterConfig."""

    segmenter: SegmenterConfig = field(default_factory=SegmenterConfig)
    vehicle: str = "uav1"
    all_vehicles: bool = False  # serve every vehicle's camera key (a ground-station segmenter)
    lockstep: bool = False  # answer every frame in order instead of the newest one

    def __post_init__(self) -> None:
        keys.check_vehicle_id(self.vehicle)

    @property
    def key_vehicle(self) -> str:
        """The vehicle chunk of the subscribed keys: the vehicle id, or `*` for all vehicles."""
        return keys.ANY_VEHICLE if self.all_vehicles else self.vehicle


class SegmenterService:
    """The Zenoh side of the segmenter; `run(stop)` serves until `stop` is set, `close()` undeclares."""

    def __init__(self, session: zenoh.Session, config: ServiceConfig, core: SegmenterCore) -> None:
        self.session, self.config, self.core = session, config, core
        self.heatmaps_published = 0
        self.queries_answered = 0
        self.queries_refused = 0
        self.prompt_errors = 0
        self._publishers: dict[str, zenoh.Publisher] = {}
        vehicle = config.key_vehicle
        self.camera_key = keys.camera(vehicle)
        self.prompts_key = keys.prompts(vehicle)
        self.segment_key = keys.segment(keys.ANY_VEHICLE)
        # Frames and prompts wake the loop at once; queries are polled (see IDLE_WAIT_S).
        self.wakeup = threading.Event()
        self.frames = Inbox(session, self.camera_key, CameraFrame, newest_only=not config.lockstep,
                            depth=LOCKSTEP_FRAME_DEPTH, wakeup=self.wakeup)
        self.prompt_inbox = Inbox(session, self.prompts_key, PromptSetMsg, newest_only=False, wakeup=self.wakeup)
        self.queryable = session.declare_queryable(self.segment_key, zenoh.handlers.FifoChannel(QUERY_DEPTH))
        # Declared last: when the token is visible, every subscription above already exists.
        self.token = declare_alive(session, vehicle, SERVICE)

    # -- counters --------------------------------------------------------------------------------

    @property
    def rejected(self) -> Counter[str]:
        """Frames rejected by reason: the core's (size, no_truth, ...) plus "decode" for payloads
        the codec refused (garbage, broken JPEG; `stats()` details those by problem)."""
        total = Counter(self.core.rejected)
        if self.frames.rejected:
            total[REJECT_DECODE] += sum(self.frames.rejected.values())
        return total

    def stats(self) -> dict[str, object]:
        return {**self.core.stats(), "rejected": dict(self.rejected), "decode_problems": dict(self.frames.rejected),
                "heatmaps_published": self.heatmaps_published,
                "queries_answered": self.queries_answered, "queries_refused": self.queries_refused,
                "prompt_errors": self.prompt_errors}

    # -- the loop --------------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self.wakeup.clear()  # before polling: anything arriving after this sets it again
            # Prompts first so that a change reaches the very next frame; then one query and one
            # frame per turn, so neither stream can starve the other.
            busy = self._apply_prompts()
            busy = self._serve_one_query() or busy
            busy = self._serve_one_frame() or busy
            if not busy:
                self.wakeup.wait(IDLE_WAIT_S)

    def _apply_prompts(self) -> bool:
        busy = False
        while (msg := self.prompt_inbox.poll()) is not None:
            busy = True
            try:
                self.core.set_prompts(msg)
            except PromptError as exc:
                # The old set stays in force; an operator's typo must not stop the segmenter.
                self.prompt_errors += 1
                log.warning("prompt set refused, keeping %s: %s", self.core.prompts.set_id, exc)
        return busy

    def _serve_one_frame(self) -> bool:
        got = self.frames.poll_keyed()
        if got is None:
            return False
        recv_wall_s = self.frames.last_recv_wall_s  # transport latency only; nothing is decided on it
        frame, key = got
        try:
            vehicle = self._vehicle_of_key(key, frame)
            heatmap = self.core.process(frame)
        except FrameRejected as exc:
            log.warning("%s on %s", exc, key)
            return True
        self._publisher(vehicle).put(encode(self._stamped(heatmap, frame, recv_wall_s)))
        self.heatmaps_published += 1
        return True

    def _serve_one_query(self) -> bool:
        query = self.queryable.try_recv()
        if query is None:
            return False
        recv_wall_s = time.time()
        key = str(query.key_expr)
        try:
            if query.payload is None:
                self.core.count_rejected(REJECT_DECODE)
                raise FrameRejected(REJECT_DECODE, "a segment query must carry an encoded CameraFrame")
            try:
                frame = decode(query.payload.to_bytes(), CameraFrame, key=key)
            except ProtocolError as exc:
                self.core.count_rejected(REJECT_DECODE)
                raise FrameRejected(REJECT_DECODE, exc.problem) from None
            vehicle = self._vehicle_of_key(key, frame, wildcard_ok=True)
            heatmap = self.core.process(frame)
            query.reply(keys.segment(vehicle), encode(self._stamped(heatmap, frame, recv_wall_s)))
            self.queries_answered += 1
        except FrameRejected as exc:
            self.queries_refused += 1
            log.warning("segment query on %s refused: %s", key, exc)
            query.reply_err(str(exc))
        finally:
            # Finalises the query so the caller's get() completes without waiting for its timeout.
            query.drop()
        return True

    def _vehicle_of_key(self, key: str, frame: CameraFrame, wildcard_ok: bool = False) -> str:
        """The vehicle the key names; a frame claiming another vehicle is refused (and counted)."""
        try:
            if wildcard_ok and key.split("/")[1:2] == [keys.ANY_VEHICLE]:
                # A query on dovesei/*/segment names no vehicle: the frame does (and must be a key chunk).
                return keys.check_vehicle_id(frame.vehicle_id)
            vehicle = keys.vehicle_of(key)
        except ConfigError as exc:
            self.core.count_rejected(REJECT_VEHICLE)
            raise FrameRejected(REJECT_VEHICLE, str(exc)) from None
        if vehicle != frame.vehicle_id:
            self.core.count_rejected(REJECT_VEHICLE)
            raise FrameRejected(REJECT_VEHICLE, f"key {key!r} names vehicle {vehicle!r}, the frame says "
                                                f"{frame.vehicle_id!r} (seq {frame.seq})")
        return vehicle

    @staticmethod
    def _stamped(heatmap: SafetyHeatmap, frame: CameraFrame, recv_wall_s: float) -> SafetyHeatmap:
        """The heatmap with the transport figures (wall clock, measurement only) filled in."""
        # sent_wall_s == 0 means the sender did not stamp the frame: leave the latency at 0.
        to_segmenter_s = recv_wall_s - frame.sent_wall_s if frame.sent_wall_s > 0 else 0.0
        return replace(heatmap, frame_to_segmenter_s=to_segmenter_s, sent_wall_s=time.time())

    def _publisher(self, vehicle: str) -> zenoh.Publisher:
        # One declared publisher per vehicle seen: cheaper per put than session.put on a new key.
        pub = self._publishers.get(vehicle)
        if pub is None:
            # Lockstep: the controller waits for every heatmap, so a dropped one stalls the episode.
            flow = zenoh.CongestionControl.BLOCK if self.config.lockstep else zenoh.CongestionControl.DROP
            pub = self.session.declare_publisher(keys.heatmap(vehicle), congestion_control=flow)
            self._publishers[vehicle] = pub
        return pub

    def close(self) -> None:
        self.token.undeclare()
        self.queryable.undeclare()
        self.prompt_inbox.close()
        self.frames.close()
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()

    def __enter__(self) -> SegmenterService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run(session: zenoh.Session, *, config: ServiceConfig, stop: threading.Event,
        backend: FrameBackend | None = None) -> dict[str, object]:
    """Serve until `stop` is set; returns the final counters. Builds the backend when none is given."""
    core = SegmenterCore(backend if backend is not None else make_backend(config.segmenter), config.segmenter)
    with SegmenterService(session, config, core) as service:
        _log_start(service)
        service.run(stop)
        stats = service.stats()
    log.info("segmenter stopped: %s", stats)
    return stats


def _log_start(service: SegmenterService) -> None:
    backend, cfg = service.core.backend, service.config
    if backend.simulated:
        log.warning("SIMULATED perception: heatmaps come from the sim's ground truth, not from a model; "
                    "frames without truth (a real camera) are rejected (%s)", backend.reason)
    log.info("segmenter up: %s; backend chosen: %s", backend.describe(), backend.reason)
    log.info("segmenter keys: frames %s (%s), heatmaps %s, queryable %s, prompts %s, alive %s; heatmap dtype %s; "
             "prompt set %s", service.camera_key, "FIFO, lockstep" if cfg.lockstep else "newest wins",
             keys.heatmap(cfg.key_vehicle), service.segment_key, service.prompts_key,
             keys.alive(cfg.key_vehicle, SERVICE), cfg.segmenter.heatmap_dtype, service.core.prompts.set_id)


# --- command line -------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dovesei-segmenter",
                                description="Camera frames in, per-pixel safe-to-land probabilities out (Zenoh).")
    p.add_argument("--vehicle-id", dest="vehicle", default="uav1", help="vehicle id of the keys (default: uav1)")
    p.add_argument("--all-vehicles", action="store_true", help="serve every vehicle's camera key (ground station)")
    p.add_argument("--lockstep", action="store_true", help="answer every frame in order (lockstep benchmarks)")
    p.add_argument("--backend", choices=BACKENDS, default="auto",
                   help="auto: CLIPSeg, else simulated perception with a warning (default: auto)")
    p.add_argument("--model", default=DEFAULT_MODEL, help=f"CLIPSeg Hub id or local directory (default: {DEFAULT_MODEL})")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda:0 (default: cpu)")
    p.add_argument("--dtype", choices=DTYPES, default="float32")
    p.add_argument("--compile", action="store_true", help="torch.compile the fast path")
    p.add_argument("--threads", type=int, help="torch intra-op threads")
    p.add_argument("--fusion", choices=FUSION_MODES, default="grouped",
                   help="grouped (default, independent of the number of negatives) or dovesei (the reference)")
    p.add_argument("--fusion-temperature", type=float, default=1.0)
    p.add_argument("--sim-noise", type=float, default=1.0, help="simulated perception error scale, 0 = clean labels")
    p.add_argument("--sim-seed", type=int, default=0)
    p.add_argument("--heatmap-dtype", choices=HEATMAP_DTYPES, default="uint8")
    p.add_argument("--frame-size", metavar="WxH", help="accept only frames of this size, e.g. 352x352")
    p.add_argument("--max-side-px", type=int, default=4096, help="largest accepted frame side")
    p.add_argument("--prompts", type=Path, metavar="FILE",
                   help='JSON {"positive": [...], "negative": [...], "template": "... {} ..."} (default: the reference\'s)')
    p.add_argument("--stats-out", type=Path, metavar="FILE", help="write the run's counters as JSON at exit")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    add_zenoh_args(p)
    return p


def _frame_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        width_px, height_px = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--frame-size {text!r}: expected WIDTHxHEIGHT, e.g. 352x352") from None
    return height_px, width_px


def _load_prompts(path: Path | None) -> PromptSet:
    if path is None:
        return REFERENCE_PROMPTS
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"--prompts {str(path)!r}: cannot read a JSON object: {exc}") from None
    if not isinstance(data, dict) or set(data) - {"positive", "negative", "template"}:
        raise ConfigError(f"--prompts {str(path)!r}: expected an object with positive, negative and template")
    try:
        return PromptSet(positive=data.get("positive", ()), negative=data.get("negative", ()),
                         template=data.get("template", "{}"))
    except PromptError as exc:
        raise ConfigError(f"--prompts {str(path)!r}: {exc}") from None


def config_from_args(args: argparse.Namespace) -> ServiceConfig:
    seg = SegmenterConfig(
        backend=args.backend, model=args.model, device=args.device, dtype=args.dtype, compile=args.compile,
        threads=args.threads, fusion=args.fusion, fusion_temperature=args.fusion_temperature,
        sim_noise=args.sim_noise, sim_seed=args.sim_seed, heatmap_dtype=args.heatmap_dtype,
        max_side_px=args.max_side_px, expected_size_px=_frame_size(args.frame_size), prompts=_load_prompts(args.prompts),
    )
    return ServiceConfig(segmenter=seg, vehicle=args.vehicle, all_vehicles=args.all_vehicles, lockstep=args.lockstep)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = install_stop_handlers()
    try:
        config = config_from_args(args)
        zconf = zenoh_config_from_args(args)
        # Weights load before the session opens: a missing model fails fast, before any key is declared.
        backend = make_backend(config.segmenter)
    except (DoveseiError, ValueError) as exc:
        log.error("segmenter not started: %s", exc)
        return 2
    with zenoh.open(zconf) as session:
        stats = run(session, config=config, stop=stop, backend=backend)
    if args.stats_out is not None:
        write_stats(args.stats_out, stats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
