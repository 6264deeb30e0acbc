"""A robot's mapping state as a ``wire.Checkpoint``, and a fresh KISS-ICP seeded from one.

What continues a trajectory on another mapper: the last pose (so poses stay in the same world
frame), the last motion per scan period (KISS-ICP's constant-velocity prediction), the local map
the next scan registers against (coarsened to one point per ``resolution`` voxel), and the
mapper's own configuration (voxel size, ranges, points per voxel), which the next mapper must
share.

The map's resolution is what a seeded odometry's accuracy hangs on. The robot's own odometry
(robot/odometry.py, 0.8 m on the simulator) seeded from a checkpoint and run over 20 scans, at 49
places along the simulator's drive (``python -m benchmarks.bench_checkpoint``): from a map at the
mapper's voxel (0.4 m, one point per voxel, the default before) it ended 0.166 degrees and 4.0 cm
off on average, from one at half that voxel 0.046 degrees and 2.6 cm, as from the whole local map.
Heading is what a bridged outage hands back to the edge and what the trajectory carries on: 0.1
degree is 7 cm forty metres on. So the default is half the mapper's voxel (KISS-ICP's own grid for
a scan's points), and the map is coded as a scan's q16d payload (steps of a tenth of that voxel,
sorted along the grid so that consecutive points differ by little): 136 kB a checkpoint against
235 kB for the coarser float32 map before (medians; four times the points).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from zoffload.mapping.se3 import as_rigid
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.protocol.coding import encode_q16d, quant_step

RESOLUTION = 0.5  # of the mapper's voxel: a checkpoint's local map by default (module docstring)
STEP = 0.1  # of the map's resolution: its quantisation step when coded (the whole map: of RESOLUTION)


def take_checkpoint(odometry: Any, robot: str, edge: str, epoch: int, seq: int, stamp: float,
                    resolution: float | None = None, coded: bool = True, turn_rate: float = 0.0
                    ) -> wire.Checkpoint:
    """The state of ``odometry`` (a ``kiss_icp.KissICP``) after scan ``seq``; the local map is
    coarsened to one point per ``resolution`` voxel (default: half KISS-ICP's voxel size coded, its
    voxel size in float32, as before version 6; 0: the whole local map, every point KISS-ICP keeps:
    a mapper seeded from it continues within a centimetre) and, ``coded``, sent as a q16d payload
    on steps of a tenth of that (version 6; float32 points for a peer that reads 5 or older);
    ``turn_rate`` is the mapper's (``RobotMapper.turn_rate``; version 8, 0: not said)."""
    cfg = odometry.config
    voxel = float(cfg.mapping.voxel_size)
    local = np.asarray(odometry.local_map.point_cloud(), np.float64).reshape(-1, 3)
    cell = (RESOLUTION if coded else 1.0) * voxel if resolution is None else resolution
    coarse = local if cell <= 0 or not len(local) else voxel_downsample(local, cell)
    cp = wire.Checkpoint(
        robot=robot, edge=edge, epoch=epoch, seq=seq, stamp=stamp, voxel_size=voxel,
        max_range=float(cfg.data.max_range), min_range=float(cfg.data.min_range),
        max_points_per_voxel=int(cfg.mapping.max_points_per_voxel),
        pose=np.asarray(odometry.last_pose, np.float64), delta=np.asarray(odometry.last_delta, np.float64),
        points=np.ascontiguousarray(coarse if not coded else coarse[:0], np.float32),
        turn_rate=min(max(float(turn_rate), 0.0), np.pi))
    if not coded or not len(coarse):
        return cp
    grid = cell if cell > 0 else RESOLUTION * voxel
    step = quant_step(grid, STEP, floor=0.001)
    # Along the grid (x, then y, then z cell): the codec's differences between neighbours stay small
    # (one packed key: a single sort, 1.8 against 4.4 ms for a three-key lexsort of 53k points)
    cells = np.floor(coarse / grid).astype(np.int64)
    cells -= cells.min(axis=0)
    span = int(cells.max()) + 1
    order = np.argsort((cells[:, 0] * span + cells[:, 1]) * span + cells[:, 2], kind="stable")
    ordered = np.ascontiguousarray(coarse[order])
    origin, step, packed = encode_q16d(ordered, step, level=1, widen=True)
    return replace(cp, quant_step=step, n_points=len(ordered), origin=origin,
                   packed=np.frombuffer(packed, np.uint8))


def seed(odometry: Any, checkpoint: wire.Checkpoint) -> None:
    """Continue ``checkpoint``'s trajectory on a fresh ``KissICP`` built with the checkpoint's
    configuration: its local map, last pose and last motion. ``WireError`` if its coded map does
    not decode (the receivers check it when it arrives)."""
    points = checkpoint.cloud()
    if len(points):
        odometry.local_map.add_points(np.ascontiguousarray(points, np.float64))
    odometry.last_pose = as_rigid(checkpoint.pose)  # (Sophus aborts on a rotation off by 1e-10)
    odometry.last_delta = as_rigid(checkpoint.delta)


def config_matches(odometry: Any, checkpoint: wire.Checkpoint) -> bool:
    """Whether ``odometry`` was built as the checkpoint's mapper was (else seeding would mix
    two voxel grids)."""
    cfg = odometry.config
    return bool(np.isclose(cfg.mapping.voxel_size, checkpoint.voxel_size)
                and np.isclose(cfg.data.max_range, checkpoint.max_range)
                and cfg.mapping.max_points_per_voxel == checkpoint.max_points_per_voxel)
