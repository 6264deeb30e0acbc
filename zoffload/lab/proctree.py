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
