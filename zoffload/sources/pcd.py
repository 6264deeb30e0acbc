"""PCL's ``.pcd`` point clouds with all their fields: ascii, binary and binary_compressed.

The header names each field with its size, type (F float, I signed, U unsigned) and count; the
data follows as text rows, packed binary rows, or (binary_compressed) one LZF block holding the
fields one after another. Sizes are checked against the header before anything is allocated.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from numba import njit

from zoffload.sources.base import ScanSourceError

MAX_POINTS = 4_000_000  # as wire.Limits.max_points
_KINDS = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
          ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


@njit(cache=True, nogil=True)
def _lzf_decompress(src: np.ndarray, dst: np.ndarray) -> int:  # pragma: no cover - compiled
    """LZF (liblzf's format) into ``dst``; the bytes written, or -1 for corrupt input."""
    ip, op, n_in, n_out = 0, 0, src.shape[0], dst.shape[0]
    while ip < n_in:
        ctrl = int(src[ip])
        ip += 1
        if ctrl < 32:  # a literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n_in or op + length > n_out:
                return -1
            dst[op:op + length] = src[ip:ip + length]
            ip += length
            op += length
        else:  # a back reference
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    return -1
                length += int(src[ip])
                ip += 1
            if ip >= n_in:
                return -1
            ref = op - ((ctrl & 0x1F) << 8) - int(src[ip]) - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > n_out:
                return -1
            for k in range(length):  # byte by byte: the reference may overlap the output
                dst[op + k] = dst[ref + k]
            op += length
    return op


def _header(path: Path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    fields: dict[str, list[str]] = {}
    pos, end_of_header = 0, min(len(raw), 64 * 1024)  # a header is a few hundred bytes
    while pos < end_of_header:
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        fields[key.upper()] = values
        if key.upper() == "DATA":
            return fields, pos
    raise ScanSourceError(f"{path}: not a PCD file (no DATA line in its header)")


def read_pcd(path: Path) -> dict[str, np.ndarray]:
    """Every single-valued field of a ``.pcd`` file by name (1-D arrays of its own type);
    ``ScanSourceError`` for anything the header and the data do not agree on."""
    raw = path.read_bytes()
    head, start = _header(path, raw)
    try:
        names = head["FIELDS"]
        sizes = [int(v) for v in head["SIZE"]]
        types = head["TYPE"]
        counts = [int(v) for v in head.get("COUNT", ["1"] * len(names))]
        n = int(head.get("POINTS", [0])[0]) or int(head["WIDTH"][0]) * int(head.get("HEIGHT", ["1"])[0])
        mode = head["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as exc:
        raise ScanSourceError(f"{path}: malformed PCD header ({exc})") from exc
    if not len(names) == len(sizes) == len(types) == len(counts) or min(counts, default=1) < 1:
        raise ScanSourceError(f"{path}: PCD header FIELDS/SIZE/TYPE/COUNT do not match")
    if not 0 <= n <= MAX_POINTS:
        raise ScanSourceError(f"{path}: {n} points (at most {MAX_POINTS})")
    try:
        kinds = [_KINDS[(t.upper(), s)] for t, s in zip(types, sizes, strict=True)]
    except KeyError as exc:
        raise ScanSourceError(f"{path}: PCD field type/size {exc} not understood") from exc
    # Fields with COUNT > 1 (e.g. PCL's 33-value descriptors) are kept as padding
    dtype = np.dtype([(f"{name}#{i}", "<" + kind, (count,)) if count > 1 else (f"{name}#{i}", "<" + kind)
                      for i, (name, kind, count) in enumerate(zip(names, kinds, counts, strict=True))])
    body = raw[start:]
    if mode == "ascii":
        rows = _ascii_rows(path, body, n, dtype)
    elif mode == "binary":
        if len(body) < n * dtype.itemsize:
            raise ScanSourceError(f"{path}: {len(body)} data bytes for {n} points of {dtype.itemsize} "
                                  "bytes (truncated?)")
        rows = np.frombuffer(body, dtype, count=n)
    elif mode == "binary_compressed":
        rows = _compressed_rows(path, body, n, dtype)
    else:
        raise ScanSourceError(f"{path}: PCD DATA {mode!r} (ascii, binary, binary_compressed)")
    return {name.split("#")[0]: np.asarray(rows[name]) for name in dtype.names or ()
            if rows[name].ndim == 1}


def _ascii_rows(path: Path, body: bytes, n: int, dtype: np.dtype) -> np.ndarray:
    names = dtype.names or ()
    widths = [int(np.prod(dtype[name].shape)) or 1 for name in names]
    cols = sum(widths)
    values = np.array(body.split(), dtype=np.float64) if body.strip() else np.zeros(0)
    if values.size < n * cols:
        raise ScanSourceError(f"{path}: {values.size} values for {n} points of {cols} (truncated?)")
    table = values[: n * cols].reshape(n, cols)
    rows = np.zeros(n, dtype)
    c = 0
    for name, width in zip(names, widths, strict=True):
        rows[name] = table[:, c] if width == 1 else table[:, c:c + width]
        c += width
    return rows


def _compressed_rows(path: Path, body: bytes, n: int, dtype: np.dtype) -> np.ndarray:
    if len(body) < 8:
        raise ScanSourceError(f"{path}: binary_compressed PCD without its sizes")
    packed, unpacked = struct.unpack_from("<II", body)
    want = n * dtype.itemsize
    if unpacked != want or packed > len(body) - 8:
        raise ScanSourceError(f"{path}: compressed block of {packed} -> {unpacked} bytes where "
                              f"{n} points need {want} (truncated or corrupt)")
    out = np.empty(want, np.uint8)
    if want and _lzf_decompress(np.frombuffer(body, np.uint8, packed, 8), out) != want:
        raise ScanSourceError(f"{path}: corrupt LZF data")
    # The block holds each field's values for all points, one field after the other
    rows = np.zeros(n, dtype)
    pos = 0
    for i, name in enumerate(dtype.names or ()):
        size = dtype[i].itemsize * n
        rows[name] = np.frombuffer(out[pos:pos + size].tobytes(), dtype[i].base,
                                   count=n * (int(np.prod(dtype[i].shape)) or 1)).reshape(rows[name].shape)
        pos += size
    return rows
