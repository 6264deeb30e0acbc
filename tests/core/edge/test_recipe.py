"""The edge's mapper recipe and budgets: clamped sizing from hostile scans, the range filter, the
global map budget and the trajectory ring with its spill to disk."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from zoffload.edge.export import RobotFiles
from zoffload.edge.recipe import RANGE_BOUNDS, VOXEL_BOUNDS, MapperRecipe
from zoffload.protocol import wire

pytest.importorskip("kiss_icp")


def scan(max_range: float = 40.0, voxel_max: float = 0.07) -> wire.Scan:
    return wire.Scan(robot="r1", seq=0, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=voxel_max,
                     max_range=max_range, n_raw=0, points=np.zeros((0, 3), np.float32))


def cloud(seed: int, n: int = 3000, spread: float = 15.0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-spread, spread, (n, 3))


@pytest.mark.parametrize("max_range, voxel_max", [(10_000.0, 10.0), (0.1, 0.0), (10_000.0, 0.0), (0.1, 10.0)])
def test_a_mapper_sized_by_a_scan_at_the_codec_bounds_is_clamped_and_registers(
        max_range: float, voxel_max: float) -> None:
    m = MapperRecipe()(scan(max_range, voxel_max))
    cfg = m.inner.config
    assert RANGE_BOUNDS[0] <= cfg.data.max_range <= RANGE_BOUNDS[1]
    assert VOXEL_BOUNDS[0] <= cfg.mapping.voxel_size <= VOXEL_BOUNDS[1]
    for seq in range(3):
        try:
            m.register(seq, cloud(seq, spread=min(cfg.data.max_range, 15.0) / 2))
        except ValueError as exc:  # nothing within range is an error, not a crash
            assert "range" in str(exc)


def test_the_edge_settings_are_taken_as_they_are() -> None:
    m = MapperRecipe(voxel_size=0.01, max_range=5000.0)(scan())
    assert m.inner.config.mapping.voxel_size == 0.01 and m.inner.config.data.max_range == 5000.0


def test_points_beyond_the_range_are_dropped_before_registration() -> None:
    m = MapperRecipe()(scan(max_range=40.0))
    pts = cloud(0)
    pts[:50] = 1e30  # far beyond any grid: the global map would refuse them after KISS-ICP moved on
    reg = m.register(0, pts)
    assert reg.map_points > 0 and m.scans == 1
    with pytest.raises(ValueError, match="no point within"):
        m.register(1, np.full((10, 3), 1e6))
    assert m.scans == 1  # the refused scan left no pose behind


def test_map_budget_and_trajectory_ring(tmp_path: Path) -> None:
    files = RobotFiles(tmp_path, "r1")
    m = MapperRecipe(map_budget=5000, trajectory_budget=10)(scan(), spill=files.spill)
    rng = np.random.default_rng(1)
    for seq in range(40):
        m.register(seq, rng.uniform(-15, 15, (3000, 3)))  # new voxels every scan
    assert m.map_points == 5000 and m.map_overflow > 0
    seqs, poses = m.trajectory()
    assert 10 <= len(seqs) <= 11 and seqs[-1] == 39 and m.scans == 40
    assert files.spilled == 40 - len(seqs) and files.parts
    # The export holds the whole trajectory and removes the parts
    path = files.export(m, {"registered": 40})
    assert path is not None and path.exists()
    full = np.load(tmp_path / "r1_trajectory.npz")
    assert full["seqs"].tolist() == list(range(40)) and full["poses"].shape == (40, 4, 4)
    assert not list(tmp_path.glob("*.part*"))
    summary = json.loads((tmp_path / "r1_edge.json").read_text())
    assert summary["registered"] == 40 and summary["backfilled_seqs"] == []  # none came in a backfill
    # A later session of the same robot writes beside it, not over it
    again = RobotFiles(tmp_path, "r1", generation=1)
    again.export(m, {})
    assert (tmp_path / "r1_map.1.ply").exists() and (tmp_path / "r1_map.ply").exists()


def test_without_a_folder_trimmed_poses_are_only_counted() -> None:
    files = RobotFiles(None, "r1")
    m = MapperRecipe(trajectory_budget=5)(scan(), spill=files.spill)
    for seq in range(20):
        m.register(seq, cloud(seq))
    assert m.scans == 20 and files.spilled == m.trimmed > 0 and files.export(m, {}) is None


def test_per_point_times_follow_the_range_filter_into_a_deskewing_mapper() -> None:
    m = MapperRecipe(deskew=True)(scan(max_range=40.0))
    pts = cloud(0)
    pts[:10] = 1e4  # beyond the range: dropped, and their times with them
    times = np.linspace(0.0, 0.1, len(pts))
    for seq in range(3):
        reg = m.register(seq, pts, times)
    assert reg.map_points > 0 and m.scans == 3
