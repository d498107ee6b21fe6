"""`dovesei perception-stats`: the statistics and the command line."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from dovesei import perception_stats
from dovesei.perception_stats import roc_auc, world_stats
from dovesei.segmenter.sim_backend import profile_params
from dovesei.sim.world import ClassInfo, World
from tests.sim.test_judge import blocks_world


def test_statistics_are_in_range_and_the_judge_side_alone_reads_the_flags() -> None:
    stats = world_stats(blocks_world(), profile_params("realistic"), 6, 2, seed=3)
    # The same world under the same name (its per-world draws are keyed by the name), flags flipped.
    flipped = world_stats(dataclasses.replace(blocks_world(flip=True), name="blocks"), profile_params("realistic"),
                          6, 2, seed=3)
    assert stats.frames == 12 and 0.0 < stats.median_threshold < 0.85
    assert 0.0 <= stats.lowered_fraction <= 1.0 and 0.0 <= stats.frame_agreement <= 1.0
    # The perception is blind to the flags: same thresholds and masks; only the verdicts flip.
    assert (flipped.median_threshold, flipped.lowered_fraction, flipped.frame_agreement) == (
        stats.median_threshold, stats.lowered_fraction, stats.frame_agreement)
    assert stats.target_precision > 0.6 and flipped.target_precision < 0.4
    # Separability is about the truth too: flipped flags turn it around (AUC -> 1 - AUC).
    assert stats.separability > 0.8 and flipped.separability == pytest.approx(1.0 - stats.separability, abs=0.05)


def test_roc_auc_counts_ties_half_and_refuses_an_empty_side() -> None:
    assert roc_auc(np.array([2.0, 3.0]), np.array([0.0, 1.0])) == 1.0
    assert roc_auc(np.array([0.0, 1.0]), np.array([2.0, 3.0])) == 0.0
    assert roc_auc(np.array([1.0, 1.0]), np.array([1.0])) == 0.5
    # 5 beats both negatives; 1 ties one and beats the other: (2 + 1.5) / 4.
    assert roc_auc(np.array([5.0, 1.0]), np.array([1.0, 0.0])) == pytest.approx(3.5 / 4.0)
    rng = np.random.default_rng(0)
    assert abs(roc_auc(rng.normal(size=4000), rng.normal(size=4000)) - 0.5) < 0.02
    with pytest.raises(ValueError, match="at least one positive"):
        roc_auc(np.array([]), np.array([1.0]))


def test_clean_perception_targets_the_lawns_and_nears_the_oracle() -> None:
    stats = world_stats(blocks_world(), profile_params("clean"), 6, 2, seed=0)
    assert stats.target_precision > 0.9 and stats.core_precision == 1.0
    assert stats.oracle_precision > 0.9
    assert stats.target_precision > stats.oracle_precision - 0.05


def test_command_line_json_and_bad_flags(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(perception_stats, "load_world", lambda spec: blocks_world())
    assert perception_stats.main(["--world", "blocks", "--starts", "2", "--frames", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("median_threshold", "lowered_fraction", "target_precision", "frame_agreement", "separability"):
        assert math.isfinite(out[key])
    assert out["perception"] == "realistic" and out["fusion"] == "dovesei" and out["alt_m"] == 100.0
    assert perception_stats.main(["--world", "blocks", "--frames", "1"]) == 2
    with pytest.raises(SystemExit) as info:
        perception_stats.main(["--perception", "dreamy"])
    assert info.value.code == 2


def test_below_floor_counts_views_with_under_a_tenth_of_disk_safe_ground() -> None:
    # The lawn blocks fill most of any 148 m view; a world of road with one 20 m lawn never does.
    assert world_stats(blocks_world(), profile_params("clean"), 4, 2, seed=0).below_floor_fraction == 0.0
    labels = np.full((600, 600), 2, np.uint8)
    labels[290:310, 290:310] = 1
    sparse = World(np.zeros((600, 600, 3), np.uint8), labels, 1.0,
                   {1: ClassInfo("grass", True), 2: ClassInfo("road", False)}, name="sparse")
    stats = world_stats(sparse, profile_params("clean"), 4, 2, seed=0)
    assert stats.below_floor_fraction == 1.0
    # The reference's 10 % floor then forces target pixels onto the road: precision stays low
    # however right the perception is about each class (the oracle's own frames fail instead).
    assert stats.target_precision < 0.5


def test_suite_flag_names_the_suites(capsys) -> None:
    assert perception_stats.main(["--suite", "nope"]) == 2
    assert "suite 'nope'" in capsys.readouterr().err
    assert perception_stats.main(["--suite", "default", "--world", "dubai"]) == 2
