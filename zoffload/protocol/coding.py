"""Scan payload coding that keeps points instead of dropping them.

``q16z``: each coordinate quantised to a grid of ``step`` metres relative to the scan's lower
corner (unsigned 16 bit: 65,535 steps, 655 m at 1 cm), the three columns stored one after the other
(x..., y..., z...: neighbouring points have near values, which the byte-level compressor finds),
then Zstandard-compressed. The error per coordinate is at most ``step / 2``; the robot chooses the
step relative to its voxel size (a tenth of it by default), far below the map's resolution.
A scan with per-point times carries them as a fourth 16-bit plane: the fraction of the scan's time
span (1.5 µs steps over a 100 ms sweep).

``f32`` is the plain float32 payload (with times, if any, as a separate 16-bit array).

Decoding trusts nothing: the Zstandard frame must declare exactly the size the point count implies
before anything is decompressed, and decompression is capped at that size.
"""

from __future__ import annotations

import numpy as np

CODINGS = ("f32", "q16z")
MAX_STEPS = 65535


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


def encode_q16z(points: np.ndarray, step: float, level: int = 3, widen: bool = False,
                times: np.ndarray | None = None) -> tuple[np.ndarray, float, bytes]:
    """(origin (3,) float64, step, compressed bytes) of ``points`` (n, 3) on a ``step`` grid, with
    the u16 ``times`` plane appended when given. With ``widen``, a scan too large for 65,535 steps
    gets the smallest step that fits instead of an error (a 160 m wide outdoor scan: 2.5 mm)."""
    import zstandard

    if step <= 0:
        raise CodingError(f"quantisation step {step} must be positive")
    pts = np.asarray(points, np.float64)
    if len(pts) == 0:
        return np.zeros(3), step, zstandard.ZstdCompressor(level=level, write_content_size=True).compress(b"")
    origin = pts.min(axis=0)
    extent = float((pts.max(axis=0) - origin).max())
    if extent / step > MAX_STEPS:
        if not widen:
            raise CodingError(f"scan extent {extent:.1f} m does not fit 16-bit steps of {step} m")
        step = extent / MAX_STEPS * (1 + 1e-9)
    q = np.rint((pts - origin) / step)
    planar = np.ascontiguousarray(q.astype("<u2").T)  # x..., y..., z...
    payload = planar.tobytes()
    if times is not None:
        if len(times) != len(pts):
            raise CodingError(f"{len(times)} times for {len(pts)} points")
        payload += np.ascontiguousarray(times, "<u2").tobytes()
    return origin, step, zstandard.ZstdCompressor(level=level, write_content_size=True).compress(payload)


def decode_q16z(blob: bytes | np.ndarray, n: int, origin: np.ndarray, step: float,
                with_times: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Float32 points (n, 3) and, ``with_times``, the u16 time plane (n,) from ``encode_q16z``'s
    output; ``CodingError`` if it does not fit. The frame's declared content size must be exactly
    what ``n`` implies, and decompression never produces more than that."""
    import zstandard

    planes = 4 if with_times else 3
    want = n * planes * 2
    data = blob.tobytes() if isinstance(blob, np.ndarray) else bytes(blob)
    try:
        declared = zstandard.frame_content_size(data)
    except zstandard.ZstdError as exc:
        raise CodingError(f"corrupt q16z payload: {exc}") from exc
    if declared != want:
        raise CodingError(f"q16z frame declares {declared} bytes for {n} points ({want} expected)")
    try:
        raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=want)
    except zstandard.ZstdError as exc:
        raise CodingError(f"corrupt q16z payload: {exc}") from exc
    if len(raw) != want:
        raise CodingError(f"q16z payload holds {len(raw)} bytes for {n} points ({want} expected)")
    q = np.frombuffer(raw, "<u2")
    xyz = q[: 3 * n].reshape(3, n).T
    pts = (xyz * step + np.asarray(origin, np.float64)).astype(np.float32)
    return pts, (q[3 * n:] if with_times else None)
