"""The robot's records stay bounded in memory however long it runs; the totals and the files on
disk still hold every scan."""

from __future__ import annotations

import csv
import math
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from zoffload.robot.scanlog import Histogram, ScanLog


def record(seq: int, status: str = "acked") -> dict[str, object]:
    return {"seq": seq, "status": status, "bytes": 1000, "n_raw": 100, "n_sent": 50, "work_ms": 2.0,
            "cpu_ms": 1.0 + (seq % 10) / 10, "cpu_loop_ms": 0.5, "cpu_send_ms": 0.5, "rtt": 0.05,
            "interarrival": 0.1 if seq % 4 else 0.2, "map_points": seq}


def fill(log: ScanLog, n: int) -> None:
    for seq in range(n):
        log.records[seq] = record(seq)
        log.poses[seq] = np.eye(4) * seq
        log.gt_poses[seq] = np.eye(4)
        log.trim()


def test_memory_stays_flat_and_totals_count_every_scan(tmp_path: Path) -> None:
    log = ScanLog(keep=500, folder=tmp_path)
    fill(log, 2000)  # warm: the ring is full
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for seq in range(2000, 22_000):
        log.records[seq] = record(seq)
        log.poses[seq] = np.eye(4)
        log.trim()
    grown = sum(s.size_diff for s in tracemalloc.take_snapshot().compare_to(before, "filename"))
    tracemalloc.stop()
    assert len(log.records) == 500 and len(log.poses) == 500
    assert grown < 2_000_000, grown  # 20k more scans, far less than the ~1 kB each they would hold
    scans = log.totals.with_records(log.records.values()).scans(skipped=0)
    assert scans["sent"] == scans["acked"] == 22_000 and scans["map_points"] == 21_999
    assert scans["mean_T"] == pytest.approx(0.125) and scans["frac_T_le_0.11"] == pytest.approx(0.75)
    log.write(tmp_path)
    rows = list(csv.DictReader(open(tmp_path / "robot_scans.csv")))
    assert [int(r["seq"]) for r in rows] == list(range(22_000))
    poses = np.load(tmp_path / "robot_poses.npz")
    assert list(poses["acked_seqs"]) == list(range(22_000)) and poses["acked_poses"][7][0, 0] == 7
    assert len(poses["gt_seqs"]) == 2000  # the ground truth given for the first 2000
    assert not list(tmp_path.glob(".robot_poses_*"))


def test_a_record_an_ack_may_still_change_is_not_retired() -> None:
    log = ScanLog(keep=64)
    log.records[0] = record(0, status="in_flight")
    fill_from = 1
    for seq in range(fill_from, 200):
        log.records[seq] = record(seq)
        log.trim()
    assert 0 in log.records and len(log.records) == 200  # all held back behind the live one
    log.records[0]["status"] = "lost"
    log.trim()
    assert 0 not in log.records and len(log.records) == 64


def test_histogram_quantiles_within_a_percent() -> None:
    h = Histogram()
    values = np.random.default_rng(0).lognormal(0.5, 1.0, 100_000)
    for v in values:
        h.add(float(v))
    for q in (0.5, 0.95):
        got = h.quantile(q)
        assert got is not None and abs(got / np.quantile(values, q) - 1) < 0.02
    assert h.mean() == pytest.approx(values.mean()) and Histogram().quantile(0.5) is None
    h.add(math.nan)
    assert h.n == 100_000


def test_pose_gaps_and_switch_jumps_over_records_in_scan_order() -> None:
    from zoffload.robot.scanlog import PoseContinuity

    def pose(x: float) -> np.ndarray:
        p = np.eye(4)
        p[0, 3] = x
        return p

    c = PoseContinuity()
    rows = [(0, "edge", "e1", 0.0), (1, "edge", "e1", 1.0), (2, None, None, None), (3, None, None, None),
            (4, "local", "", 4.2), (5, "local", "", 5.2), (6, "edge", "e2", 6.0)]
    for seq, src, edge, x in rows:
        c.add({"seq": seq, "capture_stamp": seq / 10, "pose_source": src, "edge": edge},
              None if x is None else pose(x))
    assert c.max_gap_scans == 2 and abs(c.max_gap_s - 0.3) < 1e-9  # poses at 0.1 s and 0.4 s
    assert np.allclose(c.jumps, [0.2, 0.2])  # 4.2 against 4.0 predicted; 6.0 against 6.2
