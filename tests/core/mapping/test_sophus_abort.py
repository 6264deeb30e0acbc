"""Poses from outside the odometry never reach KISS-ICP unchecked: its Sophus aborts the whole
process (SIGABRT, no exception) on a rotation off by more than 1e-10 or a NaN pose. Found by
``bench_stream``: a robot whose edge runs ``--no-mapping`` (acks carry a NaN pose) fell back to
local odometry seeded from that pose and died. Each case runs in a child process, so a
regression is a failed assertion with the child's output, not a dead test run."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("kiss_icp")

PRELUDE = """
import numpy as np
from zoffload.sources.simulated import SimulatedSource
src = SimulatedSource()
scans = [src.read(i).points for i in range(6)]
off = np.eye(4); off[0, 0] += 1e-8; off[0, 3] = 1.0  # within the codec's 1e-6, beyond Sophus's 1e-10
nan = np.full((4, 4), np.nan)
"""

CASES = {
    # the robot: acks without a pose, then its local odometry starts from the newest acked ones
    "robot local odometry after pose-less and noisy acks": """
import threading
from zoffload.robot.fleet import FleetState
from zoffload.robot.ledger import ScanLedger
from zoffload.robot.localpose import PoseKeeper
from zoffload.robot.odometry import LocalOdometry
odo = LocalOdometry("r1", src.max_range, voxel=1.0)
keeper = PoseKeeper(odo, FleetState("r1", 2.0), ScanLedger(), threading.Lock(), 0.1, 2.0)
keeper.edge_pose(0, nan)
assert keeper.pose is None, "a pose-less ack became the robot's pose"
odo.begin(None, [(0, off), (1, off @ off)])
for i in range(2, 6):
    odo.register(i, scans[i], float(i))
""",
    # the local odometry seeded from a checkpoint whose pose and delta are off by float noise
    "local odometry seeded from a noisy checkpoint": """
from zoffload.mapping.checkpoint import take_checkpoint
from zoffload.robot.odometry import LocalOdometry
import dataclasses
a = LocalOdometry("r1", src.max_range, voxel=1.0)
a.begin(None, [])
for i in range(3):
    a.register(i, scans[i], float(i))
cp = dataclasses.replace(a.snapshot().checkpoint, pose=off, delta=off)
b = LocalOdometry("r1", src.max_range, voxel=1.0)
b.begin(cp, [])
for i in range(3, 6):
    b.register(i, scans[i], float(i))
""",
    # the edge: an attach whose checkpoint and local poses are off by float noise
    "edge mapper continuing a noisy attach": """
from zoffload.mapping.checkpoint import take_checkpoint
from zoffload.mapping.mapper import RobotMapper
import dataclasses
a = RobotMapper(voxel_size=0.5, max_range=src.max_range)
for i in range(3):
    a.register(i, scans[i])
cp = dataclasses.replace(take_checkpoint(a.odometry, "r1", "e1", 1, 2, 0.0), pose=off, delta=off)
b = RobotMapper(voxel_size=0.5, max_range=src.max_range)
b.continue_from(cp, np.array([3]), np.array([off]))
b.register(5, scans[5])  # a gap of two scans: the stretched motion model too
""",
}


@pytest.mark.parametrize("name", list(CASES))
def test_no_pose_from_outside_aborts_the_process(name: str) -> None:
    code = textwrap.dedent(PRELUDE) + textwrap.dedent(CASES[name]) + "\nprint('survived')\n"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "survived" in r.stdout, \
        f"{name}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
