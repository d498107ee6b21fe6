"""The segmenter process ends promptly on SIGTERM, even after importing torch and transformers.

`dovesei up` logged "segmenter ignored SIGTERM for 5 s: killing it" in 2 of 6 runs: the service
stopped at once, but with torch and transformers imported (CLIPSeg, or then `--backend auto`
trying it before it fell back) the interpreter's teardown after `main` took 2-5 s on a loaded host. The process
entry now ends without that teardown, once the session is closed and the stats are written.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from dovesei.shared.lifecycle import wait_until
from dovesei.shared.zconfig import free_port
from dovesei.up.children import TERM_GRACE_S

REPO = Path(__file__).resolve().parents[2]

# The module run as `python -m dovesei.segmenter.service` would be, with an atexit marker: atexit
# handlers run only in the interpreter's teardown, so the marker says whether it ran.
_ENTRY = """
import atexit, runpy, sys
import torch, transformers  # what a CLIPSeg segmenter has loaded (auto without weights no longer imports them)
marker = sys.argv.pop(1)
atexit.register(lambda: open(marker, "w").close())
sys.argv[0] = "dovesei-segmenter"
runpy.run_module("dovesei.segmenter.service", run_name="__main__", alter_sys=True)
"""


def test_sigterm_ends_the_segmenter_without_the_interpreter_teardown(tmp_path: Path) -> None:
    marker, stats, log_path = tmp_path / "teardown-ran", tmp_path / "stats.json", tmp_path / "segmenter.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-c", _ENTRY, str(marker), "--backend", "auto", "--lockstep", "--mode", "peer",
             "--no-multicast-scouting", "--listen", f"tcp/127.0.0.1:{free_port()}", "--stats-out", str(stats)],
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "HF_HUB_OFFLINE": "1"})
        try:
            assert wait_until(lambda: b"segmenter up" in log_path.read_bytes() or proc.poll() is not None, 240.0)
            assert proc.poll() is None, log_path.read_text()
            t0 = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=60)
            took_s = time.monotonic() - t0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    out = log_path.read_text()
    assert code == 0, out
    assert not marker.exists(), "the interpreter's teardown ran (it took 2-5 s with torch imported)"
    assert stats.is_file() and '"backend": "simulated"' in stats.read_text()  # saved before the exit (auto fell back)
    assert out.rstrip().endswith("'vehicles': {}}"), out[-500:]  # the last log line was flushed
    assert took_s < TERM_GRACE_S, f"{took_s:.1f} s: `up` would have killed it"
