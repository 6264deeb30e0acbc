"""``zoffload experiment fleet``: N robots × M edges as local processes around a Zenoh router,
with scripted edge kills, drains and restarts, and optionally a link trace per robot.

Processes: ``zoffload router`` on a free loopback port; M ``zoffload edge`` clients
(``edge1`` ...) and N ``zoffload robot`` clients (``robot1`` ...), each robot either straight to
the router or through its own ``zoffload link`` emulator. With ``routers=2`` the edges have a
router of their own (``router2``, linked to the robots' one), as a rack's would be. Multicast
scouting and shared memory are off everywhere; every process announces a short Zenoh lease
(``lease_ms``, default 1 s: the router notices a silent edge within it; a SIGKILLed one closes its
TCP connection at once on loopback).
The event clock starts when every robot's liveliness token is seen. Robots replay the simulator
(a different scene seed each, with ground truth) or a folder of scans (KITTI-360: the reference is
KISS-ICP on every raw scan, as in ``experiment scan``).

Each run writes ``runN/``: ``results.json`` (per-robot figures, CPU per process, the event
timeline), the robots' own folders under ``robots/``, the edges' maps under ``edges/`` and every
log. ``--baseline`` repeats the runs without events under ``baseline/runN``. Runs already complete
are kept, so the same command resumes. Then ``report.md`` and ``results.json`` at the top: mean ±
sd over repeats and the ATE ratio scripted / baseline.
"""

from __future__ import annotations

import json
import shlex
import signal
import subprocess
import threading
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.lab import fleet_report as fr
from zoffload.lab.fleet_scenario import (
    EdgeEvent,
    edge_ids,
    kills,
    parse_edge_cpu,
    parse_events,
    parse_traces,
    robot_ids,
)
from zoffload.lab.proctree import TreeCpu
from zoffload.lab.runner import (
    ROBOT_SNDBUF,
    Spawned,
    StartError,
    connect_when_listening,
    environment_settings,
    sigterm_interrupts,
    wait_token,
)
from zoffload.protocol.keys import Keys
from zoffload.robot.scanlog import read_scan_rows
from zoffload.runtime.session import free_tcp_port, loopback_endpoint

SESSION = ["--no-multicast-scouting", "--no-shm"]
REPLAY_FOLDER = "pingpong"  # a folder of scans plays forth and back (the reference follows the same order)
KEYS = Keys()


@dataclass(frozen=True)
class FleetExperiment:
    out: str
    robots: int = 3
    edges: int = 2
    events: str = ""  # e.g. "kill:edge1@5,restart:edge1@8,drain:edge2@12"
    traces: tuple[str, ...] = ()  # TRACE or ROBOT=TRACE
    scans: str = "sim"
    max_scans: int = 300  # per robot
    rate_hz: float | None = None
    repeat: int = 1
    baseline: bool = False
    seed: int = 0
    lease_ms: int = 1000
    routers: int = 1  # 2: the edges connect to a second router, linked to the robots'
    edge_workers: int | None = None
    edge_flags: str = ""  # extra flags for every edge, e.g. "--fleet.checkpoint-every 5"
    robot_flags: str = ""  # extra flags for every robot, e.g. "--fleet.no-attach"
    edge_cpu: str = ""  # CFS quota per edge process, "CORES" or "edge1=0.5,edge2=0.9" (fleet_scenario.py)


class CpuSampler:
    """CPU seconds of each child process and the processes it started (the edge's mapper
    processes: lab/proctree.py), sampled every half second with psutil (a killed process keeps
    its last sample)."""

    def __init__(self, period: float = 0.5) -> None:
        import psutil

        self._psutil = psutil
        self._procs: dict[str, Any] = {}
        self.figures: dict[str, dict[str, float]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, args=(period,), daemon=True)
        self._thread.start()

    def add(self, name: str, pid: int) -> None:
        try:
            p = TreeCpu(self._psutil.Process(pid))
            with self._lock:
                self._procs[name] = p
                self.figures[name] = {"pid": pid, "cpu_s": 0.0, "wall_s": 0.0, "cores": 0.0}
        except self._psutil.Error:
            pass

    def _sample(self) -> None:
        with self._lock:
            procs = list(self._procs.items())
        for name, p in procs:
            try:
                cpu = p.read()
                wall = time.time() - p.proc.create_time()
            except self._psutil.Error:
                continue
            self.figures[name].update(cpu_s=cpu, wall_s=wall, cores=cpu / wall if wall > 0 else 0.0)

    def _loop(self, period: float) -> None:
        while not self._stop.wait(period):
            self._sample()

    def close(self) -> dict[str, dict[str, float]]:
        self._stop.set()
        self._thread.join(5)
        return self.figures


class Fleet:
    """The processes of one run and the edge events applied to them."""

    def __init__(self, exp: FleetExperiment, out: Path, sampler: CpuSampler,
                 edge_cpu: dict[str, float]) -> None:
        self.exp, self.out, self.cpu = exp, out, sampler
        self.port = free_tcp_port()
        self.endpoint = loopback_endpoint(self.port)
        self.edge_endpoint = self.endpoint if exp.routers == 1 else loopback_endpoint(free_tcp_port())
        self.lease = ["--cfg", f"transport/link/tx/lease:{exp.lease_ms}",
                      "--cfg", "transport/link/tx/keep_alive:4"]
        self.edges: dict[str, Spawned] = {}
        self.starts: dict[str, int] = {}
        self.others: list[Spawned] = []
        self.robots: dict[str, Spawned] = {}
        self.edge_cpu = edge_cpu  # edge id -> cores of its CFS quota (fleet_scenario.parse_edge_cpu)
        self.quotas: dict[str, str] = {}  # process name -> how its quota was applied
        self._groups: list[Path] = []

    def _spawn(self, name: str, args: list[str]) -> Spawned:
        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        p = Spawned(name, args, self.out / "logs" / f"{name}.log")
        self.cpu.add(name, p.proc.pid)
        return p

    def start_routers(self) -> list[Spawned]:
        """The robots' router, and the edges' when there are two (linked to the first)."""
        routers = [self._spawn("router", ["router", *SESSION, "-l", self.endpoint, *self.lease])]
        if self.edge_endpoint != self.endpoint:
            routers.append(self._spawn("router2", ["router", *SESSION, "-l", self.edge_endpoint,
                                                   "-e", self.endpoint, *self.lease]))
        self.others += routers
        return routers

    def start_edge(self, edge: str) -> None:
        n = self.starts[edge] = self.starts.get(edge, 0) + 1
        name = edge if n == 1 else f"{edge}.{n}"
        args = ["edge", *SESSION, "-m", "client", "-e", self.edge_endpoint, *self.lease, "--edge-id", edge,
                "--map-dir", str(self.out / "edges" / name)]
        if self.exp.edge_workers:
            args += ["--mapper.workers", str(self.exp.edge_workers)]
        self.edges[edge] = self._spawn(name, args + shlex.split(self.exp.edge_flags))
        if edge in self.edge_cpu:
            self._limit(name, self.edges[edge], self.edge_cpu[edge])

    def _limit(self, name: str, p: Spawned, cores: float) -> None:
        """The process under a CFS quota (its threads start after this: an interpreter's start-up
        outlasts it). Without a writable cgroup the run would measure something else: it stops."""
        from zoffload.runtime.quota import limit_process

        how, group = limit_process(p.proc.pid, cores, f"zoffload-fleet-{self.port}-{name}")
        if group is None:
            raise StartError(f"no CPU quota for {name}: needs root and a writable cgroup with the cpu "
                             "controller (or the process had already exited; see the log)")
        self._groups.append(group)
        self.quotas[name] = f"{cores:g} cores ({how})"

    def start_robot(self, robot: str, index: int, seed: int, trace: str | None) -> None:
        endpoint, extra = self.endpoint, []
        if trace:  # the robot's own emulated link in front of the router
            lp = free_tcp_port()
            self.others.append(self._spawn(f"link-{robot}", [
                "link", "--trace", trace, "--listen-port", str(lp), "--target", f"127.0.0.1:{self.port}",
                "--report", str(self.out / "logs" / f"link-{robot}.csv"), "--seed", str(seed + index),
                "--quiet"]))
            endpoint, extra = loopback_endpoint(lp), ["--cfg", f"transport/link/tcp/so_sndbuf:{ROBOT_SNDBUF}"]
        e = self.exp
        args = ["robot", *SESSION, "-m", "client", "-e", endpoint, *self.lease, *extra, "--robot-id", robot,
                "--scans", e.scans, "--max-scans", str(e.max_scans), "--sim-seed", str(seed + index),
                "--replay", "once" if e.scans == "sim" else REPLAY_FOLDER, "--wait-edge", "30",
                "--out", str(self.out / "robots" / robot)]
        if e.rate_hz:
            args += ["--rate", str(e.rate_hz)]
        self.robots[robot] = self._spawn(robot, args + shlex.split(e.robot_flags))

    def apply(self, event: EdgeEvent) -> None:
        p = self.edges[event.edge]
        if event.action == "kill":
            p.proc.kill()
        elif event.action == "drain":
            p.proc.send_signal(signal.SIGTERM)
        else:  # restart: the drained or killed process must be gone first (same id, same token)
            try:
                p.proc.wait(30)
            except subprocess.TimeoutExpired:
                p.proc.kill()
                p.proc.wait()
            p.stop()
            self.start_edge(event.edge)

    def stop_all(self) -> dict[str, int]:
        from zoffload.runtime.quota import remove_group

        codes = {}
        try:
            for name, p in [*self.robots.items(), *self.edges.items()]:
                codes[name] = p.stop()
            for p in reversed(self.others):  # links, then the router
                codes[p.name] = p.stop()
        finally:
            for group in self._groups:
                if not remove_group(group):
                    print(f"cgroup {group} not removed (a process still in it?)", flush=True)
        return codes


def _run_once(exp: FleetExperiment, out: Path, events: list[EdgeEvent], traces: dict[str, str],
              quotas: dict[str, float], seed: int, refs: dict[int, Any]) -> dict[str, Any]:
    from zoffload.lab.runner import loopback_zenoh

    out.mkdir(parents=True, exist_ok=True)
    robots, edges = robot_ids(exp.robots), edge_ids(exp.edges)
    sampler = CpuSampler()
    fleet = Fleet(exp, out, sampler, quotas)
    timeline: list[dict[str, Any]] = []
    rate = exp.rate_hz or 10.0
    limit = exp.max_scans / rate + 90
    try:
        routers = fleet.start_routers()
        session = connect_when_listening(loopback_zenoh(mode="client", connect=[fleet.endpoint]), routers[0])
        if session is None:
            raise StartError("the router did not start:\n" + routers[0].tail())
        if len(routers) > 1:  # the edges' router must listen before the edges dial it
            probe = connect_when_listening(loopback_zenoh(mode="client", connect=[fleet.edge_endpoint]),
                                           routers[1])
            if probe is None:
                raise StartError("the edges' router did not start:\n" + routers[1].tail())
            probe.close()
        with session:  # on the robots' router: the edges' tokens come across the router link
            for e in edges:
                fleet.start_edge(e)
            for e in edges:
                if not wait_token(session, KEYS.edge_alive(e), 60, alive=fleet.edges[e].running):
                    raise StartError(f"{e} did not come up:\n" + fleet.edges[e].tail())
            for i, r in enumerate(robots):
                fleet.start_robot(r, i, seed, traces.get(r))
            for r in robots:
                if not wait_token(session, KEYS.robot_alive(r), 60, alive=fleet.robots[r].running):
                    raise StartError(f"{r} did not come up:\n" + fleet.robots[r].tail())
            t0, wall0 = time.monotonic(), time.time()
            pending = list(events)
            while any(p.proc.poll() is None for p in fleet.robots.values()):
                now = time.monotonic() - t0
                while pending and pending[0].at <= now:
                    ev = pending.pop(0)
                    fleet.apply(ev)
                    timeline.append({"event": ev.label(), "t": time.monotonic() - t0, "wall": time.time()})
                    print(f"[{now:5.1f} s] {ev.label()}", flush=True)
                if now > limit:
                    print(f"robots still running after {limit:.0f} s: stopping them", flush=True)
                    break
                time.sleep(0.05)
            timeline += [{"event": f"not applied (robots done): {ev.label()}", "t": None, "wall": None}
                         for ev in pending]
    finally:
        codes = fleet.stop_all()
        cpu = sampler.close()
    rows = {r: read_scan_rows(out / "robots" / r / "robot_scans.csv") for r in robots}
    figures = {r: _robot_result(exp, out / "robots" / r, rows[r], rate, refs) for r in robots}
    settled = fr.settled_phase(rows, 1 / rate, wall0)
    result = {"experiment": _jsonable(exp), "seed": seed, "environment": environment_settings(),
              "events": timeline, "clock_wall_start": wall0,
              "traces": traces, "edge_cpu": fleet.quotas, "exit_codes": codes, "cpu": cpu, "robots": figures,
              "settled": settled, "summary": fr.run_summary(figures, cpu, settled)}
    (out / "results.json").write_text(json.dumps(result, indent=2, default=str))
    return result


def _robot_result(exp: FleetExperiment, folder: Path, rows: list[dict[str, Any]], rate: float,
                  refs: dict[int, Any]) -> dict[str, Any]:
    mp = folder / "robot_metrics.json"
    metrics = json.loads(mp.read_text()) if mp.exists() else {}
    fig = fr.robot_figures(metrics, rows, 1 / rate, _ate(exp, folder, rows, refs))
    fig["exited"] = mp.exists()
    return fig


def _ate(exp: FleetExperiment, folder: Path, rows: list[dict[str, Any]], refs: dict[int, Any]
         ) -> dict[str, Any] | None:
    """Trajectory error of the robot's poses (edge and local) against ground truth (simulator) or
    KISS-ICP on every raw scan (a folder)."""
    from zoffload.lab.eval.trajectory import trajectory_error

    path = folder / "robot_poses.npz"
    if not path.exists():
        return None
    poses = np.load(path)
    seqs, est = poses["acked_seqs"], poses["acked_poses"]
    if "local_seqs" in poses.files:  # local poses kept apart: merge them, edge poses win
        extra = ~np.isin(poses["local_seqs"], seqs)
        seqs = np.concatenate([seqs, poses["local_seqs"][extra]])
        est = np.concatenate([est, poses["local_poses"][extra]])
    if len(seqs) < 2:
        return None
    if exp.scans == "sim":
        ref_seqs, ref_poses = poses["gt_seqs"], poses["gt_poses"]
    else:
        newest = max((int(r["seq"]) for r in rows), default=-1)
        if newest not in refs:
            from zoffload.lab.scan_experiment import reference_trajectory
            from zoffload.sources import open_scan_source

            refs[newest] = reference_trajectory(open_scan_source(exp.scans), REPLAY_FOLDER, newest)
        ref_seqs, ref_poses = refs[newest]
    err = trajectory_error(seqs, est, ref_seqs, ref_poses)
    return err.as_dict() if err else None


def _jsonable(exp: FleetExperiment) -> dict[str, Any]:
    d = asdict(exp)
    d["keys"] = KEYS.ns
    return d


def _series(exp: FleetExperiment, folder: Path, events: list[EdgeEvent], traces: dict[str, str],
            quotas: dict[str, float], refs: dict[int, Any]) -> list[dict[str, Any]]:
    runs = []
    environment = environment_settings()
    for i in range(1, exp.repeat + 1):
        run = folder / f"run{i}"
        if (run / "results.json").exists():  # resume: a complete run is kept, under the same variables
            done = json.loads((run / "results.json").read_text())
            if done.get("environment", {}) == environment:
                runs.append(done)
                continue
            print(f"{run}: made with the variables {done.get('environment', {})}, not "
                  f"{environment}: run again", flush=True)
            (run / "results.json").unlink()  # (a rerun cut short must not leave the old one complete)
        print(f"{folder.name} run {i}/{exp.repeat}: {exp.robots} robots x {exp.edges} edges, "
              f"events: {', '.join(e.label() for e in events) or 'none'}", flush=True)
        runs.append(_run_once(exp, run, events, traces, quotas, exp.seed + i - 1, refs))
        print(summary_line(runs[-1]["summary"]), flush=True)
    return runs


def run_fleet_experiment(exp: FleetExperiment) -> dict[str, Any]:
    """Every run (and the baseline's), then ``report.md`` and ``results.json`` under ``out``."""
    events = parse_events(exp.events, edge_ids(exp.edges))
    traces = parse_traces(exp.traces, robot_ids(exp.robots))
    quotas = parse_edge_cpu(exp.edge_cpu, edge_ids(exp.edges))
    environment_settings()  # a variable naming no setting fails here, before the run
    out = Path(exp.out)
    out.mkdir(parents=True, exist_ok=True)
    refs: dict[int, Any] = {}
    with sigterm_interrupts():  # a SIGTERM to the harness stops its router, edges and robots too
        runs = _series(exp, out, events, traces, quotas, refs)
        base = (_series(replace(exp, events=""), out / "baseline", [], traces, quotas, refs) if exp.baseline
                else None)
    agg = fr.aggregate([r["summary"] for r in runs])
    base_agg = fr.aggregate([r["summary"] for r in base]) if base else None
    per_robot = {rid: fr.aggregate([fr.robot_scalars(r["robots"][rid]) for r in runs])
                 for rid in robot_ids(exp.robots)}
    ratio = fr.ate_ratio(agg, base_agg) if base_agg else None
    setup = (f"{exp.robots} robots × {exp.edges} edges, {exp.max_scans} scans per robot of {exp.scans}, "
             f"{exp.repeat} run(s); events: {exp.events or 'none'}; link traces: "
             f"{', '.join(f'{r}={t}' for r, t in traces.items()) or 'none'}; "
             f"{'one router' if exp.routers == 1 else 'two routers (robots, edges)'}; "
             f"Zenoh lease {exp.lease_ms} ms; edge CPU quota: "
             f"{', '.join(f'{e}={c:g} cores' for e, c in quotas.items()) or 'none'}. "
             "Robot process CPU includes its simulated sensor; the robot's ms/scan excludes it.")
    text = fr.markdown("Fleet experiment", setup, agg, base_agg, per_robot, ratio, kills(events))
    (out / "report.md").write_text(text)
    summary = {"experiment": _jsonable(exp), "aggregate": agg, "baseline": base_agg, "ate_ratio": ratio,
               "per_robot": per_robot, "runs": [r["summary"] for r in runs],
               "baseline_runs": [r["summary"] for r in base] if base else None}
    (out / "results.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def summary_line(s: dict[str, Any]) -> str:
    def f(x: Any, spec: str) -> str:
        return "-" if x is None else format(x, spec)

    return (f"  {s['robots']} robots: produced {s['produced']}, acked {s['acked']}, local {s['local']}, "
            f"lost {s['lost']}, balanced {s['balanced_all']}, ATE {f(s['ate_rmse_mean'], '.3f')} m, "
            f"max pose gap {f(s['max_pose_gap_scans'], '.0f')} scans, failovers {s['failovers']} "
            f"(max {f(s['failover_s_max'], '.2f')} s)")
