"""The voxel grid against a straightforward reference, and the global-map voxel set."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from zoffload.mapping.voxel import voxel_downsample, voxel_downsample_counts
from zoffload.mapping.voxelset import VoxelSet
from zoffload.sources.kitti import read_kitti_bin


def reference_grid(points: np.ndarray, v: float) -> dict[tuple[int, int, int], np.ndarray]:
    """The seed's definition, written the plain way: key = floor(p / v), centroid per voxel."""
    acc: dict[tuple[int, int, int], list[np.ndarray]] = {}
    for p in points.astype(np.float64):
        key = (math.floor(p[0] / v), math.floor(p[1] / v), math.floor(p[2] / v))
        acc.setdefault(key, []).append(p)
    return {k: np.mean(ps, axis=0) for k, ps in acc.items()}


def assert_matches_reference(points: np.ndarray, v: float) -> None:
    """Same number of voxels, same centroids (compared as sorted sets), every point counted."""
    ref = reference_grid(points, v)
    got, counts = voxel_downsample_counts(points, v)
    assert len(got) == len(ref)
    assert counts.sum() == len(points)
    ref_arr = np.array(sorted(map(tuple, ref.values())))
    got_arr = np.array(sorted(map(tuple, got)))
    np.testing.assert_allclose(got_arr, ref_arr, rtol=0, atol=1e-9)


@pytest.mark.parametrize("v", [0.01, 0.05, 0.3, 1.0])
def test_random_cloud_matches_reference(v: float) -> None:
    rng = np.random.default_rng(7)
    pts = rng.uniform(-5, 5, size=(3000, 3)).astype(np.float32)
    assert_matches_reference(pts, v)


def test_points_on_voxel_boundaries_and_negatives() -> None:
    # Exact multiples of v and values just below them are where a sloppy floor differs.
    v = 0.1
    base = np.array([[0.0, 0.0, 0.0], [-0.1, 0.2, -0.3], [0.3, -0.0, 1.0]])
    pts = np.concatenate([base, np.nextafter(base, -np.inf), np.nextafter(base, np.inf)])
    assert_matches_reference(pts, v)


def test_centroid_values_exact() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.05, 0.07], [0.15, 0.0, 0.0], [-0.01, 0, 0]])
    out, counts = voxel_downsample_counts(pts, 0.1)
    np.testing.assert_allclose(out[0], [0.02, 0.03, 0.04])
    np.testing.assert_allclose(out[1], [0.15, 0.0, 0.0])
    np.testing.assert_allclose(out[2], [-0.01, 0.0, 0.0])
    assert counts.tolist() == [2, 1, 1]


def test_real_kitti_scan_matches_reference(kitti_dir: Path) -> None:
    pts = read_kitti_bin(kitti_dir / "0000003000.bin")
    sub = pts[::4]  # the pure-Python reference is slow; 28k real points still cover the scan
    for v in (0.05, 0.5):
        assert_matches_reference(sub, v)


def test_reduces_and_keeps_extent() -> None:
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(20000, 3))
    out = voxel_downsample(pts, 0.5)
    assert 0 < len(out) < len(pts)
    assert np.all(out.min(0) >= pts.min(0) - 1e-12) and np.all(out.max(0) <= pts.max(0) + 1e-12)


def test_empty_and_bad_input() -> None:
    assert voxel_downsample(np.empty((0, 3)), 0.1).shape == (0, 3)
    with pytest.raises(ValueError, match="NaN"):
        voxel_downsample(np.array([[0.0, np.nan, 0.0]]), 0.1)
    with pytest.raises(ValueError, match="positive"):
        voxel_downsample(np.zeros((3, 3)), 0.0)
    with pytest.raises(ValueError, match="shape"):
        voxel_downsample(np.zeros((3, 2)), 0.1)
    with pytest.raises(ValueError, match="too far"):
        voxel_downsample(np.array([[1e6, 0.0, 0.0]]), 0.01)


def test_voxel_set_counts_distinct_voxels_and_grows() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, size=(50_000, 3))
    vs = VoxelSet(0.5, capacity=8)  # forces several rehashes
    new1 = vs.add(pts[:25_000])
    new2 = vs.add(pts[25_000:])
    assert new1 + new2 == len(vs) == len(voxel_downsample(pts, 0.5))
    assert vs.add(pts) == 0  # nothing new
    keys = np.floor(vs.points() / 0.5)
    assert len(np.unique(keys, axis=0)) == len(vs)


def test_voxel_set_transforms_by_pose() -> None:
    rng = np.random.default_rng(2)
    pts = rng.uniform(-10, 10, size=(5000, 3))
    c, sn = np.cos(0.7), np.sin(0.7)
    pose = np.array([[c, -sn, 0, 3.0], [sn, c, 0, -1.0], [0, 0, 1, 0.5], [0, 0, 0, 1]])
    a, b = VoxelSet(0.3), VoxelSet(0.3)
    a.add(pts, pose)
    b.add(pts @ pose[:3, :3].T + pose[:3, 3])
    assert len(a) == len(b)
    np.testing.assert_allclose(a.points(), b.points(), atol=1e-9)
    with pytest.raises(ValueError, match="4x4"):
        a.add(pts, np.eye(3))


def test_voxel_set_budget_keeps_the_first_voxels_and_counts_the_rest() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-20, 20, size=(20_000, 3))
    vs = VoxelSet(0.5, capacity=8, max_points=1000)
    assert vs.add(pts[:600]) == len(vs) <= 600 and vs.overflow == 0
    vs.add(pts[600:])
    assert len(vs) == 1000 and vs.full
    distinct = len(voxel_downsample(pts, 0.5))
    assert vs.overflow >= distinct - 1000  # every point in a voxel it had no room for
    kept = vs.points()
    before = vs.overflow
    assert vs.add(kept) == 0 and vs.overflow == before  # known voxels cost nothing
    # The first voxels seen are the ones kept, in order
    ref = VoxelSet(0.5)
    ref.add(pts)
    np.testing.assert_allclose(kept, ref.points()[:1000])
    assert vs._store.shape[0] <= 1000  # memory stops at the budget
    with pytest.raises(ValueError, match="max_points"):
        VoxelSet(0.5, max_points=0)


def test_voxel_set_salt_scatters_points_crafted_against_the_plain_hash() -> None:
    import time

    from benchmarks.bench_collisions import crafted_points, insert_time, random_points

    VoxelSet(0.1).add(np.zeros((4, 3)))  # compiled
    crafted, rand = crafted_points(20_000, 0.1), random_points(20_000, 0.1)
    assert VoxelSet(0.1)._salt != VoxelSet(0.1)._salt  # one salt per set
    # Same points out whatever the salt: the salt moves slots, not what is stored
    a, b = VoxelSet(0.1), VoxelSet(0.1)
    b._salt = np.int64(0)
    a.add(crafted[:3000])
    b.add(crafted[:3000])
    np.testing.assert_array_equal(a.points(), b.points())
    # Unsalted, the crafted points share one probe chain (quadratic); salted, they cost about what
    # random points cost. Bounds are loose: the machine is shared.
    t0 = time.perf_counter()
    unsalted = insert_time(crafted, 0.1, salted=False)
    salted = min(insert_time(crafted, 0.1, salted=True) for _ in range(3))
    random_t = min(insert_time(rand, 0.1, salted=True) for _ in range(3))
    assert unsalted > 10 * salted, (unsalted, salted, time.perf_counter() - t0)
    assert salted < 10 * random_t + 0.05, (salted, random_t)
