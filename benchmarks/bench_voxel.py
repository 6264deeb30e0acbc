"""Voxel grid: zoffload's kernel vs Open3D ``voxel_down_sample`` on a real HDL-64 scan.

Open3D's time includes the numpy -> ``Vector3dVector`` conversion and back, as a robot pays it;
ours is ``voxel_downsample`` (a new centroid array) and, as the robot runs it, the grid pass alone
(``VoxelGrid.run``: sums in scratch buffers, invalid points skipped, read straight into the
payload). Wall times (Open3D may use several threads). The same scan over and over keeps it and
the grid's table in the caches; the robot meets each scan once, after the sender and Zenoh have
run, so the last column is the grid pass with the caches cold: every KITTI-360 scan in turn, 3
times, a 64 MB write between passes, thread CPU time, median.
Run: python -m benchmarks.bench_voxel
"""

from __future__ import annotations

import functools
import statistics
import time

import numpy as np

from benchmarks.common import header, kitti_scans, median_ms
from zoffload.mapping.voxel import VoxelGrid, voxel_downsample, warmup


def open3d_grid(points: np.ndarray, v: float) -> np.ndarray:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    return np.asarray(cloud.voxel_down_sample(v).points)


def unique_grid(points: np.ndarray, v: float) -> np.ndarray:
    keys = np.floor(points.astype(np.float64) / v).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inv.ravel(), points)
    return sums / counts[:, None]


def cold_pass_ms(grid: VoxelGrid, scans: list[np.ndarray], v: float, rounds: int = 3) -> float:
    """Median thread CPU ms of the grid pass over ``scans`` in turn, caches evicted before each."""
    evict = np.ones(8_000_000)  # 64 MB, twice the last-level cache
    times = []
    for _ in range(rounds):
        for pts in scans:
            evict += 1.0
            t0 = time.thread_time()
            grid.run(pts, v, skip_invalid=True)
            times.append(time.thread_time() - t0)
    return statistics.median(times) * 1e3


def main() -> None:
    header("voxel grid vs Open3D (KITTI-360 scan 0000003000, conversion included)")
    scans = kitti_scans(50)
    pts = scans[0]
    warmup()
    print(f"scan: {len(pts):,} points; cold: {len(scans)} scans, {np.mean([len(s) for s in scans]):,.0f} "
          "points on average")
    grid = VoxelGrid()
    print(f"{'voxel':>6} | {'zoffload ms':>11} | {'grid pass':>9} | {'open3d ms':>9} | {'speed-up':>8} | "
          f"{'voxels ours/o3d':>15} | grid pass, cold")
    for v in (0.02, 0.05, 0.2, 0.5):
        # Timed in separate blocks with a pause: Open3D's OpenMP threads keep spinning for a while
        # after each call and would steal the core from whatever runs right after them.
        time.sleep(0.5)
        ours = median_ms(functools.partial(voxel_downsample, pts, v), repeat=50)
        robot = median_ms(functools.partial(grid.run, pts, v, skip_invalid=True), repeat=50)
        o3d_ms = median_ms(functools.partial(open3d_grid, pts, v), repeat=50)
        n_ours, n_o3d = len(voxel_downsample(pts, v)), len(open3d_grid(pts, v))
        ratio = o3d_ms / ours
        cold = cold_pass_ms(grid, scans, v)
        print(f"{v:>6.2f} | {ours:>11.2f} | {robot:>9.2f} | {o3d_ms:>9.2f} | {ratio:>7.1f}x | "
              f"{f'{n_ours:,}/{n_o3d:,}':>15} | {cold:.2f}")
    u = median_ms(lambda: unique_grid(pts, 0.05), repeat=5, warmup=1)
    print(f"plain np.unique grid at 0.05: {u:.1f} ms")
    print("(voxel counts differ slightly: Open3D anchors its grid at the cloud's min bound - v/2,"
          " zoffload at the origin as the paper defines it)")


if __name__ == "__main__":
    main()
