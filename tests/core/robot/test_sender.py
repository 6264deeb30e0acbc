"""The sender thread's one-slot handoff: the loop never waits, the newest item replaces an unsent
one, a failing send does not end the thread, closing returns what was never sent."""

from __future__ import annotations

import threading
import time

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
