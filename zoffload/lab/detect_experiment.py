"""``zoffload experiment detect``: camera frames from one robot, detected on the robot or on the
edge frame by frame, measured as the offloading thesis measured them (its Tables 6.3–6.5).

Processes: ``zoffload-edge`` (detector on, mapper off), optionally ``zoffload link`` in front of
it (``--trace none`` = the unconstrained link: direct loopback TCP), and ``zoffload-robot`` with
``scans: none`` and a camera source (default: pan/zoom clips over the COCO person images, 25 FPS,
848x480 raw bgr8 = 244 Mbps). The robot's process runs under a CFS CPU quota (``--cpu-quota``
cores) as the thesis' robot container did, so its light detector is the slower side.

Writes ``results.json`` (one table row), ``frames.csv``, ``detections.npz``, ``monitor.csv``,
``vision_metrics.json``, configs and logs. ``sweep`` runs the thesis' grid of strategies.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from zoffload.lab.eval.detection import detection_metrics
from zoffload.lab.runner import frames_line, run_offload
from zoffload.runtime.config import (
    DetectorSettings,
    EdgeSettings,
    MapperSettings,
    PerceptionSettings,
    RobotSettings,
)
from zoffload.sources.images import CocoClipSource, open_image_source

# The thesis' grid: robot-only, ratios 0.1 … 0.9, edge-only, its dynamic rule, and ours (with raw
# frames as everyone else, and with JPEG frames: going further than the thesis)
SWEEP_STRATEGIES = ["robot", *[f"ratio:{r / 10:g}" for r in range(1, 10)], "edge", "thesis", "dynamic",
                    "dynamic@jpeg"]
# Its three links: unconstrained, capped at about 65 % of the raw stream, fluctuating Wi-Fi
SWEEP_TRACES = ["none", "detect-capped", "wifi-locations"]


@dataclass(frozen=True)
class DetectExperiment:
    trace: str  # a trace name or CSV, or "none" for direct loopback
    strategy: str
    out: str
    images: str = "coco-clips"
    max_frames: int = 750  # 30 s at 25 FPS: 15 clips
    cpu_quota: float | None = 0.25
    encoding: str = "bgr8"
    edge_model: str = "picodet-s"
    local_model: str = "nanodet-m"
    seed: int = 0
    extra: dict[str, Any] = field(default_factory=dict)  # further perception settings


def run_detect_experiment(exp: DetectExperiment) -> dict[str, Any]:
    out = Path(exp.out)
    out.mkdir(parents=True, exist_ok=True)
    source = open_image_source(exp.images)  # fails early, with a clear message, if it is missing
    (out / "experiment.json").write_text(json.dumps(asdict(exp), indent=2))
    trace = None if exp.trace == "none" else exp.trace
    print(f"experiment detect: strategy {exp.strategy}, link {exp.trace}, {exp.max_frames} frames of "
          f"{source.name}, robot CPU quota {exp.cpu_quota} -> {out}", flush=True)
    edge = EdgeSettings(mapper=MapperSettings(enabled=False),
                        detector=DetectorSettings(enabled=True, model=exp.edge_model))  # type: ignore[arg-type]
    perception = PerceptionSettings(strategy=exp.strategy, max_frames=exp.max_frames, cpu_quota=exp.cpu_quota,
                                    encoding=exp.encoding, local_model=exp.local_model,  # type: ignore[arg-type]
                                    **exp.extra)
    robot = RobotSettings(scans="none", images=exp.images, out_dir=str(out), wait_edge=30,
                          perception=perception)
    fps = perception.fps or source.rate_hz
    run = run_offload(out, edge, robot, trace, ["--seed", str(exp.seed), "--quiet"], exp.max_frames,
                      exp.max_frames / fps + 120, keep_interrupted=True, line=frames_line, fetch=False)
    row = detect_row(exp, out, source)
    row["cut_short"] = run.cut_short
    row["robot_exit_code"] = run.robot_code
    (out / "results.json").write_text(json.dumps(row, indent=2))
    return row


def detect_row(exp: DetectExperiment, out: Path, source: Any) -> dict[str, Any]:
    metrics_path = out / "vision_metrics.json"
    if not metrics_path.exists():
        return {"kind": "detect", "strategy": exp.strategy, "trace": exp.trace, "error": "no robot results"}
    m = json.loads(metrics_path.read_text())
    label = exp.strategy if exp.encoding == "bgr8" else f"{exp.strategy}@{exp.encoding}"
    row: dict[str, Any] = {"kind": "detect", "strategy": label, "trace": exp.trace,
                           "encoding": exp.encoding, "cpu_quota": exp.cpu_quota}
    if isinstance(source, CocoClipSource):
        row.update(detection_metrics(out, source.boxes, m["balance"]["frames_in"]))
    for k in ("processed_pct", "offloaded_pct", "robot_rtt_ms", "edge_rtt_ms", "local_infer_ms",
              "edge_infer_ms", "cpu_process_pct", "cpu_system_pct", "power_w", "power_available",
              "mbps_out", "balance", "balanced", "fallbacks"):
        row[k] = m.get(k)
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


def run_sweep(out: Path, traces: list[str], strategies: list[str], **kw: Any) -> list[dict[str, Any]]:
    """Every strategy on every trace; ``S@jpeg`` runs strategy S with JPEG frames."""
    rows = []
    for trace in traces:
        for spec in strategies:
            strategy, _, encoding = spec.partition("@")
            name = spec.replace(":", "_").replace("@", "_")
            args = dict(kw, encoding=encoding or kw.get("encoding", "bgr8"))
            exp = DetectExperiment(trace=trace, strategy=strategy, out=str(out / Path(trace).stem / name),
                                   **args)
            row = run_detect_experiment(exp)
            print(summary_line(row), flush=True)
            rows.append(row)
    return rows
