"""Shared helpers for the benchmarks: real data location, timing, printing."""

from __future__ import annotations

import os
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ZOFFLOAD_DATA", ROOT.parent / "shared" / "data"))
KITTI = DATA / "kitti360-hdl64" / "velodyne"


def kitti_dir() -> Path:
    if not KITTI.is_dir():
        sys.exit(f"benchmark needs the real KITTI-360 scans at {KITTI} (set ZOFFLOAD_DATA)")
    return KITTI


def kitti_scans(n: int = 50) -> list[np.ndarray]:
    from zoffload.sources.kitti import KittiBinSource

    src = KittiBinSource(kitti_dir())
    return [src.read(i).points for i in range(min(n, len(src)))]


def median_ms(fn: Callable[[], object], repeat: int = 30, warmup: int = 3,
              clock: Callable[[], float] = time.perf_counter) -> float:
    """Median milliseconds of ``fn`` on ``clock`` (wall time by default; ``time.thread_time`` for
    the CPU time of a single-threaded call)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return statistics.median(times) * 1e3


def header(title: str) -> None:
    print(f"\n== {title} ==")
    print(f"machine: {os.cpu_count()} cores, python {sys.version.split()[0]}, numpy {np.__version__}")



class MemorySource:
    """Scans read up front, so a benchmark measures the robot and not the disk or the simulator."""

    def __init__(self, frames: list[Any], rate_hz: float = 10.0, max_range: float = 100.0,
                 name: str = "memory") -> None:
        self.frames, self.rate_hz, self.max_range, self.name = frames, rate_hz, max_range, name

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, index: int) -> object:
        return self.frames[index]


def sensor_frames(sensor: str, n: int) -> tuple[list[Any], float]:
    """(frames, max range) of the simulator's VLP-16 (``sim``: ``n`` scans) or the real KITTI-360
    HDL-64 (``kitti``: its 50 scans, at most ``n``)."""
    if sensor == "sim":
        from zoffload.sources.simulated import SimulatedSource

        sim = SimulatedSource(seed=0)
        return [sim.read(i) for i in range(n)], sim.max_range
    from zoffload.sources.kitti import KittiBinSource

    src = KittiBinSource(kitti_dir())
    return [src.read(i) for i in range(min(n, len(src)))], src.max_range


def spawn(args: list[str], ready: str | None = None) -> subprocess.Popen[str]:
    """A zoffload program as a child process (``ready``: wait for a line starting with it)."""
    out = subprocess.PIPE if ready is not None else subprocess.DEVNULL
    p = subprocess.Popen([sys.executable, "-m", "zoffload.cli", *args], stdout=out, stderr=subprocess.STDOUT,
                         text=True)
    if ready is not None:
        assert p.stdout is not None
        for line in p.stdout:  # then nothing more is read: the program must print little after it
            if line.startswith(ready):
                break
    return p


def stop(p: subprocess.Popen[str]) -> None:
    p.send_signal(signal.SIGINT)
    try:
        p.wait(20)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()
