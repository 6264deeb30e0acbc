"""The real KITTI-360 scans through a bag written here: the same points, so the same trajectory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("kiss_icp")

from tests.core.sources.bags import scan_bag  # noqa: E402
from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size  # noqa: E402
from zoffload.sources import open_scan_source  # noqa: E402

N = 20


def trajectory(source: object, n: int) -> np.ndarray:
    mapper = RobotMapper(voxel_size=mapper_voxel_size(100.0, 0.07), max_range=100.0)
    for i in range(n):
        f = source.read(i)  # type: ignore[attr-defined]
        mapper.register(i, f.points, f.times)
    return mapper.trajectory()[1]


@pytest.mark.realdata
@pytest.mark.parametrize("storage", ["mcap", "ros1"])
def test_kitti360_from_a_bag_maps_as_the_folder(kitti_dir: Path, tmp_path: Path, storage: str) -> None:
    folder = open_scan_source(str(kitti_dir))
    scans = [folder.read(i).points for i in range(N)]
    path = scan_bag(tmp_path / "kitti360", [(p, None) for p in scans], storage=storage)
    bag = open_scan_source(f"bag:{path}")
    assert len(bag) == N and bag.rate_hz == pytest.approx(10.0)
    for i in (0, N - 1):
        np.testing.assert_array_equal(bag.read(i).points, scans[i])
    from_folder, from_bag = trajectory(folder, N), trajectory(bag, N)
    assert np.linalg.norm(from_folder[-1][:3, 3]) > 5.0  # the car moved
    # KISS-ICP's parallel reductions make reruns differ at 1e-16 m; the inputs are the same bits
    np.testing.assert_allclose(from_bag, from_folder, atol=1e-6)
