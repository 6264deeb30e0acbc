"""A process with the processes it started, measured as one: the edge's mappers run in processes
of their own (edge/isolate.py), and a figure "of the edge" (its CPU, its memory, its threads and
fds) must keep counting what they do. ``psutil``'s own CPU times count a child only once its
parent has waited for it; the children still running are added here."""

from __future__ import annotations

from typing import Any


def tree_cpu_s(proc: Any) -> float:
    """CPU seconds (user + system) of ``proc`` (a ``psutil.Process``), of its children it has
    reaped, and of those still running (raises ``psutil.Error`` when ``proc`` is gone)."""
    import psutil

    t = proc.cpu_times()
    total = float(t.user + t.system + t.children_user + t.children_system)
    for child in proc.children(recursive=True):
        try:
            ct = child.cpu_times()
        except psutil.Error:  # gone between the listing and the reading: counted once reaped
            continue
        total += float(ct.user + ct.system)
    return total


class TreeCpu:
    """``tree_cpu_s`` of one process, never less than it read before: a child that ended and was
    not yet reaped, or the children of a killed process (a zombie until reaped, its children no
    longer listed), drop out of the sum."""

    def __init__(self, proc: Any) -> None:
        self.proc = proc
        self.cpu_s = 0.0

    def read(self) -> float:
        """The process tree's CPU seconds now (raises ``psutil.Error`` when ``proc`` is gone)."""
        self.cpu_s = max(tree_cpu_s(self.proc), self.cpu_s)
        return self.cpu_s


def tree_resources(proc: Any) -> dict[str, float]:
    """Resident memory (MB), threads and open fds of ``proc`` and its running children, summed
    (raises ``psutil.Error`` when ``proc`` is gone)."""
    import psutil

    with proc.oneshot():
        values: dict[str, float] = {"rss_mb": proc.memory_info().rss / 2**20,
                                    "threads": proc.num_threads(), "fds": proc.num_fds()}  # (ints)
    for child in proc.children(recursive=True):
        try:
            with child.oneshot():
                values["rss_mb"] += child.memory_info().rss / 2**20
                values["threads"] += child.num_threads()
                values["fds"] += child.num_fds()
        except psutil.Error:
            continue
    return values
