"""Scan payload coding: quantised, compressed, decoded on the edge within half a step."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.protocol import wire
from zoffload.protocol.coding import CodingError, decode_q16z, encode_q16z, quant_step
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
