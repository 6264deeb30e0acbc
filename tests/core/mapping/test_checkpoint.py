"""A checkpoint carries a trajectory to a fresh KISS-ICP: seeded, the next mapper continues in the
same frame where an unseeded one starts again at the origin."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.mapping.checkpoint import config_matches, seed, take_checkpoint
from zoffload.mapping.mapper import RobotMapper
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")


def test_a_seeded_mapper_continues_the_trajectory() -> None:
    src = SimulatedSource()
    scans = [voxel_downsample(src.read(i).points, 0.05) for i in range(40)]
    a = RobotMapper(voxel_size=0.5, max_range=src.max_range)
    for i in range(25):
        a.register(i, scans[i])
    cp = take_checkpoint(a.odometry, "r1", "e1", epoch=3, seq=24, stamp=2.4)
    cp = wire.decode(wire.encode(cp), expect=wire.Checkpoint)  # it travels
    assert 1000 < len(cp.points) < 20_000 and len(wire.encode(cp)) < 300_000
    b, fresh = RobotMapper(voxel_size=cp.voxel_size, max_range=cp.max_range), \
        RobotMapper(voxel_size=0.5, max_range=src.max_range)
    assert config_matches(b.odometry, cp)
    seed(b.odometry, cp)
    for i in range(25, 40):
        ra, rb, rf = a.register(i, scans[i]), b.register(i, scans[i]), fresh.register(i, scans[i])
    gap = np.linalg.norm(ra.pose[:3, 3] - rb.pose[:3, 3])
    assert gap < 0.05, gap  # the seeded mapper is where the original one is
    assert np.linalg.norm(ra.pose[:3, 3] - rf.pose[:3, 3]) > 0.5  # the fresh one starts over


def test_the_whole_local_map_continues_closer_than_the_coarse_one() -> None:
    """A final checkpoint (drain, shed) carries every point of KISS-ICP's local map: the next
    mapper's first poses are then within a centimetre of the original's, where the coarse map
    (one point per voxel, the periodic checkpoints) leaves a few centimetres."""
    src = SimulatedSource(seed=5)
    scans = [src.read(i).points for i in range(0, 90, 2)]
    a = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    for i in range(35):
        a.register(i, scans[i])
    local = np.asarray(a.odometry.local_map.point_cloud())
    whole = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=34, stamp=0.0, resolution=0.0)
    coarse = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=34, stamp=0.0)
    assert len(whole.points) == len(local) > 3 * len(coarse.points)
    for i in range(35, 40):  # the original carries on: the reference
        a.register(i, scans[i])
    errors = {}
    for name, cp in (("whole", whole), ("coarse", coarse)):
        b = RobotMapper(voxel_size=0.4, max_range=src.max_range)
        b.continue_from(cp, np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        errors[name] = max(np.linalg.norm(b.register(i, scans[i]).pose[:3, 3] - a.poses[i][:3, 3])
                           for i in range(35, 40))
    assert errors["whole"] < 0.015 and errors["whole"] < errors["coarse"], errors
