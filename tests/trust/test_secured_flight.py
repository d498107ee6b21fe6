"""A whole episode over the secured link: the three real services, each a TLS client with its own
role certificate, through a router enforcing the ACL; the result read by a `monitor` certificate.

This is what proves the ACL is not only tight but sufficient: every put, subscription, liveliness
token and query the services really make is allowed for their role (a missing rule would stall the
lockstep episode, and the test would time out instead of reading a verdict).
"""

from __future__ import annotations

import json
import os
import subprocess
import threading
from pathlib import Path

import pytest
import zenoh

from dovesei.certs import router_config, write_pki
from dovesei.shared import keys
from dovesei.shared.codec import decode
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.messages import EpisodeResult
from dovesei.shared.zconfig import TlsFiles, free_port, zenoh_config
from dovesei.up import preflight
from dovesei.up.launch import SERVICES, child_commands
from dovesei.up.options import build_parser, options_from_args

WORLD = "synthetic:size_m=400,seed=1"  # the e2e tests' world: generated in about a second, cached


@pytest.mark.slow
def test_an_episode_flies_over_mutual_tls_and_the_acl(tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    write_pki(certs)
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    options = options_from_args(build_parser().parse_args(
        # A whole episode (start to judged result) over the secured link; its length proves nothing
        # more, so 10 s of sim time, not the 49 s this start takes to a hand-over.
        ["--world", WORLD, "--segmenter", "sim", "--noise", "0", "--start-seed", "0", "--time-limit-s", "10",
         "--out", str(tmp_path / "run"), "--connect", endpoint]))
    _, _, configs = preflight(options)
    commands = child_commands(options, configs, {}, tmp_path / "run")
    (tmp_path / "run" / "stats").mkdir(parents=True)
    router = zenoh.open(zenoh.Config.from_json5(json.dumps(router_config(str(certs), listen=[endpoint]))))
    monitor = zenoh.open(zenoh_config(mode="client", connect=[endpoint], env={},
                                      tls=TlsFiles(certs / "ca.pem", certs / "monitor.pem", certs / "monitor.key")))
    results: list[EpisodeResult] = []
    lock = threading.Lock()

    def on_result(sample: zenoh.Sample) -> None:
        with lock:
            results.append(decode(sample.payload.to_bytes(), EpisodeResult))
    sub = monitor.declare_subscriber(keys.episode(options.vehicle_id), on_result)
    procs: dict[str, subprocess.Popen] = {}
    logs = {name: (tmp_path / f"{name}.log").open("w") for name in SERVICES}
    try:
        for name in SERVICES:
            argv = [*commands[name], "--tls-ca", str(certs / "ca.pem"), "--tls-cert", str(certs / f"{name}.pem"),
                    "--tls-key", str(certs / f"{name}.key")]
            procs[name] = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=logs[name], stderr=subprocess.STDOUT,
                                           env=_env())
        done = wait_until(lambda: bool(results) or any(p.poll() not in (None, 0) for p in procs.values()), 240.0,
                          poll_s=0.1)
        tails = {n: (tmp_path / f"{n}.log").read_text()[-2000:] for n in SERVICES}
        assert done and results, f"no episode result over the secured link: {tails}"
        assert results[0].outcome in ("safe", "unsafe", "timeout", "out_of_world"), results[0]
        assert results[0].sim_time_s > 0
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for f in logs.values():
            f.close()
        sub.undeclare()
        monitor.close()
        router.close()
    # Nothing the services sent was refused by a receiver: the ACL let the whole protocol through.
    for name in SERVICES:
        stats_file = tmp_path / "run" / "stats" / f"{name}.json"
        if stats_file.exists():
            text = stats_file.read_text()
            assert '"stamp from the future"' not in text, (name, text[:500])


def _env() -> dict[str, str]:
    """The children's environment: offline, and no ZENOH_CONFIG of the caller's to change the link."""
    return {**{k: v for k, v in os.environ.items() if k != "ZENOH_CONFIG"}, "HF_HUB_OFFLINE": "1"}
