"""MAVLink connection URLs: the one parser `dovesei up` and the controller both use.

The forms are pymavlink's (`mavutil.mavlink_connection`), the ones MAVProxy and the ArduPilot and
PX4 docs print:

    udpin:HOST:PORT     listen for an autopilot sending to us (binds the local port)
    udp:HOST:PORT       pymavlink's legacy spelling of udpin (binds)
    udpout:HOST:PORT    send to an autopilot listening there
    udpbcast:HOST:PORT  send to a broadcast address
    tcp:HOST:PORT       connect to an autopilot (SITL's TCP 5760)
    tcpin:HOST:PORT     listen for a TCP connection (binds)
    DEVICE[,BAUD]       a serial port (/dev/ttyACM0,921600; COM3,57600 on Windows); 115200 baud
                        when not given, pymavlink's default

Nothing here opens a socket or a device: `parse_mavlink_url` checks the form (ConfigError names the
flag), `check_serial_device` whether a serial device can be opened at all, which the operator wants
to hear in one line before anything starts. URLs of other tools (`serial:///dev/ttyACM0:921600`,
a bare `HOST:PORT`) are refused with the spelling to use instead: pymavlink would take the first
for a UDP address and open a bare path that is a regular file as a log to replay.
"""

from __future__ import annotations

import os
import re
import stat
from dataclasses import dataclass

from dovesei.shared.errors import ConfigError

# Scheme -> whether opening the URL binds the local endpoint (a listener).
SCHEMES = {"udpin": True, "udp": True, "tcpin": True, "udpout": False, "udpbcast": False, "tcp": False}
DEFAULT_BAUD = 115200  # pymavlink's default for a serial port
FORMS = ("udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT "
         "or a serial device such as /dev/ttyACM0,921600")
_COM = re.compile(r"COM\d+", re.IGNORECASE)


@dataclass(frozen=True)
class MavlinkEndpoint:
    """A parsed MAVLink URL. For a serial link `host` is the device path and `port` 0."""

    url: str
    scheme: str  # one of SCHEMES, or "serial"
    host: str
    port: int
    binds: bool  # opening it takes the local endpoint (a listener, or a serial device)
    baud: int = DEFAULT_BAUD

    @property
    def endpoint(self) -> tuple[str, int]:
        return self.host, self.port

    @property
    def serial(self) -> bool:
        return self.scheme == "serial"

    @property
    def device(self) -> str:
        """What pymavlink's `mavlink_connection` takes (the baud goes beside it as `baud=`)."""
        return self.host if self.serial else self.url


def parse_mavlink_url(url: object, flag: str = "--vehicle-url") -> MavlinkEndpoint:
    """`url` checked for its form; ConfigError names `flag`, the URL and the accepted forms."""
    if not isinstance(url, str) or not url.strip():
        raise ConfigError(f"{flag}: a MAVLink URL must be a non-empty string, got {url!r}")
    text = url.strip()
    if text.lower().startswith("serial:"):
        device, _, baud = text[len("serial:"):].lstrip("/").partition(":")
        hint = f"/{device}" + (f",{baud}" if baud else "")
        raise ConfigError(f"{flag} {url!r}: pymavlink has no serial: URLs; write the device and baud as "
                          f"{hint}")
    scheme, sep, rest = text.partition(":")
    if sep and scheme in SCHEMES:
        host, sep, port_text = rest.rpartition(":")
        if not sep or not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            raise ConfigError(f"{flag} {url!r}: expected {scheme}:HOST:PORT with a port in 1..65535 "
                              f"(accepted forms: {FORMS})")
        return MavlinkEndpoint(text, scheme, host, int(port_text), SCHEMES[scheme])
    device, comma, baud_text = text.partition(",")
    if device.startswith("/") or _COM.fullmatch(device):
        if comma and not (baud_text.isdigit() and int(baud_text) > 0):
            raise ConfigError(f"{flag} {url!r}: the baud rate after ',' must be a positive integer")
        return MavlinkEndpoint(text, "serial", device, 0, True, int(baud_text) if comma else DEFAULT_BAUD)
    if re.fullmatch(r"[^:/]+:\d+", text):
        raise ConfigError(f"{flag} {url!r}: say which way the link goes: udpin:{text} (listen) or "
                          f"udpout:{text} (send)")
    raise ConfigError(f"{flag} {url!r}: not a MAVLink URL; accepted forms: {FORMS}")


def check_serial_device(ep: MavlinkEndpoint, flag: str = "--vehicle-url") -> None:
    """A serial device that exists, is a character device and that this process may read and write.

    The kernel has the last word when the port is opened (a device another process holds, a
    USB adapter unplugged in between); this catches what an operator can fix before a flight.
    """
    if not ep.serial or not ep.host.startswith("/"):
        return  # sockets, and COM ports (Windows) that only opening can check
    try:
        mode = os.stat(ep.host).st_mode
    except FileNotFoundError:
        raise ConfigError(f"{flag} {ep.url!r}: no such serial device {ep.host} (is the autopilot plugged in? "
                          "`ls /dev/serial/by-id/` lists USB serial ports)") from None
    except OSError as exc:
        raise ConfigError(f"{flag} {ep.url!r}: cannot read {ep.host} ({exc.strerror or exc})") from None
    if not stat.S_ISCHR(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "a file"
        raise ConfigError(f"{flag} {ep.url!r}: {ep.host} is {kind}, not a serial device")
    if not os.access(ep.host, os.R_OK | os.W_OK):
        raise ConfigError(f"{flag} {ep.url!r}: no permission to read and write {ep.host} (add the user to the "
                          "group that owns it, e.g. dialout)")
