"""Scan-stream throughput: zoffload's robot -> edge path vs raw Zenoh put/sub, same payloads.

Both sides are separate processes on loopback TCP with shared memory OFF (so every byte crosses
the socket), sending raw KITTI-360 HDL-64 scans (~1.45 MB encoded) as fast as the sender can;
the raw publisher uses congestion control DROP, the robot its own (BLOCK_FIRST for scans).
Raw: pre-encoded bytes put in a loop to a bare subscriber. zoffload: the robot daemon (per-scan
NaN filter, wire encoding, put, ack booking) to ``zoffload-edge --no-mapping`` (decode, stamp,
queue, ack). Delivered = scans that reached the receiver.

Run: python -m benchmarks.bench_stream [seconds]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import zenoh

from benchmarks.common import header, kitti_dir
from zoffload.protocol import wire
from zoffload.robot.scans import scan_streamer
from zoffload.robot.server import RobotServer
from zoffload.runtime.config import RobotSettings, ZenohSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import free_tcp_port, loopback_endpoint, open_session
from zoffload.sources.base import ScanFrame
from zoffload.sources.kitti import KittiBinSource


class MemorySource:
    """The real scans, preloaded, so the sender measures the stream and not the disk."""

    def __init__(self, frames: list[ScanFrame], rate_hz: float) -> None:
        self.frames, self.rate_hz, self.max_range, self.name = frames, rate_hz, 100.0, "memory"

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, index: int) -> ScanFrame:
        return self.frames[index]


def z(port: int, listen: bool) -> ZenohSettings:
    ep = [loopback_endpoint(port)]
    return ZenohSettings(listen=ep if listen else [], connect=[] if listen else ep,
                         multicast_scouting=False, shared_memory=False)


def raw(payloads: list[bytes], seconds: float) -> tuple[float, float]:
    port = free_tcp_port()
    sink = subprocess.Popen([sys.executable, "-m", "benchmarks.raw_sink", str(port), str(seconds + 3)],
                            stdout=subprocess.PIPE, text=True)
    assert sink.stdout is not None
    sink.stdout.readline()
    s = open_session(z(port, listen=False))
    got = []
    s.liveliness().declare_subscriber("bench/sink", lambda x: got.append(1), history=True)
    while not got:
        time.sleep(0.01)
    pub = s.declare_publisher("bench/raw", congestion_control=zenoh.CongestionControl.DROP)
    sent = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pub.put(payloads[sent % len(payloads)])
        sent += 1
    stats = json.loads(sink.stdout.readline())
    sink.wait()
    s.close()
    span = stats["last"] - stats["first"]
    return stats["bytes"] / span / 1e6, stats["n"] / span


def daemons(
    frames: list[ScanFrame], seconds: float, max_in_flight: int
) -> tuple[float, float, dict[str, int]]:
    port = free_tcp_port()
    edge = subprocess.Popen([sys.executable, "-m", "zoffload.cli", "edge", "--no-mapping",
                             "--no-multicast-scouting", "--no-shm", "-l", loopback_endpoint(port),
                             "--log-level", "WARNING"])
    rate = float(os.environ.get("BENCH_OFFERED_HZ", "1000"))  # beyond what either path delivers
    settings = RobotSettings(voxel=0.0, rate_hz=rate, replay="loop", max_scans=int(rate * seconds),
                             ack_timeout=2.0, wait_edge=30, status_period=5.0, max_in_flight=max_in_flight,
                             zenoh=z(port, False))
    stop = StopSignal()
    robot = scan_streamer(settings, stop, source=MemorySource(frames, rate))
    RobotServer(settings, [robot], stop).run()
    edge.send_signal(2)
    edge.wait()
    b = robot.ledger.balance()
    # Delivered: the edge answered (acked, or dropped from its queue after arrival)
    recs = [r for r in robot.ledger.records.values() if r.get("status") in ("acked", "edge_dropped")]
    # Robot clock: first scan sent to last ack received (both stamps are time.monotonic())
    elapsed = max(r["send_stamp"] + r["rtt"] for r in recs) - min(r["send_stamp"] for r in recs)
    mbytes = sum(r["bytes"] for r in recs) / 1e6
    work = [r["work_ms"] for r in robot.ledger.records.values() if "work_ms" in r]
    print(f"  (robot process() per scan: median {np.median(work):.2f} ms; "
          f"{b['published'] / elapsed:.0f} scans/s published)")
    return mbytes / elapsed, len(recs) / elapsed, b


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 8.0
    header(f"scan stream throughput, {seconds:g} s each, shared memory off, DROP")
    src = KittiBinSource(kitti_dir())
    frames = [src.read(i) for i in range(10)]
    payloads = [wire.encode(wire.Scan(robot="robot1", seq=i, send_stamp=0.0, capture_stamp=0.0,
                                      voxel=0.0, voxel_max=0.07, max_range=100.0, n_raw=len(f.points),
                                      points=np.ascontiguousarray(f.points))) for i, f in enumerate(frames)]
    print(f"payload: {np.mean([len(p) for p in payloads]) / 1e6:.2f} MB per scan (raw HDL-64)")
    raw_mb, raw_n = raw(payloads, seconds)
    print(f"raw zenoh put/sub : {raw_mb:7.1f} MB/s  {raw_n:6.1f} scans/s")
    for window in (0, RobotSettings().max_in_flight):
        d_mb, d_n, balance = daemons(frames, seconds, window)
        label = f"window {window}" if window else "no window"
        print(f"robot -> edge, {label:9}: {d_mb:7.1f} MB/s  {d_n:6.1f} scans/s delivered  (ledger {balance})")
        print(f"  ratio zoffload / raw: {d_mb / raw_mb:.2f} (target >= 0.90)")


if __name__ == "__main__":
    main()
