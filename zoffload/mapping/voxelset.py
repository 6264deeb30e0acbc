"""The global map's voxel set: one point per occupied voxel (the first seen), kept in a growing
open-addressing hash table, so a map's size is known at every insert without copying it.

Two defences, because the points come from the network:

* **Salted hash.** A voxel's packed key is XORed with a random 64-bit salt drawn for each set
  before the Fibonacci multiply. Without it the slot of a key is public, so a sender can choose
  points whose voxels all land in one slot (keys ``k = t * GOLDEN^-1``: ``k * GOLDEN = t``) and
  turn every insert into a walk along one long probe chain: 60k such points took 840 ms against
  3.8 ms for random points. With the salt the same points scatter like random ones
  (``benchmarks/bench_collisions.py`` measures both).
* **Budget.** ``max_points`` caps the set: once it holds that many voxels, points in new voxels
  are counted in ``overflow`` and not stored (the map keeps what it has and stops growing; points
  in voxels it already has cost nothing). Memory then stops at 24 bytes per point stored plus a
  table of 16-byte slots, the power of two at least twice the budget: 2 M points take 115 MB.
"""

from __future__ import annotations

import secrets

import numpy as np
from numba import njit

from zoffload.mapping.voxel import GOLDEN, KEY_BITS, KEY_OFFSET, MAX_INDEX, check_points


@njit(cache=True, nogil=True)
def _set_insert(  # pragma: no cover - compiled
    points: np.ndarray, pose: np.ndarray, v: float, slot_key: np.ndarray, slot_index: np.ndarray,
    store: np.ndarray, count: int, limit: int, salt: np.int64,
) -> tuple[int, int]:
    """Insert; returns (count, points in new voxels refused because ``count`` reached ``limit``)."""
    cap = slot_key.shape[0]
    bits = 0
    while (1 << bits) < cap:
        bits += 1
    shift = np.uint64(64 - bits)
    overflow = 0
    for i in range(points.shape[0]):
        # Transform here rather than with a numpy matmul: no temporary, and no multithreaded
        # BLAS call whose spinning threads would steal the cores from KISS-ICP's TBB workers.
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        x = pose[0, 0] * px + pose[0, 1] * py + pose[0, 2] * pz + pose[0, 3]
        y = pose[1, 0] * px + pose[1, 1] * py + pose[1, 2] * pz + pose[1, 3]
        z = pose[2, 0] * px + pose[2, 1] * py + pose[2, 2] * pz + pose[2, 3]
        kx = np.int64(np.floor(x / v)) + KEY_OFFSET
        ky = np.int64(np.floor(y / v)) + KEY_OFFSET
        kz = np.int64(np.floor(z / v)) + KEY_OFFSET
        key = (kx << (2 * KEY_BITS)) | (ky << KEY_BITS) | kz
        s = np.int64(np.uint64((key ^ salt) * GOLDEN) >> shift)
        while True:
            k = slot_key[s]
            if k == key:
                break
            if k == -1:
                if count >= limit:
                    overflow += 1
                    break
                slot_key[s] = key
                slot_index[s] = count
                store[count, 0] = x
                store[count, 1] = y
                store[count, 2] = z
                count += 1
                break
            s = (s + 1) & (cap - 1)
    return count, overflow


_IDENTITY = np.eye(4)
UNLIMITED = np.iinfo(np.int64).max


def _random_salt() -> np.int64:
    return np.int64(secrets.randbits(64) - (1 << 63))


class VoxelSet:
    """A growing set of occupied voxels keeping the first point seen in each: a global map whose
    size is known at every insert without copying it. ``max_points``: the budget (None: none)."""

    def __init__(self, voxel_size: float, capacity: int = 1 << 16, max_points: int | None = None) -> None:
        if not voxel_size > 0:
            raise ValueError(f"voxel size must be positive, got {voxel_size!r}")
        if max_points is not None and max_points < 1:
            raise ValueError(f"max_points must be at least 1, got {max_points}")
        self.voxel_size = float(voxel_size)
        self.max_points = max_points
        self.overflow = 0  # points in new voxels refused since the budget was reached
        self._salt = _random_salt()
        capacity = min(capacity, max_points) if max_points else capacity
        cap = 1
        while cap < 2 * capacity:
            cap <<= 1
        self._slot_key = np.full(cap, -1, np.int64)
        self._slot_index = np.empty(cap, np.int64)
        self._store = np.empty((capacity, 3), np.float64)
        self._count = 0

    def __len__(self) -> int:
        return self._count

    @property
    def full(self) -> bool:
        return self.max_points is not None and self._count >= self.max_points

    def set_budget(self, max_points: int | None) -> None:
        """Change the budget; a set already larger keeps its points and stops growing."""
        if max_points is not None and max_points < 1:
            raise ValueError(f"max_points must be at least 1, got {max_points}")
        self.max_points = max_points

    def _grow(self, needed: int) -> None:
        if self.max_points is not None:
            needed = min(needed, max(self.max_points, self._count))
        if needed > len(self._store):
            new = np.empty((max(needed, min(2 * len(self._store), self.max_points or UNLIMITED)), 3),
                           np.float64)
            new[: self._count] = self._store[: self._count]
            self._store = new
        if 2 * needed > len(self._slot_key):
            # Rehash the stored points into a table twice as large as needed (at most twice the
            # budget: the load factor stays at most 1/2)
            target = 4 * needed if self.max_points is None else min(4 * needed, 2 * self.max_points)
            cap = len(self._slot_key)
            while cap < target:
                cap <<= 1
            self._slot_key = np.full(cap, -1, np.int64)
            self._slot_index = np.empty(cap, np.int64)
            kept = self._store[: self._count].copy()
            self._count, _ = _set_insert(kept, _IDENTITY, self.voxel_size, self._slot_key,
                                         self._slot_index, self._store, 0, UNLIMITED, self._salt)

    def add(self, points: np.ndarray, pose: np.ndarray | None = None) -> int:
        """Insert points, transformed by the 4x4 ``pose`` first if given (sensor -> world);
        returns how many new voxels they occupied (points beyond the budget: ``overflow``)."""
        pts = check_points(points, self.voxel_size)
        tf = _IDENTITY if pose is None else np.ascontiguousarray(pose, dtype=np.float64)
        if tf.shape != (4, 4) or not np.isfinite(tf).all():
            raise ValueError("pose must be a finite 4x4 matrix")
        if len(pts) and not np.isfinite(pts).all():
            raise ValueError("points contain NaN or infinite coordinates")
        # A rotation can move a coordinate's largest absolute value up by sqrt(3)
        reach = 1.7321 * float(np.abs(pts).max()) + float(np.abs(tf[:3, 3]).max()) if len(pts) else 0.0
        if reach / self.voxel_size >= MAX_INDEX:
            raise ValueError(f"points too far from the origin for voxel size {self.voxel_size}")
        before = self._count
        self._grow(self._count + len(pts))
        limit = len(self._store) if self.max_points is None else min(self.max_points, len(self._store))
        self._count, overflow = _set_insert(
            pts, tf, self.voxel_size, self._slot_key, self._slot_index, self._store, self._count,
            limit, self._salt,
        )
        self.overflow += overflow
        return self._count - before

    def points(self) -> np.ndarray:
        return self._store[: self._count].copy()


def warmup() -> None:
    """Compile (or load from numba's cache) the insert kernel for float32 and float64 input."""
    for dtype in (np.float32, np.float64):
        VoxelSet(0.1, capacity=4).add(np.zeros((4, 3), dtype))
