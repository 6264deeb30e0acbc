"""How long the edge's other Python threads wait while its mapper registers a scan.

KISS-ICP's Python binding does not release the GIL: while ``register`` runs (the edge's mapper,
``RobotMapper``, on a worker thread), every other Python thread of the process waits: the Zenoh
callbacks that stamp a scan's arrival, the other robots' scans, camera frames, the fleet's
messages. A thread that sleeps 1 ms in a loop shows it: the gaps between its wake-ups, while a
worker thread registers the 50 KITTI-360 HDL-64 scans (each twice) beside it, against the same
loop beside a worker doing numpy work that releases the GIL (an SVD), alone, and beside the same
registrations in a mapper process (``edge/isolate.py``, the edge's default since 2026-12-06:
``mapper.processes``), where the worker thread waits on a socket with the GIL released.

Run: python -m benchmarks.bench_gil
"""

from __future__ import annotations

import statistics
import threading
import time
from collections.abc import Callable

import numpy as np

from benchmarks.common import header, sensor_frames
from zoffload.edge.isolate import MapperPool
from zoffload.edge.recipe import MapperRecipe
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size
from zoffload.protocol import wire


def wake_gaps(work: Callable[[], None] | None, seconds: float = 3.0) -> list[float]:
    """Milliseconds between the wake-ups of a thread sleeping 1 ms, while ``work`` runs beside it
    (or for ``seconds`` alone)."""
    done = threading.Event()

    def run() -> None:
        try:
            if work is None:
                time.sleep(seconds)
            else:
                work()
        finally:
            done.set()

    worker = threading.Thread(target=run)
    gaps: list[float] = []
    worker.start()
    last = time.perf_counter()
    while not done.is_set():
        time.sleep(0.001)
        now = time.perf_counter()
        gaps.append((now - last) * 1e3)
        last = now
    worker.join()
    return gaps


def main() -> None:
    header("a 1 ms sleeper's wake-ups beside the edge's mapper (KISS-ICP holds the GIL)")
    frames, max_range = sensor_frames("kitti", 50)
    scans = [drop_non_finite(f.points)[0].astype(np.float64) for f in frames]
    mapper = RobotMapper(voxel_size=mapper_voxel_size(max_range, 0.5), max_range=max_range)

    def registering(register: Callable[[int, np.ndarray], object], ms: list[float]) -> Callable[[], None]:
        """Registering every scan twice with ``register``, each one's wall time into ``ms``."""
        def run() -> None:
            for seq, pts in enumerate(scans * 2):
                t0 = time.perf_counter()
                register(seq, pts)
                ms.append((time.perf_counter() - t0) * 1e3)
        return run

    x = np.random.default_rng(0).random((300, 300))
    pool = MapperPool(MapperRecipe(), 1)
    pool.warm_up()
    first = wire.Scan(robot="r1", seq=0, send_stamp=0.0, capture_stamp=0.0, voxel=0.0, voxel_max=0.5,
                      max_range=max_range, n_raw=0, points=np.zeros((0, 3), np.float32))
    remote = pool(first)
    reg_ms: list[float] = []
    remote_ms: list[float] = []

    def svd() -> None:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 3.0:
            np.linalg.svd(x)

    print(f"{'beside':34} {'wake-ups':>9} {'median ms':>10} {'p99 ms':>8} {'max ms':>8}")
    for label, work in (("nothing", None), ("numpy SVD (releases the GIL)", svd),
                        ("RobotMapper.register (KISS-ICP)", registering(mapper.register, reg_ms)),
                        ("the same in a mapper process", registering(remote.register, remote_ms))):
        gaps = wake_gaps(work)
        print(f"{label:34} {len(gaps):9d} {statistics.median(gaps):10.2f} "
              f"{float(np.percentile(gaps, 99)):8.1f} {max(gaps):8.1f}")
    pool.close()
    print(f"registration: {statistics.median(reg_ms):.1f} ms a scan in the process, "
          f"{statistics.median(remote_ms):.1f} ms in a mapper process, request and reply included "
          f"(median wall time, {len(reg_ms)} HDL-64 scans)")


if __name__ == "__main__":
    main()
