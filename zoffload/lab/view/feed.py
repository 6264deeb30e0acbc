"""The live view's Zenoh side: subscriptions, the map poller, and the one thread that logs.

Subscribed (``<ns>`` the namespace): ``status/<robot>`` and ``status/edge/<edge>`` (1 Hz),
``data/<robot>/scan_ack/<edge>``, ``data/<robot>/scan`` (unless ``scans`` is off: every scan crosses to the
viewer), ``view/<robot>/preview`` (the robot publishes previews only while a viewer listens),
``data/<robot>/detections/<edge>`` and, when ``frames`` is on, ``data/<robot>/frame``. The map comes from
the ``ctrl/<robot>/map/<edge>`` query, every ``map_period`` and only when the map grew, asked of the
edge whose ack came last (the edge that maps the robot), else of every live edge (runtime/maps.py: a
reply naming another edge than asked is a counted drop).

Zenoh callbacks only keep bytes: the newest message per robot and kind (scans, previews, frames,
statuses) or a bounded queue (acks, detections, which the trajectory and the pairing need in
order). One worker decodes and logs them every ``tick``, so a slow viewer never holds Zenoh's
threads, and memory stays bounded whatever arrives. Robots are admitted by an allowlist or up to
``max_robots`` (first come); everything refused or malformed is a counted drop (runtime.drops).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Collection
from functools import partial
from typing import Any

import zenoh

from zoffload.lab.view.recording import Recording
from zoffload.protocol import wire
from zoffload.protocol.keys import ID, Keys
from zoffload.runtime.drops import Drops
from zoffload.runtime.maps import fetch_map
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.view")

QUEUED_MAX = 2048  # acks and detections waiting for the worker (a few seconds of a busy fleet)


class Feed:
    """Feeds a ``Recording`` from a Zenoh session: ``start()``, then ``close()``."""

    def __init__(self, session: zenoh.Session, keys: Keys, recording: Recording,
                 robots: Collection[str] = (), max_robots: int = 16, max_edges: int = 16,
                 map_period: float = 3.0, map_timeout: float = 10.0, scans: bool = True,
                 frames: bool = False, tick: float = 0.1, clock: Callable[[], float] = time.time) -> None:
        self.session, self.keys, self.recording = session, keys, recording
        self.allow = frozenset(robots)
        self.max_robots, self.max_edges = max_robots, max_edges
        self.map_period, self.map_timeout = map_period, map_timeout
        self.scans, self.frames, self.tick, self.clock = scans, frames, tick, clock
        self.drops = Drops(log)
        self.admitted: set[str] = set()
        self.edges: set[str] = set()
        self._latest: dict[tuple[str, str], bytes] = {}
        self._queued: deque[tuple[str, str, bytes]] = deque(maxlen=QUEUED_MAX)
        self._maps: dict[str, wire.MapReply] = {}
        self._map_points: dict[str, tuple[float, float]] = {}  # robot -> (seen, fetched)
        self._mapped_by: dict[str, str] = {}  # robot -> the edge of its latest ack: whom to ask for its map
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._subs: list[Any] = []
        self._threads: list[threading.Thread] = []
        self.logged = 0  # messages logged, for tests and the status line

    # Startup
    def start(self) -> None:
        k, sub = self.keys, self.session.declare_subscriber
        routes: list[tuple[str, Callable[[zenoh.Sample], None]]] = [
            (k.all_robot_status(), self._on_status),
            (k.all_edge_status(), self._on_edge_status),
            (k.answers("scan_ack"), self._queue("ack")),
            (k.all_previews(), self._keep("preview")),
            (k.answers("detections"), self._queue("detections")),
        ]
        if self.scans:
            routes.append((k.all_scans(), self._keep("scan")))
        if self.frames:
            routes.append((k.all_frames(), self._keep("frame")))
        for key, callback in routes:
            self._subs.append(sub(key, self.drops.guard(callback, key)))
        for target, name in ((self._work, "view-log"), (self._poll_maps, "view-maps")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    # Zenoh callbacks: admission, then bytes into the inbox
    def _admit(self, robot: str | None) -> str | None:
        if robot is None:
            self.drops.drop("bad_key", "no robot id in the key")
            return None
        with self._lock:
            if robot in self.admitted:
                return robot
            if (robot in self.allow) if self.allow else len(self.admitted) < self.max_robots:
                self.admitted.add(robot)
                return robot
        self.drops.drop("robot_not_admitted", f"robot {robot!r} (allowlist or max_robots)")
        return None

    def _keep(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def on(sample: zenoh.Sample) -> None:
            robot = self._admit(self.keys.robot_of(str(sample.key_expr)))
            if robot is not None:
                data = sample.payload.to_bytes()
                with self._lock:
                    self._latest[(kind, robot)] = data
        return on

    def _queue(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def on(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            robot = self._admit(self.keys.robot_of(key))
            if robot is not None:
                data = sample.payload.to_bytes()
                edge = self.keys.answering_edge(key) if kind == "ack" else None
                with self._lock:
                    self._queued.append((kind, robot, data))
                    if edge:
                        self._mapped_by[robot] = edge
        return on

    def _on_status(self, sample: zenoh.Sample) -> None:
        chunk = self.keys.last_chunk(str(sample.key_expr))
        robot = self._admit(chunk if ID.match(chunk) else None)
        if robot is not None:
            data = sample.payload.to_bytes()
            with self._lock:
                self._latest[("status", robot)] = data

    def _on_edge_status(self, sample: zenoh.Sample) -> None:
        edge = self.keys.last_chunk(str(sample.key_expr))
        with self._lock:
            if edge not in self.edges and len(self.edges) >= self.max_edges:
                edge = ""
            else:
                self.edges.add(edge)
                self._latest[("edge_status", edge)] = sample.payload.to_bytes()
        if not edge:
            self.drops.drop("edge_not_admitted", "more edges than max_edges")

    # The worker: decode and log, in arrival order for the queued kinds
    def _work(self) -> None:
        while not self._stop.wait(self.tick):
            self.drain()

    def drain(self) -> int:
        """Decode and log what has arrived; returns how many messages were logged."""
        with self._lock:
            queued, self._queued = list(self._queued), deque(maxlen=QUEUED_MAX)
            latest, self._latest = self._latest, {}
            maps, self._maps = self._maps, {}
        now = self.clock()
        n = 0
        # Acks first: a scan that came with its ack is then placed at once
        items = queued + [(kind, robot, data) for (kind, robot), data in latest.items()]
        for kind, robot, data in items:
            n += self._log(kind, robot, data, now)
        for robot, reply in maps.items():
            n += self._call(partial(self.recording.map, reply, now), f"map of {robot}")
        self.logged += n
        return n

    def _log(self, kind: str, robot: str, data: bytes, now: float) -> int:
        rec = self.recording
        try:
            if kind == "edge_status":
                st = wire.decode(data, expect=wire.Status)
                return self._call(lambda: rec.status(st, now), kind) if st.source == "edge" else 0
            msg = wire.decode(data, expect=_TYPES[kind])
        except wire.WireError as exc:
            self.drops.drop("malformed", f"{kind} of {robot}: {exc}")
            return 0
        if getattr(msg, "robot", getattr(msg, "id", None)) != robot:
            self.drops.drop("robot_mismatch", f"{kind} on {robot}'s key names another robot")
            return 0
        if isinstance(msg, wire.Status):
            self._saw_map(robot, msg.values.get("map_points", 0.0))
            return self._call(lambda: rec.status(msg, now), kind) if msg.source == "robot" else 0
        if isinstance(msg, wire.ScanAck):
            self._saw_map(robot, float(msg.map_points))
            return self._call(lambda: rec.ack(msg, now), kind)
        if isinstance(msg, wire.Scan):
            return self._call(lambda: rec.scan(robot, msg.seq, msg.cloud(), now), kind)
        if isinstance(msg, wire.Preview):
            return self._call(lambda: rec.preview(msg, now), kind)
        if isinstance(msg, wire.Frame):
            return self._call(lambda: rec.frame(msg, now), kind)
        if isinstance(msg, wire.Detections):
            return self._call(lambda: rec.detections(msg, now), kind)
        return 0

    def _call(self, fn: Callable[[], None], what: str) -> int:
        try:
            fn()
        except Exception as exc:  # one bad message (or a viewer hiccup) must not stop the view
            self.drops.drop("not_logged", f"{what}: {exc.__class__.__name__}: {exc}")
            return 0
        return 1

    # The map poller: a full map per query, so only when it grew and at most every map_period
    def _saw_map(self, robot: str, points: float) -> None:
        with self._lock:
            _, fetched = self._map_points.get(robot, (0.0, 0.0))
            self._map_points[robot] = (points, fetched)

    def _poll_maps(self) -> None:
        while not self._stop.wait(self.map_period):
            with self._lock:
                due = [r for r, (seen, fetched) in self._map_points.items() if seen > fetched]
            for robot in due:
                if self._stop.is_set():
                    return
                self.fetch_map(robot)

    def fetch_map(self, robot: str) -> bool:
        """Query ``robot``'s map now; True when one came back (it is logged on the next drain)."""
        with self._lock:
            asked_at, _ = self._map_points.get(robot, (0.0, 0.0))
            edge = self._mapped_by.get(robot)
        try:
            msg = fetch_map(self.session, self.keys, robot, [edge] if edge else [], self.drops,
                            self.map_timeout)
        except Exception as exc:  # the session is closing, or the query could not be sent
            log.debug("map query for %s failed: %s", robot, exc)
            return False
        if msg is None:
            return False
        with self._lock:
            self._maps[robot] = msg
            seen, _ = self._map_points.get(robot, (0.0, 0.0))
            self._map_points[robot] = (seen, asked_at)
        return True

    # Shutdown
    def close(self) -> None:
        self._stop.set()
        undeclare(*self._subs)
        self._subs.clear()
        for t in self._threads:
            t.join(timeout=self.map_timeout + 1)
        self._threads.clear()
        self.drain()  # what arrived last still reaches the recording


_TYPES: dict[str, type[wire.Message]] = {
    "status": wire.Status, "ack": wire.ScanAck, "scan": wire.Scan, "preview": wire.Preview,
    "frame": wire.Frame, "detections": wire.Detections,
}
