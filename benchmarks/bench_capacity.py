"""Edge capacity: how many robots streaming at 10 Hz one edge maps without falling behind.

Real processes on loopback (multicast scouting and shared memory off): one ``zoffload edge``
listening (``--mapper.workers`` = ``--edge-workers``, shedding off so it keeps every robot and the
figure is its raw capacity, capacity raised to the robots offered), N ``zoffload robot`` processes
connecting to it as clients, each replaying ``--scans`` scans at 10 Hz with a fixed voxel grid (so
the load does not adapt): (a) the simulator's VLP-16 (a scene seed per robot), (b) the real
KITTI-360 HDL-64 scans (``ZOFFLOAD_DATA``/kitti360-hdl64/velodyne, replayed ping-pong; skipped
with a message when absent). N steps 1, 2, 3, ... up to ``--max-robots`` and stops at the first
step where a robot's on-time share (scans acked within one period, 100 ms, on the robot's clock,
from its ``robot_scans.csv``, after ``--warmup`` scans) drops below 95 % or scans are not acked
(drops, losses, local registration). Robots per edge = the last step that held; per core = that
divided by the edge's mapper workers.

The robots run on the same machine as the edge and their sensors (the simulator's ray casting,
the replay's file reads) take CPU from it: on a small machine the figure is a lower bound; run the
robots elsewhere (or on a bigger machine than the edge's cores) for the edge's own limit.
``--pin K`` gives the edge K cores of its own instead (CPU affinity: the last K cores, set
before its threads start; its mapper workers default to K) and the robots the others, so the
figure is the edge's per core, not the shared machine's.

Run: python -m benchmarks.bench_capacity [--max-robots 8] [--scans 300] [--edge-workers 2]
         [--sensors sim kitti] [--no-attach] [--pin K] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.common import KITTI, header
from zoffload.lab.fleet_experiment import SESSION, CpuSampler
from zoffload.lab.fleet_report import on_time_share
from zoffload.lab.runner import Spawned, connect_when_listening, loopback_zenoh, wait_token
from zoffload.protocol.keys import Keys
from zoffload.robot.scanlog import read_scan_rows
from zoffload.runtime.session import free_tcp_port, loopback_endpoint

RATE_HZ = 10.0
ON_TIME = 0.95
KEYS = Keys()


def cores(pin: int) -> tuple[set[int], set[int]]:
    """(the edge's cores, the robots') with ``pin`` cores for the edge; both empty without."""
    if pin < 0:
        raise SystemExit(f"--pin {pin}: a number of cores, 0 or more")
    if not pin:
        return set(), set()
    mine = sorted(os.sched_getaffinity(0))
    if pin >= len(mine):
        raise SystemExit(f"--pin {pin}: this process has {len(mine)} cores, the robots need one at least")
    return set(mine[-pin:]), set(mine[:-pin])


def step(sensor: str, n: int, a: argparse.Namespace, out: Path) -> dict[str, Any]:
    """One edge and ``n`` robots until every robot has sent its scans; their timeliness."""
    out.mkdir(parents=True, exist_ok=True)
    ep = loopback_endpoint(free_tcp_port())
    cpu = CpuSampler()
    edge_args = ["edge", *SESSION, "-l", ep, "--edge-id", "edge1", "--map-dir", str(out / "edge"),
                 "--fleet.no-shed", "--fleet.capacity", str(n), "--admission.max-robots", str(max(16, n))]
    if a.edge_workers or a.pin:
        edge_args += ["--mapper.workers", str(a.edge_workers or a.pin)]
    edge = Spawned("edge", edge_args, out / "edge.log")
    edge_cpus, robot_cpus = cores(a.pin)
    if edge_cpus:
        os.sched_setaffinity(edge.proc.pid, edge_cpus)
    cpu.add("edge", edge.proc.pid)
    robots: list[Spawned] = []
    try:
        session = connect_when_listening(loopback_zenoh(mode="client", connect=[ep]), edge)
        if session is None or not wait_token(session, KEYS.edge_alive("edge1"), 60):
            raise SystemExit("the edge did not start:\n" + edge.tail())
        session.close()
        scans = "sim" if sensor == "sim" else str(KITTI)
        for i in range(1, n + 1):
            args = ["robot", *SESSION, "-m", "client", "-e", ep, "--robot-id", f"robot{i}", "--scans", scans,
                    "--replay", "once" if sensor == "sim" else "pingpong", "--max-scans", str(a.scans),
                    "--rate", str(RATE_HZ), "--scale-policy", "fixed", "--sim-seed", str(i),
                    "--voxel", str(a.sim_voxel if sensor == "sim" else a.kitti_voxel), "--wait-edge", "30",
                    "--out", str(out / f"robot{i}")] + (["--fleet.no-attach"] if a.no_attach else [])
            robots.append(Spawned(f"robot{i}", args, out / f"robot{i}.log"))
            if robot_cpus:
                os.sched_setaffinity(robots[-1].proc.pid, robot_cpus)
            cpu.add(f"robot{i}", robots[-1].proc.pid)
        deadline = time.monotonic() + a.scans / RATE_HZ + 120
        while any(r.proc.poll() is None for r in robots) and time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        for r in robots:
            r.stop()
        edge.stop()
        figures = cpu.close()
    shares, not_acked = [], 0
    for i in range(1, n + 1):
        rows = read_scan_rows(out / f"robot{i}" / "robot_scans.csv")
        share, missing = on_time_share(rows, a.within, a.warmup)
        shares.append(share if share is not None else 0.0)
        not_acked += missing
    return {"sensor": sensor, "robots": n, "on_time_min": min(shares),
            "on_time_mean": statistics.fmean(shares), "not_acked": not_acked,
            "edge_cores": figures.get("edge", {}).get("cores"),
            "ok": min(shares) >= ON_TIME and not_acked <= a.drop_tolerance}


def sweep(sensor: str, a: argparse.Namespace, out: Path) -> int:
    """Robots per edge for one sensor: the last step that held."""
    held = 0
    for n in range(1, a.max_robots + 1):
        r = step(sensor, n, a, out / sensor / f"n{n}")
        print(f"{sensor:>5} x {n}: on time min {100 * r['on_time_min']:5.1f} %, mean "
              f"{100 * r['on_time_mean']:5.1f} %, not acked {r['not_acked']}, edge "
              f"{r['edge_cores'] or 0:.2f} cores -> {'ok' if r['ok'] else 'behind'}", flush=True)
        (out / sensor / f"n{n}" / "step.json").write_text(json.dumps(r, indent=2))
        if not r["ok"]:
            break
        held = n
    return held


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--max-robots", type=int, default=8, help="largest step (default 8)")
    p.add_argument("--scans", type=int, default=300, help="scans per robot per step (default 300 = 30 s)")
    p.add_argument("--edge-workers", type=int, default=None,
                   help="the edge's mapper threads (default: one per core, the edge's default)")
    p.add_argument("--sensors", nargs="+", choices=["sim", "kitti"], default=["sim", "kitti"])
    p.add_argument("--sim-voxel", type=float, default=0.05, help="robots' voxel grid, VLP-16 (default 0.05)")
    p.add_argument("--kitti-voxel", type=float, default=0.1, help="robots' voxel grid, HDL-64 (default 0.1)")
    p.add_argument("--within", type=float, default=1 / RATE_HZ,
                   help="an ack is on time within this many seconds of the send (default 0.1: one period)")
    p.add_argument("--warmup", type=int, default=10, help="first scans of each robot not judged (default 10)")
    p.add_argument("--drop-tolerance", type=int, default=0,
                   help="scans not acked (all robots, after warm-up) a step may have and still hold "
                   "(default 0)")
    p.add_argument("--no-attach", action="store_true", help="robots without the attach protocol (legacy)")
    p.add_argument("--pin", type=int, default=0, metavar="K",
                   help="the edge on K cores of its own (the last K), the robots on the others (default: "
                   "all share every core)")
    p.add_argument("--out", default=None, help="keep the runs here (default: a temporary folder)")
    a = p.parse_args(argv)
    header("edge capacity: robots at 10 Hz per edge")
    workers = a.edge_workers or a.pin or os.cpu_count() or 1
    edge_cpus, robot_cpus = cores(a.pin)
    print(f"edge mapper workers: {workers}; {a.scans} scans per robot; on time = acked within "
          f"{1e3 * a.within:.0f} ms on >= {100 * ON_TIME:.0f} % of scans; "
          + (f"edge pinned to cores {sorted(edge_cpus)}, robots to {sorted(robot_cpus)}" if a.pin
             else "edge and robots share every core"))
    with tempfile.TemporaryDirectory(prefix="bench-capacity-") as tmp:
        out = Path(a.out or tmp)
        result: dict[str, int] = {}
        for sensor in a.sensors:
            if sensor == "kitti" and not KITTI.is_dir():
                print(f"kitti: skipped, no KITTI-360 scans at {KITTI} (set ZOFFLOAD_DATA)")
                continue
            result[sensor] = sweep(sensor, a, out)
        print()
        for sensor, held in result.items():
            name = "simulator VLP-16" if sensor == "sim" else "KITTI-360 HDL-64"
            limit = " (the largest step tried: raise --max-robots)" if held == a.max_robots else ""
            per = (f"{held / a.pin:.2f} per edge core ({a.pin} pinned)" if a.pin
                   else f"{held / workers:.2f} per mapper worker/core ({workers} workers)")
            print(f"{name}: {held} robots per edge{limit}, {per}")


if __name__ == "__main__":
    main()
