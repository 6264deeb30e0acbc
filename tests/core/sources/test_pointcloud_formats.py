"""PCD and PLY scans read by their declared fields, with per-point times where they have them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from zoffload.sources import ScanSourceError, open_scan_source
from zoffload.sources.pcd import _lzf_decompress, read_pcd
from zoffload.sources.ply import read_ply

PTS = np.random.default_rng(0).uniform(-20, 20, (40, 3)).astype(np.float32)
T_NS = (np.arange(40) * 1_000_000).astype(np.uint32)  # Ouster-style t: 0..39 ms


def pcd_header(n: int, data: str, fields: str = "x y z t", size: str = "4 4 4 4",
               type_: str = "F F F U") -> bytes:
    return (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\n"
            f"TYPE {type_}\nCOUNT {' '.join('1' * len(fields.split()))}\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()


def records() -> np.ndarray:
    rec = np.zeros(40, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["t"] = PTS[:, 0], PTS[:, 1], PTS[:, 2], T_NS
    return rec


def lzf_literals(data: bytes) -> bytes:
    """A valid LZF stream of literal runs only (what liblzf emits for incompressible data)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out += bytes([len(chunk) - 1]) + chunk
    return bytes(out)


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_with_time_field(tmp_path: Path, mode: str) -> None:
    rec = records()
    if mode == "ascii":
        body = "\n".join(f"{x!r} {y!r} {z!r} {t}" for x, y, z, t in
                         zip(PTS[:, 0].tolist(), PTS[:, 1].tolist(), PTS[:, 2].tolist(), T_NS.tolist(),
                             strict=True)).encode()
    elif mode == "binary":
        body = rec.tobytes()
    else:  # fields one after another, LZF-compressed, behind (compressed, uncompressed) sizes
        planar = b"".join(np.ascontiguousarray(rec[name]).tobytes() for name in ("x", "y", "z", "t"))
        packed = lzf_literals(planar)
        body = np.array([len(packed), len(planar)], "<u4").tobytes() + packed
    (tmp_path / "scan.pcd").write_bytes(pcd_header(40, mode) + body)
    f = open_scan_source(str(tmp_path)).read(0)
    np.testing.assert_allclose(f.points, PTS, atol=1e-6)
    assert f.times is not None
    np.testing.assert_allclose(f.times, T_NS * 1e-9)


def test_pcd_written_by_open3d_compressed(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    pts = np.random.default_rng(1).random((500, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(tmp_path / "a.pcd"), cloud, compressed=True)
    assert b"binary_compressed" in (tmp_path / "a.pcd").read_bytes()[:300]
    fields = read_pcd(tmp_path / "a.pcd")
    np.testing.assert_allclose(np.stack([fields["x"], fields["y"], fields["z"]], 1), pts, atol=1e-6)


def test_lzf_back_references() -> None:
    # "abcabcabc": literals "abc", then a back reference of 6 bytes to offset 3 (overlapping)
    stream = bytes([2]) + b"abc" + bytes([(4 << 5) | 0, 2])
    out = np.zeros(9, np.uint8)
    assert _lzf_decompress(np.frombuffer(stream, np.uint8), out) == 9 and out.tobytes() == b"abcabcabc"
    assert _lzf_decompress(np.frombuffer(bytes([(4 << 5), 200]), np.uint8), out) == -1  # before the start


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_with_time_property(tmp_path: Path, fmt: str) -> None:
    order = ">" if fmt.endswith("big_endian") else "<"
    head = (f"ply\nformat {fmt} 1.0\ncomment a LiDAR scan\nelement vertex 40\nproperty float x\n"
            "property float y\nproperty float z\nproperty double time\nend_header\n").encode()
    times = 1.7e9 + np.arange(40) * 1e-3  # absolute seconds
    if fmt == "ascii":
        body = "\n".join(f"{x!r} {y!r} {z!r} {t!r}" for x, y, z, t in
                         zip(*PTS.T.tolist(), times.tolist(), strict=True)).encode() + b"\n"
    else:
        rec = np.zeros(40, [("x", order + "f4"), ("y", order + "f4"), ("z", order + "f4"),
                            ("time", order + "f8")])
        rec["x"], rec["y"], rec["z"], rec["time"] = PTS[:, 0], PTS[:, 1], PTS[:, 2], times
        body = rec.tobytes()
    (tmp_path / "scan.ply").write_bytes(head + body)
    f = open_scan_source(str(tmp_path)).read(0)
    np.testing.assert_allclose(f.points, PTS, atol=1e-6)
    assert f.times is not None
    np.testing.assert_allclose(f.times, np.arange(40) * 1e-3, atol=1e-6)
    assert read_ply(tmp_path / "scan.ply")["time"].dtype == np.float64


def test_truncated_and_malformed_files(tmp_path: Path) -> None:
    (tmp_path / "a.pcd").write_bytes(pcd_header(40, "binary") + records().tobytes()[:-10])
    with pytest.raises(ScanSourceError, match="truncated"):
        open_scan_source(str(tmp_path)).read(0)
    sizes = b"\x10\x00\x00\x00\x00\x01\x00\x00"  # 16 bytes unpacking to 256: not 40 points' 640
    (tmp_path / "a.pcd").write_bytes(pcd_header(40, "binary_compressed") + sizes)
    with pytest.raises(ScanSourceError, match="need"):
        read_pcd(tmp_path / "a.pcd")
    (tmp_path / "a.pcd").write_bytes(pcd_header(40, "binary", type_="F F F Q") + records().tobytes())
    with pytest.raises(ScanSourceError, match="not understood"):
        read_pcd(tmp_path / "a.pcd")
    (tmp_path / "a.pcd").write_bytes(pcd_header(10**9, "binary"))
    with pytest.raises(ScanSourceError, match="at most"):
        read_pcd(tmp_path / "a.pcd")
    (tmp_path / "a.pcd").write_bytes(pcd_header(40, "binary", fields="a b c t") + records().tobytes())
    with pytest.raises(ScanSourceError, match="no x/y/z"):
        open_scan_source(str(tmp_path)).read(0)
    (tmp_path / "b.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n"
                                     b"property float x\n")
    with pytest.raises(ScanSourceError, match="end_header"):
        read_ply(tmp_path / "b.ply")
