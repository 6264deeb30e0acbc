"""Scan payload coding that keeps points instead of dropping them.

Both quantised codings store each coordinate on a grid of ``step`` metres relative to the scan's
lower corner (unsigned 16 bit: 65,535 steps, 655 m at 1 cm); the error per coordinate is at most
``step / 2``, and the robot chooses the step relative to its voxel size (a tenth of it by
default), far below the map's resolution. A scan with per-point times carries them as a fourth
16-bit plane: the fraction of the scan's time span (1.5 µs steps over a 100 ms sweep).

``q16z`` (the first version): the planes one after the other as little-endian u16 (x..., y...,
z..., [t...]), Zstandard-compressed (level 3 on the robot).

``q16d`` (the robot's default): each plane as zigzag-coded differences between consecutive points
(points come in sweep order, so neighbours are close and most differences are a few steps), its
low bytes then its high bytes (the high bytes are then mostly zero and compress to almost
nothing), then Zstandard at a fast level (1 by default). On the KITTI-360 HDL-64 this is half of
q16z's bytes for a third of its compression time. The payload's first byte says whether the rest
is compressed (1) or the planes as they are (0): where the link has room to spare the robot skips
Zstandard and saves its CPU (the scale policy decides, ``policy/rate.py``).

``f32`` is the plain float32 payload (with times, if any, as a separate 16-bit array).

The robot fills either layout straight from its voxel grid's sums (``pack_q16``, compiled, no
intermediate array); ``encode_q16z`` / ``encode_q16d`` do the same from a point array and define
the formats. Decoding trusts nothing: the Zstandard frame must declare exactly the size the point
count implies before anything is decompressed, and decompression is capped at that size.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

CODINGS = ("f32", "q16z", "q16d")
MAX_STEPS = 65535
Q16Z_LEVEL = 3  # q16z's documented level: its bytes in the README were measured with it
RAW, ZSTD = 0, 1  # q16d's first byte
LAYOUT = {"q16z": 0, "q16d": 1}
_NO_COUNTS = np.empty(0, np.int32)
_NO_TIMES = np.empty(0, np.float64)


class CodingError(ValueError):
    """A payload that cannot be encoded (a scan larger than the grid) or decoded (corrupt data)."""


def quant_step(voxel: float, fraction: float = 0.1, floor: float = 0.005) -> float:
    """The quantisation step for a scan downsampled at ``voxel``: a tenth of it, never below 5 mm
    (a LiDAR's range noise is centimetres; raw scans get 5 mm)."""
    return max(floor, voxel * fraction) if voxel > 0 else 0.005


def times_to_u16(times: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-point times (any unit of seconds, any offset) as (u16 fractions of the span, span [s])."""
    t = np.asarray(times, np.float64)
    if len(t) == 0:
        return np.zeros(0, "<u2"), 0.0
    t0, span = float(t.min()), float(t.max() - t.min())
    if not np.isfinite(span) or span <= 0:
        return np.zeros(len(t), "<u2"), 0.0
    return np.rint((t - t0) * (MAX_STEPS / span)).astype("<u2"), span


def times_from_u16(q: np.ndarray, span: float) -> np.ndarray:
    """Seconds from the scan's first point, float64."""
    return np.asarray(q, np.float64) * (span / MAX_STEPS)


def _zstd() -> Any:
    import zstandard

    return zstandard


def payload_size(n: int, timed: bool) -> int:
    """Bytes of a q16 scan's planes before compression."""
    return n * (4 if timed else 3) * 2


@njit(cache=True, nogil=True, error_model="numpy")
def bounds(cloud: np.ndarray, times: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """[min x, y, z, max x, y, z, min t, max t] of points (n, 3) and times (n,) or empty (a
    numba loop: numpy's axis-0 min/max of an (n, 3) float32 array costs 20 times as much)."""
    box = np.array([np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf, np.inf, -np.inf])
    timed = times.shape[0] == cloud.shape[0]
    for i in range(cloud.shape[0]):
        for a in range(3):
            x = np.float64(cloud[i, a])
            box[a] = min(box[a], x)
            box[a + 3] = max(box[a + 3], x)
        if timed:
            box[6] = min(box[6], times[i])
            box[7] = max(box[7], times[i])
    return box


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _quantise(x: float, lo: float, scale: float) -> int:  # pragma: no cover - compiled
    """Steps from ``lo``, clamped to 16 bits: a centroid computed from its sum may round a hair
    outside the box it came from, and must not wrap around."""
    return int(min(max(np.rint((x - lo) * scale), 0.0), float(MAX_STEPS)))


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _zigzag(q: int, prev: int) -> int:  # pragma: no cover - compiled
    """The 16-bit difference q - prev, zigzag-coded (small magnitudes, either sign: small codes)."""
    d = (q - prev) & 0xFFFF
    return ((d << 1) ^ (-(d >> 15))) & 0xFFFF


@njit(cache=True, nogil=True, error_model="numpy")
def pack_q16(  # pragma: no cover - compiled
    cloud: np.ndarray, counts: np.ndarray, tsums: np.ndarray, box: np.ndarray, step: float, widen: bool,
    layout: int, out: np.ndarray,
) -> tuple[float, float, float, float, float, int]:
    """Quantise and lay out a scan into ``out`` (uint8, ``payload_size`` bytes).

    ``cloud``: points (n, 3), or per-voxel sums when ``counts`` (n,) is given (the centroid is
    sum / count, computed here: a voxel grid's output is read once, never copied). ``tsums``:
    per-point times, or per-voxel time sums with ``counts``; empty for none. ``box``: a box that
    holds every point and time, as ``bounds`` gives it (a grid pass gives its points' box, which
    holds their centroids); its lower corner is the origin. Returns (origin x, y, z, step, time
    span, status): status 1 when the extent does not fit 65,535 steps and not ``widen`` (nothing
    written)."""
    n = cloud.shape[0]
    by_count = counts.shape[0] == n
    timed = tsums.shape[0] == n and n > 0
    if n == 0:
        return 0.0, 0.0, 0.0, step, 0.0, 0
    lx, ly, lz = box[0], box[1], box[2]
    extent = max(box[3] - lx, max(box[4] - ly, box[5] - lz))
    if extent / step > MAX_STEPS:
        if not widen:
            return lx, ly, lz, step, 0.0, 1
        step = extent / MAX_STEPS * (1 + 1e-9)
    span = box[7] - box[6] if timed else 0.0
    if not (span > 0 and np.isfinite(span)):
        span = 0.0
    s = 1.0 / step
    ts = MAX_STEPS / span if span > 0 else 0.0
    n2 = 2 * n
    px = py = pz = pt = 0
    for i in range(n):
        c = 1.0 / counts[i] if by_count else 1.0
        qx = _quantise(cloud[i, 0] * c, lx, s)
        qy = _quantise(cloud[i, 1] * c, ly, s)
        qz = _quantise(cloud[i, 2] * c, lz, s)
        qt = _quantise(tsums[i] * c, box[6], ts) if span > 0 else 0
        if layout == 0:  # q16z: little-endian u16, plane after plane
            out[2 * i], out[2 * i + 1] = qx & 0xFF, qx >> 8
            out[n2 + 2 * i], out[n2 + 2 * i + 1] = qy & 0xFF, qy >> 8
            out[2 * n2 + 2 * i], out[2 * n2 + 2 * i + 1] = qz & 0xFF, qz >> 8
            if span > 0:
                out[3 * n2 + 2 * i], out[3 * n2 + 2 * i + 1] = qt & 0xFF, qt >> 8
        else:  # q16d: zigzag differences to the previous point, low bytes then high bytes
            zx, zy, zz = _zigzag(qx, px), _zigzag(qy, py), _zigzag(qz, pz)
            px, py, pz = qx, qy, qz
            out[i], out[n + i] = zx & 0xFF, zx >> 8
            out[n2 + i], out[n2 + n + i] = zy & 0xFF, zy >> 8
            out[2 * n2 + i], out[2 * n2 + n + i] = zz & 0xFF, zz >> 8
            if span > 0:
                zt = _zigzag(qt, pt)
                pt = qt
                out[3 * n2 + i], out[3 * n2 + n + i] = zt & 0xFF, zt >> 8
    return lx, ly, lz, step, span, 0


def _planes(points: np.ndarray, times: np.ndarray | None, step: float, widen: bool, layout: int
            ) -> tuple[np.ndarray, float, np.ndarray]:
    """(origin, step, planes as uint8) of ``points`` (n, 3) with an optional u16 ``times`` plane."""
    pts = np.ascontiguousarray(points, np.float64)
    if times is not None and len(times) != len(pts):
        raise CodingError(f"{len(times)} times for {len(pts)} points")
    out = np.empty(payload_size(len(pts), False), np.uint8)
    box = bounds(pts, _NO_TIMES)
    ox, oy, oz, step, _, status = pack_q16(pts, _NO_COUNTS, _NO_TIMES, box, step, widen, layout, out)
    if status:
        extent = float((box[3:6] - box[:3]).max())
        raise CodingError(f"scan extent {extent:.1f} m does not fit 16-bit steps of {step} m")
    if times is not None:  # the time plane is already quantised: lay it out the same way
        q = np.ascontiguousarray(times, "<u2")
        if layout == 0:
            tail = q.view(np.uint8)
        else:
            d = np.diff(q, prepend=np.uint16(0)).view(np.int16).astype(np.int32)
            z = ((d << 1) ^ (d >> 15)).astype("<u2")
            tail = np.concatenate([z.view(np.uint8)[0::2], z.view(np.uint8)[1::2]])
        out = np.concatenate([out, tail])
    return np.array([ox, oy, oz]), step, out


def encode_q16z(points: np.ndarray, step: float, level: int = Q16Z_LEVEL, widen: bool = False,
                times: np.ndarray | None = None) -> tuple[np.ndarray, float, bytes]:
    """(origin (3,) float64, step, compressed bytes) of ``points`` (n, 3) on a ``step`` grid, with
    the u16 ``times`` plane appended when given. With ``widen``, a scan too large for 65,535 steps
    gets the smallest step that fits instead of an error (a 160 m wide outdoor scan: 2.5 mm)."""
    if step <= 0:
        raise CodingError(f"quantisation step {step} must be positive")
    origin, step, planes = _planes(points, times, step, widen, LAYOUT["q16z"])
    return origin, step, compress(planes, level)


def encode_q16d(points: np.ndarray, step: float, level: int | None = 1, widen: bool = False,
                times: np.ndarray | None = None) -> tuple[np.ndarray, float, bytes]:
    """Like ``encode_q16z`` in the q16d layout; ``level`` None leaves the planes uncompressed."""
    if step <= 0:
        raise CodingError(f"quantisation step {step} must be positive")
    origin, step, planes = _planes(points, times, step, widen, LAYOUT["q16d"])
    if level is None:
        return origin, step, bytes([RAW]) + planes.tobytes()
    return origin, step, bytes([ZSTD]) + compress(planes, level)


def compress(data: np.ndarray | bytes | memoryview, level: int) -> bytes:
    """A Zstandard frame that declares its content size (the decoder checks it first)."""
    z = _zstd()
    return bytes(z.ZstdCompressor(level=level, write_content_size=True).compress(data))


def _decompress(data: bytes, want: int, coding: str) -> bytes:
    z = _zstd()
    try:
        declared = z.frame_content_size(data)
    except z.ZstdError as exc:
        raise CodingError(f"corrupt {coding} payload: {exc}") from exc
    if declared != want:
        raise CodingError(f"{coding} frame declares {declared} bytes ({want} expected)")
    try:
        raw = z.ZstdDecompressor().decompress(data, max_output_size=want)
    except z.ZstdError as exc:
        raise CodingError(f"corrupt {coding} payload: {exc}") from exc
    if len(raw) != want:
        raise CodingError(f"{coding} payload holds {len(raw)} bytes ({want} expected)")
    return bytes(raw)


def decode_q16z(blob: bytes | np.ndarray, n: int, origin: np.ndarray, step: float,
                with_times: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Float32 points (n, 3) and, ``with_times``, the u16 time plane (n,) from ``encode_q16z``'s
    output; ``CodingError`` if it does not fit. The frame's declared content size must be exactly
    what ``n`` implies, and decompression never produces more than that."""
    data = blob.tobytes() if isinstance(blob, np.ndarray) else bytes(blob)
    raw = _decompress(data, payload_size(n, with_times), "q16z")
    q = np.frombuffer(raw, "<u2")
    return _points(q[: 3 * n].reshape(3, n), origin, step), (q[3 * n:] if with_times else None)


def decode_q16d(blob: bytes | np.ndarray, n: int, origin: np.ndarray, step: float,
                with_times: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Float32 points (n, 3) and, ``with_times``, the u16 time plane (n,) from ``encode_q16d``'s
    output (or the robot's ``pack_q16``); ``CodingError`` if it does not fit."""
    data = blob.tobytes() if isinstance(blob, np.ndarray) else bytes(blob)
    want = payload_size(n, with_times)
    if not data or data[0] not in (RAW, ZSTD):
        raise CodingError(f"q16d payload starts with {data[:1].hex() or 'nothing'}, not 00 or 01")
    if data[0] == RAW:
        if len(data) - 1 != want:
            raise CodingError(f"uncompressed q16d payload of {len(data) - 1} bytes ({want} expected)")
        raw = data[1:]
    else:
        raw = _decompress(data[1:], want, "q16d")
    planes = 4 if with_times else 3
    b = np.frombuffer(raw, np.uint8).reshape(planes, 2, n)
    z = b[:, 0, :].astype(np.uint16) | (b[:, 1, :].astype(np.uint16) << 8)
    d = (z >> 1) ^ (np.uint16(0) - (z & 1))  # zigzag back to two's complement differences
    q = np.cumsum(d, axis=1, dtype=np.uint16)  # wraps modulo 2^16, as the differences were taken
    return _points(q[:3], origin, step), (q[3] if with_times else None)


def _points(q: np.ndarray, origin: np.ndarray, step: float) -> np.ndarray:
    """(n, 3) float32 points from the (3, n) planes, row-major: ``q.T`` is column-major, and
    KISS-ICP's binding converts a column-major array point by point (43.8 ms for an 81k-point
    KITTI-360 scan against 0.1 ms row-major, medians of 50; ``python -m benchmarks.bench_mapper``)."""
    return (q.T * step + np.asarray(origin, np.float64)).astype(np.float32, order="C")


DECODERS = {"q16z": decode_q16z, "q16d": decode_q16d}


def warmup() -> None:
    """Compile (or load from numba's cache) ``pack_q16`` for the robot's inputs: a grid's sums and
    counts, or raw float32/float64 points, with and without times, in both layouts."""
    compress(b"warm up", 1)  # imports zstandard
    out = np.empty(64, np.uint8)
    sums, counts, times = np.ones((2, 3)), np.ones(2, np.int32), np.zeros(2)
    for layout in LAYOUT.values():
        for tsums in (times, _NO_TIMES):
            pack_q16(sums, counts, tsums, bounds(sums, tsums), 0.01, True, layout, out)
            for dtype in (np.float32, np.float64):
                pts = np.ones((2, 3), dtype)
                pack_q16(pts, _NO_COUNTS, tsums, bounds(pts, tsums), 0.01, True, layout, out)
