"""zoffload-edge: receives every robot's scans, maps each robot with its own KISS-ICP, answers.

Inputs:  ``<ns>/data/*/scan`` (wire.Scan).
Outputs: ``<ns>/data/<robot>/scan_ack`` (wire.ScanAck, one per scan, also for scans it had to
         drop), ``<ns>/status/edge/<edge>`` (wire.Status, 1 Hz), liveliness ``<ns>/alive/edge/<edge>``.
Queries: ``<ns>/ctrl/<robot>/map`` (wire.MapReply), ``<ns>/ctrl/<robot>/ping`` (wire.Pong).
Detector: ``<ns>/data/*/frame`` → ``<ns>/data/<robot>/detections`` (edge/detector.py), when the
         configured model can be found (or ``detector.enabled: true``, then a missing model is fatal).

The Zenoh callback only stamps, decodes and queues; registration runs on one worker thread per
robot, so a slow mapper never blocks reception and inter-arrival T stays an arrival-time measure.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.mapping.mapper import RobotMapper, load_kiss_icp, mapper_voxel_size
from zoffload.mapping.voxel import warmup
from zoffload.protocol import wire
from zoffload.protocol.intake import decode_from_robot
from zoffload.protocol.keys import Keys
from zoffload.runtime.config import EdgeSettings, MapperSettings, ZenohSettings, write_effective
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import open_session

log = logging.getLogger("zoffload.edge")


@dataclass
class _Queued:
    scan: wire.Scan
    arrival: float  # edge monotonic clock
    interarrival: float


@dataclass
class RobotSession:
    """Per-robot state on the edge: the mapper (made on the first scan), the queue, counters."""

    robot: str
    mapper: RobotMapper | None = None
    queue: deque[_Queued] = field(default_factory=deque)
    cond: threading.Condition = field(default_factory=threading.Condition)
    last_arrival: float | None = None
    counters: Counter[str] = field(default_factory=Counter)
    worker: threading.Thread | None = None
    ack_pub: Any = None
    proc_times: list[float] = field(default_factory=list)


DROP_WAIT_KEY = "transport/link/tx/queue/congestion_control/drop/wait_before_drop"
DROP_WAIT_US = 50_000


def edge_zenoh(z: ZenohSettings) -> ZenohSettings:
    """The edge's session settings: acks and detections are small and published with DROP (a
    stalled robot must not block the mapper or the detector), but Zenoh's default 1 ms wait before
    dropping loses some of a burst of acks when the edge's CPU is busy. The edge waits up to 50 ms
    (two camera frames) unless the user's ``--cfg`` or config file sets the key."""
    if z.config_file or any(item.split(":", 1)[0] == DROP_WAIT_KEY for item in z.cfg):
        return z
    return z.model_copy(update={"cfg": [f"{DROP_WAIT_KEY}:{DROP_WAIT_US}", *z.cfg]})


class EdgeDaemon:
    def __init__(self, settings: EdgeSettings, stop: StopSignal | None = None) -> None:
        self.settings = settings
        self.keys = Keys(settings.namespace)
        self.stop = stop or StopSignal()
        self.robots: dict[str, RobotSession] = {}
        self.counters: Counter[str] = Counter()
        self._lock = threading.Lock()
        self.session: Any = None
        self.detector: Any = None

    # Startup
    def start(self) -> None:
        import zenoh

        s = self.settings
        # Compile the map kernels and load KISS-ICP now, not while the first scans queue up
        warmup()
        load_kiss_icp()
        self.session = open_session(edge_zenoh(s.zenoh))
        self._token = self.session.liveliness().declare_token(self.keys.edge_alive(s.edge_id))
        self._sub = self.session.declare_subscriber(self.keys.all_scans(), self._on_scan)
        self._map_q = self.session.declare_queryable(self.keys.all_maps(), self._on_map_query)
        self._ping_q = self.session.declare_queryable(self.keys.all_pings(), self._on_ping)
        self._status_pub = self.session.declare_publisher(
            self.keys.edge_status(s.edge_id), congestion_control=zenoh.CongestionControl.DROP
        )
        self._start_detector()
        log.info("edge %s up (zenoh %s, listen=%s, connect=%s)", s.edge_id, s.zenoh.mode,
                 s.zenoh.listen, s.zenoh.connect)

    def _start_detector(self) -> None:
        d = self.settings.detector
        if d.enabled is False:
            return
        from zoffload.detect.detector import Detector
        from zoffload.detect.models import ModelError
        from zoffload.edge.detection import DetectorService

        try:
            model = Detector(d.model, d.model_path, threads=d.threads, url=d.model_url)
        except ModelError as exc:
            if d.enabled:
                raise
            log.warning("object detector off: %s", exc)
            return
        self.detector = DetectorService(model, self.session, self.keys, self.settings.edge_id,
                                        queue=d.queue, batch=d.batch)
        self.detector.start()

    # Reception (Zenoh callback thread: stamp, decode, queue; nothing slow)
    def _on_scan(self, sample: Any) -> None:
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
            while len(rs.queue) > self.settings.mapper.queue:
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
                import zenoh

                rs = RobotSession(robot)
                rs.ack_pub = self.session.declare_publisher(
                    self.keys.scan_ack(robot), congestion_control=zenoh.CongestionControl.DROP,
                    express=True,
                )
                rs.worker = threading.Thread(target=self._work, args=(rs,), name=f"map-{robot}",
                                             daemon=True)
                self.robots[robot] = rs
                rs.worker.start()
                log.info("new robot %s", robot)
            return rs

    # Registration (one worker per robot)
    def _work(self, rs: RobotSession) -> None:
        while not self.stop.is_set():
            with rs.cond:
                while not rs.queue and not self.stop.is_set():
                    rs.cond.wait(0.2)
                if not rs.queue:
                    continue
                item = rs.queue.popleft()
            self._register(rs, item)

    def _register(self, rs: RobotSession, item: _Queued) -> None:
        scan = item.scan
        if not self.settings.mapper.enabled:
            rs.counters["received_only"] += 1
            self._ack(rs, item, status="ok", detail="mapping disabled", queue_time=0.0)
            return
        try:
            if rs.mapper is None:
                rs.mapper = self._make_mapper(scan)
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
        rs.proc_times.append(reg.proc_time)
        self._ack(rs, item, status="ok", queue_time=start - item.arrival, reg=reg)

    def _make_mapper(self, scan: wire.Scan) -> RobotMapper:
        m: MapperSettings = self.settings.mapper
        max_range = m.max_range or scan.max_range
        voxel = mapper_voxel_size(max_range, scan.voxel_max, m.voxel_size)
        log.info("robot %s: KISS-ICP voxel %.3f m, max range %.1f m (robot voxel_max %.3f)",
                 scan.robot, voxel, max_range, scan.voxel_max)
        return RobotMapper(voxel_size=voxel, max_range=max_range, min_range=m.min_range,
                           max_points_per_voxel=m.max_points_per_voxel, deskew=m.deskew,
                           map_resolution=m.map_resolution)

    def _ack(self, rs: RobotSession, item: _Queued, status: str, detail: str = "",
             queue_time: float = float("nan"), reg: Any = None) -> None:
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

    # Queries
    def _on_map_query(self, query: Any) -> None:
        robot = self.keys.robot_of(str(query.key_expr))
        rs = self.robots.get(robot) if robot else None
        if rs is None or rs.mapper is None:
            query.reply_err(f"no map for robot {robot!r}".encode())
            return
        seqs, poses = rs.mapper.trajectory()
        reply = wire.MapReply(robot=rs.robot, scans=len(seqs), points=rs.mapper.map_cloud(),
                              seqs=seqs, poses=poses)
        query.reply(self.keys.map(rs.robot), wire.encode(reply))

    def _on_ping(self, query: Any) -> None:
        params = query.parameters
        stamp = float(params.get("stamp") or "nan") if params else float("nan")
        query.reply(query.key_expr, wire.encode(wire.Pong(edge=self.settings.edge_id, stamp=stamp)))

    # Main loop
    def status(self) -> wire.Status:
        values: dict[str, float] = {k: float(v) for k, v in self.counters.items()}
        values["robots"] = float(len(self.robots))
        for rid, rs in list(self.robots.items()):
            values[f"{rid}.map_points"] = float(rs.mapper.map_points if rs.mapper else 0)
            values[f"{rid}.queue"] = float(len(rs.queue))
        if self.detector is not None:
            values.update(self.detector.status())
        return wire.Status(source="edge", id=self.settings.edge_id, stamp=time.time(), values=values)

    def run(self) -> None:
        period = self.settings.status_period
        while not self.stop.wait(period):
            self._status_pub.put(wire.encode(self.status()))

    # Shutdown
    def shutdown(self) -> None:
        self.stop.set()
        if self.detector is not None:
            self.detector.stop()
        for rs in list(self.robots.values()):
            if rs.worker:
                rs.worker.join(timeout=5)
        s = self.settings
        if s.map_dir:
            for rid in list(self.robots):
                path = self.export_map(rid, Path(s.map_dir), s.map_format)
                if path:
                    log.info("map of %s written to %s", rid, path)
        if self.session is not None:
            self.session.close()
            self.session = None
        log.info("edge stopped: %s", dict(self.counters))

    def export_map(self, robot: str, folder: Path, fmt: str = "ply") -> Path | None:
        rs = self.robots.get(robot)
        if rs is None or rs.mapper is None:
            return None
        from zoffload.mapping.export import write_point_cloud

        folder.mkdir(parents=True, exist_ok=True)
        seqs, poses = rs.mapper.trajectory()
        np.savez(folder / f"{robot}_trajectory.npz", seqs=seqs, poses=poses)
        summary = {k: int(v) for k, v in rs.counters.items()}
        summary["map_points"] = rs.mapper.map_points
        (folder / f"{robot}_edge.json").write_text(json.dumps(summary, indent=2))
        return write_point_cloud(folder / f"{robot}_map.{fmt}", rs.mapper.map_cloud())


def run(settings: EdgeSettings, stop: StopSignal | None = None) -> None:
    """The Python API of ``zoffload-edge``: start, serve until stopped, shut down."""
    daemon = EdgeDaemon(settings, stop)
    if settings.map_dir:
        write_effective(settings, Path(settings.map_dir) / "edge_config.yaml")
    daemon.start()
    try:
        daemon.run()
    finally:
        daemon.shutdown()
