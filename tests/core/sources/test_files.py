"""Scan folders: KITTI .bin, PCD/PLY, replay orders."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from zoffload.sources import ScanSourceError, open_scan_source
from zoffload.sources.base import replay_order
from zoffload.sources.kitti import KittiBinSource, read_kitti_bin


def write_bin(path: Path, pts: np.ndarray) -> None:
    rows = np.hstack([pts, np.ones((len(pts), 1))]).astype(np.float32)
    rows.tofile(path)


def test_kitti_folder_reads_points_in_name_order(tmp_path: Path) -> None:
    for i in range(3):
        write_bin(tmp_path / f"{i:06d}.bin", np.full((5 + i, 3), float(i)))
    src = open_scan_source(str(tmp_path))
    assert isinstance(src, KittiBinSource) and len(src) == 3
    f = src.read(2)
    assert f.points.shape == (7, 3) and f.points.dtype == np.float32 and f.points[0, 0] == 2.0
    assert f.gt_pose is None


def test_truncated_or_empty_scan_file_is_a_clear_error(tmp_path: Path) -> None:
    write_bin(tmp_path / "000000.bin", np.zeros((4, 3)))
    (tmp_path / "000001.bin").write_bytes(b"\x00" * 30)  # not a multiple of 16 bytes
    with pytest.raises(ScanSourceError, match="000001.bin.*truncated"):
        open_scan_source(str(tmp_path))
    (tmp_path / "000001.bin").write_bytes(b"")
    with pytest.raises(ScanSourceError, match="empty"):
        read_kitti_bin(tmp_path / "000001.bin")


def test_missing_or_wrong_folder(tmp_path: Path) -> None:
    with pytest.raises(ScanSourceError, match="does not exist"):
        open_scan_source(str(tmp_path / "nope"))
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ScanSourceError, match="no .bin, .pcd or .ply"):
        open_scan_source(str(tmp_path))
    with pytest.raises(ScanSourceError, match="not a folder"):
        open_scan_source(str(tmp_path / "notes.txt"))


def test_pcd_and_ply_folders_through_open3d(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    pts = np.random.default_rng(0).random((100, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(tmp_path / "a.pcd"), cloud)
    o3d.io.write_point_cloud(str(tmp_path / "b.ply"), cloud)
    src = open_scan_source(str(tmp_path))
    assert len(src) == 2
    np.testing.assert_allclose(src.read(0).points, pts, atol=1e-6)
    (tmp_path / "c.pcd").write_text("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\n")  # header only
    with pytest.raises(ScanSourceError, match="c.pcd"):
        open_scan_source(str(tmp_path)).read(2)


def test_real_kitti360_scans(kitti_dir: Path) -> None:
    src = open_scan_source(str(kitti_dir))
    assert len(src) == 50
    pts = src.read(0).points
    assert 100_000 < len(pts) < 130_000  # an HDL-64 scan
    assert np.isfinite(pts).all() and np.abs(pts).max() < 130


def test_replay_orders() -> None:
    assert list(replay_order(3, "once")) == [0, 1, 2]
    assert list(itertools.islice(replay_order(3, "loop"), 7)) == [0, 1, 2, 0, 1, 2, 0]
    assert list(itertools.islice(replay_order(3, "pingpong"), 9)) == [0, 1, 2, 1, 0, 1, 2, 1, 0]
    assert list(replay_order(1, "pingpong")) == [0]
    with pytest.raises(ValueError):
        list(replay_order(3, "backwards"))
