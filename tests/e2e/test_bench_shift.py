"""`--perception-shift`: a monotone recalibration of every heatmap, drawn per start, recorded, flown
beside the plain runs; bad values refused in one line before any work."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dovesei.bench import run_bench
from dovesei.bench.shift import draw, parse_shift
from dovesei.segmenter.core import SegmenterConfig, SegmenterCore, make_backend
from dovesei.segmenter.fusion import FusionError, shift_probability
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import CameraFrame, ClassEntry, GroundTruth, Stamp

WORLD = "synthetic:size_m=400,seed=1"


def test_the_transform_is_monotone_and_is_the_stated_formula() -> None:
    p = np.linspace(0.0, 1.0, 2001, dtype=np.float32)
    for a, b in ((0.6, -0.8), (1.0, 0.0), (1.6, 0.8), (3.0, -2.0)):
        q = shift_probability(p, a, b)
        assert q.dtype == np.float32 and np.all(np.diff(q) >= 0.0)  # never reorders the ground
        mid = p[1:-1].astype(np.float64)
        want = 1.0 / (1.0 + np.exp(-(a * np.log(mid / (1.0 - mid)) + b)))
        assert np.abs(q[1:-1] - want).max() < 1e-5
    assert np.abs(shift_probability(p, 1.0, 0.0) - p).max() < 1e-5  # the identity
    # b > 0 raises every level, a > 1 spreads them away from 0.5.
    assert shift_probability(np.float32([0.5]), 1.0, 0.8)[0] > 0.68
    assert shift_probability(np.float32([0.8]), 1.6, 0.0)[0] > 0.9
    with pytest.raises(FusionError, match="a must be"):
        shift_probability(p, 0.0, 0.0)


def _frame(seq: int) -> CameraFrame:
    labels = np.full((64, 64), 1, np.uint8)
    labels[:, 32:] = 2
    truth = GroundTruth(labels, (ClassEntry(1, "grass", True), ClassEntry(2, "road", False)), (10.0, 5.0), "w")
    return CameraFrame("uav1", seq, Stamp(1.0, "sim"), np.zeros((64, 64, 3), np.uint8), 1.27, 90.0, truth=truth)


def test_the_segmenter_sends_the_shifted_map() -> None:
    plain_cfg = SegmenterConfig(backend="sim", sim_seed=4, heatmap_dtype="float16")
    shifted_cfg = SegmenterConfig(backend="sim", sim_seed=4, heatmap_dtype="float16", prob_shift=(1.6, 0.8))
    plain = SegmenterCore(make_backend(plain_cfg), plain_cfg).process(_frame(3)).prob_safe.astype(np.float32)
    shifted = SegmenterCore(make_backend(shifted_cfg), shifted_cfg).process(_frame(3)).prob_safe.astype(np.float32)
    assert np.abs(shifted - shift_probability(plain, 1.6, 0.8)).max() < 2e-3  # float16 on the wire
    assert shifted.mean() > plain.mean()
    with pytest.raises(ConfigError, match="prob_shift"):
        SegmenterConfig(backend="sim", prob_shift=(-1.0, 0.0))


def test_the_draw_is_per_start_in_range_and_the_same_for_every_policy() -> None:
    shift = (0.6, 1.6, 0.8)
    draws = [draw(shift, 0, w, i) for w in range(3) for i in range(20)]
    assert all(0.6 <= a <= 1.6 and -0.8 <= b <= 0.8 for a, b in draws)
    assert len(set(draws)) == len(draws)  # every start of every world its own
    assert draw(shift, 0, 1, 7) == draw(shift, 0, 1, 7) and draw(shift, 1, 1, 7) != draw(shift, 0, 1, 7)
    assert draw((1.0, 1.0, 0.0), 0, 0, 0) == (1.0, 0.0)


@pytest.mark.parametrize("text, needle", [
    ("0.6,1.6", "three numbers"), ("0,1,0.5", "0 < A_LO"), ("1.6,0.6,0.5", "A_LO <= A_HI"),
    ("0.6,1.6,-1", "0 <= B"), ("0.6,x,0.5", "A_HI 'x' is not a number"), ("0.6,1.6,nan", "finite"),
    ("0.5,20,0.5", "A_HI <= 10"),
])
def test_bad_values_are_refused_naming_what_is_wrong(text: str, needle: str) -> None:
    with pytest.raises(ConfigError, match="--perception-shift") as info:
        parse_shift(text)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_the_bench_flies_plain_and_shifted_beside_each_other_and_records_a_and_b(tmp_path: Path) -> None:
    doc = run_bench(world_spec=WORLD, episodes=2, seed=3, policies=["dovesei"], noise=None, timing="reference",
                    time_limit_s=8.0, start_alt_m=100.0, jobs=1, out=tmp_path, progress=False,
                    perception_shift="0.6,1.6,0.8")
    eps = doc["episodes"]
    assert sorted((e["shift"], e["index"]) for e in eps) == [("0.6,1.6,0.8", 0), ("0.6,1.6,0.8", 1),
                                                             ("none", 0), ("none", 1)]
    for e in eps:
        if e["shift"] == "none":
            assert "perception_shift" not in e
        else:
            assert (e["perception_shift"]["a"], e["perception_shift"]["b"]) == draw((0.6, 1.6, 0.8), 3, 0, e["index"])
    assert doc["summary"]["dovesei"]["episodes"] == 2  # the headline is the plain runs'
    assert [(r["policy"], r["shift"], r["episodes"]) for r in doc["per_shift"]] == [
        ("dovesei", "none", 2), ("dovesei", "0.6,1.6,0.8", 2)]
    assert doc["config"]["perception_shift"] == ["none", "0.6,1.6,0.8"]
    summary = (tmp_path / "summary.md").read_text()
    assert "## Plain and with the perception shift" in summary and "| dovesei | 0.6,1.6,0.8 |" in summary
    assert len(list((tmp_path / "tracks").glob("*.npy"))) == 2  # the plain runs'
    assert len(list((tmp_path / "tracks").glob("shift-*/*.npy"))) == 2
    # The shifted episodes saw other heatmaps: their paths differ from the plain ones somewhere.
    tracks = {p.parent.name + p.name: np.load(p) for p in (tmp_path / "tracks").rglob("*.npy")}
    plain = [v for k, v in tracks.items() if k.startswith("tracks")]
    shifted = [v for k, v in tracks.items() if k.startswith("shift")]
    assert any(a.shape != b.shape or not np.array_equal(a, b) for a, b in zip(plain, shifted))
    # Resuming the same bench flies nothing again.
    journal = (tmp_path / "episodes.jsonl").read_text()
    run_bench(world_spec=WORLD, episodes=2, seed=3, policies=["dovesei"], noise=None, timing="reference",
              time_limit_s=8.0, start_alt_m=100.0, jobs=1, out=tmp_path, progress=False,
              perception_shift="0.6,1.6,0.8")
    assert (tmp_path / "episodes.jsonl").read_text() == journal


def test_shift_only_flies_the_same_shifted_runs_and_nothing_plain(tmp_path: Path) -> None:
    kw = dict(world_spec=WORLD, seed=3, policies=["dovesei"], noise=None, timing="reference", time_limit_s=8.0,
              start_alt_m=100.0, jobs=1, progress=False, perception_shift="0.6,1.6,0.8")
    both = run_bench(episodes=1, out=tmp_path / "both", **kw)
    only = run_bench(episodes=2, out=tmp_path / "only", shift_only=True, **kw)
    assert [(e["shift"], e["index"]) for e in only["episodes"]] == [("0.6,1.6,0.8", 0), ("0.6,1.6,0.8", 1)]
    assert only["summary"]["dovesei"]["episodes"] == 2  # no plain runs: the headline is the shifted ones'
    assert only["config"]["perception_shift"] == ["0.6,1.6,0.8"]
    twin = next(e for e in both["episodes"] if e["shift"] != "none")
    mine = only["episodes"][0]
    # The same start, the same draw, the same flight as beside the plain runs.
    assert mine["perception_shift"] == twin["perception_shift"] and mine["outcome"] == twin["outcome"]
    assert np.array_equal(np.load(next((tmp_path / "only" / "tracks").rglob("*00*.npy"))),
                          np.load(next((tmp_path / "both" / "tracks").glob("shift-*/*00*.npy"))))
    assert "shifted runs only" in (tmp_path / "only" / "summary.md").read_text()
    with pytest.raises(ConfigError, match="--shift-only needs --perception-shift"):
        run_bench(episodes=1, out=tmp_path / "none", shift_only=True, **{**kw, "perception_shift": None})
    assert not (tmp_path / "none").exists()


def test_the_command_line_refuses_a_bad_shift_in_one_line_and_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "dovesei.cli", "bench", "--world", WORLD, "--perception-shift", "2,1,0.5",
                        "--out", str(out), "--no-progress"], capture_output=True, text=True, cwd=tmp_path,
                       timeout=300)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("dovesei bench: --perception-shift '2,1,0.5'"), r.stderr
    assert not out.exists()


def test_a_sweep_has_a_shift_axis(tmp_path: Path) -> None:
    from dovesei.sweep import grid_from_doc

    grid = grid_from_doc({"worlds": [WORLD], "policies": ["dovesei"], "perception": ["realistic"],
                          "perception_shift": [None, "0.6,1.6,0.8", [0.9, 1.1, 0.2]]})
    assert [v.shift for v in grid.variants] == [None, (0.6, 1.6, 0.8), (0.9, 1.1, 0.2)]
    assert json.dumps(grid.config()["perception_shift"]) == '["none", "0.6,1.6,0.8", "0.9,1.1,0.2"]'
    with pytest.raises(ConfigError, match="sweep file: 'perception_shift'"):
        grid_from_doc({"worlds": [WORLD], "perception_shift": ["1,2"]})
