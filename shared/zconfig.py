"""One place that turns flags, a config file and `ZENOH_CONFIG` into a `zenoh.Config`.

Precedence, lowest first: Zenoh's defaults, the file named by `ZENOH_CONFIG`, the file given with
`--zenoh-config`, then the individual flags (`--mode`, `--connect`, `--listen`,
`--no-multicast-scouting`, `--no-shm`, `--tls-ca`/`--tls-cert`/`--tls-key`). Every service and
test builds its config here.

Secured mode (`--tls-*`, certificates from `dovesei certs`): mutual TLS with the process's role
certificate, for connecting and (router or `--listen`) for listening; plain `tcp/` endpoints are
then refused, so a typo cannot fall back to an open link. What a role may do is the router's ACL.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from dovesei.shared.errors import ConfigError, DoveseiError

MODES = ("peer", "client", "router")
ENV_CONFIG = "ZENOH_CONFIG"


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags every entry point accepts."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", choices=MODES, help="Zenoh session mode (default: peer)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    g.add_argument("--zenoh-config", type=Path, metavar="FILE", help="Zenoh JSON5 config file")
    g.add_argument("--no-multicast-scouting", action="store_true",
                   help="do not discover peers by UDP multicast (use with --connect/--listen)")
    g.add_argument("--no-shm", action="store_true", help="disable shared-memory transport")
    g.add_argument("--tls-ca", type=Path, metavar="PEM", help="CA certificate: secured mode (mutual TLS, tls/ endpoints)")
    g.add_argument("--tls-cert", type=Path, metavar="PEM", help="this process's role certificate (from `dovesei certs`)")
    g.add_argument("--tls-key", type=Path, metavar="KEY", help="the private key of --tls-cert")


def zenoh_config(*, mode: str | None = None, connect: Sequence[str] = (), listen: Sequence[str] = (),
                 config_file: Path | str | None = None, multicast_scouting: bool | None = None,
                 shared_memory: bool | None = None, env: Mapping[str, str] | None = None,
                 tls: TlsFiles | None = None) -> zenoh.Config:
    """Build a `zenoh.Config`; a bad value raises `ConfigError` naming it."""
    env = os.environ if env is None else env
    conf = _load_file(env.get(ENV_CONFIG), f"${ENV_CONFIG}") if env.get(ENV_CONFIG) else zenoh.Config()
    if config_file is not None:
        conf = _load_file(str(config_file), "--zenoh-config")
    if mode is not None:
        if mode not in MODES:
            raise ConfigError(f"--mode {mode!r}: choose one of {MODES}")
        _insert(conf, "mode", mode)
    for flag, key, endpoints in (("--connect", "connect/endpoints", connect), ("--listen", "listen/endpoints", listen)):
        if endpoints:
            for ep in endpoints:
                if not isinstance(ep, str) or "/" not in ep:
                    raise ConfigError(f"{flag} {ep!r}: an endpoint looks like tcp/127.0.0.1:7447")
            _insert(conf, key, list(endpoints))
    if multicast_scouting is not None:
        _insert(conf, "scouting/multicast/enabled", bool(multicast_scouting))
    if shared_memory is not None:
        _insert(conf, "transport/shared_memory/enabled", bool(shared_memory))
    if tls is not None:
        _apply_tls(conf, tls)
    return conf


@dataclass(frozen=True)
class TlsFiles:
    """The three PEM files of a secured process: the CA, its role certificate and that key."""

    ca: Path
    cert: Path
    key: Path

    @classmethod
    def from_flags(cls, ca: Path | str | None, cert: Path | str | None, key: Path | str | None) -> TlsFiles | None:
        """None when no flag is given; all three or an error naming the missing ones."""
        given = {"--tls-ca": ca, "--tls-cert": cert, "--tls-key": key}
        if not any(given.values()):
            return None
        missing = [flag for flag, v in given.items() if not v]
        if missing:
            raise ConfigError(f"secured mode needs --tls-ca, --tls-cert and --tls-key; missing {', '.join(missing)}")
        for flag, v in given.items():
            if not Path(v).is_file():
                raise ConfigError(f"{flag} {str(v)!r}: no such file")
        return cls(Path(ca), Path(cert), Path(key))


def _apply_tls(conf: zenoh.Config, tls: TlsFiles) -> None:
    mode = json.loads(conf.get_json("mode") or '"peer"') or "peer"
    for section in ("connect", "listen"):
        endpoints = json.loads(conf.get_json(f"{section}/endpoints") or "null") or []
        defaults = isinstance(endpoints, dict)  # Zenoh's per-mode defaults: {"router": [...], "peer": [...]}
        if defaults:
            endpoints = endpoints.get(mode) or []
        plain = [ep for ep in endpoints if not str(ep).startswith(("tls/", "quic/"))]
        if plain and defaults and not (section == "listen" and mode == "router"):
            _insert(conf, f"{section}/endpoints", [])  # a default plain listener must not stay open
        elif plain:
            raise ConfigError(f"secured mode: {section} endpoint(s) {plain} are not TLS; use tls/HOST:PORT")
    listening = json.loads(conf.get_json("listen/endpoints") or "null") or []
    if isinstance(listening, dict):
        listening = listening.get(mode) or []
    listens = mode == "router" or bool(listening)
    files = {"root_ca_certificate": tls.ca, "connect_certificate": tls.cert, "connect_private_key": tls.key}
    if listens:
        files |= {"listen_certificate": tls.cert, "listen_private_key": tls.key}
    for key, path in files.items():
        _insert(conf, f"transport/link/tls/{key}", str(Path(path).resolve()))
    _insert(conf, "transport/link/tls/enable_mtls", True)
    # Only TLS links: a session that cannot reach the router over TLS must not try anything else.
    _insert(conf, "transport/link/protocols", ["tls"])


def zenoh_config_from_args(args: argparse.Namespace, env: Mapping[str, str] | None = None) -> zenoh.Config:
    # getattr: parsers built before the TLS flags existed (or without them) still work.
    tls = TlsFiles.from_flags(getattr(args, "tls_ca", None), getattr(args, "tls_cert", None),
                              getattr(args, "tls_key", None))
    return zenoh_config(mode=args.mode, connect=args.connect, listen=args.listen, config_file=args.zenoh_config,
                        multicast_scouting=False if args.no_multicast_scouting else None,
                        shared_memory=False if args.no_shm else None, env=env, tls=tls)


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that nothing is bound to right now (TCP by default, SOCK_DGRAM for UDP).

    For loopback peers, tests and benchmarks; another process may still take it before use.
    """
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SessionError(DoveseiError):
    """A Zenoh session that could not be opened: a listen port already taken, a router unreachable."""

    @property
    def address_in_use(self) -> bool:
        """True when a listen endpoint was taken: retrying with another port can succeed."""
        return ADDRESS_IN_USE in str(self)


ADDRESS_IN_USE = "Address already in use"  # the OS's text (EADDRINUSE), which Zenoh's error carries


def open_session(config: zenoh.Config) -> zenoh.Session:
    """`zenoh.open`, with its failure as one SessionError line instead of a ZError traceback."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        # Zenoh appends the Rust source file and line of each layer: noise for an operator.
        text = re.sub(r"\s+at \S+\.rs:\d+\.?", "", " ".join(str(exc).split()))
        raise SessionError(f"cannot open the Zenoh session: {text}") from None


def loopback_config(listen_port: int | None = None, connect_ports: Sequence[int] = (),
                    shared_memory: bool | None = None) -> zenoh.Config:
    """A peer on 127.0.0.1 with multicast scouting off: what tests and `dovesei up` use."""
    return zenoh_config(mode="peer",
                        listen=[f"tcp/127.0.0.1:{listen_port}"] if listen_port else (),
                        connect=[f"tcp/127.0.0.1:{p}" for p in connect_ports],
                        multicast_scouting=False, shared_memory=shared_memory, env={})


def _load_file(path: str, origin: str) -> zenoh.Config:
    if not Path(path).is_file():
        raise ConfigError(f"{origin}: Zenoh config file {path!r} does not exist")
    try:
        return zenoh.Config.from_file(path)
    except Exception as exc:  # zenoh raises its own ZError for parse errors
        raise ConfigError(f"{origin}: Zenoh config file {path!r} is invalid: {exc}") from None


def _insert(conf: zenoh.Config, key: str, value: object) -> None:
    try:
        conf.insert_json5(key, json.dumps(value))
    except Exception as exc:
        raise ConfigError(f"Zenoh config {key} = {value!r} rejected: {exc}") from None
