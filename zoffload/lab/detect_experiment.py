"""``zoffload experiment detect``: camera frames from one robot, detected on the robot or on the
edge frame by frame, measured as the offloading thesis measured them (its Tables 6.3–6.5).

Processes: ``zoffload-edge`` (detector on, mapper off), optionally ``zoffload link`` in front of
it (``--trace none`` = the unconstrained link: direct loopback TCP), and ``zoffload-robot`` with
``scans: none`` and a camera source (default: pan/zoom clips over the COCO person images, 25 FPS,
848x480 raw bgr8 = 244 Mbps). The robot's process runs under a CFS CPU quota (``--cpu-quota``
cores) as the thesis' robot container did, so its light detector is the slower side.

Writes ``results.json`` (one table row), ``frames.csv``, ``detections.npz``, ``monitor.csv``,
``vision_metrics.json``, configs and logs. ``run_sweep`` runs the thesis' grid of strategies on
every link and CPU quota, ``repeats`` times, into ``OUT/q<quota>/<link>/<strategy>/run<i>``; a run
whose results are complete is not run again, so an interrupted sweep resumes where it stopped.

The honest protocol: strategies are tuned on ``coco-clips@tune`` and reported on
``coco-clips@holdout`` (sources/images.py ``coco_half``: the images sorted by file name, even
positions tune, odd positions holdout), and on a link not used to tune them until 2026-12-07, when
the overflow rule's tuning pairs used it (``mmwave-blockage``,
lab/detect_link.py).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from zoffload.lab.eval.detect_report import RUN_SETTINGS, run_label, run_settings
from zoffload.lab.eval.detection import detection_metrics
from zoffload.lab.runner import StartError, edge_apart_cores, environment_settings, frames_line, run_offload
from zoffload.runtime.config import (
    DetectorSettings,
    EdgeSettings,
    MapperSettings,
    PerceptionSettings,
    RobotSettings,
)
from zoffload.runtime.errors import ConfigError
from zoffload.sources.images import CocoClipSource, open_image_source

# The thesis' grid: robot-only, ratios 0.1 … 0.9, edge-only, its dynamic rule, our earlier rule and
# our dispatcher, all with raw frames (``S@jpeg`` runs strategy S with JPEG frames, ``S@auto`` with the
# encoding chosen per frame)
SWEEP_STRATEGIES = ["robot", *[f"ratio:{r / 10:g}" for r in range(1, 10)], "edge", "thesis", "dynamic",
                    "dispatch"]
# Its three links (unconstrained, capped at about 65 % of the raw stream, fluctuating Wi-Fi) and one
# that no strategy was tuned on
SWEEP_TRACES = ["none", "detect-capped", "wifi-locations", "mmwave-blockage"]
SWEEP_QUOTAS = [0.25, 1.0]  # robot cores: the thesis' weak robot, and one full core
SWEEP_IMAGES = "coco-clips@holdout"


@dataclass(frozen=True)
class DetectExperiment:
    trace: str  # a trace name or CSV, or "none" for direct loopback
    strategy: str
    out: str
    images: str = "coco-clips"
    max_frames: int | None = 750  # 30 s at 25 FPS: 15 clips; None: every frame of the source
    cpu_quota: float | None = 0.25
    encoding: str = "bgr8"
    # Frames to the edge at the camera's size (the thesis' protocol), or "detector": shrunk to the
    # edge detector's input on the way (the daemon's default; labelled ``S@ENC+shrunk``)
    send_size: str = "camera"
    edge_model: str = RUN_SETTINGS["edge_model"]
    # One inference thread on the edge: robot and edge share this 2-core machine, and an edge on
    # both cores is slowed by whatever the robot runs (measured: 47 -> 71 ms per frame while the
    # robot's detector ran), which a separate edge computer would not be; one thread costs the
    # edge ~10 % (47.8 against 43.4 ms, docs/perception-log.md's detector table)
    edge_threads: int = RUN_SETTINGS["edge_threads"]
    local_model: str = RUN_SETTINGS["local_model"]
    # The edge process on a core of its own, the robot and the link emulator on the others
    # (runner.edge_apart_cores), as on separate computers: the robot's local detections then take
    # nothing from the edge's detector (co-located, the edge ran 57 ms a frame in edge-only runs
    # against 65 in ours, README "Experiments")
    edge_apart: bool = RUN_SETTINGS["edge_apart"]
    seed: int = 0
    repeat: int = 1  # runs of this experiment: run1 ... runN under ``out`` when more than one
    extra: dict[str, Any] = field(default_factory=dict)  # further perception settings


def run_detect_experiment(exp: DetectExperiment) -> dict[str, Any]:
    """One run into ``out``, or with ``repeat`` > 1 each run into ``out/run<i>`` (complete runs are
    kept, not run again); returns the last run's row."""
    if exp.repeat > 1:
        row: dict[str, Any] = {}
        for i in range(1, exp.repeat + 1):
            # each run its own link seed (the emulator's jitter), as the scan experiment's repeats
            row = run_or_reuse(replace(exp, out=str(Path(exp.out) / f"run{i}"), repeat=1,
                                       seed=exp.seed + i - 1))
            if row.get("cut_short"):
                break
        return row
    environment_settings()  # a variable naming no setting fails here, before the run
    cpus = edge_apart_cores() if exp.edge_apart else {}
    if exp.edge_apart and (not cpus or shutil.which("taskset") is None):
        raise ConfigError("the edge on a core of its own (edge_apart) needs two cores to split and "
                          "taskset (util-linux): --no-edge-apart runs robot and edge on every core")
    out = Path(exp.out)
    out.mkdir(parents=True, exist_ok=True)
    source = open_image_source(exp.images)  # fails early, with a clear message, if it is missing
    max_frames = exp.max_frames or len(source)
    (out / "experiment.json").write_text(json.dumps(asdict(exp), indent=2))
    trace = None if exp.trace == "none" else exp.trace
    print(f"experiment detect: strategy {exp.strategy}, link {exp.trace}, {max_frames} frames of "
          f"{source.name}, robot CPU quota {exp.cpu_quota} -> {out}", flush=True)
    edge = EdgeSettings(mapper=MapperSettings(enabled=False),
                        detector=DetectorSettings(enabled=True, model=exp.edge_model,  # type: ignore[arg-type]
                                                  threads=exp.edge_threads))
    perception = PerceptionSettings(strategy=exp.strategy, max_frames=max_frames, cpu_quota=exp.cpu_quota,
                                    encoding=exp.encoding, local_model=exp.local_model,  # type: ignore[arg-type]
                                    send_size=exp.send_size,  # type: ignore[arg-type]
                                    preview_period=0, **exp.extra)
    robot = RobotSettings(scans="none", images=exp.images, out_dir=str(out), wait_edge=30,
                          perception=perception)
    fps = perception.fps or source.rate_hz
    run = run_offload(out, edge, robot, trace, ["--seed", str(exp.seed), "--quiet"], max_frames,
                      max_frames / fps + 120, keep_interrupted=True, line=frames_line, fetch=False, cpus=cpus)
    row = detect_row(exp, out, source)
    row["cpus"] = {name: sorted(c) for name, c in cpus.items()}
    row["cut_short"] = run.cut_short
    row["robot_exit_code"] = run.robot_code
    (out / "results.json").write_text(json.dumps(row, indent=2))
    return row


def _settings(exp: DetectExperiment) -> dict[str, Any]:
    """What the run ran with besides link, strategy and images (detect_report's RUN_SETTINGS), the
    settings ``ZOFFLOAD_ROBOT__*`` / ``ZOFFLOAD_EDGE__*`` variables gave the daemons included."""
    return {"edge_model": exp.edge_model, "edge_threads": exp.edge_threads, "local_model": exp.local_model,
            "extra": dict(exp.extra), "edge_apart": exp.edge_apart, "environment": environment_settings()}


def detect_row(exp: DetectExperiment, out: Path, source: Any) -> dict[str, Any]:
    metrics_path = out / "vision_metrics.json"
    if not metrics_path.exists():
        return {"kind": "detect", "strategy": exp.strategy, "trace": exp.trace, "error": "no robot results"}
    m = json.loads(metrics_path.read_text())
    label = run_label(exp.strategy, exp.encoding, exp.send_size)
    row: dict[str, Any] = {"kind": "detect", "strategy": label, "trace": exp.trace,
                           "encoding": exp.encoding, "send_size": exp.send_size, "cpu_quota": exp.cpu_quota,
                           "images": exp.images, "max_frames": exp.max_frames, "seed": exp.seed,
                           **_settings(exp)}
    if isinstance(source, CocoClipSource):
        row.update(detection_metrics(out, source.boxes, m["balance"]["frames_in"]))
    for k in ("processed_pct", "offloaded_pct", "robot_rtt_ms", "edge_rtt_ms", "local_infer_ms",
              "edge_infer_ms", "cpu_process_pct", "cpu_system_pct", "power_w", "power_available",
              "mbps_out", "balance", "balanced", "fallbacks", "cpu_quota_applied"):
        row[k] = m.get(k)
    bal = m.get("balance") or {}
    if bal.get("frames_in"):
        row["skipped_pct"] = 100.0 * bal.get("skipped", 0) / bal["frames_in"]
    return row


def summary_line(row: dict[str, Any]) -> str:
    def f(x: Any, fmt: str) -> str:
        return "-" if x is None else format(x, fmt)

    return (f"{row['strategy']:>10} on {row['trace']}: AP50 async {f(row.get('ap50_async'), '.1f')} % "
            f"(sync {f(row.get('ap50_sync'), '.1f')}), processed {f(row.get('processed_pct'), '.0f')} %, "
            f"offloaded {f(row.get('offloaded_pct'), '.0f')} %, "
            f"RTT robot {f(row.get('robot_rtt_ms'), '.0f')} "
            f"/ edge {f(row.get('edge_rtt_ms'), '.0f')} ms, CPU {f(row.get('cpu_process_pct'), '.0f')} %, "
            f"{f(row.get('mbps_out'), '.0f')} Mbps")


def complete(out: Path) -> dict[str, Any] | None:
    """The row of a finished run in ``out`` (robot exited cleanly, not cut short), else None."""
    try:
        row: dict[str, Any] = json.loads((out / "results.json").read_text())
    except (OSError, ValueError):
        return None
    ok = row.get("robot_exit_code") == 0 and not row.get("cut_short") and "error" not in row
    return row if ok else None


def run_or_reuse(exp: DetectExperiment) -> dict[str, Any]:
    """The run's row: from its folder when it is already complete with this link seed, models,
    threads and settings, else from running it (a folder of an older sweep, whose repeats all ran
    seed 0, is run again)."""
    done = complete(Path(exp.out))
    same = done is not None and run_settings(done) == run_settings(_settings(exp))
    if done is not None and same and done.get("seed", 0) == exp.seed:
        print(f"done already: {exp.out}", flush=True)
        return done
    if done is not None:
        print(f"{exp.out}: made with link seed {done.get('seed', 0)} and {run_settings(done)}, not "
              f"{exp.seed} and {run_settings(_settings(exp))}: run again", flush=True)
    row = run_detect_experiment(exp)
    print(summary_line(row), flush=True)
    return row


def sweep_runs(out: Path, traces: Sequence[str], strategies: Sequence[str], quotas: Sequence[float | None],
               repeats: int, **kw: Any) -> list[DetectExperiment]:
    """Every run of the grid, repeat-major: the whole grid once, then again (an interrupted sweep
    still holds complete tables of its first repeats)."""
    runs = []
    for i in range(1, repeats + 1):
        for quota in quotas:
            for trace in traces:
                for spec in strategies:
                    strategy, _, encoding = spec.partition("@")
                    name = spec.replace(":", "_").replace("@", "_")
                    if kw.get("send_size") == "detector":
                        name += "_shrunk"
                    folder = out / f"q{quota or 0:g}" / Path(trace).stem / name / f"run{i}"
                    args = dict(kw, encoding=encoding or kw.get("encoding", "bgr8"), cpu_quota=quota,
                                seed=int(kw.get("seed") or 0) + i - 1)  # repeat i: its own link seed
                    runs.append(DetectExperiment(trace=trace, strategy=strategy, out=str(folder), **args))
    return runs


def run_sweep(out: Path, traces: Sequence[str], strategies: Sequence[str],
              quotas: Sequence[float | None] | None = None, repeats: int = 1,
              **kw: Any) -> list[dict[str, Any]]:
    """Every strategy on every trace and CPU quota, ``repeats`` times; complete runs are skipped, and
    an interrupted run (Ctrl-C) ends the sweep (run the same command again to resume). A run whose
    edge never came up is reported (a row with ``error``) and the sweep goes on: hours of runs do
    not end on one."""
    rows = []
    default = kw.pop("cpu_quota", 0.25)
    plan = sweep_runs(out, traces, strategies, quotas or [default], repeats, **kw)
    for k, exp in enumerate(plan, 1):
        print(f"[{k}/{len(plan)}]", end=" ", flush=True)
        try:
            row = run_or_reuse(exp)
        except StartError as exc:
            print(f"run not done, the sweep goes on: {exc}", flush=True)
            rows.append({"kind": "detect", "strategy": exp.strategy, "trace": exp.trace, "out": exp.out,
                         "start_failed": True, "error": f"start failed: {str(exc).splitlines()[0]}"})
            continue
        rows.append(row)
        if row.get("cut_short"):
            print("sweep interrupted: run the same command again to resume", flush=True)
            break
    return rows
