"""What every scan source yields, and how a source is chosen from a config string."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

import numpy as np

Replay = Literal["once", "loop", "pingpong"]


class ScanSourceError(Exception):
    """A scan source that cannot be opened or read: missing folder, truncated or empty file."""


@dataclass(frozen=True)
class ScanFrame:
    """One LiDAR scan in the sensor frame."""

    index: int  # position in the source's sequence (repeats when a replay loops)
    points: np.ndarray  # (N, 3) float32, may contain non-finite rows straight from the sensor
    gt_pose: np.ndarray | None = None  # 4x4 sensor-to-world ground truth, if the source has one


class ScanSource(Protocol):
    """A finite sequence of scans; replay (pacing, looping) is the sensor's job, not the source's."""

    name: str
    rate_hz: float
    max_range: float  # what the mapper should use as its range limit for this sensor

    def __len__(self) -> int: ...

    def read(self, index: int) -> ScanFrame: ...


def replay_order(n: int, mode: str) -> Iterator[int]:
    """Indices of a replay: ``once``; ``loop`` (0..n-1, 0..n-1, ...); ``pingpong`` (forward then
    back, so a short real sequence plays as one continuous longer drive)."""
    if n <= 0:
        return
    if mode == "once":
        yield from range(n)
    elif mode == "loop":
        while True:
            yield from range(n)
    elif mode == "pingpong":
        yield from range(n)
        while n > 1:
            yield from range(n - 2, -1, -1)
            yield from range(1, n)
    else:
        raise ValueError(f"unknown replay mode {mode!r} (once, loop, pingpong)")


def open_scan_source(spec: str, *, sim_seed: int = 0) -> ScanSource:
    """``sim`` for the simulator, or a folder of ``.bin`` (KITTI), ``.pcd`` or ``.ply`` scans."""
    if spec == "sim" or spec.startswith("sim:"):
        from zoffload.sources.simulated import SimulatedSource

        return SimulatedSource(seed=sim_seed)
    path = Path(spec).expanduser()
    if not path.exists():
        raise ScanSourceError(f"scan folder {path} does not exist")
    if not path.is_dir():
        raise ScanSourceError(f"{path} is not a folder of scans")
    if any(path.glob("*.bin")):
        from zoffload.sources.kitti import KittiBinSource

        return KittiBinSource(path)
    if any(path.glob("*.pcd")) or any(path.glob("*.ply")):
        from zoffload.sources.pointcloud_files import PointCloudFolderSource

        return PointCloudFolderSource(path)
    raise ScanSourceError(f"no .bin, .pcd or .ply scans in {path}")
