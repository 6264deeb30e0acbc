"""A sender thread with a one-slot handoff: the sensor loop hands over the newest item and goes
back to the sensor, whatever the link does.

The thread takes items one at a time and calls ``send`` on each (for scans: compress, encode,
book, ``put()``). ``put()`` with congestion control BLOCK_FIRST may block on a congested link:
then only this thread waits. An item handed over while the previous one still waits in the slot
replaces it (``offer`` returns the replaced one, never sent, for the caller to book), so the link
always gets the newest scan next and the loop never blocks — the BLOCK_FIRST semantics (one
message waits for room, newer ones do not queue behind it) kept one level up.

An optional ``gate`` holds an item back until it may go (for scans: a slot in the window of
unanswered ones): the thread asks it again on every ``poke()`` (an ack) and every ``POLL`` seconds,
and gives the item up (``on_drop``) when the gate says so or when a newer item is handed over.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")
log = logging.getLogger("zoffload.robot.sender")

POLL = 0.01  # seconds between the gate's checks on an item it holds, when nothing pokes


class Sender(Generic[T]):
    def __init__(self, send: Callable[[T], None], name: str = "sender",
                 gate: Callable[[T], bool | None] | None = None,
                 on_drop: Callable[[T], None] | None = None) -> None:
        """``gate(item)``: True to send it now, False to hold it, None to give it up; an item
        given up, or held when a newer one comes, goes to ``on_drop`` (never sent)."""
        self._send = send
        self._gate = gate
        self._on_drop = on_drop
        self._slot: T | None = None
        self._busy = False
        self._closing = False
        self._cond = threading.Condition()
        self.sent = 0
        self.replaced = 0
        self.errors = 0
        self.held = 0  # items the gate held before sending them
        self.given_up = 0  # items the gate held and never sent
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

    def poke(self) -> None:
        """Something the gate reads changed (an ack came): ask it again now."""
        with self._cond:
            self._cond.notify()

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
                if self._through_gate(item):
                    self._send(item)
                    self.sent += 1
            except Exception:  # one bad item must not end the thread
                self.errors += 1
                log.exception("sending failed")
            finally:
                with self._cond:
                    self._busy = False

    def _through_gate(self, item: T) -> bool:
        """Hold ``item`` while the gate says so; False when it was given up (and handed to
        ``on_drop``): the gate said so, a newer item came, or the sender is closing."""
        if self._gate is None:
            return True
        waited = False
        while True:
            verdict = self._gate(item)  # (outside the condition: the gate takes the caller's lock)
            if verdict:
                self.held += waited
                return True
            with self._cond:
                if verdict is not None and self._slot is None and not self._closing:
                    waited = True
                    self._cond.wait(POLL)
                    continue
            self.given_up += 1
            if self._on_drop is not None:
                self._on_drop(item)
            return False
