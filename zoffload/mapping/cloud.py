"""Point-cloud hygiene shared by every consumer of raw sensor scans."""

from __future__ import annotations

import numpy as np


def drop_non_finite(points: np.ndarray) -> tuple[np.ndarray, int]:
    """Points without NaN/inf rows, and how many rows were dropped. A finite sum proves every
    value finite (NaN and inf propagate), so the common clean scan costs one reduction."""
    if np.isfinite(np.add.reduce(points, axis=None, dtype=np.float64)):
        return points, 0
    finite = np.isfinite(points).all(axis=1)
    return points[finite], int(len(points) - finite.sum())
