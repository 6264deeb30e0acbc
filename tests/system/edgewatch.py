"""A real edge process seen from outside, for the abuse tests: its published status, its threads,
and its peak resident memory around one case (Linux: ``VmHWM``, reset through ``clear_refs``)."""

from __future__ import annotations

from pathlib import Path

import psutil
import zenoh

from tests.helpers import KEYS, wait_for
from zoffload.protocol import wire


class EdgeWatch:
    def __init__(self, session: zenoh.Session, pid: int, edge: str = "edge1") -> None:
        self.pid = pid
        self.proc = psutil.Process(pid)
        self.values: dict[str, float] = {}
        self.statuses = 0
        self._sub = session.declare_subscriber(KEYS.edge_status(edge), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        self.values = dict(wire.decode(sample.payload.to_bytes(), expect=wire.Status).values)
        self.statuses += 1

    def value(self, name: str) -> float:
        return self.values.get(name, 0.0)

    def wait(self, name: str, at_least: float, timeout: float = 30.0) -> None:
        wait_for(lambda: self.value(name) >= at_least, timeout, f"edge status {name} >= {at_least}")

    def settle(self, timeout: float = 30.0) -> None:
        """Until the edge's status reports every sample it received as accounted for (a scan
        naming another edge is counted as ``other_edge``: a mutated ``Scan.edge`` does that)."""
        wait_for(lambda: self.value("samples") == self.value("received") + self.value("drops")
                 + self.value("other_edge") and self.statuses > 0,
                 timeout, "the edge to account for every sample")

    def alive(self) -> bool:
        return self.proc.is_running() and self.proc.status() != psutil.STATUS_ZOMBIE

    def threads(self) -> int:
        return self.proc.num_threads()

    def rss_mb(self) -> float:
        return self.proc.memory_info().rss / 2**20

    def reset_peak(self) -> float:
        """Reset the peak RSS to the current RSS; returns the current RSS in MB."""
        Path(f"/proc/{self.pid}/clear_refs").write_text("5")
        return self.rss_mb()

    def peak_mb(self) -> float:
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
        raise AssertionError("no VmHWM in /proc/PID/status")

    def close(self) -> None:
        self._sub.undeclare()
