"""The camera pipeline's records bounded for long runs: a book that keeps 100 records in memory
writes the same frames.csv and detections.npz, and reports the same figures, as one that keeps
everything (issue 11: 25 FPS for a day is 2 M frames)."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from zoffload.policy.offload import BOTH, EDGE, LOCAL, SKIP, OffloadState, Strategy
from zoffload.robot.framelog import FrameLog
from zoffload.robot.frames import FallbackRules, FrameBook

RULES = FallbackRules(reply_timeout=0.5, fallback_losses=3, probe_period=0.5, resume_after=3)
PERIOD = 0.04


class Cycle(Strategy):
    """Edge, local, both (local plus a copy), skip, chosen by a seeded generator."""

    def __init__(self, seed: int) -> None:
        self.name = "cycle"
        self.rng = random.Random(seed)

    def choose(self, st: OffloadState) -> str:
        return self.rng.choices([EDGE, LOCAL, BOTH, SKIP], weights=[5, 3, 1, 1])[0]


def persons(rng: random.Random) -> tuple[np.ndarray, np.ndarray]:
    n = rng.randrange(4)
    boxes = np.array([[rng.uniform(0, 600) for _ in range(4)] for _ in range(n)], np.float32).reshape(-1, 4)
    return boxes, np.array([rng.random() for _ in range(n)], np.float32)


def run(n: int, keep: int | None, folder: Path | None, seed: int = 1) -> tuple[FrameBook, int]:
    """A scripted run of ``n`` frames: edge answers after a few frames (ok, dropped, some never),
    local results one frame later, copies answered or not. Returns the book and the most records
    it held at once."""
    b = FrameBook(Cycle(seed), RULES, keep=keep, folder=folder)
    b.edges_changed(True, 0.0)
    rng = random.Random(seed)
    edge_due: list[tuple[float, int, str]] = []  # (answer time, seq, status)
    local_due: list[int] = []
    most = 0
    for seq in range(n):
        t = seq * PERIOD
        for due in [d for d in edge_due if d[0] <= t]:
            edge_due.remove(due)
            _, s, status = due
            b.edge_result(s, status, t, 0.02 + 0.001 * (s % 7), 0.003, *persons(rng), edge="e1")
        for s in local_due:
            boxes, scores = persons(rng)
            b.local_result(s, t, 0.03, 0.025 + 0.0001 * (s % 11), boxes, scores, cpu=0.03)
        local_due = []
        b.expire(t)
        side, probe = b.decide(seq, seq, capture=t, now=t)
        if side in (EDGE, BOTH):
            b.sent(seq, t, probe, copy=side == BOTH, edge="e1")
            b.records[seq]["bytes"] = 40_000 + seq % 100
            roll = rng.random()
            if roll < 0.9:  # answered 1-5 frames later; otherwise never (lost after the timeout)
                edge_due.append((t + PERIOD * rng.randint(1, 5), seq, "ok" if roll < 0.85 else "dropped"))
        if side in (LOCAL, BOTH):
            local_due.append(seq)
        most = max(most, len(b.records))
    b.close(n * PERIOD + 1.0, None, local_due[0] if local_due else None)
    return b, most


def comparable(summary: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in summary.items() if k not in ("records_retired", "records_on_disk")}


def test_a_bounded_book_stays_bounded_and_reports_what_an_unbounded_one_does(tmp_path: Path) -> None:
    n, keep = 20_000, 100
    full, _ = run(n, None, None)
    bounded, most = run(n, keep, tmp_path / "bounded")
    assert len(full.records) == n and full.log.retired == 0
    assert most <= keep + 10  # only the frames still being decided exceed it, briefly
    assert len(bounded.records) <= keep and len(bounded.persons) <= keep
    assert bounded.log.retired == n - len(bounded.records)
    s_full, s_bounded = full.summary(), bounded.summary()
    assert s_bounded["records_retired"] == bounded.log.retired and s_bounded["records_on_disk"]
    assert s_full["records_retired"] == 0
    assert comparable(s_bounded) == comparable(s_full)  # exact, not approximately
    assert s_full["balanced"] and s_full["balance"]["frames_in"] == n
    assert s_full["edge_rtt_ms"] is not None and s_full["robot_rtt_ms"] is not None
    # The files: what was retired as the run went plus the final write = the unbounded book's
    full.log.write(tmp_path / "full", PERIOD)
    bounded.log.write(tmp_path / "bounded", PERIOD)
    csv_full = (tmp_path / "full" / "frames.csv").read_bytes()
    assert (tmp_path / "bounded" / "frames.csv").read_bytes() == csv_full
    assert csv_full.count(b"\n") == n + 1
    a, b = np.load(tmp_path / "full" / "detections.npz"), np.load(tmp_path / "bounded" / "detections.npz")
    assert sorted(a.files) == sorted(b.files) == ["boxes", "counts", "period", "scores", "seqs"]
    for key in a.files:
        assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key]), key
    assert a["counts"].sum() == len(a["boxes"]) > 0
    assert not list((tmp_path / "bounded").glob(".*"))  # the spill files are gone


def test_without_a_folder_retired_records_are_only_counted(tmp_path: Path) -> None:
    full, _ = run(3000, None, None, seed=2)
    counted, _ = run(3000, 64, None, seed=2)
    s = counted.summary()
    assert s["records_retired"] == 3000 - len(counted.records) > 0 and not s["records_on_disk"]
    assert comparable(s) == comparable(full.summary())
    counted.log.write(tmp_path, PERIOD)  # only what is still in memory
    assert (tmp_path / "frames.csv").read_text().count("\n") == len(counted.records) + 1


def test_a_short_run_writes_what_the_unbounded_book_writes(tmp_path: Path) -> None:
    """Experiments are short: nothing retires, and the files are the unbounded book's."""
    full, _ = run(500, None, None, seed=3)
    short, _ = run(500, 4096, tmp_path / "short", seed=3)
    assert short.log.retired == 0 and not (tmp_path / "short").exists()  # nothing written before the end
    full.log.write(tmp_path / "full", PERIOD)
    short.log.write(tmp_path / "short", PERIOD)
    assert (tmp_path / "short" / "frames.csv").read_bytes() == (tmp_path / "full" / "frames.csv").read_bytes()
    a, b = np.load(tmp_path / "full" / "detections.npz"), np.load(tmp_path / "short" / "detections.npz")
    assert all(np.array_equal(a[k], b[k]) for k in a.files)


def test_records_retire_oldest_first_and_never_past_a_pending_one_or_a_copy_in_flight() -> None:
    log = FrameLog(keep=2)
    for seq in range(5):
        log.records[seq] = {"seq": seq, "status": "local_done"}
    log.records[1]["status"] = "pending"
    log.trim()
    assert list(log.records) == [1, 2, 3, 4] and log.retired == 1  # 0 retired; 1 still pending
    log.records[1]["status"] = "edge_done"
    log.trim(held={2})  # 2's copy is still in flight
    assert list(log.records) == [2, 3, 4] and log.retired == 2
    log.trim()
    assert list(log.records) == [3, 4] and log.retired == 3


def test_persons_out_of_seq_order_are_sorted_in_the_detections_file(tmp_path: Path) -> None:
    log = FrameLog(keep=1, folder=tmp_path)
    one = (np.array([[1, 2, 3, 4]], np.float32), np.array([0.5], np.float32))
    two = (np.array([[5, 6, 7, 8], [9, 10, 11, 12]], np.float32), np.array([0.6, 0.7], np.float32))
    for seq, p in ((5, two), (2, one), (9, one)):  # a seq booked out of order
        log.records[seq] = {"seq": seq, "status": "local_done"}
        log.persons[seq] = p
        log.trim()
    log.write(tmp_path, 0.04)
    z = np.load(tmp_path / "detections.npz")
    assert z["seqs"].tolist() == [2, 5, 9] and z["counts"].tolist() == [1, 2, 1]
    assert z["boxes"][:, 0].tolist() == [1, 5, 9, 1]
    assert z["scores"].tolist() == pytest.approx([0.5, 0.6, 0.7, 0.5])
    with pytest.raises(ValueError, match="spill"):
        FrameLog(keep=1, folder=tmp_path / "a").write(tmp_path / "b", 0.04)
