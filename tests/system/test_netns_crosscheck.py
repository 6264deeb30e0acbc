"""Cross-check: the user-space emulator against the kernel's tbf on a veth pair, same cap."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from zoffload.lab.link import netns
from zoffload.runtime.session import free_tcp_port

pytestmark = pytest.mark.system
RATE = 20.0
SECONDS = 4


def probe(*args: str) -> list[str]:
    return [sys.executable, "-m", "zoffload.lab.link.probe", *args]


def measure_netns() -> list[float]:
    with netns.NetnsLink(RATE) as link:
        sink = link.popen("edge", probe("sink", "9000", str(SECONDS), link.addr["edge"]),
                          stdout=subprocess.PIPE)
        assert sink.stdout is not None and sink.stdout.readline().strip() == "listening"
        sender = link.popen("robot", probe("send", link.addr["edge"], "9000", str(SECONDS + 1)))
        out = json.loads(sink.stdout.readline())
        sender.wait(30)
        sink.wait(30)
    return out["mbps"]


def measure_emulator(tmp_path: Path) -> list[float]:
    trace = tmp_path / "cap.csv"
    trace.write_text(f"time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage\n0, {RATE}, {RATE}, 0, 0, 0\n")
    sink_port, link_port = free_tcp_port(), free_tcp_port()
    sink = subprocess.Popen(probe("sink", str(sink_port), str(SECONDS)), stdout=subprocess.PIPE, text=True)
    assert sink.stdout is not None and sink.stdout.readline().strip() == "listening"
    emu = subprocess.Popen([sys.executable, "-m", "zoffload.cli", "link", "--trace", str(trace),
                            "--listen-port", str(link_port), "--target", f"127.0.0.1:{sink_port}", "--quiet"],
                           stdout=subprocess.PIPE, text=True)
    assert emu.stdout is not None and emu.stdout.readline().startswith("ready")
    sender = subprocess.Popen(probe("send", "127.0.0.1", str(link_port), str(SECONDS + 1)))
    out = json.loads(sink.stdout.readline())
    sender.wait(30)
    sink.wait(30)
    emu.send_signal(2)
    emu.wait(20)
    return out["mbps"]


def test_emulator_matches_kernel_tbf(tmp_path: Path) -> None:
    reason = netns.available()
    if reason:
        pytest.skip(f"kernel cross-check {reason}")
    try:
        kernel = measure_netns()
    except netns.NetnsError as exc:
        pytest.skip(f"network namespaces not usable here: {exc}")
    time.sleep(0.2)
    ours = measure_emulator(tmp_path)
    # Whole seconds after the first: both within 10 % of the cap and of each other
    for k, o in zip(kernel[1:], ours[1:], strict=True):
        assert abs(k - RATE) <= 0.1 * RATE, kernel
        assert abs(o - RATE) <= 0.1 * RATE, ours
        assert abs(o - k) <= 0.1 * RATE, (kernel, ours)
