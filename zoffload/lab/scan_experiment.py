"""``zoffload experiment scan``: one robot -> link emulator -> edge run with real processes,
measured as the scale-optimisation paper's Table I.

Processes: ``zoffload-edge`` (peer, listening), ``zoffload link`` (the emulator, in front of the
edge), ``zoffload-robot`` (client mode, so every byte goes through the emulator: a peer could
learn the edge's own address and connect around it). Shared memory is off everywhere, the robot's
TCP send buffer is kept small so a slow link reaches Zenoh's congestion control (BLOCK_FIRST for
scans) instead of hiding in the kernel. The harness's own session talks to the edge directly
(measurement only).

Every run writes, even when cut short: ``results.json`` (the Table I row, with the robot's CPU
per scan, the scans deliberately skipped and the share on time for their slot), ``scans.csv``
(per-scan decisions with their reason, measurements, the link rate at that moment), ``link.csv``
(what the emulator let through per second), the configs and the logs. ``repeat`` runs the same
experiment N times into ``run1`` ... ``runN`` (the link emulator's jitter seeded differently each
time) for ``zoffload report`` to give mean and spread.
"""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import asdict, dataclass, replace
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.edge.export import registered_backfill
from zoffload.lab.eval.trajectory import trajectory_error
from zoffload.lab.link.ceiling import stream_shares, stream_start
from zoffload.lab.link.trace import Trace, load_trace
from zoffload.lab.runner import edge_apart_cores, environment_settings, link_clock_start, run_offload
from zoffload.robot.scanlog import RECORD_FIELDS, read_scan_rows
from zoffload.runtime.config import EdgeSettings, RobotFleetSettings, RobotSettings
from zoffload.runtime.errors import ConfigError
from zoffload.sources import open_scan_source
from zoffload.sources.base import Replay, ScanSource, replay_order


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
    coding: str = "f32"  # scan payload coding: "f32", "q16z" or "q16d"
    voxel_range: tuple[float, float] | None = None  # the policies' range (default the robot's)
    repeat: int = 1  # runs of the same experiment (run1 ... runN under ``out``)
    # The robot's fleet defaults (attach protocol on): while the link is out it registers scans
    # with its own light odometry and hands the poses to the edge when it attaches again. Off by
    # default: the paper's set-up, every scan offered to the one edge.
    attach: bool = False
    # The edge on a core of its own, the robot and the link emulator on the others (taskset), as
    # on separate computers (lab/runner.py ``edge_apart_cores``). Off by default: the tables were
    # measured with every process on every core, and on a 2-core host the robot, its simulator and
    # the emulator sharing one core were on time 12-15 points less often on ``wifi-locations``
    # (docs/scan-policy-log.md, 2026-12-06).
    edge_apart: bool = False


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


def reference_trajectory(source: ScanSource, replay: str, newest: int) -> tuple[np.ndarray, np.ndarray]:
    """KISS-ICP run locally on every raw scan the sensor produced, seq 0 to ``newest``, each at its
    place in the replay (``replay_order``): the scans the robot never read as well. A loop overrun
    leaves a seq with no record, so numbering the records instead shifts the reference one scan
    per overrun against the robot's poses (on the KITTI-360 replay, metres)."""
    from zoffload.mapping.cloud import drop_non_finite
    from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size

    mapper = RobotMapper(voxel_size=mapper_voxel_size(source.max_range, 0.0), max_range=source.max_range)
    for seq, index in enumerate(islice(replay_order(len(source), replay), newest + 1)):
        mapper.register(seq, drop_non_finite(source.read(index).points)[0])
    return mapper.trajectory()


def _reference(source: ScanSource, recs: list[dict[str, Any]], replay: str, is_sim: bool,
               gt: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, str]:
    """Reference trajectory per seq: ground truth, or KISS-ICP locally on every raw scan."""
    if is_sim:
        seqs = np.array(sorted(gt), np.int64)
        return seqs, np.array([gt[s] for s in seqs]).reshape(-1, 4, 4), "simulator ground truth"
    newest = max((int(r["seq"]) for r in recs), default=-1)
    seqs, poses = reference_trajectory(source, replay, newest)
    return seqs, poses, "KISS-ICP run locally on every raw scan (no ground truth for real data)"


def edge_registered(recs: list[dict[str, Any]]) -> int:
    """Scans the edge registered: acked, and those whose ack came after the robot gave up waiting
    (``late``, the edge's answer ``ok``)."""
    return sum(1 for r in recs if r.get("status") == "acked"
               or (r.get("status") == "late" and r.get("late_status") == "ok"))


DELIBERATE = ("source:pace", "source:skip", "source:stall")  # the robot chose not to send them
SLOT_SLACK = 1.1  # on time for its slot: T <= 1.1 x the period the robot intended


def kept_local(recs: list[dict[str, Any]]) -> int:
    """Scans the robot kept while its edge's answers were overdue (status ``local``) and registered
    with its own odometry (``pose_source`` local): not sent, bridged by a real pose that joins the
    edge's trajectory when the robot attaches again."""
    return sum(r.get("status") == "local" and r.get("pose_source") == "local" for r in recs)


def _slot_figures(recs: list[dict[str, Any]], received: list[dict[str, Any]], period: float,
                  produced: int, registered: set[int] | None = None) -> dict[str, Any]:
    """Skipped scans and timeliness per slot: a scan sent after k deliberately skipped ones was
    meant to arrive (k + 1) periods after the previous one. ``delivered_skipped_or_local`` also
    counts the scans an outage kept local (``kept_local``), ``delivered_skipped_or_backfilled``
    those the edge registered from an attach's backfill: the robot's records mark the scans of a
    backfill an edge *accepted* (``backfill``), and of those only the seqs the edge says it
    registered (``registered``, its ``backfilled_seqs``) count; an edge that left a backfill
    unused (too far behind, a failed registration) took none of it. Without ``registered`` (an
    edge that does not say) the marks count."""
    skipped = sum(r.get("status") in DELIBERATE for r in recs)
    local = kept_local(recs)
    counted = {r.get("seq") for r in received} | {r.get("seq") for r in recs if r.get("status") in DELIBERATE}
    backfilled = sum(str(r.get("backfill") or "") == "1" and r.get("seq") not in counted
                     and (registered is None or _seq(r) in registered) for r in recs)
    on_time = [float(r["interarrival"]) <= SLOT_SLACK * period * (1 + int(float(r.get("skipped") or 0)))
               for r in received if r.get("interarrival") not in (None, "")
               and np.isfinite(float(r["interarrival"]))]
    return {
        "scans_skipped": skipped,
        # of them, those the policy held back in an ack silence (``source:stall``: mostly an
        # outage's scans, which the link could not have carried; announced, so the edge bridges them)
        "scans_stalled": sum(r.get("status") == "source:stall" for r in recs),
        "skipped_share": skipped / produced if produced else None,
        "delivered_or_skipped": (len(received) + skipped) / produced if produced else None,
        "scans_kept_local": local,
        "delivered_skipped_or_local": (len(received) + skipped + local) / produced if produced else None,
        # ... or handed to the edge later in an attach's backfill (robot/odometry.py), each scan once
        "delivered_skipped_or_backfilled": ((len(received) + skipped + backfilled) / produced if produced
                                            else None),
        "on_time_slot": float(np.mean(on_time)) if on_time else None,
    }


def _seq(r: dict[str, Any]) -> int | None:
    try:
        return int(r.get("seq"))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


def _table_row(exp: ScanExperiment, recs: list[dict[str, Any]], map_points: int | None, err: Any,
               reference: str, balance: dict[str, int] | None, period: float = 0.1,
               cpu: dict[str, Any] | None = None, registered: set[int] | None = None) -> dict[str, Any]:
    sent = [r for r in recs if r.get("bytes") not in (None, "")]
    # the edge got them: answered in time (acked, or dropped or failed there), or late but not refused
    received = [r for r in recs if r.get("status") in ("acked", "edge_dropped", "edge_error")
                or (r.get("status") == "late" and r.get("late_status") != "refused")]
    t = np.array([float(r["interarrival"]) for r in received if r.get("interarrival") not in (None, "")
                  and np.isfinite(float(r["interarrival"]))])
    produced = (balance or {}).get("produced", len(recs))
    return {
        "policy": (exp.policy if exp.coding == "f32" else f"{exp.policy}+{exp.coding}")
        + ("+attach" if exp.attach and exp.policy != "local" else "")
        + ("+apart" if exp.edge_apart and exp.policy != "local" else ""),
        "trace": exp.trace, "scans": exp.scans,
        "S_kB": float(np.mean([float(r["bytes"]) for r in sent]) / 1e3) if sent and exp.policy != "local"
        else None,
        "points_before": float(np.mean([float(r["n_raw"]) for r in recs])) if recs else None,
        "points_after": _mean([r.get("n_sent") for r in recs]),
        "scans_produced": (balance or {}).get("produced", len(recs)),
        "scans_sent": len(sent) if exp.policy != "local" else len(recs),
        "scans_received": len(received) if exp.policy != "local" else len(recs),
        # of those, registered by the edge; the rest it dropped (late, full queue, overloaded) or
        # answered with an error
        "scans_registered": edge_registered(received) if exp.policy != "local" else len(recs),
        # registered by the robot's own odometry while the link was out (``--attach``)
        "scans_local": sum(1 for r in recs if r.get("status") == "local") if exp.policy != "local" else 0,
        "T_mean": float(t.mean()) if len(t) else None,
        "T_le_0.11": float((t <= 0.11).mean()) if len(t) else None,
        "map_points": map_points,
        "trajectory_error": err.as_dict() if err else None,
        "trajectory_reference": reference,
        "balance": balance,
        **(_slot_figures(recs, received, period, produced, registered) if exp.policy != "local" else {}),
        # the robot's CPU per scan: the offload path (median per scan sent), or KISS-ICP locally
        "robot_cpu_ms": (cpu or {}).get("per_scan_ms"),
        "robot_process_cpu_ms": (cpu or {}).get("process_ms_per_scan"),
        "cpu": cpu,
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
    """One run, or with ``repeat`` > 1 every run into ``run1`` ... ``runN`` (the last one's row is
    returned; ``zoffload report OUT/run*`` aggregates them)."""
    if exp.repeat <= 1:
        return _run_once(exp)
    row: dict[str, Any] = {}
    for i in range(1, exp.repeat + 1):
        run = replace(exp, out=str(Path(exp.out) / f"run{i}"), repeat=1)
        row = _run_once(run, link_seed=exp.seed + i - 1)
        print(summary_line(row), flush=True)
    return row


def _run_once(exp: ScanExperiment, link_seed: int | None = None) -> dict[str, Any]:
    out = Path(exp.out)
    out.mkdir(parents=True, exist_ok=True)
    environment = environment_settings()  # (a variable naming no setting fails here, before the run)
    voxel = policy_voxel(exp.policy)
    trace = load_trace(exp.trace)
    is_sim = exp.scans == "sim"
    source = open_scan_source(exp.scans, sim_seed=exp.seed)
    rate = exp.rate_hz or source.rate_hz
    replay: Replay = exp.replay or ("once" if is_sim else "pingpong")
    max_scans = exp.max_scans or int((trace.duration + 10) * rate)
    (out / "experiment.json").write_text(json.dumps(asdict(exp) | {"max_scans": max_scans, "replay": replay,
                                                                    "rate": rate}, indent=2))
    print(f"experiment scan: policy {exp.policy}, trace {trace.name}, {max_scans} scans of "
          f"{source.name} at {rate:g} Hz -> {out}", flush=True)
    if voxel is None:
        row = _run_local(exp, source, rate, replay, max_scans, is_sim, out)
    else:
        row = _run_offload(exp, trace, voxel, rate, replay, max_scans, is_sim, source, out,
                           exp.seed if link_seed is None else link_seed)
    # what ZOFFLOAD_ROBOT__* / ZOFFLOAD_EDGE__* set ({} for nothing; a local run starts no daemon)
    row["environment"] = environment if voxel is not None else {}
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
    ref_seqs, ref_poses, reference = _reference(source, run.records, replay, is_sim, run.gt)
    err = trajectory_error(seqs, poses, ref_seqs, ref_poses)
    scans = max(1, len(run.records))
    cpu = {"per_scan_ms": 1e3 * (run.cpu_s - run.sensor_cpu_s) / scans,  # KISS-ICP + the global map
           "process_s": run.cpu_s, "sensor_s": run.sensor_cpu_s,
           "process_ms_per_scan": 1e3 * (run.cpu_s - run.sensor_cpu_s) / scans}
    return _table_row(exp, run.records, run.mapper.map_points, err, reference,
                      {"produced": len(run.records) + run.overrun, "overrun": run.overrun}, 1 / rate, cpu)


def _sample(points: np.ndarray, n: int = 200_000) -> np.ndarray:
    return points[:: max(1, len(points) // n)].astype(np.float32)


def _run_offload(exp: ScanExperiment, trace: Trace, voxel: float, rate: float, replay: Replay,
                 max_scans: int, is_sim: bool, source: ScanSource, out: Path, link_seed: int
                 ) -> dict[str, Any]:
    edge = EdgeSettings(map_dir=str(out))
    robot = RobotSettings(
        scans=exp.scans, replay=replay, max_scans=max_scans, voxel=voxel, rate_hz=rate, sim_seed=exp.seed,
        scale_policy=exp.policy if exp.policy.startswith("dqn") or exp.policy == "rate" else "fixed",
        out_dir=str(out), wait_edge=30, scan_coding=exp.coding,  # type: ignore[arg-type]
        # The paper's set-up: one edge, every scan offered to it (a scan is dropped at the source
        # while the edge's liveliness token is gone). With ``--attach``, the robot's defaults:
        # while the link is out it maps with its own odometry and hands the poses over on return
        fleet=RobotFleetSettings(attach=exp.attach),
    )
    if exp.voxel_range:
        robot.voxel_range = exp.voxel_range
    cpus = edge_apart_cores() if exp.edge_apart else {}
    if exp.edge_apart and (not cpus or shutil.which("taskset") is None):
        raise ConfigError("the edge on a core of its own (--edge-apart) needs two cores to split and "
                          "taskset (util-linux)")
    run = run_offload(out, edge, robot, exp.trace, ["--seed", str(link_seed)], max_scans,
                      max_scans / rate + 120, keep_interrupted=True, cpus=cpus)
    reply = run.reply
    wall_start = link_clock_start(out / "link.log")
    recs = read_scan_rows(out / "robot_scans.csv")
    _with_link_rate(recs, trace, wall_start)
    _write_scans(out / "scans.csv", recs)
    metrics_path = out / "robot_metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.exists() else {}
    poses = np.load(out / "robot_poses.npz") if (out / "robot_poses.npz").exists() else None
    gt = {int(s): p for s, p in zip(poses["gt_seqs"], poses["gt_poses"], strict=True)} if poses else {}
    # no answer to the final map query: no map (unknown, not 0), and none of an earlier attempt's
    err, reference = None, ""
    map_points = len(reply.points) if reply is not None else None
    for stale in ("trajectory.npz", "map_sample.npy"):
        (out / stale).unlink(missing_ok=True)
    if reply is not None and reply.scans:
        np.savez(out / "trajectory.npz", seqs=reply.seqs, poses=reply.poses)
        np.save(out / "map_sample.npy", _sample(reply.points))
        ref_seqs, ref_poses, reference = _reference(source, recs, replay, is_sim, gt)
        err = trajectory_error(reply.seqs, reply.poses, ref_seqs, ref_poses)
    # the outage scans the robot handed its edge with an attach, registered there
    backfilled, registered = _backfilled(out / f"{robot.robot_id}_edge.json") if exp.attach else ({}, None)
    row = _table_row(exp, recs, map_points, err, reference, metrics.get("balance"), 1 / rate,
                     metrics.get("cpu"), registered)
    row["cut_short"] = run.cut_short
    row["link_seed"] = link_seed
    if row.get("S_kB") and wall_start is not None:
        # the link emulator's model alone over the run's stretch of the trace (lab/link/ceiling.py):
        # a scan every period of 1 byte (what its jitter leaves) and of the run's mean size
        captures = (float(r["capture_stamp"]) for r in recs if r.get("capture_stamp") not in (None, ""))
        start = stream_start(captures, wall_start)
        row["on_time_tiny"], row["on_time_steady_size"] = stream_shares(
            trace, period=1 / rate, size=1e3 * row["S_kB"], duration=max_scans / rate, start=start)
    row.update(backfilled)
    if "backfill_unknown" in backfilled:  # which backfilled scans the edge registered: unknown
        row["delivered_skipped_or_backfilled"] = None
    return row


def _backfilled(path: Path) -> tuple[dict[str, Any], set[int] | None]:
    """``scans_backfilled``: the edge's counter of the outage scans it registered from an attach's
    backfill (late: robot/odometry.py; some were also booked skipped, a stall, or lost on the way,
    so it is not added to "delivered or skipped"), and the seqs it registered (its
    ``backfilled_seqs``; None when it does not say). An edge that wrote nothing readable leaves
    both unknown: ``scans_backfilled`` None and ``backfill_unknown`` says why (the run's
    "+ backfilled" is then None, not the lower bound of no scan backfilled)."""
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return {"scans_backfilled": None, "backfill_unknown": f"{path.name}: {exc}"[:200]}, None
    if not isinstance(summary, dict):
        return {"scans_backfilled": None, "backfill_unknown": f"{path.name}: not a JSON object"}, None
    registered = registered_backfill(summary)
    try:
        return {"scans_backfilled": int(summary.get("backfilled", 0))}, registered
    except (ValueError, TypeError):
        return {}, registered


def summary_line(row: dict[str, Any]) -> str:
    def f(x: Any, fmt: str) -> str:
        return "-" if x is None else format(x, fmt)

    err = row.get("trajectory_error") or {}
    return (f"{row['policy']:>12} on {row['trace']}: S {f(row['S_kB'], '.0f')} kB, points "
            f"{f(row['points_before'], '.0f')} -> {f(row['points_after'], '.0f')}, received "
            f"{row['scans_received']}/{row['scans_produced']} (sent {row['scans_sent']}; registered "
            f"{row.get('scans_registered', '-')}), "
            f"T {f(row['T_mean'], '.3f')} s "
            f"({f(100 * row['T_le_0.11'] if row['T_le_0.11'] is not None else None, '.0f')} % <= 0.11), "
            f"map {f(row['map_points'], ',')} pts, ATE {f(err.get('ate_rmse'), '.3f')} m, "
            f"robot CPU {f(row.get('robot_cpu_ms'), '.2f')} ms/scan"
            + (f", skipped {row['scans_skipped']}, on time for slot "
               f"{f(100 * row['on_time_slot'] if row.get('on_time_slot') is not None else None, '.0f')} %"
               if "scans_skipped" in row else "")
            + (f" (1-byte scans on this link: {100 * row['on_time_tiny']:.0f} %)"
               if row.get("on_time_tiny") is not None else ""))


