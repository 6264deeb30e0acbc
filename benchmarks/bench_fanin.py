"""Scans lost at the router when several robots stream to one edge on a busy CPU.

Topology of the fleet experiment: a `zoffload router` process; ``--robots`` child processes, each a
client publishing scan-sized payloads (``--size`` bytes) with BLOCK_FIRST on its own
``data/<robot>/scan`` at ``--rate`` Hz, the robots' publications aligned on the same wall-clock
instants (as robots started together drift into); this process as the edge, a client subscribed to
all of them, counting which sequence numbers arrive. ``--burn`` busy-looping processes stand for
the CPU the fleet's mappers and simulators use (default: one per core). Shared memory off.

Zenoh queues a BLOCK_FIRST message from a spawned task that holds the link's block-first slot
until it is done; a second BLOCK_FIRST message for the same link waits for that slot at most
``wait_before_drop`` and is then dropped, with no error on either side. In a router, the scans of
every robot bound for one edge share that edge's link. Modes: ``zenoh`` (router told Zenoh's default
1 ms) and ``zoffload`` (the router as it starts by default, nothing passed: 50 ms, runtime/session.py
DROP_WAIT_US). The robots
wait 200 ms for their own slot, so a loss here is the router's.

Printed per mode: scans lost out of those sent, per run, and in all. Modes alternate ``--runs``
times.

Run: python -m benchmarks.bench_fanin [--robots 3] [--rate 20] [--seconds 20] [--size 20000]
     [--burn 2] [--runs 5]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from collections import defaultdict

import zenoh

from benchmarks.common import header
from zoffload.lab.runner import loopback_zenoh
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.session import (
    DROP_WAIT_KEY,
    DROP_WAIT_US,
    free_tcp_port,
    loopback_endpoint,
    open_session,
)

MODES = {"zenoh": 1_000, "zoffload": DROP_WAIT_US}
SETTLE = 1.5  # seconds for every session to connect and see the subscription before the first scan
KEY = "bench/fanin/{}/scan"


def client(endpoint: str, cfg: tuple[str, ...] = ()) -> ZenohSettings:
    return loopback_zenoh(mode="client", connect=[endpoint], cfg=list(cfg))


def robot(endpoint: str, name: str, start: float, n: int, rate: float, size: int) -> None:
    """One robot: ``n`` payloads at ``rate`` Hz from the wall-clock instant ``start``."""
    session = open_session(client(endpoint, (f"{DROP_WAIT_KEY}:200000",)))
    pub = session.declare_publisher(KEY.format(name), congestion_control=zenoh.CongestionControl.BLOCK_FIRST)
    payload = bytearray(size)
    for i in range(n):
        delay = start + i / rate - time.time()
        if delay > 0:
            time.sleep(delay)
        payload[:8] = i.to_bytes(8, "little")
        pub.put(bytes(payload))
    time.sleep(1.0)
    session.close()


def burner() -> None:
    while True:
        pass


def run_once(mode: str, a: argparse.Namespace) -> tuple[int, int]:
    """(lost, sent) of one run with the router in ``mode``."""
    port = free_tcp_port()
    endpoint = loopback_endpoint(port)
    py = [sys.executable, "-m", "benchmarks.bench_fanin"]
    # zoffload: the router as it runs by default (runtime/router.py), no setting passed
    cfg = ["--cfg", f"{DROP_WAIT_KEY}:{MODES[mode]}"] if mode == "zenoh" else []
    got: dict[str, set[int]] = defaultdict(set)
    lock = threading.Lock()
    n = int(a.seconds * a.rate)

    def on(sample: zenoh.Sample) -> None:
        seq = int.from_bytes(sample.payload.to_bytes()[:8], "little")
        with lock:
            got[str(sample.key_expr)].add(seq)

    procs: list[subprocess.Popen[bytes]] = []
    session = None
    try:
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "zoffload.cli", "router", "-l", endpoint, "--no-multicast-scouting",
             "--no-shm", *cfg], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        procs += [subprocess.Popen([*py, "--burner"]) for _ in range(a.burn)]
        time.sleep(1.0)  # the router's listener
        session = open_session(client(endpoint))
        session.declare_subscriber(KEY.format("*"), on)
        start = time.time() + SETTLE + 1.0
        robots = [subprocess.Popen([*py, "--robot", endpoint, f"robot{i}", f"{start:.6f}", str(n),
                                    str(a.rate), str(a.size)]) for i in range(a.robots)]
        procs += robots
        for p in robots:
            p.wait(timeout=a.seconds + 60)
        time.sleep(0.5)
    finally:
        if session is not None:
            session.close()
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    with lock:
        received = sum(len(v) for v in got.values())
    sent = n * a.robots
    return sent - received, sent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--rate", type=float, default=20.0, help="scans per second per robot")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--size", type=int, default=20_000, help="bytes per scan (20 kB: a coded scan)")
    ap.add_argument("--burn", type=int, default=os.cpu_count() or 2, help="busy-looping processes")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--robot", nargs=6, help=argparse.SUPPRESS)
    ap.add_argument("--burner", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.burner:
        burner()
        return
    if a.robot:
        endpoint, name, start, n, rate, size = a.robot
        robot(endpoint, name, float(start), int(n), float(rate), int(size))
        return
    header("scans lost at the router: several robots' BLOCK_FIRST scans to one edge, busy CPU")
    print(f"{a.robots} robots x {a.rate:g} Hz x {a.seconds:g} s, {a.size} B per scan, "
          f"{a.burn} busy processes")
    totals = {m: [0, 0] for m in MODES}
    per_run: dict[str, list[int]] = {m: [] for m in MODES}
    for _ in range(a.runs):
        for mode in MODES:
            lost, sent = run_once(mode, a)
            totals[mode][0] += lost
            totals[mode][1] += sent
            per_run[mode].append(lost)
    for mode, wait in MODES.items():
        lost, sent = totals[mode]
        print(f"router wait_before_drop {wait / 1000:g} ms ({mode}): lost per run {per_run[mode]}, "
              f"in all {lost} of {sent} ({100 * lost / max(sent, 1):.2f} %)")


if __name__ == "__main__":
    main()
