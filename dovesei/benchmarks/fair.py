"""The fairness figure of ``dovesei bench-segmenter``: many vehicles sharing one segmenter.

Four vehicles' cameras ask 2 Hz each (8 Hz offered) from one ground-station segmenter that
serves about 3 Hz in total; each vehicle should get 25 % +/- 5 % of the served frames, and the
overload should be reported with per-vehicle rates, never a silent starvation.

It runs the real service (``SegmenterService`` with ``all_vehicles``, its per-vehicle slots of
``fair.py``) over two in-process Zenoh sessions on loopback. The backend is the simulated
perception plus a fixed sleep that stands for the model's inference time (``serve_hz``), so
the figure is about scheduling, not about this host's model speed; the vehicles' cameras tick
together at ``rate_hz`` in the same order each tick, the order in which one shared newest-frame
slot starved a vehicle (measured before the per-vehicle slots: 0 heatmaps in 40 s for one of four).
Counting starts at the first heatmap of the last vehicle to appear (the subscriptions propagate).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from dovesei.segmenter.core import SegmenterConfig, SegmenterCore, make_backend
from dovesei.segmenter.service import SegmenterService, ServiceConfig
from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.lifecycle import Inbox, is_alive, wait_until
from dovesei.shared.messages import CameraFrame, ClassEntry, GroundTruth, SafetyHeatmap, Stamp
from dovesei.shared.zconfig import free_port, loopback_config

LOG = logging.getLogger(__name__)

TARGET_SHARE_TOLERANCE = 0.05  # each vehicle's share within 1/N +/- this
FRAME_PX = 64  # small frames: the figure is about scheduling, not image size
_CLASSES = (ClassEntry(1, "grass", True), ClassEntry(2, "road", False))


class _TimedBackend:
    """The simulated perception plus a fixed inference time (stands for a model serving `serve_hz`)."""

    def __init__(self, inner, delay_s: float) -> None:
        self.inner, self.delay_s = inner, delay_s
        self.name, self.simulated, self.fuses = inner.name, inner.simulated, inner.fuses
        self.reason = f"simulated perception + {delay_s:.3f} s per frame (fairness benchmark)"

    def describe(self) -> str:
        return f"timed({self.inner.describe()}, {self.delay_s:.3f} s)"

    def prepare(self, prompts) -> None:
        self.inner.prepare(prompts)

    def safe_probability(self, frame, prompts, fusion) -> np.ndarray:
        time.sleep(self.delay_s)
        return self.inner.safe_probability(frame, prompts, fusion)


def _frame(vehicle: str, seq: int) -> CameraFrame:
    image = np.full((FRAME_PX, FRAME_PX, 3), 90, np.uint8)
    labels = np.full((FRAME_PX, FRAME_PX), 2, np.uint8)
    labels[:, : FRAME_PX // 2] = 1
    return CameraFrame(vehicle, seq, Stamp(0.05 * seq, "sim"), image, 1.274, 80.0, sent_wall_s=time.time(),
                       truth=GroundTruth(labels, _CLASSES))


@dataclass(frozen=True)
class FairnessResult:
    vehicles: tuple[str, ...]
    rate_hz: float  # asked per vehicle
    serve_hz: float  # the stand-in model's rate
    counted_s: float
    served: dict[str, int]  # heatmaps received per vehicle in the counted window
    service_counts: dict[str, dict[str, int]]  # the service's own offered/served/superseded
    overload_warnings: tuple[str, ...]  # the service's overload reports at WARNING

    @property
    def shares(self) -> dict[str, float]:
        total = sum(self.served.values())
        return {v: (n / total if total else 0.0) for v, n in self.served.items()}

    @property
    def passed(self) -> bool:
        expected = 1.0 / len(self.vehicles)
        return sum(self.served.values()) > 0 and all(
            abs(share - expected) <= TARGET_SHARE_TOLERANCE for share in self.shares.values())

    def as_dict(self) -> dict[str, object]:
        total = sum(self.served.values())
        return {
            "vehicles": len(self.vehicles), "asked_hz_per_vehicle": self.rate_hz, "model_hz": self.serve_hz,
            "counted_s": round(self.counted_s, 2), "served_hz_total": total / self.counted_s if self.counted_s else 0.0,
            "per_vehicle": {v: {"share": self.shares[v], "served_hz": self.served[v] / self.counted_s,
                                **self.service_counts.get(v, {})} for v in self.vehicles},
            "target_share": [1.0 / len(self.vehicles) - TARGET_SHARE_TOLERANCE,
                             1.0 / len(self.vehicles) + TARGET_SHARE_TOLERANCE],
            "overload_warnings": len(self.overload_warnings),
            "first_overload_warning": self.overload_warnings[0] if self.overload_warnings else None,
            "passed": self.passed,
        }


class _CountWarnings(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if "overload" in record.getMessage():
            self.messages.append(record.getMessage())


def measure_fairness(duration_s: float = 12.0, n_vehicles: int = 4, rate_hz: float = 2.0,
                     serve_hz: float = 3.0) -> FairnessResult:
    """Run the service with `n_vehicles` cameras at `rate_hz` each for `duration_s`; see the module docstring."""
    import zenoh

    vehicles = tuple(f"uav{i + 1}" for i in range(n_vehicles))
    sim = SegmenterConfig(backend="sim", sim_noise=1.0)
    config = ServiceConfig(segmenter=sim, all_vehicles=True, overload_report_s=2.0)
    warnings = _CountWarnings()
    service_logger = logging.getLogger("dovesei.segmenter.service")
    service_logger.addHandler(warnings)
    port = free_port()
    server = zenoh.open(loopback_config(listen_port=port))
    client = zenoh.open(loopback_config(connect_ports=[port]))
    try:
        if not wait_until(lambda: any(True for _ in server.info.peers_zid()), 10.0):
            raise RuntimeError("fairness benchmark: the two loopback Zenoh peers did not connect")
        core = SegmenterCore(_TimedBackend(make_backend(sim), 1.0 / serve_hz), sim)
        service = SegmenterService(server, config, core)
        stop_service, stop_cameras = threading.Event(), threading.Event()
        loop = threading.Thread(target=service.run, args=(stop_service,), daemon=True)
        publishers = []
        got: list[str] = []
        try:
            with Inbox(client, keys.heatmap(keys.ANY_VEHICLE), SafetyHeatmap, newest_only=False, depth=1024) as inbox:
                loop.start()
                if not wait_until(lambda: is_alive(client, vehicles[0], "segmenter", 0.3), 10.0):
                    raise RuntimeError("fairness benchmark: the segmenter's liveliness never appeared")
                publishers = [client.declare_publisher(keys.camera(v)) for v in vehicles]

                def cameras() -> None:
                    start_s, tick = time.monotonic(), 0
                    while not stop_cameras.is_set():
                        for index, pub in enumerate(publishers):
                            pub.put(encode(_frame(vehicles[index], tick * n_vehicles + index)))
                        tick += 1
                        stop_cameras.wait(max(0.0, start_s + tick / rate_hz - time.monotonic()))

                camera_thread = threading.Thread(target=cameras, daemon=True)
                camera_thread.start()
                arrivals_s: list[float] = []
                deadline_s = time.monotonic() + duration_s
                while time.monotonic() < deadline_s:
                    heatmap = inbox.recv(0.2)
                    if heatmap is not None:
                        got.append(heatmap.vehicle_id)
                        arrivals_s.append(time.monotonic())
                stop_cameras.set()
                camera_thread.join(5.0)
                counts = service.stats()["vehicles"]
        finally:
            stop_cameras.set()
            stop_service.set()
            loop.join(5.0)
            for pub in publishers:
                pub.undeclare()
            service.close()
    finally:
        service_logger.removeHandler(warnings)
        client.close()
        server.close()
    missing = [v for v in vehicles if v not in got]
    if missing:  # a starved vehicle: count everything, its share of 0 fails the figure
        LOG.warning("fairness benchmark: no heatmap at all for %s", missing)
    first = 0 if missing else max(got.index(v) for v in vehicles)
    counted = got[first:]
    counted_s = arrivals_s[-1] - arrivals_s[first] if len(counted) > 1 else 0.0
    return FairnessResult(vehicles=vehicles, rate_hz=rate_hz, serve_hz=serve_hz, counted_s=counted_s,
                          served={v: counted.count(v) for v in vehicles}, service_counts=counts,
                          overload_warnings=tuple(warnings.messages))
