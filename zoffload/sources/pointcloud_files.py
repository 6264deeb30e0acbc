"""Folders of ``.pcd`` or ``.ply`` scans (one scan per file, name order), read by their declared
fields: x, y, z and, where the file has one, the per-point time (``t``, ``time``, ``timestamp``
or ``offset_time``, normalised as PointCloud2's, see ros2/pointcloud.py). A PLY file whose vertex
layout has list properties is read through open3d instead (x, y, z only)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from zoffload.ros2.pointcloud import TIME_FIELDS, seconds
from zoffload.sources.base import ScanFrame, ScanSourceError
from zoffload.sources.pcd import read_pcd
from zoffload.sources.ply import PlyLayoutError, read_ply


def _open3d() -> Any:
    try:
        import open3d as o3d
    except ImportError as exc:
        raise ScanSourceError(
            "reading this PLY file needs open3d: pip install 'zoffload[robot]' "
            "(and apt-get install libusb-1.0-0)"
        ) from exc
    return o3d


def cloud_from_fields(path: Path, fields: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
    """Points and times from a file's fields; rows without finite coordinates (and time) are
    left out when the file has times, so the two stay aligned."""
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise ScanSourceError(f"{path}: no {'/'.join(missing)} field (fields: {', '.join(fields) or 'none'})")
    points = np.stack([fields["x"], fields["y"], fields["z"]], axis=1).astype(np.float32)
    name = next((f for f in fields if f in TIME_FIELDS), None)
    if name is None:
        return points, None
    times = seconds(fields[name])
    keep = np.isfinite(points).all(axis=1) & np.isfinite(times)
    return points[keep], times[keep]


def read_point_cloud_times(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float32 points and (N,) float64 times in seconds (None without a time field)."""
    if not path.is_file() or path.stat().st_size == 0:
        raise ScanSourceError(f"{path}: missing or empty scan file")
    if path.suffix.lower() == ".pcd":
        points, times = cloud_from_fields(path, read_pcd(path))
    else:
        try:
            points, times = cloud_from_fields(path, read_ply(path))
        except PlyLayoutError:
            cloud = _open3d().io.read_point_cloud(str(path))
            points, times = np.asarray(cloud.points, dtype=np.float32), None
    if len(points) == 0:
        raise ScanSourceError(f"{path}: no points could be read (truncated or not a point cloud)")
    return points, times


def read_point_cloud_file(path: Path) -> np.ndarray:
    return read_point_cloud_times(path)[0]


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
        points, times = read_point_cloud_times(self.files[index])
        return ScanFrame(index=index, points=points, times=times)
