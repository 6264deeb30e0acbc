"""The link emulator's timeliness, real against its model: what the process adds to a trace.

``python -m zoffload.lab.link.ceiling`` gives the share of scans on time for their slot from the
emulator's scheduling code alone (lab/link/ceiling.py). Here the real ``zoffload link`` process
carries a stream of messages, one every 100 ms, from a plain TCP sender to a plain TCP receiver on
loopback (no Zenoh, no robot, no edge), and the receiver's on-time share (interarrival <= 110 ms)
is set beside the model's for the same trace and size (the mean of 20 seeds). The difference is
the emulator process's own part: its event loop's wake-ups, the sockets, the host.

Run: python -m benchmarks.bench_link_timing [--messages 300] [--seeds 3]   (about 8 minutes)
"""

from __future__ import annotations

import argparse
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.common import header
from zoffload.lab.link.ceiling import RUN_SEEDS, SLOT_SLACK, slot_ceiling
from zoffload.lab.link.probe import listening
from zoffload.lab.link.trace import parse_trace
from zoffload.runtime.session import free_tcp_port

HEAD = "time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage\n"
PERIOD = 0.1
# (label, the trace's one row: rate Mbps, delay ms, jitter ms; message bytes)
CASES = [
    ("steady 40 Mbps, 6 ms, no jitter", (40, 6, 0), 64_000),
    ("Wi-Fi strong: 40 Mbps, 6 ms, jitter 3 ms", (40, 6, 3), 64_000),
    ("Wi-Fi strong, uncompressed scans", (40, 6, 3), 168_000),
    ("Wi-Fi weak: 12 Mbps, 25 ms, jitter 10 ms", (12, 25, 10), 64),
    ("Wi-Fi weak, the policy's scans", (12, 25, 10), 66_000),
]


def receive(port: int, arrivals: list[float], ready: threading.Event) -> None:
    """Accept one connection; the arrival time of every whole message (4-byte length first)."""
    with listening(port) as srv:
        ready.set()
        conn, _ = srv.accept()
        with conn:
            buf = b""
            while True:
                chunk = conn.recv(1 << 16)
                if not chunk:
                    return
                buf += chunk
                while len(buf) >= 4 and len(buf) >= 4 + (n := struct.unpack("<I", buf[:4])[0]):
                    arrivals.append(time.perf_counter())
                    buf = buf[4 + n:]


def measure(row: tuple[int, int, int], size: int, messages: int, seed: int) -> float:
    """The real emulator's on-time share for ``messages`` messages of ``size`` bytes."""
    rate, delay, jitter = row
    with tempfile.TemporaryDirectory() as tmp:
        trace = Path(tmp) / "t.csv"
        trace.write_text(HEAD + f"0, {rate}, {rate}, {delay}, {jitter}, 0\n")
        target, listen = free_tcp_port(), free_tcp_port()
        arrivals: list[float] = []
        ready = threading.Event()
        rx = threading.Thread(target=receive, args=(target, arrivals, ready), daemon=True)
        rx.start()
        ready.wait(5)
        link = subprocess.Popen([sys.executable, "-m", "zoffload.cli", "link", "--trace", str(trace),
                                 "--listen-port", str(listen), "--target", f"127.0.0.1:{target}",
                                 "--seed", str(seed), "--quiet"], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True)
        try:
            assert link.stdout is not None and link.stdout.readline().startswith("ready")
            payload = struct.pack("<I", size - 4) + bytes(size - 4)
            with socket.create_connection(("127.0.0.1", listen)) as c:
                c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                t0 = time.perf_counter() + 0.2
                for k in range(messages):
                    time.sleep(max(0.0, t0 + k * PERIOD - time.perf_counter()))
                    c.sendall(payload)
                time.sleep(1.0)
        finally:
            link.send_signal(2)
            link.wait(20)
        rx.join(5)
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:], strict=False)]
    return sum(g <= SLOT_SLACK * PERIOD for g in gaps) / max(1, len(gaps))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--messages", type=int, default=300, help="messages per run, 10 a second (default 300)")
    ap.add_argument("--seeds", type=int, default=3, help="runs per case, emulator seeds 0.. (default 3)")
    a = ap.parse_args()
    header("the link emulator's on-time share for its slot: the real process against its model")
    print(f"{'case':44} {'bytes':>8} {'model':>8} {'real, per seed':>24} {'real - model':>13}")
    for label, row, size in CASES:
        trace = parse_trace(HEAD + f"0, {row[0]}, {row[0]}, {row[1]}, {row[2]}, 0\n", name=label)
        span = a.messages * PERIOD
        model = statistics.fmean(slot_ceiling(trace, size=size, seed=s, duration=span).on_time_share
                                 for s in range(RUN_SEEDS))
        real = [measure(row, size, a.messages, s) for s in range(a.seeds)]
        shown = ", ".join(f"{100 * r:.1f}" for r in real)
        diff = 100 * (statistics.fmean(real) - model)
        print(f"{label:44} {size:8,d} {100 * model:7.1f}% {shown:>23}% {diff:+12.1f}")


if __name__ == "__main__":
    main()
