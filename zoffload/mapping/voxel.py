"""Voxel-grid centroid downsampling, as the scale-optimisation paper defines it.

A point ``p`` falls in voxel ``floor(p / v)`` (grid anchored at the origin, division in float64);
each non-empty voxel is replaced by the centroid of its points. Voxels come out in the order of
their first point, so the result is deterministic for a given scan.

The kernel is a single pass with an open-addressing hash table, compiled by numba, working in
per-thread scratch buffers; benchmarks/bench_voxel.py compares it with Open3D and a ``np.unique``
grid on a real HDL-64 scan.
"""

from __future__ import annotations

import threading

import numpy as np
from numba import njit

# Each voxel index is packed into 21 bits per axis, offset so negatives fit.
_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MAX_INDEX = _OFFSET - 1
_GOLDEN = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)


_LIMIT = float(_MAX_INDEX)


@njit(cache=True, nogil=True)
def _voxel_centroids(  # pragma: no cover - compiled
    points: np.ndarray, v: float, slot_key: np.ndarray, slot_voxel: np.ndarray, acc: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """One pass: hash each point's voxel and accumulate its sums; consecutive LiDAR points often
    share a voxel, hence the last-key cache. Returns (centroids, counts, -1), or the index of the
    first point that is non-finite or off the grid as the third value."""
    n = points.shape[0]
    cap = 1
    bits = 0
    while cap < 2 * n:
        cap <<= 1
        bits += 1
    shift = np.uint64(64 - bits)
    slot_key[:cap] = -1
    nv = 0
    last_key = np.int64(-1)
    j = 0
    for i in range(n):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        fx = np.floor(x / v)
        fy = np.floor(y / v)
        fz = np.floor(z / v)
        # NaN fails every comparison: one test rejects non-finite and off-grid points
        if not (-_LIMIT < fx < _LIMIT and -_LIMIT < fy < _LIMIT and -_LIMIT < fz < _LIMIT):
            return np.empty((0, 3)), np.empty(0, np.int64), i
        key = (
            ((np.int64(fx) + _OFFSET) << (2 * _BITS))
            | ((np.int64(fy) + _OFFSET) << _BITS)
            | (np.int64(fz) + _OFFSET)
        )
        if key != last_key:
            s = np.int64(np.uint64(key * _GOLDEN) >> shift)
            while True:
                k = slot_key[s]
                if k == key:
                    j = slot_voxel[s]
                    break
                if k == -1:
                    slot_key[s] = key
                    slot_voxel[s] = nv
                    j = nv
                    acc[j, 0] = 0.0
                    acc[j, 1] = 0.0
                    acc[j, 2] = 0.0
                    acc[j, 3] = 0.0
                    nv += 1
                    break
                s = (s + 1) & (cap - 1)
            last_key = key
        acc[j, 0] += x
        acc[j, 1] += y
        acc[j, 2] += z
        acc[j, 3] += 1.0
    out = np.empty((nv, 3), np.float64)
    counts = np.empty(nv, np.int64)
    for q in range(nv):
        c = acc[q, 3]
        out[q, 0] = acc[q, 0] / c
        out[q, 1] = acc[q, 1] / c
        out[q, 2] = acc[q, 2] / c
        counts[q] = np.int64(c)
    return out, counts, -1


_scratch = threading.local()


def _buffers(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-thread scratch arrays, reused across scans: no allocation (and no page faults) in the
    per-scan hot path once the largest scan has been seen."""
    cap = 1
    while cap < 2 * n:
        cap <<= 1
    bufs = getattr(_scratch, "bufs", None)
    if bufs is None or len(bufs[0]) < cap or len(bufs[2]) < n:
        bufs = (np.empty(cap, np.int64), np.empty(cap, np.int32), np.empty((max(n, 1), 4)))
        _scratch.bufs = bufs
    return bufs


def _check(points: np.ndarray, voxel_size: float) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {pts.shape}")
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    if not (voxel_size > 0 and np.isfinite(voxel_size)):
        raise ValueError(f"voxel size must be a positive number, got {voxel_size!r}")
    return np.ascontiguousarray(pts[:, :3])


def _bad_point(pts: np.ndarray, index: int, voxel_size: float) -> ValueError:
    p = pts[index]
    if not np.isfinite(p).all():
        return ValueError(f"points contain NaN or infinite coordinates (point {index}); drop them first")
    return ValueError(
        f"point {index} at {np.abs(p).max():.1f} m is too far for voxel size {voxel_size} "
        f"(at most {_MAX_INDEX} voxels from the origin per axis)"
    )


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centroid of every non-empty voxel ``floor(p / voxel_size)``, as a float64 (M, 3) array.

    Only the first three columns of ``points`` are used. Raises ``ValueError`` on non-finite
    points, a non-positive voxel size, or coordinates too far from the origin for the grid.
    """
    return voxel_downsample_counts(points, voxel_size)[0]


def voxel_downsample_counts(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Like ``voxel_downsample`` but also returns how many points each voxel holds."""
    pts = _check(points, voxel_size)
    if len(pts) == 0:
        return np.empty((0, 3)), np.empty(0, np.int64)
    out, counts, bad = _voxel_centroids(pts, float(voxel_size), *_buffers(len(pts)))
    if bad >= 0:
        raise _bad_point(pts, bad, voxel_size)
    return out, counts


def warmup() -> None:
    """Compile (or load from numba's cache) the kernel for float32 and float64 input."""
    for dtype in (np.float32, np.float64):
        voxel_downsample(np.zeros((4, 3), dtype), 0.1)
        VoxelSet(0.1, capacity=4).add(np.zeros((4, 3), dtype))


@njit(cache=True, nogil=True)
def _set_insert(  # pragma: no cover - compiled
    points: np.ndarray, pose: np.ndarray, v: float, slot_key: np.ndarray, slot_index: np.ndarray,
    store: np.ndarray, count: int,
) -> int:
    cap = slot_key.shape[0]
    bits = 0
    while (1 << bits) < cap:
        bits += 1
    shift = np.uint64(64 - bits)
    for i in range(points.shape[0]):
        # Transform here rather than with a numpy matmul: no temporary, and no multithreaded
        # BLAS call whose spinning threads would steal the cores from KISS-ICP's TBB workers.
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        x = pose[0, 0] * px + pose[0, 1] * py + pose[0, 2] * pz + pose[0, 3]
        y = pose[1, 0] * px + pose[1, 1] * py + pose[1, 2] * pz + pose[1, 3]
        z = pose[2, 0] * px + pose[2, 1] * py + pose[2, 2] * pz + pose[2, 3]
        kx = np.int64(np.floor(x / v)) + _OFFSET
        ky = np.int64(np.floor(y / v)) + _OFFSET
        kz = np.int64(np.floor(z / v)) + _OFFSET
        key = (kx << (2 * _BITS)) | (ky << _BITS) | kz
        s = np.int64(np.uint64(key * _GOLDEN) >> shift)
        while True:
            k = slot_key[s]
            if k == key:
                break
            if k == -1:
                slot_key[s] = key
                slot_index[s] = count
                store[count, 0] = x
                store[count, 1] = y
                store[count, 2] = z
                count += 1
                break
            s = (s + 1) & (cap - 1)
    return count


_IDENTITY = np.eye(4)


class VoxelSet:
    """A growing set of occupied voxels keeping the first point seen in each: a global map whose
    size is known at every insert without copying it."""

    def __init__(self, voxel_size: float, capacity: int = 1 << 16) -> None:
        if not voxel_size > 0:
            raise ValueError(f"voxel size must be positive, got {voxel_size!r}")
        self.voxel_size = float(voxel_size)
        cap = 1
        while cap < 2 * capacity:
            cap <<= 1
        self._slot_key = np.full(cap, -1, np.int64)
        self._slot_index = np.empty(cap, np.int64)
        self._store = np.empty((capacity, 3), np.float64)
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def _grow(self, needed: int) -> None:
        if needed > len(self._store):
            new = np.empty((max(needed, 2 * len(self._store)), 3), np.float64)
            new[: self._count] = self._store[: self._count]
            self._store = new
        if 2 * needed > len(self._slot_key):
            # Rehash the stored points into a table twice as large as needed
            cap = len(self._slot_key)
            while cap < 4 * needed:
                cap <<= 1
            self._slot_key = np.full(cap, -1, np.int64)
            self._slot_index = np.empty(cap, np.int64)
            kept = self._store[: self._count].copy()
            self._count = _set_insert(
                kept, _IDENTITY, self.voxel_size, self._slot_key, self._slot_index, self._store, 0
            )

    def add(self, points: np.ndarray, pose: np.ndarray | None = None) -> int:
        """Insert points, transformed by the 4x4 ``pose`` first if given (sensor -> world);
        returns how many new voxels they occupied."""
        pts = _check(points, self.voxel_size)
        tf = _IDENTITY if pose is None else np.ascontiguousarray(pose, dtype=np.float64)
        if tf.shape != (4, 4) or not np.isfinite(tf).all():
            raise ValueError("pose must be a finite 4x4 matrix")
        if len(pts) and not np.isfinite(pts).all():
            raise ValueError("points contain NaN or infinite coordinates")
        # A rotation can move a coordinate's largest absolute value up by sqrt(3)
        reach = 1.7321 * float(np.abs(pts).max()) + float(np.abs(tf[:3, 3]).max()) if len(pts) else 0.0
        if reach / self.voxel_size >= _MAX_INDEX:
            raise ValueError(f"points too far from the origin for voxel size {self.voxel_size}")
        before = self._count
        self._grow(self._count + len(pts))
        self._count = _set_insert(
            pts, tf, self.voxel_size, self._slot_key, self._slot_index, self._store, self._count
        )
        return self._count - before

    def points(self) -> np.ndarray:
        return self._store[: self._count].copy()
