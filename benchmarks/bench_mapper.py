"""KISS-ICP inside the edge daemon vs KISS-ICP called directly, on the same real scans.

Direct: ``kiss_icp.kiss_icp.KissICP.register_frame`` in a loop over the 50 KITTI-360 scans
(downsampled at 5 cm as the robot sends them), given row-major points, and again column-major:
the layout ``decode_q16d`` returned before 2026-12-07, which KISS-ICP's binding converts point by
point. Edge: the same scans published to a real ``zoffload-edge`` process one at a time (each
after the previous ack) and registered by its per-robot mapper, as float32 and coded ``q16d`` (the
robot's default coding; quantised at a tenth of the voxel); the figures are the registration time
the edge reports in each ack (its mapper process's: decoding, in the edge's, is not in it), and
the wall time per scan including transport. Also KISS-ICP's conversion of the points to its own
type alone, row-major and column-major.

Run: python -m benchmarks.bench_mapper
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

from benchmarks.common import header, kitti_scans
from zoffload.mapping.mapper import mapper_voxel_size
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.protocol.coding import encode_q16d, quant_step
from zoffload.protocol.keys import Keys
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.session import free_tcp_port, loopback_endpoint, open_session


def direct(scans: list[np.ndarray], voxel: float, layout: Any = np.ascontiguousarray) -> list[float]:
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.max_range, cfg.data.deskew, cfg.mapping.voxel_size = 100.0, False, voxel
    odom = KissICP(cfg)
    times = []
    for pts in scans:
        frame = layout(pts.astype(np.float64))
        t0 = time.perf_counter()
        odom.register_frame(frame, np.empty(0))
        times.append(time.perf_counter() - t0)
    return times


def conversion(scans: list[np.ndarray], layout: Any) -> list[float]:
    """KISS-ICP's conversion of each scan's points (float64) to its own vector type, alone."""
    from kiss_icp.pybind import kiss_icp_pybind

    times = []
    for pts in scans:
        frame = layout(pts.astype(np.float64))
        t0 = time.perf_counter()
        kiss_icp_pybind._Vector3dVector(frame)
        times.append(time.perf_counter() - t0)
    return times


def scan_message(seq: int, pts: np.ndarray, coding: str) -> bytes:
    fields: dict[str, Any] = {"points": pts.astype(np.float32)}
    if coding == "q16d":
        step = quant_step(0.05, 0.1)
        origin, step, blob = encode_q16d(pts, step)
        fields = {"points": np.empty((0, 3), np.float32), "coding": "q16d", "quant_step": step,
                  "n_points": len(pts), "origin": origin, "packed": np.frombuffer(blob, np.uint8)}
    return wire.encode(wire.Scan(robot="bench", seq=seq, send_stamp=time.monotonic(), capture_stamp=0.0,
                                 voxel=0.05, voxel_max=0.07, max_range=100.0, n_raw=len(pts), **fields))


def through_edge(scans: list[np.ndarray], coding: str) -> tuple[list[float], list[float], list[float]]:
    port = free_tcp_port()
    edge = subprocess.Popen([sys.executable, "-m", "zoffload.cli", "edge", "--no-multicast-scouting",
                             "--no-shm", "-l", loopback_endpoint(port), "--log-level", "WARNING"])
    keys = Keys()
    s = open_session(ZenohSettings(connect=[loopback_endpoint(port)], multicast_scouting=False,
                                   shared_memory=False))
    acks: list[wire.ScanAck] = []
    got = threading.Event()

    def on_ack(sample: Any) -> None:
        msg = wire.decode(sample.payload.to_bytes(), expect=wire.ScanAck)
        assert isinstance(msg, wire.ScanAck)
        acks.append(msg)
        got.set()

    up: list[int] = []
    s.liveliness().declare_subscriber(keys.any_edge_alive(), lambda x: up.append(1), history=True)
    while not up:
        time.sleep(0.01)
    s.declare_subscriber(keys.scan_acks("bench"), on_ack)
    pub = s.declare_publisher(keys.scan("bench"))
    walls = []
    for seq, pts in enumerate(scans):
        data = scan_message(seq, pts, coding)
        got.clear()
        t0 = time.perf_counter()
        pub.put(data)
        got.wait(30)  # block, do not poll: the mapper needs both cores
        walls.append(time.perf_counter() - t0)
    s.close()
    edge.send_signal(2)
    edge.wait()
    assert all(a.status == "ok" for a in acks)
    return [a.icp_time for a in acks], [a.proc_time for a in acks], walls


def main() -> None:
    header("KISS-ICP: inside zoffload-edge vs called directly (50 KITTI-360 scans at 5 cm)")
    scans = [voxel_downsample(p, 0.05) for p in kitti_scans(50)]
    voxel = mapper_voxel_size(100.0, 0.07)
    # Direct runs before and after the edge runs: this VM's speed drifts by tens of percent
    d = direct(scans, voxel)
    column = direct(scans, voxel, np.asfortranarray)
    edge = {coding: through_edge(scans, coding) for coding in ("f32", "q16d")}
    d2 = direct(scans, voxel)
    d_ms = statistics.median(d + d2) * 1e3
    c_ms = statistics.median(column) * 1e3
    conv_row, conv_col = (statistics.median(conversion(scans, f)) * 1e3
                          for f in (np.ascontiguousarray, np.asfortranarray))
    n = int(statistics.median(len(p) for p in scans))
    print(f"KISS-ICP's point conversion alone ({n} points)      : row-major {conv_row:.1f} ms, "
          f"column-major {conv_col:.1f} ms")
    print(f"direct KissICP.register_frame, row-major points    : {d_ms:6.1f} ms per scan "
          "(median of two runs)")
    print(f"direct, column-major (q16d's decode before 12-07)  : {c_ms:6.1f} ms per scan  "
          f"ratio {c_ms / d_ms:.2f}")
    for coding, (e_icp, e_proc, e_wall) in edge.items():
        i_ms, p_ms, w_ms = (statistics.median(x) * 1e3 for x in (e_icp, e_proc, e_wall))
        print(f"{coding}: KISS-ICP inside the edge (icp_time)         : {i_ms:6.1f} ms per scan  ratio "
              f"{i_ms / d_ms:.2f}  (target <= 1.10)")
        print(f"{coding}: + the global map update (proc_time)     : {p_ms:6.1f} ms per scan  ratio "
              f"{p_ms / d_ms:.2f}")
        print(f"{coding}: edge wall time, send -> ack                 : {w_ms:6.1f} ms per scan  ratio "
              f"{w_ms / d_ms:.2f}")


if __name__ == "__main__":
    main()
