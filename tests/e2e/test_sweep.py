"""`dovesei sweep FILE`: the grid file is checked before any work, every cell flies the same starts,
one table and plot, resumable."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dovesei.shared.errors import ConfigError
from dovesei.sweep import grid_from_doc, run_sweep

WORLD = "synthetic:size_m=400,seed=1"
GRASS = {"positive": ["grass", "lawn"], "negative": ["building", "road", "water", "tree"]}


def _write(tmp_path: Path, doc: dict, suffix: str = ".json") -> Path:
    path = tmp_path / f"grid{suffix}"
    if suffix == ".json":
        path.write_text(json.dumps(doc))
    else:
        import yaml

        path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_a_grid_runs_every_cell_from_the_same_starts_and_resumes(tmp_path: Path) -> None:
    doc = {"worlds": [WORLD], "episodes": 1, "seed": 2, "timing": "reference", "time_limit_s": 6.0,
           "policies": ["dovesei"], "perception": ["realistic"], "prompts": {"reference": None, "grass": GRASS}}
    path = _write(tmp_path, doc, ".yaml")
    out = tmp_path / "out"
    res = run_sweep(path, out=out, jobs=1, progress=False)
    cells = [(e["policy"], e["perception"], e["prompts"]) for e in res["episodes"]]
    assert cells == [("dovesei", "realistic", "reference"), ("dovesei", "realistic", "grass")]
    assert len({json.dumps(e["start"]) for e in res["episodes"]}) == 1  # the same start in every cell
    assert [(r["prompts"], r["episodes"]) for r in res["per_variant"]] == [("reference", 1), ("grass", 1)]
    assert all(len(r["success_ci95"]) == 2 for r in res["per_variant"])
    summary = (out / "summary.md").read_text()
    assert "## Per perception profile and prompt set" in summary and "| dovesei | realistic | grass |" in summary
    assert (out / "sweep.png").stat().st_size > 0
    journal = (out / "episodes.jsonl").read_text()
    again = run_sweep(path, out=out, jobs=1, progress=False)
    assert (out / "episodes.jsonl").read_text() == journal and again["per_variant"] == res["per_variant"]


def test_prompt_sets_reach_the_segmenter(tmp_path: Path) -> None:
    grid = grid_from_doc({"worlds": [WORLD], "prompts": {"grass": GRASS}})
    (variant,) = grid.variants
    assert variant.prompts["positive"] == ["grass", "lawn"] and variant.labelled
    from dovesei.episode import EpisodeSpec, segmenter_config
    from dovesei.sim.starts import Start

    spec = EpisodeSpec.from_job({"policy": "dovesei", "timing": "reference", "seed": 0, "time_limit_s": 5.0,
                                 "prompts": variant.prompts, "perception": variant.perception}, Start(0, 0, 100))
    cfg = segmenter_config(spec)
    assert cfg.prompts.positive == ("grass", "lawn") and cfg.fusion == "dovesei"  # the paper's fusion for its policy


@pytest.mark.parametrize("doc, needle", [
    ({"wolds": [WORLD]}, "wolds"),
    ({"worlds": [WORLD], "suite": "default"}, "not both"),
    ({"episodes": 0}, "episodes"),
    ({"policies": ["dovesei", "nope"]}, "nope"),
    ({"perception": ["dreamy"]}, "dreamy"),
    ({"timing": "fast"}, "fast"),
    ({"prompts": {"bad": {"positive": ["grass"], "negative": [], "colour": "red"}}}, "colour"),
    ({"noise": 9}, "noise"),
])
def test_bad_grids_are_refused_by_name(doc: dict, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        grid_from_doc(doc)


def test_cli_bad_file_is_one_line_and_leaves_no_folder(tmp_path: Path) -> None:
    path = tmp_path / "grid.json"
    path.write_text("{not json")
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "dovesei.cli", "sweep", str(path), "--out", str(out)], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "not valid JSON" in lines[0] and not out.exists()
