"""Map export: PLY or PCD through open3d."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_point_cloud(path: Path, points: np.ndarray) -> Path:
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("map export needs open3d: pip install 'zoffload[edge]'") from exc
    # row-major float64: open3d's binding converts any other array point by point
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, np.float64)))
    if not o3d.io.write_point_cloud(path, cloud):
        raise OSError(f"open3d could not write {path}")
    return path
