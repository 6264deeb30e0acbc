"""What offloading costs the robot: its CPU time per scan beside KISS-ICP's on the same scans.

For each sensor (the simulator's VLP-16, 28k points; the real KITTI-360 HDL-64, 121k points):

1. **KISS-ICP locally**: process CPU time (``time.process_time``: KISS-ICP is multithreaded)
   around ``KissICP.register_frame`` on every raw scan, configured as the robot's local run.
2. **The offload path per scale policy x coding**: the robot's scan pipeline in this process
   (sensor replay from memory at 10 Hz, sizing, sender thread, real Zenoh, shared memory off) to a
   ``zoffload-edge --no-mapping`` process, optionally through the link emulator; the figure is the
   pipeline's own measurement (``robot_metrics.json`` ``cpu.per_scan_ms``): thread CPU time of the
   sensor loop and the sender thread for each scan sent, median.
3. **The robot process's whole CPU per scan**: ``zoffload-robot`` as its own process against the
   edge for N scans, 3 runs; the figure is the process's own steady-state window
   (``robot_metrics.json`` ``cpu.steady_process_ms_per_scan``: process CPU time, every thread,
   Zenoh's included, from its 10th scan read to its last, so start-up and the final drain are left
   out), mean and spread over the runs. The sensor thread's own CPU (reading files, or ray casting
   the simulator) is taken out: a real sensor's driver is not offloading work. A cross-check,
   ``os.wait4``'s whole-run CPU per scan (start-up included), is printed beside it.

Run: python -m benchmarks.bench_robot_cost [--scans 100] [--process 200] [--repeats 3]
     [--sensors sim kitti] [--cases defaults baseline ...]   (about 9 minutes with the defaults)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import MemorySource, header, kitti_dir, sensor_frames, spawn, stop
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.mapper import mapper_voxel_size
from zoffload.robot.scans import scan_streamer
from zoffload.robot.server import RobotServer
from zoffload.runtime.config import RobotSettings, ZenohSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.loading import write_effective
from zoffload.runtime.session import free_tcp_port, loopback_endpoint

# (name, label, settings, link trace or None). The defaults first, then the paper's baseline.
FIXED = {"scale_policy": "fixed", "voxel": 0.05}
RAW = {"scale_policy": "fixed", "voxel": 0.0}
CASES: list[tuple[str, str, dict[str, Any], str | None]] = [
    ("defaults", "rate + q16d (defaults)", {}, None),
    ("defaults-capped", "rate + q16d, 20 Mbps link", {}, "capped"),
    ("baseline", "fixed 0.05 + f32 (paper)", {**FIXED, "scan_coding": "f32"}, None),
    ("fixed-q16d", "fixed 0.05 + q16d", {**FIXED, "scan_coding": "q16d"}, None),
    ("raw-f32", "raw + f32", {**RAW, "scan_coding": "f32"}, None),
    ("raw-q16d", "raw + q16d", {**RAW, "scan_coding": "q16d"}, None),
    ("rate-q16z", "rate + q16z (old defaults)", {"scan_coding": "q16z"}, None),
    ("rate-f32", "rate + f32", {"scan_coding": "f32"}, None),
    ("dqn-q16d", "dqn + q16d", {"scale_policy": "dqn"}, None),
    ("dqn-f32", "dqn + f32", {"scale_policy": "dqn", "scan_coding": "f32"}, None),
]
# The sensor-aware voxel range (README "Ours"): the paper's for the VLP-16, wider for the HDL-64
RANGES = {"sim": (0.01, 0.07), "kitti": (0.02, 0.5)}


def kiss_icp_cpu(frames: list[Any], max_range: float, voxel_max: float) -> float:
    """Median process CPU ms of ``register_frame`` per raw scan (the robot mapping on its own)."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.max_range, cfg.data.deskew = max_range, False
    cfg.mapping.voxel_size = mapper_voxel_size(max_range, voxel_max)
    odom = KissICP(cfg)
    cpu = []
    for f in frames:
        pts = drop_non_finite(f.points)[0].astype(np.float64)
        c0 = time.process_time()
        odom.register_frame(pts, np.empty(0))
        cpu.append(time.process_time() - c0)
    return statistics.median(cpu[3:]) * 1e3


def zenoh_to(port: int, client: bool = False) -> ZenohSettings:
    return ZenohSettings(mode="client" if client else "peer", connect=[loopback_endpoint(port)],
                         multicast_scouting=False, shared_memory=False)


def offload_cpu(sensor: str, frames: list[Any], max_range: float, n: int, over: dict[str, Any],
                trace: str | None, edge_port: int) -> dict[str, Any]:
    """One pipeline run in this process; returns its metrics."""
    port = edge_port
    link = None
    if trace is not None:
        port = free_tcp_port()
        link = spawn(["link", "--trace", trace, "--listen-port", str(port), "--target",
                      f"127.0.0.1:{edge_port}", "--quiet"], ready="ready")
    settings = RobotSettings(zenoh=zenoh_to(port, client=trace is not None), rate_hz=10.0, replay="pingpong",
                             max_scans=n, wait_edge=30, status_period=5.0, voxel_range=RANGES[sensor],
                             **over)
    stop_signal = StopSignal()
    robot = scan_streamer(settings, stop_signal, source=MemorySource(frames, 10.0, max_range))  # type: ignore[arg-type]
    RobotServer(settings, [robot], stop_signal).run()
    if link is not None:
        stop(link)
    return robot.metrics()


def process_cpu(sensor: str, n: int, over: dict[str, Any], edge_port: int) -> dict[str, float]:
    """``zoffload-robot`` for ``n`` scans: its CPU seconds (os.wait4) and its sensor thread's."""
    with tempfile.TemporaryDirectory() as tmp:
        settings = RobotSettings(zenoh=zenoh_to(edge_port), rate_hz=10.0, max_scans=n, wait_edge=30,
                                 replay="pingpong", voxel_range=RANGES[sensor], out_dir=tmp,
                                 scans="sim" if sensor == "sim" else str(kitti_dir()), **over)
        path = write_effective(settings, Path(tmp) / "robot.yaml")
        p = spawn(["robot", "--settings", str(path), "--log-level", "WARNING"])
        _, status, usage = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        if p.returncode != 0:
            sys.exit(f"zoffload-robot exited with {p.returncode}")
        m = json.loads((Path(tmp) / "robot_metrics.json").read_text())
    return {"cpu_s": usage.ru_utime + usage.ru_stime, "sensor_s": m["cpu"]["sensor_s"],
            "produced": m["balance"]["produced"], "steady_ms": m["cpu"]["steady_process_ms_per_scan"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=100, help="scans per offload run (default 100, at 10 Hz)")
    ap.add_argument("--process", type=int, default=200,
                    help="scans per robot process run (default 200; 0 = skip)")
    ap.add_argument("--repeats", type=int, default=3, help="robot process runs per case (default 3)")
    ap.add_argument("--sensors", nargs="+", default=["sim", "kitti"], choices=["sim", "kitti"])
    ap.add_argument("--cases", nargs="+", default=[c[0] for c in CASES], choices=[c[0] for c in CASES])
    a = ap.parse_args()
    header("robot CPU per scan vs KISS-ICP locally (CPU time, not wall)")
    edge_port = free_tcp_port()
    edge = spawn(["edge", "--no-mapping", "--no-multicast-scouting", "--no-shm", "-l",
                  loopback_endpoint(edge_port), "--log-level", "WARNING"])
    try:
        for sensor in a.sensors:
            frames, max_range = sensor_frames(sensor, 100)
            kiss = kiss_icp_cpu(frames, max_range, 0.07)
            name = "simulator VLP-16" if sensor == "sim" else "KITTI-360 HDL-64"
            print(f"\n{name}: {np.mean([len(f.points) for f in frames]):,.0f} points per scan; "
                  f"KISS-ICP locally (raw scans): {kiss:.1f} ms CPU per scan (median)")
            print(f"{'case':30} {'kept':>5} {'kB':>6} {'CPU/scan':>9} {'p95':>6} {'loop':>6} {'send':>6} "
                  f"{'vs KISS-ICP':>11}")
            for key, label, over, trace in CASES:
                if key not in a.cases:
                    continue
                m = offload_cpu(sensor, frames, max_range, a.scans, over, trace, edge_port)
                c, s = m["cpu"], m["scans"]
                if c["per_scan_ms"] is None:
                    print(f"{label:30} nothing sent: {m['balance']}")
                    continue
                kept = s["mean_points_sent"] / s["mean_points_raw"]
                print(f"{label:30} {100 * kept:4.0f}% {s['mean_kB_sent']:6.0f} {c['per_scan_ms']:6.2f} ms "
                      f"{c['p95_per_scan_ms']:6.2f} {c['loop_ms']:6.2f} {c['send_ms']:6.2f} "
                      f"{100 * c['per_scan_ms'] / kiss:9.1f} %")
            if a.process:
                print(f"robot process, whole CPU per scan in steady state ({a.process} scans, "
                      f"{a.repeats} runs, the sensor thread's own CPU taken out):")
                for key in ("defaults", "baseline"):
                    over = next(c[2] for c in CASES if c[0] == key)
                    runs = [process_cpu(sensor, a.process, over, edge_port) for _ in range(a.repeats)]
                    steady = [r["steady_ms"] for r in runs if r["steady_ms"] is not None]
                    whole = [1e3 * (r["cpu_s"] - r["sensor_s"]) / max(1, r["produced"]) for r in runs]
                    if not steady:
                        print(f"  {key:12}: no steady-state window (fewer than 11 scans read)")
                        continue
                    # the sample sd, as the experiment reports print (0 for a single run)
                    mean = statistics.mean(steady)
                    sd = statistics.stdev(steady) if len(steady) > 1 else 0.0
                    print(f"  {key:12}: {mean:6.2f} ± {sd:4.2f} ms per scan = {100 * mean / kiss:5.1f} % of "
                          f"KISS-ICP (runs: {', '.join(f'{x:.2f}' for x in steady)}; whole run with "
                          f"start-up {statistics.mean(whole):.2f} ms)")
    finally:
        stop(edge)


if __name__ == "__main__":
    main()
