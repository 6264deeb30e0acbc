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
from typing import Any

import numpy as np

from zoffload.lab.runner import StartError, link_clock_start, run_offload
from zoffload.protocol import wire
from zoffload.runtime.config import EdgeSettings, RobotSettings
from zoffload.runtime.errors import ConfigError, ExitCode
from zoffload.sources.base import Replay


@dataclass(frozen=True)
class DemoOptions:
    duration: float = 30.0
    scans: str = "sim"
    out: str | None = None
    voxel: float = 0.05
    scale_policy: str = "rate"
    replay: Replay | None = None
    trace: str | None = "demo"  # the link emulator's trace; None: no emulator, direct TCP
    camera: str | None = None  # also stream camera frames (e.g. "coco-clips") to the edge detector
    view: Any = None  # a lab.view.live.ViewOptions: serve the live view (saved to OUT/view.rrd)


def run(opts: DemoOptions) -> int:
    if opts.trace:  # a wrong name now, with the list, not as the robot failing to connect
        from zoffload.lab.link.trace import TraceError, load_trace

        try:
            load_trace(opts.trace)
        except TraceError as exc:
            raise ConfigError(str(exc)) from exc
    try:  # a wrong policy now, not after the results folder was made
        RobotSettings(scale_policy=opts.scale_policy, voxel=opts.voxel)
    except ValueError as exc:  # pydantic's ValidationError names the setting
        raise ConfigError(str(exc).replace("\n", " ")) from exc
    out = Path(opts.out or f"results/demo-{time.strftime('%Y%m%d-%H%M%S')}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    is_sim = opts.scans == "sim"
    replay: Replay = opts.replay or ("once" if is_sim else "pingpong")
    max_scans = max(1, int(round(opts.duration * 10)))
    edge = EdgeSettings(map_dir=str(out))
    robot = RobotSettings(scans=opts.scans, replay=replay, max_scans=max_scans, voxel=opts.voxel,
                          scale_policy=opts.scale_policy, out_dir=str(out))
    if opts.camera:
        from zoffload.detect.models import resolve
        from zoffload.runtime.config import DetectorSettings, PerceptionSettings
        from zoffload.sources.images import open_image_source

        resolve("nanodet-m"), resolve("picodet-s")  # a missing model: a clear message now
        fps = open_image_source(opts.camera).rate_hz
        edge = edge.model_copy(update={"detector": DetectorSettings(enabled=True)})
        # JPEG frames: the demo's bad patch (9 Mbps) could not carry raw ones (244 Mbps)
        robot = robot.model_copy(update={"images": opts.camera, "perception": PerceptionSettings(
            encoding="jpeg", max_frames=int(opts.duration * fps))})
    link = (f"through the link emulator (trace {opts.trace})" if opts.trace else "direct TCP")
    print(f"zoffload demo: {opts.duration:g} s of {'simulated warehouse' if is_sim else opts.scans} "
          f"scans, robot -> edge {link}, results in {out}")
    view = _live_view(opts.view, out) if opts.view else None
    try:
        run = run_offload(out, edge, robot, opts.trace, ["--quiet"], max_scans, opts.duration + 120,
                          on_watch=view.announce if view else None)
    except StartError as exc:
        print(exc)
        return ExitCode.FAILURE
    finally:
        if view is not None:
            view.close()
    if run.robot_code != 0:
        return run.robot_code
    code = _report(out, run.reply, is_sim, opts.trace)
    if opts.camera:
        _report_camera(out, opts.camera)
    return code


def _live_view(options: Any, out: Path) -> Any:
    from dataclasses import replace

    from zoffload.lab.view.live import LiveView

    return LiveView(replace(options, save=options.save or str(out / "view.rrd")))


def _report(out: Path, reply: wire.MapReply | None, is_sim: bool, trace: str | None) -> int:
    from zoffload.lab.eval.plots import plot_trajectory_and_map
    from zoffload.lab.eval.trajectory import relative_to_first, trajectory_error
    from zoffload.mapping.export import write_point_cloud

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
    anchor = int(reply.seqs[0])
    if len(poses["gt_seqs"]):
        err = trajectory_error(reply.seqs, reply.poses, poses["gt_seqs"], poses["gt_poses"])
        anchor = int(np.intersect1d(reply.seqs, poses["gt_seqs"])[0])
        ref_xyz = relative_to_first(poses["gt_seqs"], poses["gt_poses"], anchor)[:, :3, 3]
    est_xyz = relative_to_first(reply.seqs, reply.poses, anchor)[:, :3, 3]
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
    fleet = robot_metrics.get("fleet")
    if fleet and (b.get("local") or fleet.get("failovers")):
        local_cpu = (fleet.get("local_cpu_ms_per_scan") or {}).get("median")
        print(f"local odometry: {b.get('local', 0)} scans registered on the robot while no edge answered "
              f"({fleet.get('attaches', 0)} attaches, max {fleet.get('max_pose_gap_scans', 0)} scans "
              f"without a pose" + (f", {local_cpu:.1f} ms CPU per local scan)" if local_cpu else ")"))
    if s["sent"]:
        print(f"points per scan: {s['mean_points_raw']:.0f} raw -> {s['mean_points_sent']:.0f} sent "
              f"({s['mean_kB_sent']:.0f} kB), {s.get('skipped', 0)} scans skipped by the policy")
    cpu = robot_metrics.get("cpu") or {}
    if cpu.get("per_scan_ms") is not None:
        print(f"robot CPU: {cpu['per_scan_ms']:.2f} ms per scan sent (offload path, median; p95 "
              f"{cpu['p95_per_scan_ms']:.2f}), whole process {cpu['process_ms_per_scan']:.1f} ms per scan "
              f"(the sensor's replay, {1e3 * cpu['sensor_s'] / max(1, b['produced']):.1f} ms, not counted)")
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


def _report_camera(out: Path, camera: str) -> None:
    from zoffload.lab.eval.detection import detection_metrics
    from zoffload.sources.images import CocoClipSource, open_image_source

    m = json.loads((out / "vision_metrics.json").read_text())
    b = m["balance"]
    dropped = b["frames_in"] - b["local_done"] - b["edge_done"] - b["pending"]
    print(f"camera: {b['frames_in']} frames, {b['local_done']} detected on the robot, {b['edge_done']} "
          f"on the edge, {dropped} dropped or lost (balanced: {m['balanced']}); strategy {m['strategy']}, "
          f"{len(m['fallbacks'])} fallback(s) to local")
    print(f"detection RTT: robot {m['robot_rtt_ms'] or float('nan'):.0f} ms, edge "
          f"{m['edge_rtt_ms'] or float('nan'):.0f} ms; robot CPU {m['cpu_process_pct'] or 0:.0f} %, "
          f"{m['mbps_out'] or 0:.1f} Mbps of frames")
    src = open_image_source(camera)
    if isinstance(src, CocoClipSource):
        d = detection_metrics(out, src.boxes, b["frames_in"])
        print(f"person AP50: {d['ap50_async']:.1f} % asynchronous (scored when the result arrived), "
              f"{d['ap50_sync']:.1f} % on the processed frames themselves")


def _print_link_phases(out: Path, trace_name: str) -> None:
    """Scans acked per phase of the link trace: how the robot rode through the bad patch."""
    import csv

    from zoffload.lab.link.trace import load_trace

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
