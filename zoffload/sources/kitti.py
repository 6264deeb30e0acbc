"""KITTI / KITTI-360 Velodyne folders: float32 rows ``x, y, z, reflectance`` per ``.bin`` file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from zoffload.sources.base import ScanFrame, ScanSourceError

_ROW = 16  # bytes per point: 4 x float32


def read_kitti_bin(path: Path) -> np.ndarray:
    """The (N, 3) float32 points of one scan; ``ScanSourceError`` if empty or truncated."""
    size = path.stat().st_size if path.exists() else -1
    if size < 0:
        raise ScanSourceError(f"{path}: no such scan file")
    if size == 0:
        raise ScanSourceError(f"{path}: empty scan file")
    if size % _ROW:
        raise ScanSourceError(
            f"{path}: {size} bytes is not a whole number of 16-byte points (truncated file?)"
        )
    data = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    return np.ascontiguousarray(data[:, :3])


class KittiBinSource:
    """A folder of KITTI ``.bin`` scans, played in file-name order at ``rate_hz``."""

    def __init__(self, folder: Path, rate_hz: float = 10.0, max_range: float = 100.0) -> None:
        self.files = sorted(Path(folder).glob("*.bin"))
        if not self.files:
            raise ScanSourceError(f"no .bin scans in {folder}")
        # Check every file's size up front: a truncated file is an error at start, not mid-run.
        for f in self.files:
            size = f.stat().st_size
            if size == 0 or size % _ROW:
                raise ScanSourceError(
                    f"{f}: {size} bytes is not a whole number of 16-byte points (empty or truncated)"
                )
        self.name = f"kitti:{folder}"
        self.rate_hz = rate_hz
        self.max_range = max_range

    def __len__(self) -> int:
        return len(self.files)

    def read(self, index: int) -> ScanFrame:
        return ScanFrame(index=index, points=read_kitti_bin(self.files[index]))
