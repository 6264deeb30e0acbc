"""Robot per-scan work on real HDL-64 scans: the daemon's own ``process()`` (drop non-finite
points, downsample, encode, publish on a live Zenoh session with a subscriber in another session).

Run: python -m benchmarks.bench_robot_scan
"""

from __future__ import annotations

import statistics
import time

from benchmarks.common import header, kitti_dir
from zoffload.robot.scans import RobotDaemon
from zoffload.robot.sensor import Reading
from zoffload.runtime.config import RobotSettings, ZenohSettings
from zoffload.runtime.session import free_tcp_port, loopback_endpoint, open_session
from zoffload.sources.kitti import KittiBinSource


def main() -> None:
    header("robot per-scan work (KITTI-360 HDL-64, 50 scans)")
    src = KittiBinSource(kitti_dir())
    frames = [src.read(i) for i in range(len(src))]
    port = free_tcp_port()
    sink = open_session(ZenohSettings(listen=[loopback_endpoint(port)], multicast_scouting=False,
                                      shared_memory=False))
    received = [0]
    sink.declare_subscriber("zoffload/data/*/scan", lambda s: received.__setitem__(0, received[0] + 1))
    for voxel in (0.05, 0.1, 0.0):
        settings = RobotSettings(voxel=voxel, wait_edge=0, zenoh=ZenohSettings(
            connect=[loopback_endpoint(port)], multicast_scouting=False, shared_memory=False))
        robot = RobotDaemon(settings, source=src)
        robot.start()
        robot.edges.add("bench")  # no edge daemon here: the subscriber above stands in for it
        for seq, f in enumerate(frames * 2):
            robot.process(Reading(seq=seq, frame=f, capture_stamp=time.time()))
        work = [r["work_ms"] for r in robot.ledger.records.values()][5:]
        kept = [r["n_sent"] / r["n_raw"] for r in robot.ledger.records.values()]
        kb = [r["bytes"] / 1e3 for r in robot.ledger.records.values()]
        print(f"voxel {voxel:4.2f} m: median {statistics.median(work):5.2f} ms, "
              f"p95 {sorted(work)[int(0.95 * len(work))]:5.2f} ms per scan; keeps "
              f"{100 * statistics.mean(kept):4.1f} % of points, {statistics.mean(kb):6.0f} kB sent")
        robot.shutdown()
    time.sleep(0.5)
    sink.close()
    print(f"(subscriber received {received[0]} scans; target: <= 10 ms per HDL-64 scan)")


if __name__ == "__main__":
    main()
