"""`dovesei closelook-stats`: the close look's finding rule measured on simulated crops of people and
of clear ground, through the real crop, perception and verdict path; bad flags refused in one line."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from dovesei.benchmarks.closelook_stats import _gate_opens, looks_of, summarise
from dovesei.controller.policies.clearance.closelook import CloseLookConfig
from dovesei.sim.world import load_world

WORLD = "synthetic:style=villas,seed=2"


def test_the_gate_opens_on_two_clear_looks_in_a_row() -> None:
    assert _gate_opens([True, False, False]) and not _gate_opens([False, True, False, True])
    assert not _gate_opens([False]) and not _gate_opens([])


def test_the_rule_finds_people_and_a_blind_rule_finds_none() -> None:
    world = load_world(WORLD)
    seen = summarise(looks_of(world, "realistic", 4, 3, 300))
    assert seen["person_squares"] == 2 and seen["clear_squares"] == 2 and seen["person_looks"] == 6
    assert seen["person_looks_missed"] <= 1 and seen["person_gate_opened"] == 0
    blind = dataclasses.replace(CloseLookConfig(), never_p_min=1.0, blob_min_logit=1e6)
    unseen = summarise(looks_of(world, "realistic", 4, 3, 300, blind))
    assert unseen["person_looks_missed"] == 6 and unseen["person_gate_opened"] == 2
    assert unseen["clear_looks_fired"] == 0


def test_cars_within_the_vehicle_separation_are_found_and_a_blind_rule_misses_them() -> None:
    world = load_world(WORLD)
    cars = looks_of(world, "realistic", 3, 2, 300, vehicles=True)
    assert len(cars) == 3 and all(r["vehicle"] and r["nearest_vehicle_m"] <= 5.0 for r in cars)
    seen = summarise(cars)
    assert seen["vehicle_squares"] == 3 and seen["person_squares"] == seen["clear_squares"] == 0
    assert seen["vehicle_looks"] == 6 and seen["vehicle_looks_missed"] <= 1 and seen["vehicle_gate_opened"] == 0
    blind = dataclasses.replace(CloseLookConfig(), never_p_min=1.0, blob_min_logit=1e6)
    unseen = summarise(looks_of(world, "realistic", 3, 2, 300, blind, vehicles=True))
    assert unseen["vehicle_looks_missed"] == 6 and unseen["vehicle_gate_opened"] == 3


def test_the_command_prints_its_figures_and_refuses_the_reported_seeds() -> None:
    run = [sys.executable, "-m", "dovesei.cli", "closelook-stats", "--world", WORLD, "--crops", "2", "--looks", "2",
           "--vehicle-crops", "1", "--profile", "harsh", "--margin-m", "5.7", "--json"]
    r = subprocess.run(run, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout.strip().splitlines()[-1])
    s = doc["profiles"]["harsh"]
    assert doc["seed_base"] == 200 and s["person_looks"] + s["clear_looks"] == 4 and s["vehicle_looks"] == 2
    assert doc["side_m"] == pytest.approx(11.4) and doc["out_px"] == 352  # the final looks' square, as asked
    assert 0 <= s["person_looks_missed"] <= s["person_looks"] and len(doc["loadavg"]) == 3
    for flags, needle in ((["--seed-base", "5"], "--seed-base 5"), (["--profile", "fuzzy"], "--profile 'fuzzy'"),
                          (["--looks", "0"], "--looks 0"), (["--vehicle-crops", "-1"], "--vehicle-crops -1"),
                          (["--margin-m", "nan"], "--margin-m nan"), (["--margin-m", "40"], "--margin-m 40"),
                          (["--out-px", "8"], "--out-px 8")):
        r = subprocess.run(run[:4] + flags, capture_output=True, text=True, timeout=120)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2 and len(lines) == 1 and needle in lines[0], r.stderr


@pytest.mark.parametrize("margin_m", [None, 5.7])
def test_clear_squares_are_safe_ground_away_from_everyone(margin_m: float | None) -> None:
    world = load_world(WORLD)
    for rec in looks_of(world, "realistic", 4, 1, 400, margin_m=margin_m):
        if rec["person"]:
            assert rec["nearest_person_m"] <= 3.5
        else:
            assert rec["nearest_person_m"] >= 6.0
