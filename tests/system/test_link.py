"""The link emulator as its own process, measured with plain sockets on loopback."""

from __future__ import annotations

import socket
import statistics
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from zoffload.runtime.session import free_tcp_port

pytestmark = pytest.mark.system
HEAD = "time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage\n"


@contextmanager
def emulator(trace: Path, target_port: int, extra: list[str] | None = None
             ) -> Iterator[tuple[int, subprocess.Popen[str]]]:
    port = free_tcp_port()
    p = subprocess.Popen([sys.executable, "-m", "zoffload.cli", "link", "--trace", str(trace),
                          "--listen-port", str(port), "--target", f"127.0.0.1:{target_port}", "--quiet",
                          *(extra or [])], stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None
    line = p.stdout.readline()
    assert line.startswith("ready"), line
    try:
        yield port, p
    finally:
        p.send_signal(2)
        p.wait(20)


def serve_one(port: int, ready: threading.Event, handle: Callable[[socket.socket], None]) -> None:
    """Accept one connection on ``port`` and hand it to ``handle``."""
    with socket.socket() as srv:
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", port))
        srv.listen()
        ready.set()
        conn, _ = srv.accept()
        with conn:
            handle(conn)


def sink(port: int, arrivals: list[tuple[float, int]], ready: threading.Event) -> None:
    def record(conn: socket.socket) -> None:
        while data := conn.recv(65536):
            arrivals.append((time.time(), len(data)))

    serve_one(port, ready, record)


def saturate(trace_text: str, tmp_path: Path, seconds: float) -> tuple[float, list[tuple[float, int]]]:
    trace = tmp_path / "t.csv"
    trace.write_text(trace_text)
    sink_port = free_tcp_port()
    arrivals: list[tuple[float, int]] = []
    ready = threading.Event()
    threading.Thread(target=sink, args=(sink_port, arrivals, ready), daemon=True).start()
    ready.wait(5)
    with emulator(trace, sink_port) as (port, proc):
        with socket.create_connection(("127.0.0.1", port)) as c:
            assert proc.stdout is not None
            wall_start = float(proc.stdout.readline().split("wall_start=")[1])  # clock starts now
            buf = b"\x00" * 65536
            end = time.time() + seconds
            while time.time() < end:
                c.sendall(buf)
        time.sleep(0.3)
    return wall_start, arrivals


def mbps_in(arrivals: list[tuple[float, int]], start: float, t0: float, t1: float) -> float:
    n = sum(size for t, size in arrivals if t0 <= t - start < t1)
    return n * 8 / 1e6 / (t1 - t0)


@pytest.mark.parametrize("rate", [20, 100])
def test_throughput_within_10_percent_per_second(rate: int, tmp_path: Path) -> None:
    start, arr = saturate(HEAD + f"0, {rate}, {rate}, 0, 0, 0\n", tmp_path, 3.2)
    for s in (1, 2):  # whole 1 s windows after the connection has settled
        got = mbps_in(arr, start, s, s + 1)
        assert abs(got - rate) <= 0.10 * rate, (s, got)


def test_trace_change_takes_effect_within_100_ms(tmp_path: Path) -> None:
    start, arr = saturate(HEAD + "0, 40, 40, 0, 0, 0\n2, 10, 10, 0, 0, 0\n", tmp_path, 3.5)
    assert abs(mbps_in(arr, start, 1.0, 2.0) - 40) <= 4
    assert abs(mbps_in(arr, start, 2.1, 3.1) - 10) <= 1  # from 100 ms after the change


def test_outage_stalls_then_resumes(tmp_path: Path) -> None:
    start, arr = saturate(HEAD + "0, 30, 30, 0, 0, 0\n1, 0, 0, 0, 0, 1\n2, 30, 30, 0, 0, 0\n", tmp_path, 3.0)
    assert mbps_in(arr, start, 1.05, 1.95) == 0
    assert mbps_in(arr, start, 2.1, 2.9) > 25


def echo_server(port: int, ready: threading.Event) -> None:
    def echo(conn: socket.socket) -> None:
        while data := conn.recv(4096):
            conn.sendall(data)

    serve_one(port, ready, echo)


def round_trips(trace_text: str, tmp_path: Path, n: int = 30) -> list[float]:
    trace = tmp_path / "d.csv"
    trace.write_text(trace_text)
    port = free_tcp_port()
    ready = threading.Event()
    threading.Thread(target=echo_server, args=(port, ready), daemon=True).start()
    ready.wait(5)
    rtts = []
    with emulator(trace, port) as (proxy, _), socket.create_connection(("127.0.0.1", proxy)) as c:
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for _ in range(n):
            t0 = time.perf_counter()
            c.sendall(struct.pack("<d", t0))
            got = b""
            while len(got) < 8:
                got += c.recv(8 - len(got))
            rtts.append(time.perf_counter() - t0)
            time.sleep(0.02)
    return rtts[3:]


def test_added_delay_within_5_ms(tmp_path: Path) -> None:
    rtts = round_trips(HEAD + "0, 100, 100, 30, 0, 0\n", tmp_path)
    one_way_ms = sorted(r / 2 * 1e3 for r in rtts)
    # Never early (that would be the emulator's fault whatever the load), the median on the
    # trace's delay, and nine in ten trips within 5 ms: a late trip can be a scheduling hiccup of
    # the 2-core machine under the suite's other processes (seen in CI: one trip of 27 over, and
    # once two trips over in one run). The median within 3 ms: each hop wakes an event loop or a
    # thread, and on the Intel VM of 2026-12-06 asyncio's 30 ms sleep alone woke 0.7 ms late (its
    # epoll timeout rounds up to the millisecond): medians 32.2 and 32.3 ms in two suite runs
    assert all(d >= 29 for d in one_way_ms), one_way_ms
    assert abs(statistics.median(one_way_ms) - 30) <= 3, one_way_ms
    assert sum(abs(d - 30) <= 5 for d in one_way_ms) >= 0.9 * len(one_way_ms), one_way_ms


def test_jitter_spreads_delay_but_keeps_order(tmp_path: Path) -> None:
    rtts = round_trips(HEAD + "0, 100, 100, 20, 8, 0\n", tmp_path, n=40)
    ms = [r * 1e3 for r in rtts]
    assert min(ms) >= 39 and max(ms) - min(ms) > 5  # never below 2 x delay, visibly spread


def test_report_csv_says_what_passed(tmp_path: Path) -> None:
    trace = tmp_path / "r.csv"
    trace.write_text(HEAD + "0, 16, 16, 0, 0, 0\n")
    report = tmp_path / "report.csv"
    sink_port = free_tcp_port()
    arrivals: list[tuple[float, int]] = []
    ready = threading.Event()
    threading.Thread(target=sink, args=(sink_port, arrivals, ready), daemon=True).start()
    ready.wait(5)
    with emulator(trace, sink_port, ["--report", str(report)]) as (port, _):
        with socket.create_connection(("127.0.0.1", port)) as c:
            end = time.time() + 3.3
            while time.time() < end:
                c.sendall(b"\x00" * 65536)
        time.sleep(0.5)
    rows = list(csvrows(report))
    assert rows[0][:3] == ["second", "up_mbps", "down_mbps"]
    assert abs(float(rows[3][1]) - 16) < 1.6 and float(rows[3][3]) == 16  # second 2: measured, trace


def csvrows(path: Path) -> Iterator[list[str]]:
    import csv

    with open(path) as f:
        yield from csv.reader(f)



def test_malformed_trace_exits_with_config_code_naming_the_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text(HEAD + "0, 10, 10, 0, 0, 0\n5, 10, 10, zero, 0, 0\n")
    r = subprocess.run([sys.executable, "-m", "zoffload.cli", "link", "--trace", str(bad), "--listen-port",
                        str(free_tcp_port()), "--target", "127.0.0.1:1"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "bad.csv:3: not a number" in r.stderr
