"""The robot's scan pipeline: replays a scan source at sensor rate, downsamples each scan with the
scale policy's voxel size, streams it to the edge, books every ack.

Inputs:  a scan source (``sim`` or a folder), ``<ns>/data/<robot>/scan_ack`` (wire.ScanAck), the
         edges present (the robot server's ``EdgePresence``).
Outputs: ``<ns>/data/<robot>/scan`` (wire.Scan, congestion control BLOCK_FIRST: the first scan that
         meets a full queue waits, newer ones are dropped at source and counted, never in pieces);
         status values for the robot's 1 Hz status message; results in ``out_dir`` (metrics,
         per-scan CSV, poses).
"""

from __future__ import annotations

import csv
import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.voxel import voxel_downsample, warmup
from zoffload.policy.onnx_scale import load_scale_policy
from zoffload.policy.rate import LinkAwareScale, LinkView
from zoffload.policy.scale import ScalePolicy
from zoffload.protocol import wire
from zoffload.protocol.coding import encode_q16z, quant_step
from zoffload.protocol.keys import Keys
from zoffload.robot.ledger import RECORD_FIELDS, ScanLedger
from zoffload.robot.presence import EdgePresence
from zoffload.robot.sensor import Reading, SensorThread
from zoffload.runtime.config import RobotSettings
from zoffload.runtime.drops import Drops
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import undeclare
from zoffload.sources import ScanSource, open_scan_source

log = logging.getLogger("zoffload.robot.scans")


@dataclass(frozen=True)
class StreamOptions:
    """How the streamer sends: the robot settings this pipeline uses, unpacked."""

    robot_id: str
    rate_hz: float  # the sensor's rate
    replay: str = "once"
    max_scans: int | None = None
    voxel_range: tuple[float, float] = (0.01, 0.07)
    coding: str = "q16z"  # "f32" or "q16z"
    quant_fraction: float = 0.1
    ack_timeout: float = 1.0
    max_in_flight: int = 3  # unanswered scans before the next is held back; 0 = no limit


class ScanStreamer:
    """A pipeline (robot/pipeline.py): sensor thread → downsample → publish → book acks."""

    name = "scans"

    def __init__(self, source: ScanSource, policy: ScalePolicy, keys: Keys, options: StreamOptions,
                 stop: StopSignal) -> None:
        self.source = source
        self.policy = policy
        self.keys = keys
        self.opts = options
        self.stop = stop
        self.ledger = ScanLedger()
        self.drops = Drops(log)
        self._lock = threading.Lock()  # the ack callback and the loop share the ledger
        self.voxel = self.policy.reset()
        self.presence: EdgePresence | None = None
        self._sensor: SensorThread | None = None
        self._booked_overwrites = 0

    # Startup
    def start(self, session: zenoh.Session, presence: EdgePresence) -> None:
        warmup()  # compile the voxel kernel before the first scan, not during it
        self.presence = presence
        robot = self.opts.robot_id
        self._ack_sub = session.declare_subscriber(self.keys.scan_ack(robot),
                                                   self.drops.guard(self._on_ack, "ack"))
        # BLOCK_FIRST: on a congested link the first scan waits for room (the loop blocks; the
        # sensor's newer scans are dropped at source and counted) and others are dropped whole.
        # With DROP every fragment of a large scan gets only 50 ms to find room, so on a narrow
        # link every large scan loses some fragments and none reassembles (KITTI-360 raw at
        # 20 Mbps: 0 of 100 scans received with DROP, 16 with BLOCK_FIRST).
        self._scan_pub = session.declare_publisher(
            self.keys.scan(robot), congestion_control=zenoh.CongestionControl.BLOCK_FIRST)
        log.info("scans from %s (%d), policy %s, coding %s", self.source.name, len(self.source),
                 self.policy.name, self.opts.coding)

    def close(self) -> None:
        undeclare(getattr(self, "_ack_sub", None), getattr(self, "_scan_pub", None))

    def _on_ack(self, sample: zenoh.Sample) -> None:
        recv = time.monotonic()
        try:
            ack = wire.decode(sample.payload.to_bytes(), expect=wire.ScanAck)
        except wire.WireError as exc:
            self.drops.drop("malformed_ack", str(exc))
            return
        if ack.robot != self.opts.robot_id:
            self.drops.drop("foreign_ack", f"an ack for robot {ack.robot!r}")
            return
        # Answers come from an edge that is present (an ACL'd router lets only edge identities put
        # acks; without one, a forged ack from nowhere is refused here at least)
        if ack.edge and self.presence is not None and ack.edge not in self.presence.edges:
            self.drops.drop("foreign_ack", f"ack from {ack.edge!r}, not a present edge")
            return
        with self._lock:
            self.ledger.on_ack(ack, recv)

    # Per-scan work
    def process(self, reading: Reading) -> None:
        t0 = time.perf_counter()
        pts, n_nonfinite = drop_non_finite(reading.frame.points)
        record: dict[str, Any] = {"index": reading.frame.index, "capture_stamp": reading.capture_stamp,
                                  "n_raw": len(pts), "n_nonfinite": n_nonfinite}
        if reading.frame.gt_pose is not None:
            self.ledger.gt_poses[reading.seq] = reading.frame.gt_pose
        edge_present = self.presence is not None and self.presence.any
        with self._lock:
            if len(pts) == 0:
                self.ledger.drop_at_source(reading.seq, "empty", record)
                return
            if not edge_present:
                self.ledger.drop_at_source(reading.seq, "edge_absent", record)
                return
            if self.opts.max_in_flight and self.ledger.in_flight >= self.opts.max_in_flight:
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
        data = wire.encode(self._scan_message(reading, send_stamp, len(pts), down))
        record.update(voxel=self.voxel, n_sent=len(down), bytes=len(data))
        with self._lock:
            self.ledger.published(reading.seq, send_stamp, record)
        self._scan_pub.put(data)
        work_ms = (time.perf_counter() - t0) * 1e3
        with self._lock:
            self.ledger.records[reading.seq]["work_ms"] = work_ms

    def _link_view(self) -> LinkView:
        """The link as the acks show it: last T, bytes acked in the last second, bytes per point."""
        now = time.monotonic()
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
            period=1.0 / self.opts.rate_hz,
            acks=seen)

    def _scan_message(self, reading: Reading, send_stamp: float, n_raw: int, down: np.ndarray) -> wire.Scan:
        o = self.opts
        common: dict[str, Any] = dict(
            robot=o.robot_id, seq=reading.seq, send_stamp=send_stamp, capture_stamp=reading.capture_stamp,
            voxel=self.voxel, voxel_max=max(o.voxel_range[1], self.voxel), max_range=self.source.max_range,
            n_raw=n_raw)
        if o.coding == "q16z":
            origin, step, blob = encode_q16z(down, quant_step(self.voxel, o.quant_fraction), widen=True)
            return wire.Scan(**common, points=np.zeros((0, 3), np.float32), coding="q16z",
                             quant_step=step, n_points=len(down), origin=origin,
                             packed=np.frombuffer(blob, np.uint8))
        return wire.Scan(**common, points=np.ascontiguousarray(down, np.float32))

    # Main loop
    def run(self) -> None:
        o = self.opts
        sensor = self._sensor = SensorThread(self.source, o.rate_hz, o.replay, o.max_scans)
        sensor.start()
        try:
            while not self.stop.is_set():
                reading = sensor.take(timeout=0.05)
                with self._lock:
                    self.ledger.expire(time.monotonic(), o.ack_timeout)
                    self._book_overwrites(sensor)
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

    def _book_overwrites(self, sensor: SensorThread) -> None:
        """Scans the sensor replaced before the loop took them: produced, dropped at source."""
        new = sensor.overwritten - self._booked_overwrites
        for _ in range(new):
            self.ledger.produced()
            self.ledger.drop_at_source(None, "overrun")
        self._booked_overwrites += new

    def _drain(self) -> None:
        """Give in-flight scans their ack timeout, then book the rest as lost."""
        deadline = time.monotonic() + self.opts.ack_timeout
        while time.monotonic() < deadline:
            with self._lock:
                if self.ledger.in_flight == 0:
                    break
            time.sleep(0.02)
        with self._lock:
            self.ledger.finish()

    def status(self) -> dict[str, float]:
        with self._lock:
            values = {k: float(v) for k, v in self.ledger.balance().items()}
            values["voxel"] = float(self.voxel)
            values["last_T"] = float(self.ledger.last_interarrival)
            recent = [r for r in list(self.ledger.records.values())[-20:] if "rtt" in r]
        if recent:
            values["rtt_ms"] = float(np.mean([r["rtt"] for r in recent]) * 1e3)
            values["map_points"] = float(recent[-1]["map_points"])
        return values

    # Results
    def metrics(self) -> dict[str, Any]:
        with self._lock:
            recs = [self.ledger.records[k] for k in sorted(self.ledger.records)]
            balance = self.ledger.balance()
            out: dict[str, Any] = {
                "robot": self.opts.robot_id,
                "source": self.source.name,
                "policy": self.policy.name,
                "balance": balance,
                "balanced": self.ledger.balanced(),
                "dropped_source": dict(self.ledger.dropped_source),
                "other": {k: v for k, v in self.ledger.counters.items() if k not in balance},
                "drops": self.drops.snapshot(),
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


def scan_streamer(settings: RobotSettings, stop: StopSignal, source: ScanSource | None = None,
                  policy: ScalePolicy | None = None) -> ScanStreamer:
    """The scan pipeline for these settings (``source`` and ``policy`` to inject others)."""
    source = source or open_scan_source(settings.scans, sim_seed=settings.sim_seed)
    policy = policy or load_scale_policy(settings.scale_policy, settings.voxel, settings.voxel_range)
    options = StreamOptions(
        robot_id=settings.robot_id, rate_hz=settings.rate_hz or source.rate_hz, replay=settings.replay,
        max_scans=settings.max_scans, voxel_range=settings.voxel_range, coding=settings.scan_coding,
        quant_fraction=settings.quant_fraction, ack_timeout=settings.ack_timeout,
        max_in_flight=settings.max_in_flight)
    return ScanStreamer(source, policy, Keys(settings.namespace), options, stop)
