"""The scan experiment's reference trajectory on real-data folders (KISS-ICP on every raw scan):
numbered by the sensor's seq, not by the robot's records (a loop overrun leaves a seq with none)."""

from __future__ import annotations

from itertools import islice
from pathlib import Path

import numpy as np

from zoffload.lab.scan_experiment import _reference
from zoffload.sources import open_scan_source
from zoffload.sources.base import replay_order


def test_the_reference_follows_the_replay_past_scans_the_robot_never_read(tmp_path: Path) -> None:
    """A folder of 8 scans replayed forth and back; the robot's records miss seqs 3 and 9 (its loop
    overran). Numbering the records as seqs shifted every later reference pose by a scan (0.8 m
    here; metres on KITTI-360); each seq must sit where its own scan was taken."""
    sim = open_scan_source("sim:speed=8")  # 0.8 m a scan at 10 Hz
    gt = []
    for i in range(8):
        frame = sim.read(i)
        assert frame.gt_pose is not None
        gt.append(frame.gt_pose)
        xyzi = np.zeros((len(frame.points), 4), np.float32)
        xyzi[:, :3] = frame.points
        xyzi.tofile(tmp_path / f"{i:06d}.bin")
    folder = open_scan_source(str(tmp_path))
    order = list(islice(replay_order(8, "pingpong"), 14))  # 0..7, 6..1, 0, 1
    recs = [{"seq": s, "index": order[s]} for s in range(14) if s not in (3, 9)]

    seqs, poses, what = _reference(folder, recs, "pingpong", False, {})
    assert "every raw scan" in what
    assert list(seqs) == list(range(14))
    rel = np.linalg.inv(poses[0]) @ poses
    for s in range(14):
        truth = np.linalg.inv(gt[0]) @ gt[order[s]]
        assert np.linalg.norm(rel[s, :3, 3] - truth[:3, 3]) < 0.2, (s, order[s])
