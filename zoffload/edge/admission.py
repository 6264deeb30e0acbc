"""Which robots the edge serves. A robot id comes from a key any sender can write, so state on the
edge (a mapper, a queue, a publisher) is created only for an admitted robot: one in the allowlist,
or, without an allowlist, one of the first ``max_robots`` ids seen. A robot silent for
``idle_timeout`` seconds is expired by the server's housekeeping, which frees its place, and each
service then drops its state (the mapping service exports the map first).

Refused senders are answered so a misconfigured robot learns why, but at most ``refusals_per_s``
answers a second across all of them (a token bucket): a flood of ids costs a counter, not a
message each.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterable


class Admission:
    def __init__(self, allow: Iterable[str] = (), max_robots: int = 16, idle_timeout: float = 300.0,
                 refusals_per_s: float = 20.0) -> None:
        self.allow = frozenset(allow)
        self.max_robots = max_robots
        self.idle_timeout = idle_timeout
        self.refusals_per_s = refusals_per_s
        self.counters: Counter[str] = Counter()
        self._last: dict[str, float] = {}  # admitted robot -> last activity (monotonic)
        self._tokens = refusals_per_s  # bucket of one second's refusals
        self._refill: float | None = None
        self._lock = threading.Lock()

    def admit(self, robot: str, now: float | None = None) -> bool:
        """Whether ``robot`` is served; admits it if there is room. Marks it active."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if robot in self._last:
                self._last[robot] = now
                return True
            if self.allow and robot not in self.allow:
                self.counters["refused_not_allowed"] += 1
                return False
            if len(self._last) >= self.max_robots:
                self.counters["refused_full"] += 1
                return False
            self._last[robot] = now
            self.counters["admitted"] += 1
            return True

    def why_refused(self, robot: str) -> str:
        if self.allow and robot not in self.allow:
            return f"robot {robot!r} is not in this edge's allowlist"
        return f"this edge serves at most {self.max_robots} robots"

    def answer_refusal(self, now: float | None = None) -> bool:
        """Whether a refusal may be answered now (else it is only counted)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if self._refill is not None:
                self._tokens = min(self.refusals_per_s,
                                   self._tokens + max(0.0, now - self._refill) * self.refusals_per_s)
            self._refill = now
            if self._tokens >= 1.0:
                self._tokens -= 1.0
                self.counters["refusals_answered"] += 1
                return True
            self.counters["refusals_silent"] += 1
            return False

    def expire(self, now: float | None = None) -> list[str]:
        """Forget the robots silent for longer than ``idle_timeout`` and return them: the caller
        drops their state. A robot that sends again afterwards is admitted anew, if there is room."""
        now = time.monotonic() if now is None else now
        with self._lock:
            gone = [r for r, t in self._last.items() if now - t > self.idle_timeout]
            for r in gone:
                del self._last[r]
            self.counters["evicted"] += len(gone)
        return gone

    def is_admitted(self, robot: str) -> bool:
        with self._lock:
            return robot in self._last

    @property
    def robots(self) -> list[str]:
        with self._lock:
            return list(self._last)

    def status(self) -> dict[str, float]:
        with self._lock:
            values = {f"admission.{k}": float(v) for k, v in self.counters.items()}
            values["admission.robots"] = float(len(self._last))
        return values
