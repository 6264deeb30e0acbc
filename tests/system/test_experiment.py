"""The scan experiment harness with real processes: robot -> link emulator -> edge."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.system.procs import script

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")

HEAD = "time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage\n"
# Good for 1.5 s, then 12 Mbps: raw simulator scans need ~27 Mbps, 10 cm voxels (~9 Mbps) fit.
BAD_LINK = HEAD + "0, 100, 100, 2, 0, 0\n1.5, 12, 12, 30, 5, 0\n"


def experiment(tmp_path: Path, policy: str, trace: Path, scans: int, name: str) -> dict:
    out = tmp_path / name
    r = subprocess.run(script("zoffload") + ["experiment", "scan", "--trace", str(trace), "--policy", policy,
                                             "--out", str(out), "--max-scans", str(scans)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads((out / "results.json").read_text())


def test_raw_degrades_on_a_bad_link_while_local_and_downsampled_do_not(tmp_path: Path) -> None:
    trace = tmp_path / "bad.csv"
    trace.write_text(BAD_LINK)
    local = experiment(tmp_path, "local", trace, 60, "local")
    raw = experiment(tmp_path, "raw", trace, 60, "raw")
    small = experiment(tmp_path, "fixed:0.1", trace, 60, "fixed")
    # Local: (nearly) every scan, at the sensor period (a loaded machine may make its KISS-ICP miss one)
    assert local["scans_received"] == local["scans_sent"] >= 58
    assert 0.085 < local["T_mean"] < 0.13 and local["S_kB"] is None
    # Raw through 12 Mbps: fewer scans reach the edge, further apart
    assert raw["scans_received"] < 0.7 * raw["scans_produced"], raw
    assert raw["T_mean"] > 0.15, raw
    assert raw["scans_produced"] == 60
    # 10 cm voxels fit the same link
    assert small["scans_received"] >= 0.9 * small["scans_produced"] and small["T_mean"] < 0.13, small
    assert 0.5 * small["scans_received"] <= small["scans_registered"] <= small["scans_received"], small
    assert small["points_after"] < 0.5 * small["points_before"]
    # The robot's CPU per scan is a figure of every row: the offload path, or KISS-ICP locally
    assert 0 < small["robot_cpu_ms"] < local["robot_cpu_ms"] and small["robot_process_cpu_ms"] > 0
    assert small["scans_skipped"] == 0 and small["delivered_or_skipped"] >= 0.9
    assert small["on_time_slot"] > 0.5
    # the emulator's model alone: 1-byte scans, and a steady stream of the run's size
    assert 0.5 < small["on_time_tiny"] <= 1.0 and 0.5 < small["on_time_steady_size"] <= 1.0
    assert "on_time_tiny" not in local
    # The emulator really shaped the bad phase, and every scan record says what the link was
    with open(tmp_path / "raw" / "link.csv") as f:
        link = list(csv.DictReader(f))
    assert max(float(x["up_mbps"]) for x in link[3:6]) < 12 * 1.1
    with open(tmp_path / "raw" / "scans.csv") as f:
        recs = list(csv.DictReader(f))
    assert {r["link_up_mbps"] for r in recs} >= {"100.0", "12.0"}
    assert {"seq", "voxel", "bytes", "interarrival", "rtt", "status", "reason", "skipped",
            "cpu_ms"} <= set(recs[0])
    # The report renders our rows, the paper's rows and the plots
    r = subprocess.run(script("zoffload") + ["report", str(tmp_path / "local"), str(tmp_path / "raw"),
                                             str(tmp_path / "fixed"), "--out", str(tmp_path / "report")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    md = (tmp_path / "report" / "report.md").read_text()
    assert "| raw |" in md and "| local | (no network) |" in md and "(paper)" in md
    for png in ("T_over_time.png", "points_per_scan.png", "maps.png"):
        assert (tmp_path / "report" / png).stat().st_size > 10_000


def test_a_run_cut_short_still_writes_what_it_measured(tmp_path: Path) -> None:
    out = tmp_path / "cut"
    # Ctrl-C as a user at a terminal sends it: with SIGINT's default action in the child (a shell
    # running this suite in the background, as CI may, starts it with SIGINT ignored, and Python
    # then installs no KeyboardInterrupt at all)
    p = subprocess.Popen(script("zoffload") + ["experiment", "scan", "--trace", "ethernet", "--policy",
                                               "fixed:0.05", "--out", str(out), "--max-scans", "600"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    assert p.stdout is not None
    for line in p.stdout:  # wait until scans are being acked
        if " acked" in line and "scans 0/" not in line or time.monotonic() > deadline:
            break
    os.kill(p.pid, signal.SIGINT)
    rest = p.communicate(timeout=120)[0]
    assert p.returncode == 0, rest
    res = json.loads((out / "results.json").read_text())
    assert res["cut_short"] is True
    assert 0 < res["scans_sent"] < 600 and res["balance"]["in_flight"] == 0


def test_bad_trace_or_policy_is_a_config_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text(HEAD + "0, 10, 10, 0, 0\n")
    for args in (["--trace", str(bad), "--policy", "raw"], ["--trace", "ethernet", "--policy", "magic"]):
        r = subprocess.run([sys.executable, "-m", "zoffload.cli", "experiment", "scan", *args, "--out",
                            str(tmp_path / "x")], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, r.stderr
    assert "bad.csv:2" in subprocess.run(
        [sys.executable, "-m", "zoffload.cli", "experiment", "scan", "--trace", str(bad), "--policy", "raw",
         "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=60).stderr


# -m slow (two whole runs): tests/core/lab/test_report.py makes one row of repeated runs, and
# tests/core/lab/test_detect_sweep.py repeats runs into their folders with their own seeds
@pytest.mark.slow
def test_repeated_runs_make_one_row_with_mean_and_spread(tmp_path: Path) -> None:
    out = tmp_path / "rate"
    r = subprocess.run(script("zoffload") + ["experiment", "scan", "--trace", "ethernet", "--policy", "rate",
                                             "--coding", "q16d", "--out", str(out), "--max-scans", "10",
                                             "--repeat", "2"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    rows = [json.loads((out / f"run{i}" / "results.json").read_text()) for i in (1, 2)]
    assert [row["link_seed"] for row in rows] == [0, 1]
    assert all(row["scans_produced"] == 10 and row["policy"] == "rate+q16d" for row in rows)
    r = subprocess.run(script("zoffload") + ["report", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "| rate+q16d (2 runs) | ethernet |" in (out / "report.md").read_text()


@pytest.mark.slow  # a whole run for one retry; the harness's starts run in every test here
def test_an_edge_that_cannot_listen_is_started_again_on_other_ports(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A port taken between being picked and the edge listening on it (a detection sweep lost a run
    so): the edge really fails to bind (this test holds the port), and the run starts it again on
    other ports instead of failing."""
    import socket

    from zoffload.lab import runner
    from zoffload.lab.scan_experiment import ScanExperiment, run_scan_experiment
    from zoffload.runtime.session import free_tcp_port

    held = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    held.bind(("127.0.0.1", 0))  # bound, not listening: the edge cannot bind, a connection is refused
    picks = iter([held.getsockname()[1]])
    monkeypatch.setattr(runner, "free_tcp_port", lambda: next(picks, None) or free_tcp_port())
    try:
        row = run_scan_experiment(ScanExperiment(trace="ethernet", policy="fixed:0.1",
                                                 out=str(tmp_path / "run"), max_scans=20))
    finally:
        held.close()
    assert "start 1 of 3 failed" in capsys.readouterr().out
    assert row["scans_sent"] == 20 and row["balance"]["in_flight"] == 0
