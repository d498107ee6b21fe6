"""One valid instance of every message type, for round-trip and fuzz tests."""

from __future__ import annotations

import numpy as np

from dovesei.shared.messages import (
    CameraFrame, ClassEntry, ControllerStatus, CropFrame, CropHeatmap, CropRequest, EpisodeResult, GroundTruth, PromptSetMsg, SafetyHeatmap,
    StageLatency, Stamp, VehicleState, VelocityCommand, VisualOdometry,
)


def sample_messages(size_px: int = 32) -> list:
    rng = np.random.default_rng(0)
    stamp = Stamp(12.5, "sim")
    image = rng.integers(0, 255, (size_px, size_px, 3), dtype=np.uint8)
    labels = rng.integers(1, 4, (size_px, size_px), dtype=np.uint8)
    truth = GroundTruth(labels, (ClassEntry(1, "grass", True), ClassEntry(2, "road", False)))
    return [
        CameraFrame("uav1", 7, stamp, image, 1.274, 100.0, 0.01, -0.02, 0.3, 1.7e9, truth),
        VehicleState("uav1", 8, stamp, 99.5, (1.0, -0.5, 0.2), yaw_rad=0.1, mode="GUIDED",
                     pos_valid=True, pos_local_ned_m=(3.0, 4.0, -99.5), await_frame_seq=7),
        SafetyHeatmap("uav1", 7, stamp, rng.random((size_px, size_px)).astype(np.float16), 100.0, 1.274,
                      "simulated", True, "abc123", "grouped", 0.004, 0.001),
        SafetyHeatmap("uav1", 7, stamp, rng.integers(0, 255, (size_px, size_px), dtype=np.uint8), 100.0, 1.274,
                      "clipseg", False, "abc123", "dovesei", 0.3),
        VelocityCommand("uav1", 9, stamp, (1.5, 0.0, 0.6), 0.0, 8, 7, 1.7e9, StageLatency(0.001, 0.2, 0.001, 0.003)),
        ControllerStatus("uav1", 9, stamp, "dovesei", "AIMING", "ok", "", 7, 0.25, 320.0, True, 100.0, 180.0,
                         True, 0.51, (1.5, 0.0, 0.6), 99.0),
        PromptSetMsg(stamp, ("grass", "park"), ("building", "road"), "aerial photo of {}"),
        EpisodeResult("uav1", stamp, "safe", 410.0, 95.0, 300.0, 420.0, 19.9, ("grass",), True, 3.5, ""),
        VisualOdometry("uav1", 7, 6, stamp, (2.0, -0.5, 0.1), 0.04, 0.8, True, 0.1, 99.0),
        CropRequest("uav1", 3, stamp, (1.5, -2.0), 12.0, 352, -1, 1.7e9),
        CropFrame("uav1", 3, 7, stamp, image, (1.5, -2.0), 12.0, 40.0, 0.015, 0.01, -0.02, 0.3, 1.7e9, truth),
        CropHeatmap("uav1", 3, 7, stamp, rng.random((size_px, size_px)).astype(np.float16),
                    rng.integers(0, 255, (size_px, size_px), dtype=np.uint8), (1.5, -2.0), 12.0, 40.0, "simulated",
                    True, "abc123", "def456", 0.02),
    ]
