"""Scan payload coding that keeps points instead of dropping them.

``q16z``: each coordinate quantised to a grid of ``step`` metres relative to the scan's lower
corner (unsigned 16 bit: 65,535 steps, 655 m at 1 cm), the three columns stored one after the other
(x..., y..., z...: neighbouring points have near values, which the byte-level compressor finds),
then Zstandard-compressed. The error per coordinate is at most ``step / 2``; the robot chooses the
step relative to its voxel size (a tenth of it by default), far below the map's resolution.
``f32`` is the plain float32 payload.
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


def encode_q16z(points: np.ndarray, step: float, level: int = 3,
                widen: bool = False) -> tuple[np.ndarray, float, bytes]:
    """(origin (3,) float64, step, compressed bytes) of ``points`` (n, 3) on a ``step`` grid. With
    ``widen``, a scan too large for 65,535 steps gets the smallest step that fits instead of an
    error (a 160 m wide outdoor scan: 2.5 mm)."""
    import zstandard

    if step <= 0:
        raise CodingError(f"quantisation step {step} must be positive")
    pts = np.asarray(points, np.float64)
    if len(pts) == 0:
        return np.zeros(3), step, zstandard.ZstdCompressor(level=level).compress(b"")
    origin = pts.min(axis=0)
    extent = float((pts.max(axis=0) - origin).max())
    if extent / step > MAX_STEPS:
        if not widen:
            raise CodingError(f"scan extent {extent:.1f} m does not fit 16-bit steps of {step} m")
        step = extent / MAX_STEPS * (1 + 1e-9)
    q = np.rint((pts - origin) / step)
    planar = np.ascontiguousarray(q.astype("<u2").T)  # x..., y..., z...
    return origin, step, zstandard.ZstdCompressor(level=level).compress(planar.tobytes())


def decode_q16z(blob: bytes, n: int, origin: np.ndarray, step: float) -> np.ndarray:
    """Float32 points (n, 3) from ``encode_q16z``'s output; ``CodingError`` if it does not fit."""
    import zstandard

    try:
        raw = zstandard.ZstdDecompressor().decompress(blob, max_output_size=n * 6 + 1)
    except zstandard.ZstdError as exc:
        raise CodingError(f"corrupt q16z payload: {exc}") from exc
    if len(raw) != n * 6:
        raise CodingError(f"q16z payload holds {len(raw)} bytes for {n} points ({n * 6} expected)")
    q = np.frombuffer(raw, "<u2").reshape(3, n).T
    return (q * step + np.asarray(origin, np.float64)).astype(np.float32)
