"""A CPU quota for the robot process, as the offloading thesis limited its robot container.

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

log = logging.getLogger("zoffload.robot.quota")

PERIOD_US = 100_000
V1 = Path("/sys/fs/cgroup/cpu")
V2 = Path("/sys/fs/cgroup")


def apply_cpu_quota(cores: float, name: str | None = None) -> str:
    """Limit this process to ``cores`` CPUs; returns "cgroup-v1", "cgroup-v2" or "threads"."""
    name = name or f"zoffload-robot-{os.getpid()}"
    quota_us = max(1000, int(cores * PERIOD_US))
    pid = str(os.getpid())
    if (V1 / "cpu.cfs_quota_us").exists():
        group = V1 / name
        try:
            group.mkdir(exist_ok=True)
            (group / "cpu.cfs_period_us").write_text(str(PERIOD_US))
            (group / "cpu.cfs_quota_us").write_text(str(quota_us))
            (group / "cgroup.procs").write_text(pid)
            atexit.register(_leave, V1, group)
            log.info("CPU quota %.2f cores via %s", cores, group)
            return "cgroup-v1"
        except OSError as exc:
            log.warning("cgroup v1 quota not applied (%s)", exc)
    if (V2 / "cgroup.controllers").exists():
        group = V2 / name
        try:
            group.mkdir(exist_ok=True)
            (group / "cpu.max").write_text(f"{quota_us} {PERIOD_US}")
            (group / "cgroup.procs").write_text(pid)
            atexit.register(_leave, V2, group)
            log.info("CPU quota %.2f cores via %s", cores, group)
            return "cgroup-v2"
        except OSError as exc:
            log.warning("cgroup v2 quota not applied (%s)", exc)
    log.warning("no writable cgroup: limiting detector threads to %d instead of a CPU quota",
                math.ceil(cores))
    return "threads"


def _leave(root: Path, group: Path) -> None:
    """At exit: move this process back to the root group and remove its own (now empty) group."""
    try:
        (root / "cgroup.procs").write_text(str(os.getpid()))
        group.rmdir()
    except OSError as exc:  # threads still exiting keep it busy: the group stays, harmless
        log.debug("cgroup %s not removed: %s", group, exc)
