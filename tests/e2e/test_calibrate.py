"""`dovesei calibrate`: flags and world checked before any work, seeds disjoint from the reported bench's."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dovesei.calibrate import main

WORLD = "synthetic:size_m=400,seed=1"


@pytest.mark.parametrize("args, needle", [
    (["--world", "no/such/world"], "no/such/world"),
    (["--episodes", "-1"], "--episodes"),
    (["--seed", "0"], "--seed 0"),
    (["--noise", "0,x"], "--noise"),
    (["--noise", "9"], "--noise"),
    (["--timing", "fast"], "fast"),
    (["--episodes", "many"], "--episodes"),
    (["--perception", "dreamy"], "--perception"),
])
def test_bad_flags_are_one_line_and_leave_no_folder(tmp_path: Path, args: list[str], needle: str) -> None:
    out = tmp_path / "cal"
    r = subprocess.run([sys.executable, "-m", "dovesei.cli", "calibrate", *args, "--out", str(out)], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("dovesei calibrate:") and needle in lines[0], r.stderr
    assert not out.exists()


def test_a_small_calibration_names_its_disjoint_seeds(tmp_path: Path, capsys) -> None:
    out = tmp_path / "cal"
    assert main(["--world", WORLD, "--timing", "reference", "--noise", "0", "--episodes", "1", "--jobs", "1",
                 "--policy", "dovesei", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "calibration start seed 1 (episode seeds 100003..100003)" in text and "disjoint" in text
    doc = json.loads((out / "calibration.json").read_text())
    assert [(c["timing"], c["noise"], c["policy"], c["episodes"]) for c in doc["cells"]] == [
        ("reference", 0.0, "dovesei", 1)]
    bench = json.loads((out / "reference-noise0" / "results.json").read_text())
    assert [e["seed"] for e in bench["episodes"]] == [100003]
