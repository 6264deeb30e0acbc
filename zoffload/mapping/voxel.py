"""Voxel-grid centroid downsampling, as the scale-optimisation paper defines it.

A point ``p`` falls in voxel ``floor(p / v)`` (grid anchored at the origin, division in float64);
each non-empty voxel is replaced by the centroid of its points. Voxels come out in the order of
their first point, so the result is deterministic for a given scan.

The kernel (numba) works in two passes over the points: the voxel keys first (divisions, floors,
range checks over the flat array of coordinates: a loop the compiler vectorises), then one
open-addressing hash pass that sums each run of consecutive points sharing a voxel in registers
and touches the table once per run, prefetching the slot of the point ``PREFETCH_AHEAD`` on (the
table is the pass's one random access), and takes the valid points' bounds on the way. A slot
(int32, at least twice as many slots as points) holds a voxel id and 7 bits of the key's hash
above it: a probe past a slot of another voxel reads that voxel's key (a second random access)
only when the 7 bits agree, 1 in 128. The table is reset by clearing only the slots used, or the
whole table when most were, so a coarse grid does not pay for a table sized for the raw scan.
On the 50 KITTI-360 scans, caches cold, 5 cm: 1.41-1.49 ms a pass against 1.71 with keys from
the (n, 3) rows and bare ids (``benchmarks/bench_voxel.py``, 2026-12-08). Per-point times, when a
scan has them, are averaged like the coordinates (a centroid's time is the mean of its points'
times).

The table's hash is salted per process: ``(key ^ salt) * GOLDEN``. Points may come from the
network (ROS topics), and with a public hash a sender could choose points whose voxels share one
probe chain. ``benchmarks/bench_voxel.py`` compares the kernel with Open3D on a real HDL-64 scan.

``VoxelGrid`` keeps the scratch buffers and hands out ``Grid`` results (views of its buffers,
valid until its next pass on the same buffer): the robot reads centroids straight from them into
its payload (``protocol/coding.py``), with no intermediate array.
"""

from __future__ import annotations

import secrets
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

# Each voxel index is packed into 21 bits per axis, offset so negatives fit.
KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
MAX_INDEX = KEY_OFFSET - 1
GOLDEN = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)
_LIMIT = float(MAX_INDEX)


def new_salt() -> np.int64:
    """A random 64-bit salt for the voxel hash."""
    return np.int64(secrets.randbits(64) - (1 << 63))


SALT = new_salt()  # this process's


def _prefetch_intrinsic(typingctx: Any, arr: Any, idx: Any) -> Any:
    """``_prefetch(arr, idx)``: ask the CPU to bring ``arr[idx]`` into its caches (LLVM's
    ``llvm.prefetch``: a hint, never a fault, whatever the address)."""
    sig = types.void(arr, idx)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]), "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])  # read, keep, data
        return context.get_dummy_value()

    return sig, codegen


_prefetch: Any = intrinsic(_prefetch_intrinsic)

# How many points ahead the hash pass prefetches its table slot: a slot is a miss to the last
# level cache (the table is twice the scan's points), and the pass has about that many points'
# work to hide it behind (the 50 KITTI-360 scans, caches cold, 5 cm: 16 took ~20 % off the pass,
# 4 and 8 about half that).
PREFETCH_AHEAD = 16


_OFF = np.int32(-(1 << 31))  # a coordinate off the grid (or not finite) in the keys pass


@njit(cache=True, nogil=True, error_model="numpy")
def _grid_keys(points: np.ndarray, times: np.ndarray, v: float, cells: np.ndarray, keys: np.ndarray
               ) -> tuple[int, int]:  # pragma: no cover - compiled
    """Packed voxel key per point, -1 for a point that is non-finite, off the grid, or has a
    non-finite time. Returns (invalid points, index of the first).

    Two loops: each coordinate's cell over the flat (3n) array (divisions and floors, in float64;
    a loop the compiler vectorises, where one over (n, 3) rows would not: the rows' stride of
    three keeps it scalar, 3x slower on an HDL-64 scan), then the keys from the cells."""
    n = points.shape[0]
    flat = points.reshape(-1)
    for j in range(3 * n):
        f = np.floor(np.float64(flat[j]) / v)
        ok = (-_LIMIT < f) & (f < _LIMIT)  # NaN fails every comparison: non-finite is off too
        cells[j] = np.int32(f if ok else 0.0) if ok else _OFF
    timed = times.shape[0] == n
    bad = 0
    for i in range(n):
        a = cells[3 * i]
        b = cells[3 * i + 1]
        c = cells[3 * i + 2]
        ok = (a != _OFF) & (b != _OFF) & (c != _OFF)
        if timed:
            ok = ok & np.isfinite(times[i])
        key = (((np.int64(a) + KEY_OFFSET) << (2 * KEY_BITS)) | ((np.int64(b) + KEY_OFFSET) << KEY_BITS)
               | (np.int64(c) + KEY_OFFSET))
        keys[i] = key if ok else -1
        bad += 0 if ok else 1
    first = -1
    if bad:
        for i in range(n):
            if keys[i] < 0:
                first = i
                break
    return bad, first


@njit(cache=True, nogil=True, error_model="numpy")
def _grid_pass(  # pragma: no cover - compiled
    points: np.ndarray, times: np.ndarray, v: float, salt: np.int64, skip_invalid: bool, id_bits: int,
    cells: np.ndarray, keys: np.ndarray, slots: np.ndarray, keyof: np.ndarray, vslot: np.ndarray,
    sums: np.ndarray, tsums: np.ndarray, counts: np.ndarray, box: np.ndarray,
) -> tuple[int, int, int, float]:
    """Sums and counts per voxel, voxels in the order of their first point, and the valid
    points' bounds in ``box`` (times relative to the reference). Returns (voxels, invalid points,
    first invalid index, time reference). Without ``skip_invalid`` an invalid point stops the pass
    before anything is hashed (voxels = 0, its index returned). A slot holds a voxel id in its
    low ``id_bits`` bits and a fingerprint of the key's hash above them (``_id_bits``)."""
    n = points.shape[0]
    timed = times.shape[0] == n
    bad, first = _grid_keys(points, times, v, cells, keys)
    if bad and not skip_invalid:
        return 0, bad, first, 0.0
    t_ref = 0.0  # times are summed relative to the first valid point's, for precision
    if timed:
        for i in range(n):
            if keys[i] >= 0:
                t_ref = times[i]
                break
    cap = slots.shape[0]
    bits = 0
    while (1 << bits) < cap:
        bits += 1
    shift = np.uint64(64 - bits)
    fp_shift = np.uint64(64 - bits - (31 - id_bits))  # the hash's bits just below the slot's
    fp_mask = np.int64((1 << (31 - id_bits)) - 1)
    id_mask = np.int32((1 << id_bits) - 1)
    mask = cap - 1
    nv = 0
    last = np.int64(-1)
    j = -1
    sx = sy = sz = st = 0.0
    c = 0
    lx = ly = lz = tl = np.inf
    hx = hy = hz = th = -np.inf
    ahead = n - PREFETCH_AHEAD
    for i in range(n):
        key = keys[i]
        if key < 0:
            continue
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        lx, ly, lz = min(lx, x), min(ly, y), min(lz, z)
        hx, hy, hz = max(hx, x), max(hy, y), max(hz, z)
        t = 0.0
        if timed:
            t = times[i] - t_ref
            tl, th = min(tl, t), max(th, t)
        if key == last:  # LiDAR points come in sweeps: neighbours often share a voxel
            sx += x
            sy += y
            sz += z
            st += t
            c += 1
            continue
        if i < ahead:  # a later point's slot (-1, an invalid point: any slot, a harmless hint)
            _prefetch(slots, np.int64(np.uint64((keys[i + PREFETCH_AHEAD] ^ salt) * GOLDEN) >> shift))
        if j >= 0:  # the run ends: add it to its voxel
            sums[j, 0] += sx
            sums[j, 1] += sy
            sums[j, 2] += sz
            if timed:
                tsums[j] += st
            counts[j] += c
        h = np.uint64((key ^ salt) * GOLDEN)
        s = np.int64(h >> shift)
        fp = np.int32((np.int64(h >> fp_shift) & fp_mask) << id_bits)
        while True:
            e = slots[s]
            if e < 0:
                slots[s] = fp | np.int32(nv)
                keyof[nv] = key
                vslot[nv] = s
                j = nv
                sums[j, 0] = 0.0
                sums[j, 1] = 0.0
                sums[j, 2] = 0.0
                if timed:
                    tsums[j] = 0.0
                counts[j] = 0
                nv += 1
                break
            if (e & ~id_mask) == fp:  # the same fingerprint: read the voxel's key (else: not it)
                q = e & id_mask
                if keyof[q] == key:
                    j = q
                    break
            s = (s + 1) & mask
        last = key
        sx, sy, sz, st, c = x, y, z, t, 1
    if j >= 0:
        sums[j, 0] += sx
        sums[j, 1] += sy
        sums[j, 2] += sz
        if timed:
            tsums[j] += st
        counts[j] += c
    box[0], box[1], box[2], box[3], box[4], box[5], box[6], box[7] = lx, ly, lz, hx, hy, hz, tl, th
    # Leave the table empty for the next pass: slot by slot when few were used (a coarse grid of
    # a big scan), the whole table at once when many were (one linear fill beats scattered stores)
    if nv * 8 > cap:
        slots[:] = -1
    else:
        for q in range(nv):
            slots[vslot[q]] = -1
    return nv, bad, first, t_ref


def _id_bits(n: int) -> int:
    """Bits of a slot that hold the voxel id, for a scan of ``n`` points: 24 (ids to 16.7 M; 7 bits
    of fingerprint above them) or, for a larger scan, all 31 (no fingerprint)."""
    return 24 if n < (1 << 24) else 31


@njit(cache=True, nogil=True, error_model="numpy")
def _centroids(sums: np.ndarray, counts: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out = sums / counts`` per voxel: each count spread over its three coordinates first, so
    the divisions run over flat arrays (vectorised; over (m, 3) rows they stay scalar, 2.4x slower
    for the 78 k voxels of an HDL-64 scan at 5 cm). The same divisions, the same results. The
    spread counts are a scratch of 3m floats allocated per call: one held across calls measured
    the same (0.135 against 0.139 ms for 78 k voxels; the allocator reuses the freed block)."""
    m = out.shape[0]
    per = np.empty(3 * m)
    for q in range(m):
        c = np.float64(counts[q])
        per[3 * q] = c
        per[3 * q + 1] = c
        per[3 * q + 2] = c
    s = sums.reshape(-1)
    o = out.reshape(-1)
    for k in range(3 * m):
        o[k] = s[k] / per[k]


@dataclass(frozen=True)
class Grid:
    """One grid pass: per-voxel sums and counts (views of the grid's scratch buffers, valid until
    its next pass on the same buffer) and the invalid points that were skipped."""

    voxel: float
    sums: np.ndarray  # (m, 3) float64
    counts: np.ndarray  # (m,) int32
    tsums: np.ndarray | None  # (m,) float64, times relative to ``t_ref``; None without times
    t_ref: float
    n_invalid: int
    box: np.ndarray  # the valid points' bounds: min x, y, z, max x, y, z, min t, max t (t - t_ref)

    def __len__(self) -> int:
        return len(self.counts)

    def centroids(self, dtype: type = np.float64, out: np.ndarray | None = None) -> np.ndarray:
        """The voxels' centroids, (m, 3): a new array, or written into ``out`` (a C-contiguous
        (m, 3) array of ``dtype``: the robot's sizer passes a view of its pooled payload buffer)."""
        if out is None:
            out = np.empty((len(self.counts), 3), dtype)
        elif out.shape != (len(self.counts), 3) or out.dtype != dtype or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous ({len(self.counts)}, 3) {np.dtype(dtype)} array, "
                             f"got {out.shape} {out.dtype}")
        _centroids(self.sums, self.counts, out)
        return out

    def mean_times(self) -> np.ndarray | None:
        """Each voxel's mean point time relative to ``t_ref`` (float64), None without times."""
        return None if self.tsums is None else self.tsums / self.counts


_NO_TIMES = np.empty(0, np.float64)


class VoxelGrid:
    """Scratch buffers for grid passes, reused across scans: a pass allocates nothing large (and
    causes no page faults) once the largest scan has been seen. ``buffers`` results can be held
    at once (a scale policy trying two sizes keeps both). Not thread-safe: one per thread."""

    def __init__(self, buffers: int = 1, salt: np.int64 | None = None) -> None:
        self.salt = SALT if salt is None else np.int64(salt)
        self.id_bits = 0  # bits of a slot for the voxel id; 0: ``_id_bits`` of each scan (tests set it)
        self._n = -1
        self._buffers = buffers
        self._shared: tuple[np.ndarray, ...] = ()
        self._results: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def _ensure(self, n: int) -> None:
        if n <= self._n:
            return
        n = max(n, 64)
        cap = 1
        while cap < 2 * n:
            cap <<= 1
        self._shared = (np.empty(3 * n, np.int32), np.empty(n, np.int64), np.full(cap, -1, np.int32),
                        np.empty(n, np.int64), np.empty(n, np.int64))
        self._results = [(np.empty((n, 3)), np.empty(n), np.empty(n, np.int32)) for _ in range(self._buffers)]
        self._n = n

    def run(self, points: np.ndarray, voxel_size: float, times: np.ndarray | None = None,
            skip_invalid: bool = False, buffer: int = 0) -> Grid:
        """One pass over ``points`` ((n, 3) float32 or float64; as ``check_points`` takes them: of
        wider rows the first three columns, copied, other types as float64). Invalid points
        (non-finite, off the grid, a non-finite time) are skipped and counted with
        ``skip_invalid``, otherwise the first one raises ``ValueError``."""
        points = check_points(points, voxel_size)  # the keys pass reads them as one flat array
        n = len(points)
        if self.id_bits and n >= 1 << self.id_bits:
            raise ValueError(f"{n} points need more than {self.id_bits} id bits")
        t = _NO_TIMES if times is None else np.ascontiguousarray(times, np.float64)
        if times is not None and len(t) != n:
            raise ValueError(f"{len(t)} times for {n} points")
        self._ensure(n)
        cells, keys, slots, keyof, vslot = self._shared
        sums, tsums, counts = self._results[buffer]
        box = np.empty(8)
        nv, bad, first, t_ref = _grid_pass(points, t, float(voxel_size), self.salt, skip_invalid,
                                           self.id_bits or _id_bits(n), cells, keys, slots, keyof, vslot,
                                           sums, tsums, counts, box)
        if bad and not skip_invalid:
            raise _bad_point(points, first, voxel_size, times)
        return Grid(float(voxel_size), sums[:nv], counts[:nv], None if times is None else tsums[:nv],
                    float(t_ref), int(bad), box)


def check_points(points: np.ndarray, voxel_size: float) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {pts.shape}")
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    if not (voxel_size > 0 and np.isfinite(voxel_size)):
        raise ValueError(f"voxel size must be a positive number, got {voxel_size!r}")
    return np.ascontiguousarray(pts[:, :3])


def _bad_point(pts: np.ndarray, index: int, voxel_size: float, times: np.ndarray | None = None) -> ValueError:
    p = pts[index]
    if not np.isfinite(p).all():
        return ValueError(f"points contain NaN or infinite coordinates (point {index}); drop them first")
    if times is not None and not np.isfinite(times[index]):
        return ValueError(f"point {index} has a non-finite time")
    return ValueError(
        f"point {index} at {np.abs(p).max():.1f} m is too far for voxel size {voxel_size} "
        f"(at most {MAX_INDEX} voxels from the origin per axis)"
    )


_local = threading.local()


def thread_grid() -> VoxelGrid:
    """This thread's grid (its scratch buffers persist across calls)."""
    grid = getattr(_local, "grid", None)
    if grid is None:
        grid = _local.grid = VoxelGrid()
    return grid


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
    grid = thread_grid().run(pts, voxel_size)
    return grid.centroids(), grid.counts.astype(np.int64)


def warmup() -> None:
    """Compile (or load from numba's cache) the kernels for float32 and float64 input, with and
    without times."""
    grid = VoxelGrid()
    for dtype in (np.float32, np.float64):
        pts = np.zeros((4, 3), dtype)
        grid.run(pts, 0.1).centroids()
        grid.run(pts, 0.1, times=np.zeros(4), skip_invalid=True).centroids()
