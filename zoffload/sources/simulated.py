"""The built-in simulator as a scan source: the warehouse ray-cast along its loop, with poses."""

from __future__ import annotations

import numpy as np

from zoffload.sources.base import ScanFrame
from zoffload.sources.sim import VLP16, LidarModel, cast_scan, warehouse, warehouse_loop


class SimulatedSource:
    """Scans of a VLP-16-like sensor driving ``laps`` loops of the warehouse at ``speed`` m/s.

    Scan ``i`` is taken at ``i / rate_hz`` seconds; each scan's noise is seeded by its index, so
    reading a scan twice gives the same points.
    """

    def __init__(
        self, seed: int = 0, speed: float = 1.2, laps: float = 1.0, lidar: LidarModel = VLP16
    ) -> None:
        self.trajectory = warehouse_loop(speed=speed)
        self.scene = warehouse(self.trajectory.xy, seed=seed)
        self.lidar = lidar
        self.seed = seed
        self.name = "sim:warehouse"
        self.rate_hz = lidar.rate_hz
        self.max_range = 40.0  # indoor: nothing is farther; sizes the mapper's voxel
        self._n = int(laps * self.trajectory.length / speed * self.rate_hz)

    def __len__(self) -> int:
        return self._n

    def read(self, index: int) -> ScanFrame:
        pose = self.trajectory.pose_at(index / self.rate_hz)
        rng = np.random.default_rng((self.seed, index))
        return ScanFrame(index=index, points=cast_scan(self.scene, pose, self.lidar, rng), gt_pose=pose)
