"""The lab's commands: ``zoffload demo``, ``experiment scan|detect|detect-sweep|fleet``, ``report``,
``train-policy`` and ``link`` (the emulator). Each runs product code from ``zoffload.lab``.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from zoffload.runtime.errors import ConfigError, ExitCode
from zoffload.runtime.lifecycle import StopSignal


def _run_demo(a: argparse.Namespace) -> int:
    from zoffload.cli.view import view_options
    from zoffload.lab.demo import DemoOptions, run

    return run(DemoOptions(duration=a.duration, scans=a.scans, out=a.out, voxel=a.voxel,
                           scale_policy=a.scale_policy, replay=a.replay, trace=a.trace, camera=a.camera,
                           view=view_options(a, "view-") if a.view else None))


def _run_link(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.lab.link.run import run
    from zoffload.lab.link.trace import TraceError, load_trace

    try:
        trace = load_trace(a.trace, loop=a.loop)
        host, port = a.target.rsplit(":", 1)
        target = (host, int(port))
    except (TraceError, ValueError) as exc:
        raise ConfigError(str(exc)) from exc
    run(trace, a.listen_port, target, StopSignal().install(),
        report=Path(a.report) if a.report else None, seed=a.seed, queue_ms=a.queue_ms, quiet=a.quiet)
    return ExitCode.OK


def _run_experiment(a: argparse.Namespace) -> int:
    from zoffload.lab.link.trace import TraceError
    from zoffload.lab.scan_experiment import ScanExperiment, run_scan_experiment, summary_line

    try:
        row = run_scan_experiment(ScanExperiment(
            trace=a.trace, policy=a.policy, scans=a.scans, out=a.out, max_scans=a.max_scans,
            replay=a.replay, rate_hz=a.rate, seed=a.seed, coding=a.coding,
            voxel_range=tuple(a.voxel_range) if a.voxel_range else None, repeat=a.repeat,
            attach=a.attach, edge_apart=a.edge_apart))
    except TraceError as exc:
        raise ConfigError(str(exc)) from exc
    print(summary_line(row))
    return ExitCode.OK


def _run_fleet(a: argparse.Namespace) -> int:
    from zoffload.lab.fleet_experiment import FleetExperiment, run_fleet_experiment
    from zoffload.lab.fleet_report import ROWS
    from zoffload.lab.fleet_scenario import ScenarioError

    try:
        result = run_fleet_experiment(FleetExperiment(
            out=a.out, robots=a.robots, edges=a.edges, events=a.events or "", traces=tuple(a.trace or ()),
            scans=a.scans, max_scans=a.max_scans, rate_hz=a.rate, repeat=a.repeat, baseline=a.baseline,
            seed=a.seed, lease_ms=a.lease_ms, routers=a.routers, edge_workers=a.edge_workers,
            edge_flags=a.edge_flags, robot_flags=a.robot_flags, edge_cpu=a.edge_cpu or ""))
    except ScenarioError as exc:
        raise ConfigError(str(exc)) from exc
    labels = {key: label for label, key, _ in ROWS}
    for key in ("acked", "local", "lost", "ate_rmse_mean", "max_pose_gap_scans", "failover_s_max"):
        fig = result["aggregate"].get(key)
        if fig:
            print(f"{labels[key]}: {fig['mean']:.3f}" + (f" ± {fig['sd']:.3f}" if fig.get("sd") else ""))
    if result["ate_ratio"] is not None:
        print(f"ATE ratio scripted / baseline: {result['ate_ratio']:.2f}x")
    print(f"report written to {a.out}/report.md")
    return ExitCode.OK


def _detect_arguments(p: argparse.ArgumentParser, sweep: bool = False) -> None:
    p.add_argument("--images", default="coco-clips@holdout" if sweep else "coco-clips",
                   help="camera source: coco-clips[:FOLDER][@tune|@holdout] (has ground truth; @tune: the "
                   "half of the images strategies are tuned on, @holdout: the other half, the sweep's "
                   "default), a folder or a video")
    p.add_argument("--max-frames", type=int, default=None if sweep else 750,
                   help="camera frames per run (default: " + ("every frame of the source, 1250 for a half "
                   "of coco-clips" if sweep else "750 = 30 s") + ")")
    if sweep:
        p.add_argument("--cpu-quotas", type=float, nargs="+", default=[0.25, 1.0],
                       help="robot cores, one sweep per value (CFS quota; default 0.25 1.0; 0 = no quota)")
    else:
        p.add_argument("--cpu-quota", type=float, default=0.25,
                       help="cores the robot process may use (CFS quota; default 0.25; 0 = no quota)")
    p.add_argument("--repeat", type=int, default=3 if sweep else 1,
                   help="runs of each experiment, into OUT/.../run1 ... runN; runs already complete are "
                   f"kept, so the same command resumes (default {3 if sweep else 1})")
    p.add_argument("--encoding", choices=["bgr8", "jpeg", "auto"], default="bgr8",
                   help="frame encoding (default bgr8; auto: chosen per frame by the link)")
    p.add_argument("--send-size", choices=["camera", "detector"], default="camera",
                   help="frames to the edge at the camera's size (default: the thesis' protocol) or shrunk "
                   "to the edge detector's input (detector: the daemon's default; rows S@ENC+shrunk)")
    p.add_argument("--edge-threads", type=int, default=1,
                   help="inference threads of the edge's detector (default 1: robot and edge share this "
                   "machine, and an edge on every core is slowed by whatever the robot runs)")
    p.add_argument("--edge-apart", action=argparse.BooleanOptionalAction, default=True,
                   help="the edge process on a core of its own (the highest), the robot and the link "
                   "emulator on the others, as on separate computers (default; needs 2 cores and "
                   "taskset); --no-edge-apart: all on every core")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--log-level", default="WARNING")


def _detect_kw(a: argparse.Namespace) -> dict[str, Any]:
    return {"images": a.images, "max_frames": a.max_frames, "encoding": a.encoding, "seed": a.seed,
            "edge_threads": a.edge_threads, "send_size": a.send_size, "edge_apart": a.edge_apart}


def _run_detect(a: argparse.Namespace) -> int:
    from zoffload.lab.detect_experiment import DetectExperiment, run_detect_experiment, summary_line
    from zoffload.lab.link.trace import TraceError, load_trace
    from zoffload.policy.offload import make_strategy

    try:
        make_strategy(a.strategy)
        if a.trace != "none":
            load_trace(a.trace)
    except (ValueError, TraceError) as exc:
        raise ConfigError(str(exc)) from exc
    row = run_detect_experiment(DetectExperiment(trace=a.trace, strategy=a.strategy, out=a.out,
                                                 cpu_quota=a.cpu_quota or None, repeat=a.repeat,
                                                 **_detect_kw(a)))
    print(summary_line(row))
    return ExitCode.OK


def _run_detect_sweep(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.lab.detect_experiment import SWEEP_STRATEGIES, SWEEP_TRACES, run_sweep

    rows = run_sweep(Path(a.out), a.traces or SWEEP_TRACES, a.strategies or SWEEP_STRATEGIES,
                     [q or None for q in a.cpu_quotas], a.repeat, **_detect_kw(a))
    print(f"sweep written to {a.out}; render it with: zoffload report {a.out}/*/*/*/run*")
    failed = [r["out"] for r in rows if r.get("start_failed")]
    if failed:
        print(f"{len(failed)} run(s) not done (the edge did not start); run the same command again: "
              + ", ".join(failed))
        return ExitCode.FAILURE
    return ExitCode.OK


def _run_report(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.lab.eval.detect_report import is_detect_run, write_detect_report
    from zoffload.lab.eval.report import expand_runs, write_report

    folders = expand_runs([Path(d) for d in a.runs])  # a folder of run1 ... runN: its runs
    missing = [str(f) for f in folders if not (f / "results.json").is_file()]
    if missing:
        raise ConfigError(f"not experiment folders (no results.json): {', '.join(missing)}")
    detect = [is_detect_run(f) for f in folders]
    if any(detect) and not all(detect):
        raise ConfigError("mixed scan and detect runs: report them separately")
    out = Path(a.out) if a.out else None
    path = write_detect_report(folders, out) if all(detect) else write_report(folders, out)
    print(path.read_text())
    print(f"report written to {path}")
    return ExitCode.OK


def _run_train(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.lab.train_policy import run_training
    from zoffload.policy.dqn import DQNConfig

    lo, hi = a.voxel_range
    if not 0 < lo < hi:
        raise ConfigError(f"--voxel-range {lo} {hi}: need 0 < low < high")
    metrics = run_training([Path(d) for d in a.data], Path(a.out),
                           DQNConfig(episodes=a.episodes, seed=a.seed), (lo, hi))
    print(json.dumps(metrics["evaluation"], indent=2))
    print(f"model, curves and metrics in {a.out}")
    return ExitCode.OK


def add_demo(sub: Any) -> None:
    d = sub.add_parser("demo", help="robot + edge on localhost with the simulator, ~30 s")
    d.add_argument("--duration", type=float, default=30.0, help="seconds of sensor data (default 30)")
    d.add_argument("--scans", default="sim", help="'sim' (default) or a folder of real scans")
    d.add_argument("--replay", choices=["once", "loop", "pingpong"], default=None,
                   help="replay mode (default: once for sim, pingpong for a folder)")
    d.add_argument("--voxel", type=float, default=0.05,
                   help="robot voxel size in m: the start of the rate policy (the default), the "
                   "fixed policy's grid (default 0.05)")
    d.add_argument("--scale-policy", default="rate",
                   help="voxel sizing: rate (default: sized for the link), fixed (every scan at --voxel), "
                   "dqn, dqn:PATH")
    d.add_argument("--out", default=None, help="results folder (default results/demo-<time>)")
    d.add_argument("--trace", default="demo",
                   help="link emulator trace between robot and edge (default: demo, good -> bad -> good)")
    d.add_argument("--no-link", dest="trace", action="store_const", const=None,
                   help="no link emulator: robot and edge over direct loopback TCP")
    d.add_argument("--camera", nargs="?", const="coco-clips", default=None, metavar="SOURCE",
                   help="also stream camera frames (default source: coco-clips, needs the models) to the "
                   "edge detector, detected on the robot or the edge frame by frame")
    d.add_argument("--log-level", default=None)
    from zoffload.cli.view import add_view_flags

    add_view_flags(d, "view-")
    d.set_defaults(func=_run_demo)


def add_experiment(sub: Any) -> None:
    ex = sub.add_parser("experiment", help="reproduce the source studies' tables with real processes")
    exs = ex.add_subparsers(dest="kind", required=True)
    es = exs.add_parser("scan", help="robot -> link emulator -> edge, Table I of the scale paper")
    es.add_argument("--trace", required=True, help="shipped trace name or CSV file")
    es.add_argument("--policy", required=True,
                    help="local, raw, fixed:V (e.g. fixed:0.05), dqn (the packaged model), dqn:PATH or rate "
                    "(ours: sized for the link from the acks)")
    es.add_argument("--scans", default="sim", help="'sim' or a folder of real scans")
    es.add_argument("--out", required=True, help="results folder of this run")
    es.add_argument("--max-scans", type=int, help="default: the trace's length at the sensor rate + 10 s")
    es.add_argument("--replay", choices=["once", "loop", "pingpong"])
    es.add_argument("--rate", type=float, help="sensor rate in Hz (default: the source's)")
    es.add_argument("--seed", type=int, default=0)
    es.add_argument("--coding", choices=["f32", "q16z", "q16d"], default="f32",
                    help="scan payload: float32 (default), q16z or q16d (quantised; the robot uses q16d)")
    es.add_argument("--repeat", type=int, default=1,
                    help="runs of the experiment, into OUT/run1 ... OUT/runN (report them with OUT/run*)")
    es.add_argument("--voxel-range", type=float, nargs=2, default=None, metavar=("LOW", "HIGH"),
                    help="the scale policies' voxel range (default 0.01 0.07, a VLP-16 indoors)")
    es.add_argument("--attach", action="store_true",
                    help="the robot's fleet defaults: the attach protocol, local odometry while the link "
                         "is out, its poses handed to the edge on return (default: the paper's set-up, "
                         "every scan offered to the one edge)")
    es.add_argument("--edge-apart", action="store_true",
                    help="the edge on a core of its own, robot and link emulator on the others "
                         "(taskset), as on separate computers (default: all on every core)")
    es.add_argument("--log-level", default="WARNING")
    es.set_defaults(func=_run_experiment)
    ed = exs.add_parser("detect", help="camera frames robot/edge, the offloading thesis' Tables 6.3-6.5")
    ed.add_argument("--trace", required=True,
                    help="'none' (unconstrained loopback), a shipped trace (detect-capped, "
                    "wifi-locations) or a CSV file")
    ed.add_argument("--strategy", required=True,
                    help="robot, edge, ratio:R, thesis, dynamic or dispatch (ours)")
    ed.add_argument("--out", required=True, help="results folder of this run")
    _detect_arguments(ed)
    ed.set_defaults(func=_run_detect)
    sw = exs.add_parser("detect-sweep", help="the thesis' grid: strategies x links x CPU quotas x repeats")
    sw.add_argument("--out", required=True, help="sweep folder (one sub-folder per link and strategy)")
    sw.add_argument("--traces", nargs="+", default=None,
                    help="default: none detect-capped wifi-locations mmwave-blockage "
                         "(held out until 2026-12-07)")
    sw.add_argument("--strategies", nargs="+", default=None,
                    help="default: robot, ratio:0.1 ... ratio:0.9, edge, thesis, dynamic, dispatch "
                    "(S@jpeg: strategy S with JPEG frames; S@auto: encoding chosen per frame)")
    _detect_arguments(sw, sweep=True)
    sw.set_defaults(func=_run_detect_sweep)
    fl = exs.add_parser("fleet",
                        help="N robots x M edges around a router, scripted edge kills/drains/restarts")
    fl.add_argument("--out", required=True, help="results folder (run1 ... runN, baseline/, report.md)")
    fl.add_argument("--robots", type=int, default=3, help="robot processes robot1 ... (default 3)")
    fl.add_argument("--edges", type=int, default=2, help="edge processes edge1 ... (default 2)")
    fl.add_argument("--events", default="",
                    help="edge events, ACTION:EDGE@SECONDS after every robot is up, comma-separated; kill = "
                    "SIGKILL, drain = SIGTERM, restart = start again with the same id (e.g. "
                    "kill:edge1@5,restart:edge1@8,drain:edge2@12)")
    fl.add_argument("--trace", action="append", metavar="[ROBOT=]TRACE",
                    help="link emulator between a robot and the router: TRACE for every robot or ROBOT=TRACE "
                    "for one (repeatable; shipped name or CSV; default: direct loopback)")
    fl.add_argument("--scans", default="sim",
                    help="'sim' (default: a scene seed per robot, ground truth) or a folder of scans (e.g. "
                    "KITTI-360; reference: KISS-ICP on every raw scan)")
    fl.add_argument("--max-scans", type=int, default=300,
                    help="scans per robot (default 300 = 30 s at 10 Hz)")
    fl.add_argument("--rate", type=float, help="sensor rate in Hz (default: the source's)")
    fl.add_argument("--repeat", type=int, default=1,
                    help="runs, into OUT/run1 ... runN; complete runs are kept, so the command resumes")
    fl.add_argument("--baseline", action="store_true",
                    help="also the same runs without events (OUT/baseline), for the ATE ratio")
    fl.add_argument("--seed", type=int, default=0, help="first run's seed (scene seeds, link jitter)")
    fl.add_argument("--lease-ms", type=int, default=1000,
                    help="Zenoh lease every process announces (default 1000: a silent edge is gone "
                    "within 1 s)")
    fl.add_argument("--routers", type=int, choices=(1, 2), default=1,
                    help="1 (default): every process on one router; 2: the edges on a router of their own, "
                    "linked to the robots' (every robot-edge message crosses both)")
    fl.add_argument("--edge-workers", type=int, default=None,
                    help="mapper threads per edge (default: one per core)")
    fl.add_argument("--edge-cpu", default="", metavar="[EDGE=]CORES,...",
                    help="run edges under a CFS CPU quota (root, cgroups), as a container's cpus "
                    "would: CORES for every edge or EDGE=CORES for one (e.g. edge1=0.5,edge2=0.9); over "
                    "capacity on a machine the robots share")
    fl.add_argument("--edge-flags", default="",
                    help="extra flags for every edge, e.g. '--fleet.checkpoint-every 5'")
    fl.add_argument("--robot-flags", default="",
                    help="extra flags for every robot, e.g. '--fleet.no-attach'")
    fl.add_argument("--log-level", default="WARNING")
    fl.set_defaults(func=_run_fleet)


def add_report(sub: Any) -> None:
    rp = sub.add_parser("report", help="tables and plots from experiment folders")
    rp.add_argument("runs", nargs="+", help="experiment run folders")
    rp.add_argument("--out", help="report folder (default: the common parent of the runs)")
    rp.add_argument("--log-level", default=None)
    rp.set_defaults(func=_run_report)


def add_train_policy(sub: Any) -> None:
    tp = sub.add_parser("train-policy", help="train the DQN scale policy from recorded runs (torch)")
    tp.add_argument("--data", nargs="+", required=True, help="experiment run folders (their scans.csv)")
    tp.add_argument("--out", required=True, help="where the ONNX model, curves and metrics go")
    tp.add_argument("--episodes", type=int, default=300_000, help="one scan = one episode (default 300000)")
    tp.add_argument("--voxel-range", type=float, nargs=2, default=(0.01, 0.07), metavar=("LOW", "HIGH"))
    tp.add_argument("--seed", type=int, default=0)
    tp.add_argument("--log-level", default=None)
    tp.set_defaults(func=_run_train)


def add_link(sub: Any) -> None:
    lk = sub.add_parser("link", help="the link emulator: a shaping TCP proxy driven by a trace")
    lk.add_argument("--trace", required=True,
                    help="a shipped trace (ethernet, capped, wifi-locations, outage) or a CSV file")
    lk.add_argument("--listen-port", type=int, required=True, help="port to listen on (127.0.0.1)")
    lk.add_argument("--target", required=True, metavar="HOST:PORT", help="where to forward to")
    lk.add_argument("--loop", action="store_true", help="repeat the trace")
    lk.add_argument("--report", help="write delivered Mbps per second to this CSV at exit")
    lk.add_argument("--seed", type=int, default=0, help="jitter random seed")
    lk.add_argument("--queue-ms", type=float, default=100.0,
                    help="emulated queue before backpressure, in ms of transmission (default 100)")
    lk.add_argument("--quiet", action="store_true", help="no per-second lines")
    lk.add_argument("--log-level", default=None)
    lk.set_defaults(func=_run_link)


