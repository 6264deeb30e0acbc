"""The edge's mapping service: every robot's scans, one KISS-ICP mapper per robot, one ack per scan.

Inputs:  ``<ns>/data/*/scan`` (wire.Scan).
Outputs: ``<ns>/data/<robot>/scan_ack`` (wire.ScanAck, one per scan, also for scans it had to
         drop or could not register).
Queries: ``<ns>/ctrl/<robot>/map`` (wire.MapReply: the robot's registered map and trajectory).
On stop: with a ``map_dir``, every robot's ``<robot>_map.<fmt>``, ``<robot>_trajectory.npz`` and
         ``<robot>_edge.json`` (its counters) are written there.

The Zenoh callback only stamps, decodes and queues; registration runs on one worker thread per
robot, so a slow mapper never blocks reception and inter-arrival T stays an arrival-time measure.
Each robot keeps at most ``queue`` waiting scans; the oldest is acked ``dropped`` when a newer one
comes.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import zenoh

from zoffload.mapping import voxel, voxelset
from zoffload.mapping.export import write_point_cloud
from zoffload.mapping.mapper import Registration, RobotMapper, load_kiss_icp, mapper_voxel_size
from zoffload.protocol import wire
from zoffload.protocol.intake import decode_from_robot
from zoffload.protocol.keys import Keys

log = logging.getLogger("zoffload.edge.mapping")


class Mapper(Protocol):
    """What the service needs of a robot's mapper: ``RobotMapper``, or a stand-in in tests."""

    @property
    def map_points(self) -> int: ...

    def register(self, seq: int, points: np.ndarray) -> Registration: ...

    def map_cloud(self) -> np.ndarray: ...

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]: ...


class MapperFactory(Protocol):
    """Makes a robot's mapper from its first scan: ``MapperRecipe``, or a stand-in in tests."""

    def warm_up(self) -> None: ...

    def __call__(self, scan: wire.Scan) -> Mapper: ...


@dataclass(frozen=True)
class MapperRecipe:
    """Builds a robot's KISS-ICP on its first scan: the robot's sensor range and voxel bound, sent
    with every scan, fill what the edge's settings leave open (see ``mapper_voxel_size``)."""

    voxel_size: float | None = None
    min_range: float = 0.0
    max_range: float | None = None
    max_points_per_voxel: int = 20
    deskew: bool = False
    map_resolution: float = 0.1

    def warm_up(self) -> None:
        # Compile the map kernels and load KISS-ICP now, not while the first scans queue up
        voxel.warmup()
        voxelset.warmup()
        load_kiss_icp()

    def __call__(self, scan: wire.Scan) -> RobotMapper:
        max_range = self.max_range or scan.max_range
        voxel = mapper_voxel_size(max_range, scan.voxel_max, self.voxel_size)
        log.info("robot %s: KISS-ICP voxel %.3f m, max range %.1f m (robot voxel_max %.3f)",
                 scan.robot, voxel, max_range, scan.voxel_max)
        return RobotMapper(voxel_size=voxel, max_range=max_range, min_range=self.min_range,
                           max_points_per_voxel=self.max_points_per_voxel, deskew=self.deskew,
                           map_resolution=self.map_resolution)


@dataclass
class _Queued:
    scan: wire.Scan
    arrival: float  # edge monotonic clock
    interarrival: float


@dataclass
class RobotSession:
    """Per-robot state on the edge: the mapper (made on the first scan), the queue, counters."""

    robot: str
    ack_pub: zenoh.Publisher
    mapper: Mapper | None = None
    queue: deque[_Queued] = field(default_factory=deque)
    cond: threading.Condition = field(default_factory=threading.Condition)
    last_arrival: float | None = None
    counters: Counter[str] = field(default_factory=Counter)
    worker: threading.Thread | None = None


class MappingService:
    """Maps every robot that sends scans. ``make_mapper`` None: receive and ack only (link checks,
    stream benchmarks), nothing decoded or registered."""

    name = "mapping"

    def __init__(self, keys: Keys, make_mapper: MapperFactory | None, queue: int = 2,
                 map_dir: Path | None = None, map_format: str = "ply") -> None:
        self.keys = keys
        self.make_mapper = make_mapper
        self.queue_len = queue
        self.map_dir = map_dir
        self.map_format = map_format
        self.robots: dict[str, RobotSession] = {}
        self.counters: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._session: zenoh.Session | None = None
        self._sub: zenoh.Subscriber[None] | None = None
        self._map_q: zenoh.Queryable[None] | None = None

    def start(self, session: zenoh.Session) -> None:
        if self.make_mapper is not None:
            self.make_mapper.warm_up()
        self._session = session
        self._sub = session.declare_subscriber(self.keys.all_scans(), self._on_scan)
        self._map_q = session.declare_queryable(self.keys.all_maps(), self._on_map_query)

    def stop(self) -> None:
        # No new scans first: one queued after the workers stop would never be acked. The map
        # queryable and the ack publishers go with the session, so maps are served to the end.
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        self._stop.set()
        for rs in list(self.robots.values()):
            with rs.cond:
                rs.cond.notify_all()
            if rs.worker:
                rs.worker.join(timeout=5)
        if self.map_dir:
            for rid in list(self.robots):
                path = self.export_map(rid, self.map_dir, self.map_format)
                if path:
                    log.info("map of %s written to %s", rid, path)
        log.info("mapping stopped: %s", dict(self.counters))

    def status(self) -> dict[str, float]:
        values = {k: float(v) for k, v in list(self.counters.items())}
        values["robots"] = float(len(self.robots))
        for rid, rs in list(self.robots.items()):
            values[f"{rid}.map_points"] = float(rs.mapper.map_points if rs.mapper else 0)
            values[f"{rid}.queue"] = float(len(rs.queue))
        return values

    # Reception (Zenoh callback thread: stamp, decode, queue; nothing slow)
    def _on_scan(self, sample: zenoh.Sample) -> None:
        arrival = time.monotonic()
        scan = decode_from_robot(sample, wire.Scan, self.keys, self.counters, log, "scan")
        if scan is None:
            return
        rs = self._robot(scan.robot)
        interarrival = float("nan") if rs.last_arrival is None else arrival - rs.last_arrival
        rs.last_arrival = arrival
        rs.counters["received"] += 1
        self.counters["received"] += 1
        with rs.cond:
            rs.queue.append(_Queued(scan, arrival, interarrival))
            overflow = []
            while len(rs.queue) > self.queue_len:
                overflow.append(rs.queue.popleft())
            rs.cond.notify()
        for q in overflow:
            rs.counters["dropped"] += 1
            self.counters["dropped"] += 1
            self._ack(rs, q, status="dropped", detail="edge mapper overloaded")

    def _robot(self, robot: str) -> RobotSession:
        with self._lock:
            rs = self.robots.get(robot)
            if rs is None:
                assert self._session is not None, "scans arrive only after start()"
                pub = self._session.declare_publisher(
                    self.keys.scan_ack(robot), congestion_control=zenoh.CongestionControl.DROP,
                    express=True,
                )
                rs = RobotSession(robot, pub)
                rs.worker = threading.Thread(target=self._work, args=(rs,), name=f"map-{robot}",
                                             daemon=True)
                self.robots[robot] = rs
                rs.worker.start()
                log.info("new robot %s", robot)
            return rs

    # Registration (one worker per robot)
    def _work(self, rs: RobotSession) -> None:
        while not self._stop.is_set():
            with rs.cond:
                while not rs.queue and not self._stop.is_set():
                    rs.cond.wait(0.2)
                if not rs.queue:
                    continue
                item = rs.queue.popleft()
            self._register(rs, item)

    def _register(self, rs: RobotSession, item: _Queued) -> None:
        scan = item.scan
        if self.make_mapper is None:
            rs.counters["received_only"] += 1
            self._ack(rs, item, status="ok", detail="mapping disabled", queue_time=0.0)
            return
        try:
            if rs.mapper is None:
                rs.mapper = self.make_mapper(scan)
            points = scan.cloud()  # decodes a coded payload; WireError if it is corrupt
            if len(points) == 0 or not np.isfinite(points).all():
                raise ValueError("scan has no points or non-finite points")
            start = time.monotonic()
            reg = rs.mapper.register(scan.seq, points)
        except Exception as exc:  # a bad scan must not take the worker down
            rs.counters["errors"] += 1
            self.counters["errors"] += 1
            log.warning("robot %s scan %d: registration failed: %s", rs.robot, scan.seq, exc)
            self._ack(rs, item, status="error", detail=str(exc)[:200])
            return
        rs.counters["registered"] += 1
        self.counters["registered"] += 1
        self._ack(rs, item, status="ok", queue_time=start - item.arrival, reg=reg)

    def _ack(self, rs: RobotSession, item: _Queued, status: str, detail: str = "",
             queue_time: float = float("nan"), reg: Registration | None = None) -> None:
        ack = wire.ScanAck(
            robot=rs.robot, seq=item.scan.seq, send_stamp=item.scan.send_stamp, status=status,
            interarrival=item.interarrival, queue_time=queue_time,
            proc_time=reg.proc_time if reg else float("nan"),
            icp_time=reg.icp_time if reg else float("nan"),
            map_points=reg.map_points if reg else (rs.mapper.map_points if rs.mapper else 0),
            keypoints=reg.keypoints if reg else 0, sigma=reg.sigma if reg else float("nan"),
            detail=detail, pose=reg.pose if reg else np.full((4, 4), np.nan),
        )
        rs.ack_pub.put(wire.encode(ack))

    # Map queries and export
    def _on_map_query(self, query: zenoh.Query) -> None:
        robot = self.keys.robot_of(str(query.key_expr))
        rs = self.robots.get(robot) if robot else None
        if rs is None or rs.mapper is None:
            query.reply_err(f"no map for robot {robot!r}".encode())
            return
        seqs, poses = rs.mapper.trajectory()
        reply = wire.MapReply(robot=rs.robot, scans=len(seqs), points=rs.mapper.map_cloud(),
                              seqs=seqs, poses=poses)
        query.reply(self.keys.map(rs.robot), wire.encode(reply))

    def export_map(self, robot: str, folder: Path, fmt: str = "ply") -> Path | None:
        """Write the robot's map, trajectory and counters to ``folder``; None if it has no map."""
        rs = self.robots.get(robot)
        if rs is None or rs.mapper is None:
            return None
        folder.mkdir(parents=True, exist_ok=True)
        seqs, poses = rs.mapper.trajectory()
        np.savez(folder / f"{robot}_trajectory.npz", seqs=seqs, poses=poses)
        summary = {k: int(v) for k, v in rs.counters.items()}
        summary["map_points"] = rs.mapper.map_points
        (folder / f"{robot}_edge.json").write_text(json.dumps(summary, indent=2))
        return write_point_cloud(folder / f"{robot}_map.{fmt}", rs.mapper.map_cloud())
