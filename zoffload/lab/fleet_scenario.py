"""The fleet experiment's script: edge events over time and link traces per robot (pure parsing).

Events, comma-separated, ``ACTION:EDGE@SECONDS`` (seconds after every robot is up):

* ``kill``: SIGKILL, the edge vanishes without a goodbye (its connection closes, its token goes);
* ``drain``: SIGTERM, the planned hand-over (final checkpoints, then the edge stops);
* ``restart``: start the edge again with the same id (after a kill or a drain).

Traces, ``TRACE`` (every robot) or ``ROBOT=TRACE`` (that robot; it wins over the former), each a
shipped trace name or a CSV file: the robot's link to the router goes through the link emulator.

Edge CPU, ``CORES`` (every edge) or ``EDGE=CORES`` (that edge; it wins), comma-separated: each
edge process (restarts too) runs under a CFS quota of that many cores, as a container's ``cpus``
would hold it; the way to make one edge over capacity on a machine the robots share.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

ACTIONS = ("kill", "drain", "restart")
_EVENT = re.compile(r"^(kill|drain|restart):([A-Za-z0-9_-]+)@([0-9]+(?:\.[0-9]*)?)$")


class ScenarioError(ValueError):
    """An events or traces script that cannot be run; the message says which item and why."""


@dataclass(frozen=True)
class EdgeEvent:
    action: str  # one of ACTIONS
    edge: str
    at: float  # seconds after every robot is up

    def label(self) -> str:
        return f"{self.action}:{self.edge}@{self.at:g}"


def edge_ids(n: int) -> list[str]:
    return [f"edge{i}" for i in range(1, n + 1)]


def robot_ids(n: int) -> list[str]:
    return [f"robot{i}" for i in range(1, n + 1)]


def parse_events(text: str | None, edges: Iterable[str]) -> list[EdgeEvent]:
    """The events in time order, checked against the edges and against each other: an edge is
    killed or drained only while it runs and restarted only after it stopped. Every edge may be
    down at once: that is what the robots' local odometry is for."""
    known = list(edges)
    events: list[EdgeEvent] = []
    for item in (text or "").split(","):
        item = item.strip()
        if not item:
            continue
        m = _EVENT.match(item)
        if not m:
            raise ScenarioError(f"event {item!r}: expected ACTION:EDGE@SECONDS with ACTION one of "
                                f"{', '.join(ACTIONS)} (e.g. kill:edge1@5)")
        action, edge, at = m.group(1), m.group(2), float(m.group(3))
        if edge not in known:
            raise ScenarioError(f"event {item!r}: no edge {edge!r} in this run ({', '.join(known)})")
        events.append(EdgeEvent(action, edge, at))
    events.sort(key=lambda e: e.at)  # stable: same-time events keep their written order
    running = dict.fromkeys(known, True)
    for e in events:
        if e.action == "restart" and running[e.edge]:
            raise ScenarioError(f"event {e.label()}: {e.edge} is running then (kill or drain it first)")
        if e.action != "restart" and not running[e.edge]:
            raise ScenarioError(f"event {e.label()}: {e.edge} is not running then (restart it first)")
        running[e.edge] = e.action == "restart"
    return events


def parse_traces(items: Iterable[str] | None, robots: Iterable[str]) -> dict[str, str]:
    """Robot id -> trace, for the robots that get a link emulator."""
    ids = list(robots)
    every: str | None = None
    own: dict[str, str] = {}
    for item in items or ():
        robot, sep, trace = item.partition("=")
        if not sep:
            every = item.strip()
            continue
        robot, trace = robot.strip(), trace.strip()
        if robot not in ids:
            raise ScenarioError(f"trace {item!r}: no robot {robot!r} in this run ({', '.join(ids)})")
        if not trace:
            raise ScenarioError(f"trace {item!r}: name a trace after '='")
        own[robot] = trace
    out = dict.fromkeys(ids, every) if every else {}
    out.update(own)
    return {r: t for r, t in out.items() if t and t != "none"}


def parse_edge_cpu(text: str | None, edges: Iterable[str]) -> dict[str, float]:
    """Edge id -> cores, for the edges under a quota."""
    ids = list(edges)
    every: float | None = None
    own: dict[str, float] = {}
    for item in (text or "").split(","):
        item = item.strip()
        if not item:
            continue
        edge, sep, value = item.rpartition("=")
        try:
            cores = float(value)
        except ValueError:
            raise ScenarioError(f"edge CPU {item!r}: expected CORES or EDGE=CORES (e.g. edge1=0.5)") from None
        if not 0.01 <= cores <= 1024:
            raise ScenarioError(f"edge CPU {item!r}: cores must be between 0.01 and 1024")
        if (edge.strip() if sep else "") in own or (not sep and every is not None):
            raise ScenarioError(f"edge CPU {item!r}: given twice")
        if not sep:
            every = cores
        elif edge.strip() not in ids:
            raise ScenarioError(f"edge CPU {item!r}: no edge {edge.strip()!r} in this run ({', '.join(ids)})")
        else:
            own[edge.strip()] = cores
    out = dict.fromkeys(ids, every) if every is not None else {}
    out.update(own)
    return {e: c for e, c in out.items() if c is not None}


def kills(events: Iterable[EdgeEvent]) -> int:
    return sum(e.action == "kill" for e in events)
