"""``zoffload demo``: the edge and the robot as separate processes on localhost, the simulator
as the sensor, a live progress line, then a summary and a results folder.

The demo's own Zenoh session only watches (robot status, edge liveliness) and fetches the map at
the end; all scan traffic goes robot -> edge over TCP on an explicit loopback endpoint, with
multicast scouting and shared memory off.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from zoffload import wire
from zoffload.config import EdgeSettings, RobotSettings, ZenohSettings, write_effective
from zoffload.errors import ExitCode
from zoffload.keys import Keys
from zoffload.net import free_tcp_port, loopback_endpoint
from zoffload.runner import (
    Spawned,
    StatusWatcher,
    connect_when_listening,
    fetch_map,
    link_clock_start,
    wait_token,
    watch,
)


@dataclass(frozen=True)
class DemoOptions:
    duration: float = 30.0
    scans: str = "sim"
    out: str | None = None
    voxel: float = 0.05
    replay: Literal["once", "loop", "pingpong"] | None = None
    trace: str | None = "demo"  # the link emulator's trace; None: no emulator, direct TCP


def run(opts: DemoOptions) -> int:
    out = Path(opts.out or f"results/demo-{time.strftime('%Y%m%d-%H%M%S')}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    port, link_port = free_tcp_port(), free_tcp_port()
    endpoint = loopback_endpoint(port)
    # Router-less: the edge listens; the robot connects through the link emulator (client mode, so
    # it cannot learn the edge's address and go around it); the demo's watcher connects directly.
    edge_z = ZenohSettings(listen=[endpoint], multicast_scouting=False, shared_memory=False)
    client_z = ZenohSettings(connect=[endpoint], multicast_scouting=False, shared_memory=False)
    robot_z = client_z
    if opts.trace:
        robot_z = ZenohSettings(mode="client", connect=[loopback_endpoint(link_port)],
                                multicast_scouting=False, shared_memory=False,
                                cfg=["transport/link/tcp/so_sndbuf:65536"])
    is_sim = opts.scans == "sim"
    replay = opts.replay or ("once" if is_sim else "pingpong")
    max_scans = max(1, int(round(opts.duration * 10)))
    edge = EdgeSettings(map_dir=str(out), zenoh=edge_z)
    robot = RobotSettings(scans=opts.scans, replay=replay, max_scans=max_scans, voxel=opts.voxel,
                          out_dir=str(out), zenoh=robot_z)
    write_effective(edge, out / "edge.yaml")
    write_effective(robot, out / "robot.yaml")
    keys = Keys(robot.namespace)

    link = (f"through the link emulator (trace {opts.trace})" if opts.trace else "direct TCP")
    print(f"zoffload demo: {opts.duration:g} s of {'simulated warehouse' if is_sim else opts.scans} "
          f"scans, robot -> edge {link}, results in {out}")
    edge_p = Spawned("edge", ["edge", "--settings", str(out / "edge.yaml")], out / "edge.log")
    link_p = None
    if opts.trace:
        link_p = Spawned("link", ["link", "--trace", opts.trace, "--listen-port", str(link_port),
                                  "--target", f"127.0.0.1:{port}", "--report", str(out / "link.csv"),
                                  "--quiet"], out / "link.log")
    robot_p: Spawned | None = None
    try:
        session = connect_when_listening(client_z, edge_p)
        if session is None:
            print("the edge did not start:\n" + edge_p.tail())
            return ExitCode.FAILURE
        with session:
            status = StatusWatcher(session, keys, robot.robot_id)
            if not wait_token(session, keys.any_edge_alive(), 30):
                print("the edge did not come up:\n" + edge_p.tail())
                return ExitCode.FAILURE
            robot_p = Spawned("robot", ["robot", "--settings", str(out / "robot.yaml")], out / "robot.log")
            code = watch(robot_p, status, max_scans, opts.duration + 120)
            if code != 0:
                print(f"\nthe robot exited with code {code}:\n" + robot_p.tail())
                return code
            reply = fetch_map(session, keys, robot.robot_id)
            status.close()
    finally:
        if robot_p is not None:
            robot_p.stop()
        if link_p is not None:
            link_p.stop()
        edge_code = edge_p.stop()
    if edge_code != 0:
        print(f"the edge exited with code {edge_code}:\n" + edge_p.tail())
    return _report(out, reply, is_sim, opts.trace)


def _report(out: Path, reply: wire.MapReply | None, is_sim: bool, trace: str | None) -> int:
    from zoffload.edge.store import write_point_cloud
    from zoffload.eval.plots import plot_trajectory_and_map
    from zoffload.eval.trajectory import trajectory_error

    robot_metrics = json.loads((out / "robot_metrics.json").read_text())
    poses = np.load(out / "robot_poses.npz")
    summary: dict[str, Any] = {"robot": robot_metrics}
    if reply is None or reply.scans == 0:
        print("no map came back from the edge")
        (out / "metrics.json").write_text(json.dumps(summary, indent=2))
        return ExitCode.FAILURE
    write_point_cloud(out / "map.ply", reply.points)
    np.savez(out / "trajectory.npz", seqs=reply.seqs, poses=reply.poses)
    err = None
    ref_xyz = None
    if len(poses["gt_seqs"]):
        err = trajectory_error(reply.seqs, reply.poses, poses["gt_seqs"], poses["gt_poses"])
        anchor = int(np.intersect1d(reply.seqs, poses["gt_seqs"])[0])
        gi = np.flatnonzero(poses["gt_seqs"] == anchor)[0]
        ref = np.linalg.inv(poses["gt_poses"][gi]) @ poses["gt_poses"]
        ref_xyz = ref[:, :3, 3]
    ei = np.flatnonzero(reply.seqs == (int(np.intersect1d(reply.seqs, poses["gt_seqs"])[0])
                                       if ref_xyz is not None else reply.seqs[0]))[0]
    est_xyz = (np.linalg.inv(reply.poses[ei]) @ reply.poses)[:, :3, 3]
    summary["map"] = {"points": len(reply.points), "scans_registered": reply.scans}
    summary["trajectory_error"] = err.as_dict() if err else None
    summary["trajectory_reference"] = "simulator ground truth" if is_sim else "none (real data)"
    plot_trajectory_and_map(out / "trajectory.png", est_xyz, ref_xyz, reply.points,
                            title="zoffload demo: edge map and trajectory")
    (out / "metrics.json").write_text(json.dumps(summary, indent=2))

    s, b = robot_metrics["scans"], robot_metrics["balance"]
    print("\n=== zoffload demo summary ===")
    print(f"scans: {b['produced']} produced, {b['published']} sent, {b['acked']} acked, "
          f"{b['lost']} lost, {b['late']} late, {b['edge_dropped']} dropped by the edge, "
          f"{b['dropped_source']} dropped at source (balanced: {robot_metrics['balanced']})")
    if s["sent"]:
        print(f"points per scan: {s['mean_points_raw']:.0f} raw -> {s['mean_points_sent']:.0f} sent "
              f"({s['mean_kB_sent']:.0f} kB), robot work {s['mean_work_ms']:.1f} ms/scan")
    if s["mean_T"] is not None:
        print(f"inter-arrival at the edge: mean T {s['mean_T']:.3f} s, "
              f"{100 * s['frac_T_le_0.11']:.0f} % <= 0.11 s; mean RTT {s['mean_rtt_ms']:.0f} ms")
    if trace:
        _print_link_phases(out, trace)
    print(f"map: {len(reply.points):,} points from {reply.scans} registered scans")
    if err:
        print(f"trajectory vs ground truth: ATE RMSE {err.ate_rmse:.3f} m, max {err.ate_max:.3f} m, "
              f"final {err.final_error:.3f} m over {err.path_length:.1f} m ({err.drift_percent:.2f} %)")
    print(f"results: {out} (metrics.json, map.ply, trajectory.png, robot_scans.csv, configs, logs)")
    return ExitCode.OK


def _print_link_phases(out: Path, trace_name: str) -> None:
    """Scans acked per phase of the link trace: how the robot rode through the bad patch."""
    import csv

    from zoffload.link.trace import load_trace

    trace = load_trace(trace_name)
    wall_start = link_clock_start(out / "link.log")
    if wall_start is None:
        return
    with open(out / "robot_scans.csv") as f:
        recs = list(csv.DictReader(f))
    phases: dict[tuple[float, float], list[str]] = {}
    for r in recs:
        st = trace.at(float(r["capture_stamp"]) - wall_start)
        key = (0.0, 0.0) if st.outage else (st.up_mbps, st.delay_ms)
        phases.setdefault(key, []).append(r["status"])
    parts = []
    for (mbps, delay), statuses in phases.items():
        name = "outage" if mbps == 0 else f"{mbps:g} Mbps/{delay:g} ms"
        parts.append(f"{name}: {statuses.count('acked')}/{len(statuses)} acked")
    print("link phases: " + "; ".join(parts))
