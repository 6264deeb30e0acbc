"""The robot's per-scan path stage by stage, without the network: where its CPU goes.

For each sensor (simulator VLP-16, KITTI-360 HDL-64) and each path (the defaults on a fast link:
the rate policy sends the scan as it is, uncompressed q16d; the defaults on a narrow link: a
0.1 m grid, compressed q16d; the paper's baseline: a fixed 5 cm grid, float32), the thread CPU
time (``time.thread_time``, median over the scans) of: the sizing (``ScanSizer.size``: the
policy's choice, the grid pass with the invalid points skipped, the payload's layout filled from
the grid), of which the grid pass alone, the compression (``finish``) and the wire encoding. The
Zenoh ``put()`` and the threads around it are in ``bench_robot_cost`` (whole path) and
``bench_stream`` (throughput).

Run: python -m benchmarks.bench_robot_scan
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from benchmarks.common import header, sensor_frames
from zoffload.mapping.voxel import VoxelGrid, warmup
from zoffload.policy.rate import LinkAwareScale, LinkView
from zoffload.policy.scale import FixedScale
from zoffload.protocol import coding, wire
from zoffload.robot.sizer import ScanSizer, finish, scan_message

FAST = LinkView(0.1, 1e9, 3.0, 0.1, raw_bytes_per_point=6.0)  # on time: the budget grows 5 % a scan


def run(frames: list[Any], sizer: ScanSizer, link: LinkView, grid_voxel: float | None) -> dict[str, float]:
    times: dict[str, list[float]] = {"size": [], "grid": [], "compress": [], "encode": []}
    grid = VoxelGrid()
    data = b""
    n_points = 0
    for i, f in enumerate(frames * 2):  # the first pass lets the policy settle
        view = LinkView(link.last_t, link.acked_bytes_per_s, link.bytes_per_point, link.period, acks=i,
                        raw_bytes_per_point=link.raw_bytes_per_point)
        t0 = time.thread_time()
        sized = sizer.size(f.points, None, lambda view=view: view)  # type: ignore[misc]
        t1 = time.thread_time()
        if grid_voxel:
            grid.run(f.points, grid_voxel, skip_invalid=True)
        t2 = time.thread_time()
        finish(sized, 1)
        t3 = time.thread_time()
        msg = scan_message(sized, robot="r", seq=i, send_stamp=0.0, capture_stamp=0.0, voxel_max=0.5,
                           max_range=100.0, n_raw=sized.n_valid)
        t4 = time.thread_time()
        data = wire.encode(msg)
        t5 = time.thread_time()
        for key, dt in (("size", t1 - t0), ("grid", t2 - t1), ("compress", t3 - t2), ("encode", t5 - t4)):
            times[key].append(dt * 1e3)
        n_points = sized.n_points
        sizer.pool.give(sized.buffer)
    out = {k: statistics.median(v[len(frames):]) for k, v in times.items()}  # the second pass
    out["kB"] = len(data) / 1e3
    out["points"] = n_points
    return out


def main() -> None:
    header("robot per-scan path by stage (thread CPU time, median; no network)")
    warmup()
    coding.warmup()
    for sensor, rng in (("sim", (0.01, 0.07)), ("kitti", (0.02, 0.5))):
        frames, _ = sensor_frames(sensor, 50)
        print(f"\n{'simulator VLP-16' if sensor == 'sim' else 'KITTI-360 HDL-64'}: "
              f"{statistics.mean(len(f.points) for f in frames):,.0f} points per scan")
        narrow = LinkAwareScale(rng, raw_share=1.0)
        cases = [
            ("defaults, fast link", ScanSizer(LinkAwareScale(rng), "q16d"), FAST, None),
            ("defaults, narrow link", ScanSizer(narrow, "q16d"), FAST, None),
            ("fixed 0.05 + f32 (paper)", ScanSizer(FixedScale(0.05), "f32"), FAST, 0.05),
        ]
        print(f"{'path':34} {'points':>8} {'kB':>6} {'size':>7} {'(grid)':>7} {'compress':>9} {'encode':>7}")
        for label, sizer, link, grid_voxel in cases:
            if sizer.policy is narrow:  # a budget that holds about a 0.1 m grid's compressed bytes
                narrow.choose_cloud(frames[0].points, LinkView(0.0, float("nan"), float("nan"), 0.1))
                narrow.budget = len(VoxelGrid().run(frames[0].points, 0.1, skip_invalid=True)) * 2.6
                narrow.grow_fast = narrow.grow_slow = 0.0
                link = LinkView(0.1, 1e6, 2.5, 0.1, raw_bytes_per_point=6.0)
                grid_voxel = 0.1
            r = run(frames, sizer, link, grid_voxel)
            print(f"{label:34} {r['points']:8,.0f} {r['kB']:6.0f} {r['size']:5.2f}ms "
                  f"{r.get('grid', 0):5.2f}ms {r['compress']:7.2f}ms {r['encode']:5.2f}ms")


if __name__ == "__main__":
    main()
