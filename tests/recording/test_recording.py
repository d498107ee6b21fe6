"""Flight recordings: an in-process episode written to MCAP, read back with mcap's own reader and
with ours, then replayed to the same decisions (recorded heatmaps, and the simulated segmenter
re-run on the recorded frames)."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from dovesei.episode import EpisodeSpec, run_episode
from dovesei.replay import episode_metadata, main as replay_main, replay
from dovesei.segmenter.core import SegmenterConfig
from dovesei.shared.messages import ControllerStatus, SafetyHeatmap, VehicleState
from dovesei.shared.recording import (
    CAMERA_IMAGE_TOPIC, HEATMAP_IMAGE_TOPIC, FlightRecorder, FlightRecording, RecordingError,
)
from dovesei.sim.starts import Start
from dovesei.sim.world import load_world

WORLD = "synthetic:size_m=400,seed=1"


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory):
    # From this start the paper's policy goes through every state to a hand-over in 26 s of sim time
    # (525 ticks): the recording holds the whole state chain at under half the cost of a 60 s timeout.
    spec = EpisodeSpec(policy="dovesei", start=Start(150.0, 250.0, 40.0), seed=3, time_limit_s=60.0)
    path = tmp_path_factory.mktemp("rec") / "recording.mcap"
    statuses: list[ControllerStatus] = []

    def record(msg):
        rec.write(msg)
        if isinstance(msg, ControllerStatus):
            statuses.append(msg)

    with FlightRecorder(path, metadata=episode_metadata(spec, WORLD)) as rec:
        live = run_episode(load_world(WORLD), spec, record=record)
    return path, spec, live, statuses


def test_mcap_reader_sees_json_channels_and_foxglove_images(flight) -> None:
    path, _, live, statuses = flight
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        counts = Counter()
        first_image = None
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] += 1
            if channel.topic == HEATMAP_IMAGE_TOPIC and first_image is None:
                first_image = json.loads(message.data)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert schemas[CAMERA_IMAGE_TOPIC].name == "foxglove.CompressedImage"
    assert schemas[CAMERA_IMAGE_TOPIC].encoding == "jsonschema"
    assert schemas["/dovesei/status"].name == "dovesei.controller_status" or "status" in schemas["/dovesei/status"].name
    state_schema = json.loads(schemas["/dovesei/state"].data)
    assert state_schema["properties"]["alt_agl_m"] == {"type": "number"}
    assert counts["/dovesei/status"] == len(statuses) and counts["/dovesei/episode"] == 1
    assert counts[CAMERA_IMAGE_TOPIC] == counts["/dovesei/camera"] > 0
    assert first_image["format"] == "png" and first_image["data"]
    assert json.loads(meta["run"]["lockstep"]) is True and meta["run"]["policy"] == "dovesei"
    assert "positive" in meta["prompts"]


def test_our_reader_gives_back_the_same_messages(flight) -> None:
    path, _, live, statuses = flight
    recording = FlightRecording(path)
    read = [m for _, m in recording.messages((ControllerStatus,))]
    assert read == statuses  # dataclass equality: every field as sent
    heatmaps = [m for _, m in recording.messages((SafetyHeatmap,))]
    assert heatmaps and heatmaps[0].prob_safe.dtype == np.uint8


def test_replay_with_recorded_heatmaps_makes_the_same_decisions(flight) -> None:
    path, _, live, statuses = flight
    result = replay(FlightRecording(path))
    assert result.compared == len(statuses) and result.same == result.compared, result.first_difference
    assert list(result.states) == [s.state for s in statuses]
    assert result.recorded_outcome == live.result.outcome


def test_replay_with_the_simulated_segmenter_on_recorded_frames(flight, tmp_path: Path) -> None:
    path, spec, live, statuses = flight
    meta = FlightRecording(path).meta("segmenter")
    seg = SegmenterConfig(backend="sim", fusion=meta["fusion"], sim_noise=meta["sim_noise"], sim_seed=meta["sim_seed"])
    result = replay(FlightRecording(path), segmenter=seg)
    assert result.same == result.compared == len(statuses), result.first_difference
    # A different policy runs on the same inputs; its decisions are its own.
    other = replay(FlightRecording(path), policy="clearance")
    assert other.ticks == len(statuses) and other.compared == 0


def test_replay_command_writes_its_report(flight, tmp_path: Path, capsys) -> None:
    path, *_ = flight
    assert replay_main([str(path), "--segmenter", "sim", "--out", str(tmp_path / "r")]) == 0
    doc = json.loads((tmp_path / "r" / "replay.json").read_text())
    assert doc["same"] == doc["compared"] > 0 and doc["segmenter"] == "sim"
    assert doc["files"]["trajectory_plot"] == "trajectory.png" and (tmp_path / "r" / "trajectory.png").stat().st_size > 10_000
    again = FlightRecording(tmp_path / "r" / "replay.mcap")
    assert sum(1 for _ in again.messages((ControllerStatus,))) == doc["ticks"]
    assert sum(1 for _ in again.messages((VehicleState,))) >= doc["ticks"]


@pytest.mark.parametrize("keep", ["all but 100 bytes", "half", "a tenth"])
def test_a_recording_cut_anywhere_replays_up_to_the_cut(flight, tmp_path: Path, keep: str, capsys) -> None:
    # What a crash or a power loss leaves: no footer, no summary, maybe half a chunk. Was: not
    # replayable at all, even with only the last 100 bytes missing.
    path, _, live, statuses = flight
    data = path.read_bytes()
    size = {"all but 100 bytes": len(data) - 100, "half": len(data) // 2, "a tenth": len(data) // 10}[keep]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:size])
    recording = FlightRecording(cut)
    assert not recording.complete and recording.meta("run")["policy"] == "dovesei"
    read = [m for _, m in recording.messages((ControllerStatus,))]
    assert recording.cut is not None and "near byte" in recording.cut
    assert read == statuses[:len(read)]  # a prefix, exactly as recorded
    if keep == "all but 100 bytes":
        assert read == statuses  # only the footer was lost
    else:
        assert 0 < len(read) < len(statuses)
    assert "recovered the" in recording.describe()
    assert replay_main([str(cut), "--out", str(tmp_path / "r")]) == 0
    doc = json.loads((tmp_path / "r" / "replay.json").read_text())
    assert doc["recording_cut"] and doc["recovered_messages"] > 0 and doc["same"] == doc["compared"] > 0
    assert "is cut" in capsys.readouterr().out
    whole = FlightRecording(path)
    assert whole.complete and sum(1 for _ in whole.messages((ControllerStatus,))) == len(statuses)
    assert whole.cut is None


def test_not_a_recording_is_one_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not mcap at all")
    with pytest.raises(RecordingError, match="not a readable MCAP"):
        FlightRecording(bad)
    with pytest.raises(RecordingError, match="no such file"):
        FlightRecording(tmp_path / "missing.mcap")
