"""What `dovesei up` sees on Zenoh, as any operator would: the monitor session and its recorder.

    Zenoh callbacks --Sample (arrival stamped, bytes)--> queue --drain()--> Recorder.handle
        state, status, cmd, heatmap, camera (a subsample kept for the video), episode results
        (candidates: `dovesei.up.watch` accepts one only from the sim), liveliness of each service

The recorder keeps, per stream, the wall time of the newest arrival: the watcher reports a service
whose stream fell silent. It also derives the trajectory, labelled with the controller's state at
the nearest time, and the per-decision transport overhead.
"""

from __future__ import annotations

import bisect
import logging
import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import zenoh

from dovesei.shared import keys
from dovesei.shared.codec import decode
from dovesei.shared.errors import ProtocolError
from dovesei.shared.lifecycle import RateLimitedLog
from dovesei.shared.messages import (
    CameraFrame, ControllerStatus, CropFrame, CropHeatmap, EpisodeResult, SafetyHeatmap, VehicleState, VelocityCommand,
)

log = logging.getLogger("dovesei.up")

STAGES = ("frame_to_segmenter", "inference", "heatmap_to_controller", "policy", "command_to_sim")
MAX_VIDEO_FRAMES = 900
EARLY_SLOTS = 64  # heatmaps/statuses held for camera frames still on their way
PROGRESS_EVERY_S = 10.0  # sim seconds between progress lines (state changes are logged at once)
STATE_LOG_MIN_S = 1.0  # sim seconds: faster state changes are counted, not logged one by one
LIVELINESS = "alive"  # the Sample topic of a liveliness change (payload: the service name)
_TYPES = {"state": VehicleState, "status": ControllerStatus, "cmd": VelocityCommand, "heatmap": SafetyHeatmap,
          "camera": CameraFrame, "episode": EpisodeResult, "look": None}  # look: a CropFrame or a CropHeatmap
LOOKS_KEPT = 600  # close looks kept for the video (crop + scores each): ten minutes of 1 Hz looks


@dataclass(frozen=True)
class Sample:
    """One received payload, stamped on arrival in Zenoh's thread; decoded later by the Recorder."""

    topic: str
    recv_wall_s: float
    payload: bytes
    alive: bool = True  # liveliness samples only: False when the token was dropped


class Recorder:
    """What the monitor saw, decoded and kept for the report (one thread: the caller's)."""

    def __init__(self, start: tuple[float, float, float], video: bool, video_period_s: float = 0.25,
                 vehicle_id: str = "uav1") -> None:
        self.start = start
        self.video = video
        self.vehicle_id = vehicle_id
        self.states: list[VehicleState] = []
        self.statuses: dict[float, ControllerStatus] = {}  # by the state stamp they answer
        self.status_count = 0
        self.handover_seen = False  # the controller reported HANDOVER at least once
        self.steering_statuses = 0  # statuses outside the hand-over: each tick sent a command
        self.commands = 0
        self.latency: dict[str, list[float]] = {s: [] for s in STAGES}
        self.delivery_s: dict[str, list[float]] = {"camera": [], "heatmap": [], "cmd": [], "state": []}
        self.heatmap_delivery_by_seq: dict[int, float] = {}
        self.hm_to_ctrl_by_seq: dict[int, float] = {}  # the controller's own stamp per frame
        self.camera_delivery_by_seq: dict[int, float] = {}
        self.frame_to_seg_by_seq: dict[int, float] = {}
        self.cmd_delivery_by_frame: dict[int, float] = {}
        self.frames = 0
        self.heatmaps = 0
        self.rejected = 0
        self.backend: tuple[str, bool] | None = None
        self.result: EpisodeResult | None = None  # set by the watcher once it accepts a candidate
        self.result_candidates: list[tuple[EpisodeResult, float]] = []  # (result, arrival wall s)
        self.results_refused = 0  # candidates not accepted as the sim's (see dovesei.up.watch)
        self.foreign = 0  # messages on our keys naming another vehicle
        self.last_recv_wall_s: dict[str, float] = {}  # per topic: the newest valid arrival
        self.alive: dict[str, bool] = {}  # per service: its liveliness token is visible
        self.expect_exits = False  # set once the run is ending: a dropped token is then no news
        self.first_state_wall_s: float | None = None  # wall clock at the monitor: the episode's duration
        # Vehicle clock at which the mission began (after a --takeoff climb): earlier states are the
        # climb, recorded but not part of the mission's trajectory. None: from the first state.
        self.mission_start_t_s: float | None = None
        self.result_wall_s: float | None = None
        self.last_state_name, self.last_watchdog = "", ""
        self.gnss_lost = False  # the newest status said GNSS is lost (a real autopilot)
        self.logged_state, self.logged_watchdog = "", ""
        self.unlogged_changes = 0
        self.last_progress_t_s = -math.inf
        # Video: frames kept every `video_period_s` of sim time; the period doubles when too many.
        self.video_period_s = video_period_s
        self._next_video_t_s = 0.0
        self.video_frames: dict[int, dict[str, Any]] = {}
        # The controller's close looks by request: {"crop": CropFrame, "heatmap": CropHeatmap}.
        self.looks: dict[int, dict[str, Any]] = {}
        # A heatmap or status can arrive before its (much larger) camera frame: held here by frame
        # seq until the frame comes, so the video does not lose them (bounded: the newest only).
        self._early: dict[int, dict[str, Any]] = {}
        self._last_camera_seq = -1
        self._latency_seen: set[int] = set()
        # A flood of garbage on a key (dovesei faults: ~400/s) logged one line per message.
        self._reject_log = RateLimitedLog(log, "monitor rejected messages")
        # Taps see every valid message of ours with its arrival time: the flight recording, the live view.
        self.taps: list[Any] = []

    def handle(self, s: Sample) -> None:
        if s.topic == LIVELINESS:
            service = s.payload.decode("utf-8", "replace")
            if self.alive.get(service) != s.alive:
                quiet = s.alive or self.expect_exits or self.result_candidates
                log.log(logging.INFO if quiet else logging.WARNING, "%s liveliness token %s", service,
                        "visible" if s.alive else "dropped")
            self.alive[service] = s.alive
            return
        try:
            msg = decode(s.payload, _TYPES[s.topic], key=s.topic)
        except ProtocolError as exc:
            self.rejected += 1
            self._reject_log.warn(s.topic, f"a {s.topic} message: {exc.problem}")
            return
        if getattr(msg, "vehicle_id", self.vehicle_id) != self.vehicle_id:
            self.foreign += 1  # on our key but about another vehicle: never ours to record
            return
        self.last_recv_wall_s[s.topic] = s.recv_wall_s
        for tap in self.taps:
            tap(msg, s.recv_wall_s)
        sent = getattr(msg, "sent_wall_s", 0.0)
        if sent > 0 and s.topic in self.delivery_s:
            self.delivery_s[s.topic].append(s.recv_wall_s - sent)
            if s.topic == "camera":
                self.camera_delivery_by_seq[msg.seq] = s.recv_wall_s - sent
        getattr(self, f"_on_{s.topic}")(msg, s)

    def _on_look(self, msg: Any, s: Sample) -> None:
        if not isinstance(msg, (CropFrame, CropHeatmap)):
            self.rejected += 1
            self._reject_log.warn("look", f"a look message of schema {msg.SCHEMA!r}")
            return
        if self.video:
            self.looks.setdefault(msg.request_seq, {})["crop" if isinstance(msg, CropFrame) else "heatmap"] = msg
            while len(self.looks) > LOOKS_KEPT:
                del self.looks[min(self.looks)]

    def _on_state(self, st: VehicleState, s: Sample) -> None:
        if self.first_state_wall_s is None:
            self.first_state_wall_s = s.recv_wall_s  # after a takeoff: the first state of the episode
        self.states.append(st)

    def _on_status(self, st: ControllerStatus, s: Sample) -> None:
        self.status_count += 1
        self.handover_seen = self.handover_seen or st.state == "HANDOVER"
        if st.state != "HANDOVER":
            self.steering_statuses += 1
        self.statuses[st.stamp.t_s] = st
        kept = self.video_frames.get(st.frame_seq)
        if kept is None and self.video and st.frame_seq >= 0:
            kept = self._early_slot(st.frame_seq)
        if kept is not None and "status" not in kept:
            kept["status"] = st  # the first decision taken with this frame's heatmap
        changed = st.state != self.last_state_name or st.watchdog != self.last_watchdog
        since_s = st.stamp.t_s - self.last_progress_t_s
        if changed and since_s < STATE_LOG_MIN_S:
            # The reference policy can flip state every tick (its AIMING/LANDING oscillation):
            # count the flips and say so once instead of flooding the log.
            self.unlogged_changes += 1
        elif changed or since_s >= PROGRESS_EVERY_S or (self.unlogged_changes and since_s >= STATE_LOG_MIN_S):
            state = st.state if st.state == self.logged_state else f"{self.logged_state or 'start'} -> {st.state}"
            watchdog = (st.watchdog if st.watchdog == self.logged_watchdog
                        else f"{self.logged_watchdog or 'start'} -> {st.watchdog}")
            flips = f"; {self.unlogged_changes} more changes since the last line" if self.unlogged_changes else ""
            log.info("t=%.2f s alt %.1f m: controller %s, watchdog %s%s", st.stamp.t_s, st.alt_agl_m, state,
                     watchdog, flips)
            self.logged_state, self.logged_watchdog, self.unlogged_changes = st.state, st.watchdog, 0
            self.last_progress_t_s = st.stamp.t_s
        self.last_state_name, self.last_watchdog = st.state, st.watchdog
        if st.gnss_lost != self.gnss_lost:
            # Said once per change, whatever the progress lines: the operator must see this one.
            log.warning("t=%.2f s alt %.1f m: %s", st.stamp.t_s, st.alt_agl_m,
                        st.nav_reason if st.gnss_lost else "GNSS back")
            self.gnss_lost = st.gnss_lost

    def _on_cmd(self, cmd: VelocityCommand, s: Sample) -> None:
        self.commands += 1
        if cmd.sent_wall_s > 0 and cmd.frame_seq >= 0:
            self.cmd_delivery_by_frame.setdefault(cmd.frame_seq, s.recv_wall_s - cmd.sent_wall_s)
        # A decision's latency rides on every command until the next one: count it once.
        if cmd.latency is not None and cmd.frame_seq not in self._latency_seen:
            self._latency_seen.add(cmd.frame_seq)
            lat = cmd.latency
            self.latency["heatmap_to_controller"].append(lat.heatmap_to_controller_s)
            self.hm_to_ctrl_by_seq[cmd.frame_seq] = lat.heatmap_to_controller_s
            self.latency["policy"].append(lat.policy_s)

    def _on_heatmap(self, hm: SafetyHeatmap, s: Sample) -> None:
        self.heatmaps += 1
        if self.backend is None:
            self.backend = (hm.backend, hm.simulated)
            log.info("perception: %s%s", hm.backend, " (SIMULATED: a test instrument, not a model)" if hm.simulated
                     else "")
        self.latency["frame_to_segmenter"].append(hm.frame_to_segmenter_s)
        self.latency["inference"].append(hm.inference_s)
        self.frame_to_seg_by_seq[hm.seq] = hm.frame_to_segmenter_s
        if hm.sent_wall_s > 0:
            self.heatmap_delivery_by_seq[hm.seq] = s.recv_wall_s - hm.sent_wall_s
        kept = self.video_frames.get(hm.seq)
        if kept is None and self.video:
            kept = self._early_slot(hm.seq)
        if kept is not None:
            kept["prob"] = (np.asarray(hm.prob_safe).copy(), hm.prob_safe.dtype == np.uint8)

    def _early_slot(self, seq: int) -> dict[str, Any] | None:
        """The holding slot of a frame not seen yet (None for one already passed over)."""
        if seq <= self._last_camera_seq:
            return None  # its frame came and was not kept for the video
        if seq not in self._early and len(self._early) >= EARLY_SLOTS:
            del self._early[min(self._early)]
        return self._early.setdefault(seq, {})

    def _on_camera(self, frame: CameraFrame, s: Sample) -> None:
        self.frames += 1
        self._last_camera_seq = max(self._last_camera_seq, frame.seq)
        early = self._early.pop(frame.seq, {})
        for seq in [q for q in self._early if q < frame.seq]:
            del self._early[seq]  # frames that never came (dropped on the way)
        if not self.video or frame.stamp.t_s + 1e-9 < self._next_video_t_s:
            return
        self._next_video_t_s = frame.stamp.t_s + self.video_period_s
        # Kept as JPEG: a 1200 s episode keeps up to MAX_VIDEO_FRAMES frames, ~40 kB each instead of 370 kB.
        bgr = cv2.cvtColor(frame.image_rgb, cv2.COLOR_RGB2BGR)
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 85])
        if ok:
            self.video_frames[frame.seq] = {**early, "t_s": frame.stamp.t_s, "alt": frame.alt_agl_m, "jpeg": jpeg,
                                            "hfov": frame.hfov_rad}  # sizes a map policy's spot circle
        if len(self.video_frames) > MAX_VIDEO_FRAMES:
            # Long episode: keep every other frame and halve the rate from now on (bounded memory).
            for seq in sorted(self.video_frames)[1::2]:
                del self.video_frames[seq]
            self.video_period_s *= 2.0

    def _on_episode(self, result: EpisodeResult, s: Sample) -> None:
        # Only a candidate: anyone can put on the episode key, the watcher decides whether it is the sim's.
        self.result_candidates.append((result, s.recv_wall_s))
        log.info("episode result received: %s after %.1f s of sim time (%s)", result.outcome, result.sim_time_s,
                 result.detail)

    def accept_result(self, result: EpisodeResult, recv_wall_s: float) -> None:
        self.result, self.result_wall_s = result, recv_wall_s

    # -- derived --------------------------------------------------------------------------------

    def trajectory(self) -> dict[str, list]:
        """Per state of the mission: time, world position (start + local NED), altitude, the controller's state.

        States before `mission_start_t_s` (a --takeoff climb from the ground) are left out: the
        mission, its plot and its path length start at the start altitude.
        Each state takes the status stamped nearest to it, within half the slower stream's period
        (a real autopilot's states and the controller's 20 Hz ticks never share stamps, and
        exact matching left the labels one lag behind); with none that close the last label holds.
        """
        x0, y0, _ = self.start
        rows: dict[str, list] = {"t_s": [], "x_m": [], "y_m": [], "alt_m": [], "state": [], "watchdog": [],
                                 "cmd_down_m_s": [], "look": []}
        start_t_s = self.mission_start_t_s
        states = [st for st in self.states if start_t_s is None or st.stamp.t_s >= start_t_s]
        status_t = sorted(self.statuses)
        state_t = [st.stamp.t_s for st in states]
        tol_s = 0.5 * max(_median_step(state_t), _median_step(status_t)) + 1e-9
        name, watchdog, down_m_s, look = "INIT", "hold", 0.0, ""
        for st in states:
            status = _nearest(self.statuses, status_t, st.stamp.t_s, tol_s)
            if status is not None:
                name, watchdog, down_m_s = status.state, status.watchdog, status.vel_body_frd_m_s[2]
                look = status.look_verdict
            north_m, east_m, _down_m = st.pos_local_ned_m
            rows["t_s"].append(st.stamp.t_s)
            rows["x_m"].append(x0 + east_m)
            rows["y_m"].append(y0 + north_m)
            rows["alt_m"].append(st.alt_agl_m)
            rows["state"].append(name)
            rows["watchdog"].append(watchdog)
            rows["cmd_down_m_s"].append(down_m_s)  # what the controller commanded at this tick
            rows["look"].append(look)  # the policy's last close look's verdict ("" before any)
        return rows

    def transport_overhead_s(self, command_to_sim_s: dict[int, float] | None, lockstep: bool) -> list[float]:
        """Per decision: frame->segmenter + heatmap->controller + command->sim, wall seconds.

        Everything between a frame's publication and its command's arrival except inference,
        policy and the lockstep protocol's deliberate waits (a heatmap is held until it is due).
        Each hop is the receiving service's own stamp. In real time the controller takes a
        heatmap at its next 20 Hz tick, a wait that is the loop's, not transport: that hop is
        then the monitor's delivery time instead.
        """
        cmd_hops = command_to_sim_s if command_to_sim_s else self.cmd_delivery_by_frame
        hm_hops = self.hm_to_ctrl_by_seq if lockstep else self.heatmap_delivery_by_seq
        return self._chain(self.frame_to_seg_by_seq, hm_hops, cmd_hops)

    def zenoh_delivery_overhead_s(self) -> list[float]:
        """The same three hops as Zenoh delivers them (arrival stamped in the monitor's callbacks)."""
        return self._chain(self.camera_delivery_by_seq, self.heatmap_delivery_by_seq, self.cmd_delivery_by_frame)

    @staticmethod
    def _chain(first: dict[int, float], middle: dict[int, float], last: dict[int, float]) -> list[float]:
        out = []
        for seq, first_s in first.items():
            hm_s, last_s = middle.get(seq), last.get(seq)
            if hm_s is not None and last_s is not None:
                out.append(first_s + hm_s + last_s)
        return out


def _median_step(times: list[float]) -> float:
    steps = np.diff(np.asarray(times, dtype=np.float64))
    steps = steps[steps > 0]
    return float(np.median(steps)) if steps.size else 0.0


def _nearest(by_t: dict[float, Any], sorted_t: list[float], t_s: float, tol_s: float) -> Any:
    """The value whose time key is nearest `t_s` (ties: the earlier), None if none within `tol_s`."""
    i = bisect.bisect_left(sorted_t, t_s)
    best = None
    for j in (i - 1, i):
        if 0 <= j < len(sorted_t) and abs(sorted_t[j] - t_s) <= tol_s:
            if best is None or abs(sorted_t[j] - t_s) < abs(best - t_s):
                best = sorted_t[j]
    return by_t[best] if best is not None else None


class Monitor:
    """`up`'s own Zenoh session: callbacks only stamp arrival and queue; `drain()` decodes."""

    TOPICS = ("state", "status", "cmd", "heatmap", "camera", "episode", "look")

    def __init__(self, session: Any, vehicle_id: str, recorder: Recorder, with_camera: bool) -> None:
        self.recorder = recorder
        self._queue: deque[Sample] = deque()  # deque.append/popleft are atomic: no lock needed
        # Per topic, the newest arrival (wall s), queued or not: while the queue runs behind (an
        # overloaded host, where recording is the slow part) a silence is judged on these.
        self.arrived: dict[str, float] = {}
        self._subs = []
        for topic in self.TOPICS:
            if topic == "camera" and not with_camera:
                continue
            key = getattr(keys, topic)(vehicle_id)
            self._subs.append(session.declare_subscriber(key, self._callback(topic)))
        # history=True: tokens declared before this subscriber are reported too.
        self._subs.append(session.liveliness().declare_subscriber(keys.alive(vehicle_id, "*"), self._on_token,
                                                                  history=True))

    def _on_token(self, sample: Any) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        self._queue.append(Sample(LIVELINESS, time.time(), service.encode(), sample.kind == zenoh.SampleKind.PUT))

    def _callback(self, topic: str):
        queue, arrived = self._queue, self.arrived

        def on_sample(sample: Any) -> None:
            # Arrival stamped here, in Zenoh's thread: it is the transport measurement.
            now = time.time()
            arrived[topic] = now  # before the queue: a recorded arrival is never newer than this
            queue.append(Sample(topic, now, sample.payload.to_bytes()))

        return on_sample

    def drain(self, max_items: int = 10_000, max_s: float = math.inf) -> int:
        """Hand queued messages to the recorder, oldest first: all of them, or `max_items`, or as
        many as `max_s` of work allows (a watch loop's slice: its stop and failure checks run
        between slices; a lockstep backlog under load once kept a Ctrl-C waiting 24 s)."""
        n = 0
        deadline = time.monotonic() + max_s
        while self._queue and n < max_items:
            self.recorder.handle(self._queue.popleft())
            n += 1
            if n % 32 == 0 and time.monotonic() > deadline:
                break
        return n

    @property
    def backlog(self) -> int:
        """Messages received but not yet handed to the recorder."""
        return len(self._queue)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()
