"""Point layouts of headerless ``.bin`` scans: declared (``--bin-fields x,y,z,i,t``) or known by
the file's name (``.pcd.bin`` is nuScenes), never guessed from the file size.

A layout is a comma-separated list of columns ``name[:type[:unit]]``: ``type`` one of f4 f8 i1 u1
i2 u2 i4 u4 (default f4, little-endian); ``unit`` of a time column s, ms, us or ns (default: s for
a float column, ns for an integer one, as PointCloud2 drivers write them). A time column is one
named ``t``, ``time``, ``timestamp`` or ``offset_time``; x, y and z must be there.

A file whose size is not a whole number of rows gets an error that names the layout tried and
the known layouts its size would fit, so the fix is one flag away.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from zoffload.sources.base import ScanSourceError

TIME_NAMES = ("t", "time", "timestamp", "offset_time")
_TYPES = {"f4", "f8", "i1", "u1", "i2", "u2", "i4", "u4"}
_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}


@dataclass(frozen=True)
class Column:
    name: str
    kind: str  # numpy type code without byte order: f4, u2, ...
    unit: float  # seconds per unit (time columns)


@dataclass(frozen=True)
class BinLayout:
    name: str  # "kitti", "nuscenes" or the declared text
    columns: tuple[Column, ...]

    @property
    def dtype(self) -> np.dtype:
        return np.dtype([(c.name, "<" + c.kind) for c in self.columns])

    @property
    def row_bytes(self) -> int:
        return int(self.dtype.itemsize)

    @property
    def time_column(self) -> Column | None:
        return next((c for c in self.columns if c.name in TIME_NAMES), None)

    def describe(self) -> str:
        text = ",".join(c.name if c.kind == "f4" else f"{c.name}:{c.kind}" for c in self.columns)
        label = f" ({self.name})" if self.name != text else ""
        return f"{text}{label}, {self.row_bytes} B/point"


def parse_layout(text: str, name: str | None = None) -> BinLayout:
    """``x,y,z,intensity,t`` (or with types and units, ``x,y,z,i,t:u4:ns``) as a layout;
    ``ValueError`` naming what is wrong."""
    columns = []
    for item in text.split(","):
        parts = item.strip().split(":")
        col, kind = parts[0], (parts[1] if len(parts) > 1 else "f4")
        if not col.isidentifier() or len(parts) > 3:
            raise ValueError(f"bin column {item!r}: use name[:type[:unit]] (e.g. t:u4:ns)")
        if kind not in _TYPES:
            raise ValueError(f"bin column {item!r}: type {kind!r} is not one of {', '.join(sorted(_TYPES))}")
        unit = parts[2] if len(parts) > 2 else ("s" if kind.startswith("f") else "ns")
        if unit not in _UNITS or (len(parts) > 2 and col not in TIME_NAMES):
            raise ValueError(f"bin column {item!r}: a unit ({', '.join(_UNITS)}) is for a time column "
                             f"({', '.join(TIME_NAMES)})")
        columns.append(Column(col, kind, _UNITS[unit]))
    names = [c.name for c in columns]
    if len(set(names)) != len(names) or not {"x", "y", "z"} <= set(names):
        raise ValueError(f"bin layout {text!r} needs x, y and z, each once")
    if sum(n in TIME_NAMES for n in names) > 1:
        raise ValueError(f"bin layout {text!r} has more than one time column")
    return BinLayout(name or text.replace(" ", ""), tuple(columns))


KITTI = parse_layout("x,y,z,intensity", "kitti")
NUSCENES = parse_layout("x,y,z,intensity,ring", "nuscenes")
# Known layouts a misfitting file is compared with, to name the ones its size fits
KNOWN = (KITTI, NUSCENES, parse_layout("x,y,z"), parse_layout("x,y,z,intensity,t"),
         parse_layout("x,y,z,intensity,ring,t"))


def layout_for(path: Path, declared: BinLayout | None) -> BinLayout:
    """The declared layout, else by the name: ``*.pcd.bin`` nuScenes, other ``.bin`` KITTI."""
    if declared is not None:
        return declared
    return NUSCENES if path.name.endswith(".pcd.bin") else KITTI


def check_size(path: Path, layout: BinLayout) -> int:
    """The file's point count; ``ScanSourceError`` for a missing or empty file, or a size that
    is not a whole number of the layout's rows (naming the known layouts that would fit)."""
    size = path.stat().st_size if path.exists() else -1
    if size < 0:
        raise ScanSourceError(f"{path}: no such scan file")
    if size == 0:
        raise ScanSourceError(f"{path}: empty scan file")
    if size % layout.row_bytes:
        fits = [k.describe() for k in KNOWN if size % k.row_bytes == 0 and k != layout]
        hint = (f"; its size fits {' or '.join(fits)}: declare the columns with --bin-fields"
                if fits else "; no known layout fits its size")
        raise ScanSourceError(
            f"{path}: {size} bytes is not a whole number of points of the layout tried, "
            f"{layout.describe()} (truncated file, or another layout{hint})")
    return size // layout.row_bytes


def read_bin(path: Path, layout: BinLayout) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float32 points and, with a time column, (N,) float64 seconds from the first."""
    check_size(path, layout)
    rows = np.fromfile(path, dtype=layout.dtype)
    points = np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(np.float32)
    tc = layout.time_column
    if tc is None:
        return points, None
    raw = rows[tc.name]
    if raw.dtype.kind in "iu":
        times = (raw.astype(np.int64) - int(raw.min())).astype(np.float64) * tc.unit
    else:
        times = raw.astype(np.float64) * tc.unit
    # Rows without finite coordinates or time go here, so points and times stay aligned
    keep = np.isfinite(points).all(axis=1) & np.isfinite(times)
    points, times = points[keep], times[keep]
    return points, times - times.min() if len(times) else times
