"""Which edges are alive and what they say: one watcher for every pipeline of a robot.

Each edge holds ``<ns>/alive/edge/<edge>`` while it runs. The watcher keeps the set of present
edges and tells its listeners about every change, so a pipeline can react the moment the last
edge goes (book frames in flight as lost, fall back to local work) and when one comes back.
It also reads the edges' 1 Hz status (``<ns>/status/edge/*``: capacity, load, draining, the
detector's free share) once for the whole robot and hands each valid one to its status listeners
(the fleet link, the camera); malformed or foreign ones are counted here.

A "gone" is checked again: one liveliness query for the edges' tokens 0.25, 1 and 3 s later (one
query for every edge due then). A token still there makes the edge present again (``rechecked``,
logged), so one lost or out-of-order token event (a link closed and reopened within milliseconds,
as a frozen edge's does) cannot leave the robot without its edge for the rest of the run; a later
check that misses it takes it away again, an answer older than the edge's latest token event is
not applied, and the checks under way are bounded (``MAX_EDGES``, the overflow counted). Changes
are applied and told to the listeners one at a time, so no listener sees an older set of edges
after a newer one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from zoffload.protocol import wire
from zoffload.protocol.intake import edge_status, edge_token
from zoffload.protocol.keys import Keys
from zoffload.runtime.drops import Drops
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.robot.presence")

MAX_EDGES = 256
RECHECK_AFTER = (0.25, 1.0, 3.0)  # s after an edge's token went: is it there after all?
RECHECK_TIMEOUT = 1.0  # s a re-check waits for its answer
# (edge id, present now?, the edges present after this change)
Listener = Callable[[str, bool, frozenset[str]], None]
StatusListener = Callable[[wire.Status], None]


@dataclass
class _Check:
    """The re-checks of one edge whose token went: ``RECHECK_AFTER`` after ``gone``."""
    gone: float
    step: int = 0
    events: int = 0  # token events for this edge since: a re-check answered across one is stale
    revived: bool = False  # a re-check found the token; the subscriber has not confirmed it yet

    def due(self) -> float:
        """When the next check is due (the last step's until it is applied)."""
        return self.gone + RECHECK_AFTER[min(self.step, len(RECHECK_AFTER) - 1)]


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
        # One change at a time, told to the listeners in order. Not re-entrant: a listener must not
        # cause a token event on its own thread (none does: they only update state)
        self._change = threading.Lock()
        self._due: dict[str, _Check] = {}  # edges whose token went, being re-checked
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
        if self._checker is not None:
            raise RuntimeError("EdgePresence.start: already started")
        self._session = session
        self._stopping = False
        # history=True: tokens declared before this subscriber count as present at once
        self._sub = session.liveliness().declare_subscriber(
            self.keys.any_edge_alive(), self.drops.guard(self._on_token, "edge token"), history=True)
        self._status_sub = session.declare_subscriber(
            self.keys.all_edge_status(), self.drops.guard(self._on_status, "edge status"))
        self._checker = threading.Thread(target=self._recheck_loop, name="edge-recheck", daemon=True)
        self._checker.start()

    def stop(self) -> None:
        undeclare(self._sub, self._status_sub)
        self._sub = self._status_sub = None
        with self._wake:
            self._stopping = True
            self._session = None
            self._due.clear()
            self._wake.notify_all()
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
        edge = edge_token(sample, self.keys, self.drops)
        if edge is None:
            return
        present = sample.kind == zenoh.SampleKind.PUT
        with self._change:
            with self._lock:
                if present and edge not in self._edges and len(self._edges) >= MAX_EDGES:
                    # without an ACL anyone may declare edge tokens: the set stays bounded
                    self.drops.drop("too_many_edges", f"edge token {edge!r} beyond {MAX_EDGES} edges")
                    return
                was = edge in self._edges
                check = self._due.get(edge)
                if check is not None:
                    check.events += 1  # a re-check under way for it answers an older state
                if present:
                    self._edges.add(edge)
                    self._seen.set()
                    self._due.pop(edge, None)  # the subscriber confirms it
                else:
                    self._edges.discard(edge)
                    self._schedule(edge, was, check)
                now = frozenset(self._edges)
                listeners = list(self._listeners)
            if present:
                log.info("edge %s present", edge)
            else:
                log.warning("edge %s gone%s", edge, "" if now else ": no edge left")
            self._tell(listeners, edge, present, now)

    def _schedule(self, edge: str, was: bool, check: _Check | None) -> None:
        """(Under the lock.) Re-check an edge whose token went: one that was here, or one being
        re-checked already (its checks start over); a bounded set."""
        if self._stopping or not (was or check is not None):
            return
        if check is None and len(self._due) >= MAX_EDGES:
            self.drops.drop("too_many_rechecks", f"edge {edge!r}: {MAX_EDGES} re-checks under way")
            return
        events = check.events if check is not None else 0
        self._due[edge] = _Check(gone=time.monotonic(), events=events)
        self._wake.notify_all()

    @staticmethod
    def _tell(listeners: list[Listener], edge: str, present: bool, now: frozenset[str]) -> None:
        for listener in listeners:
            listener(edge, present, now)

    def _recheck_loop(self) -> None:
        last_step = len(RECHECK_AFTER) - 1
        while True:
            with self._wake:
                while not self._stopping:
                    due_at = min((c.due() for c in self._due.values()), default=None)
                    if due_at is not None and due_at <= time.monotonic():
                        break
                    self._wake.wait(60.0 if due_at is None else due_at - time.monotonic())
                if self._stopping:
                    return
                now = time.monotonic()
                due = [(edge, c.events, c.step >= last_step) for edge, c in self._due.items()
                       if c.due() <= now]
                for edge, _, _ in due:
                    self._due[edge].step += 1  # (the last step's check stays until it is applied)
                session = self._session
            found = self._tokens_there(session, {edge for edge, _, _ in due})
            for edge, events, last in due:
                try:
                    self._rechecked(edge, None if found is None else edge in found, events, last)
                except Exception as exc:  # a listener's bug must not end the re-checks
                    self.drops.drop("recheck_error", f"{type(exc).__name__}: {exc}")

    def _rechecked(self, edge: str, there: bool | None, events: int, last: bool) -> None:
        """Apply one re-check's answer (None: the query failed), unless a token event for the edge
        came meanwhile."""
        with self._change:
            with self._lock:
                check = self._due.get(edge)
                if self._stopping or check is None or check.events != events:
                    return  # a token event came while it was asked: that event is newer
                if last:
                    del self._due[edge]
                change = None
                if there and edge not in self._edges and len(self._edges) < MAX_EDGES:
                    self._edges.add(edge)
                    check.revived = True
                    self.rechecked += 1
                    change = True
                elif there is False and edge in self._edges and check.revived:
                    self._edges.discard(edge)  # revived by an earlier check, gone again by this one
                    check.revived = False
                    change = False
                if change is None:
                    return
                now = frozenset(self._edges)
                listeners = list(self._listeners)
            if change:
                log.warning("edge %s present: its token is there after all (a late 'gone')", edge)
            else:
                log.warning("edge %s gone: its token is not there (re-check)", edge)
            self._tell(listeners, edge, change, now)

    def _tokens_there(self, session: zenoh.Session | None, edges: set[str]) -> set[str] | None:
        """Which of ``edges`` hold a token now: one query for every edge token (any number due);
        None when it could not be asked."""
        if session is None or not edges:
            return None
        found: set[str] = set()
        try:
            for reply in session.liveliness().get(self.keys.any_edge_alive(), timeout=RECHECK_TIMEOUT):
                if reply.ok is not None:
                    edge = self.keys.last_chunk(str(reply.ok.key_expr))
                    if edge in edges:
                        found.add(edge)
        except Exception as exc:  # a closing session: the next change tells
            log.debug("re-check of edges %s failed: %s", sorted(edges)[:5], exc)
            return None
        return found

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
