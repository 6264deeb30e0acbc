"""The KISS-ICP mapper on simulated scans."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.lab.eval.trajectory import trajectory_error
from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size
from zoffload.mapping.voxel import voxel_downsample
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")


def test_mapper_voxel_follows_sensor_and_robot_voxels() -> None:
    assert mapper_voxel_size(100.0, 0.07) == 1.0  # KISS-ICP's own default
    assert mapper_voxel_size(40.0, 0.07) == 0.4
    assert mapper_voxel_size(20.0, 0.3) == 0.6  # never finer than twice the robot's voxel
    assert mapper_voxel_size(20.0, 0.3, configured=0.25) == 0.25


def test_kiss_icp_tracks_the_simulated_warehouse() -> None:
    src = SimulatedSource()
    m = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    gt = []
    counts = []
    for i in range(60):
        f = src.read(i)
        r = m.register(i, voxel_downsample(f.points, 0.05))
        gt.append(f.gt_pose)
        counts.append(r.map_points)
        assert r.keypoints > 100 and np.isfinite(r.sigma)
    seqs, poses = m.trajectory()
    err = trajectory_error(seqs, poses, np.arange(60), np.array(gt))
    assert err is not None and err.path_length > 4.0
    assert err.ate_rmse < 0.3, err
    assert counts[-1] > counts[0] and all(b >= a for a, b in zip(counts, counts[1:], strict=False))
    assert len(m.map_cloud()) == m.map_points


def test_lost_scans_do_not_derail_the_mapper() -> None:
    """Every 20 scans, 10 are lost (1 s of a 1.2 m/s robot): the seq gap stretches the motion model."""
    src = SimulatedSource()
    kept = [i for i in range(140) if i < 30 or (i % 20) < 10]
    m = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    gt = {}
    for i in kept:
        f = src.read(i)
        m.register(i, voxel_downsample(f.points, 0.05))
        gt[i] = f.gt_pose
    seqs, poses = m.trajectory()
    err = trajectory_error(seqs, poses, np.array(kept), np.array([gt[i] for i in kept]))
    assert err is not None and err.ate_rmse < 0.5, err
