"""The edge's mapping service: every admitted robot's scans, one bounded KISS-ICP mapper per robot,
one ack per scan.

Inputs:  ``<ns>/data/*/scan`` (wire.Scan).
Outputs: ``<ns>/data/<robot>/scan_ack`` (wire.ScanAck, one per scan, also for scans it had to
         drop or could not register; ``refused`` for robots not admitted, rate-limited).
Queries: ``<ns>/ctrl/<robot>/map`` (wire.MapReply: the robot's registered map and the poses in
         memory; one reply built at a time, others answered "busy").
On eviction and stop: with a ``map_dir``, the robot's map, trajectory and counters (edge/export.py).

The Zenoh callback only stamps, checks and queues; registration runs on a fixed pool of worker
threads serving the robots' queues in turn, one scan per turn, so a slow mapper never blocks
reception, inter-arrival T stays an arrival-time measure, and the thread count does not depend on
how many robots there are. A robot is held by at most one worker at a time: its scans are
registered in order, never concurrently. Each robot keeps at most ``queue`` waiting scans; the
oldest is acked ``dropped`` when a newer one comes.

Every sample is counted once: ``samples`` = ``received`` + the drops by reason (``bad_key``,
``refused``, ``malformed``, ``foreign``, ``callback_error``: runtime/drops.py).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import zenoh

from zoffload.edge.admission import Admission
from zoffload.edge.export import RobotFiles
from zoffload.edge.recipe import Spill
from zoffload.mapping.mapper import Registration
from zoffload.protocol import wire
from zoffload.protocol.intake import decode_from_robot, robot_in_key
from zoffload.protocol.keys import Keys
from zoffload.runtime.drops import Drops
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.edge.mapping")

GENERATIONS_KEPT = 4096  # robot ids whose session count is remembered (for export file names)


class Mapper(Protocol):
    """What the service needs of a robot's mapper: ``recipe.BoundedMapper``, or a stand-in."""

    @property
    def map_points(self) -> int: ...

    @property
    def scans(self) -> int: ...

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration: ...

    def map_cloud(self) -> np.ndarray: ...

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]: ...


class MapperFactory(Protocol):
    """Makes a robot's mapper from its first scan: ``recipe.MapperRecipe``, or a stand-in."""

    def warm_up(self) -> None: ...

    def __call__(self, scan: wire.Scan, spill: Spill | None = None) -> Mapper: ...


@dataclass
class _Queued:
    scan: wire.Scan
    arrival: float  # edge monotonic clock
    interarrival: float


@dataclass
class RobotSession:
    """Per-robot state on the edge: the mapper (made on the first scan), the queue, counters.
    ``scheduled``: in the ready queue or held by a worker; ``closed``: evicted."""

    robot: str
    ack_pub: zenoh.Publisher
    files: RobotFiles
    mapper: Mapper | None = None
    queue: deque[_Queued] = field(default_factory=deque)
    last_arrival: float | None = None
    counters: Counter[str] = field(default_factory=Counter)
    scheduled: bool = False
    closed: bool = False


class MappingService:
    """Maps every admitted robot that sends scans. ``make_mapper`` None: receive and ack only (link
    checks, stream benchmarks), nothing decoded or registered."""

    name = "mapping"

    def __init__(self, keys: Keys, make_mapper: MapperFactory | None, queue: int = 2,
                 map_dir: Path | None = None, map_format: str = "ply", edge_id: str = "",
                 workers: int | None = None, admission: Admission | None = None,
                 limits: wire.Limits = wire.DEFAULT_LIMITS) -> None:
        self.keys = keys
        self.make_mapper = make_mapper
        self.queue_len = queue
        self.map_dir = map_dir
        self.map_format = map_format
        self.edge_id = edge_id
        self.admission = admission or Admission()
        self.limits = limits
        self.robots: dict[str, RobotSession] = {}
        self.counters: Counter[str] = Counter()
        self.drops = Drops(log)
        self._generations: OrderedDict[str, int] = OrderedDict()
        self._lock = threading.Condition()  # robots, queues, the ready queue and counters
        self._ready: deque[RobotSession] = deque()
        self._stop = threading.Event()
        self._map_reply = threading.Semaphore(1)
        self._workers = [threading.Thread(target=self._work, name=f"mapper-{i}", daemon=True)
                         for i in range(workers or os.cpu_count() or 1)]
        self._session: zenoh.Session | None = None
        self._sub: zenoh.Subscriber[None] | None = None
        self._map_q: zenoh.Queryable[None] | None = None

    def start(self, session: zenoh.Session) -> None:
        if self.make_mapper is not None:
            self.make_mapper.warm_up()
        self._session = session
        for w in self._workers:
            w.start()
        self._sub = session.declare_subscriber(self.keys.all_scans(), self.drops.guard(self._on_scan, "scan"))
        self._map_q = session.declare_queryable(self.keys.all_maps(),
                                                self.drops.guard(self._on_map_query, "map query"))

    def stop(self) -> None:
        # No new scans first: one queued after the workers stop would never be acked. The map
        # queryable and the ack publishers go with the session, so maps are served to the end.
        undeclare(self._sub)
        self._sub = None
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        for w in self._workers:
            if w.is_alive():
                w.join(timeout=5)
        if self.map_dir:
            for rs in list(self.robots.values()):
                self._export(rs)
        log.info("mapping stopped: %s, drops %s", dict(self.counters), self.drops.snapshot())

    def status(self) -> dict[str, float]:
        with self._lock:
            values = {k: float(v) for k, v in self.counters.items()}
            robots = list(self.robots.values())
        drops = self.drops.snapshot()
        values.update({f"drop.{k}": float(v) for k, v in drops.items()})
        values["drops"] = float(sum(drops.values()))
        values["malformed"] = float(drops.get("malformed", 0))
        values["robots"] = float(len(robots))
        values["workers"] = float(sum(w.is_alive() for w in self._workers))
        for rs in robots:
            values[f"{rs.robot}.map_points"] = float(rs.mapper.map_points if rs.mapper else 0)
            values[f"{rs.robot}.queue"] = float(len(rs.queue))
            overflow = getattr(rs.mapper, "map_overflow", 0)
            if overflow:
                values[f"{rs.robot}.map_overflow"] = float(overflow)
        return values

    # Reception (Zenoh callback threads: stamp, check, queue; nothing slow)
    def _on_scan(self, sample: zenoh.Sample) -> None:
        arrival = time.monotonic()
        with self._lock:
            self.counters["samples"] += 1
        robot = robot_in_key(sample, self.keys, self.drops, "scan")
        if robot is None:
            return
        if not self.admission.admit(robot, arrival):
            self._refuse(sample, robot)
            return
        scan = decode_from_robot(sample, wire.Scan, robot, self.drops, "scan", self.limits)
        if scan is None:
            return
        if scan.coding != "f32" and scan.n_points > self.limits.max_points:  # before it waits in a queue
            self.drops.drop("malformed", f"scan of {scan.n_points} points (at most {self.limits.max_points})")
            return
        overflow: list[_Queued] = []
        with self._lock:
            rs = self.robots.get(robot) or self._new_robot(robot)
            interarrival = float("nan") if rs.last_arrival is None else arrival - rs.last_arrival
            rs.last_arrival = arrival
            rs.counters["received"] += 1
            self.counters["received"] += 1
            rs.queue.append(_Queued(scan, arrival, interarrival))
            while len(rs.queue) > self.queue_len:
                overflow.append(rs.queue.popleft())
            if not rs.scheduled:
                rs.scheduled = True
                self._ready.append(rs)
                self._lock.notify()
            for _ in overflow:
                rs.counters["dropped"] += 1
                self.counters["dropped"] += 1
        for q in overflow:
            self._ack(rs, q, status="dropped", detail="edge mapper overloaded")

    def _refuse(self, sample: zenoh.Sample, robot: str) -> None:
        """A scan from a robot not admitted: counted; answered while the refusal budget allows."""
        why = self.admission.why_refused(robot)
        self.drops.drop("refused", why)
        if self._session is None or not self.admission.answer_refusal():
            return
        try:
            scan = wire.decode(sample.payload.to_bytes(), expect=wire.Scan, limits=self.limits)
        except wire.WireError:
            return  # already counted as refused; nothing to answer
        if scan.robot != robot:
            return
        ack = _ack_message(robot, scan.seq, scan.send_stamp, "refused", self.edge_id, scan.epoch, detail=why)
        # No per-id publisher: refused ids must not cost the edge any state
        self._session.put(self.keys.scan_ack(robot), wire.encode(ack),
                          congestion_control=zenoh.CongestionControl.DROP, express=True)

    def _new_robot(self, robot: str) -> RobotSession:
        """Called with the lock held, for an admitted robot without a session."""
        assert self._session is not None, "scans arrive only after start()"
        pub = self._session.declare_publisher(
            self.keys.scan_ack(robot), congestion_control=zenoh.CongestionControl.DROP, express=True)
        generation = self._generations.pop(robot, -1) + 1
        self._generations[robot] = generation
        while len(self._generations) > GENERATIONS_KEPT:
            self._generations.popitem(last=False)
        rs = RobotSession(robot, pub, RobotFiles(self.map_dir, robot, generation, self.map_format))
        self.robots[robot] = rs
        log.info("new robot %s%s", robot, f" (session {generation})" if generation else "")
        return rs

    # Registration (the worker pool)
    def _work(self) -> None:
        while True:
            with self._lock:
                while not self._ready and not self._stop.is_set():
                    self._lock.wait(0.2)
                if self._stop.is_set():
                    return
                rs = self._ready.popleft()
                item = rs.queue.popleft() if rs.queue else None
            if item is not None:
                self._register(rs, item)
            with self._lock:
                if rs.queue and not rs.closed:
                    self._ready.append(rs)  # its next scan waits behind the other robots' turns
                    self._lock.notify()
                    continue
                rs.scheduled = False
                closed = rs.closed
            if closed:
                self._close(rs)

    def _register(self, rs: RobotSession, item: _Queued) -> None:
        scan = item.scan
        if self.make_mapper is None:
            self._count(rs, "received_only")
            self._ack(rs, item, status="ok", detail="mapping disabled", queue_time=0.0)
            return
        try:
            if rs.mapper is None:
                rs.mapper = self.make_mapper(scan, rs.files.spill)
            # Decodes a coded payload (WireError if it is corrupt); the per-point times, when the
            # scan carries them, deskew it if the mapper was made to
            points, times = scan.cloud_and_times(self.limits)
            if len(points) == 0:  # (finite: the codec checks raw points, coded ones are by construction)
                raise ValueError("scan has no points")
            start = time.monotonic()
            reg = rs.mapper.register(scan.seq, points, times)
        except Exception as exc:  # a bad scan must not take the worker down
            self._count(rs, "errors")
            if rs.counters["errors"] <= 10 or rs.counters["errors"] % 1000 == 0:
                log.warning("robot %s scan %d: registration failed (%d so far): %s", rs.robot, scan.seq,
                            rs.counters["errors"], str(exc)[:200])
            self._ack(rs, item, status="error", detail=str(exc)[:200])
            return
        self._count(rs, "registered")
        self._ack(rs, item, status="ok", queue_time=start - item.arrival, reg=reg)

    def _count(self, rs: RobotSession, what: str) -> None:
        with self._lock:
            rs.counters[what] += 1
            self.counters[what] += 1

    def _ack(self, rs: RobotSession, item: _Queued, status: str, detail: str = "",
             queue_time: float = float("nan"), reg: Registration | None = None) -> None:
        scan = item.scan
        ack = _ack_message(rs.robot, scan.seq, scan.send_stamp, status, self.edge_id, scan.epoch, detail,
                           item.interarrival, queue_time, reg,
                           reg.map_points if reg else (rs.mapper.map_points if rs.mapper else 0))
        try:
            rs.ack_pub.put(wire.encode(ack))
        except Exception as exc:  # the session is closing, or the robot was evicted meanwhile
            log.debug("ack not published: %s", exc)
            return
        with self._lock:
            self.counters["acks"] += 1

    # Eviction (the server's housekeeping, for robots the admission expired)
    def evict(self, robot: str) -> None:
        """Drop the robot's state, its map exported first; a scan it sends later starts anew."""
        with self._lock:
            rs = self.robots.pop(robot, None)
            if rs is None:
                return
            rs.closed = True
            busy = rs.scheduled  # a worker holds it: that worker closes it when done
        if not busy:
            self._close(rs)

    def _close(self, rs: RobotSession) -> None:
        for item in list(rs.queue):
            self._ack(rs, item, status="dropped", detail="robot evicted from the edge")
        rs.queue.clear()
        if self.map_dir:
            self._export(rs)
        undeclare(rs.ack_pub)
        with self._lock:
            self.counters["evicted"] += 1
        log.info("robot %s evicted after %d scans", rs.robot, rs.counters["received"])

    # Map queries and export
    def _on_map_query(self, query: zenoh.Query) -> None:
        robot = self.keys.robot_of(str(query.key_expr))
        with self._lock:
            rs = self.robots.get(robot) if robot else None
        if rs is None or rs.mapper is None:
            query.reply_err(f"no map for robot {robot!r}".encode())
            return
        if not self._map_reply.acquire(blocking=False):
            query.reply_err(b"busy: another map reply is being built; ask again")
            return
        try:
            seqs, poses = rs.mapper.trajectory()
            reply = wire.MapReply(robot=rs.robot, scans=rs.mapper.scans, points=rs.mapper.map_cloud(),
                                  seqs=seqs, poses=poses)
            query.reply(self.keys.map(rs.robot), wire.encode(reply))
        finally:
            self._map_reply.release()

    def _export(self, rs: RobotSession) -> Path | None:
        """Export one robot's map; a failure is logged, so the other robots' maps still get written."""
        if rs.mapper is None:
            return None
        try:
            path = rs.files.export(rs.mapper, {k: int(v) for k, v in rs.counters.items()})
        except Exception as exc:  # a full disk, an unwritable folder: say so, keep going
            log.error("map of %s not written: %s", rs.robot, exc)
            return None
        if path is not None:
            log.info("map of %s written to %s", rs.robot, path)
        return path

    def export_map(self, robot: str) -> Path | None:
        """Write the robot's map, trajectory and counters to ``map_dir``; None without a map."""
        rs = self.robots.get(robot)
        return self._export(rs) if rs is not None else None


def _ack_message(robot: str, seq: int, send_stamp: float, status: str, edge: str, epoch: int,
                 detail: str = "", interarrival: float = float("nan"), queue_time: float = float("nan"),
                 reg: Registration | None = None, map_points: int = 0) -> wire.ScanAck:
    nan = float("nan")

    def duration(x: float) -> float:  # what the codec accepts of a duration; NaN = not measured
        return x if 0.0 <= x <= 3600.0 else nan

    pose = reg.pose if reg is not None and np.isfinite(reg.pose).all() else np.full((4, 4), nan)
    return wire.ScanAck(
        robot=robot, seq=seq, send_stamp=send_stamp, status=status, interarrival=duration(interarrival),
        queue_time=duration(queue_time), proc_time=duration(reg.proc_time) if reg else nan,
        icp_time=duration(reg.icp_time) if reg else nan, map_points=map_points,
        keypoints=reg.keypoints if reg else 0, sigma=reg.sigma if reg and 0 <= reg.sigma <= 1e6 else nan,
        detail=detail, pose=pose, epoch=epoch, edge=edge)
