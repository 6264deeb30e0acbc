"""Shared helpers for the benchmarks: real data location, timing, printing."""

from __future__ import annotations

import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

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


def median_ms(fn: Callable[[], object], repeat: int = 30, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def header(title: str) -> None:
    print(f"\n== {title} ==")
    print(f"machine: {os.cpu_count()} cores, python {sys.version.split()[0]}, numpy {np.__version__}")

