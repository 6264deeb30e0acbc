"""The sender thread's one-slot handoff: the loop never waits, the newest item replaces an unsent
one, a failing send does not end the thread, closing returns what was never sent; an item its gate
holds goes when poked and is given up for a newer one."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from zoffload.robot.sender import Sender


def test_a_blocked_send_never_blocks_the_offer_and_the_newest_item_waits() -> None:
    gate = threading.Event()
    sent: list[int] = []

    def send(item: int) -> None:
        gate.wait(5)  # a put() blocked on a congested link (BLOCK_FIRST)
        sent.append(item)

    s: Sender[int] = Sender(send)
    s.start()
    assert s.offer(1) is None
    time.sleep(0.05)  # the thread took item 1 and blocks on it
    t0 = time.perf_counter()
    assert s.offer(2) is None
    assert s.offer(3) == 2  # 2 never left: replaced by the newer scan
    assert s.offer(4) == 3
    assert time.perf_counter() - t0 < 0.05  # the offers did not wait for the link
    assert not s.idle
    gate.set()
    deadline = time.monotonic() + 5
    while not s.idle and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sent == [1, 4] and s.replaced == 2 and s.sent == 2
    assert s.close(1.0) is None


def test_a_failing_send_is_counted_and_the_thread_goes_on() -> None:
    sent: list[int] = []

    def send(item: int) -> None:
        if item == 1:
            raise RuntimeError("boom")
        sent.append(item)

    s: Sender[int] = Sender(send)
    s.start()
    s.offer(1)
    time.sleep(0.05)
    s.offer(2)
    assert s.close(2.0) is None
    assert sent == [2] and s.errors == 1


def test_close_hands_back_an_item_stuck_behind_a_dead_link() -> None:
    gate = threading.Event()
    s: Sender[int] = Sender(lambda item: None if gate.wait(10) else None)
    s.start()
    s.offer(1)
    time.sleep(0.05)
    s.offer(2)
    assert s.close(0.2) == 2  # 1 is stuck in its send, 2 never left
    gate.set()


def _wait_for(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.005)


def test_a_gated_item_waits_for_its_gate_and_goes_when_poked() -> None:
    room = [False]
    sent: list[int] = []
    s: Sender[int] = Sender(sent.append, gate=lambda item: room[0])
    s.start()
    s.offer(1)
    time.sleep(0.1)  # ten polls: the gate still says no
    assert sent == [] and not s.idle
    room[0] = True  # an ack freed a slot ...
    s.poke()  # ... and says so
    _wait_for(lambda: sent == [1])
    assert sent == [1] and s.held == 1 and s.given_up == 0
    assert s.close(1.0) is None


def test_a_held_item_is_given_up_for_a_newer_one_or_when_its_gate_says_so() -> None:
    sent: list[int] = []
    dropped: list[int] = []
    verdicts = {1: False, 2: True, 3: None}  # 1 held (no room), 2 goes, 3 given up at once
    s: Sender[int] = Sender(sent.append, gate=verdicts.get, on_drop=dropped.append)
    s.start()
    s.offer(1)
    time.sleep(0.05)  # the thread holds 1 at its gate
    assert s.offer(2) is None  # the slot was empty: the thread took 1 out of it
    _wait_for(lambda: sent == [2])
    assert dropped == [1] and sent == [2]  # the newer item went, the held one was given up
    s.offer(3)
    _wait_for(lambda: dropped == [1, 3])
    assert dropped == [1, 3] and sent == [2] and s.given_up == 2 and s.held == 0


def test_closing_gives_up_a_held_item() -> None:
    dropped: list[int] = []
    s: Sender[int] = Sender(lambda item: None, gate=lambda item: False, on_drop=dropped.append)
    s.start()
    s.offer(1)
    time.sleep(0.05)
    assert s.close(1.0) is None and dropped == [1]
