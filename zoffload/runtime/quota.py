"""A CPU quota for the robot process, as the offloading thesis limited its robot container (and,
in the fleet experiment, for edge processes, as a container's ``cpus`` would).

With root and a cgroup-v1 ``cpu`` hierarchy (``/sys/fs/cgroup/cpu``) or cgroup v2 (``cpu.max``),
the process moves itself into its own group with ``quota`` cores of CFS time per 100 ms period;
all its threads (onnxruntime's included) share that budget. Where neither is writable, the
fallback is a thread limit: onnxruntime gets ``ceil(quota)`` threads, which caps parallelism but
not the time share, and the result says which one was applied.
"""

from __future__ import annotations

import atexit
import logging
import math
import os
from pathlib import Path

log = logging.getLogger("zoffload.runtime.quota")

PERIOD_US = 100_000
V1 = Path("/sys/fs/cgroup/cpu")
V2 = Path("/sys/fs/cgroup")


def apply_cpu_quota(cores: float, name: str | None = None) -> str:
    """Limit this process to ``cores`` CPUs; returns "cgroup-v1", "cgroup-v2" or "threads"."""
    how, group = limit_process(os.getpid(), cores, name or f"zoffload-robot-{os.getpid()}")
    if group is not None:
        atexit.register(_leave, group.parent, group)
        return how
    log.warning("no writable cgroup: limiting detector threads to %d instead of a CPU quota",
                math.ceil(cores))
    return "threads"


def limit_process(pid: int, cores: float, name: str) -> tuple[str, Path | None]:
    """Put process ``pid`` (every thread of it) in a new cgroup ``name`` with ``cores`` CPUs of CFS
    time: ("cgroup-v1" or "cgroup-v2", the group), or ("none", None) where no cgroup is writable.
    The caller removes the group (``remove_group``) once the process is gone."""
    quota_us = max(1000, int(cores * PERIOD_US))
    # v1: period and quota files; v2: one cpu.max ("quota period"). Written in this order.
    for version, root, probe, limits in (
        ("v1", V1, "cpu.cfs_quota_us",
         {"cpu.cfs_period_us": str(PERIOD_US), "cpu.cfs_quota_us": str(quota_us)}),
        ("v2", V2, "cgroup.controllers", {"cpu.max": f"{quota_us} {PERIOD_US}"}),
    ):
        if not (root / probe).exists():
            continue
        group = root / name
        try:
            group.mkdir(exist_ok=True)
            for file, value in limits.items():
                (group / file).write_text(value)
            (group / "cgroup.procs").write_text(str(pid))
            log.info("CPU quota %.2f cores for process %d via %s", cores, pid, group)
            return f"cgroup-{version}", group
        except OSError as exc:
            log.warning("cgroup %s quota for process %d not applied (%s)", version, pid, exc)
            remove_group(group)  # made here, left empty
    return "none", None


def remove_group(group: Path) -> bool:
    """Remove a group made by ``limit_process`` whose processes have exited; False if it stays."""
    try:
        group.rmdir()
        return True
    except OSError as exc:  # still a process in it (or already gone)
        log.debug("cgroup %s not removed: %s", group, exc)
        return not group.exists()


def _leave(root: Path, group: Path) -> None:
    """At exit: move this process back to the root group and remove its own (now empty) group."""
    try:
        (root / "cgroup.procs").write_text(str(os.getpid()))
        group.rmdir()
    except OSError as exc:  # threads still exiting keep it busy: the group stays, harmless
        log.debug("cgroup %s not removed: %s", group, exc)
