"""`dovesei certs`: a certificate authority, one certificate per role, and the router's ACL.

Zenoh's mutual TLS admits every certificate the CA signed; the access-control list decides what
each one may do. The list here is deny by default, and its subjects are the certificates'
common names, one role per service:

    role        may put                         may subscribe to
    controller  cmd, status, state (autopilot)  heatmap, state, odometry
    segmenter   heatmap (and segment replies)   camera, prompts (and answers segment queries)
    sim         camera, state, episode,         cmd, state, status (the hand-over, external pose)
                odometry
    camera      camera, odometry                state
    operator    prompts (and segment queries)   status, episode, heatmap, state, camera
    monitor     nothing                         everything (`dovesei up`, `dovesei health`)

Every role may declare its own liveliness token and ask which tokens exist. The router's own
certificate (`router`) names the host names and addresses clients dial (`--router-name`).

    dovesei certs --out certs/ --router-name ground.local --router-name 192.168.1.10

writes `ca.pem`, `<role>.pem` + `<role>.key` for each role and the router, and
`router.json5` (TLS listener + ACL) pointing at them; the CA's key (`ca.key`) stays with whoever
issues certificates and should not travel to a vehicle. Keys are written readable by the owner only.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import json
import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import keys
from dovesei.shared.errors import ConfigError

ROUTER = "router"
DEFAULT_ROUTER_NAMES = ("router", "localhost", "127.0.0.1")
DEFAULT_LISTEN = "tls/0.0.0.0:7447"
DEFAULT_DAYS = 825  # the longest leaf lifetime common TLS stacks accept without complaint


@dataclass(frozen=True)
class Role:
    """What one service may do on the network; topics are the `keys.TOPICS` names."""

    puts: tuple[str, ...] = ()
    subscribes: tuple[str, ...] = ()
    answers: tuple[str, ...] = ()  # queryables it declares (and replies it sends)
    asks: tuple[str, ...] = ()  # queryables it queries
    alive_as: tuple[str, ...] = ()  # liveliness tokens it may declare (`keys.SERVICES`)


ROLES: dict[str, Role] = {
    # The controller owns the autopilot link, so the vehicle's state in flight comes from it.
    # It flies on (or feeds the EKF with) the camera's visual velocity, which only the camera (or
    # the sim in its place) may publish.
    # Its close looks: a crop from the camera (or the sim in its place), scored by the segmenter.
    "controller": Role(puts=("cmd", "status", "state", "look"), subscribes=("heatmap", "state", "odometry"),
                       asks=("crop", "segment"), alive_as=("controller", "mavlink")),
    "segmenter": Role(puts=("heatmap",), subscribes=("camera", "prompts"), answers=("segment",),
                      alive_as=("segmenter",)),
    # The sim hears the controller's status for its hand-over in external-pose mode (sim.judge).
    "sim": Role(puts=("camera", "state", "episode", "odometry"), subscribes=("cmd", "state", "status"),
                answers=("crop",), alive_as=("sim",)),
    "camera": Role(puts=("camera", "odometry"), subscribes=("state",), answers=("crop",), alive_as=("camera",)),
    "operator": Role(puts=("prompts",), subscribes=("status", "episode", "heatmap", "state", "camera", "look"),
                     asks=("segment",)),
    "monitor": Role(subscribes=tuple(t for t in keys.TOPICS if t not in ("segment", "crop"))),
}


def _topic_keys(vehicle: str, topics: Iterable[str]) -> list[str]:
    return [f"{keys.ROOT}/{vehicle}/{t}" for t in topics]


def acl_config(vehicle: str = keys.ANY_VEHICLE, roles: dict[str, Role] | None = None) -> dict:
    """The `access_control` section of the router's config: deny by default, one subject per role.

    `vehicle` narrows every key to one vehicle (a ground station serving one drone); the default
    `*` lets the same certificates serve a fleet.
    """
    if vehicle != keys.ANY_VEHICLE:
        keys.check_vehicle_id(vehicle)
    roles = ROLES if roles is None else roles
    rules, subjects, policies = [], [], []

    def rule(rid: str, messages: Sequence[str], flow: str, key_exprs: list[str]) -> str:
        rules.append({"id": rid, "messages": list(messages), "flows": [flow], "permission": "allow",
                      "key_exprs": key_exprs})
        return rid

    for name, role in roles.items():
        own: list[str] = []
        if role.puts:
            own.append(rule(f"{name}-put", ["put"], "ingress", _topic_keys(vehicle, role.puts)))
            # A publisher learns who subscribes to its key from the router, and sends nothing
            # when it hears of nobody: the subscribers' declarations must reach it.
            own.append(rule(f"{name}-put-matching", ["declare_subscriber"], "egress", _topic_keys(vehicle, role.puts)))
        if role.subscribes:
            # Declaring the subscription comes in; the samples it asked for go out to it.
            own.append(rule(f"{name}-subscribe", ["declare_subscriber"], "ingress", _topic_keys(vehicle, role.subscribes)))
            own.append(rule(f"{name}-receive", ["put", "delete"], "egress", _topic_keys(vehicle, role.subscribes)))
        if role.answers:
            own.append(rule(f"{name}-queryable", ["declare_queryable", "reply"], "ingress",
                            _topic_keys(vehicle, role.answers)))
            own.append(rule(f"{name}-queried", ["query"], "egress", _topic_keys(vehicle, role.answers)))
        if role.asks:
            own.append(rule(f"{name}-ask", ["query"], "ingress", _topic_keys(vehicle, role.asks)))
            own.append(rule(f"{name}-ask-matching", ["declare_queryable"], "egress", _topic_keys(vehicle, role.asks)))
            own.append(rule(f"{name}-answered", ["reply"], "egress", _topic_keys(vehicle, role.asks)))
        if role.alive_as:
            own.append(rule(f"{name}-alive", ["liveliness_token"], "ingress",
                            [f"{keys.ROOT}/{vehicle}/alive/{s}" for s in role.alive_as]))
        # Everyone may ask who is alive (health checks, `up`, the sim waiting for the controller).
        alive_all = [f"{keys.ROOT}/{vehicle}/alive/*"]
        own.append(rule(f"{name}-liveliness-ask", ["liveliness_query", "declare_liveliness_subscriber"], "ingress",
                        alive_all))
        own.append(rule(f"{name}-liveliness-hear", ["liveliness_token", "reply"], "egress", alive_all))
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": name, "rules": own, "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def tls_section(directory: str, cert: str, *, listen: bool, connect: bool, verify_name: bool = True) -> dict:
    """`transport.link.tls` for a process holding `<cert>.pem`/`<cert>.key` from `directory`."""
    tls: dict = {"root_ca_certificate": f"{directory}/ca.pem", "enable_mtls": True}
    if listen:
        tls |= {"listen_certificate": f"{directory}/{cert}.pem", "listen_private_key": f"{directory}/{cert}.key"}
    if connect:
        tls |= {"connect_certificate": f"{directory}/{cert}.pem", "connect_private_key": f"{directory}/{cert}.key",
                "verify_name_on_connect": verify_name}
    return tls


def router_config(directory: str, *, listen: Sequence[str] = (DEFAULT_LISTEN,),
                  vehicle: str = keys.ANY_VEHICLE) -> dict:
    """A complete router config: TLS only, mutual, the ACL, no multicast."""
    for ep in listen:
        if not ep.startswith("tls/"):
            raise ConfigError(f"router endpoint {ep!r}: a secured router listens on tls/ endpoints only")
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"protocols": ["tls"], "tls": tls_section(directory, ROUTER, listen=True, connect=False)}},
        "access_control": acl_config(vehicle),
    }


def router_json5(conf: dict) -> str:
    """A router config as JSON5 text a person can review: one ACL rule, subject or policy per line."""
    conf = dict(conf)
    acl = conf.pop("access_control", None)
    text = json.dumps(conf, indent=2)
    if acl is None:
        return text + "\n"
    lines = [text[:-2] + ",", '  "access_control": {', f'    "enabled": {json.dumps(acl["enabled"])},',
             f'    "default_permission": {json.dumps(acl["default_permission"])},']
    for part in ("rules", "subjects", "policies"):
        lines += [f'    "{part}": [', *(f"      {json.dumps(item)}," for item in acl[part]), "    ],"]
    return "\n".join([*lines, "  }", "}"]) + "\n"


# --- certificates -------------------------------------------------------------------------------------


def _crypto():
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:
        raise ConfigError("dovesei certs needs the 'cryptography' package: pip install 'dovesei[trust]'") from None
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


@dataclass(frozen=True)
class Issued:
    """PEM bytes of one certificate and its private key."""

    cert_pem: bytes
    key_pem: bytes


def make_ca(common_name: str = "dovesei-ca", days: int = 3650) -> Issued:
    """A self-signed CA (ECDSA P-256) that may sign leaf certificates only (path length 0)."""
    x509, hashes, serialization, ec, _, NameOID = _crypto()
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = dt.datetime.now(dt.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return Issued(cert.public_bytes(serialization.Encoding.PEM), _key_pem(key))


def make_leaf(ca: Issued, common_name: str, names: Sequence[str] = (), days: int = DEFAULT_DAYS) -> Issued:
    """A certificate for one role: the CN is the ACL subject, `names` (DNS or IP) what clients dial."""
    x509, hashes, serialization, ec, EKU, NameOID = _crypto()
    ca_cert = x509.load_pem_x509_certificate(ca.cert_pem)
    ca_key = serialization.load_pem_private_key(ca.key_pem, password=None)
    key = ec.generate_private_key(ec.SECP256R1())
    sans: list = []
    for n in dict.fromkeys([common_name, *names]):  # de-duplicated, order kept
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            sans.append(x509.DNSName(n))
    now = dt.datetime.now(dt.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH]), critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    return Issued(cert.public_bytes(serialization.Encoding.PEM), _key_pem(key))


def _key_pem(key) -> bytes:
    _, _, serialization, _, _, _ = _crypto()
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _write(path: Path, data: bytes, private: bool) -> None:
    # Created with the final mode, so a key is never readable by others even for a moment.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600 if private else 0o644)


def write_pki(out: Path, *, roles: Iterable[str] = tuple(ROLES), router_names: Sequence[str] = DEFAULT_ROUTER_NAMES,
              days: int = DEFAULT_DAYS, vehicle: str = keys.ANY_VEHICLE, config_dir: str | None = None,
              listen: Sequence[str] = (DEFAULT_LISTEN,), ca: Issued | None = None, force: bool = False) -> dict[str, Path]:
    """Write the CA, the router's and each role's certificate, and `router.json5`; returns the paths.

    An existing CA in `out` is reused (new roles join the same trust), unless `ca` is given.
    `config_dir` is where the files will be found at run time (e.g. a container's mount point);
    by default `out` itself.
    """
    roles = list(roles)
    unknown = [r for r in roles if r not in ROLES]
    if unknown:
        raise ConfigError(f"unknown role(s) {unknown}: choose from {', '.join(ROLES)}")
    if not 1 <= days <= 3650:
        raise ConfigError(f"--days {days}: choose 1..3650")
    if vehicle != keys.ANY_VEHICLE:
        keys.check_vehicle_id(vehicle)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    ca_cert, ca_key = out / "ca.pem", out / "ca.key"
    if ca is None and ca_cert.exists() and ca_key.exists() and not force:
        ca = Issued(ca_cert.read_bytes(), ca_key.read_bytes())
    elif ca is None:
        ca = make_ca()
    if force or not ca_cert.exists() or ca_cert.read_bytes() != ca.cert_pem:
        _write(ca_cert, ca.cert_pem, private=False)
        _write(ca_key, ca.key_pem, private=True)
    written["ca"] = ca_cert
    for name in [ROUTER, *roles]:
        leaf = make_leaf(ca, name, router_names if name == ROUTER else (), days=days)
        _write(out / f"{name}.pem", leaf.cert_pem, private=False)
        _write(out / f"{name}.key", leaf.key_pem, private=True)
        written[name] = out / f"{name}.pem"
    conf = router_config(config_dir or str(out.resolve()), listen=listen, vehicle=vehicle)
    (out / "router.json5").write_text(
        "// Written by `dovesei certs`: the secured Zenoh router (mutual TLS + ACL, deny by default).\n"
        + router_json5(conf))
    written["router.json5"] = out / "router.json5"
    return written


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei certs", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="folder for the CA, certificates and router.json5")
    p.add_argument("--router-name", action="append", default=[], metavar="NAME",
                   help="a host name or IP address clients use to reach the router (repeatable; "
                        f"default {', '.join(DEFAULT_ROUTER_NAMES)})")
    p.add_argument("--role", action="append", default=[], choices=list(ROLES),
                   help="issue only these roles (repeatable; default all)")
    p.add_argument("--vehicle-id", default=keys.ANY_VEHICLE, help="narrow the ACL to one vehicle (default: any)")
    p.add_argument("--days", type=int, default=DEFAULT_DAYS, help=f"leaf certificate lifetime (default {DEFAULT_DAYS})")
    p.add_argument("--config-dir", help="where the files will be at run time, for router.json5 (default: --out)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"the router's TLS endpoint(s) in router.json5 (default {DEFAULT_LISTEN})")
    p.add_argument("--force", action="store_true", help="make a new CA even if --out already holds one")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        written = write_pki(args.out, roles=args.role or tuple(ROLES),
                            router_names=args.router_name or DEFAULT_ROUTER_NAMES, days=args.days,
                            vehicle=args.vehicle_id, config_dir=args.config_dir,
                            listen=args.listen or (DEFAULT_LISTEN,), force=args.force)
    except (ConfigError, OSError) as exc:
        print(f"dovesei certs: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {', '.join(p.name for p in written.values())} to {args.out}")
    print("keep ca.key off the vehicle; give each service its own <role>.pem and <role>.key with ca.pem")
    return 0


if __name__ == "__main__":
    sys.exit(main())
