"""A sensor thread that replays a source (LiDAR scans or camera frames) at its rate, like a real
driver: it never waits for the consumer. Only the newest reading is kept; one overwritten before it
was taken is counted. The thread's CPU time is kept (``cpu_s``): a replayed or simulated sensor
runs in the robot's process, and its work is not the robot's offloading work.

A live topic paces itself, and its real rate is not always the nominal one (a driver at 9.4 Hz,
a 20 Hz sensor under the default 10 Hz): ``period_now`` is then the median gap between the last
readings, the period the scan policies judge lateness by (at the nominal period, a topic a few
per cent slower than it reads as a late link on every scan)."""

from __future__ import annotations

import logging
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Protocol

from zoffload.sources.base import ReplayClock, ScanSourceError, replay_order

log = logging.getLogger("zoffload.robot.sensor")


class FrameSource(Protocol):
    """Anything with a length and frames by index: scan sources and image sources alike."""

    name: str
    rate_hz: float

    def __len__(self) -> int: ...

    def read(self, index: int) -> Any: ...


@dataclass(frozen=True)
class Reading:
    seq: int  # 0, 1, 2, ... over the whole replay
    frame: Any  # a ScanFrame or an ImageFrame
    capture_stamp: float  # robot wall clock when the scan was complete


GAPS_KEPT = 50  # live topics: the gaps the measured period is the median of
GAPS_NEEDED = 3  # ... and how many before it replaces the nominal period
GAP_MOST = 1.0  # [s] a longer gap (a driver paused) is a pause, not the rate; 5 periods if longer
# A reading the source cannot read (a truncated file, a malformed message: ScanSourceError) is
# skipped and counted (``read_errors``); this many in a row end the replay as a failed source
READ_ERRORS_IN_A_ROW = 10
SKIPS_LOGGED, SKIPS_LOGGED_EVERY = 10, 100  # the first skipped readings logged, then every 100th


class SensorThread:
    def __init__(self, source: FrameSource, rate_hz: float, mode: str = "once",
                 max_scans: int | None = None, name: str = "sensor") -> None:
        self.source = source
        self.period = 1.0 / rate_hz
        self.mode = mode
        self.max_scans = max_scans
        self.produced = 0
        self.overwritten = 0
        self.read_errors = 0  # readings that failed: each skipped, or the one that ended the replay
        self.failed: str | None = None  # why the replay ended early (None: it did not)
        self.resynced = 0  # readings more than a period late: the replay clock restarted at them
        self.cpu_s = 0.0  # CPU time of this thread so far (reading, simulating, pacing)
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._slot: Reading | None = None
        self._gaps: deque[float] = deque(maxlen=GAPS_KEPT)  # live topics: seconds between readings
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        start = time.monotonic()
        live = bool(getattr(self.source, "live", False))
        # A spinning sensor delivers a scan every period, whoever listens; a bag's frames come as
        # far apart as they were recorded (stretched to --rate); a live topic paces itself
        clock = ReplayClock(start, self.period, live=live, scale=self.period * self.source.rate_hz)
        last: float | None = None
        in_a_row = 0  # unreadable readings in a row
        last_error = ""
        try:
            for k, index in enumerate(replay_order(len(self.source), self.mode)):
                if self._stop.is_set() or (self.max_scans is not None and k >= self.max_scans):
                    break
                try:
                    frame = self.source.read(index)  # a live topic's: waits for its next message
                except ScanSourceError as exc:  # one unreadable scan (a truncated file): skipped
                    if self._stop.is_set():  # the source closed under a read at shutdown
                        break
                    self.cpu_s = time.thread_time()
                    self.read_errors += 1
                    in_a_row += 1
                    if in_a_row >= READ_ERRORS_IN_A_ROW:
                        raise ScanSourceError(f"{in_a_row} readings in a row failed, the last: "
                                              f"{exc}") from exc
                    if self.read_errors <= SKIPS_LOGGED or self.read_errors % SKIPS_LOGGED_EVERY == 0:
                        log.warning("%s: reading %d skipped (%d so far): %s", self._thread.name, index,
                                    self.read_errors, exc)
                    last_error = str(exc)
                    clock.skip()  # it keeps its slot: the next reading comes a period later
                    continue
                in_a_row = 0
                self.cpu_s = time.thread_time()
                due, mono = clock.due(getattr(frame, "stamp", None)), time.monotonic()
                if clock.behind(mono):  # no burst of overdue readings
                    self.resynced += 1
                    due = mono
                delay = due - mono
                if delay > 0 and self._stop.wait(delay):
                    break
                if live:  # never waited above (a live reading is due at once): ``mono`` is now
                    if last is not None and 0 < mono - last <= max(GAP_MOST, 5 * self.period):
                        with self._cond:
                            self._gaps.append(mono - last)
                    last = mono
                now, stamp = time.time(), getattr(frame, "stamp", None)
                # A live topic's header stamp is when the sensor completed the scan (same clock)
                capture = stamp if live and stamp is not None and abs(stamp - now) < 5.0 else now
                reading = Reading(seq=k, frame=frame, capture_stamp=capture)
                with self._cond:
                    if self._slot is not None:
                        self.overwritten += 1
                    self._slot = reading
                    self.produced += 1
                    self._cond.notify()
            if self.produced == 0 and self.read_errors:
                self.failed = (f"none of its readings could be read ({self.read_errors} failed, the "
                               f"last: {last_error})")
                log.error("%s source failed: %s", self._thread.name, self.failed)
        except Exception as exc:  # a source failing mid-run ends the replay, it is logged
            if self._stop.is_set():  # closed under a read at shutdown: not a failure
                return
            if not isinstance(exc, ScanSourceError):
                self.read_errors += 1
            self.failed = str(exc)[:500]
            log.error("%s source failed: %s", self._thread.name, exc)
        finally:
            self.cpu_s = time.thread_time()
            self.finished.set()
            with self._cond:
                self._cond.notify_all()

    def period_now(self) -> float:
        """The sensor's period: a live topic's measured one (the median of the last gaps between
        its readings) once it has a few, else the nominal ``1 / rate_hz``."""
        with self._cond:
            gaps = list(self._gaps)
        return statistics.median(gaps) if len(gaps) >= GAPS_NEEDED else self.period

    def take(self, timeout: float) -> Reading | None:
        """The newest unread scan, waiting up to ``timeout``; None if none came."""
        with self._cond:
            if self._slot is None and not self.finished.is_set():
                self._cond.wait(timeout)
            reading, self._slot = self._slot, None
            return reading

    @property
    def exhausted(self) -> bool:
        with self._cond:
            return self.finished.is_set() and self._slot is None
