"""`dovesei up` under a busy host: ports taken between picking and binding, runs started in the
same second.

Seen before the fixes: "Address already in use" for the controller's listener killed 1 run in 6
under load (a port `up` picked was taken before the child bound it), and two `up` started in the
same second wrote into one `runs/up-<second>/`. Here a port is taken on purpose, exactly where
the race put it, and `up` must still fly; folders are claimed by concurrent threads.
"""

from __future__ import annotations

import logging
import socket
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

import dovesei.up as up
from dovesei.shared.zconfig import SessionError, free_port, open_session, zenoh_config
from dovesei.up.options import build_parser, options_from_args

WORLD = "synthetic:size_m=400,seed=1"


def test_claimed_run_folders_are_unique_under_concurrency(tmp_path: Path) -> None:
    base = tmp_path / "runs" / "up-20260101-120000"
    with ThreadPoolExecutor(max_workers=8) as pool:
        folders = list(pool.map(lambda _: up.claim_folder(base), range(8)))
    assert len(set(folders)) == 8 and all(f.is_dir() for f in folders)
    assert base in folders and base.with_name(base.name + "-2") in folders


def test_a_default_out_is_claimed_and_a_given_one_is_used_as_is(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    default = options_from_args(build_parser().parse_args([]))
    given = options_from_args(build_parser().parse_args(["--out", "mine"]))
    assert default.out_unique and default.out.parent == Path("runs") and default.out.name.startswith("up-")
    assert not given.out_unique and given.out == Path("mine")


def test_open_session_names_a_taken_port_in_one_line() -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        with pytest.raises(SessionError) as exc:
            open_session(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False, env={}))
    assert exc.value.address_in_use and str(port) in str(exc.value)
    assert "\n" not in str(exc.value) and ".rs:" not in str(exc.value)


@pytest.mark.slow
def test_up_flies_when_its_ports_are_taken_before_they_are_bound(tmp_path: Path, monkeypatch, caplog) -> None:
    """The race, forced: the monitor's first port and the controller's first port are held by another
    socket when they are bound. `up` picks the monitor's again in-process, restarts the services on
    new ports once the controller reports the taken port, and flies the episode."""
    holders = []

    def taken_port() -> int:
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        s.listen()
        holders.append(s)
        return s.getsockname()[1]

    # up picks the monitor's port first, then sim, segmenter, controller (SERVICES order).
    plan = iter(["taken", "free", "free", "free", "taken"])
    picked: list[int] = []

    def racy_free_port(kind: int = socket.SOCK_STREAM) -> int:
        port = taken_port() if next(plan, "free") == "taken" else free_port(kind)
        picked.append(port)
        return port

    monkeypatch.setattr(up, "free_port", racy_free_port)
    options = options_from_args(build_parser().parse_args([
        "--world", WORLD, "--segmenter", "sim", "--start", "200,200,35", "--time-limit-s", "10", "--no-video",
        "--no-record", "--out", str(tmp_path / "run")]))
    caplog.set_level(logging.INFO, logger="dovesei.up")
    try:
        code = up.run(options, stop=threading.Event())
    finally:
        for s in holders:
            s.close()
    assert code in (up.EXIT_OK, up.EXIT_UNSAFE), caplog.text[-3000:]
    assert (tmp_path / "run" / "report.json").is_file()
    assert f"monitor port {picked[0]} was taken" in caplog.text
    assert f"controller could not listen on port {picked[4]}" in caplog.text
    assert "attempt 2 of 3" in caplog.text
    assert len(picked) == 8  # monitor twice, three services twice
