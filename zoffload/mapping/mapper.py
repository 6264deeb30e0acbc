"""One robot's map on the edge: KISS-ICP odometry plus a global registered map.

Scans lost on the way (a gap in the sequence numbers) stretch KISS-ICP's constant-velocity
prediction over the gap; without it, one lost second of a moving robot derails the odometry.

KISS-ICP fixes its voxel size at construction and downsamples every frame again internally (at
0.5x and 1.5x that size). The edge sizes it so the robot's own downsampling never makes the
mapper's grids finer than the data: ``voxel = max(max_range / 100, 2 * robot voxel_max)``
(KISS-ICP's own default is max_range / 100). KISS-ICP's local map forgets points beyond
``max_range``; the global map kept here does not, and is what "map points" counts.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from zoffload.mapping.se3 import se3_power
from zoffload.mapping.voxelset import VoxelSet


@dataclass(frozen=True)
class Registration:
    pose: np.ndarray  # 4x4, first registered scan = identity
    keypoints: int  # points KISS-ICP aligned against its local map
    sigma: float  # adaptive threshold after this scan
    map_points: int
    proc_time: float  # seconds of registration on the edge (ICP + global map)
    icp_time: float  # seconds of KISS-ICP alone


def mapper_voxel_size(max_range: float, robot_voxel_max: float, configured: float | None = None) -> float:
    """The KISS-ICP voxel size the edge uses for a robot (see module docstring)."""
    if configured is not None:
        return configured
    return max(max_range / 100.0, 2.0 * robot_voxel_max)


def load_kiss_icp() -> tuple[Any, Any]:
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("the edge mapper needs kiss-icp: pip install 'zoffload[edge]'") from exc
    return KISSConfig, KissICP


def deskew_times(times: np.ndarray | None, n: int) -> np.ndarray:
    """Per-point times as KISS-ICP's deskewing takes them: float64 in [0, 1] over the scan (the
    fraction every KISS-ICP version understands: up to 1.2.1 it expected them normalised, from
    1.2.2 it normalises them itself). An empty array (no deskew) when there are none or they do
    not spread: KISS-ICP 1.3 aborts the process (SOPHUS_ENSURE) on all-equal times.
    ``ValueError`` when there is not one finite time per point."""
    if times is None or n == 0:
        return np.empty(0)
    t = np.asarray(times, np.float64).reshape(-1)
    if len(t) != n:
        raise ValueError(f"{len(t)} point times for {n} points")
    if not np.isfinite(t).all():
        raise ValueError("non-finite point times")
    lo, hi = float(t.min()), float(t.max())
    if not hi > lo:
        return np.empty(0)
    return (t - lo) / (hi - lo)


class RobotMapper:
    """KISS-ICP odometry and a global map for one robot."""

    def __init__(
        self,
        voxel_size: float,
        max_range: float,
        min_range: float = 0.0,
        max_points_per_voxel: int = 20,
        deskew: bool = False,
        map_resolution: float = 0.1,
        max_gap: int = 50,
    ) -> None:
        KISSConfig, KissICP = load_kiss_icp()
        config = KISSConfig()
        config.data.max_range = max_range
        config.data.min_range = min_range
        config.data.deskew = deskew
        config.mapping.voxel_size = voxel_size
        config.mapping.max_points_per_voxel = max_points_per_voxel
        self.config = config
        self.odometry = KissICP(config)
        # One point per map voxel, never forgotten: the registered global map.
        self.global_map = VoxelSet(map_resolution)
        self.map_resolution = map_resolution
        self.voxel_size = voxel_size
        self.max_gap = max_gap  # beyond this many lost scans, constant velocity means nothing
        self.deskew = deskew
        self.seqs: list[int] = []
        self.poses: list[np.ndarray] = []

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration:
        """Register one scan; ``times`` (per point, seconds, any offset) deskew it when the
        mapper was made with ``deskew`` (see ``deskew_times``)."""
        t0 = time.perf_counter()
        frame = np.asarray(points, dtype=np.float64)
        stamps = deskew_times(times, len(frame)) if self.deskew else np.empty(0)
        # Scans lost on the way: KISS-ICP predicts one scan period of motion, so stretch its
        # constant-velocity model over the gap, and bring it back to one period afterwards.
        gap = int(seq) - self.seqs[-1] if self.seqs else 1
        stretch = 1 < gap <= self.max_gap
        if stretch and len(stamps):
            # Deskew with one period of motion (the sweep's), not the stretched prediction
            frame = self.odometry.preprocessor.preprocess(frame, stamps, self.odometry.last_delta)
            stamps = np.empty(0)
        if stretch:
            self.odometry.last_delta = se3_power(self.odometry.last_delta, gap)
        # Run KISS-ICP (it returns the scan deskewed, which is what the global map keeps)
        frame_out, keypoints = self.odometry.register_frame(frame, stamps)
        if len(stamps):
            frame = np.asarray(frame_out)
        if stretch:
            self.odometry.last_delta = se3_power(self.odometry.last_delta, 1.0 / gap)
        icp_time = time.perf_counter() - t0
        pose = self.odometry.last_pose.copy()
        # Grow the global map with the scan in world coordinates
        self.global_map.add(frame, pose)
        self.seqs.append(int(seq))
        self.poses.append(pose)
        return Registration(
            pose=pose,
            keypoints=int(len(keypoints)),
            sigma=float(self.odometry.adaptive_threshold.get_threshold()),
            map_points=len(self.global_map),
            proc_time=time.perf_counter() - t0,
            icp_time=icp_time,
        )

    @property
    def map_points(self) -> int:
        return len(self.global_map)

    def map_cloud(self) -> np.ndarray:
        return self.global_map.points().astype(np.float32)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        seqs = np.asarray(self.seqs, np.int64)
        poses = np.asarray(self.poses, np.float64).reshape(-1, 4, 4)
        return seqs, poses
