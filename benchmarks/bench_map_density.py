"""The edge mapper's cost and accuracy against KISS-ICP's local map density (``max_points_per_voxel``).

KISS-ICP keeps up to ``max_points_per_voxel`` points in each voxel of its local map (its default,
and the edge's, 20) and searches the 27 voxels around each scan point. Where the robot stays in a
closed space (the simulator's warehouse loop) the voxels fill up over the run and a registration
costs more and more; on a road (KITTI-360) the map moves on with the car. This benchmark registers
the same scans with ``RobotMapper`` (the edge's mapper, no network) at 20, 10 and 5 points per voxel
and prints each one's registration CPU time (all threads: KISS-ICP's are several) over the run's
first and last scans, and its trajectory against the ground truth (the simulator) or against the
run at 20 (KITTI-360 carries no poses: a difference, not an error).

Scans as the robot sends them: the simulator's at a 10 cm grid, KITTI-360's at 5 cm; the edge's
KISS-ICP voxel (``mapper_voxel_size``): 0.4 m and 1.0 m. Seeds: ``--seeds`` (default 0 and 7).

Run: python -m benchmarks.bench_map_density [--scans N] [--seeds 0,7]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.common import header, kitti_scans
from zoffload.lab.eval.trajectory import TrajectoryError, trajectory_error
from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size
from zoffload.mapping.voxel import voxel_downsample

DENSITIES = (20, 10, 5)


def register_all(scans: list[np.ndarray], voxel: float, max_range: float,
                 density: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(registration CPU ms per scan, registered seqs, their poses)."""
    mapper = RobotMapper(voxel_size=voxel, max_range=max_range, max_points_per_voxel=density)
    cpu = []
    for seq, points in enumerate(scans):
        t0 = time.process_time()
        mapper.register(seq, points)
        cpu.append(time.process_time() - t0)
    seqs, poses = mapper.trajectory()
    return np.array(cpu) * 1e3, seqs, poses


def row(name: str, cpu: np.ndarray, err: TrajectoryError | None, base_cpu: float) -> str:
    k = max(1, len(cpu) // 5)
    rmse, most = (f"{err.ate_rmse:.3f}", f"{err.ate_max:.3f}") if err is not None else ("–", "–")
    return (f"| {name} | {np.median(cpu[:k]):.1f} | {np.median(cpu[-k:]):.1f} | {cpu.mean():.1f} "
            f"| {cpu.mean() / base_cpu:.2f} | {rmse} | {most} |")


def simulator(seed: int, n: int) -> None:
    from zoffload.sources.simulated import SimulatedSource

    sim = SimulatedSource(seed=seed)
    frames = [sim.read(i) for i in range(min(n, len(sim)))]
    scans = [voxel_downsample(f.points, 0.1) for f in frames]
    truth = np.array([f.gt_pose for f in frames])
    voxel = mapper_voxel_size(sim.max_range, 0.1)
    print(f"\nsimulator VLP-16, seed {seed}: {len(scans)} scans (of a {len(sim)}-scan lap), "
          f"~{int(np.mean([len(s) for s in scans]))} points each, KISS-ICP voxel {voxel:g} m")
    print("| points per voxel | CPU ms, first fifth (median) | last fifth | mean | mean vs 20 "
          "| error vs truth, ATE RMSE m | max m |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    base = None
    for density in DENSITIES:
        cpu, seqs, poses = register_all(scans, voxel, sim.max_range, density)
        base = cpu.mean() if base is None else base
        err = trajectory_error(seqs, poses, np.arange(len(truth)), truth)
        print(row(str(density), cpu, err, base), flush=True)


def kitti() -> None:
    scans = [voxel_downsample(p, 0.05) for p in kitti_scans()]
    voxel = mapper_voxel_size(100.0, 0.07)
    print(f"\nKITTI-360 HDL-64: its {len(scans)} scans at 5 cm, KISS-ICP voxel {voxel:g} m "
          "(no ground truth: the trajectory against the run at 20 points per voxel)")
    print("| points per voxel | CPU ms, first fifth (median) | last fifth | mean | mean vs 20 "
          "| difference from 20, RMSE m | max m |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    base: tuple[float, np.ndarray, np.ndarray] | None = None
    for density in DENSITIES:
        cpu, seqs, poses = register_all(scans, voxel, 100.0, density)
        if base is None:
            base = cpu.mean(), seqs, poses
        print(row(str(density), cpu, trajectory_error(seqs, poses, base[1], base[2]), base[0]), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=700, help="simulator scans per run (a lap: 1294)")
    ap.add_argument("--seeds", default="0,7", help="simulator seeds, comma-separated")
    args = ap.parse_args()
    header("the edge mapper's registration CPU and trajectory against KISS-ICP's points per voxel")
    for seed in (int(s) for s in args.seeds.split(",") if s):
        simulator(seed, args.scans)
    kitti()


if __name__ == "__main__":
    main()
