"""The built-in simulator: a warehouse scene ray-cast with a VLP-16-like LiDAR along a trajectory."""

from zoffload.sources.sim.lidar import VLP16, LidarModel, cast_scan
from zoffload.sources.sim.scene import Scene, warehouse
from zoffload.sources.sim.trajectory import Trajectory, warehouse_loop

__all__ = ["LidarModel", "VLP16", "cast_scan", "Scene", "warehouse", "Trajectory", "warehouse_loop"]
