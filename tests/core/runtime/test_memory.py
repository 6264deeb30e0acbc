"""Returning the allocator's free memory: real glibc, a pattern that leaves freed memory behind."""

from __future__ import annotations

import threading

import numpy as np
import psutil
import pytest

from zoffload.runtime.memory import _TRIM, HeapTrimmer, trim_heap

pytestmark = pytest.mark.skipif(_TRIM is None, reason="no malloc_trim in this C library (not glibc)")


def _rss_mb() -> float:
    return psutil.Process().memory_info().rss / 2**20


def test_trim_returns_memory_freed_on_another_thread() -> None:
    """Many small arrays allocated on a worker thread (its own arena, below the mmap threshold),
    most of them freed, a few kept scattered among them: RSS stays up until a trim."""
    kept: list[np.ndarray] = []

    def work() -> None:
        arrays = [np.ones(8_000) for _ in range(6_000)]  # 64 kB each (under the mmap threshold): 390 MB
        kept.extend(arrays[::200])  # every 200th survives: the arena cannot shrink from the top
        arrays.clear()

    t = threading.Thread(target=work)
    t.start()
    t.join()
    before = _rss_mb()
    assert trim_heap()
    after = _rss_mb()
    assert before - after > 100, (before, after)  # of the ~390 MB freed, most goes back
    assert len(kept) == 30


def test_the_trimmer_keeps_its_period() -> None:
    now = [0.0]
    trimmer = HeapTrimmer(period=60.0, clock=lambda: now[0])
    assert not trimmer.maybe()
    now[0] = 61.0
    assert trimmer.maybe() and trimmer.trims == 1
    now[0] = 100.0
    assert not trimmer.maybe()
    now[0] = 121.5
    assert trimmer.maybe() and trimmer.trims == 2
    assert not HeapTrimmer(period=0.0, clock=lambda: 1e9).maybe()
