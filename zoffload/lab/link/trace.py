"""Link traces: piecewise-constant link conditions over time, per direction.

File format (CSV, ``#`` starts a comment, a header line is required)::

    time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage
    0,      300,     300,       2,        1,         0
    20,     40,      40,        10,       5,         0
    41.5,   0,       0,         0,        0,         1

Each row holds from its ``time_s`` until the next row's; the last row holds for ever (or the trace
repeats with ``loop``). ``up`` is robot -> edge, ``down`` edge -> robot. ``delay_ms`` is one-way
and applies to each direction; ``jitter_ms`` is the standard deviation of extra delay (order is
kept, as on a TCP link). ``outage`` 1 stalls both directions: nothing passes, data waits (a TCP
connection over a dead Wi-Fi link retransmits until it comes back). ``up_mbps = 0`` without an
outage is an error: say ``outage`` instead.
"""

from __future__ import annotations

import bisect
import csv
import io
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

COLUMNS = ("time_s", "up_mbps", "down_mbps", "delay_ms", "jitter_ms", "outage")


class TraceError(ValueError):
    """A trace file that cannot be used; the message names the file and line."""


@dataclass(frozen=True)
class LinkState:
    up_mbps: float
    down_mbps: float
    delay_ms: float
    jitter_ms: float
    outage: bool

    def rate_bps(self, direction: str) -> float:
        """Bytes per second allowed in ``direction`` ("up" or "down"); 0 during an outage."""
        if self.outage:
            return 0.0
        return (self.up_mbps if direction == "up" else self.down_mbps) * 1e6 / 8


@dataclass(frozen=True)
class Trace:
    name: str
    times: tuple[float, ...]
    states: tuple[LinkState, ...]
    loop: bool = False

    @property
    def duration(self) -> float:
        """Start time of the last row (the length of one pass when looping)."""
        return self.times[-1]

    def at(self, t: float) -> LinkState:
        if t < 0:
            t = 0.0
        if self.loop and self.duration > 0:
            t = t % self.duration
        return self.states[bisect.bisect_right(self.times, t) - 1]

    def next_change(self, t: float) -> float | None:
        """Seconds from ``t`` to the next row boundary (None if the state holds for ever)."""
        base = 0.0
        if self.loop and self.duration > 0:
            base = t - (t % self.duration)
            t = t % self.duration
        i = bisect.bisect_right(self.times, t)
        if i < len(self.times):
            return base + self.times[i] - (base + t)
        if self.loop and self.duration > 0:
            return self.duration - t
        return None


def constant(up_mbps: float, down_mbps: float | None = None, delay_ms: float = 0.0,
             jitter_ms: float = 0.0, name: str = "constant") -> Trace:
    state = LinkState(up_mbps, up_mbps if down_mbps is None else down_mbps, delay_ms, jitter_ms, False)
    return Trace(name=name, times=(0.0,), states=(state,))


def parse_trace(text: str, name: str = "trace", loop: bool = False) -> Trace:
    """Parse the CSV format above; ``TraceError`` names the line and the problem."""
    rows: list[tuple[int, list[str]]] = []
    for lineno, line in enumerate(io.StringIO(text), start=1):
        stripped = line.split("#", 1)[0].strip()
        if stripped:
            rows.append((lineno, next(csv.reader([stripped]))))
    if not rows:
        raise TraceError(f"{name}: empty trace")
    header_line, header = rows[0]
    header = [h.strip() for h in header]
    if tuple(header) != COLUMNS:
        raise TraceError(
            f"{name}:{header_line}: header must be {', '.join(COLUMNS)}; got {', '.join(header)}"
        )
    times: list[float] = []
    states: list[LinkState] = []
    for lineno, cells in rows[1:]:
        where = f"{name}:{lineno}"
        if len(cells) != len(COLUMNS):
            raise TraceError(f"{where}: {len(cells)} values where {len(COLUMNS)} are expected")
        try:
            t, up, down, delay, jitter = (float(c) for c in cells[:5])
            outage_raw = cells[5].strip().lower()
        except ValueError as exc:
            raise TraceError(f"{where}: not a number ({exc})") from exc
        if outage_raw not in ("0", "1", "true", "false"):
            raise TraceError(f"{where}: outage must be 0 or 1, got {cells[5].strip()!r}")
        outage = outage_raw in ("1", "true")
        if any(x != x or x < 0 for x in (t, up, down, delay, jitter)):
            raise TraceError(f"{where}: values must be non-negative numbers")
        if not outage and (up == 0 or down == 0):
            raise TraceError(f"{where}: a rate of 0 Mbps: mark the row as an outage instead")
        if not times and t != 0:
            raise TraceError(f"{where}: the first row must start at time 0")
        if times and t <= times[-1]:
            raise TraceError(f"{where}: time {t} does not increase (previous row at {times[-1]})")
        times.append(t)
        states.append(LinkState(up, down, delay, jitter, outage))
    if not times:
        raise TraceError(f"{name}: no rows after the header")
    return Trace(name=name, times=tuple(times), states=tuple(states), loop=loop)


def shipped_traces() -> list[str]:
    folder = resources.files("zoffload.lab.link") / "traces"
    return sorted(p.name[:-4] for p in folder.iterdir() if p.name.endswith(".csv"))


def load_trace(spec: str, loop: bool = False) -> Trace:
    """A shipped trace by name (``wifi-locations``), or a CSV file path."""
    folder = resources.files("zoffload.lab.link") / "traces"
    shipped = folder / f"{spec}.csv"
    if shipped.is_file():
        return parse_trace(shipped.read_text(), name=spec, loop=loop)
    path = Path(spec)
    if not path.is_file():
        raise TraceError(f"no trace {spec!r}: not a file, and not one of {', '.join(shipped_traces())}")
    return parse_trace(path.read_text(), name=str(path), loop=loop)
