"""``.bin`` scans of any column layout, declared or known by name, never guessed from the size."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from zoffload.sources import ScanSourceError, open_scan_source
from zoffload.sources.layouts import KITTI, NUSCENES, parse_layout, read_bin

PTS = np.random.default_rng(0).uniform(-20, 20, (50, 3)).astype(np.float32)


def write(path: Path, columns: list[np.ndarray], dtypes: list[str]) -> None:
    rec = np.zeros(len(columns[0]), [(f"c{i}", d) for i, d in enumerate(dtypes)])
    for i, col in enumerate(columns):
        rec[f"c{i}"] = col
    rec.tofile(path)


def test_five_column_scans_with_time_read_when_declared(tmp_path: Path) -> None:
    t = np.linspace(0.0, 0.1, 50)
    for i in range(2):
        write(tmp_path / f"{i:06d}.bin", [*PTS.T, np.ones(50), t + 100.0], ["<f4"] * 5)
    with pytest.raises(ScanSourceError) as err:  # the KITTI default does not fit 20-byte rows
        open_scan_source(str(tmp_path))
    msg = str(err.value)
    assert "x,y,z,intensity (kitti), 16 B/point" in msg and "20 B/point" in msg and "--bin-fields" in msg
    src = open_scan_source(str(tmp_path), bin_fields="x,y,z,i,t")
    f = src.read(1)
    np.testing.assert_array_equal(f.points, PTS)
    assert f.times is not None
    np.testing.assert_allclose(f.times, t, atol=1e-5)  # float32 column, offset removed


def test_typed_time_column_in_nanoseconds(tmp_path: Path) -> None:
    ns = (np.arange(50) * 2_000_000).astype(np.uint32)
    write(tmp_path / "a.bin", [*PTS.T, ns], ["<f4", "<f4", "<f4", "<u4"])
    f = open_scan_source(str(tmp_path), bin_fields="x,y,z,t:u4").read(0)  # integer time: ns
    assert f.times is not None
    np.testing.assert_allclose(f.times, np.arange(50) * 2e-3)
    f = open_scan_source(str(tmp_path), bin_fields="x,y,z,t:u4:us").read(0)
    assert f.times is not None
    np.testing.assert_allclose(f.times, np.arange(50) * 2.0)


def test_nuscenes_pcd_bin_by_name(tmp_path: Path) -> None:
    write(tmp_path / "n015-LIDAR_TOP.pcd.bin", [*PTS.T, np.ones(50), np.arange(50) % 32], ["<f4"] * 5)
    src = open_scan_source(str(tmp_path))
    assert src.name.startswith("nuscenes:")
    f = src.read(0)
    np.testing.assert_array_equal(f.points, PTS)
    assert f.times is None


def test_size_that_fits_nothing_known(tmp_path: Path) -> None:
    (tmp_path / "a.bin").write_bytes(b"\x00" * 30)
    with pytest.raises(ScanSourceError, match="no known layout fits"):
        open_scan_source(str(tmp_path))
    with pytest.raises(ScanSourceError, match="x,y,z,intensity,t, 20 B/point"):
        open_scan_source(str(tmp_path), bin_fields="x,y,z,intensity,t")


def test_non_finite_rows_leave_with_their_times(tmp_path: Path) -> None:
    pts = PTS.copy()
    pts[3, 1] = np.nan
    t = np.arange(50, dtype=np.float32) * 1e-3
    t[7] = np.inf
    write(tmp_path / "a.bin", [*pts.T, t], ["<f4"] * 4)
    points, times = read_bin(tmp_path / "a.bin", parse_layout("x,y,z,t"))
    assert times is not None and len(points) == len(times) == 48 and np.isfinite(points).all()


@pytest.mark.parametrize("bad", ["x,y", "x,y,z,x", "x,y,z,t:f16", "x,y,z,i:f4:ns", "x,y,z,t,time",
                                 "x,y,z,t:u4:hours", "x,y,z,a b"])
def test_bad_layouts(tmp_path: Path, bad: str) -> None:
    with pytest.raises(ValueError):
        parse_layout(bad)
    (tmp_path / "a.bin").write_bytes(b"\x00" * 16)
    with pytest.raises(ScanSourceError):
        open_scan_source(str(tmp_path), bin_fields=bad)


def test_known_layouts() -> None:
    assert (KITTI.row_bytes, NUSCENES.row_bytes) == (16, 20)
    assert parse_layout("x,y,z,t:f8").row_bytes == 20 and parse_layout("x,y,z,t:f8").time_column is not None
