"""Per-scan bookkeeping on the robot: every scan ends in exactly one bucket.

    produced  = published + dropped at source (by reason)
    published = acked + edge_dropped + edge_error + lost + late + in_flight

``lost``: no ack within the timeout. ``late``: its ack came after that (moved out of ``lost``).
Round-trip times use the robot's clock only: the send stamp travels with the scan and is echoed.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zoffload.protocol import wire

RECORD_FIELDS = (
    "seq", "index", "capture_stamp", "voxel", "n_raw", "n_nonfinite", "n_sent", "bytes",
    "work_ms", "send_stamp", "status", "rtt", "network_time", "interarrival", "queue_time",
    "proc_time", "map_points", "keypoints", "sigma",
)


@dataclass
class ScanLedger:
    records: dict[int, dict[str, Any]] = field(default_factory=dict)
    poses: dict[int, np.ndarray] = field(default_factory=dict)
    gt_poses: dict[int, np.ndarray] = field(default_factory=dict)
    counters: Counter[str] = field(default_factory=Counter)
    dropped_source: Counter[str] = field(default_factory=Counter)
    pending: dict[int, float] = field(default_factory=dict)  # seq -> send stamp
    last_interarrival: float = 0.0  # T_{n-1}; 0 before any ack (the paper's T0)
    interarrivals_seen: int = 0  # how many acks have brought a T (a policy reacts to new ones)

    def produced(self, n: int = 1) -> None:
        self.counters["produced"] += n

    def drop_at_source(self, seq: int | None, reason: str, record: dict[str, Any] | None = None) -> None:
        self.dropped_source[reason] += 1
        if seq is not None:
            rec = dict(record or {}, seq=seq, status=f"source:{reason}")
            self.records[seq] = rec

    def published(self, seq: int, send_stamp: float, record: dict[str, Any]) -> None:
        self.counters["published"] += 1
        self.pending[seq] = send_stamp
        self.records[seq] = dict(record, seq=seq, send_stamp=send_stamp, status="in_flight")

    def on_ack(self, ack: wire.ScanAck, recv_stamp: float) -> str:
        """Book an ack; returns the bucket it landed in ("acked", "edge_dropped", "edge_error",
        "late", "duplicate" or "unknown")."""
        rec = self.records.get(ack.seq)
        if rec is None or "send_stamp" not in rec or rec["send_stamp"] != ack.send_stamp:
            self.counters["unknown_acks"] += 1
            return "unknown"
        rtt = recv_stamp - ack.send_stamp
        edge_time = sum(x for x in (ack.queue_time, ack.proc_time) if math.isfinite(x))
        rec.update(rtt=rtt, network_time=rtt - edge_time, interarrival=ack.interarrival,
                   queue_time=ack.queue_time, proc_time=ack.proc_time, map_points=ack.map_points,
                   keypoints=ack.keypoints, sigma=ack.sigma)
        if math.isfinite(ack.interarrival):
            self.last_interarrival = ack.interarrival
            self.interarrivals_seen += 1
        if ack.seq in self.pending:
            del self.pending[ack.seq]
            bucket = {"ok": "acked", "dropped": "edge_dropped"}.get(ack.status, "edge_error")
            self.counters[bucket] += 1
            rec["status"] = bucket
            if bucket == "acked":
                self.poses[ack.seq] = np.array(ack.pose)
            return bucket
        if rec.get("status") == "lost":
            self.counters["lost"] -= 1
            self.counters["late"] += 1
            rec["status"] = "late"
            return "late"
        self.counters["duplicate_acks"] += 1
        return "duplicate"

    def expire(self, now: float, timeout: float) -> int:
        """Declare lost every scan unanswered for ``timeout`` seconds; returns how many."""
        expired = [seq for seq, stamp in self.pending.items() if now - stamp > timeout]
        for seq in expired:
            del self.pending[seq]
            self.counters["lost"] += 1
            self.records[seq]["status"] = "lost"
        return len(expired)

    def finish(self) -> None:
        """End of run: whatever is still unanswered is lost."""
        self.expire(float("inf"), 0.0)

    @property
    def in_flight(self) -> int:
        return len(self.pending)

    def balance(self) -> dict[str, int]:
        c = self.counters
        return {
            "produced": c["produced"],
            "published": c["published"],
            "dropped_source": sum(self.dropped_source.values()),
            "acked": c["acked"],
            "edge_dropped": c["edge_dropped"],
            "edge_error": c["edge_error"],
            "lost": c["lost"],
            "late": c["late"],
            "in_flight": self.in_flight,
        }

    def balanced(self) -> bool:
        b = self.balance()
        return (
            b["produced"] == b["published"] + b["dropped_source"]
            and b["published"]
            == b["acked"] + b["edge_dropped"] + b["edge_error"] + b["lost"] + b["late"] + b["in_flight"]
        )
