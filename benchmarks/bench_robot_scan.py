"""Robot per-scan work on real HDL-64 scans: the scan pipeline's own ``process()`` (drop
non-finite points, choose the voxel size, downsample, encode, publish on a live Zenoh session with
a subscriber in another session), at the robot's defaults and at the paper's baseline side by side.

Run: python -m benchmarks.bench_robot_scan
"""

from __future__ import annotations

import statistics
import time

from benchmarks.common import header, kitti_dir
from zoffload.protocol.keys import Keys
from zoffload.robot.presence import EdgePresence
from zoffload.robot.scans import scan_streamer
from zoffload.robot.sensor import Reading
from zoffload.runtime.config import RobotSettings, ZenohSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import free_tcp_port, loopback_endpoint, open_session
from zoffload.sources.kitti import KittiBinSource

# (label, settings overrides): the defaults first, then the paper's baseline path and its neighbours
CASES = [
    ("defaults (rate + q16z, range 0.02-0.5)", {"voxel_range": (0.02, 0.5)}),
    ("fixed 0.05 m, f32 (paper baseline)", {"scale_policy": "fixed", "voxel": 0.05, "scan_coding": "f32"}),
    ("fixed 0.1 m, f32", {"scale_policy": "fixed", "voxel": 0.1, "scan_coding": "f32"}),
    ("raw, f32", {"scale_policy": "fixed", "voxel": 0.0, "scan_coding": "f32"}),
]


def main() -> None:
    header("robot per-scan work (KITTI-360 HDL-64, 50 scans x 2), wall time of process()")
    src = KittiBinSource(kitti_dir())
    frames = [src.read(i) for i in range(len(src))]
    port = free_tcp_port()
    sink = open_session(ZenohSettings(listen=[loopback_endpoint(port)], multicast_scouting=False,
                                      shared_memory=False))
    received = [0]
    sink.declare_subscriber("zoffload/data/*/scan", lambda s: received.__setitem__(0, received[0] + 1))
    # No edge daemon here: the subscriber above stands in for it, and so does its token
    token = sink.liveliness().declare_token(Keys().edge_alive("bench"))
    for label, over in CASES:
        z = ZenohSettings(connect=[loopback_endpoint(port)], multicast_scouting=False, shared_memory=False)
        settings = RobotSettings(wait_edge=0, max_in_flight=0, zenoh=z, **over)  # type: ignore[arg-type]
        session = open_session(settings.zenoh)
        presence = EdgePresence(Keys())
        presence.start(session)
        presence.wait(5)
        robot = scan_streamer(settings, StopSignal(), source=src)
        robot.start(session, presence)
        for seq, f in enumerate(frames * 2):
            robot.process(Reading(seq=seq, frame=f, capture_stamp=time.time()))
        recs = list(robot.ledger.records.values())
        work = [r["work_ms"] for r in recs][5:]
        kept = [r["n_sent"] / r["n_raw"] for r in recs]
        kb = [r["bytes"] / 1e3 for r in recs]
        print(f"{label:40}: median {statistics.median(work):5.2f} ms, "
              f"p95 {sorted(work)[int(0.95 * len(work))]:5.2f} ms per scan; keeps "
              f"{100 * statistics.mean(kept):5.1f} % of points, {statistics.mean(kb):6.0f} kB sent")
        robot.close()
        presence.stop()
        session.close()
    time.sleep(0.5)
    token.undeclare()
    sink.close()
    print(f"(subscriber received {received[0]} scans)")


if __name__ == "__main__":
    main()
