"""The Zenoh flag group's secured mode: --tls-ca/--tls-cert/--tls-key become mutual TLS, TLS only."""

from __future__ import annotations

import argparse
import json

import pytest

from dovesei.certs import write_pki
from dovesei.shared.errors import ConfigError
from dovesei.shared.zconfig import ENV_CONFIG, add_zenoh_args, zenoh_config_from_args


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    out = tmp_path_factory.mktemp("pki")
    write_pki(out, roles=["sim"])
    return out


def _parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_zenoh_args(p)
    return p.parse_args(argv)


def _get(conf, key):
    return json.loads(conf.get_json(key))


def test_tls_flags_make_a_mutual_tls_client(pki) -> None:
    args = _parse(["--mode", "client", "--connect", "tls/10.0.0.2:7447", "--tls-ca", str(pki / "ca.pem"),
                   "--tls-cert", str(pki / "sim.pem"), "--tls-key", str(pki / "sim.key")])
    conf = zenoh_config_from_args(args, env={})
    tls = _get(conf, "transport/link/tls")
    assert tls["root_ca_certificate"] == str((pki / "ca.pem").resolve())
    assert tls["connect_certificate"].endswith("sim.pem") and tls["connect_private_key"].endswith("sim.key")
    assert tls["enable_mtls"] is True and tls["listen_certificate"] is None  # a client does not listen
    assert _get(conf, "transport/link/protocols") == ["tls"]


def test_a_secured_peer_drops_zenohs_default_plain_listener(pki) -> None:
    args = _parse(["--connect", "tls/127.0.0.1:7447", "--tls-ca", str(pki / "ca.pem"),
                   "--tls-cert", str(pki / "sim.pem"), "--tls-key", str(pki / "sim.key")])
    conf = zenoh_config_from_args(args, env={})
    assert _get(conf, "listen/endpoints") == []


def test_a_secured_listener_presents_its_certificate(pki) -> None:
    args = _parse(["--mode", "router", "--listen", "tls/0.0.0.0:7447", "--tls-ca", str(pki / "ca.pem"),
                   "--tls-cert", str(pki / "router.pem"), "--tls-key", str(pki / "router.key")])
    tls = _get(zenoh_config_from_args(args, env={}), "transport/link/tls")
    assert tls["listen_certificate"].endswith("router.pem") and tls["listen_private_key"].endswith("router.key")


@pytest.mark.parametrize(("extra", "message"), [
    (["--connect", "tcp/10.0.0.2:7447"], "not TLS"),
    (["--listen", "tcp/0.0.0.0:7447"], "not TLS"),
    (["--mode", "router"], "not TLS"),  # a router's default listener is plain: say so, do not open it
])
def test_secured_mode_refuses_plain_endpoints(pki, extra, message) -> None:
    args = _parse([*extra, "--tls-ca", str(pki / "ca.pem"), "--tls-cert", str(pki / "sim.pem"),
                   "--tls-key", str(pki / "sim.key")])
    with pytest.raises(ConfigError, match=message):
        zenoh_config_from_args(args, env={})


def test_tls_flags_name_what_is_missing(pki, tmp_path) -> None:
    with pytest.raises(ConfigError, match="missing --tls-cert, --tls-key"):
        zenoh_config_from_args(_parse(["--tls-ca", str(pki / "ca.pem")]), env={})
    with pytest.raises(ConfigError, match="--tls-key .*no such file"):
        zenoh_config_from_args(_parse(["--tls-ca", str(pki / "ca.pem"), "--tls-cert", str(pki / "sim.pem"),
                                       "--tls-key", str(tmp_path / "nope.key")]), env={})


def test_zenoh_config_env_file_still_applies_under_the_flags(pki, tmp_path) -> None:
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "client", connect: { endpoints: ["tls/127.0.0.1:7447"] } }')
    args = _parse(["--tls-ca", str(pki / "ca.pem"), "--tls-cert", str(pki / "sim.pem"), "--tls-key", str(pki / "sim.key")])
    conf = zenoh_config_from_args(args, env={ENV_CONFIG: str(f)})
    assert _get(conf, "mode") == "client" and _get(conf, "connect/endpoints") == ["tls/127.0.0.1:7447"]
    assert _get(conf, "transport/link/tls/enable_mtls") is True


def test_parsers_without_the_tls_flags_still_work() -> None:
    args = argparse.Namespace(mode="peer", connect=[], listen=[], zenoh_config=None, no_multicast_scouting=True,
                              no_shm=False)
    assert _get(zenoh_config_from_args(args, env={}), "mode") == "peer"
