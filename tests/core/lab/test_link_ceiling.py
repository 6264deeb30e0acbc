"""The on-time ceiling of a trace (lab/link/ceiling.py), run on the emulator's own scheduling."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from zoffload.lab.link.ceiling import RUN_SEEDS, main, run_streams, slot_ceiling, stream_shares
from zoffload.lab.link.trace import constant, load_trace, parse_trace


def test_a_steady_link_puts_every_scan_on_time() -> None:
    c = slot_ceiling(constant(100.0, delay_ms=30.0), size=20_000, duration=10.0)
    assert (c.sent, c.received, c.skipped) == (100, 100, 0)
    assert c.on_time_share == 1.0
    assert abs(c.late_ms_p95) < 1.0


def test_jitter_makes_small_scans_late_and_a_longer_slot_absorbs_it() -> None:
    jittery = constant(100.0, delay_ms=50.0, jitter_ms=15.0)
    one = slot_ceiling(jittery, size=1, duration=60.0, seed=3)
    two = slot_ceiling(jittery, size=1, every=2, duration=60.0, seed=3)
    # a 10 ms slack against the difference of two clipped 15 ms Gaussians: many late, not most
    assert 0.55 < one.on_time_share < 0.95
    assert two.on_time_share > one.on_time_share + 0.03
    assert one.late_ms_p95 > 10.0
    # bigger scans have more pieces, each with its own delay: never more on time
    big = [slot_ceiling(jittery, size=60_000, duration=60.0, seed=s).on_time_share for s in range(3)]
    small = [slot_ceiling(jittery, size=1, duration=60.0, seed=s).on_time_share for s in range(3)]
    assert sum(big) < sum(small)


def test_scans_in_an_outage_are_skipped_and_the_next_slot_covers_them() -> None:
    trace = parse_trace("time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage\n"
                        "0, 50, 50, 20, 0, 0\n2, 0, 0, 0, 0, 1\n3, 50, 50, 20, 0, 0\n", name="gap")
    c = slot_ceiling(trace, size=1_000, duration=5.0)
    assert c.skipped == 10 and c.received == 40
    assert c.on_time == c.received - 1  # the scan after the gap was meant to take 11 periods


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError):
        slot_ceiling(constant(10.0), size=0)
    with pytest.raises(ValueError):
        slot_ceiling(constant(10.0), every=0)


def test_the_command_prints_a_row_per_size_and_pace(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--trace", "capped", "--sizes", "1", "40000", "--every", "1", "--seeds", "2"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| capped")]
    assert len(rows) == 2 and all("%" in r for r in rows)
    assert main(["--trace", "no-such-trace"]) == 2


def test_runs_are_set_against_streams_over_their_stretch_of_the_trace(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run1"
    run.mkdir()
    (run / "experiment.json").write_text(json.dumps({"max_scans": 300, "rate": 10.0, "seed": 0}))
    (run / "results.json").write_text(json.dumps({"trace": "/gone/tree/cellular-heldout.csv", "S_kB": 50.0,
                                                  "on_time_slot": 0.7}))
    bad = tmp_path / "run2"
    bad.mkdir()
    assert main(["--runs", str(run), str(bad)]) == 2  # the unreadable one is named, the other printed
    out = capsys.readouterr()
    line = next(x for x in out.out.splitlines() if x.startswith(f"| {run} "))
    trace = load_trace("cellular-heldout")
    tiny, steady = stream_shares(trace, period=0.1, size=50_000, start=0.0, duration=30.0)
    assert f"| cellular-heldout | 50 | 70.0 % | {100 * tiny:.1f} % | {100 * steady:.1f} % | – |" in line
    assert str(bad) in out.err
    # the mean over seeds: a run's own seed drew other messages' jitter too, not only its scans'
    assert tiny == pytest.approx(sum(slot_ceiling(trace, size=1, seed=s, duration=30.0).on_time_share
                                     for s in range(RUN_SEEDS)) / RUN_SEEDS)
    # the run's stretch of the trace: from its first scan on the link's clock
    (run / "link.log").write_text("clock wall_start=100.0\n")
    (run / "scans.csv").write_text("seq,capture_stamp\n0,125.0\n1,125.1\n")
    later = run_streams(run)
    assert later == stream_shares(trace, period=0.1, size=50_000, start=25.0, duration=30.0) != (tiny, steady)


def test_a_runs_own_scans_are_replayed_alone_on_its_link(tmp_path: Path) -> None:
    """The run's sizes, send times and announced skips through the emulator's model: a scan too
    big for its slot is late, the one queued behind it is not, a slot after a skip is longer."""
    import csv

    from zoffload.lab.link.ceiling import own_scans_share

    trace = tmp_path / "steady.csv"
    trace.write_text("time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage\n0, 10, 10, 10, 0, 0\n")
    run = tmp_path / "run1"
    run.mkdir()
    (run / "results.json").write_text(json.dumps({"trace": str(trace), "S_kB": 1.0}))
    (run / "experiment.json").write_text(json.dumps({"max_scans": 30, "rate": 10.0}))
    (run / "link.log").write_text("listening\nclock wall_start=1000.000000\n")
    rows = []
    for seq in range(20):
        if seq == 12:
            continue  # skipped on purpose: the next scan says so and gets two periods
        rows.append({"seq": seq, "capture_stamp": 1000.5 + 0.1 * seq, "send_stamp": 50.0 + 0.1 * seq,
                     "bytes": 200_000 if seq == 5 else 1_000, "skipped": 1 if seq == 13 else 0})
    with open(run / "scans.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    # 19 scans sent, 18 interarrivals: only the 200 kB scan (160 ms at 10 Mbps) is late
    assert own_scans_share(run) == pytest.approx(17 / 18)
    (run / "link.log").write_text("listening\n")  # no clock: unknown
    assert own_scans_share(run) is None
