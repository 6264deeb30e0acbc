"""The voxel grid's pass as the robot uses it: invalid points skipped and counted, per-point times
averaged per voxel, the points' bounds, a salted hash, and scratch buffers held side by side."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.core.mapping.test_voxel import reference_grid
from zoffload.mapping.voxel import VoxelGrid, new_salt, voxel_downsample_counts


def test_invalid_points_are_skipped_and_counted_and_the_rest_is_the_papers_grid() -> None:
    rng = np.random.default_rng(5)
    pts = rng.uniform(-5, 5, size=(4000, 3)).astype(np.float32)
    dirty = pts.copy()
    dirty[[3, 77, 900], 1] = np.nan
    dirty[[10, 11], 0] = np.inf
    dirty[500] = [1e9, 0, 0]  # off the grid at 1 cm
    grid = VoxelGrid().run(dirty, 0.01, skip_invalid=True)
    assert grid.n_invalid == 6 and grid.counts.sum() == 4000 - 6
    clean = np.delete(pts, [3, 77, 900, 10, 11, 500], axis=0)
    ref = reference_grid(clean, 0.01)
    got = grid.centroids()
    assert len(got) == len(ref)
    np.testing.assert_allclose(np.array(sorted(map(tuple, got))), np.array(sorted(map(tuple, ref.values()))),
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(grid.box[:3], clean.min(axis=0), rtol=0, atol=0)
    np.testing.assert_allclose(grid.box[3:6], clean.max(axis=0), rtol=0, atol=0)
    with pytest.raises(ValueError, match="NaN"):
        VoxelGrid().run(dirty, 0.01)


def test_a_centroid_time_is_the_mean_of_its_points_times() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.05, 0.07], [0.15, 0.0, 0.0], [0.02, 0.02, 0.02]])
    times = np.array([1000.0, 1000.02, 1000.05, 1000.04])  # any offset
    grid = VoxelGrid().run(pts, 0.1, times=times)
    assert grid.counts.tolist() == [3, 1]
    mean_t = grid.mean_times()
    assert mean_t is not None
    np.testing.assert_allclose(grid.t_ref + mean_t, [1000.02, 1000.05], atol=1e-9)
    np.testing.assert_allclose(grid.box[6:], [0.0, 0.05], atol=1e-9)  # relative to t_ref
    bad = times.copy()
    bad[1] = np.nan
    skipped = VoxelGrid().run(pts, 0.1, times=bad, skip_invalid=True)
    assert skipped.n_invalid == 1 and skipped.counts.tolist() == [2, 1]


def test_two_buffers_hold_two_sizes_of_one_scan() -> None:
    pts = np.random.default_rng(1).normal(size=(5000, 3))
    grid = VoxelGrid(buffers=2)
    a = grid.run(pts, 0.2, buffer=0)
    b = grid.run(pts, 0.5, buffer=1)
    np.testing.assert_allclose(a.centroids(), voxel_downsample_counts(pts, 0.2)[0], atol=1e-12)
    np.testing.assert_allclose(b.centroids(), voxel_downsample_counts(pts, 0.5)[0], atol=1e-12)


def test_the_salt_moves_slots_not_results_and_scatters_crafted_points() -> None:
    from benchmarks.bench_collisions import crafted_points

    crafted = crafted_points(20_000, 0.1)  # voxels that share one probe chain under the plain hash
    plain, salted = VoxelGrid(salt=np.int64(0)), VoxelGrid(salt=new_salt())
    a, b = plain.run(crafted, 0.1), salted.run(crafted, 0.1)
    np.testing.assert_array_equal(a.centroids(), b.centroids())
    rand = np.random.default_rng(0).uniform(-50, 50, size=(20_000, 3))

    def best(grid: VoxelGrid, pts: np.ndarray) -> float:
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            grid.run(pts, 0.1)
            times.append(time.perf_counter() - t0)
        return min(times)

    unsalted, with_salt, random_t = best(plain, crafted), best(salted, crafted), best(salted, rand)
    # Loose bounds: the machine is shared
    assert unsalted > 10 * with_salt, (unsalted, with_salt)
    assert with_salt < 10 * random_t + 0.02, (with_salt, random_t)


def test_a_reused_grid_leaves_its_table_empty_whichever_way_it_clears_it() -> None:
    # A fine grid of a scattered cloud fills most of the table (cleared with one fill); a coarse one
    # uses a few slots (cleared slot by slot). A slot left behind would send the next pass's points
    # to a voxel of the last one.
    rng = np.random.default_rng(11)
    grid = VoxelGrid()
    for i, v in enumerate([0.01, 1.0, 0.01, 0.02, 2.0, 0.01]):
        pts = rng.uniform(-5, 5, size=(3000, 3)).astype(np.float32) + np.float32(i)
        got = grid.run(pts, v)
        ref = reference_grid(pts, v)
        assert len(got) == len(ref) and got.counts.sum() == len(pts)
        np.testing.assert_allclose(np.array(sorted(map(tuple, got.centroids()))),
                                   np.array(sorted(map(tuple, ref.values()))), rtol=0, atol=1e-9)


@pytest.mark.parametrize("id_bits", [16, 30, 31])
def test_a_slots_fingerprint_only_saves_reads_and_never_merges_voxels(id_bits: int) -> None:
    # A slot holds the voxel id and, above it, a fingerprint of the key's hash (7 bits by default).
    # With 1 bit (30) half of the slots passed on a probe share it, so the key is read and compared
    # for them; with none (31, a scan beyond 2^24 points) for every one; with 16 id bits the ids
    # reach the top one (34,000 voxels) and the fingerprint sits right above it. Every voxel is
    # met again later, out of order, so finding it goes through the probing. A fingerprint that
    # merged two voxels or missed one, or an id cut short by its bits, would change the result.
    rng = np.random.default_rng(3)
    first = rng.uniform(-20, 20, size=(34_000, 3))
    pts = np.vstack([first, first[rng.permutation(len(first))[:30_000]] + 0.001])
    times = rng.uniform(0.0, 0.1, size=len(pts))
    base = VoxelGrid().run(pts, 0.05, times=times)
    narrow = VoxelGrid()
    narrow.id_bits = id_bits
    got = narrow.run(pts, 0.05, times=times)
    assert len(base) > 1 << 15 and (base.counts == 2).sum() > 25_000
    np.testing.assert_array_equal(got.counts, base.counts)
    np.testing.assert_array_equal(got.sums, base.sums)
    assert base.tsums is not None and got.tsums is not None
    np.testing.assert_array_equal(got.tsums, base.tsums)
    # against the plain definition, voxel by voxel in the order of their first point
    ref = reference_grid(pts, 0.05)
    ref_counts = {}
    for p in pts:
        k = tuple(int(c) for c in np.floor(p / 0.05))
        ref_counts[k] = ref_counts.get(k, 0) + 1
    assert got.counts.tolist() == list(ref_counts.values())
    np.testing.assert_allclose(got.centroids(), np.array(list(ref.values())), rtol=0, atol=1e-9)


def test_an_id_override_too_narrow_for_the_scan_and_rows_of_the_wrong_shape_are_refused() -> None:
    grid = VoxelGrid()
    grid.id_bits = 10
    with pytest.raises(ValueError, match="id bits"):
        grid.run(np.zeros((2000, 3)), 0.1)
    for bad in (np.zeros(30), np.zeros((10, 2))):
        with pytest.raises(ValueError, match="shape"):
            VoxelGrid().run(bad, 0.1)


def test_rows_wider_than_three_columns_use_the_first_three() -> None:
    # The keys pass reads the coordinates as one flat array: a row with intensity (x, y, z, i)
    # must not shift them.
    rng = np.random.default_rng(4)
    xyzi = rng.uniform(-5, 5, size=(2000, 4)).astype(np.float32)
    got = VoxelGrid().run(xyzi, 0.2)
    want = VoxelGrid().run(np.ascontiguousarray(xyzi[:, :3]), 0.2)
    np.testing.assert_array_equal(got.sums, want.sums)
    np.testing.assert_array_equal(got.box, want.box)
