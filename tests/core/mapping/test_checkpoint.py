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
