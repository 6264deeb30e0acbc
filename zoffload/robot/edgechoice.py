"""Which edge detects the robot's camera frames, among the edges present.

Pure (no Zenoh, no clock: ``now`` is passed in), tested directly. The camera pipeline feeds it the
edges' liveliness (robot/presence.py) and their 1 Hz status values: ``detector.free`` (the share of
the last few seconds the edge's detector thread was idle, edge/detection.py), ``draining``
(1 while the edge leaves, from the fleet protocol) and the detector's network input
(``detector.input_w``, ``detector.input_h``, ``detector.stretch``): what a frame can be shrunk to
on its way there without changing what the network sees (``send_size``), and ``wire.reads``, the
newest codec version the edge reads (``reads``: whether its answers can carry the frame's arrival).

Frames are stateless work, so unlike the mapping assignment (robot/assign.py) there is no attach:
the robot names the edge in each frame (``Frame.edge``) and only that edge answers it. The choice
is weighted rendezvous hashing, as robot/assign.py ranks edges (the same ``pair_uniform``): each
(robot, edge) pair draws a stable number u in (0, 1) and the edge scores ``free / -ln(u)``, so idle
edges share the robots evenly and stably, a busier edge wins fewer. It is sticky: the robot stays
with its edge while it is present, not draining and not full (``free`` below ``full_below``); when
it is full the robot moves to a ranked edge that is not, at most once per ``dwell`` seconds (a
robot that fills any edge alone would otherwise hop every status period); a gone or draining edge
is left at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from zoffload.detect.detector import shrink_size
from zoffload.protocol import wire
from zoffload.robot.assign import pair_uniform

FREE, DRAINING = "detector.free", "draining"
INPUT_W, INPUT_H, STRETCH = "detector.input_w", "detector.input_h", "detector.stretch"
INPUT_SIDES = (32, 8192)  # a network input side outside these is not believed (the frame stays whole)


@dataclass
class DetectorLoad:
    free: float = 1.0  # idle share of the edge's detector; 1 until the edge says otherwise
    draining: bool = False
    input_hw: tuple[int, int] | None = None  # its detector's network input, once the edge says it
    stretch: bool = False  # whether that detector stretches a frame to its input (else letterbox)
    reads: int = 3  # the newest codec version the edge said it reads


def _whole(value: float | None, lo: int, hi: int) -> int | None:
    """A status value that is a whole number within [lo, hi], else None (not believed)."""
    if value is None or not math.isfinite(value) or value != int(value):
        return None
    return int(value) if lo <= value <= hi else None


def _side(value: float | None) -> int | None:
    return _whole(value, *INPUT_SIDES)


class EdgeChoice:
    def __init__(self, robot: str, full_below: float = 0.1, dwell: float = 5.0) -> None:
        self.robot = robot
        self.full_below = full_below
        self.dwell = dwell
        self.edges: dict[str, DetectorLoad] = {}
        self.current: str | None = None
        self.switches = 0  # moves from one edge to another (not the first choice)
        self._since = -math.inf  # when the robot last moved from one edge to another

    # What the network says
    def present(self, edges: frozenset[str]) -> None:
        """The edges present now (their tokens); loads of edges that stay are kept."""
        self.edges = {e: self.edges.get(e) or DetectorLoad() for e in edges}

    def status(self, edge: str, values: dict[str, float]) -> None:
        """An edge's status values (ignored for an edge whose token is not held: not live)."""
        load = self.edges.get(edge)
        if load is None:
            return
        free = values.get(FREE)
        if free is not None and math.isfinite(free):
            load.free = min(max(float(free), 0.0), 1.0)
        load.draining = values.get(DRAINING, 0.0) == 1.0
        w, h = _side(values.get(INPUT_W)), _side(values.get(INPUT_H))
        if w is not None and h is not None:
            load.input_hw, load.stretch = (h, w), values.get(STRETCH, 0.0) == 1.0
        # each status is the whole picture: an edge restarted as an older build stops saying it
        load.reads = wire.reads_in(values)

    def reads(self, edge: str) -> int:
        """The codec version to tell ``edge`` this robot reads: 4 when the edge reads 4 too (it then
        stamps its answers with the frame's arrival), else 3, which any edge takes without the field."""
        load = self.edges.get(edge)
        return min(max(wire.READS), load.reads) if load is not None and load.reads >= 4 else 3

    def send_size(self, edge: str, width: int, height: int) -> tuple[int, int]:
        """The size to send a ``width`` x ``height`` frame to ``edge`` at: shrunk to what its
        detector's network takes (detect/detector.py ``shrink_size``) once the edge has said what
        that is; whole until then, and for an edge that is gone or not named ("")."""
        load = self.edges.get(edge)
        if load is None or load.input_hw is None:
            return width, height
        return shrink_size(width, height, load.input_hw, load.stretch)

    # The choice
    def full(self, edge: str) -> bool:
        return self.edges[edge].free < self.full_below

    def rank(self, skip_full: bool = True) -> list[str]:
        """Present edges that are not draining (nor full, with ``skip_full``), best first."""
        scored = []
        for edge, load in self.edges.items():
            if load.draining or (skip_full and self.full(edge)):
                continue
            weight = max(load.free, 1e-6)  # a full edge still ranks, last, when all are full
            scored.append((weight / -math.log(pair_uniform(self.robot, edge)), edge))
        return [edge for _, edge in sorted(scored, reverse=True)]

    def pick(self, now: float) -> str | None:
        """The edge for the next frame (None when no edge is present)."""
        cur = self.current
        if cur is not None and cur in self.edges and not self.edges[cur].draining:
            if not self.full(cur) or now - self._since < self.dwell:
                return cur
            free = self.rank()
            if not free:
                return cur  # every edge is full: staying costs nothing
            return self._move(free[0], now)
        order = self.rank() or self.rank(skip_full=False) or sorted(self.edges)
        return self._move(order[0], now) if order else self._move(None, now)

    def _move(self, edge: str | None, now: float) -> str | None:
        if edge != self.current and self.current is not None and edge is not None:
            self.switches += 1
            self._since = now  # the dwell runs from a move, not from the first choice
        self.current = edge
        return edge
