"""The robot in a fleet of edges: which edge maps it, when it moves, what it hands the next one.

Inputs:  the edges' liveliness (the server's ``EdgePresence``), ``<ns>/status/edge/*``
         (wire.Status: capacity, robots, draining), ``<ns>/data/<robot>/checkpoint/**``
         (wire.Checkpoint), the acks the scan pipeline books (told here).
Outputs: attach queries ``<ns>/ctrl/<robot>/attach/<edge>`` (wire.Attach → wire.AttachReply), on
         the fleet thread only (never in a Zenoh callback: a query waits up to attach_timeout).

``FleetState`` is the pure part (no Zenoh, the clock passed in), tested directly: the
``Assignment`` (robot/assign.py), the latest checkpoint of the robot's edge, the ack-silence
detector, the failover timings. ``FleetLink`` wires it to Zenoh and runs the attaches.

The robot moves when its edge's token goes, its status says draining, it sends a final
checkpoint, it refuses a scan under the current epoch, or it leaves scans unanswered for
``failover_after`` seconds while another live edge could take the robot (with none, the robot
stays and its local odometry bridges, up to ``STAY_SILENT`` times that). Attaches that get no
answer at all (an edge without the attach protocol, a lost query) are retried with a backoff
doubling from 0.2 s to 5 s.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.protocol.coding import CodingError, encode_q16d, quant_step
from zoffload.protocol.intake import answer_from
from zoffload.protocol.keys import Keys
from zoffload.robot.assign import ATTACHED, UNASSIGNED, Assignment
from zoffload.robot.odometry import Backfilled, Snapshot
from zoffload.robot.presence import EdgePresence
from zoffload.runtime.drops import Drops
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.robot.fleet")

DRAIN_WAIT = 1.0  # seconds a robot waits for its draining edge's final checkpoint before moving
STATUS_WAIT = 2.0  # seconds a new edge may take to send its status before the robot asks it anyway
OWN_CHECKPOINT_AFTER = 20  # scans: the robot's own checkpoint over the edge's when this much newer
BACKFILL_BYTES = 131_072  # what an attach's backfill may take on any link (RobotFleetSettings.backfill_bytes)
BACKFILL_BYTES_MAX = 1_048_576  # ... and at most, on a link seen to carry it (backfill_bytes_max)
# points of a backfill at most: an edge refuses a backfill of more than its max_points (500k by
# default) together
BACKFILL_POINTS = 400_000
BACKFILL_PROBE = 5  # scans coded first at a grid finer than the coarsest, to estimate what all take
BACKFILL_PROBE_MARGIN = 1.1  # ... left uncoded when estimated over the budget by this (estimates: within 2 %)
BACKFILL_SHARE = 0.5  # of the attach's timeout the backfill may take at the rate the link was seen at
RETRY_MIN, RETRY_MAX = 0.2, 5.0  # seconds between attaches that got no answer
MAX_TIMINGS = 10_000  # failover times kept
# A silent edge with no other edge to go to is kept (the local odometry bridges) for up to this many
# times failover_after more, then re-attached: a fresh attach re-seeds an edge that lost our state
# quietly
STAY_SILENT = 5.0


@dataclass(frozen=True)
class Sensor:
    """What an attach tells the edge about the robot's scans."""

    max_range: float
    voxel_max: float
    rate_hz: float


class FleetState:
    """The robot's fleet decisions, pure and thread-safe (one lock)."""

    def __init__(self, robot: str, failover_after: float, refusal_backoff: float = 5.0,
                 status_wait: float = 0.0) -> None:
        self.robot = robot
        self.failover_after = failover_after
        # An edge that appeared less than this long ago and whose status has not come yet is not
        # asked yet: the attach depends on the codec version it reads (``attach_message``)
        self.status_wait = status_wait
        self.assignment = Assignment(robot, refusal_backoff=refusal_backoff)
        self.checkpoint: wire.Checkpoint | None = None  # the newest from the robot's edge
        self.moves: Counter[str] = Counter()  # why the robot left an edge
        self.counters: Counter[str] = Counter()
        self.per_edge: Counter[str] = Counter()  # scans acked "ok" by each edge
        self.failover_s: list[float] = []
        self._lost_at: float | None = None  # when the robot last lost its edge (no ok ack since)
        self._waiting_since: float | None = None  # the oldest scan sent after the last ack
        self._last_ack: float | None = None  # of the current assignment (or its first scan sent)
        self._in_flight = False
        self._drain_seen: float | None = None  # when our edge announced it drains (awaiting its final)
        self._stay_since: float | None = None  # kept a silent edge since (no other edge to go to)
        self._retry = RETRY_MIN
        self._retry_at = -math.inf
        self._lock = threading.RLock()

    # What the network says
    def edge_present(self, edge: str, now: float = -math.inf) -> None:
        with self._lock:
            self.assignment.edge_present(edge, now)

    def edge_gone(self, edge: str, now: float) -> bool:
        with self._lock:
            was = self.assignment.state == ATTACHED
            return self._moved("token", now, was) if self.assignment.edge_gone(edge) else False

    def edge_status(self, edge: str, values: dict[str, float], now: float) -> bool:
        """An edge's status; True when it makes the robot move. Our own edge draining does not move
        the robot at once: its final checkpoint (the whole local map) comes after its next
        registered scan and moves it (``on_checkpoint``); ``silent`` moves it if that has not
        come within ``DRAIN_WAIT`` seconds."""
        with self._lock:
            a = self.assignment
            was = a.state == ATTACHED
            if not a.edge_status(edge, values.get("capacity", 0.0), values.get("robots", 0.0),
                                 values.get("draining", 0.0) > 0.5, wire.reads_in(values)):
                return False
            if a.state == ATTACHED:  # our edge drains: wait for its final checkpoint
                if self._drain_seen is None:
                    self._drain_seen = now
                return False
            return self._moved("draining", now, was)

    def expects(self, cp: wire.Checkpoint) -> bool:
        """Whether ``cp`` is of this robot's current assignment (edge and epoch)."""
        with self._lock:
            return self._expects(cp)

    def _expects(self, cp: wire.Checkpoint) -> bool:  # (under the lock)
        return cp.robot == self.robot and self.assignment.current(cp.edge, cp.epoch)

    def on_checkpoint(self, cp: wire.Checkpoint, now: float, checked: bool = True) -> str:
        """Keep the newest checkpoint of the current assignment; returns "kept", "stale" (another
        edge or epoch), "older", or "final" (kept, and the robot moves). ``checked``: whether its
        coded map was decoded when it came (only for the assignment then: one of an assignment
        made since is stale, not kept unchecked)."""
        with self._lock:
            if not checked or not self._expects(cp):
                self.counters["checkpoints_stale"] += 1
                return "stale"
            if self.checkpoint is not None and cp.seq < self.checkpoint.seq:
                self.counters["checkpoints_older"] += 1
                return "older"
            self.checkpoint = cp
            self.counters["checkpoints"] += 1
            if cp.final:  # draining or shedding us: move, and ask the others first
                self.assignment.no_answer(cp.edge, now, RETRY_MAX)
                self._moved("final", now, True)
                return "final"
            return "kept"

    # Scans and acks (the scan pipeline)
    def none_to_ask(self, now: float) -> bool:
        """Unassigned, with edges known and none of them to ask now (all full, or refused us)."""
        with self._lock:
            a = self.assignment
            return a.state == UNASSIGNED and bool(a.edges) and a.next_candidate(now) is None

    def target(self) -> tuple[str, int] | None:
        """(edge, epoch) to put on the next scan; None while no edge maps the robot."""
        with self._lock:
            a = self.assignment
            return (a.edge, a.epoch) if a.state == ATTACHED and a.edge is not None else None

    def count(self, what: str, n: int = 1) -> None:
        with self._lock:
            self.counters[what] += n

    def reads(self, edge: str) -> int:
        """The newest codec version ``edge`` said it reads (3 when it has not said)."""
        with self._lock:
            info = self.assignment.edges.get(edge)
            return info.reads if info is not None else 3

    def current(self, edge: str, epoch: int) -> bool:
        with self._lock:
            return self.assignment.current(edge, epoch)

    def on_sent(self, now: float) -> None:
        with self._lock:
            if self._last_ack is None or not self._in_flight:  # idle until now: the clock starts
                self._last_ack = now
            self._in_flight = True
            if self._waiting_since is None:
                self._waiting_since = now

    def on_ack(self, edge: str, epoch: int, status: str, now: float, in_flight: int) -> bool:
        """An ack the pipeline accepted; True when it makes the robot move (a refusal under the
        current epoch)."""
        with self._lock:
            current = self.assignment.current(edge, epoch)
            if current:  # the edge lives; scans sent before this ack and still unanswered were
                # lost one by one (they expire with the ack timeout), not a silent edge
                self._waiting_since, self._last_ack, self._in_flight = None, now, in_flight > 0
                self._stay_since = None
            if status == "ok":
                self.per_edge[edge] += 1
                if current and self._lost_at is not None:
                    if len(self.failover_s) < MAX_TIMINGS:
                        self.failover_s.append(now - self._lost_at)
                    self._lost_at = None
            if status == "refused" and current:
                self.assignment.refused(edge, now)
                return self._moved("refused", now, True)
            return False

    def no_scans_in_flight(self) -> None:
        """Every scan was answered or expired (the loop tells after its ack timeouts)."""
        with self._lock:
            self._waiting_since, self._in_flight = None, False

    def overdue(self, now: float, after: float) -> bool:
        """Whether the robot's edge is late answering by more than ``after`` s (the robot then
        bridges with local odometry; ``silent`` decides the move, later)."""
        with self._lock:
            return self.assignment.state == ATTACHED and self._silent_since(now) > after

    # The fleet thread
    def silent(self, now: float) -> bool:
        """Whether the robot's edge went silent; if so the robot moves. Silent: a scan sent after
        its last ack unanswered for ``failover_after`` s, or scans in flight and no ack at all for
        twice that (scans sent before the last ack that fill the window). With no other edge to
        go to, the robot stays (counted once per silence, ``silence_stayed``) until an ack comes
        or ``STAY_SILENT`` times ``failover_after`` have passed; scans expiring meanwhile (the
        robot stops sending to a silent edge) do not restart that clock."""
        with self._lock:
            if self.assignment.state != ATTACHED:
                return False
            if self._drain_seen is not None and now - self._drain_seen > DRAIN_WAIT:
                self.assignment.give_up()  # draining, and no final checkpoint came: move anyway
                return self._moved("draining", now, True)
            fa = self.failover_after
            staying = self._stay_since is not None
            if not staying and self._silent_since(now) <= fa:
                return False
            edge = self.assignment.edge
            if self.assignment.alternatives(now) == []:
                # no other edge could take us: re-attaching to this one would cost a second and a
                # re-seed; the local odometry bridges while it catches up (an edge that lost our
                # state refuses the next scan, one that died loses its token: both move us)
                if self._stay_since is None:
                    self._stay_since = now
                    self.counters["silence_stayed"] += 1
                if now - self._stay_since <= STAY_SILENT * fa:
                    return False
            self.assignment.give_up()
            if edge is not None:  # the others are asked first for a second
                self.assignment.no_answer(edge, now, 1.0)
            return self._moved("silence", now, True)

    def _silent_since(self, now: float) -> float:
        """How long the edge has been silent in the sense of ``silent`` (0 when it is not): the
        age of the oldest scan unanswered since the last ack, or, with scans in flight, half the
        time since the last ack (so that both compare with ``failover_after``)."""
        waited = now - self._waiting_since if self._waiting_since is not None else 0.0
        stalled = (now - self._last_ack) / 2 if self._in_flight and self._last_ack is not None else 0.0
        return max(waited, stalled)

    def next_attach(self, now: float, now_ms: int) -> tuple[str, int] | None:
        """The (edge, epoch) to ask now, or None (attached, attaching, nobody, or backing off)."""
        with self._lock:
            a = self.assignment
            if a.state != UNASSIGNED or now < self._retry_at:
                return None
            edge = a.next_candidate(now)
            if edge is None:
                return None
            info = a.edges.get(edge)
            if info is not None and not info.heard and now - info.present_since < self.status_wait:
                return None  # its status (which version it reads) comes within a status period
            return edge, a.begin_attach(edge, now_ms)

    def attach_result(self, edge: str, epoch: int, reply: wire.AttachReply | None, now: float) -> str:
        """The answer to our attach; returns "attached", "refused", "no_answer" or "stale"."""
        with self._lock:
            a = self.assignment
            if reply is None:
                self.counters["attach_no_answer"] += 1
                a.no_answer(edge, now, self._retry)
                self._retry_at = now + self._retry
                self._retry = min(RETRY_MAX, 2 * self._retry)
                return "no_answer"
            if reply.robot != self.robot or reply.edge != edge or reply.epoch != epoch:
                self.counters["attach_stale"] += 1
                a.no_answer(edge, now, self._retry)
                return "stale"
            if not reply.accepted:
                self.counters["attach_refused"] += 1
                a.edge_status(edge, reply.capacity, reply.robots, reply.detail == "draining")
                a.refused(edge, now)
                return "refused"
            if not a.attached(edge, epoch):
                self.counters["attach_stale"] += 1
                return "stale"
            self._retry, self._retry_at = RETRY_MIN, -math.inf
            self._waiting_since, self._last_ack, self._in_flight = None, None, False
            self._drain_seen, self._stay_since = None, None
            return "attached"

    def _moved(self, why: str, now: float, was_attached: bool) -> bool:
        self._drain_seen = None
        self._stay_since = None
        self.moves[why] += 1
        if was_attached and self._lost_at is None:
            self._lost_at = now
        self._waiting_since = None
        return True

    def attach_payload(self, snapshot: Snapshot | None
                       ) -> tuple[wire.Checkpoint | None, np.ndarray, np.ndarray]:
        """The checkpoint to continue from and the local poses after it: the edge's newest, whose
        local map is at an edge mapper's resolution, unless the local odometry's own is more than
        ``OWN_CHECKPOINT_AFTER`` scans newer (the robot has gone on far from the edge's map)."""
        with self._lock:
            cp = self.checkpoint
        seqs, poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
        if snapshot is not None:
            mine = snapshot.checkpoint
            if mine is not None and (cp is None or mine.seq > cp.seq + OWN_CHECKPOINT_AFTER):
                cp = mine
            keep = snapshot.seqs > cp.seq if cp is not None else np.ones(len(snapshot.seqs), bool)
            seqs, poses = snapshot.seqs[keep], snapshot.poses[keep]
        return cp, seqs, poses

    def metrics(self) -> dict[str, Any]:
        with self._lock:
            a = self.assignment
            return {"attaches": a.attaches, "failovers": a.failovers, "failover_s": list(self.failover_s),
                    "moves": dict(self.moves), "per_edge": dict(self.per_edge), **dict(self.counters),
                    "edge": a.edge if a.state == ATTACHED else "", "epoch": a.epoch}


def attach_message(robot: str, epoch: int, sensor: Sensor, cp: wire.Checkpoint | None, seqs: np.ndarray,
                   poses: np.ndarray, edge_reads: int, backfill: Sequence[Backfilled] = (),
                   backfill_bytes: int = BACKFILL_BYTES) -> wire.Attach:
    """The attach for an edge that reads codec version ``edge_reads``: from 6 on, the robot says
    it reads 6 (the edge then codes its checkpoints) and sends its checkpoint coded; to an older
    edge, a version-5 attach with the checkpoint's map as float32 points; the checkpoint's turn rate
    only to an edge that reads 8; the backfill as ``with_backfill`` adds it."""
    if cp is not None:
        cp = cp.readable_by(edge_reads)
    base = wire.Attach(robot=robot, epoch=epoch, max_range=sensor.max_range, voxel_max=sensor.voxel_max,
                       rate_hz=sensor.rate_hz, checkpoint=wire.encode(cp) if cp is not None else b"",
                       local_seqs=seqs, local_poses=poses, reads=max(wire.READS) if edge_reads >= 6 else 5)
    return with_backfill(base, sensor, edge_reads, backfill, backfill_bytes)


def with_backfill(base: wire.Attach, sensor: Sensor, edge_reads: int, backfill: Sequence[Backfilled],
                  backfill_bytes: int) -> wire.Attach:
    """``base`` (an attach without a backfill) with the backfill (``backfill_payload`` in
    ``backfill_bytes``), only to an edge that reads 9, and the robot's pose of each backfilled
    scan only to one that reads 10; ``base`` itself when no backfill goes."""
    data, sizes, kept = (backfill_payload(base.robot, base.epoch, sensor, backfill, backfill_bytes)
                         if edge_reads >= 9 and backfill else (None, None, []))
    if data is None:
        return base
    bposes = None
    if edge_reads >= 10 and kept and all(backfill[i].pose is not None for i in kept):
        bposes = np.stack([np.asarray(backfill[i].pose, np.float64) for i in kept])
    return dataclasses.replace(base, backfill=data, backfill_sizes=sizes, backfill_poses=bposes)


def backfill_grids(voxel: float, coarsest: float | None) -> list[float]:
    """The grids an attach tries a backfill at, finest first: ``voxel``, doubled while below
    ``coarsest``, and ``coarsest``."""
    top = max(voxel, coarsest or voxel)
    grids = [voxel]
    while grids[-1] * 2 < top:
        grids.append(grids[-1] * 2)
    if grids[-1] < top:
        grids.append(top)
    return grids


def backfill_budget(carried: float, floor: int, cap: int, attach_timeout: float) -> int:
    """The bytes an attach's backfill may take: what the link was seen to carry (``carried``,
    bytes a second, a lower bound: ``ScanLedger.carried_rate``) in ``BACKFILL_SHARE`` of the
    attach's timeout, at least ``floor`` and at most ``cap`` (a floor of 0: no backfill)."""
    if floor <= 0:
        return 0
    fit = carried * attach_timeout * BACKFILL_SHARE if math.isfinite(carried) and carried > 0 else 0.0
    return int(min(max(cap, floor), max(floor, fit)))


def backfill_payload(robot: str, epoch: int, sensor: Sensor, backfill: Sequence[Backfilled],
                     budget: int = BACKFILL_BYTES) -> tuple[np.ndarray | None, np.ndarray | None, list[int]]:
    """The attach's backfill: each scan a q16d ``Scan`` (a tenth of its grid for a step,
    Zstandard level 1), concatenated, their sizes, and the indices of the scans kept. All of them
    at the finest grid of ``backfill_grids`` where they fit in ``budget`` bytes and
    ``BACKFILL_POINTS`` points (the scan's ``voxel`` says which); at the coarsest, thinned evenly
    from the first scan (the last too where two fit) to fit both (an attach is one query, answered
    within ``attach_timeout``: 128 kB take half a second at 2 Mbps). (None, None, []) when nothing
    fits. A grid finer than the coarsest is first coded for ``BACKFILL_PROBE`` scans spread over
    the backfill; one their bytes a point put over ``BACKFILL_PROBE_MARGIN`` times the budget is
    left without coding the others."""
    if not backfill:
        return None, None, []
    grids = backfill_grids(max(b.voxel for b in backfill), max(b.coarsest or b.voxel for b in backfill))
    for grid in grids:
        clouds = [b.points if grid <= b.voxel else voxel_downsample(b.points, grid).astype(np.float32)
                  for b in backfill]
        points = np.array([len(c) for c in clouds], np.int64)
        coded: dict[int, bytes] = {}
        if grid < grids[-1]:
            if int(points.sum()) > BACKFILL_POINTS:
                continue
            # a few scans, spread, tell what all would take: a grid clearly over the budget is
            # left without coding the rest
            probe = _spread(len(backfill), BACKFILL_PROBE).tolist()
            coded = {i: _backfill_scan(robot, epoch, sensor, backfill[i], clouds[i], grid) for i in probe}
            per_point = sum(len(c) for c in coded.values()) / max(1, int(points[probe].sum()))
            if len(coded) < len(backfill) and per_point * int(points.sum()) > BACKFILL_PROBE_MARGIN * budget:
                continue
        coded_all = [coded[i] if i in coded else _backfill_scan(robot, epoch, sensor, b, clouds[i], grid)
                     for i, b in enumerate(backfill)]
        sizes = np.array([len(c) for c in coded_all], np.int64)
        if grid < grids[-1] and int(sizes.sum()) > budget:
            continue  # a coarser grid first, then fewer scans
        for m in range(len(coded_all), 0, -1):
            keep = _spread(len(coded_all), m)
            if int(sizes[keep].sum()) <= budget and int(points[keep].sum()) <= BACKFILL_POINTS:
                data = np.frombuffer(b"".join(coded_all[i] for i in keep), np.uint8)
                return data, sizes[keep], keep.tolist()
    return None, None, []


def _spread(n: int, m: int) -> np.ndarray:
    """At most ``m`` of the indices 0 … n − 1, evenly spread, the first always and the last too
    where two fit."""
    return np.unique(np.round(np.linspace(0, n - 1, min(n, m))).astype(np.int64))


def _backfill_scan(robot: str, epoch: int, sensor: Sensor, b: Backfilled, points: np.ndarray,
                   grid: float) -> bytes:
    """One backfilled scan, its ``points`` at ``grid``, coded."""
    voxel = max(grid, b.voxel)
    origin, step, packed = encode_q16d(points, quant_step(voxel), level=1, widen=True)
    return wire.encode(wire.Scan(
        robot=robot, seq=b.seq, send_stamp=time.monotonic(), capture_stamp=b.stamp, voxel=voxel,
        voxel_max=max(sensor.voxel_max, voxel), max_range=sensor.max_range, n_raw=b.n_raw,
        points=np.zeros((0, 3), np.float32), coding="q16d", quant_step=step, n_points=len(points),
        origin=origin, packed=np.frombuffer(packed, np.uint8), epoch=epoch))


class FleetLink:
    """``FleetState`` on Zenoh: subscriptions, the presence listener and the fleet thread."""

    def __init__(self, keys: Keys, state: FleetState, sensor: Sensor, attach_timeout: float,
                 snapshot: Callable[[], Snapshot | None] | None = None,
                 backfill_bytes: int = BACKFILL_BYTES,
                 on_backfill: Callable[[list[tuple[int, float]]], None] | None = None,
                 backfill_budget: Callable[[], int] | None = None) -> None:
        self.keys = keys
        self.backfill_bytes = backfill_bytes  # the backfill's floor (and its size when no budget)
        self.backfill_budget = backfill_budget  # bytes the next backfill may take (``backfill_budget``)
        self.on_backfill = on_backfill  # told (seq, grid) of a backfill an edge accepted with its attach
        self._attached_to: str | None = None  # the edge of the last attach accepted
        # since the last accepted attach, attaches with a backfill that got no answer: after one
        # larger than the floor the next carries one of the floor's size, after one at it none
        self._backfill_unanswered: int | None = None  # the bytes of the newest (None: none)
        self.state = state
        self.robot = state.robot
        self.sensor = sensor
        self.attach_timeout = attach_timeout
        self.snapshot = snapshot or (lambda: None)
        self.drops = Drops(log)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._session: zenoh.Session | None = None
        self._subs: list[Any] = []
        self._thread = threading.Thread(target=self._run, name="fleet", daemon=True)

    def start(self, session: zenoh.Session, presence: EdgePresence) -> None:
        self._session = session
        presence.subscribe(self._on_presence)
        presence.subscribe_status(self._on_status)
        for edge in presence.edges:
            self.state.edge_present(edge, time.monotonic())
        self._subs = [
            session.declare_subscriber(self.keys.checkpoints(self.robot),
                                       self.drops.guard(self._on_checkpoint, "checkpoint")),
        ]
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(self.attach_timeout + 1.0)
        undeclare(*self._subs)
        self._subs = []

    def wake(self) -> None:
        self._wake.set()

    def wait_settled(self, timeout: float, present: Callable[[], bool] | None = None) -> bool:
        """Block until the robot is attached or no live edge is left to ask (at startup, called once
        an edge's token came; ``present``: whether an edge's token is there still). While the fleet
        state knows no edge yet it waits: this link's presence callback runs after the watcher that
        let the robot start. Before, "no edge known" read as "none to ask", most likely why the
        robot mapped its first scans itself, the attach handed over nothing, and the edge began its
        map mid-drive (KITTI-360 ``satellite-heldout``, 0.058-0.061 m against 0.026 m locally,
        2026-12-07; 7 of 21 held-out runs that evening began so, none of 12 with the wait)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.state.target() is not None:
                return True
            if self.state.none_to_ask(time.monotonic()) or (present is not None and not present()):
                return False
            time.sleep(0.01)
        return False

    # Zenoh callbacks: short, they only update the state and wake the fleet thread
    def _on_presence(self, edge: str, present: bool, _now: frozenset[str]) -> None:
        if present:
            self.state.edge_present(edge, time.monotonic())
        elif self.state.edge_gone(edge, time.monotonic()):
            log.warning("edge %s gone: moving", edge)
        self._wake.set()

    def _on_status(self, st: wire.Status) -> None:
        """An edge's status (read and checked by the robot's EdgePresence)."""
        if self.state.edge_status(st.id, st.values, time.monotonic()):
            log.warning("edge %s drains: moving", st.id)
            self._wake.set()

    def _on_checkpoint(self, sample: zenoh.Sample) -> None:
        try:
            cp = wire.decode(sample.payload.to_bytes(), expect=wire.Checkpoint)
            if not answer_from(sample, self.keys, self.drops, cp.edge, "checkpoint"):  # another edge's name
                return
            checked = self.state.expects(cp)  # only then is its map worth decoding (counted stale below)
            if checked:
                cp.cloud()  # a coded local map must decode now, not when an outage needs it
        except wire.WireError as exc:
            self.drops.drop("malformed_checkpoint", str(exc))
            return
        if self.state.on_checkpoint(cp, time.monotonic(), checked) == "final":
            log.info("final checkpoint from edge %s (scan %d): moving", cp.edge, cp.seq)
            self._wake.set()

    # The fleet thread: attaches and the silence detector
    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.05)
            self._wake.clear()
            now = time.monotonic()
            if self.state.silent(now):
                log.warning("edge answered no scan for %.1f s: moving", self.state.failover_after)
            ask = self.state.next_attach(now, int(time.time() * 1e3))
            if ask is not None:
                try:
                    self._attach(*ask)
                except Exception as exc:  # a failed query must not end the thread
                    log.error("attach to %s failed: %s", ask[0], exc)
                    self.state.attach_result(ask[0], ask[1], None, time.monotonic())

    def _backfill_bytes(self) -> int:
        """What the next attach's backfill may take (0: none; see ``_backfill_unanswered``)."""
        budget = self.backfill_budget() if self.backfill_budget is not None else self.backfill_bytes
        if self._backfill_unanswered is None:
            return budget
        return min(budget, self.backfill_bytes) if self._backfill_unanswered > self.backfill_bytes else 0

    def _attach(self, edge: str, epoch: int) -> None:
        assert self._session is not None
        snapshot = self.snapshot()
        cp, seqs, poses = self.state.attach_payload(snapshot)
        # The backfill only back to the edge the robot was last attached to (another has no state
        # before it to register it from); after an attach with one went unanswered (its bytes may
        # be what a slow link could not carry within attach_timeout) at the floor's size, then none
        budget = self._backfill_bytes()
        backfill = (snapshot.backfill if snapshot is not None and edge == self._attached_to
                    and budget > 0 else ())
        reads = self.state.reads(edge)
        # without the backfill first: its checkpoint coded once, its size what the backfill may not take
        base = attach_message(self.robot, epoch, self.sensor, cp, seqs, poses, reads)
        if backfill and budget > self.backfill_bytes:  # the link's share less the rest of the attach
            budget = max(self.backfill_bytes, budget - len(wire.encode(base)))
        try:
            msg = with_backfill(base, self.sensor, reads, backfill, budget)
        except (CodingError, ValueError) as exc:  # (the robot's own scans: not expected) without it
            log.warning("backfill for edge %s not coded (%s): attaching without it", edge, exc)
            msg = base
        if msg.backfill_sizes is not None:
            self.state.count("backfill_sent", len(msg.backfill_sizes))
            self.state.count("backfill_sent_bytes", len(msg.backfill) if msg.backfill is not None else 0)
        reply: wire.AttachReply | None = None
        for r in self._session.get(self.keys.attach(self.robot, edge), payload=wire.encode(msg),
                                   timeout=self.attach_timeout):
            if r.ok is None:
                continue
            try:
                reply = wire.decode(r.ok.payload.to_bytes(), expect=wire.AttachReply)
            except wire.WireError as exc:
                self.drops.drop("malformed_attach_reply", str(exc))
                continue
            if reply.edge == edge:
                break
        result = self.state.attach_result(edge, epoch, reply, time.monotonic())
        where = f"checkpoint {cp.edge or 'local'}:{cp.seq}" if cp is not None else "no checkpoint"
        if msg.backfill is not None and reply is None:
            self._backfill_unanswered = len(msg.backfill)  # until an attach is accepted
        if result == "attached":
            self._attached_to, self._backfill_unanswered = edge, None
            if msg.backfill_sizes is not None:
                self.state.count("backfill_accepted", len(msg.backfill_sizes))
                if self.on_backfill is not None:
                    self.on_backfill([(scan.seq, scan.voxel) for scan in msg.backfill_scans()])
            log.info("attached to edge %s (epoch %d, %s, %d local poses, %d backfilled scans)", edge, epoch,
                     where, len(seqs), len(msg.backfill_sizes) if msg.backfill_sizes is not None else 0)
        elif result == "refused" and reply is not None:
            log.warning("edge %s refused the attach: %s", edge, reply.detail[:200])
        else:
            log.info("attach to edge %s: %s", edge, result)
