"""The camera pipeline's per-frame records and person detections, bounded however long it runs.

A camera at 25 FPS books 2 M frames a day. The newest ``keep`` records stay in memory, where
results, losses and the strategy still read or change them; an older *finished* one is retired:
folded into running totals (the figures of ``vision_metrics.json``) and, when the run has a results
folder, appended at once to ``frames.csv`` (header written once) and its person boxes to a hidden
binary file that ``write`` merges into ``detections.npz``. Without a folder a retired record is only
counted (``records_retired`` in the summary). Records retire oldest first and never past one that
is still pending or whose copy is still in flight (``held``), so the files stay in seq order (the
camera's seqs increase) and ``keep`` is exceeded only by the few frames still being decided, for
at most a reply timeout.

Short runs (fewer than ``keep`` frames) write exactly what an unbounded book writes; longer ones
write the same files, and their summary figures are exact: means are running sums over records in
the order they were booked, retired ones first, the same sums an unbounded book makes.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Container, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

FRAME_FIELDS = ["seq", "index", "capture", "side", "probe", "send", "result", "status", "rtt_ms",
                "edge_infer_ms", "edge_queue_ms", "local_infer_ms", "bytes", "n_persons", "copy",
                "copy_rtt_ms", "est_local_ms", "est_edge_ms", "edge", "encoding", "trial", "encode_ms",
                "sent_size", "alone", "put", "link_ms"]
_INDEX = np.dtype([("seq", "<i8"), ("count", "<i8")])  # one entry per retired frame with persons
_PERSONS_INDEX, _PERSONS_ROWS = ".detections_index.bin", ".detections_rows.bin"  # rows: x1 y1 x2 y2 score


@dataclass
class Mean:
    """A running mean of finite values (``None`` when there were none)."""

    n: int = 0
    total: float = 0.0

    def add(self, x: Any) -> None:
        if x is not None and math.isfinite(x):
            self.n += 1
            self.total += float(x)

    def value(self) -> float | None:
        return self.total / self.n if self.n else None


@dataclass
class FrameTotals:
    """The summary's per-record figures as running sums."""

    robot_rtt_ms: Mean = field(default_factory=Mean)  # frames detected locally
    edge_rtt_ms: Mean = field(default_factory=Mean)  # frames detected on the edge
    local_infer_ms: Mean = field(default_factory=Mean)  # every local inference (copies' frames too)
    edge_infer_ms: Mean = field(default_factory=Mean)  # frames detected on the edge

    def add(self, r: dict[str, Any]) -> None:
        status = r["status"]
        if status == "local_done":
            self.robot_rtt_ms.add(r.get("rtt_ms"))
        elif status == "edge_done":
            self.edge_rtt_ms.add(r.get("rtt_ms"))
            self.edge_infer_ms.add(r.get("edge_infer_ms"))
        self.local_infer_ms.add(r.get("local_infer_ms"))

    def with_records(self, records: Iterable[dict[str, Any]]) -> FrameTotals:
        """These totals plus ``records`` (the ones still in memory), as a new object."""
        out = FrameTotals(*(Mean(m.n, m.total) for m in (self.robot_rtt_ms, self.edge_rtt_ms,
                                                         self.local_infer_ms, self.edge_infer_ms)))
        for r in records:
            out.add(r)
        return out

    def figures(self) -> dict[str, float | None]:
        return {"robot_rtt_ms": self.robot_rtt_ms.value(), "edge_rtt_ms": self.edge_rtt_ms.value(),
                "local_infer_ms": self.local_infer_ms.value(), "edge_infer_ms": self.edge_infer_ms.value()}


class FrameLog:
    """Records and person detections by seq; ``keep=None`` keeps everything (the lab's simulation
    reads every record back)."""

    def __init__(self, keep: int | None = None, folder: Path | None = None) -> None:
        self.keep = None if keep is None else max(1, keep)
        self.folder = folder
        self.records: dict[int, dict[str, Any]] = {}
        self.persons: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # person boxes and scores
        self.totals = FrameTotals()
        self.retired = 0
        self._csv: IO[str] | None = None
        self._writer: Any = None
        self._persons: tuple[IO[bytes], IO[bytes]] | None = None

    def trim(self, held: Container[int] = ()) -> None:
        """Retire the oldest records beyond ``keep``, stopping at the first one not finished or
        ``held`` (a copy still in flight: its answer still updates the record)."""
        if self.keep is None:
            return
        while len(self.records) > self.keep:
            seq = next(iter(self.records))
            if self.records[seq]["status"] == "pending" or seq in held:
                break
            self._retire(seq, self.records.pop(seq), self.persons.pop(seq, None))

    def _retire(self, seq: int, rec: dict[str, Any], persons: tuple[np.ndarray, np.ndarray] | None) -> None:
        self.totals.add(rec)
        self.retired += 1
        if self.folder is None:
            return
        self._open(self.folder)
        self._writer.writerow(rec)
        if persons is not None:
            assert self._persons is not None
            index, rows = self._persons
            index.write(np.array([(seq, len(persons[1]))], _INDEX).tobytes())
            rows.write(_rows(*persons).tobytes())

    def _open(self, folder: Path) -> None:
        if self._csv is not None:
            return
        folder.mkdir(parents=True, exist_ok=True)
        self._csv = open(folder / "frames.csv", "w", newline="")
        self._writer = csv.DictWriter(self._csv, fieldnames=FRAME_FIELDS, extrasaction="ignore")
        self._writer.writeheader()
        self._persons = (open(folder / _PERSONS_INDEX, "wb"), open(folder / _PERSONS_ROWS, "wb"))

    def totals_now(self) -> FrameTotals:
        """Retired and in-memory records together."""
        return self.totals.with_records(self.records.values())

    def write(self, out_dir: Path, period: float) -> None:
        """Every record (retired ones already on disk, the rest now) to ``frames.csv`` and every
        frame's person detections to ``detections.npz`` (seqs, counts, boxes, scores, period)."""
        if self.folder is not None and self.folder.resolve() != out_dir.resolve():
            raise ValueError(f"frame records spill to {self.folder}, not {out_dir}")
        self.folder = out_dir
        self._open(out_dir)
        for seq in sorted(self.records):
            self._writer.writerow(self.records[seq])
        assert self._csv is not None and self._persons is not None
        for f in (self._csv, *self._persons):
            f.flush()
        index = np.fromfile(out_dir / _PERSONS_INDEX, _INDEX)
        rows = np.fromfile(out_dir / _PERSONS_ROWS, "<f4").reshape(-1, 5)
        live = sorted(self.persons)
        seqs = np.concatenate([index["seq"], np.array(live, np.int64)])
        counts = np.concatenate([index["count"], np.array([len(self.persons[s][1]) for s in live], np.int64)])
        rows = np.concatenate([rows, *(_rows(*self.persons[s]) for s in live)])
        seqs, counts, rows = _by_seq(seqs, counts, rows)
        boxes, scores = np.ascontiguousarray(rows[:, :4]), np.ascontiguousarray(rows[:, 4])
        np.savez(out_dir / "detections.npz", seqs=seqs, counts=counts, boxes=boxes, scores=scores,
                 period=period)
        self.close()
        for name in (_PERSONS_INDEX, _PERSONS_ROWS):
            (out_dir / name).unlink(missing_ok=True)

    def close(self) -> None:
        for f in (self._csv, *(self._persons or ())):
            if f is not None:
                f.close()
        self._csv, self._writer, self._persons = None, None, None


def _rows(boxes: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """One frame's detections as float32 rows (x1, y1, x2, y2, score)."""
    return np.column_stack([np.asarray(boxes, np.float32).reshape(-1, 4),
                            np.asarray(scores, np.float32).reshape(-1, 1)])


def _by_seq(seqs: np.ndarray, counts: np.ndarray,
            rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames (and their runs of rows) in seq order; already in order when the camera's seqs
    increase, as they do."""
    order = np.argsort(seqs, kind="stable")
    if np.array_equal(order, np.arange(len(seqs))):
        return seqs, counts, rows
    starts = np.cumsum(counts) - counts
    new_counts = counts[order]
    new_starts = np.cumsum(new_counts) - new_counts
    take = (np.arange(int(new_counts.sum())) - np.repeat(new_starts, new_counts)
            + np.repeat(starts[order], new_counts))
    return seqs[order], new_counts, rows[take]
