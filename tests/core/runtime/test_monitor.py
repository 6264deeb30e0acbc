"""Monitors: moving averages, byte rates, CPU, RAPL."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from zoffload.runtime.monitor import ByteRate, CpuMonitor, MovingAverage, RaplMonitor


def test_moving_average_and_byte_rate() -> None:
    ma = MovingAverage(3)
    assert np.isnan(ma.value)
    for v in (1, 2, 3, 4, float("nan")):
        ma.add(v)
    assert ma.value == pytest.approx(3.0)
    counter = [0.0]
    rate = ByteRate(lambda: counter[0])
    time.sleep(0.2)
    counter[0] = 1e6
    mbps = rate.sample()
    assert 8e-6 * 1e6 / 0.5 < mbps < 8e-6 * 1e6 / 0.19  # 1 MB over ~0.2 s = ~40 Mbps


def test_cpu_monitor_sees_this_process_working() -> None:
    cpu = CpuMonitor()
    end = time.process_time() + 0.3
    while time.process_time() < end:
        pass
    system, proc = cpu.sample()
    assert proc > 30 and 0 < system <= 100


def test_rapl_reports_unavailable_rather_than_a_number(tmp_path: Path) -> None:
    missing = RaplMonitor(tmp_path / "no-powercap")
    assert not missing.available and np.isnan(missing.sample())
    # A fake powercap tree (this machine has no RAPL): the arithmetic of Δenergy / Δt
    zone = tmp_path / "intel-rapl:0"
    zone.mkdir()
    (zone / "energy_uj").write_text("1000000")
    fake = RaplMonitor(tmp_path)
    assert fake.available and np.isnan(fake.sample())
    time.sleep(0.1)
    (zone / "energy_uj").write_text("3000000")  # +2 J
    assert 5 < fake.sample() < 21


def test_sample_log_is_bounded_keeps_exact_means_and_spools_everything(tmp_path: Path) -> None:
    """A daemon that runs for days: memory holds only the newest samples, the means cover all of
    them, and the spool file has every one."""
    import csv

    from zoffload.runtime.monitor import SampleLog

    spool = tmp_path / "monitor.csv"
    log = SampleLog(("t", "x"), keep=10, path=spool)
    for i in range(1000):
        log.add({"t": float(i), "x": float("nan") if i % 2 else float(i)})
    assert len(log.recent) == 10 and log.recent[-1]["t"] == 999.0 and log.count == 1000
    means = log.means()
    assert means["t"] == pytest.approx(499.5)
    assert means["x"] == pytest.approx(np.mean(np.arange(0, 1000, 2)))  # NaN samples left out
    log.write(spool)  # the spool is the file asked for: nothing rewritten
    log.close()
    rows = list(csv.DictReader(open(spool)))
    assert len(rows) == 1000 and rows[0]["t"] == "0.0"
    # Without a spool: the kept samples only
    mem = SampleLog(("t",), keep=5)
    for i in range(20):
        mem.add({"t": float(i)})
    mem.write(tmp_path / "kept.csv")
    kept = [r["t"] for r in csv.DictReader(open(tmp_path / "kept.csv"))]
    assert kept == [str(float(i)) for i in range(15, 20)]
    assert SampleLog(("t",)).means() == {"t": None}
