"""The backfill: what handing an outage's scans to the edge costs the robot, the link and the edge.

While no edge maps it, the robot registers its scans itself (robot/odometry.py) and keeps at most
``fleet.backfill_scans`` (50) of them, spread over the outage, at a quarter of its odometry's voxel
(``max_range / 50``); the attach after the outage carries them at the finest of that grid, twice
it, ... up to the odometry's voxel that fits its bytes (robot/fleet.py ``backfill_payload``), and
the edge registers each from its mapper's voxel and maps all its points (mapping/mapper.py
``BACKFILL_REGISTER_GRID``). For the simulator's VLP-16 and KITTI-360's HDL-64:

- the robot, per locally registered scan: the grid pass that keeps it (thread CPU, median ms) at
  the ring's grid and at the odometry's (the default before), its points and the ring's memory;
- the robot, per attach: ``backfill_payload`` of 50 such scans at several budgets (the grid it
  chose, the scans kept, bytes, thread CPU);
- the edge: registering 50 consecutive backfilled scans after its own as the attach sent them at
  each grid, from its voxel (the default) and from the points as sent (tried): wall ms a
  scan (what holds the robot's worker), the global map's growth (0.1 m cells: misplaced points
  fill more) and, on the simulator, the backfill's poses against the ground truth.

Run: python -m benchmarks.bench_backfill [--sensor sim|kitti|both]
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time
from typing import Any

import numpy as np

from benchmarks.common import header, median_ms, sensor_frames
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.mapper import BACKFILL_REGISTER_GRID, RobotMapper, mapper_voxel_size
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.robot.fleet import BACKFILL_BYTES, BACKFILL_BYTES_MAX, Sensor, backfill_grids, backfill_payload
from zoffload.robot.odometry import BACKFILL_FINER, Backfilled, local_voxel_size

SCANS = 50  # the ring's size (fleet.backfill_scans)
BEFORE = 10  # scans the edge registers before the backfill


def _robot(scans: list[np.ndarray], max_range: float) -> tuple[list[Backfilled], float]:
    voxel = local_voxel_size(max_range)
    fine = voxel * BACKFILL_FINER
    def pass_at(v: float) -> float:
        return median_ms(lambda: [voxel_downsample(s, v) for s in scans[:10]], repeat=5,
                         clock=time.thread_time) / 10

    grid = {v: pass_at(v) for v in (fine, voxel)}
    ring = [Backfilled(i, float(i), len(s), voxel_downsample(s, fine).astype(np.float32), fine, np.eye(4),
                       voxel) for i, s in enumerate(scans[BEFORE:BEFORE + SCANS], BEFORE)]
    pts = [len(b.points) for b in ring]
    coarse = [len(voxel_downsample(b.points, voxel)) for b in ring]
    mb = sum(b.points.nbytes for b in ring) / 1e6
    print(f"robot, per locally registered scan: the grid pass at {fine:.2f} m {grid[fine]:.2f} ms CPU "
          f"({statistics.median(pts):,.0f} points), at {voxel:.2f} m {grid[voxel]:.2f} ms "
          f"({statistics.median(coarse):,.0f} points); the ring of {len(ring)}: {mb:.1f} MB")
    sensor = Sensor(max_range, 0.07, 10.0)
    print(f"robot, per attach ({len(ring)} scans): budget -> grid, scans kept, bytes, thread CPU "
          "(median of 5)")
    for budget in (BACKFILL_BYTES, 4 * BACKFILL_BYTES, BACKFILL_BYTES_MAX):
        data, sizes, kept = backfill_payload("r1", 1, sensor, ring, budget)
        cpu = median_ms(lambda b=budget: backfill_payload("r1", 1, sensor, ring, b), repeat=5,
                        clock=time.thread_time)
        scans_out = wire.Attach(robot="r1", epoch=1, max_range=max_range, voxel_max=0.07, rate_hz=10.0,
                                checkpoint=b"", local_seqs=np.zeros(0, np.int64),
                                local_poses=np.zeros((0, 4, 4)), backfill=data,
                                backfill_sizes=sizes).backfill_scans()
        grids = sorted({s.voxel for s in scans_out})
        print(f"  {budget / 1024:>6,.0f} kB -> {', '.join(f'{g:.2f}' for g in grids)} m, {len(kept)} scans, "
              f"{len(data) if data is not None else 0:,} B, {cpu:.0f} ms")
    return ring, voxel


def _drift(m: RobotMapper, truth: list[np.ndarray | None]) -> float | None:
    """The backfill's poses against the ground truth's from the edge's last own scan: RMS of the
    translation error (m), None without a ground truth."""
    if any(t is None for t in truth):
        return None
    at = m.seqs.index(BEFORE - 1)
    base, gt0 = np.linalg.inv(m.poses[at]), np.linalg.inv(np.asarray(truth[BEFORE - 1]))
    errors = [(base @ m.poses[k])[:3, 3] - (gt0 @ np.asarray(truth[s]))[:3, 3]
              for k, s in enumerate(m.seqs) if s >= BEFORE]
    return float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))


def _edge(scans: list[np.ndarray], ring: list[Backfilled], max_range: float,
          truth: list[np.ndarray | None]) -> None:
    edge_voxel = mapper_voxel_size(max_range, 0.07)
    print(f"edge (KISS-ICP at {edge_voxel:.2f} m), registering the {len(ring)} backfilled scans after its "
          f"own {BEFORE}, as the attach sent them at each grid: wall ms a scan (median of 3; what holds "
          f"the robot's worker), the global map's growth (0.1 m cells), the backfill's poses against "
          f"the ground truth")
    grids = backfill_grids(ring[0].voxel, ring[0].coarsest)
    for grid, as_sent in [(g, False) for g in grids] + [(g, True) for g in grids[:-1]]:
        fill = [(b.seq, b.points if grid <= b.voxel else voxel_downsample(b.points, grid)) for b in ring]
        per, grew, drift = [], 0, None
        for _ in range(3):
            m = RobotMapper(voxel_size=edge_voxel, max_range=max_range)
            for i in range(BEFORE):
                m.register(i, scans[i])
            before = len(m.global_map)
            if as_sent:  # registered from its own points, not the default's coarser grid
                m.register = functools.partial(_as_sent, m.register)  # type: ignore[method-assign]
            t0 = time.perf_counter()
            m.continue_from(None, np.zeros(0, np.int64), np.zeros((0, 4, 4)), fill)
            per.append((time.perf_counter() - t0) * 1e3 / len(ring))
            grew, drift = len(m.global_map) - before, _drift(m, truth)
            assert m.backfilled == len(ring), m.backfilled
        off = f", {drift:.3f} m RMS" if drift is not None else ""
        how = ("registered as sent (tried, not the default)" if as_sent else
               f"registered at {BACKFILL_REGISTER_GRID * edge_voxel:.2f} m (the default)")
        print(f"  sent at {grid:.2f} m, {how}: {statistics.median(per):.1f} ms a scan, map +{grew:,} "
              f"points{off}")


def _as_sent(register: Any, seq: int, points: np.ndarray, times: np.ndarray | None = None,
             map_points: np.ndarray | None = None) -> Any:
    return register(seq, points if map_points is None else map_points, times)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_backfill")
    p.add_argument("--sensor", choices=("sim", "kitti", "both"), default="both")
    a = p.parse_args(argv)
    header("the backfill: the robot's ring and attach, the edge's registration")
    for sensor in ("sim", "kitti") if a.sensor == "both" else (a.sensor,):
        frames, max_range = sensor_frames(sensor, BEFORE + SCANS)  # KITTI-360: its 50 (a ring of 40)
        scans = [drop_non_finite(f.points)[0].astype(np.float64) for f in frames]
        print(f"\n-- {sensor}: {len(scans)} scans, {statistics.median(len(s) for s in scans):,.0f} points, "
              f"range {max_range:g} m")
        ring, _ = _robot(scans, max_range)
        _edge(scans, ring, max_range, [getattr(f, "gt_pose", None) for f in frames])


if __name__ == "__main__":
    main()
