"""zoffload-robot: replays a scan source at sensor rate, downsamples each scan with the scale
policy's voxel size, streams it to the edge, books every ack.

Inputs:  a scan source (``sim`` or a folder), ``<ns>/data/<robot>/scan_ack`` (wire.ScanAck),
         liveliness ``<ns>/alive/edge/*``.
Outputs: ``<ns>/data/<robot>/scan`` (wire.Scan, congestion control DROP: a slow link drops stale
         scans instead of stalling the sensor loop), ``<ns>/status/<robot>`` (wire.Status, 1 Hz),
         liveliness ``<ns>/alive/robot/<robot>``; results in ``out_dir`` (config, metrics, per-scan CSV).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.voxel import voxel_downsample, warmup
from zoffload.policy.onnx_scale import load_scale_policy
from zoffload.policy.rate import LinkAwareScale, LinkView
from zoffload.policy.scale import ScalePolicy
from zoffload.protocol import wire
from zoffload.protocol.coding import encode_q16z, quant_step
from zoffload.protocol.keys import Keys
from zoffload.robot.ledger import RECORD_FIELDS, ScanLedger
from zoffload.robot.sensor import Reading, SensorThread
from zoffload.runtime.config import RobotSettings, write_effective
from zoffload.runtime.errors import ConfigError
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import open_session
from zoffload.sources import ScanSource, open_scan_source

log = logging.getLogger("zoffload.robot")


class RobotDaemon:
    def __init__(self, settings: RobotSettings, source: ScanSource | None = None,
                 policy: ScalePolicy | None = None, stop: StopSignal | None = None) -> None:
        self.settings = settings
        self.keys = Keys(settings.namespace)
        self.stop = stop or StopSignal()
        self.source = source or open_scan_source(settings.scans, sim_seed=settings.sim_seed)
        self.policy = policy or load_scale_policy(settings.scale_policy, settings.voxel,
                                                  settings.voxel_range)
        self.ledger = ScanLedger()
        self.edges: set[str] = set()
        self._lock = threading.Lock()  # the ack callback and the main loop share the ledger
        self.session: Any = None
        self.voxel = self.policy.reset()
        self._edge_seen = threading.Event()
        self._last_ping_rtt = float("nan")

    # Startup
    def start(self, session: Any = None) -> None:
        """Open the Zenoh session, or share ``session`` (then the caller closes it)."""
        import zenoh

        s = self.settings
        warmup()  # compile the voxel kernel before the first scan, not during it
        self._owns_session = session is None
        self.session = session if session is not None else open_session(s.zenoh)
        self._token = self.session.liveliness().declare_token(self.keys.robot_alive(s.robot_id))
        self._edge_sub = self.session.liveliness().declare_subscriber(
            self.keys.any_edge_alive(), self._on_edge_liveliness, history=True
        )
        self._ack_sub = self.session.declare_subscriber(self.keys.scan_ack(s.robot_id), self._on_ack)
        # BLOCK_FIRST: on a congested link the first scan waits for room (the loop blocks; the
        # sensor's newer scans are dropped at source and counted) and others are dropped whole.
        # With DROP every fragment of a large scan gets only 50 ms to find room, so on a narrow
        # link every large scan loses some fragments and none reassembles (KITTI-360 raw at
        # 20 Mbps: 0 of 100 scans received with DROP, 16 with BLOCK_FIRST).
        self._scan_pub = self.session.declare_publisher(
            self.keys.scan(s.robot_id), congestion_control=zenoh.CongestionControl.BLOCK_FIRST
        )
        self._status_pub = self.session.declare_publisher(
            self.keys.robot_status(s.robot_id), congestion_control=zenoh.CongestionControl.DROP
        )
        log.info("robot %s up: source %s (%d scans), policy %s", s.robot_id, self.source.name,
                 len(self.source), self.policy.name)
        if s.wait_edge > 0 and not self._edge_seen.wait(s.wait_edge):
            log.warning("no edge after %.1f s; running anyway, scans are dropped until one appears",
                        s.wait_edge)

    def _on_edge_liveliness(self, sample: Any) -> None:
        import zenoh

        edge = self.keys.last_chunk(str(sample.key_expr))
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.edges.add(edge)
                self._edge_seen.set()
                log.info("edge %s present", edge)
            else:
                self.edges.discard(edge)
                log.warning("edge %s gone%s", edge, "" if self.edges else ": no edge left")

    def _on_ack(self, sample: Any) -> None:
        recv = time.monotonic()
        try:
            ack = wire.decode(sample.payload.to_bytes(), expect=wire.ScanAck)
        except wire.WireError as exc:
            with self._lock:
                self.ledger.counters["malformed_acks"] += 1
            log.warning("dropped malformed ack: %s", exc)
            return
        assert isinstance(ack, wire.ScanAck)
        with self._lock:
            self.ledger.on_ack(ack, recv)

    # Per-scan work
    def process(self, reading: Reading) -> None:
        s = self.settings
        t0 = time.perf_counter()
        pts, n_nonfinite = drop_non_finite(reading.frame.points)
        record: dict[str, Any] = {"index": reading.frame.index, "capture_stamp": reading.capture_stamp,
                                  "n_raw": len(pts), "n_nonfinite": n_nonfinite}
        if reading.frame.gt_pose is not None:
            self.ledger.gt_poses[reading.seq] = reading.frame.gt_pose
        with self._lock:
            if len(pts) == 0:
                self.ledger.drop_at_source(reading.seq, "empty", record)
                return
            if not self.edges:
                self.ledger.drop_at_source(reading.seq, "edge_absent", record)
                return
            if s.max_in_flight and self.ledger.in_flight >= s.max_in_flight:
                self.ledger.drop_at_source(reading.seq, "window", record)
                return
            last_t = self.ledger.last_interarrival
        # Choose the voxel size, downsample
        if isinstance(self.policy, LinkAwareScale):
            self.voxel, down = self.policy.choose_cloud(pts, self._link_view())
            down = down.astype(np.float32)
        else:
            self.voxel = self.policy.choose(last_t, self.voxel)
            down = voxel_downsample(pts, self.voxel).astype(np.float32) if self.voxel > 0 else pts
        # Encode and send
        send_stamp = time.monotonic()
        msg = self._scan_message(reading, send_stamp, len(pts), down)
        data = wire.encode(msg)
        record.update(voxel=self.voxel, n_sent=len(down), bytes=len(data))
        with self._lock:
            self.ledger.published(reading.seq, send_stamp, record)
        self._scan_pub.put(data)
        record_work = (time.perf_counter() - t0) * 1e3
        with self._lock:
            self.ledger.records[reading.seq]["work_ms"] = record_work

    def _link_view(self) -> LinkView:
        """The link as the acks show it: last T, bytes acked in the last second, bytes per point."""
        now = time.monotonic()
        rate = self.settings.rate_hz or self.source.rate_hz
        with self._lock:
            recs = list(self.ledger.records.values())[-60:]
            last_t = self.ledger.last_interarrival
            seen = self.ledger.interarrivals_seen
        acked = [r for r in recs if r.get("status") == "acked" and "rtt" in r]
        recent = [r for r in acked if r["send_stamp"] + r["rtt"] >= now - 1.0]
        # a rate needs a full second of acks behind it: two acks in the first 0.2 s are not 10 Hz
        young = not acked or min(r["send_stamp"] + r["rtt"] for r in acked) > now - 1.0
        sent = [r for r in recs if r.get("bytes") and r.get("n_sent")][-5:]
        return LinkView(
            last_t=last_t,
            acked_bytes_per_s=float("nan") if young else float(sum(r["bytes"] for r in recent)),
            bytes_per_point=(sum(r["bytes"] for r in sent) / sum(r["n_sent"] for r in sent)) if sent
            else float("nan"),
            period=1.0 / rate,
            acks=seen)

    def _scan_message(self, reading: Reading, send_stamp: float, n_raw: int, down: np.ndarray) -> wire.Scan:
        s = self.settings
        common = dict(robot=s.robot_id, seq=reading.seq, send_stamp=send_stamp,
                      capture_stamp=reading.capture_stamp, voxel=self.voxel,
                      voxel_max=max(s.voxel_range[1], self.voxel), max_range=self.source.max_range,
                      n_raw=n_raw)
        if s.scan_coding == "q16z":
            origin, step, blob = encode_q16z(down, quant_step(self.voxel, s.quant_fraction), widen=True)
            return wire.Scan(**common, points=np.zeros((0, 3), np.float32), coding="q16z",  # type: ignore[arg-type]
                             quant_step=step, n_points=len(down), origin=origin,
                             packed=np.frombuffer(blob, np.uint8))
        return wire.Scan(**common, points=np.ascontiguousarray(down, np.float32))  # type: ignore[arg-type]

    # Main loop
    def run(self) -> dict[str, Any]:
        s = self.settings
        rate = s.rate_hz or self.source.rate_hz
        sensor = SensorThread(self.source, rate, s.replay, s.max_scans)
        sensor.start()
        next_status = time.monotonic()
        self._booked_overwrites = 0
        try:
            while not self.stop.is_set():
                reading = sensor.take(timeout=0.05)
                now = time.monotonic()
                with self._lock:
                    self.ledger.expire(now, s.ack_timeout)
                    self._book_overwrites(sensor)
                if now >= next_status:
                    self._publish_status(sensor)
                    next_status = now + s.status_period
                if reading is None:
                    if sensor.exhausted:
                        break
                    continue
                with self._lock:
                    self.ledger.produced()
                try:
                    self.process(reading)
                except Exception as exc:  # one bad scan must not end the run
                    with self._lock:
                        self.ledger.drop_at_source(reading.seq, "error")
                    log.error("scan %d: %s", reading.seq, exc)
        finally:
            sensor.stop()
            with self._lock:
                self.ledger.counters["read_errors"] += sensor.read_errors
                self._book_overwrites(sensor)
            self._drain()
            self._publish_status(sensor)
        return self.metrics()

    def _book_overwrites(self, sensor: SensorThread) -> None:
        """Scans the sensor replaced before the loop took them: produced, dropped at source."""
        new = sensor.overwritten - self._booked_overwrites
        for _ in range(new):
            self.ledger.produced()
            self.ledger.drop_at_source(None, "overrun")
        self._booked_overwrites += new

    def _drain(self) -> None:
        """Give in-flight scans their ack timeout, then book the rest as lost."""
        deadline = time.monotonic() + self.settings.ack_timeout
        while time.monotonic() < deadline:
            with self._lock:
                if self.ledger.in_flight == 0:
                    break
            time.sleep(0.02)
        with self._lock:
            self.ledger.finish()

    def _publish_status(self, sensor: SensorThread) -> None:
        with self._lock:
            values = {k: float(v) for k, v in self.ledger.balance().items()}
            values["voxel"] = float(self.voxel)
            values["edges"] = float(len(self.edges))
            values["last_T"] = float(self.ledger.last_interarrival)
            recent = [r for r in list(self.ledger.records.values())[-20:] if "rtt" in r]
        if recent:
            values["rtt_ms"] = float(np.mean([r["rtt"] for r in recent]) * 1e3)
            values["map_points"] = float(recent[-1]["map_points"])
        status = wire.Status(source="robot", id=self.settings.robot_id, stamp=time.time(), values=values)
        try:
            self._status_pub.put(wire.encode(status))
        except Exception as exc:  # status is best effort
            log.debug("status not published: %s", exc)

    # Results
    def metrics(self) -> dict[str, Any]:
        with self._lock:
            recs = [self.ledger.records[k] for k in sorted(self.ledger.records)]
            balance = self.ledger.balance()
            out: dict[str, Any] = {
                "robot": self.settings.robot_id,
                "source": self.source.name,
                "policy": self.policy.name,
                "balance": balance,
                "balanced": self.ledger.balanced(),
                "dropped_source": dict(self.ledger.dropped_source),
                "other": {k: v for k, v in self.ledger.counters.items() if k not in balance},
            }
        sent = [r for r in recs if "bytes" in r]
        acked = [r for r in recs if r.get("status") == "acked"]
        t = [r["interarrival"] for r in acked if np.isfinite(r.get("interarrival", np.nan))]
        out["scans"] = {
            "sent": len(sent),
            "acked": len(acked),
            "mean_kB_sent": float(np.mean([r["bytes"] for r in sent]) / 1e3) if sent else None,
            "mean_points_raw": float(np.mean([r["n_raw"] for r in sent])) if sent else None,
            "mean_points_sent": float(np.mean([r["n_sent"] for r in sent])) if sent else None,
            "mean_work_ms": float(np.mean([r["work_ms"] for r in sent if "work_ms" in r])) if sent else None,
            "mean_T": float(np.mean(t)) if t else None,
            "frac_T_le_0.11": float(np.mean(np.asarray(t) <= 0.11)) if t else None,
            "mean_rtt_ms": float(np.mean([r["rtt"] for r in acked]) * 1e3) if acked else None,
            "map_points": int(acked[-1]["map_points"]) if acked else 0,
        }
        return out

    def write_results(self, out_dir: Path) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_effective(self.settings, out_dir / "robot_config.yaml")
        (out_dir / "robot_metrics.json").write_text(json.dumps(self.metrics(), indent=2))
        with self._lock:
            recs = [self.ledger.records[k] for k in sorted(self.ledger.records)]
            poses = dict(self.ledger.poses)
            gts = dict(self.ledger.gt_poses)
        with open(out_dir / "robot_scans.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=RECORD_FIELDS, extrasaction="ignore")
            w.writeheader()
            for r in recs:
                w.writerow(r)
        np.savez(
            out_dir / "robot_poses.npz",
            acked_seqs=np.array(sorted(poses), np.int64),
            acked_poses=np.array([poses[k] for k in sorted(poses)]).reshape(-1, 4, 4),
            gt_seqs=np.array(sorted(gts), np.int64),
            gt_poses=np.array([gts[k] for k in sorted(gts)]).reshape(-1, 4, 4),
        )

    # Shutdown
    def shutdown(self) -> None:
        if self.session is not None and getattr(self, "_owns_session", True):
            self.session.close()
        self.session = None


def run(settings: RobotSettings, stop: StopSignal | None = None) -> dict[str, Any]:
    """The Python API of ``zoffload-robot``: start, replay until done or stopped, write results.

    Scans (``scans``, unless "none") and camera frames (``images``) run side by side on one
    Zenoh session; the scan loop keeps the main thread, the image offloader its own. The returned
    metrics are the scan daemon's, with the image offloader's under ``vision``."""
    from zoffload.robot.camera import ImageOffloader

    stop = stop or StopSignal()
    if settings.scans == "none" and not settings.images:
        raise ConfigError("nothing to do: scans is 'none' and no images are configured")
    quota = None
    if settings.perception.cpu_quota:
        from zoffload.runtime.quota import apply_cpu_quota

        quota = apply_cpu_quota(settings.perception.cpu_quota)
        if quota == "threads":
            n = max(1, math.ceil(settings.perception.cpu_quota))
            settings = settings.model_copy(update={"perception": settings.perception.model_copy(
                update={"local_threads": min(settings.perception.local_threads or n, n)})})
    daemon = RobotDaemon(settings, stop=stop) if settings.scans != "none" else None
    vision = ImageOffloader(settings, None, stop) if settings.images else None
    session = open_session(settings.zenoh)
    metrics: dict[str, Any] = {}
    try:
        if daemon is not None:
            daemon.start(session)
        else:
            alive = Keys(settings.namespace).robot_alive(settings.robot_id)
            token = session.liveliness().declare_token(alive)
        vthread = None
        if vision is not None:
            vision.session = session
            vision.start()
            if daemon is not None:
                vthread = threading.Thread(target=vision.run, name="vision", daemon=True)
                vthread.start()
            else:
                vision.run()
        if daemon is not None:
            metrics = daemon.run()
        if vthread is not None:
            vthread.join()
        if vision is not None:
            metrics["vision"] = vision.metrics()
            metrics["vision"]["cpu_quota"] = quota
        if settings.out_dir:
            if daemon is not None:
                daemon.write_results(Path(settings.out_dir))
            if vision is not None:
                vision.write_results(Path(settings.out_dir))
                write_effective(settings, Path(settings.out_dir) / "robot_config.yaml")
    finally:
        if daemon is not None:
            daemon.shutdown()
        elif "token" in locals():
            token.undeclare()
        session.close()
    if daemon is not None:
        log.info("robot done: %s", json.dumps(metrics["balance"]))
    if vision is not None:
        log.info("camera done: %s", json.dumps(metrics["vision"]["balance"]))
    return metrics
