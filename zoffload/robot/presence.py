"""Which edges are alive and what they say: one watcher for every pipeline of a robot.

Each edge holds ``<ns>/alive/edge/<edge>`` while it runs. The watcher keeps the set of present
edges and tells its listeners about every change, so a pipeline can react the moment the last
edge goes (book frames in flight as lost, fall back to local work) and when one comes back.
It also reads the edges' 1 Hz status (``<ns>/status/edge/*``: capacity, load, draining, the
detector's free share) once for the whole robot and hands each valid one to its status listeners
(the fleet link, the camera); malformed or foreign ones are counted here.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import zenoh

from zoffload.protocol import wire
from zoffload.protocol.intake import edge_status
from zoffload.protocol.keys import ID, Keys
from zoffload.runtime.drops import Drops
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.robot.presence")

MAX_EDGES = 256
# (edge id, present now?, the edges present after this change)
Listener = Callable[[str, bool, frozenset[str]], None]
StatusListener = Callable[[wire.Status], None]


class EdgePresence:
    def __init__(self, keys: Keys) -> None:
        self.keys = keys
        self._edges: set[str] = set()
        self._listeners: list[Listener] = []
        self._status_listeners: list[StatusListener] = []
        self._lock = threading.Lock()
        self._seen = threading.Event()
        self._sub: zenoh.Subscriber | None = None
        self._status_sub: zenoh.Subscriber | None = None
        self.drops = Drops(log)

    def subscribe(self, listener: Listener) -> None:
        """Call ``listener`` on every change (from a Zenoh callback thread: keep it short)."""
        with self._lock:
            self._listeners.append(listener)

    def subscribe_status(self, listener: StatusListener) -> None:
        """Call ``listener`` with every valid edge status (from a Zenoh callback thread)."""
        with self._lock:
            self._status_listeners.append(listener)

    def start(self, session: zenoh.Session) -> None:
        # history=True: tokens declared before this subscriber count as present at once
        self._sub = session.liveliness().declare_subscriber(
            self.keys.any_edge_alive(), self.drops.guard(self._on_token, "edge token"), history=True)
        self._status_sub = session.declare_subscriber(
            self.keys.all_edge_status(), self.drops.guard(self._on_status, "edge status"))

    def stop(self) -> None:
        undeclare(self._sub, self._status_sub)
        self._sub = self._status_sub = None

    def _on_status(self, sample: zenoh.Sample) -> None:
        msg = edge_status(sample, self.keys, self.drops)
        if msg is None:
            return
        with self._lock:
            listeners = list(self._status_listeners)
        for listener in listeners:
            listener(msg)

    def _on_token(self, sample: zenoh.Sample) -> None:
        edge = self.keys.last_chunk(str(sample.key_expr))
        if not ID.match(edge):
            self.drops.drop("bad_token", f"edge token {str(sample.key_expr)[:100]!r}")
            return
        present = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if present and edge not in self._edges and len(self._edges) >= MAX_EDGES:
                # without an ACL anyone may declare edge tokens: the set stays bounded
                self.drops.drop("too_many_edges", f"edge token {edge!r} beyond {MAX_EDGES} edges")
                return
            if present:
                self._edges.add(edge)
                self._seen.set()
            else:
                self._edges.discard(edge)
            now = frozenset(self._edges)
            listeners = list(self._listeners)
        if present:
            log.info("edge %s present", edge)
        else:
            log.warning("edge %s gone%s", edge, "" if now else ": no edge left")
        for listener in listeners:
            listener(edge, present, now)

    @property
    def edges(self) -> frozenset[str]:
        with self._lock:
            return frozenset(self._edges)

    @property
    def any(self) -> bool:
        with self._lock:
            return bool(self._edges)

    def wait(self, timeout: float) -> bool:
        """Block until an edge has been seen (now or before), at most ``timeout`` seconds."""
        return self._seen.wait(timeout)
