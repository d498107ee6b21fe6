"""The service processes of one `dovesei up` run: started in their own sessions, each writing its
own log, watched for an exit, stopped in order (SIGTERM, SIGKILL after a grace period).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

log = logging.getLogger("dovesei.up")

TERM_GRACE_S = 5.0  # SIGTERM -> SIGKILL


def describe_exit(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"killed by signal {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exited with code {returncode}"


def last_error_line(log_path: Path, max_bytes: int = 16384) -> str:
    """The child's last ERROR/CRITICAL/exception line, else its last line ('' for an empty log)."""
    try:
        with log_path.open("rb") as fh:
            fh.seek(0, os.SEEK_END)
            fh.seek(max(0, fh.tell() - max_bytes))
            lines = [ln.strip() for ln in fh.read().decode("utf-8", "replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    for line in reversed(lines):
        if " ERROR " in line or " CRITICAL " in line or "Error:" in line or "Exception" in line:
            return _clip(line)
    return _clip(lines[-1]) if lines else ""


def _clip(line: str, max_chars: int = 300) -> str:
    return line if len(line) <= max_chars else line[:max_chars - 3] + "..."


class Children:
    """The three service processes: start, watch, stop; each one's output goes to its own log."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: dict[str, Any] = {}

    def start(self, name: str, argv: list[str], env: dict[str, str] | None = None) -> subprocess.Popen:
        log_path = self.log_dir / f"{name}.log"
        fh = log_path.open("wb")
        self._logs[name] = fh
        # Own session: a Ctrl-C in the terminal reaches only `up`, which then stops the children
        # in order and reaps them, instead of racing them through the same signal.
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                                start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
        self.procs[name] = proc
        log.info("started %s (pid %d): %s", name, proc.pid, " ".join(argv[2:]))
        return proc

    def wait_exit(self, name: str, timeout_s: float) -> bool:
        """Let a child finish on its own (True when it has exited within `timeout_s`)."""
        try:
            self.procs[name].wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return False
        return True

    def exited(self) -> list[tuple[str, int]]:
        return [(n, p.returncode) for n, p in self.procs.items() if p.poll() is not None]

    def log_path(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def stop_all(self, grace_s: float = TERM_GRACE_S) -> dict[str, int]:
        """SIGTERM every running child, SIGKILL what is left after `grace_s`; reap all."""
        for name, proc in self.procs.items():
            if proc.poll() is None:
                log.debug("stopping %s (pid %d)", name, proc.pid)
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for name, proc in self.procs.items():
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s (pid %d) ignored SIGTERM for %.0f s: killing it", name, proc.pid, grace_s)
                proc.kill()
                proc.wait()
        for fh in self._logs.values():
            fh.close()
        return {n: p.returncode for n, p in self.procs.items()}
