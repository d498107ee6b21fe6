"""A controller process stopped or killed mid-flight at 10 m/s, against the fake ArduCopter.

Issue 26: killed, ArduCopter flew the last setpoint for GUID_TIMEOUT (3 s, ~35 m blind), then
hovered, armed, silently; the sim drops a command after 0.5 s, so the tests underestimated the
coast six times. The fake now coasts for GUID_TIMEOUT like ArduCopter; a stopped controller
(SIGTERM) streams zero velocity before it closes the link; the GCS failsafe docs/OPERATOR.md
advises (FS_GCS_ENABLE 5, on dovesei's heartbeat as SYSID_MYGCS) lands a vehicle whose
controller died.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dovesei.shared.lifecycle import wait_until
from dovesei.shared.zconfig import free_port
from dovesei.testing.fake_autopilot import FakeAutopilot

REPO = Path(__file__).resolve().parents[2]


def _speed(fake: FakeAutopilot) -> float:
    return math.hypot(*fake.velocity_ned_m_s[:2])


def _fly_then(sig: int, **fake_kw: object) -> tuple[FakeAutopilot, float, tuple[float, float, float], float]:
    """Start the flying controller, wait for 10 m/s, send `sig`; returns (fake, signal time,
    position at the signal, time the vehicle stopped) with the fake still running."""
    port = free_port(socket.SOCK_DGRAM)
    fake = FakeAutopilot(f"udpin:127.0.0.1:{port}", flavour="ardupilot", mode="GUIDED", armed=True, alt_m=60.0,
                         heartbeat_hz=10, **fake_kw).start()
    proc = subprocess.Popen([sys.executable, "-m", "tests.controller.flying_controller", f"udpout:127.0.0.1:{port}"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert wait_until(lambda: _speed(fake) > 9.5, 60.0), f"never flew at 10 m/s: {proc.poll()}"
        time.sleep(0.5)  # noqa: a steady flight before the signal, not a synchronisation
        sent_s, at = time.monotonic(), fake.position_ned_m
        proc.send_signal(sig)
        assert wait_until(lambda: _speed(fake) < 0.05, 15.0), "the vehicle never stopped"
        stopped_s = time.monotonic()
        proc.wait(15.0)
    except BaseException:
        fake.stop()
        raise
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return fake, sent_s, at, stopped_s


def test_killed_the_vehicle_coasts_guid_timeout_on_the_last_setpoint_and_the_gcs_failsafe_lands_it() -> None:
    fake, killed_s, at, stopped_s = _fly_then(signal.SIGKILL, fs_gcs_enable="land", fs_gcs_timeout_s=5.0)
    try:
        n, e, _ = fake.position_ned_m
        coast_m = math.hypot(n - at[0], e - at[1])
        print(f"killed at 10 m/s: coasted {coast_m:.1f} m in {stopped_s - killed_s:.2f} s")
        # GUID_TIMEOUT 3 s at 10 m/s: ~30 m blind, six times what the sim's 0.5 s drop suggested.
        assert stopped_s - killed_s > 2.5 and 22.0 < coast_m < 40.0, (stopped_s - killed_s, coast_m)
        # Then FS_GCS_TIMEOUT without dovesei's heartbeat (system 255 = SYSID_MYGCS): LAND.
        assert wait_until(lambda: fake.mode == "LAND", 15.0), fake.mode
        last_heartbeat_s = max(hb.recv_s for hb in fake.received()[1] if hb.system == 255)
        assert last_heartbeat_s < killed_s and time.monotonic() - last_heartbeat_s >= 5.0
        assert any(text == "GCS Failsafe" for _, text in fake.statustexts_sent)
    finally:
        fake.stop()


def test_stopped_it_streams_zero_velocity_before_closing_and_the_vehicle_stops_at_once() -> None:
    fake, stopped_at_s, at, stopped_s = _fly_then(signal.SIGTERM, fs_gcs_enable=None)
    try:
        n, e, _ = fake.position_ned_m
        assert stopped_s - stopped_at_s < 2.0 and math.hypot(n - at[0], e - at[1]) < 15.0
        after = [sp for sp in fake.received()[0] if sp.recv_s >= stopped_at_s]
        print(f"SIGTERM at 10 m/s: stopped after {math.hypot(n - at[0], e - at[1]):.1f} m in "
              f"{stopped_s - stopped_at_s:.2f} s, {sum(sp.vel_m_s == (0.0, 0.0, 0.0) for sp in after)} zero setpoints")
        zeros = [sp for sp in after if sp.vel_m_s == (0.0, 0.0, 0.0)]
        # Several zero setpoints (one lost datagram must not leave 10 m/s flying), and zero is the last word.
        assert len(zeros) >= 5 and after[-1].vel_m_s == (0.0, 0.0, 0.0), [sp.vel_m_s for sp in after][-12:]
        assert fake.mode == "GUIDED" and fake.armed  # hovering where it stopped, for the pilot
    finally:
        fake.stop()
