"""A scan after lost ones is registered from three guesses (the motion kept over the gap, the robot
stopped, the robot reversed) and the result that overlaps the local map best is kept, the kept
motion unless another adds ``GAP_MARGIN``.

The simulator's scans taken every 5th or 10th (a car at 6-12 m/s) stand in for a fast robot. Each
case is also run with the constant-velocity guess alone, which must show the fault (or, for a robot
moving on, the same pose), so the tests fail if the guesses stop mattering."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.mapping.mapper import RobotMapper
from zoffload.mapping.voxel import voxel_downsample
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")
SRC = SimulatedSource()
KEPT_ONLY = (("kept", 1.0),)


def run(path: list[int], upto: int, gap: int, stride: int) -> dict[str, tuple[float, str]]:
    """The scan ``upto + gap`` of ``path`` after losing those between: its position error (m)
    against a mapper that registered every scan, and the guess kept; with the constant-velocity
    guess alone ("cv") and with all three ("all")."""
    scans = {i: voxel_downsample(SRC.read(stride * i).points, 0.05) for i in set(path)}
    ref = RobotMapper(0.5, SRC.max_range)
    truth = [ref.register(s, scans[i]).pose for s, i in enumerate(path[: upto + gap + 1])]
    out = {}
    for name, motions in (("cv", KEPT_ONLY), ("all", None)):
        m = RobotMapper(0.5, SRC.max_range) if motions is None else RobotMapper(0.5, SRC.max_range,
                                                                                gap_motions=motions)
        for s in range(upto + 1):
            m.register(s, scans[path[s]])
        r = m.register(upto + gap, scans[path[upto + gap]])
        out[name] = (float(np.linalg.norm(r.pose[:3, 3] - truth[upto + gap][:3, 3])), r.gap_motion)
    return out


def test_a_robot_that_stopped_while_its_scans_were_lost_is_found_where_it_stopped() -> None:
    got = run(list(range(31)) + [30] * 10, upto=30, gap=6, stride=10)
    assert got["cv"][0] > 2.0  # the fault: six periods of 1.2 m predicted, ICP settles metres off
    assert got["all"][0] < 0.05 and got["all"][1] != "kept", got


def test_a_robot_that_turned_back_during_a_gap_is_found() -> None:
    got = run(list(range(31)) + list(range(29, 0, -1)), upto=30, gap=3, stride=5)
    assert got["cv"][0] > 1.0 and got["all"][0] < 0.05 and got["all"][1] != "kept", got


@pytest.mark.parametrize("gap", [2, 6])
def test_a_robot_moving_on_keeps_its_motion(gap: int) -> None:
    """Six scans lost at 12 m/s, the car going on: the stopped guess lies where the map is densest
    (where the robot has been); scored on where ICP takes each guess, not on the guess itself,
    the motion kept still wins."""
    got = run(list(range(45)), upto=25, gap=gap, stride=10)
    assert got["cv"][0] < 0.15 and got["all"] == (pytest.approx(got["cv"][0], abs=1e-6), "kept"), got
