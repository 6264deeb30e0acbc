"""The robot's local odometry continues the edge's trajectory from a checkpoint (simulator scans)."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.mapping.checkpoint import take_checkpoint
from zoffload.mapping.mapper import RobotMapper
from zoffload.protocol import wire
from zoffload.robot.odometry import LocalOdometry, local_voxel_size
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")


@pytest.fixture(scope="module")
def edge_run() -> tuple[SimulatedSource, RobotMapper, wire.Checkpoint]:
    """An edge's mapper over scans 0-29, its checkpoint after scan 29, and the same mapper
    carried on to scan 59 (the reference)."""
    src = SimulatedSource()
    mapper = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    cp = None
    for i in range(60):
        mapper.register(i, src.read(i).points)
        if i == 29:
            cp = take_checkpoint(mapper.odometry, "robot1", "edge1", 7, 29, stamp=2.9)
    assert cp is not None
    return src, mapper, cp


def test_seeded_local_odometry_continues_the_trajectory(edge_run: tuple) -> None:
    src, mapper, cp = edge_run
    odo = LocalOdometry("robot1", src.max_range, threads=1)
    assert odo.voxel == local_voxel_size(40.0) == 0.8 and not odo.active
    odo.begin(cp, [(28, mapper.poses[28]), (29, mapper.poses[29])])
    for i in range(30, 60):
        pose, cpu = odo.register(i, src.read(i).points, 3.0 + i / 10)
        assert cpu > 0
    edge_xyz = mapper.poses[59][:3, 3]
    assert np.linalg.norm(pose[:3, 3] - edge_xyz) < 0.5, (pose[:3, 3], edge_xyz)
    assert np.linalg.norm(edge_xyz - mapper.poses[29][:3, 3]) > 3.0  # it really moved meanwhile
    # Unseeded, the same scans start again at the origin: the checkpoint is what continues it
    fresh = LocalOdometry("robot1", src.max_range)
    fresh.begin(None, [])
    for i in range(30, 35):
        p, _ = fresh.register(i, src.read(i).points, 0.0)
    assert np.linalg.norm(p[:3, 3] - mapper.poses[34][:3, 3]) > 2.0
    assert odo.cpu_summary()["median"] is not None and odo.registered == 30


def test_unanswered_scans_are_caught_up_and_the_snapshot_carries_the_rest(edge_run: tuple) -> None:
    src, mapper, cp = edge_run
    odo = LocalOdometry("robot1", src.max_range, catch_up=4, checkpoint_every=10)
    for i in range(28, 36):  # sent while attached; only 28 and 29 got an answer
        odo.hold(i, src.read(i).points, i / 10)
    assert len(odo.ring) == 4  # bounded: 32..35
    odo.begin(cp, [(29, mapper.poses[29])])
    done = odo.catch_up(before=36, posed={33})
    assert [s for s, _, _ in done] == [32, 34, 35] and not odo.ring
    for i in range(36, 48):
        pose, _ = odo.register(i, src.read(i).points, i / 10)
    assert np.linalg.norm(pose[:3, 3] - mapper.poses[47][:3, 3]) < 0.5
    snap = odo.snapshot()
    assert snap.checkpoint is not None and snap.checkpoint.edge == "" and snap.checkpoint.robot == "robot1"
    # the period's first registration took one, then every 10th registration: 32, then 43
    assert snap.checkpoint.seq == 43 and list(snap.seqs) == [32, *range(34, 48)]
    assert snap.poses.shape == (15, 4, 4)
    wire.decode(wire.encode(snap.checkpoint), expect=wire.Checkpoint)  # a valid message
    odo.end()
    assert not odo.active and len(odo.snapshot().seqs) == 0 and odo.snapshot().checkpoint is not None
