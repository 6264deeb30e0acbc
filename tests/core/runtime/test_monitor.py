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
