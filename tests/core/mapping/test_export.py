"""Map export to PLY and PCD."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from zoffload.sources import open_scan_source


def test_map_export_formats(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    from zoffload.mapping.export import write_point_cloud

    pts = np.random.default_rng(3).random((500, 3)).astype(np.float32)
    for ext in ("ply", "pcd"):
        path = write_point_cloud(tmp_path / f"map.{ext}", pts)
        back = np.asarray(o3d.io.read_point_cloud(str(path)).points)
        np.testing.assert_allclose(back, pts, atol=1e-6)
        assert open_scan_source(str(tmp_path)).read(0).points.shape == (500, 3)
