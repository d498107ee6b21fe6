"""The Rerun view: a flight recording turned into an .rrd that the Rerun SDK's own reader opens."""

from __future__ import annotations

from pathlib import Path

import pytest

from dovesei.episode import EpisodeSpec, run_episode
from dovesei.replay import episode_metadata
from dovesei.shared.errors import ConfigError
from dovesei.shared.recording import FlightRecorder
from dovesei.sim.starts import Start
from dovesei.sim.world import load_world
from dovesei.view import main as view_main, rrd_entities

WORLD = "synthetic:size_m=400,seed=1"


def test_view_writes_an_rrd_the_sdk_reads_back(tmp_path: Path) -> None:
    spec = EpisodeSpec(policy="dovesei", start=Start(150.0, 220.0, 30.0), seed=1, time_limit_s=8.0)
    folder = tmp_path / "run"
    with FlightRecorder(folder / "recording.mcap", metadata=episode_metadata(spec, WORLD)) as rec:
        live = run_episode(load_world(WORLD), spec, record=rec.write)
    assert view_main([str(folder), "--no-open"]) == 0
    rows = rrd_entities(folder / "recording.rrd")
    n_states = live.track.shape[0]
    assert rows["/plots/alt_agl_m"] == n_states
    assert rows["/camera/image"] == rows["/camera/heatmap"] > 0
    assert rows["/world/ground"] == 1 and rows["/map/image"] == 1  # the world from the recording's metadata
    assert rows["/world/path"] > 0 and rows["/world/final"] == 1
    assert rows["/log/state"] >= 1


def test_view_of_a_folder_without_a_recording_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no recording"):
        view_main([str(tmp_path), "--no-open"])
