"""The sensor thread's period: a replay keeps the nominal one; a live topic's is measured from
the gaps between its readings (its real rate), leaving out pauses."""

from __future__ import annotations

import time

import numpy as np
import pytest

from zoffload.robot import sensor as sensor_mod
from zoffload.robot.sensor import SensorThread
from zoffload.sources.base import ScanSourceError


class Paced:
    """A source whose ``read`` takes ``gap`` seconds (a live topic waiting for its next message
    when ``live``); ``pause_at``: one read that takes ``pause`` instead."""

    name = "paced"

    def __init__(self, gap: float, live: bool, n: int = 12, pause_at: int = -1, pause: float = 0.0) -> None:
        self.gap, self.live, self.n, self.pause_at, self.pause = gap, live, n, pause_at, pause
        self.rate_hz = 10.0

    def __len__(self) -> int:
        return self.n

    def read(self, index: int) -> int:
        time.sleep(self.pause if index == self.pause_at else self.gap)
        return index


def run(source: Paced, rate_hz: float = 10.0) -> SensorThread:
    s = SensorThread(source, rate_hz)
    s.start()
    while not s.exhausted:
        s.take(0.05)
    s.stop()
    return s


def test_a_live_topic_s_period_is_measured() -> None:
    s = run(Paced(0.03, live=True))
    assert s.period == pytest.approx(0.1)
    assert 0.025 <= s.period_now() <= 0.07  # the topic's ~0.03 s, not the nominal 0.1


def test_a_replay_keeps_the_nominal_period() -> None:
    s = run(Paced(0.0, live=False, n=8), rate_hz=50.0)
    assert s.period_now() == pytest.approx(0.02)


def test_too_few_gaps_keep_the_nominal_period() -> None:
    s = run(Paced(0.01, live=True, n=sensor_mod.GAPS_NEEDED))  # n readings: n - 1 gaps
    assert s.period_now() == pytest.approx(0.1)


def test_a_pause_is_not_a_gap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sensor_mod, "GAP_MOST", 0.1)
    s = run(Paced(0.01, live=True, n=8, pause_at=4, pause=0.6), rate_hz=100.0)
    assert len(s._gaps) == 6  # 7 gaps, the pause left out
    assert s.period_now() < 0.05


def test_a_replay_that_fell_behind_restarts_its_clock_instead_of_bursting() -> None:
    # the first read takes 0.4 s (a simulator's start-up) at 20 Hz: the 7 readings after it were
    # all overdue and came back to back, 5 ms apart; now a period apart, none overwritten
    s = SensorThread(Paced(0.0, live=False, n=8, pause_at=0, pause=0.4), 20.0)
    stamps: list[float] = []
    s.start()
    while not s.exhausted:
        r = s.take(0.2)
        if r is not None:
            stamps.append(r.capture_stamp)
    s.stop()
    assert s.resynced == 1 and s.overwritten == 0 and len(stamps) == 8
    gaps = list(np.diff(stamps))
    assert min(gaps) >= 0.04, gaps


class Flaky:
    """A replay of ``n`` readings whose ``bad`` ones cannot be read (a truncated file)."""

    name = "flaky"
    rate_hz = 10.0
    live = False

    def __init__(self, n: int, bad: set[int]) -> None:
        self.n, self.bad = n, bad

    def __len__(self) -> int:
        return self.n

    def read(self, index: int) -> int:
        if index in self.bad:
            raise ScanSourceError(f"{index:04d}.pcd: 10 data bytes for 40 points (truncated?)")
        return index


def _taken(source: Flaky) -> tuple[SensorThread, list[int]]:
    # 50 Hz: the sensor keeps only its newest reading, and at 500 Hz a test thread held 20 ms on a
    # loaded host (CI 85) found readings 0 and 1 already replaced by 3
    s = SensorThread(source, 50.0)
    s.start()
    seqs = []
    while not s.exhausted:
        r = s.take(0.05)
        if r is not None:
            seqs.append(r.seq)
    s.stop()
    return s, seqs


def test_an_unreadable_reading_is_skipped_and_counted_and_keeps_its_slot() -> None:
    s, seqs = _taken(Flaky(6, {2}))
    assert seqs == [0, 1, 3, 4, 5] and s.produced == 5  # its seq is a gap: the edge bridges it
    assert s.read_errors == 1 and s.failed is None


def test_a_source_none_or_too_many_of_whose_readings_read_has_failed() -> None:
    s, seqs = _taken(Flaky(3, {0, 1, 2}))  # nothing to replay at all
    assert seqs == [] and s.read_errors == 3 and s.failed is not None
    assert s.failed.startswith("none of its readings could be read (3 failed") and "0002.pcd" in s.failed
    n = sensor_mod.READ_ERRORS_IN_A_ROW
    s, seqs = _taken(Flaky(3 * n, set(range(3, 3 * n))))  # a recording that breaks off
    assert seqs == [0, 1, 2] and s.read_errors == n
    assert s.failed is not None and s.failed.startswith(f"{n} readings in a row failed")


class ClosedAtShutdown:
    """A live topic with no message: its read waits until the source is closed, then raises
    (``LiveTopic.take``: "ros2:/x closed")."""

    name = "ros2:/points"
    rate_hz = 10.0
    live = True

    def __init__(self) -> None:
        import threading

        self.closed = threading.Event()

    def __len__(self) -> int:
        return 10

    def read(self, index: int) -> int:
        self.closed.wait(5)
        raise ScanSourceError(f"{self.name} closed")


def test_a_live_source_closed_under_a_read_at_shutdown_is_not_a_failed_source() -> None:
    src = ClosedAtShutdown()
    s = SensorThread(src, 10.0)
    s.start()
    time.sleep(0.1)
    s._stop.set()  # as stop() does, before the pipeline closes the source
    src.closed.set()
    s.stop()
    assert s.finished.is_set() and s.read_errors == 0 and s.failed is None


def test_skipped_readings_are_logged_first_then_now_and_then(caplog: pytest.LogCaptureFixture) -> None:
    """A looping replay over a bad file skips it on every pass: every skip is counted, the log
    keeps the first ``SKIPS_LOGGED`` and every ``SKIPS_LOGGED_EVERY``-th, not a line a pass."""
    n = 2 * (sensor_mod.SKIPS_LOGGED + 15)
    with caplog.at_level("WARNING", logger="zoffload.robot.sensor"):
        s, seqs = _taken(Flaky(n, set(range(1, n, 2))))  # every other reading unreadable
    assert s.read_errors == n // 2 and len(seqs) == n // 2 and s.failed is None
    assert sum("skipped" in r.getMessage() for r in caplog.records) == sensor_mod.SKIPS_LOGGED
