"""Checkpoints: what a robot's local odometry seeded from one is worth, and what it costs the link.

The edge sends its robot a checkpoint every 10 scans (``fleet.checkpoint_every``); when the edge's
answers stop, the robot's own light KISS-ICP (robot/odometry.py: voxel ``max_range / 50``, one
thread) is seeded from the newest one and bridges the outage, and the edge continues from where
it got. Along the simulator's drive (VLP-16, 40 m range: the edge's KISS-ICP at 0.4 m, the
robot's at 0.8 m), at every ``--every``-th scan: the edge's state after that scan is taken as a
checkpoint of each kind, a fresh robot odometry seeded from it registers the next ``--scans`` raw
scans, and its motion over them is compared with the ground truth's (translation in cm, heading
in degrees; mean and 90th percentile over the windows). Beside it: the checkpoint's points, its
bytes on the wire, the downlink that takes at one a second, the edge's CPU to take it, the
robot's to decode it and the seeded odometry's per scan of the bridge (median ms, thread time).

Kinds: the map at the mapper's voxel in float32 (the default before), at half the voxel coded as
q16d (the default: ``checkpoint.RESOLUTION``, version 6), and the whole local map coded (what a
drain's final checkpoint carries, in float32: coded it took the draining edge too long).
Run: python -m benchmarks.bench_checkpoint [--every 25] [--scans 20]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from benchmarks.common import header
from zoffload.mapping.checkpoint import seed, take_checkpoint
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.mapper import RobotMapper, load_kiss_icp, mapper_voxel_size
from zoffload.protocol import wire
from zoffload.robot.odometry import local_voxel_size
from zoffload.sources.simulated import SimulatedSource

KINDS = (("voxel, float32 (before)", 1.0, False), ("half voxel, q16d (default)", 0.5, True),
         ("whole map, q16d", 0.0, True))


def heading_deg(t: np.ndarray) -> float:
    return abs(float(np.degrees(np.arctan2(t[1, 0], t[0, 0]))))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_checkpoint")
    p.add_argument("--every", type=int, default=25, help="scans between the windows")
    p.add_argument("--scans", type=int, default=20, help="scans the seeded odometry registers")
    a = p.parse_args(argv)
    header("checkpoints: a seeded robot odometry's error and the checkpoint's cost (simulator drive)")
    src = SimulatedSource()
    n = len(src)
    frames = [src.read(i) for i in range(n)]
    scans = [drop_non_finite(f.points)[0].astype(np.float64) for f in frames]
    edge_voxel = mapper_voxel_size(src.max_range, 0.0)
    robot_voxel = local_voxel_size(src.max_range)
    KISSConfig, KissICP = load_kiss_icp()
    edge = RobotMapper(voxel_size=edge_voxel, max_range=src.max_range)
    rows: dict[str, dict[str, list[float]]] = {k[0]: {} for k in KINDS}
    for i in range(n - a.scans):
        edge.register(i, scans[i])
        if i < 30 or i % a.every:
            continue
        truth = np.linalg.inv(frames[i].gt_pose) @ frames[i + a.scans].gt_pose
        for name, share, coded in KINDS:
            t0 = time.thread_time()
            cp = take_checkpoint(edge.odometry, "r", "e", 1, i, 0.0, share * edge_voxel, coded)
            taken = time.thread_time() - t0
            data = wire.encode(cp)
            t0 = time.thread_time()
            got = wire.decode(data, expect=wire.Checkpoint)
            points = got.cloud()
            decoded = time.thread_time() - t0
            cfg = KISSConfig()
            cfg.data.max_range, cfg.data.deskew, cfg.mapping.voxel_size = src.max_range, False, robot_voxel
            cfg.registration.max_num_threads = 1
            odo = KissICP(cfg)
            seed(odo, got)
            t0 = time.thread_time()
            for j in range(i + 1, i + 1 + a.scans):
                odo.register_frame(scans[j], np.empty(0))
            bridged = (time.thread_time() - t0) / a.scans
            moved = np.linalg.inv(np.asarray(got.pose)) @ np.asarray(odo.last_pose)
            err = np.linalg.inv(truth) @ moved
            r = rows[name]
            for key, value in (("cm", float(np.linalg.norm(err[:3, 3])) * 100), ("deg", heading_deg(err)),
                               ("points", len(points)), ("bytes", len(data)), ("take", taken * 1e3),
                               ("decode", decoded * 1e3), ("register", bridged * 1e3)):
                r.setdefault(key, []).append(value)
    windows = len(next(iter(rows.values()))["cm"])
    print(f"{windows} windows of {a.scans} scans; edge voxel {edge_voxel:g} m, "
          f"robot odometry {robot_voxel:g} m")
    print(f"{'checkpoint':28s} {'points':>8s} {'kB':>6s} {'Mbps at 1/s':>11s} {'take ms':>8s} "
          f"{'decode ms':>9s} {'robot ms/scan':>13s} {'error cm (p90)':>15s} {'heading deg (p90)':>18s}")
    base = None
    for name, _, _ in KINDS:
        r = rows[name]
        kb = statistics.median(r["bytes"]) / 1e3
        deg = statistics.fmean(r["deg"])
        base = base or deg
        print(f"{name:28s} {statistics.median(r['points']):8,.0f} {kb:6.0f} {kb * 8 / 1e3:11.2f} "
              f"{statistics.median(r['take']):8.1f} {statistics.median(r['decode']):9.1f} "
              f"{statistics.median(r['register']):13.1f} "
              f"{statistics.fmean(r['cm']):7.2f} ({np.percentile(r['cm'], 90):5.2f}) "
              f"{deg:9.3f} ({np.percentile(r['deg'], 90):5.3f})  heading x{deg / base:.2f}")


if __name__ == "__main__":
    main()
