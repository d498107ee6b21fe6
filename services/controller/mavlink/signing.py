"""MAVLink 2 signing on the adapter's link: sign what we send, accept only what the key signed.

    install(conn)  -> pymavlink signs every outgoing frame (link id 0, timestamp >= the persisted one)
    incoming frame -> check(): the SHA-256 signature first, then the timestamp (per link id, system,
                      component: strictly increasing; a new stream at most 60 s behind ours)
                   -> unsigned(): pymavlink's callback for a frame without a valid signature
    tick()         -> the timestamp follows real time and is persisted every 10 s (and at close)

Why our own check instead of pymavlink's: pymavlink stores a stream's timestamp before it checks
the hash, so one forged frame stamped far ahead would make every honest frame after it look
replayed. Every refusal is counted by kind (unsigned / wrong key / replayed) and logged through the
adapter's rate-limited warning. The timestamp file keeps the counter monotonic across restarts on
a computer without a real-time clock (the MAVLink signing spec asks for exactly that).
"""

from __future__ import annotations

import hashlib
import math
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dovesei.controller.mavlink.proto import (
    read_signing_timestamp,
    signing_timestamp_now,
    write_signing_timestamp,
)

PERSIST_PERIOD_S = 10.0
NEW_STREAM_WINDOW = 6_000_000  # signing units (10 us): a new stream may start 60 s behind ours
Warn = Callable[..., None]  # warn(kind, fmt, *args)


class LinkSigning:
    """The signing state of one link; `rejected` counts refused frames by kind."""

    def __init__(self, key: bytes, timestamp_file: str | Path | None, warn: Warn,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.key = key
        self.timestamp_file = Path(timestamp_file) if timestamp_file is not None else None
        self.rejected: Counter[str] = Counter()
        self._warn, self._clock = warn, clock
        self._mav: Any = None
        self._failed = False  # the frame being parsed failed check(): unsigned() must not count it again
        self._persisted_s = -math.inf

    def initial_timestamp(self) -> int:
        """Now, or just after the persisted timestamp if the clock is behind it."""
        return max(signing_timestamp_now(), read_signing_timestamp(self.timestamp_file) + 1)

    def install(self, conn: Any) -> None:
        """Sign everything `conn` sends; check everything it receives with our rules."""
        conn.setup_signing(self.key, sign_outgoing=True, allow_unsigned_callback=self.unsigned,
                           initial_timestamp=self.initial_timestamp(), link_id=0)
        self.attach(conn.mav)
        self.persist()

    def attach(self, mav: Any) -> None:
        """Our checks on a pymavlink MAVLink object whose signing key is already set."""
        self._mav = mav
        mav.signing.allow_unsigned_callback = self.unsigned
        mav.check_signature = self.check

    def unsigned(self, mav: Any, msg_id: int) -> bool:
        """pymavlink's callback for a frame it would reject: unsigned ones are counted here."""
        if self._failed:
            self._failed = False  # already counted by check()
            return False
        self.rejected["unsigned"] += 1
        self._warn("unsigned", "unsigned MAVLink frame (message %d) rejected [%d so far]", msg_id,
                   self.rejected["unsigned"])
        return False

    def check(self, msgbuf: bytearray, src_sys: int, src_comp: int) -> bool:
        """The hash first, then the timestamp; True when the frame is authentic and new."""
        signing = self._mav.signing
        link_id = msgbuf[-13]
        low, high = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
        timestamp = low + (high << 32)
        digest = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        if digest != bytes(msgbuf[-6:]):
            why = "wrong key"
        else:
            stream = (link_id, src_sys, src_comp)
            last = signing.stream_timestamps.get(stream)
            stale = last is None and timestamp + NEW_STREAM_WINDOW < signing.timestamp
            if (last is not None and timestamp <= last) or stale:
                why = "replayed"
            else:
                signing.stream_timestamps[stream] = timestamp
                signing.timestamp = max(signing.timestamp, timestamp)
                return True
        self._failed = True
        self.rejected[why] += 1
        self._warn(why, "MAVLink frame from system %d rejected: %s signature [%d so far]", src_sys, why,
                   self.rejected[why])
        return False

    def tick(self, tx_lock: threading.Lock) -> None:
        """Keep the timestamp at least at real time; persist it every PERSIST_PERIOD_S."""
        with tx_lock:  # pymavlink increments it on every signed send
            self._mav.signing.timestamp = max(self._mav.signing.timestamp, signing_timestamp_now())
        if self._clock() - self._persisted_s >= PERSIST_PERIOD_S:
            self.persist()

    def persist(self) -> None:
        if self._mav is None:
            return
        try:
            write_signing_timestamp(self.timestamp_file, self._mav.signing.timestamp)
        except OSError as exc:
            self._warn("persist", "signing timestamp not persisted to %s: %s", self.timestamp_file, exc)
        self._persisted_s = self._clock()
