"""`dovesei up` records the flight by default: three processes on Zenoh, the monitor's recorder
writes recording.mcap, and a replay of it gives the controller's own decisions back; `--rrd` saves
the live Rerun view of the same stream."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dovesei.replay import replay
from dovesei.shared.messages import CameraFrame, ControllerStatus, SafetyHeatmap, VehicleState
from dovesei.shared.recording import FlightRecording
from dovesei.view import rrd_entities

REPO = Path(__file__).resolve().parents[2]
WORLD = "synthetic:size_m=400,seed=1"


@pytest.mark.slow
def test_up_records_and_the_recording_replays_to_the_same_decisions(tmp_path: Path) -> None:
    out = tmp_path / "run"
    argv = [sys.executable, "-m", "dovesei.cli", "up", "--world", WORLD, "--segmenter", "sim", "--start", "200,200,35",
            "--time-limit-s", "12", "--no-video", "--rrd", str(tmp_path / "live.rrd"), "--out", str(out)]
    proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=240,
                          env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert proc.returncode in (0, 3), proc.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    recording = FlightRecording(out / "recording.mcap")
    run = recording.meta("run")
    assert run["policy"] == "dovesei" and run["lockstep"] is True and run["world"] == WORLD
    assert recording.meta("camera")["width_px"] > 0 and recording.meta("prompts")["positive"]
    kinds: dict[type, int] = {}
    for _, msg in recording.messages():
        kinds[type(msg)] = kinds.get(type(msg), 0) + 1
    assert kinds[VehicleState] == len(report["trajectory"]["t_s"])
    assert kinds[CameraFrame] == report["counts"]["frames"] and kinds[SafetyHeatmap] == report["counts"]["heatmaps"]
    result = replay(recording)
    assert result.compared == kinds[ControllerStatus] > 0
    assert result.same == result.compared, result.first_difference
    assert result.recorded_outcome == report["outcome"]
    # The live view's tap saw the same stream: the .rrd holds one altitude sample per state.
    rows = rrd_entities(tmp_path / "live.rrd")
    assert rows["/plots/alt_agl_m"] == kinds[VehicleState] and rows["/camera/heatmap"] == kinds[SafetyHeatmap]
