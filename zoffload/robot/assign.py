"""Which edge maps this robot: the live edges, a ranking among them, and the robot's assignment.

Pure (no Zenoh, no clock: ``now`` is passed in), tested directly. The robot server feeds it the
edges' liveliness tokens and their 1 Hz status values (``capacity``, ``robots``, ``draining``).

Ranking: weighted rendezvous hashing. Each (robot, edge) pair draws a stable number u in (0, 1)
from a hash; the edge's score is ``w / -ln(u)`` with ``w`` its free capacity. Without load every
robot prefers a different, stable edge (robots spread evenly and never move when an unrelated
edge comes or goes); an edge with more room wins more robots, a full edge none.

Assignment is sticky: the robot stays with its edge while that edge lives and does not drain or
refuse it, whatever the ranking says later. Every attach takes a new, larger epoch; answers
carrying another epoch or another edge are stale and ignored.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

UNASSIGNED, ATTACHING, ATTACHED = "unassigned", "attaching", "attached"


@dataclass
class EdgeInfo:
    edge: str
    capacity: int = 0  # robots it maps at most; 0 = not said yet
    robots: int = 0  # robots it maps now
    draining: bool = False  # leaving: takes no new robot
    refused_until: float = -math.inf  # it refused us: not asked again before this time
    reads: int = 3  # the newest codec version it said it reads (``wire.reads``; 3: not said)
    heard: bool = False  # a status of it arrived
    present_since: float = -math.inf  # when its token appeared (robot monotonic clock)

    @property
    def free(self) -> float:
        if self.draining:
            return 0.0
        if self.capacity <= 0:
            return 1.0  # unknown: an even share
        return max(0.0, float(self.capacity - self.robots))


def pair_uniform(robot: str, edge: str) -> float:
    """A number in (0, 1) fixed by the pair (the same on every machine and run)."""
    h = int.from_bytes(hashlib.blake2b(f"{robot}\x00{edge}".encode(), digest_size=8).digest(), "big")
    return (h + 0.5) / 2.0**64


def rank(robot: str, edges: list[EdgeInfo], now: float) -> list[str]:
    """Edges that may take ``robot`` now, best first (weighted rendezvous hashing)."""
    scored = []
    for e in edges:
        if e.free <= 0 or now < e.refused_until:
            continue
        scored.append((e.free / -math.log(pair_uniform(robot, e.edge)), e.edge))
    return [edge for _, edge in sorted(scored, reverse=True)]


@dataclass
class Assignment:
    """The robot's side of the assignment protocol."""

    robot: str
    state: str = UNASSIGNED
    edge: str | None = None
    epoch: int = 0
    edges: dict[str, EdgeInfo] = field(default_factory=dict)
    refusal_backoff: float = 5.0  # seconds before asking an edge that refused us again
    attaches: int = 0
    failovers: int = 0

    # What the network says
    def edge_present(self, edge: str, now: float = -math.inf) -> None:
        self.edges.setdefault(edge, EdgeInfo(edge, present_since=now))

    def edge_gone(self, edge: str) -> bool:
        """An edge's token went; True when it was ours (the robot must move)."""
        self.edges.pop(edge, None)
        if edge == self.edge:
            self._drop()
            return True
        return False

    def edge_status(self, edge: str, capacity: float, robots: float, draining: bool, reads: int = 3) -> bool:
        """An edge's load; True when our edge (attached or being asked) is draining. An edge being
        asked is left at once; an attached one is kept until its final checkpoint moves the robot
        (``FleetState`` times that wait)."""
        info = self.edges.get(edge)
        if info is None:
            return False  # status of an edge whose token we do not hold: not live
        info.capacity, info.robots, info.draining = _whole(capacity), _whole(robots), draining
        info.reads, info.heard = reads, True
        if draining and edge == self.edge:
            if self.state != ATTACHED:
                self._drop()
            return True
        return False

    # The robot's moves
    def next_candidate(self, now: float) -> str | None:
        """The edge to ask next, or None when no live edge may take us now."""
        order = rank(self.robot, list(self.edges.values()), now)
        return order[0] if order else None

    def alternatives(self, now: float) -> list[str]:
        """The edges other than ours that may take us now, best first."""
        return [e for e in rank(self.robot, list(self.edges.values()), now) if e != self.edge]

    def begin_attach(self, edge: str, now_ms: int) -> int:
        """Start asking ``edge``; returns the epoch to propose (larger than every earlier one and
        than the wall clock in ms, so a restarted robot still moves forward)."""
        self.state, self.edge = ATTACHING, edge
        self.epoch = max(self.epoch + 1, now_ms)
        return self.epoch

    def attached(self, edge: str, epoch: int) -> bool:
        """The edge accepted; False if the answer is not for our pending attach (stale)."""
        if self.state != ATTACHING or edge != self.edge or epoch != self.epoch:
            return False
        if self.attaches:
            self.failovers += 1
        self.state = ATTACHED
        self.attaches += 1
        return True

    def refused(self, edge: str, now: float) -> None:
        """The edge refused (full, draining, not allowed): not asked again for a while."""
        info = self.edges.get(edge)
        if info is not None:
            info.refused_until = now + self.refusal_backoff
        if edge == self.edge:
            self._drop()

    def no_answer(self, edge: str, now: float, backoff: float) -> None:
        """The edge did not answer the attach at all (an edge without the attach protocol, or a
        lost query): the others are asked first, this one again after ``backoff`` seconds."""
        info = self.edges.get(edge)
        if info is not None:
            info.refused_until = now + backoff
        if edge == self.edge:
            self._drop()

    def give_up(self) -> None:
        """The edge did not answer the attach (or stopped answering scans): move on."""
        if self.edge is not None and self.edge in self.edges:
            self.edges[self.edge].refused_until = -math.inf
        self._drop()

    def _drop(self) -> None:
        self.state, self.edge = UNASSIGNED, None

    # Answers
    def current(self, edge: str, epoch: int) -> bool:
        """Whether an answer (ack, checkpoint) comes from our edge under our epoch."""
        return self.state == ATTACHED and edge == self.edge and epoch == self.epoch


def _whole(x: float) -> int:
    """A count an edge reports, as an int: NaN or inf (the codec lets a status value be either) is
    0, not a ValueError that would lose the rest of the status (its draining flag)."""
    return int(min(max(x, 0.0), 1e9)) if math.isfinite(x) else 0
