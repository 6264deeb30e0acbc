"""``zoffload demo``: the edge and the robot as separate processes on localhost, the simulator
as the sensor, a live progress line, then a summary and a results folder.

The demo's own Zenoh session only watches (robot status, edge liveliness) and fetches the map at
the end; all scan traffic goes robot -> edge over TCP on an explicit loopback endpoint, with
multicast scouting and shared memory off.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from zoffload import wire
from zoffload.config import EdgeSettings, RobotSettings, ZenohSettings, open_session, write_effective
from zoffload.errors import ExitCode
from zoffload.keys import Keys
from zoffload.net import free_tcp_port, loopback_endpoint


@dataclass(frozen=True)
class DemoOptions:
    duration: float = 30.0
    scans: str = "sim"
    out: str | None = None
    voxel: float = 0.05
    replay: Literal["once", "loop", "pingpong"] | None = None


class Spawned:
    """A daemon in its own process, with its log in the results folder."""

    def __init__(self, name: str, args: list[str], log_path: Path) -> None:
        self.name = name
        self.log_path = log_path
        self._log = open(log_path, "w")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, "-m", "zoffload.cli", *args],
                                     stdout=self._log, stderr=subprocess.STDOUT, env=env)

    def stop(self, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return int(self.proc.returncode)

    def tail(self, n: int = 15) -> str:
        return "".join(self.log_path.read_text().splitlines(keepends=True)[-n:])


def _progress_line(st: dict[str, float], elapsed: float, total: int) -> str:
    return (
        f"[{elapsed:5.1f} s] scans {int(st.get('published', 0))}/{total} sent, "
        f"{int(st.get('acked', 0))} acked, {int(st.get('lost', 0))} lost | "
        f"voxel {st.get('voxel', 0):.2f} m | T {st.get('last_T', 0):.3f} s | "
        f"RTT {st.get('rtt_ms', float('nan')):.0f} ms | map {int(st.get('map_points', 0)):,} pts"
    )


def run(opts: DemoOptions) -> int:
    out = Path(opts.out or f"results/demo-{time.strftime('%Y%m%d-%H%M%S')}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    port = free_tcp_port()
    endpoint = loopback_endpoint(port)
    # Router-less: the edge listens, the robot and the demo's watcher connect to it.
    edge_z = ZenohSettings(listen=[endpoint], multicast_scouting=False, shared_memory=False)
    client_z = ZenohSettings(connect=[endpoint], multicast_scouting=False, shared_memory=False)
    is_sim = opts.scans == "sim"
    replay = opts.replay or ("once" if is_sim else "pingpong")
    max_scans = max(1, int(round(opts.duration * 10)))
    edge = EdgeSettings(map_dir=str(out), zenoh=edge_z)
    robot = RobotSettings(scans=opts.scans, replay=replay, max_scans=max_scans, voxel=opts.voxel,
                          out_dir=str(out), zenoh=client_z)
    write_effective(edge, out / "edge.yaml")
    write_effective(robot, out / "robot.yaml")
    keys = Keys(robot.namespace)

    print(f"zoffload demo: {opts.duration:g} s of {'simulated warehouse' if is_sim else opts.scans} "
          f"scans, edge on {endpoint}, results in {out}")
    edge_p = Spawned("edge", ["edge", "--settings", str(out / "edge.yaml")], out / "edge.log")
    robot_p: Spawned | None = None
    latest: dict[str, float] = {}
    edge_up = threading.Event()
    try:
        session = _connect(client_z, edge_p)
        if session is None:
            print("the edge did not start:\n" + edge_p.tail())
            return ExitCode.FAILURE
        with session:
            def on_status(sample: Any) -> None:
                try:
                    msg = wire.decode(sample.payload.to_bytes(), expect=wire.Status)
                    latest.update(msg.values)  # type: ignore[attr-defined]
                except wire.WireError:
                    pass

            def on_edge(sample: Any) -> None:
                edge_up.set()

            sub = session.declare_subscriber(keys.robot_status(robot.robot_id), on_status)
            lsub = session.liveliness().declare_subscriber(keys.any_edge_alive(), on_edge, history=True)
            if not edge_up.wait(30):
                print("the edge did not come up:\n" + edge_p.tail())
                return ExitCode.FAILURE
            robot_p = Spawned("robot", ["robot", "--settings", str(out / "robot.yaml")], out / "robot.log")
            code = _watch(robot_p, latest, max_scans, opts.duration)
            if code != 0:
                print(f"\nthe robot exited with code {code}:\n" + robot_p.tail())
                return code
            reply = _fetch_map(session, keys, robot.robot_id)
            sub.undeclare()
            lsub.undeclare()
    finally:
        if robot_p is not None:
            robot_p.stop()
        edge_code = edge_p.stop()
    if edge_code != 0:
        print(f"the edge exited with code {edge_code}:\n" + edge_p.tail())
    return _report(out, reply, is_sim)


def _connect(z: ZenohSettings, edge_p: Spawned) -> Any:
    """Open the watcher session once the edge listens (its port opens a moment after start)."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if edge_p.proc.poll() is not None:
            return None
        try:
            return open_session(z)
        except Exception:
            time.sleep(0.3)
    return None


def _watch(robot_p: Spawned, latest: dict[str, float], total: int, duration: float) -> int:
    tty = sys.stdout.isatty()
    start = time.monotonic()
    next_plain = start
    while robot_p.proc.poll() is None:
        time.sleep(0.25)
        elapsed = time.monotonic() - start
        line = _progress_line(latest, elapsed, total)
        if tty:
            print("\r" + line.ljust(120), end="", flush=True)
        elif time.monotonic() >= next_plain:
            print(line, flush=True)
            next_plain = time.monotonic() + 5
        if elapsed > duration + 120:
            print("\nthe robot did not finish in time; stopping it")
            robot_p.stop()
    if tty:
        print()
    return int(robot_p.proc.returncode)


def _fetch_map(session: Any, keys: Keys, robot: str) -> wire.MapReply | None:
    for reply in session.get(keys.map(robot), timeout=20.0):
        if reply.ok is not None:
            msg = wire.decode(reply.ok.payload.to_bytes(), expect=wire.MapReply)
            assert isinstance(msg, wire.MapReply)
            return msg
    return None


def _report(out: Path, reply: wire.MapReply | None, is_sim: bool) -> int:
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
    print(f"map: {len(reply.points):,} points from {reply.scans} registered scans")
    if err:
        print(f"trajectory vs ground truth: ATE RMSE {err.ate_rmse:.3f} m, max {err.ate_max:.3f} m, "
              f"final {err.final_error:.3f} m over {err.path_length:.1f} m ({err.drift_percent:.2f} %)")
    print(f"results: {out} (metrics.json, map.ply, trajectory.png, robot_scans.csv, configs, logs)")
    return ExitCode.OK
