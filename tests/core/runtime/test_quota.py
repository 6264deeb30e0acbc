"""The robot's CPU quota really limits it (CFS through cgroups, as root) and is cleaned up."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

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


@pytest.mark.skipif(os.geteuid() != 0 or not (quota.V1 / "cpu.cfs_quota_us").exists()
                    and not (quota.V2 / "cgroup.controllers").exists(),
                    reason="needs root and a cgroup cpu controller")
def test_a_quarter_core_quota_holds_a_busy_loop_to_its_share() -> None:
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["how"].startswith("cgroup")
    assert 0.1 < r["cpu"] < 0.35  # 0.2 s of CPU in 1 s of spinning (unlimited: ~1 s)
    root = quota.V1 if r["how"] == "cgroup-v1" else quota.V2
    assert not (root / f"zoffload-test-{r['pid']}").exists()  # removed at exit


def test_without_a_writable_cgroup_it_falls_back_to_threads(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(quota, "V1", tmp_path / "no-v1")
    monkeypatch.setattr(quota, "V2", tmp_path / "no-v2")
    assert quota.apply_cpu_quota(0.5) == "threads"
