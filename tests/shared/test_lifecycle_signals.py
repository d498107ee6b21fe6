"""A service's signals: SIGTERM stops it cleanly; SIGUSR1 shows where every thread is and it goes on."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

PROGRAM = """
import sys, threading
from dovesei.shared.lifecycle import install_stop_handlers
stop = install_stop_handlers()
def waiting_in_a_worker():
    stop.wait()
threading.Thread(target=waiting_in_a_worker, name="worker").start()
print("ready", flush=True)
stop.wait()
print("stopped", flush=True)
"""


def test_sigusr1_dumps_every_threads_stack_and_the_process_goes_on_until_sigterm() -> None:
    proc = subprocess.Popen([sys.executable, "-c", PROGRAM], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGUSR1)
        time.sleep(0.5)
        assert proc.poll() is None, "SIGUSR1 ended the process"
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and stdout.strip() == "stopped", stderr
    # Both threads, each with the function it waits in.
    assert stderr.count("hread 0x") == 2 and "in waiting_in_a_worker" in stderr and "in <module>" in stderr, stderr
