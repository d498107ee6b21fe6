"""The split deployment is secured (mutual TLS + ACL); the one-host one stays plain on loopback.

Read from the resolved compose model (the real Compose binary, as in test_compose.py), then run
without containers: the ground router's own config file loaded by a Python router on a free
loopback port, and each split service's Zenoh session built from its compose command by its
real parser, with the container paths pointed at certificates made by `dovesei certs`.
"""

from __future__ import annotations

import importlib
import json
import re
import shlex
import subprocess
import threading
from pathlib import Path

import compose
import pytest
import zenoh

from dovesei.certs import router_config, write_pki
from dovesei.shared import keys
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.zconfig import ENV_CONFIG, free_port, zenoh_config_from_args

from tests.deploy.test_compose import PYPROJECT, SCRIPTS

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
COMPOSE_BIN = Path(compose.__file__).parent / "docker-compose"
SPLIT = ("compose.ground.yaml", "compose.onboard.yaml")
CERTS_IN_CONTAINER = "/etc/dovesei/certs"
ROLE_OF = {"segmenter": "segmenter", "controller": "controller", "camera": "camera"}


def _model(name: str) -> dict:
    out = subprocess.run([str(COMPOSE_BIN), "-f", str(DEPLOY / name), "--profile", "gpu", "config", "--format", "json"],
                         capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)


def _flag(argv: list[str], flag: str) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == flag]


def _services(name: str) -> dict:
    return {n: s for n, s in _model(name)["services"].items() if not s["image"].startswith("eclipse/zenoh")}


@pytest.mark.parametrize("name", SPLIT)
def test_every_split_service_uses_its_own_role_certificate(name: str) -> None:
    for svc_name, svc in _services(name).items():
        role = ROLE_OF[svc_name]
        for argv in (svc["command"], svc["healthcheck"]["test"][1:]):
            assert _flag(argv, "--tls-ca") == [f"{CERTS_IN_CONTAINER}/ca.pem"], (svc_name, argv)
            assert _flag(argv, "--tls-cert") == [f"{CERTS_IN_CONTAINER}/{role}.pem"], (svc_name, argv)
            assert _flag(argv, "--tls-key") == [f"{CERTS_IN_CONTAINER}/{role}.key"], (svc_name, argv)
            assert all(ep.startswith("tls/") for ep in _flag(argv, "--connect")), (svc_name, argv)
        mounts = {v["target"]: v for v in svc["volumes"]}
        assert mounts[CERTS_IN_CONTAINER]["read_only"] is True


def test_ground_router_is_tls_only_with_the_acl_of_dovesei_certs() -> None:
    router = next(s for s in _model("compose.ground.yaml")["services"].values() if s["image"].startswith("eclipse/zenoh"))
    mounts = {v["target"]: v for v in router["volumes"]}
    config_file = Path(mounts["/etc/zenoh/router.json5"]["source"])
    assert config_file.name == "router.tls.json5" and mounts["/etc/zenoh/certs"]["read_only"] is True
    conf = zenoh.Config.from_file(str(config_file))
    # Both through Zenoh's own parser, so defaults it fills in compare equal.
    expected = zenoh.Config.from_json5(json.dumps(router_config("/etc/zenoh/certs")))
    for key in ("mode", "listen/endpoints", "scouting/multicast", "transport/link", "access_control"):
        assert json.loads(conf.get_json(key)) == json.loads(expected.get_json(key)), key
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"
    assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]


def test_ground_client_config_dials_the_router_over_tls() -> None:
    seg = _services("compose.ground.yaml")["segmenter"]
    mounts = {v["target"]: v for v in seg["volumes"]}
    conf = zenoh.Config.from_file(mounts["/etc/dovesei/zenoh.json5"]["source"])
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/router:7447"]


def test_one_host_router_is_plain_and_on_loopback_only() -> None:
    router = _model("compose.yaml")["services"]["router"]
    assert [(p.get("host_ip"), str(p["published"])) for p in router["ports"]] == [("127.0.0.1", "7447")]


def test_the_pinned_zenoh_has_what_the_secured_mode_needs() -> None:
    # TLS keys and access_control exist in this binding's config schema (an older wheel lacks them).
    tls = json.loads(zenoh.Config().get_json("transport/link/tls"))
    assert {"root_ca_certificate", "enable_mtls", "connect_certificate", "listen_certificate"} <= set(tls)
    assert "eclipse-zenoh==1.10.2" in PYPROJECT["project"]["dependencies"]


# --- the same processes without containers ------------------------------------------------------------------


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    write_pki(out)
    return out


@pytest.fixture
def ground_router(pki, tmp_path):
    """The ground router's own config file, its container paths pointed at the test PKI."""
    port = free_port()
    text = (DEPLOY / "zenoh" / "router.tls.json5").read_text()
    text = text.replace("/etc/zenoh/certs", str(pki)).replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}")
    path = tmp_path / "router.json5"
    path.write_text(text)
    with zenoh.open(zenoh.Config.from_file(str(path))) as session:
        yield port


def _session_of(svc: dict, pki: Path, port: int) -> zenoh.Session:
    """A compose service's Zenoh session as its own parser builds it, dialling the test router."""
    argv = [a.replace(CERTS_IN_CONTAINER, str(pki)) for a in svc["command"]]
    argv = [a for i, a in enumerate(argv) if a != "--connect" and (i == 0 or argv[i - 1] != "--connect")]
    module = importlib.import_module(SCRIPTS[argv[0]].split(":")[0])
    args = module.build_parser().parse_args([*argv[1:], "--connect", f"tls/127.0.0.1:{port}"])
    env = {}
    mounts = {v["target"]: v for v in svc["volumes"]}
    if "/etc/dovesei/zenoh.json5" in mounts:
        env[ENV_CONFIG] = mounts["/etc/dovesei/zenoh.json5"]["source"]
    return zenoh.open(zenoh_config_from_args(args, env=env))


def test_split_services_connect_and_their_acl_holds(pki, ground_router) -> None:
    port = ground_router
    services = {**_services("compose.ground.yaml"), **_services("compose.onboard.yaml")}
    sessions = {name: _session_of(svc, pki, port) for name, svc in services.items()}
    got: dict[str, list[bytes]] = {"heatmap": [], "camera": [], "cmd": [], "odometry": []}
    lock = threading.Lock()

    def catcher(topic):
        def on(sample):
            with lock:
                got[topic].append(sample.payload.to_bytes())
        return on
    subs = [sessions["controller"].declare_subscriber(keys.heatmap("uav1"), catcher("heatmap")),
            sessions["segmenter"].declare_subscriber(keys.camera("*"), catcher("camera")),
            sessions["controller"].declare_subscriber(keys.odometry("uav1"), catcher("odometry"))]
    try:
        for s in sessions.values():
            assert wait_until(lambda s=s: any(True for _ in s.info.routers_zid()), 5.0)

        def delivered(sender, topic, payload):
            return wait_until(lambda: (sessions[sender].put(f"dovesei/uav1/{topic}", payload),
                                       payload in got[topic])[1], 5.0, poll_s=0.05)
        assert delivered("segmenter", "heatmap", b"hm")  # ground -> vehicle
        assert delivered("camera", "camera", b"frame")  # vehicle -> ground
        # The camera's certificate may not pose as the segmenter.
        for i in range(10):
            sessions["camera"].put(keys.heatmap("uav1"), f"forged-{i}".encode())
        list(sessions["camera"].liveliness().get(keys.alive("uav1", "*"), timeout=0.5))  # its puts are routed
        assert delivered("segmenter", "heatmap", b"hm2")
        assert not [p for p in got["heatmap"] if p.startswith(b"forged")]
        # The camera's visual velocity reaches the controller; nobody else may publish one.
        assert delivered("camera", "odometry", b"odo")
        for i in range(10):
            sessions["segmenter"].put(keys.odometry("uav1"), f"forged-{i}".encode())
        list(sessions["segmenter"].liveliness().get(keys.alive("uav1", "*"), timeout=0.5))
        assert delivered("camera", "odometry", b"odo2")
        assert not [p for p in got["odometry"] if p.startswith(b"forged")]
    finally:
        for sub in subs:
            sub.undeclare()
        for s in sessions.values():
            s.close()


def test_readme_onboard_commands_are_secured_clients() -> None:
    """The README's by-hand onboard commands: TLS clients without multicast, flags the parsers accept."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Flying a real autopilot", 1)[1].split("\n## ", 1)[0]
    blocks = [b.split("```", 1)[0] for b in section.split("```sh")[1:]]
    block = next(b for b in blocks if ".venv/bin/dovesei-controller" in b).replace("\\\n", " ")
    variables = dict(re.findall(r'^(\w+)="([^"]*)"$', block, flags=re.M))
    commands = [line for line in block.splitlines() if line.startswith(".venv/bin/dovesei-")]
    assert {c.split()[0] for c in commands} == {".venv/bin/dovesei-controller", ".venv/bin/dovesei-camera"}
    for line in commands:
        argv = shlex.split(re.sub(r"\$(\w+)", lambda m: variables[m.group(1)], line))
        script = argv[0].removeprefix(".venv/bin/")
        module = importlib.import_module(SCRIPTS[script].split(":")[0])
        args = module.build_parser().parse_args(argv[1:])
        assert args.mode == "client" and args.no_multicast_scouting, line
        assert args.connect and all(ep.startswith("tls/") for ep in args.connect), line
        role = script.removeprefix("dovesei-")
        assert str(args.tls_cert).endswith(f"{role}.pem") and str(args.tls_key).endswith(f"{role}.key"), line
