"""A sender thread with a one-slot handoff: the sensor loop hands over the newest item and goes
back to the sensor, whatever the link does.

The thread takes items one at a time and calls ``send`` on each (for scans: compress, encode,
book, ``put()``). ``put()`` with congestion control BLOCK_FIRST may block on a congested link:
then only this thread waits. An item handed over while the previous one still waits in the slot
replaces it (``offer`` returns the replaced one, never sent, for the caller to book), so the link
always gets the newest scan next and the loop never blocks — the BLOCK_FIRST semantics (one
message waits for room, newer ones do not queue behind it) kept one level up.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")
log = logging.getLogger("zoffload.robot.sender")


class Sender(Generic[T]):
    def __init__(self, send: Callable[[T], None], name: str = "sender") -> None:
        self._send = send
        self._slot: T | None = None
        self._busy = False
        self._closing = False
        self._cond = threading.Condition()
        self.sent = 0
        self.replaced = 0
        self.errors = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def offer(self, item: T) -> T | None:
        """Hand ``item`` over; returns the item it replaced in the slot (not sent), if any."""
        with self._cond:
            old, self._slot = self._slot, item
            if old is not None:
                self.replaced += 1
            self._cond.notify()
        return old

    @property
    def idle(self) -> bool:
        """Nothing waiting and nothing being sent."""
        with self._cond:
            return self._slot is None and not self._busy

    def close(self, timeout: float) -> T | None:
        """Send what waits, within ``timeout``, then stop; returns an item still unsent (a send
        blocked on a dead link keeps its thread, a daemon, and its item is the caller's to book)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout)
        with self._cond:
            left, self._slot = self._slot, None
            self._cond.notify()
        return left

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._slot is None and not self._closing:
                    self._cond.wait()
                if self._slot is None:
                    return
                item, self._slot = self._slot, None
                self._busy = True
            try:
                self._send(item)
                self.sent += 1
            except Exception:  # one bad item must not end the thread
                self.errors += 1
                log.exception("sending failed")
            finally:
                with self._cond:
                    self._busy = False
