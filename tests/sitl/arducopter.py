"""ArduCopter SITL as a test fixture: one `arducopter` process in a scratch folder, stopped at the end.

The tests of this tier (marker `sitl`, see tests/conftest.py) fly dovesei against a real ArduCopter
built from an ArduPilot tree given in `DOVESEI_SITL_DIR` (a built `build/sitl/bin/arducopter`;
how to build it: docs/sitl.md). Nothing of ArduPilot is in this repository.

    arducopter --serial0 udpclient:127.0.0.1:<controller>   the autopilot's link, `up --vehicle-url udpin:...`
               --serial2 udpclient:127.0.0.1:<truth>        a separate output, `up --sitl-truth udpin:...`
               --serial5 udpclient:127.0.0.1:<monitor>      the test's own look at the autopilot (STATUSTEXT, modes)

The copter starts at ArduPilot's autotest home (CMAC) with the autotest copter defaults, eeprom
wiped, in real time. arducopter ends itself when its parent process (pytest) is gone, so nothing
outlives a killed test run; `close` stops it first anyway.
"""

from __future__ import annotations

import os
import socket
import subprocess
import time
from pathlib import Path

HOME = "-35.363261,149.165230,584,353"  # CMAC, ArduPilot's autotest home: lat, lon, alt AMSL m, heading deg
_RC_IN_PORT = 5501  # SITL listens for RC input on UDP 5501 + 10 x instance: the one port an instance binds


def sitl_tree() -> Path:
    """The ArduPilot tree of `DOVESEI_SITL_DIR`, or a one-line failure saying what is missing."""
    import pytest  # noqa: PLC0415 (a helper module: pytest only when a test asks for the tree)

    value = os.environ.get("DOVESEI_SITL_DIR", "")
    if not value:
        pytest.fail("the sitl tests need DOVESEI_SITL_DIR=<an ArduPilot tree with build/sitl/bin/arducopter> "
                    "(docs/sitl.md says how to build it)", pytrace=False)
    tree = Path(value).expanduser()
    for need in ("build/sitl/bin/arducopter", "Tools/autotest/default_params/copter.parm"):
        if not (tree / need).is_file():
            pytest.fail(f"DOVESEI_SITL_DIR={value}: no {need} (build SITL first: docs/sitl.md)", pytrace=False)
    return tree


def _free_instance() -> int:
    """An instance number whose RC-input port is free (another SITL may run on this host)."""
    for instance in range(1, 50):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("0.0.0.0", _RC_IN_PORT + 10 * instance))
            except OSError:
                continue
            return instance
    raise RuntimeError("no free SITL instance (UDP 5511..5991 all taken)")


class ArduCopterSitl:
    """`with ArduCopterSitl(tree, folder, controller_port=..., truth_port=...) as sitl:` runs one copter."""

    def __init__(self, tree: Path, folder: Path, *, controller_port: int, truth_port: int,
                 monitor_port: int | None = None, params: dict[str, float] | None = None) -> None:
        self.tree, self.folder = tree, folder
        self.ports = {"serial0": controller_port, "serial2": truth_port, "serial5": monitor_port}
        self.params = dict(params or {})
        self.proc: subprocess.Popen | None = None
        self.log_path = folder / "arducopter.log"

    def __enter__(self) -> ArduCopterSitl:
        self.folder.mkdir(parents=True, exist_ok=True)
        params = dict(self.params)
        if self.ports["serial5"] is not None:
            params.setdefault("SERIAL5_PROTOCOL", 2)  # MAVLink 2 on the monitor's output
        extra = self.folder / "extra.parm"
        extra.write_text("".join(f"{k} {v:g}\n" for k, v in params.items()))
        defaults = f"{self.tree / 'Tools/autotest/default_params/copter.parm'},{extra}"
        argv = [str(self.tree / "build/sitl/bin/arducopter"), "-I", str(_free_instance()), "-S", "-w",
                "--model", "+", "--speedup", "1", "--defaults", defaults, "--home", HOME,
                "--sim-address", "127.0.0.1", "--serial1", "none:", "--serial6", "none:", "--serial7", "none:",
                "--serial8", "none:"]
        for serial, port in self.ports.items():
            argv += [f"--{serial}", f"udpclient:127.0.0.1:{port}" if port is not None else "none:"]
        with self.log_path.open("wb") as log:
            self.proc = subprocess.Popen(argv, cwd=self.folder, stdin=subprocess.DEVNULL, stdout=log,
                                         stderr=subprocess.STDOUT)
        time.sleep(1.0)
        if self.proc.poll() is not None:
            raise RuntimeError(f"arducopter exited at once ({self.proc.returncode}): "
                               f"{self.log_path.read_text(errors='replace')[-500:]}")
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5.0)


class MavlinkWatch:
    """The test's own read of a SITL output: STATUSTEXT lines, mode changes, altitude, armed state, GPS fix.

    Parsed with pymavlink's MAVLink 2 dialect on a plain UDP socket; it asks for GLOBAL_POSITION_INT
    GPS_RAW_INT and EKF_STATUS_REPORT at 2 Hz, and with `cut_gps_below_m` it disables SITL's GPS (PARAM_SET
    SIM_GPS_DISABLE 1) once the copter, armed, has been 10 m above that altitude and sinks below it
    (`gps_cut_alt_m` records where). `texts` and `modes` grow as the flight goes.
    """

    def __init__(self, port: int, *, cut_gps_below_m: float | None = None) -> None:
        import threading  # noqa: PLC0415 (kept beside the one class that needs it)

        from pymavlink.dialects.v20 import ardupilotmega  # noqa: PLC0415 (only the sitl tier parses MAVLink here)

        self._mavlink = ardupilotmega
        self._mav = ardupilotmega.MAVLink(None, srcSystem=252, srcComponent=190)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", port))
        self._sock.settimeout(0.2)
        self._stop = threading.Event()
        self.texts_in_mode: list[tuple[int | None, str]] = []  # (custom mode when it came, text)
        self.modes: list[tuple[int, bool]] = []  # (custom mode number, armed) on each change
        self.rel_alt_m: float | None = None
        self.armed = False
        self.custom_mode: int | None = None
        self.gps_fix_type = 0
        self.ekf_flags = 0  # EKF_STATUS_REPORT flags
        self.cut_gps_below_m = cut_gps_below_m
        self.gps_cut_alt_m: float | None = None
        self._above = False
        self._thread = threading.Thread(target=self._run, name="sitl-watch", daemon=True)

    def _run(self) -> None:
        asked = 0.0
        while not self._stop.is_set():
            try:
                data, addr = self._sock.recvfrom(65536)
            except TimeoutError:
                continue
            for msg in self._mav.parse_buffer(data) or ():
                kind = msg.get_type()
                if kind == "HEARTBEAT" and msg.autopilot == 3:
                    armed = bool(msg.base_mode & 128)
                    if (msg.custom_mode, armed) != (self.custom_mode, self.armed):
                        self.modes.append((msg.custom_mode, armed))
                    self.custom_mode, self.armed = msg.custom_mode, armed
                    target = (msg.get_srcSystem(), msg.get_srcComponent())
                    if time.monotonic() - asked > 5.0:  # GLOBAL_POSITION_INT, GPS_RAW_INT, EKF_STATUS_REPORT
                        for msg_id in (33, 24, 193):
                            packet = self._mav.command_long_encode(*target, 511, 0, msg_id, 500_000, 0, 0, 0, 0,
                                                                   0).pack(self._mav)
                            self._sock.sendto(packet, addr)
                        asked = time.monotonic()
                    self._maybe_cut_gps(target, addr)
                elif kind == "STATUSTEXT":
                    self.texts_in_mode.append((self.custom_mode, msg.text))
                elif kind == "GLOBAL_POSITION_INT":
                    self.rel_alt_m = msg.relative_alt / 1000.0
                elif kind == "GPS_RAW_INT":
                    self.gps_fix_type = msg.fix_type
                elif kind == "EKF_STATUS_REPORT":
                    self.ekf_flags = msg.flags

    @property
    def texts(self) -> list[str]:
        """Every STATUSTEXT so far, in order."""
        return [text for _, text in self.texts_in_mode]

    @property
    def ekf_has_absolute_position(self) -> bool:
        """EKF_STATUS_REPORT: an absolute horizontal position (16), not in constant-position mode (128)."""
        return bool(self.ekf_flags & 16) and not self.ekf_flags & 128

    def _maybe_cut_gps(self, target: tuple[int, int], addr: tuple[str, int]) -> None:
        """SIM_GPS_DISABLE 1 (an INT8 parameter) below `cut_gps_below_m`, re-sent each heartbeat until
        the fix is gone."""
        if self.cut_gps_below_m is None or not self.armed or self.rel_alt_m is None:
            return
        self._above = self._above or self.rel_alt_m > self.cut_gps_below_m + 10.0
        if self._above and self.rel_alt_m < self.cut_gps_below_m and self.gps_fix_type >= 2:
            if self.gps_cut_alt_m is None:
                self.gps_cut_alt_m = self.rel_alt_m
            packet = self._mav.param_set_encode(*target, b"SIM_GPS_DISABLE", 1.0, 2).pack(self._mav)
            self._sock.sendto(packet, addr)

    def __enter__(self) -> MavlinkWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._sock.close()
