"""A process's figures count the processes it started (lab/proctree.py): the edge's mapper
processes' CPU and memory were missing from the fleet experiment's and the soak's edge figures."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from zoffload.lab.proctree import tree_cpu_s, tree_resources

psutil = pytest.importorskip("psutil")

# A parent that idles while the child it started burns CPU for a second and holds 50 MB
PARENT = """
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c",
    "import time\\nb = bytearray(50 * 2**20)\\nt = time.process_time()\\n"
    "while time.process_time() - t < 1.0: pass\\ntime.sleep(30)"])
time.sleep(30)
"""


def test_a_parents_figures_count_its_running_children() -> None:
    parent = subprocess.Popen([sys.executable, "-c", PARENT])
    try:
        p = psutil.Process(parent.pid)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and tree_cpu_s(p) - sum(p.cpu_times()[:2]) < 0.9:
            time.sleep(0.1)
        own = sum(p.cpu_times()[:2])
        assert tree_cpu_s(p) - own >= 0.9  # the child's second of CPU
        values = tree_resources(p)
        assert values["rss_mb"] - p.memory_info().rss / 2**20 >= 50
        assert values["threads"] >= 2 and values["fds"] >= 2
        assert isinstance(values["threads"], int) and isinstance(values["fds"], int)  # the soak's CSV counts
    finally:
        for c in psutil.Process(parent.pid).children(recursive=True):
            c.kill()
        parent.kill()
        parent.wait()
