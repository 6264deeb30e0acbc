"""Folders of ``.pcd`` or ``.ply`` scans, read with open3d (one scan per file, name order)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from zoffload.sources.base import ScanFrame, ScanSourceError


def _open3d() -> Any:
    try:
        import open3d as o3d
    except ImportError as exc:
        raise ScanSourceError(
            "reading PCD/PLY needs open3d: pip install 'zoffload[robot]' "
            "(and apt-get install libusb-1.0-0)"
        ) from exc
    return o3d


def read_point_cloud_file(path: Path) -> np.ndarray:
    if not path.is_file() or path.stat().st_size == 0:
        raise ScanSourceError(f"{path}: missing or empty scan file")
    o3d = _open3d()
    cloud = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(cloud.points, dtype=np.float32)
    if len(pts) == 0:
        raise ScanSourceError(f"{path}: no points could be read (truncated or not a point cloud)")
    return pts


class PointCloudFolderSource:
    def __init__(self, folder: Path, rate_hz: float = 10.0, max_range: float = 100.0) -> None:
        self.files = sorted([*Path(folder).glob("*.pcd"), *Path(folder).glob("*.ply")])
        if not self.files:
            raise ScanSourceError(f"no .pcd or .ply scans in {folder}")
        self.name = f"pointclouds:{folder}"
        self.rate_hz = rate_hz
        self.max_range = max_range

    def __len__(self) -> int:
        return len(self.files)

    def read(self, index: int) -> ScanFrame:
        return ScanFrame(index=index, points=read_point_cloud_file(self.files[index]))
