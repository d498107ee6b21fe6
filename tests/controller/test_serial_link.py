"""The MAVLink adapter on a serial link: a real pseudo-terminal pair, pyserial on both ends.

`dovesei-controller --vehicle-url /dev/ttyAMA0,921600` (the README's on-vehicle line) died with
`ModuleNotFoundError: No module named 'serial'`: pyserial was in no dependency list. Here the
adapter opens a /dev/pts path exactly as it opens a UART, and a fake ArduCopter answers on the
other end of a null-modem cable (`dovesei.testing.serial_cable`); a device that is missing, not a
device, or a missing pyserial is one line, never a traceback.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from dovesei.controller.mavlink import proto as mv
from dovesei.controller.mavlink.vehicle import MavlinkVehicle, VehicleConnectError
from dovesei.shared.errors import ConfigError
from dovesei.shared.lifecycle import wait_until
from dovesei.shared.mavurl import MavlinkEndpoint, check_serial_device, parse_mavlink_url
from dovesei.shared.messages import Stamp, VelocityCommand
from dovesei.shared.zconfig import free_port
from dovesei.testing.fake_autopilot import FakeAutopilot
from dovesei.testing.serial_cable import PtyCable

REPO = Path(__file__).resolve().parents[2]
DEADLINE_S = 30.0  # generous: the machine is shared


def test_pyserial_is_a_base_dependency() -> None:
    import tomllib
    deps = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]["dependencies"]
    assert any(d.replace(" ", "").lower().startswith("pyserial") for d in deps), deps
    import serial  # noqa: F401  (what pymavlink's mavserial imports)


def test_the_adapter_flies_a_fake_autopilot_over_a_pty_pair() -> None:
    with PtyCable() as cable:
        with FakeAutopilot(f"{cable.end_b},921600", mode="GUIDED", armed=True, alt_m=50.0, heartbeat_hz=10) as fake:
            vehicle = MavlinkVehicle(f"{cable.end_a},921600")
            try:
                vehicle.connect(DEADLINE_S)  # the autopilot's heartbeat came over the pty
                assert vehicle.autopilot == "ardupilot"
                assert wait_until(lambda: vehicle.poll_state() is not None, DEADLINE_S), "no state over the pty"
                # ... and ours went the other way: the companion heartbeat and a setpoint.
                assert wait_until(lambda: len(fake.received()[1]) >= 1, DEADLINE_S)
                assert fake.received()[1][0].mav_type == mv.MAV_TYPE_ONBOARD_CONTROLLER
                vehicle.send(VelocityCommand(vehicle_id="uav1", seq=0, stamp=Stamp(0.0, "vehicle"),
                                             vel_body_frd_m_s=(1.0, 0.0, 0.5), yaw_rate_rad_s=0.0))
                assert wait_until(lambda: any(sp.vel_m_s == (1.0, 0.0, 0.5) for sp in fake.received()[0]),
                                  DEADLINE_S), "no setpoint arrived over the pty"
            finally:
                vehicle.close()
        assert cable.bytes_relayed > 0


def test_the_controller_process_connects_over_a_pty() -> None:
    """The console script end to end: `--vehicle-url /dev/pts/N,921600` (the onboard form)."""
    with PtyCable() as cable, FakeAutopilot(f"{cable.end_b},921600", mode="GUIDED", armed=True, alt_m=50.0,
                                            heartbeat_hz=10) as fake:
        proc = subprocess.Popen(
            [sys.executable, "-m", "dovesei.controller.service", "--vehicle-url", f"{cable.end_a},921600",
             "--listen", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting", "--log-level", "INFO"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
        try:
            # Our companion heartbeat at the fake proves the controller opened the device and talks.
            assert wait_until(lambda: len(fake.received()[1]) >= 1 or proc.poll() is not None, 120.0)
            assert proc.poll() is None, proc.communicate(timeout=10)[0]
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=DEADLINE_S)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert proc.returncode == 0, out
    assert f"connected to ardupilot on {cable.end_a},921600" in out, out
    assert "Traceback" not in out


@pytest.mark.parametrize("url, needle", [
    ("/dev/dovesei-no-such-tty,921600", "no such serial device /dev/dovesei-no-such-tty"),
    ("/etc/hostname,57600", "is a file, not a serial device"),
])
def test_a_bad_serial_device_is_one_line_from_the_controller(url: str, needle: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "dovesei.controller.service", "--vehicle-url", url,
         "--listen", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting", "--log-level", "WARNING"],
        capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 1, proc.stderr
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in lines[0], lines


def test_a_missing_pyserial_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    with PtyCable() as cable:
        monkeypatch.setitem(sys.modules, "serial", None)  # `import serial` now fails as without pyserial
        with pytest.raises(VehicleConnectError, match="needs pyserial"):
            mv.open_link(f"{cable.end_a},921600", source_system=255, source_component=191)


# ---------------------------------------------------------------------- the one URL parser


@pytest.mark.parametrize("url, scheme, host, port, binds, baud", [
    ("udpin:0.0.0.0:14550", "udpin", "0.0.0.0", 14550, True, 115200),
    ("udp:127.0.0.1:14550", "udp", "127.0.0.1", 14550, True, 115200),
    ("udpout:10.0.0.2:14555", "udpout", "10.0.0.2", 14555, False, 115200),
    ("udpbcast:10.0.0.255:14550", "udpbcast", "10.0.0.255", 14550, False, 115200),
    ("tcp:127.0.0.1:5760", "tcp", "127.0.0.1", 5760, False, 115200),
    ("tcpin:0.0.0.0:5760", "tcpin", "0.0.0.0", 5760, True, 115200),
    ("/dev/ttyAMA0,921600", "serial", "/dev/ttyAMA0", 0, True, 921600),
    ("/dev/serial/by-id/usb-ArduPilot_fmuv3-if00", "serial", "/dev/serial/by-id/usb-ArduPilot_fmuv3-if00", 0, True,
     115200),
    ("COM3,57600", "serial", "COM3", 0, True, 57600),
])
def test_pymavlinks_forms_parse(url: str, scheme: str, host: str, port: int, binds: bool, baud: int) -> None:
    ep = parse_mavlink_url(url)
    assert (ep.scheme, ep.host, ep.port, ep.binds, ep.baud) == (scheme, host, port, binds, baud)
    assert mv.check_url(url) == ((host, baud) if scheme == "serial" else (url, baud))


@pytest.mark.parametrize("url, needle", [
    ("serial:///dev/ttyACM0:921600", "/dev/ttyACM0,921600"),  # what compose.onboard had: the fix is named
    ("127.0.0.1:14550", "udpin:127.0.0.1:14550"),
    ("udpin:0.0.0.0", "udpin:HOST:PORT"),
    ("tcp:host:70000", "1..65535"),
    ("/dev/ttyACM0,fast", "baud"),
    ("ttyACM0", "not a MAVLink URL"),
    ("", "non-empty"),
])
def test_other_forms_are_refused_naming_the_flag(url: str, needle: str) -> None:
    with pytest.raises(ConfigError, match="--vehicle-url") as exc:
        parse_mavlink_url(url)
    assert needle in str(exc.value)


def test_up_and_the_controller_refuse_and_accept_the_same_urls() -> None:
    from dovesei.controller.service import CLI
    from dovesei.up.options import build_parser, options_from_args

    for url, ok in (("/dev/ttyAMA0,921600", True), ("udpin:0.0.0.0:14550", True),
                    ("serial:///dev/ttyACM0:921600", False), ("127.0.0.1:14550", False)):
        try:
            CLI.parse(["--vehicle-url", url])
            controller_ok = True
        except ConfigError:
            controller_ok = False
        try:
            options_from_args(build_parser().parse_args(["--vehicle-url", url]))
            up_ok = True
        except (ConfigError, SystemExit):
            up_ok = False
        assert controller_ok == up_ok == ok, url


def test_check_serial_device_knows_a_tty_from_a_file(tmp_path: Path) -> None:
    with PtyCable() as cable:
        check_serial_device(parse_mavlink_url(cable.end_a))  # a character device we may open
    (tmp_path / "log.tlog").write_bytes(b"")
    with pytest.raises(ConfigError, match="is a file"):
        check_serial_device(parse_mavlink_url(str(tmp_path / "log.tlog")))
    with pytest.raises(ConfigError, match="is a folder"):
        check_serial_device(parse_mavlink_url(str(tmp_path)))
    check_serial_device(MavlinkEndpoint("udpin:0.0.0.0:1", "udpin", "0.0.0.0", 1, True))  # sockets: nothing to do
