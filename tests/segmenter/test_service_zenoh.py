"""The segmenter service over real in-process Zenoh sessions on loopback (plus one subprocess run).

The service runs in a thread on one session; the test plays sim and operator on the other.
Every wait is a condition with a deadline; the only sleep is inside `SlowBackend`, where it stands
for a model's inference time so that a burst of frames outpaces the segmenter.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from dovesei.segmenter.core import FrameBackend, SegmenterConfig, SegmenterCore, make_backend
from dovesei.segmenter.fusion import FusionConfig
from dovesei.segmenter.prompts import REFERENCE_PROMPTS, PromptSet
from dovesei.segmenter.service import SegmenterService, ServiceConfig, run
from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.lifecycle import Inbox, is_alive, wait_until
from dovesei.shared.messages import CameraFrame, ClassEntry, GroundTruth, PromptSetMsg, SafetyHeatmap, Stamp
from dovesei.shared.zconfig import loopback_config

from tests.conftest import free_port

CLASSES = (ClassEntry(1, "grass", True), ClassEntry(2, "road", False))
SIM = SegmenterConfig(backend="sim", sim_noise=1.0)


def make_frame(seq: int, vehicle: str = "uav1", truth: bool = True, size_px: int = 64) -> CameraFrame:
    image = np.full((size_px, size_px, 3), 90, np.uint8)
    labels = np.full((size_px, size_px), 2, np.uint8)
    labels[:, : size_px // 2] = 1
    return CameraFrame(vehicle, seq, Stamp(0.05 * seq, "sim"), image, 1.274, 80.0, sent_wall_s=time.time(),
                       truth=GroundTruth(labels, CLASSES) if truth else None)


class SlowBackend:
    """The simulated backend plus a fixed inference time, like a real model on a slow host."""

    def __init__(self, inner: FrameBackend, delay_s: float) -> None:
        self.inner, self.delay_s = inner, delay_s
        self.name, self.simulated, self.fuses, self.reason = inner.name, inner.simulated, inner.fuses, "test"
        self.calls = 0

    def describe(self) -> str:
        return f"slow({self.inner.describe()})"

    def prepare(self, prompts: PromptSet) -> None:
        self.inner.prepare(prompts)

    def safe_probability(self, frame: CameraFrame, prompts: PromptSet, fusion: FusionConfig) -> np.ndarray:
        self.calls += 1
        time.sleep(self.delay_s)
        return self.inner.safe_probability(frame, prompts, fusion)


@contextmanager
def serving(session: zenoh.Session, config: ServiceConfig, backend: object | None = None) -> Iterator[SegmenterService]:
    """The service looping in a thread; stopped, joined and closed on exit."""
    core = SegmenterCore(backend if backend is not None else make_backend(config.segmenter), config.segmenter)
    service = SegmenterService(session, config, core)
    stop = threading.Event()
    thread = threading.Thread(target=service.run, args=(stop,), daemon=True)
    thread.start()
    try:
        yield service
    finally:
        stop.set()
        thread.join(5.0)
        service.close()
        assert not thread.is_alive(), "service loop did not stop"


def first_heatmap(client: zenoh.Session, inbox: Inbox, key: str, frame: CameraFrame, timeout_s: float = 10.0):
    """Publish `frame` until its heatmap comes back (the subscription may still be propagating)."""
    got: list[SafetyHeatmap] = []

    def attempt() -> bool:
        client.put(key, encode(frame))
        hm = inbox.recv(0.1)
        # Both ids: heatmaps of an earlier vehicle's repeated frames may still be arriving.
        if hm is not None and (hm.vehicle_id, hm.seq) == (frame.vehicle_id, frame.seq):
            got.append(hm)
        return bool(got)

    assert wait_until(attempt, timeout_s), f"no heatmap for frame {frame.seq} on {key}"
    return got[0]


def test_frame_in_heatmap_out_and_liveliness(zenoh_pair) -> None:
    server, client = zenoh_pair
    with Inbox(client, keys.heatmap("uav1"), SafetyHeatmap, newest_only=False) as heatmaps:
        with serving(server, ServiceConfig(segmenter=SIM)) as service:
            assert wait_until(lambda: is_alive(client, "uav1", "segmenter", 0.3), 5.0)
            frame = make_frame(seq=42)
            hm = first_heatmap(client, heatmaps, keys.camera("uav1"), frame)
            assert (hm.seq, hm.stamp, hm.vehicle_id) == (42, frame.stamp, "uav1")
            assert hm.prob_safe.shape == (64, 64) and hm.backend == "simulated" and hm.simulated
            assert hm.frame_to_segmenter_s >= 0.0 and hm.sent_wall_s >= frame.sent_wall_s
            # Counted by the service's thread just after its put: the heatmap can arrive first.
            assert wait_until(lambda: service.heatmaps_published >= 1, 5.0)
        # The token goes with the service.
        assert wait_until(lambda: not is_alive(client, "uav1", "segmenter", 0.3), 5.0)


def test_newest_frame_wins_under_a_burst(zenoh_pair) -> None:
    server, client = zenoh_pair
    slow = SlowBackend(make_backend(SIM), delay_s=0.02)
    with Inbox(client, keys.heatmap("uav1"), SafetyHeatmap, newest_only=False) as heatmaps:
        with serving(server, ServiceConfig(segmenter=SIM), slow):
            first_heatmap(client, heatmaps, keys.camera("uav1"), make_frame(seq=0))
            while heatmaps.poll() is not None:  # drop answers to repeated warm-up frames
                pass
            for seq in range(100, 150):
                client.put(keys.camera("uav1"), encode(make_frame(seq)))
            seqs: list[int] = []
            assert wait_until(lambda: (hm := heatmaps.poll()) is not None and seqs.append(hm.seq) is None
                              and hm.seq == 149, 10.0), f"last frame never answered; got {seqs}"
    # 50 frames arrived within far less than 50 x 20 ms: most were overwritten, never queued.
    assert len(seqs) <= 10 and seqs == sorted(seqs), seqs


def test_lockstep_answers_every_frame_in_order(zenoh_pair) -> None:
    server, client = zenoh_pair
    slow = SlowBackend(make_backend(SIM), delay_s=0.005)
    with Inbox(client, keys.heatmap("uav1"), SafetyHeatmap, newest_only=False) as heatmaps:
        with serving(server, ServiceConfig(segmenter=SIM, lockstep=True), slow):
            first_heatmap(client, heatmaps, keys.camera("uav1"), make_frame(seq=0))
            while heatmaps.poll() is not None:
                pass
            for seq in range(1, 21):
                # As the lockstep sim publishes (it blocks under congestion; Zenoh's default drops, and
                # under a loaded CI machine frames 5-20 of this burst were lost in transit).
                client.put(keys.camera("uav1"), encode(make_frame(seq)),
                           congestion_control=zenoh.CongestionControl.BLOCK)
            seqs: list[int] = []
            assert wait_until(lambda: (hm := heatmaps.poll()) is not None and seqs.append(hm.seq) is None
                              and hm.seq == 20, 10.0), seqs
    # Answers to repeated warm-up frames (seq 0) may trail in; every real frame is answered in order.
    assert [s for s in seqs if s > 0] == list(range(1, 21))


def test_queryable_round_trip_and_error_replies(zenoh_pair) -> None:
    server, client = zenoh_pair

    def ask(key: str, payload: bytes) -> list[zenoh.Reply]:
        return list(client.get(key, payload=payload, timeout=2.0))

    with serving(server, ServiceConfig(segmenter=SIM, vehicle_id="base")) as service:
        frame = make_frame(seq=9, vehicle="uav3")
        replies: list[zenoh.Reply] = []
        # Any vehicle may ask, whatever the service's own vehicle id; retry while the queryable propagates.
        assert wait_until(lambda: bool(replies.extend(ask(keys.segment("uav3"), encode(frame))) or replies), 10.0)
        hm = decode(replies[0].ok.payload.to_bytes(), SafetyHeatmap)
        assert (hm.seq, hm.vehicle_id, hm.prob_safe.shape) == (9, "uav3", (64, 64))
        assert str(replies[0].ok.key_expr) == keys.segment("uav3")
        # A query on the wildcard key names no vehicle: the frame's vehicle id answers.
        (reply,) = ask(keys.segment(keys.ANY_VEHICLE), encode(make_frame(10, vehicle="uav9")))
        assert str(reply.ok.key_expr) == keys.segment("uav9")

        for key, payload, reason in ((keys.segment("uav3"), b"\x00garbage", "decode"),
                                     (keys.segment("uav3"), encode(make_frame(1, "uav3", truth=False)), "no_truth"),
                                     (keys.segment("uav4"), encode(frame), "vehicle_mismatch")):
            (reply,) = ask(key, payload)
            assert reply.err is not None, reason
            assert reason in reply.err.payload.to_string()
        assert service.queries_answered == 2 and service.queries_refused == 3
        assert service.rejected == {"decode": 1, "no_truth": 1, "vehicle_mismatch": 1}


def test_bad_frames_are_counted_and_the_service_keeps_serving(zenoh_pair) -> None:
    server, client = zenoh_pair
    key = keys.camera("uav1")
    body = msgpack.unpackb(encode(make_frame(5), jpeg_quality=80))
    body["image_rgb"] = {"jpeg": b"\xff\xd8 not really a jpeg"}
    broken_jpeg = msgpack.packb(body, use_bin_type=True)
    with Inbox(client, keys.heatmap("uav1"), SafetyHeatmap, newest_only=False) as heatmaps:
        with serving(server, ServiceConfig(segmenter=SIM)) as service:
            first_heatmap(client, heatmaps, key, make_frame(seq=1))
            # One bad payload at a time: the newest-wins ring would let a later one overwrite it.
            bad = ((b"\x00garbage", "decode", 1),
                   (broken_jpeg, "decode", 2),
                   (encode(make_frame(6, truth=False)), "no_truth", 1),
                   (encode(make_frame(7, size_px=4)), "size", 1),
                   (encode(make_frame(8, vehicle="uav2")), "vehicle_mismatch", 1))
            for payload, reason, count in bad:
                client.put(key, payload)
                assert wait_until(lambda: service.rejected[reason] == count, 5.0), (reason, service.rejected)
            hm = first_heatmap(client, heatmaps, key, make_frame(seq=2))
            assert hm.seq == 2
            assert sum(service.rejected.values()) == len(bad)
            problems = " | ".join(service.stats()["decode_problems"])
            assert "not a msgpack payload" in problems and "image_rgb" in problems


def test_prompt_change_over_zenoh_changes_later_heatmaps(zenoh_pair) -> None:
    server, client = zenoh_pair
    msg = PromptSetMsg(Stamp(0.0, "wall"), ("lawn", "meadow"), ("roof", "car"), "aerial photo of {}")
    new_id = PromptSet(msg.positive, msg.negative, msg.template).set_id
    bad = PromptSetMsg(Stamp(0.0, "wall"), ("lawn {0}",), ("roof",), "{}")
    with Inbox(client, keys.heatmap("uav1"), SafetyHeatmap, newest_only=False) as heatmaps:
        with serving(server, ServiceConfig(segmenter=SIM)) as service:
            hm = first_heatmap(client, heatmaps, keys.camera("uav1"), make_frame(seq=1))
            assert hm.prompt_set_id == REFERENCE_PROMPTS.set_id
            assert wait_until(lambda: (client.put(keys.prompts("uav1"), encode(msg)),
                                       service.core.prompts.set_id == new_id)[1], 5.0, poll_s=0.05)
            assert first_heatmap(client, heatmaps, keys.camera("uav1"), make_frame(seq=2)).prompt_set_id == new_id
            # A set the segmenter cannot use is refused; the current one stays in force.
            client.put(keys.prompts("uav1"), encode(bad))
            assert wait_until(lambda: service.prompt_errors == 1, 5.0)
            assert service.core.prompts.set_id == new_id and service.core.prompt_changes == 1


def test_all_vehicles_answers_on_the_key_of_the_frame(zenoh_pair) -> None:
    server, client = zenoh_pair
    with Inbox(client, keys.heatmap(keys.ANY_VEHICLE), SafetyHeatmap, newest_only=False) as heatmaps:
        with serving(server, ServiceConfig(segmenter=SIM, all_vehicles=True)):
            assert wait_until(lambda: is_alive(client, "uav7", "segmenter", 0.3), 5.0)
            for vehicle in ("uav7", "uav8"):
                hm = first_heatmap(client, heatmaps, keys.camera(vehicle), make_frame(seq=3, vehicle=vehicle))
                assert hm.vehicle_id == vehicle


def test_run_stops_cleanly_and_returns_its_counters(zenoh_pair) -> None:
    server, client = zenoh_pair
    stop = threading.Event()
    result: list[dict] = []
    thread = threading.Thread(target=lambda: result.append(run(server, config=ServiceConfig(segmenter=SIM), stop=stop)))
    thread.start()
    try:
        assert wait_until(lambda: is_alive(client, "uav1", "segmenter", 0.3), 10.0)
        with Inbox(client, keys.heatmap("uav1"), SafetyHeatmap, newest_only=False) as heatmaps:
            first_heatmap(client, heatmaps, keys.camera("uav1"), make_frame(seq=4))
    finally:
        stop.set()
        thread.join(5.0)
    assert not thread.is_alive()
    assert result[0]["processed"] >= 1 and result[0]["backend"] == "simulated"
    assert wait_until(lambda: not is_alive(client, "uav1", "segmenter", 0.3), 5.0)


@pytest.mark.slow
def test_entry_point_serves_and_exits_zero_on_sigterm() -> None:
    port = free_port()
    cmd = [sys.executable, "-m", "dovesei.segmenter.service", "--backend", "sim", "--vehicle-id", "uav5",
           "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", "--log-level", "WARNING"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "HF_HUB_OFFLINE": "1"}, cwd=Path(__file__).parent)
    try:
        with zenoh.open(loopback_config(connect_ports=[port])) as client:
            assert wait_until(lambda: proc.poll() is not None or is_alive(client, "uav5", "segmenter", 0.3), 20.0)
            assert proc.poll() is None, proc.communicate()[1]
            with Inbox(client, keys.heatmap("uav5"), SafetyHeatmap, newest_only=False) as heatmaps:
                assert first_heatmap(client, heatmaps, keys.camera("uav5"), make_frame(1, "uav5")).seq == 1
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, stderr
    assert "SIMULATED perception" in stderr  # said loudly, even at --log-level WARNING
