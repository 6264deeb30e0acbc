"""A robot's mapping state as a ``wire.Checkpoint``, and a fresh KISS-ICP seeded from one.

What continues a trajectory on another mapper: the last pose (so poses stay in the same world
frame), the last motion per scan period (KISS-ICP's constant-velocity prediction), the local map
the next scan registers against (coarsened to one point per ``resolution`` voxel: a 100 m HDL-64
map at 1 m is a few tens of thousands of points, a few hundred kB), and the mapper's own
configuration (voxel size, ranges, points per voxel), which the next mapper must share.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from zoffload.mapping.se3 import as_rigid
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire


def take_checkpoint(odometry: Any, robot: str, edge: str, epoch: int, seq: int, stamp: float,
                    resolution: float | None = None) -> wire.Checkpoint:
    """The state of ``odometry`` (a ``kiss_icp.KissICP``) after scan ``seq``; the local map is
    coarsened to one point per ``resolution`` voxel (default: KISS-ICP's own voxel size; 0: the
    whole local map, every point KISS-ICP keeps, several times larger: a mapper seeded from it
    continues within a centimetre, one seeded from the coarse map within a few)."""
    cfg = odometry.config
    voxel = float(cfg.mapping.voxel_size)
    local = np.asarray(odometry.local_map.point_cloud(), np.float64).reshape(-1, 3)
    whole = resolution is not None and resolution <= 0
    coarse = local if whole or not len(local) else voxel_downsample(local, resolution or voxel)
    return wire.Checkpoint(
        robot=robot, edge=edge, epoch=epoch, seq=seq, stamp=stamp, voxel_size=voxel,
        max_range=float(cfg.data.max_range), min_range=float(cfg.data.min_range),
        max_points_per_voxel=int(cfg.mapping.max_points_per_voxel),
        pose=np.asarray(odometry.last_pose, np.float64), delta=np.asarray(odometry.last_delta, np.float64),
        points=np.ascontiguousarray(coarse, np.float32))


def seed(odometry: Any, checkpoint: wire.Checkpoint) -> None:
    """Continue ``checkpoint``'s trajectory on a fresh ``KissICP`` built with the checkpoint's
    configuration: its local map, last pose and last motion."""
    if len(checkpoint.points):
        odometry.local_map.add_points(np.asarray(checkpoint.points, np.float64))
    odometry.last_pose = as_rigid(checkpoint.pose)  # (Sophus aborts on a rotation off by 1e-10)
    odometry.last_delta = as_rigid(checkpoint.delta)


def config_matches(odometry: Any, checkpoint: wire.Checkpoint) -> bool:
    """Whether ``odometry`` was built as the checkpoint's mapper was (else seeding would mix
    two voxel grids)."""
    cfg = odometry.config
    return bool(np.isclose(cfg.mapping.voxel_size, checkpoint.voxel_size)
                and np.isclose(cfg.data.max_range, checkpoint.max_range)
                and cfg.mapping.max_points_per_voxel == checkpoint.max_points_per_voxel)
