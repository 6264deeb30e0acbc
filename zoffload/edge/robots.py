"""What the edge's mapping service keeps per robot, and what it needs of a robot's mapper.

``Mapper`` / ``FleetMapper`` / ``MapperFactory``: the mapper's interface (``recipe.BoundedMapper``
and ``recipe.MapperRecipe``, or a test's stand-in). ``RobotSession``: one robot's state on the
edge (its mapper, queue, counters and fleet hand-over state), touched under the service's lock
or by the one worker holding the robot (edge/mapping.py).
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import zenoh

from zoffload.edge.export import RobotFiles
from zoffload.edge.recipe import Spill
from zoffload.mapping.mapper import Registration
from zoffload.protocol import wire


class MapperLost(RuntimeError):
    """A robot's mapper is gone (its process died or hung, edge/isolate.py): the service counts it
    (``mapper_lost``) and detaches an attached robot, which attaches again with its checkpoint;
    another robot's next scan starts a new map."""


class Mapper(Protocol):
    """What the service needs of a robot's mapper: ``recipe.BoundedMapper``, or a stand-in."""

    @property
    def map_points(self) -> int: ...

    @property
    def scans(self) -> int: ...

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration: ...

    def map_cloud(self) -> np.ndarray: ...

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]: ...


class FleetMapper(Mapper, Protocol):
    """A mapper that continues trajectories and hands out checkpoints (``recipe.BoundedMapper``);
    a stand-in without these methods maps attached robots without checkpoints."""

    def continue_from(self, checkpoint: wire.Checkpoint | None, local_seqs: np.ndarray,
                      local_poses: np.ndarray, backfill: Sequence[tuple[int, np.ndarray]] = (),
                      backfill_poses: np.ndarray | None = None) -> bool: ...

    def checkpoint(self, robot: str, edge: str, epoch: int, stamp: float, resolution: float | None = None,
                   final: bool = False, coded: bool = True) -> wire.Checkpoint | None: ...

    def predict_from(self, seq: int, prior_seq: int, pose: np.ndarray, delta: np.ndarray,
                     contest: bool = False, frame: int = -1) -> bool: ...


class MapperFactory(Protocol):
    """Makes a robot's mapper from its first scan: ``recipe.MapperRecipe``, or a stand-in."""

    def warm_up(self) -> None: ...

    def __call__(self, scan: wire.Scan, spill: Spill | None = None) -> Mapper: ...


@dataclass
class Queued:
    scan: wire.Scan
    arrival: float  # edge monotonic clock
    interarrival: float


@dataclass(frozen=True)
class Continue:
    """What an attach asks the robot's mapper to continue from."""

    checkpoint: wire.Checkpoint | None
    local_seqs: np.ndarray
    local_poses: np.ndarray
    backfill: tuple[wire.Scan, ...] = ()  # the scans the robot registered itself (version 9)
    backfill_poses: np.ndarray | None = None  # the robot's pose of each (version 10)


PERIOD_SCANS = 15  # inter-arrivals the robot's scan period is the median of
KEPT_SEQS = 32  # a robot's recent scans kept (received, not dropped) that pick a full queue's victim


@dataclass
class RobotSession:
    """Per-robot state on the edge: the mapper (made on the first scan), the queue, counters.
    ``scheduled``: in the ready queue or held by a worker; ``closed``: evicted."""

    robot: str
    ack_pub: zenoh.Publisher
    files: RobotFiles
    mapper: Mapper | None = None
    queue: deque[Queued] = field(default_factory=deque)
    last_arrival: float | None = None
    gaps: deque[float] = field(default_factory=lambda: deque(maxlen=PERIOD_SCANS))  # recent inter-arrivals
    kept: deque[int] = field(default_factory=lambda: deque(maxlen=KEPT_SEQS))  # seqs received, not dropped
    spared: int | None = None  # the queue's oldest scan once a full queue dropped a later one instead
    counters: Counter[str] = field(default_factory=Counter)
    scheduled: bool = False
    closed: bool = False
    # Fleet: set under the lock by attaches, drain and shedding; used by the worker holding it
    pending: Continue | None = None
    final_pending: bool = False
    checkpoint_epoch: int = 0  # the epoch of its last checkpoint (0: none yet)
    lost_epoch: int = 0  # the epoch it was detached from when its mapper was lost: its scans refused
    since_checkpoint: int = 0
    last_stamp: float = 0.0  # capture stamp of its last registered scan
    cp_pub: zenoh.Publisher | None = None

    def push(self, item: Queued, limit: int) -> list[Queued]:
        """Queue ``item``; returns the scans dropped to keep at most ``limit`` waiting (``victim``)."""
        self.queue.append(item)
        self.kept.append(item.scan.seq)
        dropped: list[Queued] = []
        while len(self.queue) > limit:
            i = self.victim()
            dropped.append(self.queue[i])
            del self.queue[i]
            if dropped[-1].scan.seq in self.kept:
                self.kept.remove(dropped[-1].scan.seq)
        return dropped

    def victim(self) -> int:
        """The index of the queued scan to drop when the queue is over its length: never the
        newest; the oldest, unless dropping the one after it leaves a shorter run of the robot's
        scans with no pose (scans before and after that this edge dropped or never got); an
        oldest scan is spared so once, then goes (a queue kept fresh in a long burst). Dropping
        the oldest every time cut two or three consecutive scans out of a robot's trajectory in
        a burst of load (a drain's hand-over: the longest pose gap 2 scans against a target of
        1); thinned, a short burst drops as many, every other one, and KISS-ICP bridges one
        missed scan by its constant velocity better than two."""
        kept, queue = self.kept, self.queue
        head = queue[0].scan.seq if queue else None
        if len(queue) < 2 or not kept or head == self.spared:
            return 0
        lo, hi = min(kept), max(kept)

        def run(seq: int) -> int:
            n = 1
            for step in (-1, 1):
                s = seq + step
                while lo <= s <= hi and s not in kept and n <= KEPT_SEQS:
                    n, s = n + 1, s + step
            return n

        best = min(range(len(queue) - 1), key=lambda i: (run(queue[i].scan.seq), i))
        if best:
            self.spared = head
        return best

    def period(self) -> float:
        """The robot's scan period as the edge sees it: the median of its recent inter-arrivals
        (NaN before two scans). A scan answered later than this after it arrived is late."""
        gaps = sorted(self.gaps)
        return gaps[len(gaps) // 2] if gaps else float("nan")
