"""Trajectory error of an estimate against a reference, matched by scan sequence number.

Both trajectories are re-expressed relative to their pose at the first sequence number they
share (the mapper starts at identity there), with no further alignment: the figure includes all
drift, as a robot would experience it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class TrajectoryError:
    matched: int  # scans present in both
    ate_rmse: float  # root mean square translation error [m]
    ate_max: float
    final_error: float  # error at the last matched scan [m]
    path_length: float  # reference path length over the matched scans [m]
    drift_percent: float  # final_error / path_length * 100

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def trajectory_error(est_seqs: np.ndarray, est_poses: np.ndarray, ref_seqs: np.ndarray,
                     ref_poses: np.ndarray) -> TrajectoryError | None:
    """None when fewer than two scans are shared."""
    common, ei, ri = np.intersect1d(np.asarray(est_seqs), np.asarray(ref_seqs), return_indices=True)
    if len(common) < 2:
        return None
    est = np.asarray(est_poses)[ei]
    ref = np.asarray(ref_poses)[ri]
    est_rel = np.linalg.inv(est[0]) @ est
    ref_rel = np.linalg.inv(ref[0]) @ ref
    err = np.linalg.norm(est_rel[:, :3, 3] - ref_rel[:, :3, 3], axis=1)
    length = float(np.sum(np.linalg.norm(np.diff(ref_rel[:, :3, 3], axis=0), axis=1)))
    return TrajectoryError(
        matched=len(common),
        ate_rmse=float(np.sqrt(np.mean(err**2))),
        ate_max=float(err.max()),
        final_error=float(err[-1]),
        path_length=length,
        drift_percent=float(err[-1] / length * 100) if length > 0 else 0.0,
    )


def relative_to_first(seqs: np.ndarray, poses: np.ndarray, anchor_seq: int) -> np.ndarray:
    """Poses expressed relative to the pose of ``anchor_seq`` (for plotting against each other)."""
    idx = int(np.flatnonzero(np.asarray(seqs) == anchor_seq)[0])
    return np.linalg.inv(poses[idx]) @ poses
