"""A scan after lost ones is registered from two guesses: the constant velocity stretched over the
gap, and standing still since the last pose; the one that fits the local map better is kept.

The simulator's scans taken every 10th (a car at about 12 m/s) stand in for a fast robot."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.mapping.mapper import RobotMapper, map_overlap
from zoffload.mapping.voxel import voxel_downsample
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")
SRC = SimulatedSource()


def run(path: list[int], upto: int, gap: int, stride: int) -> tuple[float, float, int]:
    """Error of the scan after the gap (m) with the stretched guess only and with both, and how
    often standing still was chosen; the reference registers every scan."""
    scans = {i: voxel_downsample(SRC.read(stride * i).points, 0.05) for i in set(path)}
    ref = RobotMapper(0.5, SRC.max_range)
    truth = [ref.register(s, scans[i]).pose for s, i in enumerate(path[: upto + gap + 1])]
    out = []
    for both in (False, True):
        m = RobotMapper(0.5, SRC.max_range, standstill_guess=both)
        for s in range(upto + 1):
            m.register(s, scans[path[s]])
        pose = m.register(upto + gap, scans[path[upto + gap]]).pose
        out.append(float(np.linalg.norm(pose[:3, 3] - truth[upto + gap][:3, 3])))
    return out[0], out[1], m.standstill_chosen


def test_a_robot_that_stopped_while_its_scans_were_lost_is_found_where_it_stopped() -> None:
    stretched, both, chosen = run(list(range(31)) + [30] * 10, upto=30, gap=6, stride=10)
    assert stretched > 2.0  # the fault: six periods of 1.2 m predicted, ICP settles metres off
    assert both < 0.05 and chosen == 1


def test_a_robot_that_turned_back_during_a_gap_is_found() -> None:
    stretched, both, chosen = run(list(range(31)) + list(range(29, 0, -1)), upto=30, gap=3, stride=5)
    assert stretched > 1.0 and both < 0.05 and chosen == 1


def test_a_robot_moving_on_keeps_the_stretched_guess() -> None:
    stretched, both, chosen = run(list(range(40)), upto=30, gap=2, stride=10)
    assert stretched < 0.05 and both == pytest.approx(stretched) and chosen == 0


def test_the_overlap_counts_points_in_occupied_voxels() -> None:
    from zoffload.mapping.mapper import _voxel_keys

    occupied = np.unique(_voxel_keys(np.array([[0.1, 0.1, 0.1], [1.1, 0.2, 0.3]]), 0.5))
    pts = np.array([[0.2, 0.2, 0.2], [5.0, 5.0, 5.0]])
    assert map_overlap(pts, np.eye(4), occupied, 0.5) == 0.5
    shift = np.eye(4)
    shift[0, 3] = 0.9  # (0.2 -> 1.1: the second occupied voxel; 5.9: none)
    assert map_overlap(pts, shift, occupied, 0.5) == 0.5
    shift[0, 3] = 3.0
    assert map_overlap(pts, shift, occupied, 0.5) == 0.0
    assert map_overlap(np.zeros((0, 3)), np.eye(4), occupied, 0.5) == 0.0
