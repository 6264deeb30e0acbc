"""Folders of headerless ``.bin`` scans: KITTI / KITTI-360 (float32 ``x, y, z, reflectance``),
nuScenes ``.pcd.bin`` (``x, y, z, intensity, ring``), or any declared column layout, with a
per-point time column where the layout has one (sources/layouts.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from zoffload.sources.base import ScanFrame, ScanSourceError
from zoffload.sources.layouts import KITTI, BinLayout, check_size, layout_for, read_bin


def read_kitti_bin(path: Path, layout: BinLayout = KITTI) -> np.ndarray:
    """The (N, 3) float32 points of one scan; ``ScanSourceError`` if empty or truncated."""
    return read_bin(path, layout)[0]


class KittiBinSource:
    """A folder of ``.bin`` scans, played in file-name order at ``rate_hz``. ``layout`` None: each
    file's by its name (``.pcd.bin`` nuScenes, else KITTI)."""

    def __init__(self, folder: Path, rate_hz: float = 10.0, max_range: float = 100.0,
                 layout: BinLayout | None = None) -> None:
        self.files = sorted(Path(folder).glob("*.bin"))
        if not self.files:
            raise ScanSourceError(f"no .bin scans in {folder}")
        self.layouts = [layout_for(f, layout) for f in self.files]
        # Check every file's size up front: a truncated file is an error at start, not mid-run.
        for f, lay in zip(self.files, self.layouts, strict=True):
            check_size(f, lay)
        kinds = sorted({lay.name for lay in self.layouts})
        self.name = f"{'+'.join(kinds)}:{folder}"  # kitti:FOLDER as before for KITTI
        self.rate_hz = rate_hz
        self.max_range = max_range

    def __len__(self) -> int:
        return len(self.files)

    def read(self, index: int) -> ScanFrame:
        points, times = read_bin(self.files[index], self.layouts[index])
        return ScanFrame(index=index, points=points, times=times)
