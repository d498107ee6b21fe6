"""One place that turns flags, a config file and `ZENOH_CONFIG` into a `zenoh.Config`.

Precedence, lowest first: Zenoh's defaults, the file named by `ZENOH_CONFIG`, the file given with
`--zenoh-config`, then the individual flags (`--mode`, `--connect`, `--listen`,
`--no-multicast-scouting`, `--no-shm`). Every service and test builds its config here.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
from collections.abc import Mapping, Sequence
from pathlib import Path

import zenoh

from dovesei.shared.errors import ConfigError

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


def zenoh_config(*, mode: str | None = None, connect: Sequence[str] = (), listen: Sequence[str] = (),
                 config_file: Path | str | None = None, multicast_scouting: bool | None = None,
                 shared_memory: bool | None = None, env: Mapping[str, str] | None = None) -> zenoh.Config:
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
    return conf


def zenoh_config_from_args(args: argparse.Namespace, env: Mapping[str, str] | None = None) -> zenoh.Config:
    return zenoh_config(mode=args.mode, connect=args.connect, listen=args.listen, config_file=args.zenoh_config,
                        multicast_scouting=False if args.no_multicast_scouting else None,
                        shared_memory=False if args.no_shm else None, env=env)


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that nothing is bound to right now (TCP by default, SOCK_DGRAM for UDP).

    For loopback peers, tests and benchmarks; another process may still take it before use.
    """
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
