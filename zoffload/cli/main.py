"""Command line: ``zoffload demo | robot | edge | router``, ``zoffload-robot``, ``zoffload-edge``.

``main()`` only parses arguments and calls the ``run(settings)`` functions, which are also the
Python API. Every program takes the Zenoh session flags of the zenoh examples
(``-m -e -l -c --no-multicast-scouting --cfg``) plus ``--no-shm``; program settings come from
``--settings FILE`` (YAML), then ``ZOFFLOAD_ROBOT__*`` / ``ZOFFLOAD_EDGE__*`` variables, then flags.
The daemons' flags are built from the settings models (``zoffload.cli.flags``): every setting is a
flag, ``--key-name`` or ``--section.key-name``, with the help and default its field declares.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from pydantic import BaseModel

from zoffload import __version__
from zoffload.cli.flags import Spelling, add_settings_flags, flag_values, summary
from zoffload.detect.models import ModelError
from zoffload.runtime.config import EdgeSettings, RobotSettings, ZenohSettings, load_settings
from zoffload.runtime.errors import ConfigError, ExitCode, ZenohSessionError
from zoffload.runtime.lifecycle import StopSignal, setup_logging
from zoffload.sources.base import ScanSourceError

log = logging.getLogger("zoffload")


ROBOT_ENV = "ZOFFLOAD_ROBOT__"
EDGE_ENV = "ZOFFLOAD_EDGE__"

# Flags are built from the settings models (zoffload.cli.flags): --key-name, --section.key-name.
# These tables only keep the spellings the flags have always had. The session flags are the zenoh
# examples' (-m -e -l -c --cfg); --no-multicast-scouting and --no-shm are derived from the "on" forms.
SESSION_SPELLINGS: dict[str, Spelling] = {
    "zenoh.mode": Spelling(("-m", "--mode")),
    "zenoh.connect": Spelling(("-e", "--connect"), "ENDPOINT"),
    "zenoh.listen": Spelling(("-l", "--listen"), "ENDPOINT"),
    "zenoh.multicast_scouting": Spelling(("--multicast-scouting",)),
    "zenoh.shared_memory": Spelling(("--shm",)),
    "zenoh.config_file": Spelling(("-c", "--config"), "FILE"),
    "zenoh.cfg": Spelling(("--cfg",), "KEY:VALUE"),
}
ROBOT_SPELLINGS: dict[str, Spelling] = {
    **SESSION_SPELLINGS,
    "rate_hz": Spelling(("--rate",), "HZ"),
    "voxel_range": Spelling(("--voxel-range",), ("LOW", "HIGH")),
    "out_dir": Spelling(("--out",), "DIR"),
}
EDGE_SPELLINGS: dict[str, Spelling] = {
    **SESSION_SPELLINGS,
    "mapper.enabled": Spelling(("--mapping",)),
    "detector.enabled": Spelling(("--detector",)),
}


def add_session_arguments(p: argparse.ArgumentParser) -> None:
    add_settings_flags(p, ZenohSettings, SESSION_SPELLINGS, prefix="zenoh", title="zenoh session")


def session_flags(a: argparse.Namespace) -> dict[str, Any]:
    """The Zenoh session settings given as flags (for ``ZenohSettings``)."""
    return flag_values(a, ZenohSettings, "zenoh")


class _HelpFormatter(argparse.HelpFormatter):
    """A wider flag column: most generated flags then keep their help on the same line."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=34)


def _daemon_parser(p: argparse.ArgumentParser, model: type[BaseModel], spellings: dict[str, Spelling],
                   env_prefix: str, example: str) -> None:
    p.description = p.description or summary(model)
    p.usage = "%(prog)s [--settings FILE] [flags]"  # the generated one would list every flag
    p.formatter_class = _HelpFormatter
    p.epilog = (
        "Each setting is, in rising precedence: its default (shown above), its key in --settings FILE "
        f"(YAML, sections nested), the environment variable {env_prefix}KEY or {env_prefix}SECTION__KEY "
        f"(e.g. {example}; lists in YAML: {env_prefix}ZENOH__CONNECT=[tcp/10.0.0.2:7447]; null unsets), "
        "then its flag. Unknown keys and variables are errors."
    )
    p.add_argument("--settings", metavar="FILE", help="YAML settings file: the flags' keys, sections nested")
    p.add_argument("--log-level", default=None, metavar="LEVEL",
                   help="DEBUG, INFO, WARNING (env ZOFFLOAD_LOG)")
    program = model.__name__.removesuffix("Settings").lower()
    add_settings_flags(p, model, spellings, title=f"{program} settings")


def robot_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="zoffload-robot")
    _daemon_parser(p, RobotSettings, ROBOT_SPELLINGS, ROBOT_ENV, f"{ROBOT_ENV}PERCEPTION__STRATEGY=edge")
    return p


def edge_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="zoffload-edge")
    _daemon_parser(p, EdgeSettings, EDGE_SPELLINGS, EDGE_ENV, f"{EDGE_ENV}MAPPER__QUEUE=4")
    return p


def robot_settings(a: argparse.Namespace, environ: Mapping[str, str] | None = None) -> RobotSettings:
    """Defaults < ``--settings`` file < ``ZOFFLOAD_ROBOT__*`` (``environ``, else os.environ) < flags."""
    return load_settings(RobotSettings, a.settings, flag_values(a, RobotSettings), ROBOT_ENV, environ)


def edge_settings(a: argparse.Namespace, environ: Mapping[str, str] | None = None) -> EdgeSettings:
    """Defaults < ``--settings`` file < ``ZOFFLOAD_EDGE__*`` (``environ``, else os.environ) < flags."""
    return load_settings(EdgeSettings, a.settings, flag_values(a, EdgeSettings), EDGE_ENV, environ)


def _run_robot(a: argparse.Namespace) -> int:
    from zoffload.robot.server import run

    run(robot_settings(a), StopSignal().install())
    return ExitCode.OK


def _run_edge(a: argparse.Namespace) -> int:
    from zoffload.edge.server import run

    run(edge_settings(a), StopSignal().install())
    return ExitCode.OK


def _run_router(a: argparse.Namespace) -> int:
    from zoffload.runtime.router import run

    z = session_flags(a)
    z["mode"] = "router"
    run(load_settings(RobotSettings, None, {"zenoh": z}).zenoh, StopSignal().install())
    return ExitCode.OK


def _run_demo(a: argparse.Namespace) -> int:
    from zoffload.lab.demo import DemoOptions, run

    return run(DemoOptions(duration=a.duration, scans=a.scans, out=a.out, voxel=a.voxel,
                           replay=a.replay, trace=a.trace, camera=a.camera))


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
            voxel_range=tuple(a.voxel_range) if a.voxel_range else None))
    except TraceError as exc:
        raise ConfigError(str(exc)) from exc
    print(summary_line(row))
    return ExitCode.OK


def _detect_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--images", default="coco-clips",
                   help="camera source: coco-clips[:FOLDER] (default, has ground truth), a folder or a video")
    p.add_argument("--max-frames", type=int, default=750, help="camera frames per run (default 750 = 30 s)")
    p.add_argument("--cpu-quota", type=float, default=0.25,
                   help="cores the robot process may use (CFS quota; default 0.25; 0 = no quota)")
    p.add_argument("--encoding", choices=["bgr8", "jpeg"], default="bgr8",
                   help="frame encoding (default bgr8)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--log-level", default="WARNING")


def _detect_kw(a: argparse.Namespace) -> dict[str, Any]:
    return {"images": a.images, "max_frames": a.max_frames, "cpu_quota": a.cpu_quota or None,
            "encoding": a.encoding, "seed": a.seed}


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
                                                 **_detect_kw(a)))
    print(summary_line(row))
    return ExitCode.OK


def _run_detect_sweep(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.lab.detect_experiment import SWEEP_STRATEGIES, SWEEP_TRACES, run_sweep

    run_sweep(Path(a.out), a.traces or SWEEP_TRACES, a.strategies or SWEEP_STRATEGIES, **_detect_kw(a))
    print(f"sweep written to {a.out}; render it with: zoffload report {a.out}/*/*")
    return ExitCode.OK


def _run_report(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.lab.eval.detect_report import is_detect_run, write_detect_report
    from zoffload.lab.eval.report import write_report

    folders = [Path(d) for d in a.runs]
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


def _guard(fn: Callable[[argparse.Namespace], int], a: argparse.Namespace) -> int:
    """Run a command, turning the errors a user can cause into a message and a named exit code."""
    setup_logging(getattr(a, "log_level", None))
    try:
        return int(fn(a))
    except ConfigError as exc:
        log.error("configuration error: %s", exc)
        return ExitCode.CONFIG
    except ScanSourceError as exc:
        log.error("data error: %s", exc)
        return ExitCode.DATA
    except ModelError as exc:
        log.error("model error: %s", exc)
        return ExitCode.DATA
    except ZenohSessionError as exc:
        log.error("%s", exc)
        return ExitCode.ZENOH
    except KeyboardInterrupt:
        return ExitCode.INTERRUPTED
    except Exception:
        log.exception("unexpected error")
        return ExitCode.FAILURE


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="zoffload",
        description="Offload a robot's LiDAR mapping to an edge computer over Zenoh, and keep working "
        "when the link degrades. Start with: zoffload demo",
    )
    p.add_argument("--version", action="version", version=f"zoffload {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="robot + edge on localhost with the simulator, ~30 s")
    d.add_argument("--duration", type=float, default=30.0, help="seconds of sensor data (default 30)")
    d.add_argument("--scans", default="sim", help="'sim' (default) or a folder of real scans")
    d.add_argument("--replay", choices=["once", "loop", "pingpong"], default=None,
                   help="replay mode (default: once for sim, pingpong for a folder)")
    d.add_argument("--voxel", type=float, default=0.05, help="robot voxel size in m (default 0.05)")
    d.add_argument("--out", default=None, help="results folder (default results/demo-<time>)")
    d.add_argument("--trace", default="demo",
                   help="link emulator trace between robot and edge (default: demo, good -> bad -> good)")
    d.add_argument("--no-link", dest="trace", action="store_const", const=None,
                   help="no link emulator: robot and edge over direct loopback TCP")
    d.add_argument("--camera", nargs="?", const="coco-clips", default=None, metavar="SOURCE",
                   help="also stream camera frames (default source: coco-clips, needs the models) to the "
                   "edge detector, detected on the robot or the edge frame by frame")
    d.add_argument("--log-level", default=None)
    d.set_defaults(func=_run_demo)
    r = sub.add_parser("robot", help="the robot daemon (same as zoffload-robot)")
    robot_parser(r).set_defaults(func=_run_robot)
    e = sub.add_parser("edge", help="the edge daemon (same as zoffload-edge)")
    edge_parser(e).set_defaults(func=_run_edge)
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
    es.add_argument("--coding", choices=["f32", "q16z"], default="f32",
                    help="scan payload: float32 (default) or q16z (quantised, zstd-compressed)")
    es.add_argument("--voxel-range", type=float, nargs=2, default=None, metavar=("LOW", "HIGH"),
                    help="the scale policies' voxel range (default 0.01 0.07, a VLP-16 indoors)")
    es.add_argument("--log-level", default="WARNING")
    es.set_defaults(func=_run_experiment)
    ed = exs.add_parser("detect", help="camera frames robot/edge, the offloading thesis' Tables 6.3-6.5")
    ed.add_argument("--trace", required=True,
                    help="'none' (unconstrained loopback), a shipped trace (detect-capped, "
                    "wifi-locations) or a CSV file")
    ed.add_argument("--strategy", required=True, help="robot, edge, ratio:R, thesis or dynamic")
    ed.add_argument("--out", required=True, help="results folder of this run")
    _detect_arguments(ed)
    ed.set_defaults(func=_run_detect)
    sw = exs.add_parser("detect-sweep", help="the thesis' grid: strategies x links, one folder each")
    sw.add_argument("--out", required=True, help="sweep folder (one sub-folder per link and strategy)")
    sw.add_argument("--traces", nargs="+", default=None, help="default: none detect-capped wifi-locations")
    sw.add_argument("--strategies", nargs="+", default=None,
                    help="default: robot, ratio:0.1 ... ratio:0.9, edge, thesis, dynamic, dynamic@jpeg "
                    "(S@jpeg: strategy S with JPEG frames)")
    _detect_arguments(sw)
    sw.set_defaults(func=_run_detect_sweep)
    rp = sub.add_parser("report", help="tables and plots from experiment folders")
    rp.add_argument("runs", nargs="+", help="experiment run folders")
    rp.add_argument("--out", help="report folder (default: the common parent of the runs)")
    rp.add_argument("--log-level", default=None)
    rp.set_defaults(func=_run_report)
    tp = sub.add_parser("train-policy", help="train the DQN scale policy from recorded runs (torch)")
    tp.add_argument("--data", nargs="+", required=True, help="experiment run folders (their scans.csv)")
    tp.add_argument("--out", required=True, help="where the ONNX model, curves and metrics go")
    tp.add_argument("--episodes", type=int, default=300_000, help="one scan = one episode (default 300000)")
    tp.add_argument("--voxel-range", type=float, nargs=2, default=(0.01, 0.07), metavar=("LOW", "HIGH"))
    tp.add_argument("--seed", type=int, default=0)
    tp.add_argument("--log-level", default=None)
    tp.set_defaults(func=_run_train)
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
    rt = sub.add_parser("router", help="a Zenoh router (zenoh-python in router mode)")
    add_session_arguments(rt)
    rt.add_argument("--log-level", default=None)
    rt.set_defaults(func=_run_router)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return _guard(args.func, args)


def robot_main(argv: Sequence[str] | None = None) -> int:
    args = robot_parser().parse_args(argv)
    return _guard(_run_robot, args)


def edge_main(argv: Sequence[str] | None = None) -> int:
    args = edge_parser().parse_args(argv)
    return _guard(_run_edge, args)


if __name__ == "__main__":
    sys.exit(main())
