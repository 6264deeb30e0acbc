"""Scan payload coding: quantised, compressed (or not), decoded on the edge within half a step;
the robot's fused layout from a voxel grid decodes to the grid's centroids."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.protocol import wire
from zoffload.protocol.coding import (
    LAYOUT,
    RAW,
    ZSTD,
    CodingError,
    compress,
    decode_q16d,
    decode_q16z,
    encode_q16d,
    encode_q16z,
    pack_q16,
    payload_size,
    quant_step,
    times_to_u16,
)
from zoffload.sources.simulated import SimulatedSource


def _scan() -> np.ndarray:
    pts = SimulatedSource(seed=0).read(3).points
    return pts[np.isfinite(pts).all(axis=1)].astype(np.float32)


def test_round_trip_error_is_within_half_a_step_and_smaller_than_floats() -> None:
    pts = _scan()
    step = quant_step(0.05)
    assert step == pytest.approx(0.005)
    origin, used, blob = encode_q16z(pts, step)
    assert used == step
    back = decode_q16z(blob, len(pts), origin, step)[0]
    assert back.dtype == np.float32 and back.shape == pts.shape
    assert np.abs(back - pts).max() <= step / 2 + 1e-5
    assert len(blob) < 0.4 * pts.nbytes  # measured ~0.29 on simulator scans at 5 mm
    assert quant_step(0.0) == 0.005 and quant_step(0.01) == 0.005 and quant_step(0.2) == pytest.approx(0.02)


def test_a_scan_too_large_for_the_grid_or_corrupt_data_is_an_error() -> None:
    far = np.array([[0, 0, 0], [700, 0, 0]], np.float32)
    with pytest.raises(CodingError, match="does not fit"):
        encode_q16z(far, 0.01)
    origin, step, blob = encode_q16z(far, 0.01, widen=True)  # the robot widens the step instead
    assert step == pytest.approx(700 / 65535, rel=1e-6)
    np.testing.assert_allclose(decode_q16z(blob, 2, origin, step)[0], far, atol=step / 2 + 1e-4)
    origin, _, blob = encode_q16z(_scan(), 0.005)
    with pytest.raises(CodingError, match="corrupt|expected"):
        decode_q16z(blob[:-5], len(_scan()), origin, 0.005)
    with pytest.raises(CodingError, match="expected"):
        decode_q16z(blob, len(_scan()) + 1, origin, 0.005)


def test_coded_scan_travels_on_the_wire_and_decodes() -> None:
    pts = _scan()
    origin, _, blob = encode_q16z(pts, 0.005)
    msg = wire.Scan(robot="r", seq=1, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=0.07,
                    max_range=100.0, n_raw=len(pts), points=np.zeros((0, 3), np.float32), coding="q16z",
                    quant_step=0.005, n_points=len(pts), origin=origin, packed=np.frombuffer(blob, np.uint8))
    data = wire.encode(msg)
    assert len(data) < 0.4 * pts.nbytes
    back = wire.decode(data, expect=wire.Scan)
    assert isinstance(back, wire.Scan)
    np.testing.assert_allclose(back.cloud(), pts, atol=0.0026)
    # a plain scan has no packed fields on the wire and decodes as before
    plain = wire.Scan(robot="r", seq=1, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=0.07,
                      max_range=100.0, n_raw=len(pts), points=pts)
    assert b"packed" not in wire.encode(plain)
    np.testing.assert_array_equal(wire.decode(wire.encode(plain), expect=wire.Scan).cloud(), pts)
    broken = wire.Scan(robot="r", seq=1, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=0.07,
                       max_range=100.0, n_raw=1, points=np.zeros((0, 3), np.float32), coding="q16z",
                       quant_step=0.005, n_points=10, origin=origin, packed=np.frombuffer(b"xx", np.uint8))
    with pytest.raises(wire.WireError):
        broken.cloud()


def test_q16d_round_trip_compressed_or_not_with_times_and_smaller_than_q16z() -> None:
    pts = _scan()
    q, span = times_to_u16(np.linspace(5.0, 5.1, len(pts)))
    for level in (None, 1, -3):
        origin, step, blob = encode_q16d(pts, 0.005, level=level, times=q)
        back, tq = decode_q16d(blob, len(pts), origin, step, with_times=True)
        assert np.abs(back - pts).max() <= step / 2 + 1e-5
        np.testing.assert_array_equal(tq, q)
        assert blob[0] == (RAW if level is None else ZSTD)
    assert len(encode_q16d(pts, 0.005)[2]) < 0.85 * len(encode_q16z(pts, 0.005)[2])


def test_q16d_refuses_what_does_not_fit_before_allocating() -> None:
    pts = _scan()
    origin, step, blob = encode_q16d(pts, 0.005)
    for bad, match in ((b"", "starts with"), (b"\x07" + blob[1:], "starts with"),
                       (blob[:-3], "corrupt|expected"), (b"\x00" + b"\x00" * 10, "uncompressed")):
        with pytest.raises(CodingError, match=match):
            decode_q16d(bad, len(pts), origin, step)
    with pytest.raises(CodingError, match="declares"):
        decode_q16d(blob, len(pts) + 1, origin, step)
    bomb = bytes([ZSTD]) + compress(b"\x00" * 10_000_000, 1)  # declares far more than 10 points need
    with pytest.raises(CodingError, match="declares"):
        decode_q16d(bomb, 10, np.zeros(3), 0.01)


def test_pack_from_a_voxel_grid_decodes_to_its_centroids_on_the_wire() -> None:
    from zoffload.mapping.voxel import VoxelGrid

    pts = _scan()
    times = np.linspace(0.0, 0.1, len(pts))
    grid = VoxelGrid().run(pts, 0.05, times=times)
    cent, mean_t = grid.centroids(), grid.mean_times()
    assert mean_t is not None and grid.tsums is not None
    for coding in ("q16z", "q16d"):
        n = len(grid)
        out = np.empty(1 + payload_size(n, True), np.uint8)
        ox, oy, oz, step, span, status = pack_q16(grid.sums, grid.counts, grid.tsums, grid.box, 0.005, True,
                                                  LAYOUT[coding], out[1:])
        assert status == 0 and step == 0.005 and span == pytest.approx(np.ptp(times))
        packed = compress(out[1:], 1) if coding == "q16z" else bytes([RAW]) + out[1:].tobytes()
        msg = wire.Scan(robot="r", seq=1, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=0.07,
                        max_range=40.0, n_raw=len(pts), points=np.zeros((0, 3), np.float32), coding=coding,
                        quant_step=step, n_points=n, origin=np.array([ox, oy, oz]),
                        packed=np.frombuffer(packed, np.uint8), time_span=span)
        back, t = wire.decode(wire.encode(msg), expect=wire.Scan).cloud_and_times()
        assert np.abs(back - cent).max() <= step / 2 + 1e-5
        assert t is not None
        np.testing.assert_allclose(t, mean_t - grid.box[6], atol=span / 65535)  # from the first point


def test_a_hair_outside_the_box_is_clamped_not_wrapped() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [655.35, 1.0, 1.0]])
    out = np.empty(payload_size(2, False), np.uint8)
    box = np.array([0.0, 0.0, 0.0, 655.35, 1.0, 1.0, 0.0, 0.0])
    pack_q16(pts + 1e-7, np.empty(0, np.int32), np.empty(0), box, 0.01, False, LAYOUT["q16z"], out)
    q = out.view("<u2")
    assert q[1] == 65535  # not 0


def test_decoded_points_are_row_major_as_kiss_icp_takes_them_at_full_speed() -> None:
    """Both codings decode to C-ordered (n, 3) points (and so does a coded scan on the wire):
    the planes' transpose is column-major, and KISS-ICP's binding converts that point by point,
    which cost the edge ~45 ms of each 80k-point KITTI-360 scan's registration until 2026-12-07."""
    pts = _scan()
    for encode, decode in ((encode_q16d, decode_q16d), (encode_q16z, decode_q16z)):
        origin, step, blob = encode(pts, 0.005)
        back = decode(blob, len(pts), origin, step)[0]
        assert back.shape == pts.shape and back.flags["C_CONTIGUOUS"], encode.__name__
