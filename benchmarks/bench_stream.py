"""Scan-stream throughput: zoffload's robot -> edge path vs raw Zenoh put/sub, real HDL-64 scans.

Both sides are separate processes on loopback TCP with shared memory OFF (so every byte crosses
the socket). Raw: the raw KITTI-360 HDL-64 scans (~1.45 MB encoded) put in a loop with congestion
control BLOCK_FIRST to a bare subscriber process. zoffload: the robot's scan pipeline in this
process (sensor replay from memory offered at 1000 Hz, beyond what either path carries; sizing,
the sender thread, BLOCK_FIRST, acks booked; the default window of 3 unanswered scans) to
``zoffload-edge --no-mapping`` (decode, stamp, queue, ack). Delivered = scans the edge answered,
per second of the robot's clock (first send to last ack). The figure is scans per second, as a
ratio of raw Zenoh's.

Cases: the robot's defaults (rate policy + q16d coding, the HDL-64 range [0.02, 0.5] m), the
defaults with the policy's deliberate skipping off (at 1000 Hz every scan is "late" for its 1 ms
slot, so the policy lowers the rate: that measures the policy, not the path), the paper's
baseline (fixed 5 cm grid, float32) and raw float32 scans (this benchmark's earlier
configuration), with the default window and without one (at 1000 Hz an ack lost on the loaded
loopback holds a window slot for the ack timeout, 1 s: the window measures the acks, not the path).

Run: python -m benchmarks.bench_stream [seconds] [case ...]
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import Any

import numpy as np
import zenoh

from benchmarks.common import MemorySource, header, kitti_dir, spawn, stop
from zoffload.protocol import wire
from zoffload.robot.scans import scan_streamer
from zoffload.robot.server import RobotServer
from zoffload.runtime.config import RobotSettings, ZenohSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import free_tcp_port, loopback_endpoint, open_session
from zoffload.sources.kitti import KittiBinSource

OFFERED_HZ = 1000.0
CASES: dict[str, tuple[str, dict[str, Any]]] = {
    "defaults": ("defaults (rate + q16d)", {}),
    "defaults-noskip": ("defaults, no deliberate skips", {"max_skip": 0, "stall_after": 0.0}),
    "baseline": ("fixed 0.05 + f32 (paper)", {"scale_policy": "fixed", "voxel": 0.05, "scan_coding": "f32"}),
    "raw-f32": ("raw + f32", {"scale_policy": "fixed", "voxel": 0.0, "scan_coding": "f32"}),
    "raw-f32-nowindow": ("raw + f32, no window", {"scale_policy": "fixed", "voxel": 0.0, "scan_coding": "f32",
                                                  "max_in_flight": 0}),
}


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
    pub = s.declare_publisher("bench/raw", congestion_control=zenoh.CongestionControl.BLOCK_FIRST)
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


def daemons(frames: list[Any], seconds: float, over: dict[str, Any]) -> tuple[float, float, dict[str, Any]]:
    port = free_tcp_port()
    edge = spawn(["edge", "--no-mapping", "--no-multicast-scouting", "--no-shm", "-l",
                  loopback_endpoint(port), "--log-level", "WARNING"])
    settings = RobotSettings(rate_hz=OFFERED_HZ, replay="loop", max_scans=int(OFFERED_HZ * seconds),
                             wait_edge=30, status_period=5.0, voxel_range=(0.02, 0.5),
                             zenoh=z(port, False), **over)
    stop_signal = StopSignal()
    robot = scan_streamer(settings, stop_signal, source=MemorySource(frames, OFFERED_HZ))  # type: ignore[arg-type]
    RobotServer(settings, [robot], stop_signal).run()
    stop(edge)
    m = robot.metrics()
    # Delivered: the edge answered (acked, or dropped from its queue after arrival)
    recs = [r for r in robot.ledger.records.values() if r.get("status") in ("acked", "edge_dropped")]
    # Robot clock: first scan sent to last ack received (both stamps are time.monotonic())
    elapsed = max(r["send_stamp"] + r["rtt"] for r in recs) - min(r["send_stamp"] for r in recs)
    return sum(r["bytes"] for r in recs) / 1e6 / elapsed, len(recs) / elapsed, m


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 8.0
    cases = sys.argv[2:] or list(CASES)
    header(f"scan stream throughput, {seconds:g} s each, shared memory off, BLOCK_FIRST")
    src = KittiBinSource(kitti_dir())
    frames = [src.read(i) for i in range(10)]
    payloads = [wire.encode(wire.Scan(robot="robot1", seq=i, send_stamp=0.0, capture_stamp=0.0,
                                      voxel=0.0, voxel_max=0.07, max_range=100.0, n_raw=len(f.points),
                                      points=np.ascontiguousarray(f.points))) for i, f in enumerate(frames)]
    print(f"payload: {np.mean([len(p) for p in payloads]) / 1e6:.2f} MB per scan (raw HDL-64)")
    raw_mb, raw_n = raw(payloads, seconds)
    print(f"raw zenoh put/sub             : {raw_mb:7.1f} MB/s  {raw_n:6.1f} scans/s")
    for key in cases:
        label, over = CASES[key]
        d_mb, d_n, m = daemons(frames, seconds, over)
        c, s = m["cpu"], m["scans"]
        print(f"robot -> edge, {label:30}: {d_mb:7.1f} MB/s  {d_n:6.1f} scans/s delivered, ratio "
              f"{d_n / raw_n:.2f} of raw scans/s ({s['mean_kB_sent']:.0f} kB/scan, robot CPU "
              f"{c['per_scan_ms']:.2f} ms/scan: loop {c['loop_ms']:.2f}, sender {c['send_ms']:.2f}; "
              f"dropped at source {m['dropped_source']})")


if __name__ == "__main__":
    main()
