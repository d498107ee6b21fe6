"""Keeps the memory a process frees for its own next allocations (glibc's malloc), once per process.

glibc hands a freed block of 128 KiB or more straight back to the system, and trims the top of
its heap once a little more than that lies free there (both thresholds rise as it sees large
blocks freed, by amounts that depend on the order things happened in). A loop that allocates and
frees a few MB of numpy and OpenCV arrays a frame, as the simulated perception does, then takes
much of the same memory back from the system every frame, and each 4 KiB page of it costs a page
fault and a zeroing when first written. Measured over the simulated perception (one process per
run, one core): `bench_rates` took 215 faults a heatmap for `realistic` and `harsh` and 1,485 for
`clean`, 4-6 with the thresholds raised here, for 1.2-1.4x the heatmaps per CPU second (`clean`
2.5-2.7x). How many a process takes without this is luck, the heap's history: over other frames
the same code took 13-20 a frame. So the thresholds are set, not left to that history.

The price: the heap stays at its peak instead of breathing (the perception's peak resident size
was the same either way, 118-119 MB over those frames), and blocks up to `MMAP_THRESHOLD_BYTES`
come from the heap rather than maps of their own.
Elsewhere (musl, macOS, Windows) nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys
import threading

log = logging.getLogger(__name__)

# mallopt parameters (malloc.h) and the values set: blocks below 8 MiB come from the heap (the
# perception's largest is under 2 MiB), and up to 64 MiB may lie free at its top before a trim.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 8 << 20
TRIM_THRESHOLD_BYTES = 64 << 20

_lock = threading.Lock()
_kept: bool | None = None  # None: not tried yet in this process


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process (the first call does it; later calls
    return its result). True when they were set, False where malloc is not glibc's."""
    global _kept
    with _lock:
        if _kept is None:
            _kept = _set_thresholds()
            if _kept:
                log.info("malloc keeps freed memory: mmap threshold %d MiB, trim threshold %d MiB",
                         MMAP_THRESHOLD_BYTES >> 20, TRIM_THRESHOLD_BYTES >> 20)
        return _kept


def _set_thresholds() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return False
    # Only glibc's parameter numbers are known here (gnu_get_libc_version is glibc's own symbol).
    if not (hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt")):
        return False
    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # mallopt returns 1 on success; setting either threshold stops glibc moving both on its own.
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
