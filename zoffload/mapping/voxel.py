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
KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
MAX_INDEX = KEY_OFFSET - 1
GOLDEN = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)


_LIMIT = float(MAX_INDEX)


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
            ((np.int64(fx) + KEY_OFFSET) << (2 * KEY_BITS))
            | ((np.int64(fy) + KEY_OFFSET) << KEY_BITS)
            | (np.int64(fz) + KEY_OFFSET)
        )
        if key != last_key:
            s = np.int64(np.uint64(key * GOLDEN) >> shift)
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


def check_points(points: np.ndarray, voxel_size: float) -> np.ndarray:
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
        f"(at most {MAX_INDEX} voxels from the origin per axis)"
    )


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centroid of every non-empty voxel ``floor(p / voxel_size)``, as a float64 (M, 3) array.

    Only the first three columns of ``points`` are used. Raises ``ValueError`` on non-finite
    points, a non-positive voxel size, or coordinates too far from the origin for the grid.
    """
    return voxel_downsample_counts(points, voxel_size)[0]


def voxel_downsample_counts(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Like ``voxel_downsample`` but also returns how many points each voxel holds."""
    pts = check_points(points, voxel_size)
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
