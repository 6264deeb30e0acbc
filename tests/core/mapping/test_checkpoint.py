"""A checkpoint carries a trajectory to a fresh KISS-ICP: seeded, the next mapper continues in the
same frame where an unseeded one starts again at the origin."""

from __future__ import annotations

from dataclasses import replace

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
    points = cp.cloud()
    # coded (version 6): a few bytes a point where float32 takes 12
    assert len(cp.points) == 0 and 1000 < len(points) < 80_000 and len(wire.encode(cp)) < 4 * len(points)
    plain = wire.decode(wire.encode(cp.plain()), expect=wire.Checkpoint)  # for a version-5 peer
    assert plain.packed is None and np.array_equal(plain.points, points)
    # within half a quantisation step of the map it was taken from
    same = take_checkpoint(a.odometry, "r1", "e1", 3, 24, 2.4, resolution=0.25, coded=False)
    assert np.abs(np.sort(points, axis=0) - np.sort(same.points, axis=0)).max() <= cp.quant_step / 2 + 1e-4
    # float32 without a resolution: the mapper's voxel, as before version 6
    assert len(take_checkpoint(a.odometry, "r1", "e1", 3, 24, 2.4, coded=False).points) < len(points) / 2
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
    mapper's first poses are then within a centimetre and a half of the original's. The periodic
    checkpoints' map at half the mapper's voxel (the default) continues closer than one at the
    mapper's voxel (the default before), one point per voxel."""
    src = SimulatedSource(seed=5)
    scans = [src.read(i).points for i in range(0, 90, 2)]
    a = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    for i in range(35):
        a.register(i, scans[i])
    local = np.asarray(a.odometry.local_map.point_cloud())
    whole = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=34, stamp=0.0, resolution=0.0)
    default = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=34, stamp=0.0)
    coarse = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=34, stamp=0.0, resolution=0.4, coded=False)
    assert len(whole.cloud()) == len(local) > len(default.cloud()) > 2 * len(coarse.points)
    for i in range(35, 40):  # the original carries on: the reference
        a.register(i, scans[i])
    errors = {}
    for name, cp in (("whole", whole), ("default", default), ("coarse", coarse)):
        b = RobotMapper(voxel_size=0.4, max_range=src.max_range)
        b.continue_from(cp, np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        errors[name] = max(np.linalg.norm(b.register(i, scans[i]).pose[:3, 3] - a.poses[i][:3, 3])
                           for i in range(35, 40))
    assert errors["whole"] < 0.015 and errors["whole"] < errors["coarse"], errors
    assert errors["default"] < errors["coarse"], errors


def test_a_coded_map_that_does_not_decode_is_refused() -> None:
    """The coded map comes from the network: a payload cut short, a count it does not hold, or a
    coded map with float32 points beside it is a ``WireError``, never a crash."""
    src = SimulatedSource()
    a = RobotMapper(voxel_size=0.5, max_range=src.max_range)
    for i in range(5):
        a.register(i, src.read(i).points)
    cp = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=4, stamp=0.0)
    assert cp.packed is not None and len(cp.cloud()) == cp.n_points
    for bad in (replace(cp, packed=cp.packed[: len(cp.packed) // 2]), replace(cp, n_points=cp.n_points + 1)):
        msg = wire.decode(wire.encode(bad), expect=wire.Checkpoint)  # the fields alone are valid
        with pytest.raises(wire.WireError):
            msg.cloud()
    with pytest.raises(wire.WireError, match="float32 points beside"):
        replace(cp, points=np.zeros((3, 3), np.float32))
    with pytest.raises(wire.WireError, match="at most"):
        cp.cloud(wire.Limits(max_checkpoint_points=cp.n_points - 1))
