"""``zoffload experiment scan``: one robot -> link emulator -> edge run with real processes,
measured as the scale-optimisation paper's Table I.

Processes: ``zoffload-edge`` (peer, listening), ``zoffload link`` (the emulator, in front of the
edge), ``zoffload-robot`` (client mode, so every byte goes through the emulator: a peer could
learn the edge's own address and connect around it). Shared memory is off everywhere, the robot's
TCP send buffer is kept small so a slow link reaches Zenoh's congestion control (BLOCK_FIRST for
scans) instead of hiding in the kernel. The harness's own session talks to the edge directly
(measurement only).

Every run writes, even when cut short: ``results.json`` (the Table I row), ``scans.csv`` (per-scan
decisions and measurements, with the link rate at that moment), ``link.csv`` (what the emulator
let through per second), the configs and the logs.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.lab.eval.trajectory import trajectory_error
from zoffload.lab.link.trace import Trace, load_trace
from zoffload.lab.runner import link_clock_start, run_offload
from zoffload.robot.ledger import RECORD_FIELDS
from zoffload.runtime.config import EdgeSettings, RobotSettings
from zoffload.runtime.errors import ConfigError
from zoffload.sources import open_scan_source
from zoffload.sources.base import Replay, ScanSource


@dataclass(frozen=True)
class ScanExperiment:
    trace: str
    policy: str  # "local", "raw" or "fixed:V"
    scans: str = "sim"
    out: str = "results/experiment"
    max_scans: int | None = None  # default: the trace's length at the sensor rate (+10 s)
    replay: Replay | None = None  # default: once for sim, pingpong for a folder
    rate_hz: float | None = None
    seed: int = 0
    coding: str = "f32"  # scan payload coding: "f32" or "q16z"
    voxel_range: tuple[float, float] | None = None  # the policies' range (default the robot's)


def policy_voxel(policy: str) -> float | None:
    """Voxel size of a fixed policy (the fallback size for ``dqn``); None for ``local``.
    ``ConfigError`` for an unknown policy."""
    if policy == "local":
        return None
    if policy == "dqn" or policy.startswith("dqn:") or policy == "rate":
        return 0.05
    if policy == "raw":
        return 0.0
    if policy.startswith("fixed:"):
        try:
            v = float(policy.split(":", 1)[1])
        except ValueError as exc:
            raise ConfigError(f"policy {policy!r}: fixed:V needs a number") from exc
        if v <= 0:
            raise ConfigError(f"policy {policy!r}: the voxel size must be positive")
        return v
    raise ConfigError(f"unknown policy {policy!r} (local, raw, fixed:V, dqn, dqn:PATH, rate)")


def _reference(source: ScanSource, indices: list[int], is_sim: bool, gt: dict[int, np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray, str]:
    """Reference trajectory per seq: ground truth, or KISS-ICP locally on every raw scan."""
    if is_sim:
        seqs = np.array(sorted(gt), np.int64)
        return seqs, np.array([gt[s] for s in seqs]).reshape(-1, 4, 4), "simulator ground truth"
    from zoffload.mapping.cloud import drop_non_finite
    from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size

    mapper = RobotMapper(voxel_size=mapper_voxel_size(source.max_range, 0.0), max_range=source.max_range)
    for seq, index in enumerate(indices):
        mapper.register(seq, drop_non_finite(source.read(index).points)[0])
    seqs, poses = mapper.trajectory()
    return seqs, poses, "KISS-ICP run locally on every raw scan (no ground truth for real data)"


def _table_row(exp: ScanExperiment, recs: list[dict[str, Any]], map_points: int, err: Any,
               reference: str, balance: dict[str, int] | None) -> dict[str, Any]:
    sent = [r for r in recs if r.get("bytes") not in (None, "")]
    received = [r for r in recs if r.get("status") in ("acked", "edge_dropped", "edge_error", "late")]
    t = np.array([float(r["interarrival"]) for r in received if r.get("interarrival") not in (None, "")
                  and np.isfinite(float(r["interarrival"]))])
    return {
        "policy": exp.policy if exp.coding == "f32" else f"{exp.policy}+{exp.coding}",
        "trace": exp.trace, "scans": exp.scans,
        "S_kB": float(np.mean([float(r["bytes"]) for r in sent]) / 1e3) if sent and exp.policy != "local"
        else None,
        "points_before": float(np.mean([float(r["n_raw"]) for r in recs])) if recs else None,
        "points_after": _mean([r.get("n_sent") for r in recs]),
        "scans_produced": (balance or {}).get("produced", len(recs)),
        "scans_sent": len(sent) if exp.policy != "local" else len(recs),
        "scans_received": len(received) if exp.policy != "local" else len(recs),
        "T_mean": float(t.mean()) if len(t) else None,
        "T_le_0.11": float((t <= 0.11).mean()) if len(t) else None,
        "map_points": map_points,
        "trajectory_error": err.as_dict() if err else None,
        "trajectory_reference": reference,
        "balance": balance,
    }


def _mean(values: list[Any]) -> float | None:
    nums = [float(v) for v in values if v not in (None, "")]
    return float(np.mean(nums)) if nums else None


def _with_link_rate(recs: list[dict[str, Any]], trace: Trace | None, wall_start: float | None) -> None:
    for r in recs:
        if trace is None or wall_start is None or r.get("capture_stamp") in (None, ""):
            r["link_up_mbps"] = ""
            continue
        st = trace.at(float(r["capture_stamp"]) - wall_start)
        r["link_up_mbps"] = 0.0 if st.outage else st.up_mbps


def _write_scans(path: Path, recs: list[dict[str, Any]]) -> None:
    fields = [*RECORD_FIELDS, "link_up_mbps"]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(recs)


def run_scan_experiment(exp: ScanExperiment) -> dict[str, Any]:
    out = Path(exp.out)
    out.mkdir(parents=True, exist_ok=True)
    voxel = policy_voxel(exp.policy)
    trace = load_trace(exp.trace)
    is_sim = exp.scans == "sim"
    source = open_scan_source(exp.scans, sim_seed=exp.seed)
    rate = exp.rate_hz or source.rate_hz
    replay: Replay = exp.replay or ("once" if is_sim else "pingpong")
    max_scans = exp.max_scans or int((trace.duration + 10) * rate)
    (out / "experiment.json").write_text(json.dumps(asdict(exp) | {"max_scans": max_scans,
                                                                    "replay": replay}, indent=2))
    print(f"experiment scan: policy {exp.policy}, trace {trace.name}, {max_scans} scans of "
          f"{source.name} at {rate:g} Hz -> {out}", flush=True)
    if voxel is None:
        row = _run_local(exp, source, rate, replay, max_scans, is_sim, out)
    else:
        row = _run_offload(exp, trace, voxel, rate, replay, max_scans, is_sim, source, out)
    (out / "results.json").write_text(json.dumps(row, indent=2))
    return row


def _run_local(exp: ScanExperiment, source: ScanSource, rate: float, replay: Replay, max_scans: int,
               is_sim: bool, out: Path) -> dict[str, Any]:
    from zoffload.robot.local import run_local

    run = run_local(source, rate, replay, max_scans)
    assert run.mapper is not None
    _with_link_rate(run.records, None, None)
    _write_scans(out / "scans.csv", run.records)
    seqs, poses = run.mapper.trajectory()
    np.savez(out / "trajectory.npz", seqs=seqs, poses=poses)
    np.save(out / "map_sample.npy", _sample(run.mapper.map_cloud()))
    indices = [int(r["index"]) for r in run.records]
    ref_seqs, ref_poses, reference = _reference(source, indices, is_sim, run.gt)
    if not is_sim:  # the local run registered raw scans: it is the reference, matched by seq
        ref_seqs = np.array([r["seq"] for r in run.records])[: len(ref_seqs)]
    err = trajectory_error(seqs, poses, ref_seqs, ref_poses)
    return _table_row(exp, run.records, run.mapper.map_points, err, reference,
                      {"produced": len(run.records) + run.overrun, "overrun": run.overrun})


def _sample(points: np.ndarray, n: int = 200_000) -> np.ndarray:
    return points[:: max(1, len(points) // n)].astype(np.float32)


def _run_offload(exp: ScanExperiment, trace: Trace, voxel: float, rate: float, replay: Replay,
                 max_scans: int, is_sim: bool, source: ScanSource, out: Path) -> dict[str, Any]:
    edge = EdgeSettings(map_dir=str(out))
    robot = RobotSettings(
        scans=exp.scans, replay=replay, max_scans=max_scans, voxel=voxel, rate_hz=rate, sim_seed=exp.seed,
        scale_policy=exp.policy if exp.policy.startswith("dqn") or exp.policy == "rate" else "fixed",
        out_dir=str(out), wait_edge=30, scan_coding=exp.coding,  # type: ignore[arg-type]
    )
    if exp.voxel_range:
        robot.voxel_range = exp.voxel_range
    run = run_offload(out, edge, robot, exp.trace, ["--seed", str(exp.seed)], max_scans,
                      max_scans / rate + 120, keep_interrupted=True)
    reply = run.reply
    wall_start = link_clock_start(out / "link.log")
    recs = _read_scans(out / "robot_scans.csv")
    _with_link_rate(recs, trace, wall_start)
    _write_scans(out / "scans.csv", recs)
    metrics_path = out / "robot_metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.exists() else {}
    poses = np.load(out / "robot_poses.npz") if (out / "robot_poses.npz").exists() else None
    gt = {int(s): p for s, p in zip(poses["gt_seqs"], poses["gt_poses"], strict=True)} if poses else {}
    err, reference, map_points = None, "", 0
    if reply is not None and reply.scans:
        np.savez(out / "trajectory.npz", seqs=reply.seqs, poses=reply.poses)
        np.save(out / "map_sample.npy", _sample(reply.points))
        map_points = len(reply.points)
        ref_seqs, ref_poses, reference = _reference(source, [int(r["index"]) for r in recs], is_sim, gt)
        err = trajectory_error(reply.seqs, reply.poses, ref_seqs, ref_poses)
    row = _table_row(exp, recs, map_points, err, reference, metrics.get("balance"))
    row["cut_short"] = run.cut_short
    return row


def _read_scans(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    with open(path) as f:
        return list(csv.DictReader(f))


def summary_line(row: dict[str, Any]) -> str:
    def f(x: Any, fmt: str) -> str:
        return "-" if x is None else format(x, fmt)

    err = row.get("trajectory_error") or {}
    return (f"{row['policy']:>12} on {row['trace']}: S {f(row['S_kB'], '.0f')} kB, points "
            f"{f(row['points_before'], '.0f')} -> {f(row['points_after'], '.0f')}, received "
            f"{row['scans_received']}/{row['scans_produced']} (sent {row['scans_sent']}), "
            f"T {f(row['T_mean'], '.3f')} s "
            f"({f(100 * row['T_le_0.11'] if row['T_le_0.11'] is not None else None, '.0f')} % <= 0.11), "
            f"map {row['map_points']:,} pts, ATE {f(err.get('ate_rmse'), '.3f')} m")


