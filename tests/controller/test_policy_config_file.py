"""`--policy-config FILE`: any policy's constants from TOML, checked in one line per bad key or value,
the defaults file printed by `dovesei policy-config`, and the file reaching the policy through `up`."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from dovesei import cli
from dovesei.controller import service as controller_service
from dovesei.controller.core import ControllerConfig, ControllerCore
from dovesei.controller.policies.config_file import defaults_toml, load_policy_config, preset_config
from dovesei.shared.errors import ConfigError
from dovesei.up import UpOptions
from dovesei.up.launch import child_configs
from dovesei.up.report import _policy_config

WORLD = "synthetic:size_m=400,seed=1"


@pytest.mark.parametrize("timing", ["reference", "real"])
@pytest.mark.parametrize("policy", ["clearance", "dovesei", "dovesei-nofocus"])
def test_the_defaults_file_round_trips_to_the_preset(tmp_path: Path, policy: str, timing: str) -> None:
    path = tmp_path / "p.toml"
    path.write_text(defaults_toml(policy, timing))
    assert load_policy_config(policy, path, timing) == preset_config(policy, timing)


def test_a_file_sets_only_what_it_names_and_the_controller_flies_it(tmp_path: Path) -> None:
    path = tmp_path / "mine.toml"
    path.write_text("scene_floor_p = 0.9\nlower_search_fracs = [0.5]\nmax_aborts = 3\n")
    cfg = ControllerConfig(policy="clearance", timing="real", policy_config_file=str(path), handover_alt_m=12.0)
    policy = ControllerCore(cfg).policy.config
    assert (policy.scene_floor_p, policy.lower_search_fracs, policy.max_aborts) == (0.9, (0.5,), 3)
    assert policy.handover_alt_m == 12.0  # still the controller's, handed down
    assert policy.replace(scene_floor_p=0.5, lower_search_fracs=(0.6, 0.4), max_aborts=8, handover_alt_m=20.0) == \
        preset_config("clearance", "real")
    # The controller service's own flags carry the file.
    argv = controller_service.to_argv(cfg)
    assert controller_service.config_from_args(controller_service.build_parser().parse_args(argv)) == cfg


@pytest.mark.parametrize("text, needle", [
    ("no_such = 1\n", "no_such is not a constant of the clearance policy"),
    ("scene_floor_p = 'high'\n", "scene_floor_p must be a finite number, got 'high'"),
    ("scene_floor_p = nan\n", "scene_floor_p must be a finite number"),
    ("scene_floor_p = 2.0\n", "scene_floor_p"),  # the config's own range check
    ("max_aborts = 2.5\n", "max_aborts must be an integer"),
    ("max_aborts = true\n", "max_aborts must be an integer"),
    ("lower_search_fracs = 0.5\n", "lower_search_fracs must be an array"),
    ("lower_search_fracs = [0.5, 'x']\n", "lower_search_fracs[1] must be a finite number"),
    ("handover_alt_m = 10.0\n", "handover_alt_m is set with --handover-alt-m"),
    ("timing_name = 'real'\n", "timing_name is set with --timing"),
    ("scene_floor_p = \n", "not TOML"),
])
def test_bad_keys_and_values_are_one_line_naming_file_and_key(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_policy_config("clearance", path, "real")
    msg = str(err.value)
    assert needle in msg and "bad.toml" in msg and "\n" not in msg, msg


def test_a_missing_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read it"):
        ControllerConfig(policy="clearance", policy_config_file=str(tmp_path / "nope.toml"))


def test_the_command_prints_the_defaults_and_checks_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["policy-config", "--defaults", "dovesei", "--timing", "reference"]) == 0
    doc = tomllib.loads(capsys.readouterr().out)
    assert doc["safety_radius_m"] == 2.0 and "timer_scale" not in doc and "handover_alt_m" not in doc
    bad = tmp_path / "bad.toml"
    bad.write_text("focus_rate = 'fast'\n")
    assert cli.main(["policy-config", "--check", str(bad), "--policy", "dovesei"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "focus_rate must be a finite number" in err[0]


def test_up_hands_the_file_to_the_controller_and_reports_what_it_changed(tmp_path: Path) -> None:
    path = tmp_path / "mine.toml"
    path.write_text("scene_floor_p = 0.9\nmargin_m = 1.5\n")  # margin_m is the default: not a change
    opts = UpOptions(world=WORLD, policy="clearance", timing="real", policy_config=path, out=tmp_path)
    configs = child_configs(opts, (200.0, 200.0, 100.0))
    assert configs.controller.policy_config_file == str(path.resolve())
    assert _policy_config(opts) == (str(path), {"scene_floor_p": 0.9})
    path.write_text("scene_floor_p = 0.9\nbogus = 1\n")
    with pytest.raises(ConfigError, match="bogus is not a constant"):
        UpOptions(world=WORLD, policy="clearance", timing="real", policy_config=path, out=tmp_path)
