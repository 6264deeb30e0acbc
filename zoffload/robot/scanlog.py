"""The robot's per-scan records, bounded in memory however long the robot runs.

The newest ``keep`` records (and their poses) stay in memory, where acks still update them; an
older record is retired: folded into running totals (the figures of ``robot_metrics.json``) and,
when the run has a results folder, appended to ``robot_scans.csv`` and the pose files at once. A
robot looping a replay for days therefore holds a few thousand records (a few MB), and its CSV
still has every scan. An ack for a retired scan (older than ``keep`` scans: minutes at 10 Hz,
against an ack timeout of a second) is booked as unknown.
"""

from __future__ import annotations

import copy
import csv
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

RECORD_FIELDS = (
    "seq", "index", "capture_stamp", "voxel", "n_raw", "n_nonfinite", "n_sent", "bytes", "coding",
    "compressed", "skipped", "reason", "work_ms", "cpu_ms", "cpu_loop_ms", "cpu_send_ms", "send_stamp",
    "status", "rtt", "network_time", "interarrival", "queue_time", "proc_time", "map_points",
    "keypoints", "sigma", "pose_source", "edge", "cpu_local_ms", "pose_lag_ms", "backfill", "backfill_voxel",
    "late_status",
)
MAX_JUMPS = 10_000  # switch jumps kept
JUMP_SPAN = 10  # a switch further than this many scans from the poses before it measures nothing
LIVE = ("sending", "in_flight")  # statuses an ack or the sender may still change


def read_scan_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a ``robot_scans.csv`` this module wrote (every field a string); [] without the
    file (a robot that never got as far as its first scan)."""
    if not path.exists():
        return []
    with open(path) as f:
        return list(csv.DictReader(f))


class Histogram:
    """Counts on log-spaced bins from 1 µs to 100 s (1 % wide): medians and percentiles of
    millions of values in 16 kB."""

    EDGES = np.geomspace(1e-3, 1e5, 1852)  # milliseconds

    def __init__(self) -> None:
        self.counts = np.zeros(len(self.EDGES) + 1, np.int64)
        self.n = 0
        self.total = 0.0

    def add(self, ms: float) -> None:
        if math.isfinite(ms):
            self.counts[int(np.searchsorted(self.EDGES, ms))] += 1
            self.n += 1
            self.total += ms

    def quantile(self, q: float) -> float | None:
        if not self.n:
            return None
        i = int(np.searchsorted(np.cumsum(self.counts), q * self.n, side="left"))
        lo = self.EDGES[i - 1] if i > 0 else 0.0
        hi = self.EDGES[min(i, len(self.EDGES) - 1)]
        return float(math.sqrt(lo * hi) if lo > 0 else hi)

    def mean(self) -> float | None:
        return self.total / self.n if self.n else None


@dataclass
class ScanTotals:
    """What ``robot_metrics.json`` reports, as running sums over records."""

    sent: int = 0
    bytes: float = 0.0
    points_raw: float = 0.0
    points_sent: float = 0.0
    work: list[float] = field(default_factory=lambda: [0, 0.0])  # count, sum (ms)
    acked: int = 0
    rtt_sum: float = 0.0
    t_count: int = 0
    t_sum: float = 0.0
    t_on_time: int = 0  # T <= 0.11 s
    map_points: tuple[int, int] = (-1, 0)  # (seq, map points) of the newest acked scan
    cpu_all_ms: float = 0.0
    cpu: Histogram = field(default_factory=Histogram)  # per scan sent: loop + sender threads
    cpu_loop: Histogram = field(default_factory=Histogram)
    cpu_send: Histogram = field(default_factory=Histogram)
    poses: PoseContinuity = field(default_factory=lambda: PoseContinuity())

    def add(self, r: dict[str, Any], pose: np.ndarray | None = None) -> None:
        self.poses.add(r, pose)
        if "bytes" in r:
            self.sent += 1
            self.bytes += float(r["bytes"])
            self.points_raw += float(r.get("n_raw", 0))
            self.points_sent += float(r.get("n_sent", 0))
            if "work_ms" in r:
                self.work[0] += 1
                self.work[1] += float(r["work_ms"])
        self.cpu_all_ms += float(r.get("cpu_ms", 0.0))
        if "cpu_send_ms" in r:
            self.cpu.add(float(r["cpu_ms"]))
            self.cpu_loop.add(float(r["cpu_loop_ms"]))
            self.cpu_send.add(float(r["cpu_send_ms"]))
        if r.get("status") != "acked":
            return
        self.acked += 1
        self.rtt_sum += float(r.get("rtt", 0.0))
        t = float(r.get("interarrival", math.nan))
        if math.isfinite(t):
            self.t_count += 1
            self.t_sum += t
            self.t_on_time += t <= 0.11
        if int(r["seq"]) > self.map_points[0] and "map_points" in r:
            self.map_points = (int(r["seq"]), int(r["map_points"]))

    def with_records(self, records: Iterable[dict[str, Any]],
                     poses: dict[int, np.ndarray] | None = None) -> ScanTotals:
        """These totals plus ``records`` (the ones still in memory) and their ``poses``, as a new
        object."""
        out = copy.deepcopy(self)
        for r in records:
            out.add(r, None if poses is None else poses.get(int(r["seq"])))
        return out

    def scans(self, skipped: int) -> dict[str, Any]:
        return {
            "sent": self.sent,
            "acked": self.acked,
            "skipped": skipped,
            "mean_kB_sent": self.bytes / self.sent / 1e3 if self.sent else None,
            "mean_points_raw": self.points_raw / self.sent if self.sent else None,
            "mean_points_sent": self.points_sent / self.sent if self.sent else None,
            "mean_work_ms": self.work[1] / self.work[0] if self.work[0] else None,
            "mean_T": self.t_sum / self.t_count if self.t_count else None,
            "frac_T_le_0.11": self.t_on_time / self.t_count if self.t_count else None,
            "mean_rtt_ms": self.rtt_sum / self.acked * 1e3 if self.acked else None,
            "map_points": max(self.map_points[1], 0),
        }


@dataclass
class PoseContinuity:
    """Over records in scan order: the longest run of scans without any pose (in scans, and in
    seconds between the capture of the poses on either side), and the jump at each switch of
    who gave the pose (edge to local, local to edge, one edge to another):
    |p_s - (p_a + (p_a - p_b) (s - a) / (a - b))| with a, b the two posed scans before s (for
    consecutive scans: p_s - (p_{s-1} + (p_{s-1} - p_{s-2})))."""

    run: int = 0  # scans without a pose since the last posed one
    max_gap_scans: int = 0
    max_gap_s: float = 0.0
    jumps: list[float] = field(default_factory=list)
    lag: Histogram = field(default_factory=Histogram)  # capture to the first pose known, ms
    _last: list[tuple[int, np.ndarray, float]] = field(default_factory=list)  # (seq, xyz, stamp), last 2
    _source: tuple[str, str] | None = None

    def add(self, r: dict[str, Any], pose: np.ndarray | None) -> None:
        if pose is None:
            self.run += 1
            self.max_gap_scans = max(self.max_gap_scans, self.run)
            return
        seq, xyz = int(r["seq"]), np.asarray(pose, np.float64)[:3, 3]
        stamp = float(r.get("capture_stamp", math.nan))
        self.lag.add(float(r.get("pose_lag_ms", math.nan)))
        if self.run and self._last:
            gap = stamp - self._last[-1][2]
            if math.isfinite(gap):
                self.max_gap_s = max(self.max_gap_s, gap)
        self.run = 0
        source = (str(r.get("pose_source") or ""), str(r.get("edge") or ""))
        if self._source is not None and source != self._source and len(self._last) == 2:
            (b, pb, _), (a, pa, _) = self._last
            if 0 < a - b and 0 < seq - a <= JUMP_SPAN and len(self.jumps) < MAX_JUMPS:
                predicted = pa + (pa - pb) * (seq - a) / (a - b)
                self.jumps.append(float(np.linalg.norm(xyz - predicted)))
        self._source = source
        self._last = [*self._last[-1:], (seq, xyz, stamp)]


class ScanLog:
    """The ring of records and poses, retiring into totals and, given a folder, onto disk."""

    def __init__(self, keep: int = 4096, folder: Path | None = None) -> None:
        self.keep = max(64, keep)
        self.records: dict[int, dict[str, Any]] = {}
        self.poses: dict[int, np.ndarray] = {}  # the pose each acked (or locally registered) scan got
        self.gt_poses: dict[int, np.ndarray] = {}
        self.totals = ScanTotals()
        self.retired = 0
        self.folder = folder
        self._csv: IO[str] | None = None
        self._writer: Any = None
        self._pose_files: dict[str, IO[bytes]] = {}

    def trim(self) -> None:
        """Retire the oldest records beyond ``keep`` (never one an ack or the sender may change)."""
        while len(self.records) > self.keep:
            seq = next(iter(self.records))
            if self.records[seq].get("status") in LIVE:
                break
            self._retire(seq, self.records.pop(seq))

    def _retire(self, seq: int, rec: dict[str, Any]) -> None:
        pose, gt = self.poses.pop(seq, None), self.gt_poses.pop(seq, None)
        self.totals.add(rec, pose)
        self.retired += 1
        if self.folder is None:
            return
        self._open()
        self._writer.writerow(rec)
        for name, value in (("acked", pose), ("gt", gt)):
            if value is not None:
                f = self._pose_files[name]
                f.write(np.int64(seq).tobytes())
                f.write(np.ascontiguousarray(value, np.float64).tobytes())

    def _open(self) -> None:
        if self._csv is not None or self.folder is None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        self._csv = open(self.folder / "robot_scans.csv", "w", newline="")
        self._writer = csv.DictWriter(self._csv, fieldnames=RECORD_FIELDS, extrasaction="ignore")
        self._writer.writeheader()
        for name in ("acked", "gt"):
            self._pose_files[name] = open(self.folder / f".robot_poses_{name}.bin", "wb")

    def write(self, out_dir: Path) -> None:
        """Every record (retired ones already on disk, the rest now) to ``robot_scans.csv`` and
        every pose to ``robot_poses.npz``."""
        if self.folder is not None and self.folder.resolve() != out_dir.resolve():
            raise ValueError(f"records spill to {self.folder}, not {out_dir}")
        self.folder = out_dir
        self._open()
        for seq in sorted(self.records):
            self._writer.writerow(self.records[seq])
        assert self._csv is not None
        self._csv.flush()
        arrays: dict[str, np.ndarray] = {}
        for name, live in (("acked", self.poses), ("gt", self.gt_poses)):
            f = self._pose_files[name]
            f.flush()
            raw = np.fromfile(f.name, dtype=np.dtype([("seq", "<i8"), ("pose", "<f8", (4, 4))]))
            seqs = np.concatenate([raw["seq"], np.array(sorted(live), np.int64)])
            poses = np.concatenate([raw["pose"], np.array([live[k] for k in sorted(live)]).reshape(-1, 4, 4)])
            arrays[f"{name}_seqs"], arrays[f"{name}_poses"] = seqs, poses
        np.savez(out_dir / "robot_poses.npz", acked_seqs=arrays["acked_seqs"],
                 acked_poses=arrays["acked_poses"], gt_seqs=arrays["gt_seqs"], gt_poses=arrays["gt_poses"])
        self.close()
        for name in ("acked", "gt"):
            (out_dir / f".robot_poses_{name}.bin").unlink(missing_ok=True)

    def close(self) -> None:
        for f in (self._csv, *self._pose_files.values()):
            if f is not None:
                f.close()
        self._csv, self._writer, self._pose_files = None, None, {}
