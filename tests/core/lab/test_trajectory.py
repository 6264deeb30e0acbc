from __future__ import annotations

import numpy as np

from zoffload.lab.eval.trajectory import trajectory_error


def line(n: int, step: float, offset: np.ndarray | None = None) -> np.ndarray:
    poses = np.stack([np.eye(4)] * n)
    poses[:, 0, 3] = np.arange(n) * step
    if offset is not None:
        poses = offset @ poses
    return poses


def test_identical_up_to_a_rigid_offset_has_zero_error() -> None:
    off = np.eye(4)
    off[:3, 3] = [5, -2, 1]
    off[:2, :2] = [[0, -1], [1, 0]]
    e = trajectory_error(np.arange(10), line(10, 1.0), np.arange(10), line(10, 1.0, off))
    assert e is not None and e.ate_rmse < 1e-9 and e.path_length == 9.0


def test_scale_error_is_measured_on_matched_scans_only() -> None:
    est = line(10, 0.9)  # 10 % short
    e = trajectory_error(np.arange(10), est, np.arange(20), line(20, 1.0))
    assert e is not None and e.matched == 10
    assert abs(e.final_error - 0.9) < 1e-9 and abs(e.drift_percent - 10.0) < 1e-9
    # scans lost on the way: the anchor is the first shared scan
    e2 = trajectory_error(np.arange(3, 10), est[3:], np.arange(10), line(10, 1.0))
    assert e2 is not None and e2.matched == 7 and abs(e2.final_error - 0.6) < 1e-9
    assert trajectory_error(np.array([1]), est[:1], np.arange(5), line(5, 1.0)) is None
