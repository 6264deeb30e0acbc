"""The edge's side of the fleet protocol (docs: /work/notes/fleet_contract.md, sections 1-6), pure:
no Zenoh, no threads, no clock (``now`` is passed in). The mapping service holds one ``Fleet`` and
calls it under its own lock.

* **Attach table.** Each attached robot has the epoch it attached under; an attach is accepted only
  with a larger epoch than the one held (held epochs outlive the robot's session, bounded), while
  the edge is not draining and has room (``robots`` counts map sessions; a robot that already has
  one does not count against itself).
* **Scans.** ``route`` sorts a scan by its (edge, epoch): another edge's (counted, nothing else),
  mapped, or refused with the ack detail and the drop reason.
* **Shedding.** The workers' busy seconds and the overload drops are sampled about once a second;
  over the last ``window`` seconds, a busy share above ``shed_load`` with overload drops and more
  than one attached robot sheds the newest one (at most one per ``window``), and the announced
  capacity drops to the robots kept for ``hold`` seconds.
* **Drain and final checkpoints.** Draining (SIGTERM) or shedding asks a final checkpoint of the
  robot; its scans are mapped until it moves (a shed robot's for ``quiet`` seconds after its final
  checkpoint went, then refused); the edge's drain is over when every attached robot has moved
  (its scans carry another edge) or has been quiet for ``quiet`` seconds with no final checkpoint
  still owed.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from dataclasses import dataclass

import numpy as np

from zoffload.protocol import wire

# A robot proposes its wall clock in ms (at least its last epoch + 1); an epoch further ahead of the
# edge's clock is accepted (an edge without NTP or a real-time clock boots in 1970) but not remembered
# after the robot's session: remembered, it would lock the robot's real attaches out as stale
EPOCH_AHEAD_MS = 86_400_000
EPOCHS_KEPT = 4096  # robots whose last epoch is remembered after their session went
LATE_MIN = 10  # scans answered in the window before their late share says anything

# What ``route`` decides for a scan
OTHER, MAP, REFUSE = "other_edge", "map", "refuse"


@dataclass
class Attached:
    """One robot attached to this edge."""

    epoch: int
    order: int  # attach order: the newest is shed first
    last_scan: float  # edge monotonic clock: attach time, then its last scan under this epoch
    final: str = ""  # "" no final checkpoint asked, "pending", "sent"
    final_at: float = 0.0  # edge monotonic clock: when the final checkpoint went
    shed: bool = False
    moved: bool = False  # its scans now name another edge
    reads: int = 5  # the newest codec version its attach said it reads (6: coded checkpoints)


@dataclass(frozen=True)
class Route:
    action: str  # OTHER, MAP or REFUSE
    detail: str = ""  # the refusal ack's detail
    reason: str = ""  # the drop's reason


def check_attach(attach: wire.Attach, robot: str, limits: wire.Limits = wire.DEFAULT_LIMITS
                 ) -> tuple[wire.Checkpoint | None, str]:
    """The attach's checkpoint (None: a fresh start; a coded map decoded to float32 points) and ""
    when it is usable, else the reason to refuse it (``bad checkpoint: ...``)."""
    cp: wire.Checkpoint | None = None
    if attach.checkpoint:
        try:
            cp = wire.decode(attach.checkpoint, expect=wire.Checkpoint, limits=limits)
        except wire.WireError as exc:
            return None, f"bad checkpoint: {str(exc)[:200]}"
        if cp.robot != robot:
            return None, f"bad checkpoint: made for robot {cp.robot!r}"
        if not _rigid(cp.pose[None]) or not _rigid(cp.delta[None]):
            return None, "bad checkpoint: pose or delta is not a rigid transform"
        try:
            cp = cp.plain(limits)  # decoded once, here: a coded map that does not decode is refused
        except wire.WireError as exc:
            return None, f"bad checkpoint: {str(exc)[:200]}"
    seqs = np.asarray(attach.local_seqs, np.int64)
    if len(seqs):
        if np.any(np.diff(seqs) <= 0):
            return None, "bad checkpoint: local seqs are not ascending"
        if cp is not None and seqs[0] <= cp.seq:
            return None, f"bad checkpoint: local seq {int(seqs[0])} not after the checkpoint's {cp.seq}"
        if not _rigid(np.asarray(attach.local_poses, np.float64)):
            return None, "bad checkpoint: a local pose is not a rigid transform"
    return cp, ""


def _rigid(poses: np.ndarray) -> bool:
    """Whether every 4x4 is a rigid transform (a tolerance for float32 round trips)."""
    if len(poses) == 0:
        return True
    rot = poses[:, :3, :3]
    ortho = np.einsum("nij,nkj->nik", rot, rot) - np.eye(3)
    return bool(np.allclose(poses[:, 3], [0.0, 0.0, 0.0, 1.0]) and np.abs(ortho).max() < 1e-3
                and np.abs(poses[:, :3, 3]).max() < 1e7)


class Fleet:
    def __init__(self, edge_id: str, capacity: int, require_attach: bool = False, shed: bool = True,
                 shed_load: float = 0.9, window: float = 5.0, hold: float = 30.0, quiet: float = 1.0,
                 shed_late: float = 0.05) -> None:
        self.edge_id = edge_id
        self.capacity = capacity
        self.require_attach = require_attach
        self.shed_enabled = shed
        self.shed_load = shed_load
        self.shed_late = shed_late
        self.window = window
        self.hold = hold
        self.quiet = quiet
        self.attached: dict[str, Attached] = {}
        self.epochs: OrderedDict[str, int] = OrderedDict()  # the last epoch each robot attached under
        self.draining = False
        self.drain_started: float | None = None
        self._order = 0
        # (now, busy seconds, overload drops, scans answered with a registration, of them late)
        self._samples: deque[tuple[float, float, int, int, int]] = deque()
        self._last_shed = -float("inf")
        self._held_capacity: tuple[int, float] | None = None  # (capacity, until)

    # Capacity
    def effective_capacity(self, now: float) -> int:
        if self._held_capacity is not None:
            cap, until = self._held_capacity
            if now < until:
                return min(self.capacity, cap)
            self._held_capacity = None
        return self.capacity

    # Attach
    def decide(self, robot: str, epoch: int, robots: int, has_session: bool, now: float) -> str:
        """"" to accept ``robot``'s attach under ``epoch``, else the refusal's detail. ``robots``:
        the map sessions on the edge now. Admission is the caller's last check."""
        if self.draining:
            return "draining"
        if epoch <= self.epochs.get(robot, 0):
            return "stale epoch"
        capacity = self.effective_capacity(now)
        others = robots - (1 if has_session else 0)
        if others >= capacity:
            return f"full: {robots} of {capacity} robots"
        return ""

    def attach(self, robot: str, epoch: int, now: float, reads: int = 5) -> None:
        self._order += 1
        self.attached[robot] = Attached(epoch, self._order, now, reads=reads)
        self.epochs.pop(robot, None)
        self.epochs[robot] = epoch
        while len(self.epochs) > EPOCHS_KEPT:
            self.epochs.popitem(last=False)

    def forget(self, robot: str) -> None:
        """The robot's session went (evicted): it is no longer attached. Its epoch is kept unless it
        is more than ``EPOCH_AHEAD_MS`` ahead of this edge's clock (see ``ahead``)."""
        self.attached.pop(robot, None)
        if self.ahead(self.epochs.get(robot, 0)):
            self.epochs.pop(robot, None)

    @staticmethod
    def ahead(epoch: int) -> bool:
        """An epoch more than a day ahead of this edge's wall clock: the edge's clock or the robot's
        is wrong (or the attach is hostile), so the epoch bars no later attach once its session goes."""
        return epoch > time.time() * 1e3 + EPOCH_AHEAD_MS

    # Scans
    def route(self, robot: str, edge: str, epoch: int, now: float) -> Route:
        if edge and edge != self.edge_id:
            entry = self.attached.get(robot)
            if entry is not None:
                entry.moved = True
            return Route(OTHER)
        if not edge and epoch == 0:
            if self.require_attach:
                return Route(REFUSE, "attach first", "attach_first")
            return Route(MAP)
        entry = self.attached.get(robot)
        if entry is None or entry.epoch != epoch or not edge:
            detail = "draining" if self.draining else f"not attached (epoch {epoch})"
            return Route(REFUSE, detail, "stale_epoch")
        if entry.shed and entry.final == "sent" and now - entry.final_at >= self.quiet:
            # Mapped until then, as a draining edge maps: the scans the robot sent before its
            # final checkpoint reached it got refusals and no pose (a gap of up to three scans
            # in the traced fleet runs); a robot that ignores the final is refused after it
            return Route(REFUSE, "shed: over capacity", "shed")
        entry.last_scan = now
        entry.moved = False
        return Route(MAP)

    # Final checkpoints
    def final_sent(self, robot: str, now: float) -> None:
        entry = self.attached.get(robot)
        if entry is not None:
            entry.final, entry.final_at = "sent", now

    def begin_drain(self, now: float) -> list[str]:
        """Start draining; the attached robots, each now owed a final checkpoint."""
        if not self.draining:
            self.draining = True
            self.drain_started = now
        owed = [r for r, e in self.attached.items() if not e.final]
        for r in owed:
            self.attached[r].final = "pending"
        return owed

    def drained(self, now: float) -> bool:
        """Whether every attached robot has moved or gone quiet with its final checkpoint sent."""
        return all(e.moved or (e.final != "pending" and now - e.last_scan >= self.quiet)
                   for e in self.attached.values())

    # Shedding
    def sample(self, now: float, busy: float, overload_drops: int, timed: int = 0, late: int = 0) -> None:
        """About once a second, cumulative: the workers' busy seconds, overload drops, scans
        answered with a registration and how many of them later than their robot's period after
        they arrived."""
        self._samples.append((now, busy, overload_drops, timed, late))
        while len(self._samples) > 2 and now - self._samples[1][0] >= self.window:
            self._samples.popleft()

    def busy_share(self, workers: int) -> float:
        """The workers' busy share over the sampled window (0 before two samples)."""
        if len(self._samples) < 2 or workers <= 0:
            return 0.0
        (t0, b0, *_), (t1, b1, *_) = self._samples[0], self._samples[-1]
        return 0.0 if t1 <= t0 else max(0.0, (b1 - b0) / ((t1 - t0) * workers))

    def late_share(self) -> float:
        """The share of scans answered late over the window (0 with fewer than LATE_MIN answered)."""
        if len(self._samples) < 2:
            return 0.0
        (*_, n0, l0), (*_, n1, l1) = self._samples[0], self._samples[-1]
        return (l1 - l0) / (n1 - n0) if n1 - n0 >= LATE_MIN else 0.0

    def dropping(self) -> bool:
        return len(self._samples) >= 2 and self._samples[-1][2] > self._samples[0][2]

    def overloaded(self, workers: int) -> bool:
        """Behind: more than ``shed_late`` of the scans answered late (queued into lateness, even
        with nothing dropped yet), or overload drops while the workers are busier than ``shed_load``."""
        late = behind(self.late_share(), self.shed_late)
        return late or (self.dropping() and self.busy_share(workers) > self.shed_load)

    def overload_reason(self) -> str:
        late = self.late_share()
        return (f"{100 * late:.1f} % of scans answered late" if behind(late, self.shed_late)
                else "scans dropped" if self.dropping() else "not overloaded")

    def to_shed(self, now: float, workers: int, room_elsewhere: bool = True) -> str | None:
        """The robot to shed now (it is then marked shed and owed a final checkpoint), or None.
        Only when another live edge has room (``room_elsewhere``): shedding into a full fleet only
        moves the overload around and sends robots to their local odometry."""
        kept = [(e.order, r) for r, e in self.attached.items() if not e.shed]
        if (not self.shed_enabled or not room_elsewhere or self.draining or len(kept) <= 1
                or now - self._last_shed < self.window or not self.overloaded(workers)):
            return None
        robot = max(kept)[1]
        entry = self.attached[robot]
        entry.shed = True
        if entry.final != "sent":
            entry.final = "pending"
        self._last_shed = now
        self._held_capacity = (len(kept) - 1, now + self.hold)
        return robot

    def shed_gone(self, now: float) -> list[str]:
        """Shed robots that have moved, or gone quiet after their final checkpoint: their sessions
        can go. Not before ``quiet`` s after the final (the scans mapped meanwhile would be answered
        ``dropped`` with the session)."""
        return [r for r, e in self.attached.items()
                if e.shed and e.final == "sent" and now - e.final_at >= self.quiet
                and (e.moved or now - e.last_scan >= self.quiet)]

    def status(self, now: float) -> dict[str, float]:
        return {"capacity": float(self.effective_capacity(now)), "draining": float(self.draining),
                "attached": float(len(self.attached)), "late_share": self.late_share()}


PEER_FRESH = 3.0  # seconds: an edge's status older than this says nothing about its room
MAX_PEERS = 256


def behind(late_share: float, limit: float = 0.05) -> bool:
    """Whether an edge's announced late share says it is behind (not a number: assume it is)."""
    return not late_share <= limit


class Peers:
    """The other edges' room, from their 1 Hz status (capacity, robots, draining, late share). An
    edge that is itself behind (more than ``late_limit`` of its scans answered late) has no room,
    whatever its count says: shedding to it would only move the overload and bounce robots back.
    An edge whose liveliness token went (``gone``) has none either, from that moment until its token
    is back (``back``): its last status stays fresh for ``PEER_FRESH`` seconds, and an edge that
    shed a robot into it then (a CI run: shed 1.1 s after the other edge was killed) left the robot
    on its own odometry with no edge to go to."""

    def __init__(self, edge_id: str, late_limit: float = 0.05) -> None:
        self.edge_id = edge_id
        self.late_limit = late_limit
        # edge -> capacity, robots, draining or behind, when heard
        self.seen: dict[str, tuple[float, float, bool, float]] = {}
        self.dead: set[str] = set()  # token gone, not back yet: their statuses say nothing

    def gone(self, edge: str) -> None:
        """The edge's liveliness token went: no room there, whatever it said last."""
        self.seen.pop(edge, None)
        if edge != self.edge_id and len(self.dead) < MAX_PEERS:
            self.dead.add(edge)

    def back(self, edge: str) -> None:
        """The edge's token is (again) there: its statuses count."""
        self.dead.discard(edge)

    def update(self, edge: str, values: dict[str, float], now: float) -> None:
        if (edge == self.edge_id or edge in self.dead
                or (edge not in self.seen and len(self.seen) >= MAX_PEERS)):
            return
        busy = values.get("draining", 0.0) > 0 or behind(values.get("late_share", 0.0), self.late_limit)
        self.seen[edge] = (values.get("capacity", 0.0), values.get("robots", 0.0), busy, now)

    def room_elsewhere(self, now: float) -> bool:
        for edge, (capacity, robots, busy, when) in list(self.seen.items()):
            if now - when > PEER_FRESH:
                del self.seen[edge]
            elif not busy and capacity - robots >= 1:
                return True
        return False


def peek_route(payload: bytes) -> tuple[str, int] | None:
    """A scan's ``edge`` and ``epoch`` read without decoding it (``wire.peek_fields``), so another
    edge's scans cost the edge almost nothing; None when the payload does not look like a scan (the
    full decode then counts it)."""
    got = wire.peek_fields(payload, wire.Scan.TYPE, ("edge", "epoch"))
    if got is None:
        return None
    edge, epoch = got.get("edge", ""), got.get("epoch", 0)
    if not isinstance(edge, str) or not isinstance(epoch, int) or isinstance(epoch, bool):
        return None
    return edge, epoch
