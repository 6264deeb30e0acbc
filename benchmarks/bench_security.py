"""What TLS + client certificates + the ACL cost per scan, through a router, against plain TCP.

Topology of the deployment: a `zoffload router` process; this process as robot1 and a child
process as edge1, both clients of the router, shared memory off. The robot puts a scan-sized
payload on ``data/robot1/scan`` (a Publisher, BLOCK_FIRST as the robot does); the edge answers each
with a 200-byte ``scan_ack`` (DROP, as the edge does). Modes: ``tcp`` (router on tcp/, no ACL) and
``tls`` (the router.json5 of ``zoffload certs``: TLS only, mTLS, default-deny ACL by certificate
common name; each side's certificate). Payloads: 20 kB (a downsampled, q16z-coded scan) and
1.4 MB (a raw HDL-64 scan as float32).

* RTT: one scan at a time, ``--rtt`` round trips after 30 warm-up ones: median and p90.
* Throughput: scans back to back with at most 3 unanswered (the robot's default window) for
  ``--seconds``: scans and MB per second delivered (acked).

Printed per payload: both modes and the ratio tls/tcp (RTT: > 1 is slower; throughput: < 1 is
slower). The issue's target: per-scan overhead <= 10 %, i.e. RTT ratio <= 1.10 and throughput
ratio >= 0.90. Modes alternate ``--runs`` times; the median of runs is printed.

``--edge-ms``: the edge waits that long before each ack (a stand-in for registration, e.g. 30 ms
of KISS-ICP), for the overhead relative to a whole scan's round trip rather than to the transport
alone.

Run: python -m benchmarks.bench_security [--rtt 300] [--seconds 5] [--runs 3] [--edge-ms 0]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from zoffload.protocol.keys import Keys
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.errors import ZenohSessionError
from zoffload.runtime.session import free_tcp_port, open_session

KEYS = Keys()
SIZES = {"20 kB": 20_000, "1.4 MB": 1_440_000}
WINDOW = 3


def settings(mode: str, port: int, certs: Path, identity: str) -> ZenohSettings:
    common = dict(mode="client", multicast_scouting=False, shared_memory=False)
    if mode == "tcp":
        return ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], **common)  # type: ignore[arg-type]
    return ZenohSettings(connect=[f"tls/localhost:{port}"], tls_ca=str(certs / "ca.pem"),
                         tls_cert=str(certs / f"{identity}.pem"), tls_key=str(certs / f"{identity}.key"),
                         **common)  # type: ignore[arg-type]


def echo(mode: str, port: int, certs: Path, edge_ms: float) -> None:
    """The edge side (child process): a small ack for every scan, after ``edge_ms`` of stand-in
    registration, until stdin closes."""
    s = open_session(settings(mode, port, certs, "edge1"))
    ack = s.declare_publisher(KEYS.scan_ack("robot1", "edge1"),
                              congestion_control=zenoh.CongestionControl.DROP, express=True)

    def on_scan(sample: zenoh.Sample) -> None:
        if edge_ms:
            time.sleep(edge_ms / 1e3)
        ack.put(sample.payload.to_bytes()[:200])

    sub = s.declare_subscriber(KEYS.all_scans(), on_scan)
    s.liveliness().declare_token(KEYS.edge_alive("edge1"))
    print("ready", flush=True)
    sys.stdin.read()
    sub.undeclare()
    s.close()


def start_router(mode: str, port: int, certs: Path, log: Path) -> subprocess.Popen[bytes]:
    if mode == "tcp":
        args = ["router", "--no-multicast-scouting", "-l", f"tcp/127.0.0.1:{port}"]
    else:
        args = ["router", "-c", str(certs / "router.json5")]
    return subprocess.Popen([sys.executable, "-m", "zoffload.cli", *args], stdout=open(log, "w"),
                            stderr=subprocess.STDOUT)


def connect(z: ZenohSettings, timeout: float = 30.0) -> zenoh.Session:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return open_session(z)
        except ZenohSessionError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def measure(s: zenoh.Session, size: int, rtt_n: int, seconds: float) -> tuple[float, float, float]:
    """(RTT median ms, RTT p90 ms, scans/s with the window) for one payload size."""
    got = threading.Semaphore(0)
    sub = s.declare_subscriber(KEYS.scan_acks("robot1"), lambda _s: got.release())
    pub = s.declare_publisher(KEYS.scan("robot1"), congestion_control=zenoh.CongestionControl.BLOCK_FIRST)
    payload = bytes(size)
    rtts = []
    for i in range(30 + rtt_n):
        t0 = time.perf_counter()
        pub.put(payload)
        if not got.acquire(timeout=5):
            raise RuntimeError("no ack within 5 s")
        if i >= 30:
            rtts.append(time.perf_counter() - t0)
    window = threading.Semaphore(WINDOW)
    done = 0
    sub.undeclare()

    def on_ack(_s: zenoh.Sample) -> None:
        nonlocal done
        done += 1
        window.release()

    sub = s.declare_subscriber(KEYS.scan_acks("robot1"), on_ack)
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        if window.acquire(timeout=5):
            pub.put(payload)
    elapsed = time.perf_counter() - t0
    time.sleep(0.5)
    sub.undeclare()
    pub.undeclare()
    rtts.sort()
    return (statistics.median(rtts) * 1e3, rtts[int(0.9 * len(rtts))] * 1e3, done / elapsed)


def run_mode(mode: str, certs: Path, tmp: Path, rtt_n: int, seconds: float,
             edge_ms: float) -> dict[str, tuple[float, ...]]:
    port = free_tcp_port()
    if mode == "tls":
        from zoffload.runtime.certs import write_deployment

        write_deployment(certs, ["robot1"], ["edge1"], listen=[f"tls/127.0.0.1:{port}"])
    router = start_router(mode, port, certs, tmp / f"router-{mode}.log")
    edge = None
    try:
        robot = connect(settings(mode, port, certs, "robot1"))
        edge = subprocess.Popen([sys.executable, "-m", "benchmarks.bench_security", "--echo", mode, str(port),
                                 str(certs), str(edge_ms)], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        assert edge.stdout is not None and edge.stdout.readline().strip() == b"ready"
        out: dict[str, tuple[float, ...]] = {name: measure(robot, size, rtt_n, seconds)
                                             for name, size in SIZES.items()}
        robot.close()
        return out
    finally:
        if edge is not None and edge.stdin is not None:
            edge.stdin.close()
            edge.wait(20)
        router.send_signal(2)
        router.wait(20)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rtt", type=int, default=300, help="round trips per payload (default 300)")
    p.add_argument("--seconds", type=float, default=5.0, help="throughput seconds per payload (default 5)")
    p.add_argument("--runs", type=int, default=3, help="alternating runs of each mode (default 3)")
    p.add_argument("--edge-ms", type=float, default=0.0,
                   help="stand-in registration time per scan on the edge (default 0: transport only)")
    p.add_argument("--echo", nargs=4, metavar=("MODE", "PORT", "CERTS", "MS"), help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.echo:
        echo(a.echo[0], int(a.echo[1]), Path(a.echo[2]), float(a.echo[3]))
        return
    results: dict[str, list[dict[str, tuple[float, ...]]]] = {"tcp": [], "tls": []}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for _ in range(a.runs):
            for mode in ("tcp", "tls"):
                results[mode].append(run_mode(mode, tmp / "certs", tmp, a.rtt, a.seconds, a.edge_ms))
    print("router in between, shared memory off; tls = TLS + client certificates + default-deny ACL; "
          f"edge time per scan {a.edge_ms:g} ms")
    print(f"{'payload':>8} {'mode':>4} {'RTT median ms':>14} {'RTT p90 ms':>11} {'scans/s':>9} {'MB/s':>8}")
    for name, size in SIZES.items():
        med = {m: [statistics.median(r[name][i] for r in results[m]) for i in range(3)] for m in results}
        for m in ("tcp", "tls"):
            print(f"{name:>8} {m:>4} {med[m][0]:14.3f} {med[m][1]:11.3f} {med[m][2]:9.1f} "
                  f"{med[m][2] * size / 1e6:8.1f}")
        print(f"{name:>8} ratio tls/tcp: RTT {med['tls'][0] / med['tcp'][0]:.2f} (target <= 1.10), "
              f"throughput {med['tls'][2] / med['tcp'][2]:.2f} (target >= 0.90)")


if __name__ == "__main__":
    main()
