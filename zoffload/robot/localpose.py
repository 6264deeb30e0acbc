"""The robot's pose when its edge does not give one: local odometry as the scan pipeline's fallback.

Two situations, one light KISS-ICP (robot/odometry.py):
- **No edge maps the robot** (none attached): every scan is registered here instead of being sent
  (booked ``local``).
- **Bridging**: the robot is still attached but its edge's acks are overdue (``bridge_after``
  seconds since the oldest unanswered scan; by default two scan periods or twice the recent
  round trip, whichever is longer, and at most half of ``failover_after``). The robot cannot yet
  tell a dead edge from a slow one, so it keeps sending and also registers each scan itself
  (the scan's bucket is still what its ack makes it; its pose is the local one until an ack gives
  the edge's). That covers the second or so before a failover, which otherwise left every scan
  sent to a dead edge without a pose. Bridging ends with the next scan once the edge answers
  again and has acked a scan of the bridge (a late ack of a scan sent before the outage says
  nothing of the scans the edge missed); the poses it found go to the next edge in the attach
  (the odometry's snapshot), and each bridged scan carries its own to the same edge
  (``Scan.prior``, codec version 5: an edge that missed the scans before it predicts it from
  that, mapping/mapper.py ``predict_from``).

And when the robot has moved because its edge's token went (a dead process: the move is at once,
no bridging happened), the scans in flight to it are registered here at the first scan under the
new assignment, so they have poses too. When an attach takes longer than a period, the scans
read meanwhile are registered here with no edge (after the poses the attach handed over), and
the next edge's first scans carry the newest of them as their prior, until that edge acks one:
the edge predicts from it, moved by the correction it found when it registered the attach's
backfill, as it moved the handed-over poses (mapping/mapper.py ``predict_from``). They carried
none before (the robot's pose, drifted, could have undone that correction), and an edge carried
by its backfill to the scan before the robot reversed (KITTI-360 replayed ping-pong) stretched its
motion over the scans read during the attach: 7.4 m off. Every prior says its frame
(``Scan.prior_frame``, codec version 11, ``prior_for``): that of the edge's answers when the
odometry's period began from that edge's checkpoint under the current attach, else that of the
poses the attach handed over (a bridge begun from the robot's own checkpoint right after an
attach is in it too); an edge that reads less gets no prior of a scan read with no edge.

Either way a period starts from the freshest checkpoint (the edge's or our own) and the newest
poses the robot has after it (the edge's acked ones, or its own of an earlier period), and first
registers the held scans the edge never answered (the catch-up ring).

Threads: everything here runs on the scan pipeline's loop thread, except ``edge_pose`` (ack
callback) and ``status``; the ledger is shared under the pipeline's lock.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Callable
from itertools import islice
from typing import Any

import numpy as np

from zoffload.protocol import wire
from zoffload.robot.fleet import FleetState
from zoffload.robot.ledger import ScanLedger
from zoffload.robot.odometry import MAX_GAP, LocalOdometry, Snapshot
from zoffload.robot.sensor import Reading

log = logging.getLogger("zoffload.robot.localpose")

NO_EDGE = "no edge"  # why a period began that maps scans read with no edge
UNKNOWN_FRAME = ("", -1)  # a period whose checkpoint and first pose are in different frames
HANDOVER_POSES = 64  # the robot's newest scan poses an attach may hand over (those after its checkpoint)


class PoseKeeper:
    """Which pose the robot has, and the local odometry that fills in when the edge does not."""

    def __init__(self, odometry: LocalOdometry | None, fleet: FleetState, ledger: ScanLedger,
                 lock: threading.Lock, period: float, failover_after: float,
                 bridge_after: float | None = None, alive: Callable[[str], bool] | None = None) -> None:
        self.odometry = odometry
        self.alive = alive or (lambda _edge: True)  # whether an edge's token is still there
        self.fleet = fleet
        self.ledger = ledger
        self.lock = lock
        self.period = period
        self.failover_after = failover_after
        self.bridge_after = bridge_after  # None: automatic (see module doc)
        self.bridged = 0  # scans registered here while also sent to an overdue edge
        self.bridges = 0  # periods of bridging
        self._bridging = False
        self._target: tuple[str, int] | None = None  # the assignment of the last scan sent
        self._edge_newest = -1  # the newest acked scan with a pose
        self.pose: tuple[np.ndarray, float] | None = None  # the newest pose, its source (0 edge, 1 local)
        # The bridge's first scan, until the edge acks it or a later one (the bridge and its priors
        # may end then)
        self._bridge_from: int | None = None
        # The newest bridged registration (seq, pose, motion per period, whether it was made with
        # no edge), for ``prior_for``
        self._local: tuple[int, np.ndarray, np.ndarray, bool] | None = None
        # The frame the local odometry's period is in: that of an edge's answers under an epoch
        # (it began from that edge's checkpoint), None (the robot's own, or none), or UNKNOWN_FRAME
        self._frame: tuple[str, int] | None = None
        # After a move off a dead edge: the first scan to the next edge (its ack, or a later
        # one's, ends the prior the scans carry from the dead edge's unanswered ones)
        self._prior_from: int | None = None
        self._no_edge_period = False  # the odometry's period began with no edge (``no_edge``)

    # The ack callback (caller holds the lock)
    def edge_pose(self, seq: int, pose: np.ndarray) -> None:
        """An acked scan's pose (none from an edge that does not map: all NaN, not kept)."""
        if self._bridge_from is not None and seq >= self._bridge_from:
            self._bridge_from, self._local = None, None  # the edge answered a scan of the bridge
        if self._prior_from is not None and seq >= self._prior_from:
            self._prior_from, self._local = None, None  # the next edge answered after a move
        if not np.isfinite(pose).all():
            return
        if seq > self._edge_newest:
            self._edge_newest = seq
            self.pose = (np.array(pose), 0.0)

    # The loop thread
    def threshold(self) -> float:
        """Seconds the oldest unanswered scan may wait before the robot bridges."""
        if self.bridge_after is not None:
            return self.bridge_after
        with self.lock:
            recent = [r.get("rtt") for r in islice(reversed(self.ledger.records.values()), 20)]
        rtts = [x for x in recent if isinstance(x, float)]
        return self._threshold_for(float(np.median(rtts)) if rtts else 0.0)

    def _threshold_for(self, rtt: float) -> float:
        return min(max(2.0 * self.period, 2.0 * rtt), 0.5 * self.failover_after)

    def _overdue(self, now: float) -> bool:
        """Whether the edge is late by more than ``threshold``; the round trips are looked at only
        once it is late by the least the threshold can be (nearly every scan stops there)."""
        floor = self.bridge_after if self.bridge_after is not None else self._threshold_for(0.0)
        return self.fleet.overdue(now, floor) and self.fleet.overdue(now, self.threshold())

    def no_edge(self, reading: Reading, record: dict[str, Any]) -> bool:
        """No edge maps the robot: register the scan here and book it ``local``; False without
        local odometry (the caller drops it)."""
        odo = self.odometry
        if odo is None:
            return False
        self._bridging, self._target = False, None
        with self.lock:  # the next attach hands this period's poses over
            self._bridge_from, self._local, self._prior_from = None, None, None
        if not odo.active:
            self._begin(reading.seq, NO_EDGE)
        pose, cpu = odo.register(reading.seq, reading.frame.points, reading.capture_stamp)
        with self.lock:
            self.ledger.local(reading.seq, dict(record, cpu_local_ms=cpu), pose)
            self.pose = (pose, 1.0)
            # the prior of the next edge's first scans: those read while its attach was under way
            # are after the poses it hands over (``attached`` starts it, that edge's ack ends it)
            self._local = (reading.seq, pose, odo.motion, True)
        return True

    def attached(self, reading: Reading, target: tuple[str, int]) -> tuple[np.ndarray, float] | None:
        """An edge maps the robot (``target``: edge, epoch): hold the scan for a catch-up, and while
        the edge's acks are overdue register it here as well; returns (pose, cpu ms) to book once
        the scan has its record (``book_bridged``), or None. A bridge lasts until the edge is no
        longer overdue *and* has acked a scan of the bridge: an ack of a scan sent before the
        outage (delivered late) says nothing about the scans the edge missed. Every bridged scan
        goes out with its local pose and the odometry's motion (``prior_for``): an edge that
        missed the scans before it predicts it from them."""
        odo = self.odometry
        if odo is None:
            return None
        previous, self._target = self._target, target
        if previous is None:
            with self.lock:  # after scans with no edge: the next edge's ack ends their prior
                if self._local is not None and self._bridge_from is None and self._prior_from is None:
                    self._prior_from = reading.seq
        elif previous != target:
            with self.lock:  # another assignment: the attach handed the poses over
                self._bridge_from, self._local, self._prior_from = None, None, None
            self._bridging = False  # so a bridge to the new edge is one of its own, ended by its acks
            if not odo.active and not self.alive(previous[0]):
                # Moved off a dead edge: what was in flight to it will not be answered. Those
                # scans are registered after the attach went, so the next edge learns their poses
                # as the prior its first scans carry: it predicts from the robot's newest pose
                # instead of stretching its last handed-over one over the scans it never got
                newest = self._begin(reading.seq, f"edge {previous[0]} gone")
                if newest is not None:
                    with self.lock:
                        self._local, self._prior_from = (*newest, odo.motion, False), reading.seq
                odo.end()
        with self.lock:
            answered = self._bridge_from is None
        if answered and not self._overdue(time.monotonic()):
            if odo.active:
                odo.end()  # an edge answers (again)
                self._bridging = False
            with self.lock:  # (the held scans answered since: a catch-up begins after them)
                posed = max((h.seq for h in odo.ring if h.seq in self.ledger.poses), default=-1)
            odo.hold(reading.seq, reading.frame.points, reading.capture_stamp, posed)
            return None
        if not odo.active:
            self._begin(reading.seq, "acks overdue")
        if not self._bridging:
            self._bridging, self.bridges = True, self.bridges + 1
            with self.lock:
                self._bridge_from, self._prior_from = reading.seq, None
        pose, cpu = odo.register(reading.seq, reading.frame.points, reading.capture_stamp)
        self.bridged += 1
        with self.lock:
            # (a bridge that goes on with a no-edge period's odometry is in that period's frame:
            # an edge reading < 11 gets no prior of it either)
            self._local = (reading.seq, pose, odo.motion, self._no_edge_period)
        return pose, cpu

    def prior_for(self, seq: int, reads: int = max(wire.READS)) -> tuple[int, np.ndarray, int] | None:
        """What scan ``seq`` carries to an edge that reads codec version ``reads``
        (``Scan.prior``): the newest scan the local odometry registered in the last bridge
        (``seq`` itself while bridging), or with no edge while the attach was under way, its pose
        and the odometry's motion per period then, and the frame it is in (``Scan.prior_frame``:
        0 the answers of the edge it goes to, 1 the poses the attach handed over, -1 not known
        (the period's checkpoint and first pose in different frames); -1, not said, to an edge
        that reads less than 11, which gets no prior of a scan read with no edge, nor of a bridge
        that goes on with such a period's odometry),
        (prior_seq, (2, 4, 4), frame); None once the edge has acked a scan of that bridge (or
        after the attach), or when it is ``MAX_GAP`` scans old. The edge uses it only after scans
        it missed."""
        with self.lock:
            local = self._local
            if local is None or seq - local[0] >= MAX_GAP:
                return None
            if reads < 11:
                return None if local[3] else (local[0], np.stack([local[1], local[2]]), -1)
            frame = (-1 if self._frame == UNKNOWN_FRAME
                     else 0 if self._frame is not None and self._frame == self._target else 1)
            return local[0], np.stack([local[1], local[2]]), frame

    def book_bridged(self, seq: int, pose: np.ndarray, cpu: float) -> None:
        """The local pose of a scan sent (or dropped at source) while bridging."""
        with self.lock:
            if self.ledger.local_pose(seq, pose):
                self.ledger.records[seq]["cpu_local_ms"] = cpu
            self.pose = (pose, 1.0)

    def _begin(self, seq: int, why: str) -> tuple[int, np.ndarray] | None:
        """Start a period from the freshest checkpoint and the newest poses after it (the edge's
        or the local odometry's of an earlier period), and register first the held scans the edge
        never answered; returns the newest of those (seq, pose), if any."""
        assert self.odometry is not None
        odo = self.odometry
        cp, mine = self.fleet.checkpoint, odo.snapshot().checkpoint
        if mine is not None and (cp is None or mine.seq > cp.seq):
            cp = mine
        with self.lock:
            newest = self._newest_poses(cp.seq if cp is not None else -1)
            posed = {h.seq for h in odo.ring if h.seq in self.ledger.poses}
            # The period's frame: its checkpoint's map's (an edge's answers under its epoch, or the
            # frame the robot's own checkpoints are in: the last period's), when the pose it begins
            # from is in the same one (an edge's answer under that epoch, or a local pose of the
            # last period); else not known (the edge contests both). No checkpoint: the pose's.
            frame = None if cp is None else (cp.edge, cp.epoch) if cp.edge else self._frame
            if newest:
                rec = self.ledger.records.get(newest[-1][0], {})
                by = ((str(rec.get("edge")), int(rec.get("epoch") or 0)) if rec.get("pose_source") == "edge"
                      else self._frame)
                frame = by if cp is None else frame if by == frame else UNKNOWN_FRAME
            self._frame = frame
        odo.begin(cp, newest)
        self._no_edge_period = why == NO_EDGE
        caught = odo.catch_up(seq, posed)
        for s, pose, cpu in caught:
            with self.lock:
                if self.ledger.local_pose(s, pose):
                    self.ledger.records[s]["cpu_local_ms"] = cpu
        log.info("mapping locally from scan %d, %s (checkpoint %s, %d scans caught up)", seq, why,
                 f"{cp.edge or 'local'}:{cp.seq}" if cp is not None else "none", odo.caught_up)
        return (caught[-1][0], caught[-1][1]) if caught else None

    def handover(self) -> Snapshot:
        """What the next attach hands over (fleet thread): the local odometry's newest checkpoint
        and the pose of each of the robot's newest scans (at most ``HANDOVER_POSES``): the edge's
        where one answered, else the local odometry's, its period's poses included. The attach
        sends those after the checkpoint it carries (``FleetState.attach_payload``); the next
        edge's trajectory goes on from the newest of them at the robot's own motion. It handed
        over the local odometry's poses only: after an edge was killed (a move at once, nothing
        bridged) the next edge got the last checkpoint and no pose after it, and predicted the
        robot's first scan by stretching the checkpoint's motion over up to ten scans; in a turn
        that put it 9 degrees off and the trajectory 2 m off by the end (a fleet run with five
        kills: ATE 1.05 m against 0.49)."""
        odo = self.odometry
        none = Snapshot(None, np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        snap = odo.snapshot() if odo is not None else none
        merged = {int(s): p for s, p in zip(snap.seqs, snap.poses, strict=True)}
        with self.lock:
            merged.update(self._newest_poses(-1, HANDOVER_POSES))
        seqs = sorted(merged)
        return Snapshot(snap.checkpoint, np.array(seqs, np.int64),
                        np.array([merged[s] for s in seqs], np.float64).reshape(-1, 4, 4), snap.backfill)

    def _newest_poses(self, after: int, n: int = 2) -> list[tuple[int, np.ndarray]]:
        """The newest ``n`` poses the robot has for scans after ``after``, ascending: the edge's
        where it answered, else the local odometry's. A period that started from its checkpoint
        alone ignored the local poses the robot had just found after it (a reattach hands them
        to the edge, ``attach_payload``) and stretched the checkpoint's motion over the gap to
        the first scan it registers: on KITTI-360, seven scans from the robot's own checkpoint,
        4 m off along the road, and the scans it bridged carried that to the edge. Caller holds
        the lock."""
        out: list[tuple[int, np.ndarray]] = []
        poses = self.ledger.poses
        for seq in heapq.nlargest(4 * n, (s for s in poses if s > after)):
            if np.isfinite(poses[seq]).all():  # an edge that does not map acks with NaN
                out.append((seq, np.array(poses[seq])))
                if len(out) == n:
                    break
        return out[::-1]

    def metrics(self) -> dict[str, Any]:
        odo = self.odometry
        return {"caught_up": odo.caught_up if odo is not None else 0,
                "bridged_scans": self.bridged, "bridges": self.bridges,
                "local_cpu_ms_per_scan": (odo.cpu_summary() if odo is not None
                                          else {"median": None, "mean": None}),
                "local_voxel": odo.voxel if odo is not None else None}
