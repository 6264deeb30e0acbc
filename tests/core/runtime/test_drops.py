"""Counted, logged drops: a flood is counted in full but logged sparingly; a guarded callback
turns any exception into a drop."""

from __future__ import annotations

import logging

import pytest

from zoffload.runtime.drops import Drops


def test_a_flood_is_counted_in_full_and_logged_sparingly(caplog: pytest.LogCaptureFixture) -> None:
    drops = Drops(logging.getLogger("test.drops"), first=3, every=100)
    with caplog.at_level(logging.WARNING, "test.drops"):
        for i in range(1000):
            drops.drop("malformed", f"message {i}")
        drops.drop("other", "x" * 10_000)
    assert drops.snapshot() == {"malformed": 1000, "other": 1} and drops.total() == 1001
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3 + 10 + 1  # the first three, every hundredth, the other reason's first
    assert "1000 so far" in lines[-2] and len(lines[-1]) < 400


def test_guard_counts_whatever_a_callback_raises() -> None:
    drops = Drops(logging.getLogger("test.drops"))
    seen: list[int] = []

    def callback(x: int) -> None:
        seen.append(x)
        if x % 2:
            raise KeyError(x)

    guarded = drops.guard(callback, "ack")
    for x in range(6):
        guarded(x)  # never raises
    assert seen == list(range(6)) and drops.snapshot() == {"callback_error": 3}
