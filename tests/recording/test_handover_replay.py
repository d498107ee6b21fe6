"""A flight recorded with a hand-over altitude other than the default replays with it: the
recording's run metadata carries it, and replay hands it to the controller (and so the policy)."""

from __future__ import annotations

from pathlib import Path

from dovesei.episode import EpisodeSpec, run_episode
from dovesei.replay import episode_metadata, replay
from dovesei.shared.messages import ControllerStatus
from dovesei.shared.recording import FlightRecorder, FlightRecording
from dovesei.sim.starts import Start
from dovesei.sim.world import load_world

WORLD = "synthetic:size_m=400,seed=1"


def test_replay_flies_the_recorded_handover_altitude(tmp_path: Path) -> None:
    # A 44 m start with a 35 m hand-over: from here the paper's policy finds a spot at once and hands
    # over after 16 s of sim time (from (200, 200): 27 s).
    spec = EpisodeSpec(policy="dovesei", start=Start(150.0, 250.0, 44.0), seed=3, time_limit_s=60.0,
                       handover_alt_m=35.0)
    path = tmp_path / "recording.mcap"
    statuses: list[ControllerStatus] = []

    def record(msg):
        rec.write(msg)
        if isinstance(msg, ControllerStatus):
            statuses.append(msg)

    with FlightRecorder(path, metadata=episode_metadata(spec, WORLD)) as rec:
        live = run_episode(load_world(WORLD), spec, record=record)
    assert 34.0 < live.result.final_alt_m <= 35.0
    recording = FlightRecording(path)
    assert recording.meta("run")["handover_alt_m"] == 35.0
    result = replay(recording)
    assert result.compared == len(statuses) and result.same == result.compared, result.first_difference
