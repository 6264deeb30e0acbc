"""``.ply`` point clouds with all their vertex properties: ascii, binary little and big endian.

The vertex element's scalar properties are read by name (a list property in it, or a list
element before it, cannot be laid out without walking every row: such files are refused and the
caller falls back to open3d, which reads their x, y, z).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from zoffload.sources.base import ScanSourceError

MAX_POINTS = 4_000_000
_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


class PlyLayoutError(ScanSourceError):
    """A PLY file valid as such whose vertex layout this reader does not handle (lists)."""


def read_ply(path: Path) -> dict[str, np.ndarray]:
    """Every scalar vertex property of a ``.ply`` file by name; ``ScanSourceError`` when the
    file is not a PLY file or its data is shorter than its header says."""
    raw = path.read_bytes()
    if not raw.startswith(b"ply"):
        raise ScanSourceError(f"{path}: not a PLY file")
    end = raw.find(b"end_header")
    if end < 0:
        raise ScanSourceError(f"{path}: PLY header without end_header")
    body_at = raw.find(b"\n", end) + 1
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []  # (name, count, [(prop, type|list)])
    for line in raw[:end].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                prop = ("list", words[-1]) if words[1] == "list" else (_TYPES[words[1]], words[2])
                elements[-1][2].append((prop[1], prop[0]))
        except (IndexError, ValueError, KeyError) as exc:
            raise ScanSourceError(f"{path}: malformed PLY header line {line[:80]!r}") from exc
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ScanSourceError(f"{path}: PLY format {fmt!r} not understood")
    offset, skip_rows = body_at, 0
    for name, count, props in elements:
        if any(kind == "list" for _, kind in props):
            raise PlyLayoutError(f"{path}: PLY element {name!r} has list properties")
        if not 0 <= count <= MAX_POINTS:
            raise ScanSourceError(f"{path}: {count} {name} rows (at most {MAX_POINTS})")
        order = ">" if fmt == "binary_big_endian" else "<"
        dtype = np.dtype([(p, order + kind) for p, kind in props])
        if name != "vertex":
            offset += count * dtype.itemsize
            skip_rows += count
            continue
        if fmt == "ascii":
            return _ascii(path, raw[body_at:], skip_rows, count, dtype)
        if len(raw) < offset + count * dtype.itemsize:
            raise ScanSourceError(f"{path}: {len(raw) - offset} data bytes for {count} vertices of "
                                  f"{dtype.itemsize} bytes (truncated?)")
        rows = np.frombuffer(raw, dtype, count=count, offset=offset)
        return {p: rows[p].astype(rows[p].dtype.newbyteorder("=")) for p in dtype.names or ()}
    raise ScanSourceError(f"{path}: PLY file without a vertex element")


def _ascii(path: Path, body: bytes, skip_rows: int, count: int, dtype: np.dtype) -> dict[str, np.ndarray]:
    lines = body.split(b"\n", skip_rows + count)
    if len(lines) < skip_rows + count:
        raise ScanSourceError(f"{path}: fewer than {count} vertex lines (truncated?)")
    cols = len(dtype.names or ())
    values = np.array(b" ".join(lines[skip_rows:skip_rows + count]).split(), np.float64)
    if values.size != count * cols:
        raise ScanSourceError(f"{path}: {values.size} values for {count} vertices of {cols} properties")
    table = values.reshape(count, cols)
    return {p: table[:, i].astype(dtype[i].newbyteorder("=")) for i, p in enumerate(dtype.names or ())}
