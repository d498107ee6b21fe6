"""The segmenter as a Zenoh service (entry point `dovesei-segmenter`).

    dovesei/<vehicle>/camera   CameraFrame  --subscriber (newest wins; FIFO in --lockstep)--+
    dovesei/*/segment          CameraFrame  --queryable (request-reply)---------------------+--> SegmenterCore
                               CropFrame (a close look: landing + never prompts) ----------+
    dovesei/<vehicle>/prompts  PromptSetMsg --subscriber (FIFO: every change applied once)--+
                                                                                            |
    dovesei/<vehicle>/heatmap  SafetyHeatmap <--publisher (streamed frames) <---------------+
    query reply                SafetyHeatmap (CropHeatmap for a crop), or an error reply naming the reason
    dovesei/<vehicle>/alive/segmenter  liveliness token

One loop thread does all the work (CLIPSeg is not thread-safe and a second inference thread
would only compete for the same cores): Zenoh callbacks just fill channels, and the loop takes,
in turn, every pending prompt change, one query and one frame. With `--all-vehicles` the keys use
the `*` chunk and the vehicle id of the sample's key says whose frame it is. In real-time mode
every vehicle has its own newest-frame slot (`fair.FairSlots`): the loop moves every validated
frame into its vehicle's slot (a newer one supersedes the waiting one) and serves the slots
round-robin, so a slow model always works on a newest frame, never builds a backlog, and no
vehicle can starve another; per-vehicle offered/served/superseded counts go into the stats, and
an overload (frames superseded, or a long wait) is logged at WARNING at most every 10 s. In
lockstep mode every frame is answered in order, because the controller waits for the heatmap of
a named frame.

At start `build_backend` turns a CLIPSeg backend into the variant `--variant` names, or with
`auto` into the fastest one this host runs that decides like fp32 (`picker.py`), and logs why.

Bad input never stops the service: undecodable payloads (garbage, broken JPEG) are counted by
the inbox, frames the core refuses (size, no ground truth for the simulated backend, key naming
another vehicle) are counted by reason; each is logged at WARNING with the reason.
"""

from __future__ import annotations

import json
import logging
import threading
import time
import typing
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import zenoh

from dovesei.shared import keys, validate
from dovesei.shared.cliconfig import (
    CommandLine, Flag, in_range, integer_at_least, json_or_file, non_blank,
)
from dovesei.shared.codec import decode, encode
from dovesei.shared.errors import ConfigError, DoveseiError, ProtocolError
from dovesei.shared.lifecycle import (
    Inbox, RateLimitedLog, declare_alive, exit_process, install_stop_handlers, write_stats,
)
from dovesei.shared.messages import CameraFrame, CropFrame, PromptSetMsg, SafetyHeatmap, replace
from dovesei.shared.zconfig import SessionError, open_session

from .core import (
    BACKENDS, DTYPES, HEATMAP_DTYPES, REJECT_VEHICLE, BackendUnavailableError, ClipSegFrameBackend, FrameBackend,
    FrameRejected, SegmenterConfig, SegmenterCore, make_backend,
)
from .fair import OVERLOAD_REPORT_INTERVAL_S, FairSlots
from .fusion import FUSION_MODES
from .options import CLIPSEG_VARIANTS
from .prompts import PromptError, PromptSet, never_prompts
from .simulated import PROFILE_NAMES

log = logging.getLogger(__name__)

SERVICE = "segmenter"
LOCKSTEP_FRAME_DEPTH = 64  # frames queued in lockstep; the sim waits on us, so a few suffice
# Real time: validated frames waiting to be moved into their vehicle's slot. The loop empties it
# every turn (between two inferences), so it only has to hold what arrives during one inference.
REALTIME_FRAME_DEPTH = 256
QUERY_DEPTH = 16
IDLE_WAIT_S = 0.002  # longest idle sleep: frames and prompts wake the loop, queries are polled
REJECT_DECODE = "decode"  # payloads the codec refused (garbage, broken JPEG, wrong schema)
REJECT_TOO_MANY_VEHICLES = "too_many_vehicles"  # beyond fair.MAX_VEHICLES distinct vehicle ids


@dataclass(frozen=True)
class ServiceConfig:
    """Transport settings around a SegmenterConfig."""

    segmenter: SegmenterConfig = field(default_factory=SegmenterConfig)
    vehicle_id: str = "uav1"
    all_vehicles: bool = False  # serve every vehicle's camera key (a ground-station segmenter)
    lockstep: bool = False  # answer every frame in order instead of the newest one
    overload_report_s: float = OVERLOAD_REPORT_INTERVAL_S  # shortest interval between overload warnings
    # CLIPSeg only: `auto` times the variants this host can run and keeps the fastest passing the gate.
    variant: str = "auto"

    def __post_init__(self) -> None:
        keys.check_vehicle_id(self.vehicle_id)
        validate.positive("ServiceConfig.overload_report_s", self.overload_report_s)
        if self.variant not in CLIPSEG_VARIANTS:
            raise ConfigError(f"ServiceConfig.variant: {self.variant!r} is not one of {CLIPSEG_VARIANTS}")

    @property
    def key_vehicle(self) -> str:
        """The vehicle chunk of the subscribed keys: the vehicle id, or `*` for all vehicles."""
        return keys.ANY_VEHICLE if self.all_vehicles else self.vehicle_id


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
        # FIFO in both modes: in real time the loop itself keeps the newest frame per vehicle (one
        # shared newest-only slot let one vehicle's frames starve another's).
        self.frames = Inbox(session, self.camera_key, CameraFrame, newest_only=False,
                            depth=LOCKSTEP_FRAME_DEPTH if config.lockstep else REALTIME_FRAME_DEPTH,
                            wakeup=self.wakeup)
        self.slots: FairSlots[tuple[CameraFrame, str, float]] = FairSlots(report_interval_s=config.overload_report_s)
        self._vehicle_log = RateLimitedLog(log, "segmenter")
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
                "prompt_errors": self.prompt_errors, "vehicles": self.slots.stats()}

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

    def _collect_frames(self) -> bool:
        """Move every validated frame into its vehicle's slot; True when any arrived."""
        got_any = False
        while (got := self.frames.poll_keyed()) is not None:
            got_any = True
            frame, key = got
            recv_wall_s = self.frames.last_recv_wall_s  # transport latency only; nothing is decided on it
            try:
                vehicle = self._vehicle_of_key(key, frame)
            except FrameRejected as exc:
                log.warning("%s on %s", exc, key)
                continue
            if not self.slots.offer(vehicle, (frame, key, recv_wall_s), time.monotonic()):
                self.core.count_rejected(REJECT_TOO_MANY_VEHICLES)
                self._vehicle_log.warn(REJECT_TOO_MANY_VEHICLES, f"frame of {vehicle!r} refused: already serving "
                                                                 f"{self.slots.max_vehicles} vehicles")
                continue
            if self.config.lockstep:
                break  # lockstep: one frame at a time, in arrival order (the FIFO keeps the rest)
        return got_any

    def _serve_one_frame(self) -> bool:
        busy = self._collect_frames()
        report = self.slots.overload_report(time.monotonic())
        if report is not None:
            log.warning("%s", report)
        taken = self.slots.take()
        if taken is None:
            return busy
        vehicle, (frame, key, recv_wall_s) = taken
        try:
            heatmap = self.core.process(frame)
        except FrameRejected as exc:
            log.warning("%s on %s", exc, key)
            return True
        self._publisher(vehicle).put(encode(self._stamped(heatmap, frame, recv_wall_s)))
        self.heatmaps_published += 1
        log.debug("heatmap %s/%d published", vehicle, frame.seq)
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
                frame = decode(query.payload.to_bytes(), key=key)
                if not isinstance(frame, (CameraFrame, CropFrame)):
                    raise ProtocolError(key, f"a segment query carries a CameraFrame or a CropFrame, "
                                             f"got {frame.SCHEMA!r}")
            except ProtocolError as exc:
                self.core.count_rejected(REJECT_DECODE)
                raise FrameRejected(REJECT_DECODE, exc.problem) from None
            vehicle = self._vehicle_of_key(key, frame, wildcard_ok=True)
            if isinstance(frame, CropFrame):
                # A close look: scored with the landing prompts and the never set.
                query.reply(keys.segment(vehicle), encode(replace(self.core.process_crop(frame), sent_wall_s=time.time())))
            else:
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
    core = SegmenterCore(backend if backend is not None else build_backend(config), config.segmenter)
    with SegmenterService(session, config, core) as service:
        _log_start(service)
        service.run(stop)
        stats = service.stats()
    log.info("segmenter stopped: %s", stats)
    return stats


def build_backend(config: ServiceConfig) -> FrameBackend:
    """The configured backend; for CLIPSeg, in the variant `config.variant` names or the picker picks."""
    backend = make_backend(config.segmenter)
    if not isinstance(backend, ClipSegFrameBackend):
        return backend
    # lazy: the picker imports torch, which only a CLIPSeg backend has (and has loaded by now).
    from .backends import VariantUnavailable
    from .picker import choose

    try:
        model, pick = choose(backend.model, config.variant, config.segmenter.prompts,
                             config.segmenter.fusion_config, threads=config.segmenter.threads)
    except VariantUnavailable as exc:
        raise BackendUnavailableError(str(exc)) from None
    return ClipSegFrameBackend(model, f"{backend.reason}; {pick.describe()}")


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


def _parse_frame_size(text: str) -> tuple[int, int]:
    """'WIDTHxHEIGHT' -> (height_px, width_px), the order of SegmenterConfig.expected_size_px."""
    try:
        width_px, height_px = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError("expected WIDTHxHEIGHT, e.g. 352x352") from None
    if width_px < 1 or height_px < 1:
        raise ValueError("both sides must be >= 1 px")
    return height_px, width_px


def _render_frame_size(size_px: tuple[int, int]) -> str:
    height_px, width_px = size_px
    return f"{width_px}x{height_px}"


def _parse_prompts(text: str) -> PromptSet:
    """A JSON file, or the JSON object itself (what `to_argv` writes), describing a PromptSet."""
    data = json_or_file("--prompts", text)
    if not isinstance(data, dict) or set(data) - {"positive", "negative", "template"}:
        raise ValueError("expected an object with positive, negative and template")
    try:
        return PromptSet(positive=data.get("positive", ()), negative=data.get("negative", ()),
                         template=data.get("template", "{}"))
    except PromptError as exc:
        raise ValueError(str(exc)) from None


def _parse_never(text: str) -> tuple[str, ...]:
    """A JSON list of never prompts, or a file holding one."""
    data = json_or_file("--never-prompts", text)
    try:
        return never_prompts(data if isinstance(data, list) else "not a list")
    except PromptError as exc:
        raise ValueError(str(exc)) from None


def _render_never(never: tuple[str, ...]) -> str:
    return json.dumps(list(never), ensure_ascii=False)


def _render_prompts(prompts: PromptSet) -> str:
    return json.dumps({"positive": list(prompts.positive), "negative": list(prompts.negative),
                       "template": prompts.template}, ensure_ascii=False)


# The one table of the segmenter's flags: `build_parser`, `config_from_args` and `to_argv` read it.
CLI = CommandLine(ServiceConfig, {
    "vehicle_id": Flag("--vehicle-id", "vehicle id of the keys", check=lambda _w, v: keys.check_vehicle_id(v)),
    "all_vehicles": Flag("--all-vehicles", "serve every vehicle's camera key (ground station)"),
    "lockstep": Flag("--lockstep", "answer every frame in order (lockstep benchmarks)"),
    "variant": Flag("--variant", "CLIPSeg variant: auto = time those this host can run (fp32, bf16 with native "
                    "BF16, onnx-int8 with the onnx extra once exported, cuda-fp16 with a GPU) and keep the fastest "
                    "passing the decision gate; a name pins one (onnx-int8 exports itself once)",
                    choices=CLIPSEG_VARIANTS),
    "overload_report_s": Flag("--overload-report-s", "shortest interval between overload warnings (vehicles "
                              "offering more frames than are served)", check=validate.positive),
    "segmenter.backend": Flag("--backend", "auto: CLIPSeg, else simulated perception with a warning",
                              choices=BACKENDS),
    "segmenter.model": Flag("--model", "CLIPSeg Hub id or local directory", check=non_blank),
    "segmenter.device": Flag("--device", "torch device, e.g. cpu or cuda:0", check=non_blank),
    "segmenter.dtype": Flag("--dtype", "torch dtype of the model", choices=DTYPES),
    "segmenter.compile": Flag("--compile", "torch.compile the fast path"),
    "segmenter.threads": Flag("--threads", "torch intra-op threads (default: torch's)", check=integer_at_least(1)),
    "segmenter.fusion": Flag("--fusion", "grouped (independent of the number of negatives) or dovesei "
                             "(the reference)", choices=FUSION_MODES),
    "segmenter.fusion_temperature": Flag("--fusion-temperature", "softmax temperature of the fusion",
                                         check=validate.positive),
    "segmenter.sim_profile": Flag("--perception", "simulated perception profile", choices=PROFILE_NAMES),
    "segmenter.sim_noise": Flag("--noise", "error scale within the simulated perception profile, 0 = no "
                                "misreadings (default 1, the calibrated one)", check=in_range(0.0, 4.0)),
    "segmenter.sim_seed": Flag("--sim-seed", "seed of the simulated perception", check=integer_at_least(0)),
    "segmenter.heatmap_dtype": Flag("--heatmap-dtype", "heatmap pixels on the wire", choices=HEATMAP_DTYPES),
    "segmenter.expected_size_px": Flag("--frame-size", "accept only frames of this size, e.g. 352x352",
                                       parse=_parse_frame_size, render=_render_frame_size, metavar="WxH"),
    "segmenter.max_side_px": Flag("--max-side-px", "largest accepted frame side", check=integer_at_least(1)),
    "segmenter.never": Flag("--never-prompts", 'JSON list (or a file holding it) of what a close look must never '
                            'land near, scored on crops (default: people, vehicles, bicycles, animals)',
                            parse=_parse_never, render=_render_never, metavar="FILE"),
    "segmenter.prompts": Flag("--prompts", 'JSON file (or the JSON itself) {"positive": [...], "negative": [...], '
                              '"template": "... {} ..."} (default: the reference\'s)', parse=_parse_prompts,
                              render=_render_prompts, metavar="FILE"),
}, prog="dovesei-segmenter", description="Camera frames in, per-pixel safe-to-land probabilities out (Zenoh).")


build_parser = CLI.build_parser
config_from_args = CLI.from_args
to_argv = CLI.to_argv  # what `dovesei up` passes to a child process; parses back to the same config


def main(argv: Sequence[str] | None = None) -> int:
    config, process, zconf = CLI.start(argv)  # a bad flag exits 2 with the usage line
    stop = install_stop_handlers()
    try:
        # Weights load before the session opens: a missing model fails fast, before any key is declared.
        backend = build_backend(config)
    except (DoveseiError, ValueError) as exc:
        log.error("segmenter not started: %s", exc)
        return 2
    try:
        with open_session(zconf) as session:
            stats = run(session, config=config, stop=stop, backend=backend)
    except SessionError as exc:  # a taken listen port, an unreachable router: one line, not a traceback
        log.error("segmenter not started: %s", exc)
        return 1
    if process.stats_out is not None:
        write_stats(process.stats_out, stats)
    return 0


def cli() -> typing.NoReturn:
    """The process entry (`dovesei-segmenter`, `python -m`): `main`, then out without the teardown.

    Once torch and transformers are imported (CLIPSeg, or `auto` trying it) the interpreter's own
    teardown took 2-5 s after `main` returned; `main` has closed the session and written the stats
    by then, so the process ends at once (`exit_process`) and a SIGTERM ends it promptly.
    """
    exit_process(main())


if __name__ == "__main__":
    cli()
