"""The secured split link: mutual TLS admits certificates of our CA, the ACL authorises each role.

In the style of zenoh's own authentication tests: a router (a Python session in router mode, the
same config a zenohd would load) on a free loopback port, clients with certificates from
`dovesei certs`, and for each denial the allowed path measured live in the same test, so a
"nothing arrived" can only mean "refused".
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from cryptography import x509

from dovesei.certs import ROLES, Issued, acl_config, main, make_leaf, router_config, write_pki
from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.zconfig import TlsFiles, _insert, free_port, zenoh_config

from tests.shared.samples import sample_messages

VEHICLE = "uav1"


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pki")
    write_pki(out)
    # An intruder holding a certificate our CA really signed, under a name no policy lists.
    ca = Issued((out / "ca.pem").read_bytes(), (out / "ca.key").read_bytes())
    leaf = make_leaf(ca, "intruder")
    (out / "intruder.pem").write_bytes(leaf.cert_pem)
    (out / "intruder.key").write_bytes(leaf.key_pem)
    return out


@pytest.fixture(scope="module")
def other_pki(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("other")
    write_pki(out, roles=["controller"])
    return out


@pytest.fixture
def router(pki) -> Iterator[int]:
    port = free_port()
    session = zenoh.open(zenoh.Config.from_json5(json.dumps(router_config(str(pki), listen=[f"tls/127.0.0.1:{port}"]))))
    try:
        yield port
    finally:
        session.close()


def _conf(port: int, ca: Path | None, cert: Path | None, key: Path | None, scheme: str = "tls") -> zenoh.Config:
    tls = TlsFiles(ca, cert, key) if cert is not None else None
    conf = zenoh_config(mode="client", connect=[f"{scheme}/127.0.0.1:{port}"], multicast_scouting=False, env={}, tls=tls)
    if tls is None and ca is not None:
        _insert(conf, "transport/link/tls/root_ca_certificate", str(ca))
    # Fail fast instead of retrying for ever: a refused link is what these tests look for.
    _insert(conf, "connect/timeout_ms", 3000)
    _insert(conf, "connect/exit_on_failure", True)
    return conf


def _client(pki: Path, port: int, role: str) -> zenoh.Session:
    return zenoh.open(_conf(port, pki / "ca.pem", pki / f"{role}.pem", pki / f"{role}.key"))


class Catcher:
    """A subscriber collecting payloads, with a wait that has a deadline."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self.got: list[bytes] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.got.append(sample.payload.to_bytes())

    def has(self, payload: bytes) -> bool:
        with self._lock:
            return payload in self.got

    def close(self) -> None:
        self._sub.undeclare()


def _delivered(sender: zenoh.Session, key: str, catcher: Catcher, payload: bytes, timeout_s: float = 5.0) -> bool:
    """Put until the catcher has it (the subscription may still be propagating)."""
    return wait_until(lambda: (sender.put(key, payload), catcher.has(payload))[1], timeout_s, poll_s=0.05)


def _flush(session: zenoh.Session) -> None:
    """A round trip through the router: everything this session put before it has been routed."""
    list(session.liveliness().get(keys.alive(VEHICLE, "*"), timeout=0.5))


# --- authentication: who may connect -------------------------------------------------------------------


def test_a_role_certificate_of_our_ca_connects(pki, router) -> None:
    with _client(pki, router, "controller") as s:
        assert wait_until(lambda: any(True for _ in s.info.routers_zid()), 5.0)


def test_no_certificate_cannot_connect(pki, router) -> None:
    with pytest.raises(zenoh.ZError):
        zenoh.open(_conf(router, pki / "ca.pem", None, None))


def test_a_certificate_of_another_ca_cannot_connect(pki, other_pki, router) -> None:
    # It even trusts our router: the router is what refuses it.
    with pytest.raises(zenoh.ZError):
        zenoh.open(_conf(router, pki / "ca.pem", other_pki / "controller.pem", other_pki / "controller.key"))


def test_plain_tcp_to_the_tls_port_is_refused(router) -> None:
    with pytest.raises(zenoh.ZError):
        zenoh.open(_conf(router, None, None, None, scheme="tcp"))


def test_secured_mode_refuses_a_plain_endpoint_before_opening(pki) -> None:
    with pytest.raises(ConfigError, match="not TLS"):
        zenoh_config(mode="client", connect=["tcp/127.0.0.1:7447"], env={},
                     tls=TlsFiles(pki / "ca.pem", pki / "sim.pem", pki / "sim.key"))
    with pytest.raises(ConfigError, match="missing --tls-key"):
        TlsFiles.from_flags(pki / "ca.pem", pki / "sim.pem", None)


# --- authorisation: what each role may do ---------------------------------------------------------------


def test_allowed_roles_work_end_to_end(pki, router) -> None:
    frame, state, heatmap, cmd = (encode(m) for m in (sample_messages()[0], sample_messages()[1],
                                                      sample_messages()[2], sample_messages()[4]))
    sessions = {r: _client(pki, router, r) for r in ("sim", "segmenter", "controller", "operator")}
    catchers = []
    try:
        def catch(role: str, key: str) -> Catcher:
            catchers.append(Catcher(sessions[role], key))
            return catchers[-1]
        on_seg = catch("segmenter", keys.camera(keys.ANY_VEHICLE))
        on_ctl = catch("controller", keys.heatmap(VEHICLE))
        on_ctl_state = catch("controller", keys.state(VEHICLE))
        on_sim = catch("sim", keys.cmd(VEHICLE))
        on_prompts = catch("segmenter", keys.prompts(VEHICLE))
        on_episode = catch("operator", keys.episode(VEHICLE))
        assert _delivered(sessions["sim"], keys.camera(VEHICLE), on_seg, frame)
        assert _delivered(sessions["sim"], keys.state(VEHICLE), on_ctl_state, state)
        assert _delivered(sessions["segmenter"], keys.heatmap(VEHICLE), on_ctl, heatmap)
        assert _delivered(sessions["controller"], keys.cmd(VEHICLE), on_sim, cmd)
        assert _delivered(sessions["operator"], keys.prompts(VEHICLE), on_prompts, encode(sample_messages()[6]))
        assert _delivered(sessions["sim"], keys.episode(VEHICLE), on_episode, encode(sample_messages()[7]))
        # Request-reply segmentation: the operator asks, the segmenter answers; nobody else may answer.
        queryable = sessions["segmenter"].declare_queryable(
            keys.segment(keys.ANY_VEHICLE), lambda q: q.reply(str(q.key_expr), b"heatmap-reply"))
        try:
            assert wait_until(lambda: any(r.ok is not None and r.ok.payload.to_bytes() == b"heatmap-reply"
                                          for r in sessions["operator"].get(keys.segment(VEHICLE), timeout=0.5)), 5.0)
        finally:
            queryable.undeclare()
        token = sessions["controller"].liveliness().declare_token(keys.alive(VEHICLE, "controller"))
        try:
            with _client(pki, router, "monitor") as monitor:
                assert wait_until(lambda: any(r.ok is not None for r in monitor.liveliness().get(
                    keys.alive(VEHICLE, "controller"), timeout=0.5)), 5.0)
        finally:
            token.undeclare()
    finally:
        for c in catchers:
            c.close()
        for s in sessions.values():
            s.close()


@pytest.mark.parametrize(("forger", "topic"), [
    ("intruder", "cmd"),  # a valid certificate of our CA, a name no policy lists
    ("segmenter", "cmd"),  # a listed role, not its key
    ("camera", "cmd"),
    ("controller", "episode"),  # a forged "safe" made `up` exit 0 at 290 m
    ("segmenter", "prompts"),
    ("controller", "heatmap"),
    ("sim", "heatmap"),
])
def test_a_role_cannot_put_another_roles_key(pki, router, forger: str, topic: str) -> None:
    owner = {"cmd": "controller", "episode": "sim", "prompts": "operator", "heatmap": "segmenter"}[topic]
    reader = {"cmd": "sim", "episode": "monitor", "prompts": "segmenter", "heatmap": "controller"}[topic]
    key = f"{keys.ROOT}/{VEHICLE}/{topic}"
    with _client(pki, router, owner) as honest, _client(pki, router, reader) as rx, \
            _client(pki, router, forger) as bad:
        catcher = Catcher(rx, key)
        try:
            assert _delivered(honest, key, catcher, b"honest-before")  # the path is live
            for i in range(20):
                bad.put(key, f"forged-{i}".encode())
            _flush(bad)
            assert _delivered(honest, key, catcher, b"honest-after")
            assert not [p for p in catcher.got if p.startswith(b"forged")], f"{forger} put {topic}"
        finally:
            catcher.close()


def test_only_the_segmenter_may_answer_segment_queries(pki, router) -> None:
    with _client(pki, router, "operator") as asker, _client(pki, router, "segmenter") as seg, \
            _client(pki, router, "controller") as impostor:
        real = seg.declare_queryable(keys.segment(VEHICLE), lambda q: q.reply(str(q.key_expr), b"real"))
        fake = impostor.declare_queryable(keys.segment(VEHICLE), lambda q: q.reply(str(q.key_expr), b"fake"))
        try:
            answers: list[bytes] = []

            def ask() -> bool:
                answers.extend(r.ok.payload.to_bytes() for r in asker.get(keys.segment(VEHICLE), timeout=0.5,
                                                                       consolidation=zenoh.ConsolidationMode.NONE)
                               if r.ok is not None)
                return b"real" in answers
            assert wait_until(ask, 5.0)
            assert b"fake" not in answers
        finally:
            fake.undeclare()
            real.undeclare()


def test_an_unlisted_name_reads_nothing(pki, router) -> None:
    with _client(pki, router, "controller") as ctl, _client(pki, router, "sim") as sim, \
            _client(pki, router, "intruder") as spy:
        honest, sniffed = Catcher(sim, keys.cmd(VEHICLE)), Catcher(spy, keys.cmd(VEHICLE))
        try:
            assert _delivered(ctl, keys.cmd(VEHICLE), honest, b"c1")
            _flush(ctl)
            assert _delivered(ctl, keys.cmd(VEHICLE), honest, b"c2")
            assert sniffed.got == []
        finally:
            honest.close()
            sniffed.close()


# --- the ACL itself ---------------------------------------------------------------------------------------


def test_acl_is_deny_by_default_with_one_subject_per_role() -> None:
    acl = acl_config()
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert [s["cert_common_names"] for s in acl["subjects"]] == [[r] for r in ROLES]
    puts = {rule["id"].removesuffix("-put"): rule["key_exprs"] for rule in acl["rules"] if rule["id"].endswith("-put")}
    # The controller also publishes each close look (the crop and its heatmap) for the operator.
    assert puts["controller"] == ["dovesei/*/cmd", "dovesei/*/status", "dovesei/*/state", "dovesei/*/look"]
    assert [r for r, ks in puts.items() if "dovesei/*/look" in ks] == ["controller"]
    # Crops are asked for by the controller alone and answered by whatever holds the camera.
    asks = {rule["id"].removesuffix("-ask"): rule["key_exprs"] for rule in acl["rules"] if rule["id"].endswith("-ask")}
    answers = {rule["id"].removesuffix("-queryable"): rule["key_exprs"] for rule in acl["rules"]
               if rule["id"].endswith("-queryable")}
    assert [r for r, ks in asks.items() if "dovesei/*/crop" in ks] == ["controller"]
    assert sorted(r for r, ks in answers.items() if "dovesei/*/crop" in ks) == ["camera", "sim"]
    assert puts["segmenter"] == ["dovesei/*/heatmap"]
    assert "dovesei/*/cmd" not in [k for r, ks in puts.items() if r != "controller" for k in ks]
    assert [r for r, ks in puts.items() if "dovesei/*/episode" in ks] == ["sim"]
    assert [r for r, ks in puts.items() if "dovesei/*/prompts" in ks] == ["operator"]
    narrow = acl_config("uav7")
    assert all(k.startswith("dovesei/uav7/") for rule in narrow["rules"] for k in rule["key_exprs"])


def test_dovesei_certs_command_writes_a_usable_pki(tmp_path) -> None:
    out = tmp_path / "certs"
    assert main(["--out", str(out), "--router-name", "ground.local", "--router-name", "10.0.0.2"]) == 0
    for role in ("router", *ROLES):
        assert (out / f"{role}.pem").is_file() and (out / f"{role}.key").stat().st_mode & 0o077 == 0
    assert (out / "ca.key").stat().st_mode & 0o077 == 0
    conf = zenoh.Config.from_file(str(out / "router.json5"))
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"
    router_cert = x509.load_pem_x509_certificate((out / "router.pem").read_bytes())
    san = router_cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "ground.local" in san.get_values_for_type(x509.DNSName)
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.2"]
    ca_before = (out / "ca.pem").read_bytes()
    assert main(["--out", str(out), "--role", "camera"]) == 0  # a new role joins the same CA
    assert (out / "ca.pem").read_bytes() == ca_before
    with pytest.raises(SystemExit):
        main(["--out", str(out), "--role", "pilot"])


def test_dovesei_certs_refuses_bad_input(tmp_path, capsys) -> None:
    assert main(["--out", str(tmp_path / "c"), "--days", "0"]) == 1
    assert "--days 0" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "c"), "--vehicle-id", "a/b"]) == 1
    assert "vehicle id" in capsys.readouterr().err


def test_a_role_cannot_declare_another_services_liveliness(pki, router) -> None:
    # A fake "controller alive" would let the sim start an episode nobody steers.
    with _client(pki, router, "segmenter") as seg, _client(pki, router, "monitor") as monitor:
        own = seg.liveliness().declare_token(keys.alive(VEHICLE, "segmenter"))
        fake = seg.liveliness().declare_token(keys.alive(VEHICLE, "controller"))
        try:
            def alive(service: str) -> bool:
                return any(r.ok is not None for r in monitor.liveliness().get(keys.alive(VEHICLE, service), timeout=0.5))
            assert wait_until(lambda: alive("segmenter"), 5.0)  # the path is live
            assert not alive("controller")
        finally:
            fake.undeclare()
            own.undeclare()
