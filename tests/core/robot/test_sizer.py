"""A raw scan to its payload: every coding decodes on the edge to the paper's voxel set (within
half a quantisation step), invalid points are skipped and counted, per-point times travel as each
voxel's mean time, and a policy's decision not to send is passed on."""

from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.mapping.voxel import VoxelGrid, voxel_downsample
from zoffload.policy.rate import LinkAwareScale, LinkView
from zoffload.policy.scale import FixedScale
from zoffload.protocol import wire
from zoffload.robot.sizer import ScanSizer, Sized, finish, scan_message
from zoffload.sources.simulated import SimulatedSource

VIEW = LinkView(0.1, 1e6, 3.0, 0.1)


def _scan() -> np.ndarray:
    return SimulatedSource(seed=0).read(3).points


def on_the_wire(s: Sized, level: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    finish(s, level)
    msg = scan_message(s, robot="r", seq=1, send_stamp=0.0, capture_stamp=0.0, voxel_max=0.07, max_range=40.0,
                       n_raw=s.n_valid)
    return wire.decode(wire.encode(msg), expect=wire.Scan).cloud_and_times()


@pytest.mark.parametrize("coding", ["f32", "q16z", "q16d"])
@pytest.mark.parametrize("voxel", [0.0, 0.05])
def test_every_coding_decodes_to_the_papers_voxel_set(coding: str, voxel: float) -> None:
    raw = _scan()
    pts = raw[np.isfinite(raw).all(axis=1)]
    s = ScanSizer(FixedScale(voxel), coding).size(raw, None, lambda: VIEW)
    expected = voxel_downsample(pts, voxel) if voxel > 0 else pts
    assert s.n_points == len(expected) and s.n_valid == len(pts) and s.n_invalid == len(raw) - len(pts)
    back, times = on_the_wire(s)
    step = 0.0 if coding == "f32" else s.step
    assert np.abs(back - expected).max() <= step / 2 + 1e-5
    assert times is None


def test_uncompressed_q16d_when_the_policy_says_so() -> None:
    s = ScanSizer(FixedScale(0.05), "q16d").size(_scan(), None, lambda: VIEW)
    s.decision = type(s.decision)(0.05, compress=False)
    assert not finish(s) and s.payload[0] == 0 and len(s.payload) == 1 + 6 * s.n_points


@pytest.mark.parametrize("coding", ["f32", "q16d"])
def test_point_times_travel_as_each_voxels_mean_time(coding: str) -> None:
    raw = _scan()
    pts = raw[np.isfinite(raw).all(axis=1)]
    times = 1.7e9 + np.linspace(0.0, 0.1, len(pts))  # wall-clock seconds, any offset
    s = ScanSizer(FixedScale(0.05), coding).size(pts, times, lambda: VIEW)
    grid = VoxelGrid().run(pts, 0.05, times=times)
    mean_t = grid.mean_times()
    assert mean_t is not None and s.time_span == pytest.approx(0.1, rel=1e-6)
    _, back_t = on_the_wire(s)
    assert back_t is not None and len(back_t) == len(grid)
    np.testing.assert_allclose(back_t, mean_t - grid.box[6], atol=0.1 / 65535 + 1e-9)  # from the first point


def test_a_scan_with_no_valid_point_is_empty_and_a_skip_is_passed_on() -> None:
    s = ScanSizer(FixedScale(0.05), "q16d").size(np.full((50, 3), np.nan, np.float32), None, lambda: VIEW)
    assert s.n_points == 0 and s.n_invalid == 50 and not s.skip
    policy = LinkAwareScale((0.01, 0.07), stall_after=0.5)
    sizer = ScanSizer(policy, "q16d")
    sizer.size(_scan(), None, lambda: LinkView(0.0, math.nan, math.nan, 0.1))
    stalled = LinkView(0.1, 1e6, 3.0, 0.1, acks=1, since_ack=2.0, in_flight=3)
    s = sizer.size(_scan(), None, lambda: stalled)
    assert s.skip and s.decision.cause == "stall" and s.n_points == 0


def test_f32_points_are_laid_out_in_a_pooled_buffer_given_back_after_sending() -> None:
    # The sender gives the buffer back after put(): the next scan's centroids go in the same bytes.
    raw = _scan()
    sizer = ScanSizer(FixedScale(0.05), "f32")
    first = sizer.size(raw, None, lambda: VIEW)
    assert first.buffer is not None and first.points is not None
    assert np.shares_memory(first.points, first.buffer)
    np.testing.assert_array_equal(first.points, voxel_downsample(raw[np.isfinite(raw).all(axis=1)], 0.05)
                                  .astype(np.float32))
    sizer.pool.give(first.buffer)
    second = sizer.size(raw, None, lambda: VIEW)
    assert second.buffer is first.buffer
    grid = VoxelGrid().run(raw, 0.05, skip_invalid=True)
    with pytest.raises(ValueError, match="C-contiguous"):
        grid.centroids(np.float32, out=np.empty((len(grid), 3), np.float64))
