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


def test_deskew_times_are_kiss_icp_safe() -> None:
    from zoffload.mapping.mapper import deskew_times

    np.testing.assert_allclose(deskew_times(np.array([5.0, 5.05, 5.1]), 3), [0.0, 0.5, 1.0])
    # KISS-ICP 1.3 aborts the process on all-equal times: none is no deskew instead
    assert deskew_times(np.zeros(3), 3).size == 0 and deskew_times(None, 3).size == 0
    with pytest.raises(ValueError, match="2 point times for 3 points"):
        deskew_times(np.zeros(2), 3)
    with pytest.raises(ValueError, match="non-finite"):
        deskew_times(np.array([0.0, np.nan, 1.0]), 3)
    m = RobotMapper(voxel_size=0.4, max_range=40.0, deskew=True)
    f = SimulatedSource().read(0)
    m.register(0, f.points, np.full(len(f.points), 7.0))  # equal times: registered, not aborted
    m.register(1, f.points, None)
    assert len(m.trajectory()[0]) == 2


def test_deskew_undoes_the_sweep_of_a_fast_turning_robot() -> None:
    """4 m/s through the warehouse's corners, each column fired at its own time (sim ``sweep``):
    without deskew the skewed scans cost accuracy, with the points' times it comes back to the
    level of scans cast without motion (benchmarks/bench_deskew.py measures it at length)."""
    swept, still = SimulatedSource(speed=4.0, sweep=True), SimulatedSource(speed=4.0)
    n = 50
    frames = [swept.read(i) for i in range(n)]
    gt = np.array([f.gt_pose for f in frames])
    ate = {}
    for name, deskew, source in (("skewed", False, frames), ("deskewed", True, frames),
                                 ("still", False, [still.read(i) for i in range(n)])):
        m = RobotMapper(voxel_size=0.4, max_range=swept.max_range, deskew=deskew)
        for i, f in enumerate(source):
            m.register(i, f.points, f.times)
        seqs, poses = m.trajectory()
        err = trajectory_error(seqs, poses, np.arange(n), gt)
        assert err is not None
        ate[name] = err.ate_rmse
    assert ate["deskewed"] < 0.85 * ate["skewed"], ate
    assert ate["deskewed"] < 1.2 * ate["still"] + 0.02, ate
