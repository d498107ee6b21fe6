"""The command line as an operator meets it: one-line usage errors everywhere, `--version`,
`replay` of a report folder, and the bench saying where it wrote.

Usage errors are checked for every `dovesei` subcommand and every service's console script: a bad
flag or value is ONE line on stderr naming it, with a pointer to --help, and exit code 2 (argparse's
default printed the whole usage first: 14 lines for `dovesei up`).
"""

from __future__ import annotations

import importlib.metadata
import json
import subprocess
import sys
from pathlib import Path

import pytest

from dovesei import cli
from dovesei.episode import EpisodeSpec, run_episode
from dovesei.replay import episode_metadata
from dovesei.shared.errors import ConfigError
from dovesei.shared.recording import FlightRecorder, find_recording
from dovesei.sim.starts import Start
from dovesei.sim.world import load_world

REPO = Path(__file__).resolve().parents[1]
SERVICES = ("dovesei.sim.service", "dovesei.segmenter.service", "dovesei.controller.service",
            "dovesei.camera.service")


def _one_line_usage_error(capsys: pytest.CaptureFixture[str], run, *needles: str) -> str:
    with pytest.raises(SystemExit) as exc:
        run()
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for needle in (*needles, "--help"):
        assert needle in lines[0], lines[0]
    assert "usage:" not in err
    return lines[0]


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_every_subcommand_names_an_unknown_flag_in_one_line(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    line = _one_line_usage_error(capsys, lambda: cli.main([command, "--no-such-flag"]))
    assert line.startswith(f"dovesei {command}: error: "), line
    # argparse reports a missing required argument before an unknown one: either is named.
    assert "--no-such-flag" in line or "required" in line, line


@pytest.mark.parametrize("module", SERVICES)
def test_every_service_names_an_unknown_flag_in_one_line(module: str, capsys: pytest.CaptureFixture[str]) -> None:
    main = importlib.import_module(module).main
    line = _one_line_usage_error(capsys, lambda: main(["--no-such-flag"]))
    assert "--no-such-flag" in line or "required" in line, line


@pytest.mark.parametrize("argv, needles", [
    (["up", "--perception", "nosuch"], ("--perception", "nosuch")),
    (["up", "--seed", "x"], ("--seed", "'x'")),
    (["bench", "--episodes", "many"], ("--episodes", "many")),
    (["replay"], ("recording",)),  # a missing positional
])
def test_a_bad_value_is_one_line_naming_flag_and_value(argv: list[str], needles: tuple[str, ...],
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_usage_error(capsys, lambda: cli.main(argv), *needles)


def test_a_bad_service_value_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from dovesei.controller.service import main as controller_main
    _one_line_usage_error(capsys, lambda: controller_main(["--handover-action", "jump"]), "--handover-action", "jump")


def test_help_still_prints_the_whole_usage(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["up", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: dovesei up") and "--perception" in out


def test_version_prints_the_installed_version() -> None:
    proc = subprocess.run([sys.executable, "-m", "dovesei.cli", "--version"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"dovesei {importlib.metadata.version('dovesei')}"


def test_an_unknown_command_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["nosuch"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "'nosuch'" in lines[0] and "--help" in lines[0]


# ---------------------------------------------------------------------- replay takes a report folder


def _record(folder: Path) -> None:
    world = "synthetic:size_m=400,seed=1"
    spec = EpisodeSpec(policy="dovesei", start=Start(150.0, 220.0, 30.0), seed=1, time_limit_s=4.0)
    with FlightRecorder(folder / "recording.mcap", metadata=episode_metadata(spec, world)) as rec:
        run_episode(load_world(world), spec, record=rec.write)


def test_find_recording_takes_a_file_or_a_report_folder(tmp_path: Path) -> None:
    report = tmp_path / "run"
    report.mkdir()
    (report / "recording.mcap").write_bytes(b"x")
    (report / "replay.mcap").write_bytes(b"x")
    assert find_recording(report) == report / "recording.mcap"  # recording.mcap wins over others
    assert find_recording(report / "replay.mcap") == report / "replay.mcap"
    other = tmp_path / "other"
    other.mkdir()
    (other / "only.mcap").write_bytes(b"x")
    assert find_recording(other) == other / "only.mcap"
    (other / "second.mcap").write_bytes(b"x")
    with pytest.raises(ConfigError, match="2 .mcap files"):
        find_recording(other)
    with pytest.raises(ConfigError, match="no such file or folder"):
        find_recording(tmp_path / "missing")


def test_replay_of_a_report_folder_replays_its_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "up-run"
    _record(folder)
    out = tmp_path / "replayed"
    assert cli.main(["replay", str(folder), "--out", str(out)]) == 0
    doc = json.loads((out / "replay.json").read_text())
    assert doc["recording"] == str(folder / "recording.mcap")
    assert doc["compared"] > 0 and doc["same"] == doc["compared"]
    assert f"report in {out}" in capsys.readouterr().out


def test_replay_of_an_empty_folder_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["replay", str(tmp_path)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "no recording" in lines[0], lines


# ---------------------------------------------------------------------- bench says where it wrote


def test_bench_ends_with_where_it_wrote(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "b"
    assert cli.main(["bench", "--world", "synthetic:size_m=400,seed=1", "--episodes", "1", "--policy", "dovesei",
                     "--time-limit-s", "5", "--start-alt-m", "30", "--jobs", "1", "--no-progress", "--out",
                     str(out)]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith(f"dovesei bench: wrote {out.resolve()} (")
    assert "report.html" in last and "results.json" in last and (out / "results.json").is_file()
