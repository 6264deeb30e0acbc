"""The robot's own light KISS-ICP: its pose while no edge maps it.

Coarse (voxel ``max_range / 50`` by default, against the edge's ``/ 100``) and on a fixed number
of threads, so it costs the robot a bounded share of its CPU. It continues the edge's trajectory:
a period of local odometry starts from the freshest checkpoint (the edge's, or this odometry's
own from the period before) and the newest pose the edge acknowledged after it; scans sent but
never answered (a small ring spread over them, ``CatchUpRing``) are registered first, so the
trajectory has no hole. Every ``checkpoint_every`` registrations it takes its own checkpoint
(edge ""), which the next attach hands to the next edge together with the poses estimated since.

Not thread-safe by itself except where said: the robot's loop thread registers, the fleet thread
reads ``snapshot()`` (under the lock).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from zoffload.mapping.checkpoint import seed, take_checkpoint
from zoffload.mapping.mapper import load_kiss_icp, motion_per_scan
from zoffload.mapping.se3 import as_rigid, se3_power
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.robot.scanlog import Histogram

T = TypeVar("T")

MAX_GAP = 50  # beyond this many scans without a pose, constant velocity means nothing
MAX_LOCAL_POSES = 10_000  # poses kept for the next attach (16 minutes at 10 Hz)


# The backfill's grid against the local odometry's voxel: the simulator's VLP-16 at 0.2 m is 4.9k
# points, 12 kB coded a scan (0.8 m: 0.96k, 2.1 kB); KITTI-360's HDL-64 at 0.5 m 6k, 14 kB
BACKFILL_FINER = 0.25


def local_voxel_size(max_range: float, configured: float | None = None) -> float:
    return configured if configured is not None else max_range / 50.0


@dataclass(frozen=True)
class Held:
    """A scan kept in the catch-up ring: sent to the edge, maybe never answered."""

    seq: int
    points: np.ndarray  # the raw scan (a reference, not a copy)
    stamp: float  # capture stamp (robot wall clock)


@dataclass(frozen=True)
class Backfilled:
    """A scan the local odometry registered, kept at a grid for the next attach (its backfill:
    the edge that mapped the robot registers it, mapping/mapper.py ``continue_from``). The attach
    sends it at ``voxel`` when the link has room, coarser (up to ``coarsest``) when it has less."""

    seq: int
    stamp: float  # capture stamp (robot wall clock)
    n_raw: int  # points before the grid
    points: np.ndarray  # float32 (m, 3): the centroids of the ``voxel`` grid
    voxel: float
    pose: np.ndarray | None = None  # the local odometry's pose of it (4x4; version 10 sends it)
    coarsest: float | None = None  # the coarsest grid an attach may send it at (None: ``voxel``)


@dataclass(frozen=True)
class Snapshot:
    """What the next attach draws on: the local checkpoint and the poses of this period."""

    checkpoint: wire.Checkpoint | None
    seqs: np.ndarray  # int64 (n,)
    poses: np.ndarray  # float64 (n, 4, 4)
    backfill: tuple[Backfilled, ...] = ()  # the period's scans, spread over it, ascending


def _spread(kept: list[tuple[int, T]], item: tuple[int, T], size: int, stride: int) -> int:
    """Append ``item`` (its position in a stretch, the thing) to ``kept``, which holds every
    ``stride``-th position from the stretch's first and the newest: the newest so far, off the
    stride, is replaced; more than ``size`` kept, the stride doubles. Returns the stride."""
    if kept and kept[-1][0] % stride:
        kept.pop()
    kept.append(item)
    if len(kept) > size:
        stride *= 2
        kept[:] = [(j, x) for j, x in kept if j % stride == 0 or j == item[0]]
    return stride


class BackfillRing:
    """At most ``size`` of a period's registered scans, spread evenly over the whole period: every
    ``stride``-th (the period's first always) and the newest; when more than ``size`` are kept the
    stride doubles. The newest ``size`` alone left an outage longer than the ring without its start,
    and the edge, more than ``max_gap`` scans behind the first, left the whole backfill (the
    ``deadzone`` trace's 12 and 25 s, 2026-12-06); halving the whole ring each time it filled
    instead thinned its oldest part exponentially (a 25 s outage: its first two scans 128 apart,
    the backfill left again)."""

    def __init__(self, size: int) -> None:
        self.size = max(0, size)
        self.stride = 1
        self.count = 0  # scans offered this period
        self._kept: list[tuple[int, Backfilled]] = []  # (index in the period, scan)

    def add(self, scan: Backfilled) -> None:
        if not self.size:
            return
        i, self.count = self.count, self.count + 1
        self.stride = _spread(self._kept, (i, scan), self.size, self.stride)

    def clear(self) -> None:
        self.stride, self.count, self._kept = 1, 0, []

    def scans(self) -> tuple[Backfilled, ...]:
        return tuple(b for _, b in self._kept)


class CatchUpRing:
    """The scans sent since the newest one the robot has a pose of, at most ``size`` of them spread
    evenly over that stretch: every ``stride``-th (counted from the stretch's first) and the
    newest; when more than ``size`` are held the stride doubles. A scan is held by reference (the
    raw frame, not a copy), and the scans up to the newest posed one are let go, since a period's
    catch-up begins after it. The newest ``size`` alone left a hole: on a fade acks came 2.6 s
    late, the period began 21 scans after the newest pose with the newest 10 held, and the
    odometry stretched the motion of the pose before the hole over the 10 it did not hold (KITTI-360
    ``satellite-heldout``, replayed ping-pong: the robot turned back in the hole, and its poses and
    the prior it sent were 13 m off). Every other scan of such a stretch (21-30 scans past a turn
    back) registered, the poses were within 10 cm; every fourth, 16-45 m off (the replay turns back
    at 10 m/s between two scans; tests/core/robot/test_odometry.py). 20 held keep every other scan
    of a stretch of up to 39, 3.9 s at 10 Hz; a KITTI-360 scan is 1.3 MB. (The first and the newest
    are always held: a size of 1 holds 2.)"""

    def __init__(self, size: int) -> None:
        self.maxlen = max(0, size)
        self.stride = 1
        self._base = 0  # the seq the stride counts from: the stretch's first
        self._held: list[tuple[int, Held]] = []  # (seq - base, scan)

    def append(self, held: Held, posed_upto: int = -1) -> None:
        if not self.maxlen:
            return
        keep = [h for _, h in self._held if h.seq > posed_upto]
        if len(keep) < len(self._held) or not keep:
            # Some let go: the stretch now begins after the newest posed scan, and the ones left
            # (thinned already, at most ``size``) are kept as they are, at stride 1 again. Kept
            # doubled, the stride outlived the hole: on a link slower than a period the ring never
            # empties, and every other new scan was let go with the ring nearly empty.
            self.stride, self._base = 1, (posed_upto + 1 if keep else held.seq)
            self._held = [(h.seq - self._base, h) for h in keep]
        self.stride = _spread(self._held, (held.seq - self._base, held), self.maxlen, self.stride)

    def clear(self) -> None:
        self.stride, self._held = 1, []

    def __iter__(self) -> Iterator[Held]:
        return iter([h for _, h in self._held])

    def __len__(self) -> int:
        return len(self._held)


class LocalOdometry:
    def __init__(self, robot: str, max_range: float, voxel: float | None = None, threads: int = 1,
                 catch_up: int = 20, checkpoint_every: int = 10, backfill_scans: int = 0,
                 backfill_voxel: float | None = None) -> None:
        self.robot = robot
        self.max_range = max_range
        self.voxel = local_voxel_size(max_range, voxel)
        # The period's registered scans, spread over it (the next attach's backfill), kept at a
        # quarter of the odometry's voxel: sent at it where the link has room (the edge's map of
        # the outage), coarser where it has less, up to the odometry's voxel (a grid at most 10 m)
        self.backfill_voxel = (backfill_voxel if backfill_voxel is not None
                               else min(self.voxel * BACKFILL_FINER, 10.0))
        self.backfill_coarsest = max(min(self.voxel, 10.0), self.backfill_voxel)
        self._backfill = BackfillRing(backfill_scans)
        self.threads = threads
        self.checkpoint_every = max(1, checkpoint_every)
        self.ring = CatchUpRing(catch_up)
        self.cpu = Histogram()  # thread CPU per registration, ms
        self.registered = 0
        self.caught_up = 0
        self._odometry: object | None = None
        self._last_seq: int | None = None
        self._since_checkpoint = 0
        self._period_checkpointed = False
        self._lock = threading.Lock()
        self._checkpoint: wire.Checkpoint | None = None  # our own, the newest
        self._turn_rate = 0.0  # the edge's, from the checkpoint a period starts from: its own carry it on
        self._poses: deque[tuple[int, np.ndarray]] = deque(maxlen=MAX_LOCAL_POSES)
        self.motion = np.eye(4)  # the motion per scan period after the last registration

    # The ring (loop thread, while attached)
    def hold(self, seq: int, points: np.ndarray, stamp: float, posed_upto: int = -1) -> None:
        """Hold a scan sent; ``posed_upto``: the newest held scan the robot has a pose of."""
        self.ring.append(Held(seq, points, stamp), posed_upto)  # (a ring of size 0 holds none)

    # A period of local odometry
    @property
    def active(self) -> bool:
        return self._odometry is not None

    def begin(self, checkpoint: wire.Checkpoint | None, acked: list[tuple[int, np.ndarray]]) -> None:
        """Start a period from ``checkpoint`` (None: the origin, or where the last acked pose
        says) and ``acked``: the newest poses the robot has (seq, pose; the edge's, or its own of an
        earlier period), ascending, at most a few."""
        KISSConfig, KissICP = load_kiss_icp()
        config = KISSConfig()
        config.data.max_range = self.max_range
        config.data.min_range = 0.0
        config.data.deskew = False
        config.mapping.voxel_size = self.voxel
        config.registration.max_num_threads = self.threads
        odo = KissICP(config)
        last_seq = None
        if checkpoint is not None:
            seed(odo, checkpoint)
            last_seq = checkpoint.seq
        turn_rate = checkpoint.turn_rate if checkpoint is not None else 0.0
        newer = [(s, p) for s, p in acked if last_seq is None or s > last_seq]
        if newer:
            s, p = newer[-1]
            seqs = np.array([q for q, _ in newer], np.int64)
            delta = motion_per_scan(seqs, np.array([x for _, x in newer]), max_gap=MAX_GAP,
                                    span=1)  # the newest poses' last step
            if delta is not None:
                odo.last_delta = delta
            odo.last_pose = as_rigid(p)
            last_seq = s
        with self._lock:
            self._odometry, self._last_seq, self._since_checkpoint = odo, last_seq, 0
            self._turn_rate = turn_rate
            self._period_checkpointed = False

    def end(self) -> None:
        """An edge maps the robot again: this period is over (its checkpoint stays for reference)."""
        with self._lock:
            self._odometry = None
            self._poses.clear()
            self._backfill.clear()
        self.ring.clear()

    def catch_up(self, before: int, posed: set[int]) -> list[tuple[int, np.ndarray, float]]:
        """Register the held scans after the period's start and before ``before`` that got no
        pose (``posed``); returns (seq, pose, cpu ms) of each."""
        out = []
        start = -1 if self._last_seq is None else self._last_seq
        for h in list(self.ring):
            if start < h.seq < before and h.seq not in posed:
                pose, cpu = self.register(h.seq, h.points, h.stamp)
                out.append((h.seq, pose, cpu))
                self.caught_up += 1
        self.ring.clear()
        return out

    def register(self, seq: int, points: np.ndarray, stamp: float) -> tuple[np.ndarray, float]:
        """Register one scan; returns its pose and the thread CPU it took (ms)."""
        c0 = time.thread_time()
        odo = self._odometry
        if odo is None:
            raise RuntimeError("local odometry registers only between begin() and end()")
        frame = np.asarray(points, np.float64).reshape(-1, 3)
        # row-major (boolean indexing makes a copy, C order): KISS-ICP's binding converts any
        # other layout point by point, hundreds of times slower
        frame = np.ascontiguousarray(frame[np.isfinite(frame).all(axis=1)])
        gridded = self._gridded(frame) if self._backfill.size and len(frame) else None
        gap = seq - self._last_seq if self._last_seq is not None else 1
        stretch = 1 < gap <= MAX_GAP
        with self._lock:
            if stretch:  # scans without a pose in between: predict the motion over all of them
                odo.last_delta = as_rigid(se3_power(odo.last_delta, gap))  # type: ignore[attr-defined]
            odo.register_frame(frame, np.empty(0))  # type: ignore[attr-defined]
            if stretch:
                odo.last_delta = as_rigid(se3_power(odo.last_delta, 1.0 / gap))  # type: ignore[attr-defined]
            pose = np.array(odo.last_pose, np.float64)  # type: ignore[attr-defined]
            self.motion = np.array(odo.last_delta, np.float64)  # type: ignore[attr-defined]
            self._last_seq = seq
            self._poses.append((seq, pose))
            if gridded is not None and len(gridded):
                self._backfill.add(Backfilled(seq, stamp, len(frame), gridded, self.backfill_voxel, pose,
                                              self.backfill_coarsest))
            self._since_checkpoint += 1
            # A period's first registration takes one at once (the previous one is of another period)
            if self._since_checkpoint >= self.checkpoint_every or not self._period_checkpointed:
                self._checkpoint = take_checkpoint(odo, self.robot, "", 0, seq, stamp, self.voxel,
                                                   turn_rate=self._turn_rate)
                self._since_checkpoint, self._period_checkpointed = 0, True
        self.registered += 1
        cpu = (time.thread_time() - c0) * 1e3
        self.cpu.add(cpu)
        return pose, cpu

    def _gridded(self, frame: np.ndarray) -> np.ndarray | None:
        """The scan at the backfill's (finest) grid; None (not kept) for points the grid cannot hold."""
        try:
            return voxel_downsample(frame, self.backfill_voxel).astype(np.float32)
        except ValueError:  # coordinates too far from the origin for the grid's keys
            return None

    def snapshot(self) -> Snapshot:
        """The newest local checkpoint and this period's poses (fleet thread; the attach sends
        those after the checkpoint it chooses)."""
        with self._lock:
            c = self._checkpoint
            after = list(self._poses)
            backfill = self._backfill.scans()
        seqs = np.array([s for s, _ in after], np.int64)
        poses = np.array([p for _, p in after], np.float64).reshape(-1, 4, 4)
        return Snapshot(c, seqs, poses, backfill)

    def cpu_summary(self) -> dict[str, float | None]:
        return {"median": self.cpu.quantile(0.5), "mean": self.cpu.mean()}
