"""Give the C allocator's free memory back to the system, now and then.

A daemon that runs for days allocates and frees point clouds of every size on several threads
(KISS-ICP's workers, the grid pass, Zenoh's buffers). glibc keeps what is freed in per-thread
arenas for reuse, and fragmented arenas are not returned on their own: in the 1 h soak the edge's
RSS grew from 876 to 1,007 MB while only about 520 MB was in use, and one ``malloc_trim(0)``
(called from gdb at the end) brought it to 713 MB and the robot's from 399 to 339 MB. So the
daemons call ``malloc_trim(0)`` every ``period`` seconds from their status loop (a few ms; off
the scan path). Where the C library has no ``malloc_trim`` (musl, macOS), it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import time
from collections.abc import Callable

log = logging.getLogger("zoffload.runtime.memory")


def _load_trim() -> Callable[[int], int] | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


_TRIM = _load_trim()


def trim_heap() -> bool:
    """Return the allocator's free pages to the system; False where that is not available."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


class HeapTrimmer:
    """Calls ``trim_heap`` at most every ``period`` seconds (0: never) when ``maybe`` is called."""

    def __init__(self, period: float = 60.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.period = period
        self.clock = clock
        self.trims = 0
        self.seconds = 0.0  # wall time spent trimming
        self._next = clock() + period

    def maybe(self) -> bool:
        if self.period <= 0 or _TRIM is None:
            return False
        now = self.clock()
        if now < self._next:
            return False
        self._next = now + self.period
        t0 = time.perf_counter()
        trim_heap()
        self.seconds += time.perf_counter() - t0
        self.trims += 1
        return True
