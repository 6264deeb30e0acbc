"""The built-in simulator as a scan source: the warehouse ray-cast along its loop, with poses."""

from __future__ import annotations

import numpy as np

from zoffload.sources.base import ScanFrame
from zoffload.sources.sim import VLP16, LidarModel, warehouse, warehouse_loop
from zoffload.sources.sim.lidar import cast_columns


class SimulatedSource:
    """Scans of a VLP-16-like sensor driving ``laps`` loops of the warehouse at ``speed`` m/s.

    Scan ``i`` is complete at ``i / rate_hz`` seconds and its ground truth is the pose then; each
    scan's noise is seeded by its index, so reading a scan twice gives the same points. By default
    the whole scan is cast from that one pose (no motion during the sweep). With ``sweep``, each
    column fires at its own time over the rotation before, from where the sensor is then, and
    the points carry those times, so a moving sensor's scan is skewed as a real one is (what
    deskewing undoes).
    """

    def __init__(
        self, seed: int = 0, speed: float = 1.2, laps: float = 1.0, lidar: LidarModel = VLP16,
        sweep: bool = False,
    ) -> None:
        self.trajectory = warehouse_loop(speed=speed)
        self.scene = warehouse(self.trajectory.xy, seed=seed)
        self.lidar = lidar
        self.seed = seed
        self.sweep = sweep
        options = ([f"speed={speed:g}"] if speed != 1.2 else []) + (["sweep"] if sweep else [])
        self.name = "sim:warehouse" + (f"[{','.join(options)}]" if options else "")
        self.rate_hz = lidar.rate_hz
        self.max_range = 40.0  # indoor: nothing is farther; sizes the mapper's voxel
        self._n = int(laps * self.trajectory.length / speed * self.rate_hz)

    def __len__(self) -> int:
        return self._n

    def read(self, index: int) -> ScanFrame:
        end = index / self.rate_hz
        pose = self.trajectory.pose_at(end)
        rng = np.random.default_rng((self.seed, index))
        if not self.sweep:
            points, _ = cast_columns(self.scene, pose, self.lidar, rng)
            return ScanFrame(index=index, points=points, gt_pose=pose)
        # Column c fires at (c + 1) / columns of the period before the scan is complete
        period = 1.0 / self.rate_hz
        fired = end - period + (np.arange(self.lidar.columns) + 1) * (period / self.lidar.columns)
        points, col = cast_columns(self.scene, pose, self.lidar, rng, self.trajectory.poses_at(fired))
        return ScanFrame(index=index, points=points, gt_pose=pose, times=fired[col])
