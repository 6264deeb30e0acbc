"""The robot's CPU quota really limits it (CFS through cgroups, as root) and is cleaned up."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from zoffload.runtime import quota

CHILD = """
import json, os, time
from zoffload.runtime.quota import apply_cpu_quota
how = apply_cpu_quota(0.2, name="zoffload-test-%d" % os.getpid())
t0, c0 = time.monotonic(), time.process_time()
while time.monotonic() - t0 < 1.0:
    pass
print(json.dumps({"how": how, "cpu": time.process_time() - c0, "pid": os.getpid()}))
"""


NEEDS_CGROUP = pytest.mark.skipif(os.geteuid() != 0 or not (quota.V1 / "cpu.cfs_quota_us").exists()
                                  and not (quota.V2 / "cgroup.controllers").exists(),
                                  reason="needs root and a cgroup cpu controller")
SPIN = "import time\nt0 = time.monotonic()\nwhile time.monotonic() - t0 < 30:\n    pass\n"


@NEEDS_CGROUP
def test_a_quarter_core_quota_holds_a_busy_loop_to_its_share() -> None:
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["how"].startswith("cgroup")
    assert 0.1 < r["cpu"] < 0.35  # 0.2 s of CPU in 1 s of spinning (unlimited: ~1 s)
    root = quota.V1 if r["how"] == "cgroup-v1" else quota.V2
    assert not (root / f"zoffload-test-{r['pid']}").exists()  # removed at exit


@NEEDS_CGROUP
def test_another_process_put_under_a_quota_from_outside() -> None:
    """The fleet experiment's edges: a child limited by its parent, its group removed once it
    exited (and kept while it runs)."""
    child = subprocess.Popen([sys.executable, "-c", SPIN])
    try:
        how, group = quota.limit_process(child.pid, 0.2, f"zoffload-test-child-{child.pid}")
        assert how.startswith("cgroup") and group is not None
        assert str(child.pid) in (group / "cgroup.procs").read_text().split()
        p = psutil.Process(child.pid)
        c0 = sum(p.cpu_times()[:2])
        time.sleep(1.0)
        used = sum(p.cpu_times()[:2]) - c0
        assert used < 0.35  # 0.2 s of CPU a second (unlimited: ~1 s)
        assert not quota.remove_group(group) and group.exists()  # still in use
    finally:
        child.kill()
        child.wait()
    assert quota.remove_group(group) and not group.exists()


def test_without_a_writable_cgroup_it_falls_back_to_threads(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(quota, "V1", tmp_path / "no-v1")
    monkeypatch.setattr(quota, "V2", tmp_path / "no-v2")
    assert quota.apply_cpu_quota(0.5) == "threads"
    assert quota.limit_process(os.getpid(), 0.5, "zoffload-test-none") == ("none", None)
