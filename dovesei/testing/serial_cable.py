"""A null-modem cable between two pseudo-terminals: two real serial device paths for tests.

    open(end_a) <--pts A--> master A <==relay thread==> master B <--pts B--> open(end_b)

Each end is a /dev/pts/N path that pyserial opens like /dev/ttyACM0 (termios, baud and all), so a
test can put the controller's MAVLink adapter on one end and a fake autopilot on the other, with
the whole serial path of pymavlink and pyserial in between. Both slave sides are set raw at once
and held open by the cable, so no byte is echoed or cooked before (or after) a user opens them;
the relay copies raw bytes master to master until `close()`.
"""

from __future__ import annotations

import os
import select
import threading
import tty


class PtyCable:
    """Two connected pseudo-terminals; `end_a` and `end_b` are their device paths."""

    def __init__(self) -> None:
        self._masters: list[int] = []
        self._slaves: list[int] = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no line discipline: MAVLink frames are binary
            self._masters.append(master)
            self._slaves.append(slave)
        self.end_a, self.end_b = (os.ttyname(s) for s in self._slaves)
        self.bytes_relayed = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="pty-cable", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        peer = {self._masters[0]: self._masters[1], self._masters[1]: self._masters[0]}
        while not self._stop.is_set():
            ready, _, _ = select.select(list(peer), [], [], 0.05)
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:  # EIO: the cable is being closed
                    return
                view = memoryview(data)
                while view:  # a pty write may take only part of the data
                    view = view[os.write(peer[fd], view):]
                self.bytes_relayed += len(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        for fd in (*self._masters, *self._slaves):
            os.close(fd)
        self._masters, self._slaves = [], []

    def __enter__(self) -> PtyCable:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
