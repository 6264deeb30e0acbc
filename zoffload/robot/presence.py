"""Which edges are alive and what they say: one watcher for every pipeline of a robot.

Each edge holds ``<ns>/alive/edge/<edge>`` while it runs. The watcher keeps the set of present
edges and tells its listeners about every change, so a pipeline can react the moment the last
edge goes (book frames in flight as lost, fall back to local work) and when one comes back.
It also reads the edges' 1 Hz status (``<ns>/status/edge/*``: capacity, load, draining, the
detector's free share) once for the whole robot and hands each valid one to its status listeners
(the fleet link, the camera); malformed or foreign ones are counted here.

A "gone" is checked again: a liveliness query for that edge's token 0.25, 1 and 3 s later. A token
still there makes the edge present again (``rechecked``, logged), so one lost or out-of-order token
event (a link closed and reopened within milliseconds, as a frozen edge's does) cannot leave the
robot without its edge for the rest of the run. Changes are applied and told to the listeners one
at a time, so no listener sees an older set of edges after a newer one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import zenoh

from zoffload.protocol import wire
from zoffload.protocol.intake import edge_status
from zoffload.protocol.keys import ID, Keys
from zoffload.runtime.drops import Drops
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.robot.presence")

MAX_EDGES = 256
RECHECK_AFTER = (0.25, 1.0, 3.0)  # s after an edge's token went: is it there after all?
RECHECK_TIMEOUT = 1.0  # s a re-check waits for its answer
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
        self._change = threading.Lock()  # one change at a time, told to the listeners in order
        self._due: dict[str, tuple[float, int]] = {}  # gone edge -> (next re-check, its step)
        self._wake = threading.Condition(self._lock)
        self._session: zenoh.Session | None = None
        self._checker: threading.Thread | None = None
        self._stopping = False
        self.rechecked = 0  # edges found present again by a re-check

    def subscribe(self, listener: Listener) -> None:
        """Call ``listener`` on every change (from a Zenoh callback thread: keep it short)."""
        with self._lock:
            self._listeners.append(listener)

    def subscribe_status(self, listener: StatusListener) -> None:
        """Call ``listener`` with every valid edge status (from a Zenoh callback thread)."""
        with self._lock:
            self._status_listeners.append(listener)

    def start(self, session: zenoh.Session) -> None:
        self._session = session
        self._stopping = False
        self._checker = threading.Thread(target=self._recheck_loop, name="edge-recheck", daemon=True)
        self._checker.start()
        # history=True: tokens declared before this subscriber count as present at once
        self._sub = session.liveliness().declare_subscriber(
            self.keys.any_edge_alive(), self.drops.guard(self._on_token, "edge token"), history=True)
        self._status_sub = session.declare_subscriber(
            self.keys.all_edge_status(), self.drops.guard(self._on_status, "edge status"))

    def stop(self) -> None:
        undeclare(self._sub, self._status_sub)
        self._sub = self._status_sub = None
        with self._wake:
            self._stopping = True
            self._due.clear()
            self._wake.notify()
        if self._checker is not None:
            self._checker.join(RECHECK_TIMEOUT + 1.0)
            self._checker = None

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
        self._apply(edge, sample.kind == zenoh.SampleKind.PUT)

    def _apply(self, edge: str, present: bool, rechecked: bool = False) -> None:
        """One edge's news, applied and told to every listener before the next is (a re-check only
        when it changes something)."""
        with self._change:
            with self._lock:
                if present and edge not in self._edges and len(self._edges) >= MAX_EDGES:
                    # without an ACL anyone may declare edge tokens: the set stays bounded
                    self.drops.drop("too_many_edges", f"edge token {edge!r} beyond {MAX_EDGES} edges")
                    return
                if rechecked and (self._stopping or edge in self._edges):
                    return
                was = edge in self._edges
                if present:
                    self._edges.add(edge)
                    self._seen.set()
                    self._due.pop(edge, None)
                else:
                    self._edges.discard(edge)
                    if was and not self._stopping:  # (only edges that were here: a bounded set)
                        self._due[edge] = (time.monotonic() + RECHECK_AFTER[0], 0)
                        self._wake.notify()
                now = frozenset(self._edges)
                listeners = list(self._listeners)
            if rechecked:
                self.rechecked += 1
                log.warning("edge %s present: its token is there after all (a late 'gone')", edge)
            elif present:
                log.info("edge %s present", edge)
            else:
                log.warning("edge %s gone%s", edge, "" if now else ": no edge left")
            for listener in listeners:
                listener(edge, present, now)

    def _recheck_loop(self) -> None:
        while True:
            with self._wake:
                while not self._stopping and (
                        not self._due or min(t for t, _ in self._due.values()) > time.monotonic()):
                    wait = min((t for t, _ in self._due.values()), default=time.monotonic() + 60.0)
                    self._wake.wait(max(0.0, wait - time.monotonic()))
                if self._stopping:
                    return
                now = time.monotonic()
                due = [(edge, step) for edge, (t, step) in self._due.items() if t <= now]
                for edge, step in due:
                    if step + 1 < len(RECHECK_AFTER):
                        self._due[edge] = (now + RECHECK_AFTER[step + 1] - RECHECK_AFTER[step], step + 1)
                    else:
                        del self._due[edge]
            for edge, _ in due:
                if self._token_there(edge):
                    self._apply(edge, True, rechecked=True)

    def _token_there(self, edge: str) -> bool:
        session = self._session
        if session is None:
            return False
        try:
            replies = session.liveliness().get(self.keys.edge_alive(edge), timeout=RECHECK_TIMEOUT)
            return any(r.ok is not None for r in replies)
        except Exception as exc:  # a closing session: the next change tells
            log.debug("re-check of edge %s failed: %s", edge, exc)
            return False

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
