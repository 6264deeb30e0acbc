"""Counted, logged drops of what the network sent: the one way a daemon refuses input.

Every drop is counted by reason. The log names the first ``first`` drops of each reason and then
one in ``every``, with the running count, so a peer flooding a daemon with garbage cannot fill its
disk, and the counts still say exactly what was refused. ``guard`` wraps a Zenoh callback: any
exception it raises is such a drop (``callback_error``), never a traceback in Zenoh's thread.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


class Drops:
    def __init__(self, log: logging.Logger, first: int = 10, every: int = 1000) -> None:
        self.log = log
        self.first, self.every = first, every
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()

    def drop(self, reason: str, detail: str) -> None:
        with self._lock:
            self.counts[reason] += 1
            n = self.counts[reason]
        if n <= self.first or n % self.every == 0:
            self.log.warning("dropped (%s, %d so far): %s", reason, n, detail[:300])

    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)

    def guard(self, callback: Callable[[T], None], what: str) -> Callable[[T], None]:
        """``callback`` for a Zenoh subscriber or queryable: an exception is a counted drop."""

        def guarded(arg: T) -> None:
            try:
                callback(arg)
            except Exception as exc:  # whatever a message made it raise, the daemon carries on
                self.drop("callback_error", f"{what}: {exc.__class__.__name__}: {exc}")

        return guarded
