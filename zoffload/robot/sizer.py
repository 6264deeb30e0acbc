"""A raw scan to its payload, on the robot's sensor loop: the scale policy's voxel size, the grid
pass at it (non-finite and off-grid points skipped and counted in the same pass), and the
coding's layout filled straight from the grid's sums into a pooled buffer. No copy between the
stages; compression (``finish``), the wire message (``scan_message``) and ``put()`` are the sender
thread's (robot/sender.py, robot/scans.py).

The pieces stay apart so that other ways of sending (a fleet of edges, local odometry while none
answers) reuse them: ``ScanSizer`` knows nothing of Zenoh, the ledger or the sender.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.voxel import Grid, VoxelGrid, check_points
from zoffload.policy.rate import Decision, LinkAwareScale, LinkView
from zoffload.policy.scale import ScalePolicy
from zoffload.protocol import wire
from zoffload.protocol.coding import (
    LAYOUT,
    Q16Z_LEVEL,
    RAW,
    ZSTD,
    bounds,
    compress,
    pack_q16,
    payload_size,
    quant_step,
    times_to_u16,
)

_EMPTY_I = np.empty(0, np.int32)
_EMPTY_F = np.empty(0, np.float64)


def _times_from(t: np.ndarray, first: float, last: float) -> tuple[np.ndarray | None, float]:
    """u16 fractions of [first, last] (the sweep's), and its span; no times without a span."""
    span = last - first
    if not (span > 0 and math.isfinite(span)):
        return None, 0.0
    return np.clip(np.rint((t - first) * (65535 / span)), 0, 65535).astype("<u2"), span


class BufferPool:
    """Byte buffers for payloads, reused: the loop takes one per scan, the sender gives it back
    after ``put()`` (a fresh 0.6 MB array per scan costs its page faults every time)."""

    def __init__(self, keep: int = 4) -> None:
        self.keep = keep
        self._free: list[np.ndarray] = []
        self._lock = threading.Lock()

    def take(self, n: int) -> np.ndarray:
        with self._lock:
            for i, buf in enumerate(self._free):
                if len(buf) >= n:
                    return self._free.pop(i)
        return np.empty(max(n, 1 << 16) + n // 4, np.uint8)

    def give(self, buf: np.ndarray | None) -> None:
        if buf is None:
            return
        with self._lock:
            if len(self._free) < self.keep:
                self._free.append(buf)


@dataclass
class Sized:
    """One scan ready for the sender (or a decision not to send it)."""

    voxel: float
    decision: Decision
    n_valid: int = 0  # points before downsampling, invalid ones excluded
    n_invalid: int = 0  # non-finite or off-grid points (or non-finite times), skipped
    n_points: int = 0  # points in the payload
    coding: str = "f32"
    step: float = 0.0
    origin: np.ndarray | None = None
    time_span: float = 0.0
    payload: np.ndarray = field(default_factory=lambda: _EMPTY_I.view(np.uint8))  # q16: [header, planes]
    points: np.ndarray | None = None  # f32: (m, 3) float32
    times: np.ndarray | None = None  # f32: u16 times
    buffer: np.ndarray | None = None  # the pooled buffer behind the payload, returned after sending

    @property
    def skip(self) -> bool:
        return self.decision.skip


class ScanSizer:
    """Chooses each scan's size with ``policy`` and lays it out in ``coding``."""

    def __init__(self, policy: ScalePolicy, coding: str, quant_fraction: float = 0.1,
                 pool: BufferPool | None = None) -> None:
        self.policy = policy
        self.coding = coding
        self.quant_fraction = quant_fraction
        self.pool = pool or BufferPool()
        self.grid = VoxelGrid(buffers=2)  # the policy may hold two sizes of one scan
        self.voxel = policy.reset()

    def size(self, points: np.ndarray, times: np.ndarray | None, link: Callable[[], LinkView]) -> Sized:
        pts = check_points(points, 1.0)
        t = None if times is None else np.ascontiguousarray(times, np.float64)
        if t is not None and len(t) != len(pts):
            t = None  # a source whose times do not match its points: sent without times
        grids: dict[float, tuple[Grid, int]] = {}
        turn = [0]

        def count(v: float) -> int:
            """The grid pass at ``v`` (two buffers: a third size overwrites the oldest)."""
            if v not in grids:
                b = turn[0]
                turn[0] ^= 1
                for old in [u for u, (_, ub) in grids.items() if ub == b]:
                    del grids[old]
                grids[v] = (self.grid.run(pts, v, t, skip_invalid=True, buffer=b), b)
            return len(grids[v][0])

        if isinstance(self.policy, LinkAwareScale):
            view = link()
            decision = self.policy.decide(len(pts), view, count)
        else:
            view = link()
            v = self.policy.choose(view.last_t, self.voxel)
            decision = Decision(v, reason="fixed" if self.policy.name.startswith(("fixed", "raw"))
                                else f"{self.policy.name}: T {view.last_t:.3f} s", cause="fixed")
        self.voxel = decision.voxel
        if decision.skip:
            return Sized(decision.voxel, decision, n_valid=len(pts))
        if decision.voxel > 0:
            count(decision.voxel)
            return self._pack_grid(grids[decision.voxel][0], decision, len(pts))
        return self._pack_raw(pts, t, decision)

    def held_back(self, link: Callable[[], LinkView]) -> Decision | None:
        """The policy's word on a scan the window holds back (``LinkAwareScale.held_back``): a
        stall skip, or None (a window drop; other policies have no stalls)."""
        if isinstance(self.policy, LinkAwareScale):
            return self.policy.held_back(link())
        return None

    def _step(self, v: float) -> float:
        return quant_step(v, self.quant_fraction)

    def _pack_grid(self, grid: Grid, decision: Decision, n: int) -> Sized:
        out = Sized(decision.voxel, decision, n_valid=n - grid.n_invalid, n_invalid=grid.n_invalid,
                    n_points=len(grid), coding=self.coding)
        if self.coding == "f32":
            m = len(grid)
            out.buffer = self.pool.take(12 * m)  # given back by the sender after put()
            out.points = grid.centroids(np.float32, out=out.buffer[:12 * m].view(np.float32).reshape(m, 3))
            mean_t = grid.mean_times()
            if mean_t is not None:  # from the sweep's first point, as the q16 codings do
                out.times, out.time_span = _times_from(mean_t, grid.box[6], grid.box[7])
            return out
        tsums = _EMPTY_F if grid.tsums is None else grid.tsums
        return self._pack(out, grid.sums, grid.counts, tsums, grid.box, decision.voxel)

    def _pack_raw(self, pts: np.ndarray, t: np.ndarray | None, decision: Decision) -> Sized:
        valid, n_bad = drop_non_finite(pts)
        if t is not None:
            if n_bad:
                t = t[np.isfinite(pts).all(axis=1)]
            ok = np.isfinite(t)
            if not ok.all():
                valid, t, n_bad = valid[ok], t[ok], n_bad + int((~ok).sum())
        out = Sized(0.0, decision, n_valid=len(valid), n_invalid=n_bad, n_points=len(valid),
                    coding=self.coding)
        if self.coding == "f32":
            out.points = np.ascontiguousarray(valid, np.float32)
            if t is not None and len(t):
                out.times, out.time_span = times_to_u16(t)
            return out
        tt = _EMPTY_F if t is None else t
        return self._pack(out, valid, _EMPTY_I, tt, bounds(valid, tt), 0.0)

    def _pack(self, out: Sized, cloud: np.ndarray, counts: np.ndarray, tsums: np.ndarray, box: np.ndarray,
              v: float) -> Sized:
        m = out.n_points
        timed = len(tsums) == m and m > 0
        size = payload_size(m, timed)
        buf = self.pool.take(size + 1)
        ox, oy, oz, step, span, _ = pack_q16(cloud, counts, tsums if timed else _EMPTY_F, box, self._step(v),
                                              True, LAYOUT[self.coding], buf[1:size + 1])
        if timed and not span > 0:  # no spread of times: the time plane is not sent
            size = payload_size(m, False)
        out.origin = np.array([ox, oy, oz])
        out.step = step
        out.time_span = span if timed and math.isfinite(span) else 0.0
        out.payload = buf[: size + 1]
        out.buffer = buf
        return out


def finish(sized: Sized, zstd_level: int = 1) -> bool:
    """Compress the payload where its coding asks (q16z always, q16d when the policy said so);
    True if compressed. The planes stay where the grid pass left them when they go uncompressed."""
    if sized.coding == "q16z":
        sized.payload = np.frombuffer(compress(sized.payload[1:], Q16Z_LEVEL), np.uint8)
        return True
    if sized.coding == "q16d":
        if sized.decision.compress:
            sized.payload = np.frombuffer(bytes([ZSTD]) + compress(sized.payload[1:], zstd_level), np.uint8)
            return True
        sized.payload[0] = RAW
    return False


def scan_message(sized: Sized, *, robot: str, seq: int, send_stamp: float, capture_stamp: float,
                 voxel_max: float, max_range: float, n_raw: int, skipped: int = 0, edge: str = "",
                 epoch: int = 0, prior: tuple[int, np.ndarray, int] | None = None) -> wire.Scan:
    """The wire message of a finished scan; ``edge`` and ``epoch``: the robot's assignment ("" and
    0 without the attach protocol); ``prior``: the robot's own estimate (prior_seq, its pose and
    motion per period (2, 4, 4), its frame or -1; only for an edge that reads codec version 5, the
    frame for one that reads 11)."""
    prior_seq, prior_pose, prior_frame = prior if prior is not None else (-1, None, -1)
    common: dict[str, object] = dict(
        robot=robot, seq=seq, send_stamp=send_stamp, capture_stamp=capture_stamp, voxel=sized.voxel,
        voxel_max=max(voxel_max, sized.voxel), max_range=max_range, n_raw=n_raw, skipped=skipped,
        time_span=sized.time_span, edge=edge, epoch=epoch,
        prior_seq=prior_seq, prior=prior_pose, prior_frame=prior_frame)
    if sized.coding == "f32":
        assert sized.points is not None
        return wire.Scan(**common, points=sized.points,  # type: ignore[arg-type]
                         times=sized.times if sized.time_span > 0 else None)
    return wire.Scan(**common, points=np.zeros((0, 3), np.float32), coding=sized.coding,  # type: ignore[arg-type]
                     quant_step=sized.step, n_points=sized.n_points, origin=sized.origin,
                     packed=sized.payload)
