"""The fleet experiment's figures (pure): per robot from its ``robot_metrics.json`` and
``robot_scans.csv``, per run, then mean ± sd over repeats, and the markdown report.

The robot's files are read defensively: the ``fleet`` section of the metrics and the ``edge`` /
``pose_source`` columns exist only with the attach protocol; without them the figures are derived
from the per-scan rows (a scan has a pose when its edge acked it or the robot registered it).
"""

from __future__ import annotations

import math
import statistics
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

POSED = ("edge", "local")


def _num(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _sorted_rows(rows: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    return sorted((r for r in rows if _num(r.get("seq")) is not None), key=lambda r: int(float(r["seq"])))


def has_pose(row: Mapping[str, Any]) -> bool:
    return row.get("status") in ("acked", "local") or row.get("pose_source") in POSED


def pose_gaps(rows: Iterable[Mapping[str, Any]], period: float) -> tuple[int, float]:
    """(scans, seconds) of the longest run of consecutive produced scans without any pose, after
    the first pose (a robot that never had one is not "without" it yet: the start-up is separate).
    Seconds: the longest run's, from the posed scan before it to the one after it (capture
    times; the run's end closing a last one: its last scan + a period), as the robot's own figure
    measures a gap (robot/scanlog.py, which keeps the longest in seconds, whatever its scans, and
    leaves a run still open at the end out)."""
    best = (0, 0.0)
    run: list[Mapping[str, Any]] = []
    before: float | None = None  # the capture time of the last posed scan
    seen_pose = False
    for r in [*_sorted_rows(rows), {"status": "acked"}]:  # a sentinel closes the last run
        if has_pose(r):
            t1 = _num(r.get("capture_stamp"))
            if t1 is None and run:
                last = _num(run[-1].get("capture_stamp"))
                t1 = last + period if last is not None else None
            if seen_pose and len(run) > best[0]:
                secs = (t1 - before) if t1 is not None and before is not None else (len(run) + 1) * period
                best = (len(run), secs)
            seen_pose, run, before = True, [], t1
        elif seen_pose:
            run.append(r)
    return best


def on_time_share(rows: Iterable[Mapping[str, Any]], period: float, warmup: int = 0
                  ) -> tuple[float | None, int]:
    """(share of produced scans acked within one period on the robot's clock, scans not acked),
    over the scans after the first ``warmup``."""
    body = _sorted_rows(rows)[warmup:]
    if not body:
        return None, 0
    on_time = sum(r.get("status") == "acked" and (_num(r.get("rtt")) or math.inf) <= period for r in body)
    return on_time / len(body), sum(r.get("status") != "acked" for r in body)


SETTLE_S = 5.0  # seconds after the fleet's last move before its settled phase starts
STARVING = 0.5  # a robot on time for less than this share of its settled phase starves


def last_move(rows_by_robot: Mapping[str, Sequence[Mapping[str, Any]]]) -> float | None:
    """Capture time (robot clock, wall) of the fleet's last move: the first scan any robot had
    acked by an edge other than the one that acked its previous acked scan; None without moves."""
    last = None
    for rows in rows_by_robot.values():
        prev = None
        for r in _sorted_rows(rows):
            if r.get("status") != "acked" or not r.get("edge"):
                continue
            t = _num(r.get("capture_stamp"))
            if prev is not None and r["edge"] != prev and t is not None:
                last = t if last is None else max(last, t)
            prev = r["edge"]
    return last


def settled_phase(rows_by_robot: Mapping[str, Sequence[Mapping[str, Any]]], period: float,
                  start: float | None, settle: float = SETTLE_S) -> dict[str, Any]:
    """How the fleet serves its robots once nobody moves any more: from ``settle`` s after the last
    move (or ``start``, the run's clock start, without one) to the end, each robot's on-time share
    (produced scans acked within one period) and the edge that acked most of them. For an edge
    over capacity: the robots it kept and those it moved, each on time or starving."""
    moved = last_move(rows_by_robot)
    t_from = (moved + settle) if moved is not None else start
    robots: dict[str, dict[str, Any]] = {}
    for robot, rows in rows_by_robot.items():
        body = [r for r in rows if t_from is None or (_num(r.get("capture_stamp")) or 0.0) >= t_from]
        share, _ = on_time_share(body, period)
        edges = Counter(str(r.get("edge")) for r in body if r.get("status") == "acked" and r.get("edge"))
        robots[robot] = {"scans": len(body), "on_time": share,
                         "edge": edges.most_common(1)[0][0] if edges else None}
    shares = [r["on_time"] for r in robots.values() if r["scans"] and r["on_time"] is not None]
    return {  # an empty settled phase (a move in the run's last seconds) says nothing: None
        "from_s": (t_from - start) if t_from is not None and start is not None else None,
        "robots": robots,
        "on_time_min": min(shares) if shares else None,
        "starving": sum(1 for s in shares if s < STARVING) if shares else None,
    }


def _median_of(x: Any) -> float | None:
    """A number, or the median (else mean) of a ``{"median": .., "mean": ..}`` section."""
    if isinstance(x, Mapping):
        return _num(x.get("median", x.get("mean")))
    return _num(x)


def _floats(x: Any) -> list[float]:
    return [v for v in (_num(i) for i in (x if isinstance(x, (list, tuple)) else [])) if v is not None]


def robot_figures(metrics: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], period: float,
                  ate: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """One robot's figures of one run."""
    balance = metrics.get("balance") or {}
    fleet = metrics.get("fleet") or {}
    gap_scans, gap_s = pose_gaps(rows, period)
    per_edge = fleet.get("per_edge") or dict(Counter(
        str(r.get("edge")) for r in rows if r.get("status") == "acked" and r.get("edge")))
    on_time, _ = on_time_share(rows, period)
    return {
        "produced": int(balance.get("produced", len(rows))),
        "acked": int(balance.get("acked", 0)),
        "local": int(balance.get("local", 0)),
        "lost": int(balance.get("lost", 0)) + int(balance.get("late", 0)),
        "edge_dropped": int(balance.get("edge_dropped", 0)) + int(balance.get("edge_error", 0)),
        "edge_refused": int(balance.get("edge_refused", 0)),
        "dropped_source": int(sum((metrics.get("dropped_source") or {}).values())),
        "balanced": bool(metrics.get("balanced", False)),
        "on_time": on_time,
        "attaches": fleet.get("attaches"),
        "failovers": fleet.get("failovers"),
        "failover_s": _floats(fleet.get("failover_s")),
        "switch_jumps_m": _floats(fleet.get("switch_jumps_m")),
        "local_scans": fleet.get("local_scans"),
        "local_cpu_ms_per_scan": _median_of(fleet.get("local_cpu_ms_per_scan")),
        "max_pose_gap_scans": int(fleet.get("max_pose_gap_scans", gap_scans)),
        "max_pose_gap_s": _num(fleet.get("max_pose_gap_s")) if "max_pose_gap_s" in fleet else gap_s,
        "pose_gap_from_rows": [gap_scans, gap_s],  # cross-check of the robot's own figure
        "pose_lag_ms_max": _num((fleet.get("pose_lag_ms") or {}).get("max")),
        "pose_lag_ms_p95": _num((fleet.get("pose_lag_ms") or {}).get("p95")),
        "bridged_scans": fleet.get("bridged_scans"),
        "silence_stayed": fleet.get("silence_stayed"),
        "per_edge": dict(per_edge),
        "cpu_ms_per_scan": _num((metrics.get("cpu") or {}).get("process_ms_per_scan")),
        "trajectory_error": dict(ate) if ate else None,
    }


def _mean(xs: Iterable[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return statistics.fmean(vals) if vals else None


def _max(xs: Iterable[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return max(vals) if vals else None


def run_summary(robots: Mapping[str, Mapping[str, Any]], cpu: Mapping[str, Mapping[str, Any]],
                settled: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """One run's scalars (what is averaged over repeats); ``cpu``: process name -> its figures
    (``cores``: mean cores over its life), names starting with edge/robot/router/link;
    ``settled``: ``settled_phase``'s figures."""
    settled = settled or {}
    rs = list(robots.values())
    failover = [f for r in rs for f in r.get("failover_s", [])]
    jumps = [j for r in rs for j in r.get("switch_jumps_m", [])]

    def cores(kind: str) -> float | None:
        return _mean(_num(c.get("cores")) for name, c in cpu.items() if name.startswith(kind))

    return {
        "robots": len(rs),
        "balanced_all": all(r.get("balanced") for r in rs),
        **{k: sum(int(r.get(k) or 0) for r in rs)
           for k in ("produced", "acked", "local", "lost", "edge_dropped", "edge_refused", "dropped_source")},
        "ate_rmse_mean": _mean(_num((r.get("trajectory_error") or {}).get("ate_rmse")) for r in rs),
        "ate_rmse_max": _max(_num((r.get("trajectory_error") or {}).get("ate_rmse")) for r in rs),
        "max_pose_gap_scans": _max(float(r["max_pose_gap_scans"]) for r in rs) if rs else None,
        "max_pose_gap_s": _max(_num(r.get("max_pose_gap_s")) for r in rs),
        "pose_lag_ms_p95": _max(_num(r.get("pose_lag_ms_p95")) for r in rs),
        "pose_lag_ms_max": _max(_num(r.get("pose_lag_ms_max")) for r in rs),
        "bridged_scans": sum(int(r.get("bridged_scans") or 0) for r in rs),
        "silence_stayed": sum(int(r.get("silence_stayed") or 0) for r in rs),
        "failovers": len(failover),
        "failover_s_mean": _mean(failover),
        "failover_s_max": _max(failover),
        "switch_jump_m_mean": _mean(jumps),
        "switch_jump_m_max": _max(jumps),
        "local_cpu_ms_per_scan": _mean(_num(r.get("local_cpu_ms_per_scan")) for r in rs),
        "robot_cpu_ms_per_scan": _mean(_num(r.get("cpu_ms_per_scan")) for r in rs),
        "on_time_mean": _mean(_num(r.get("on_time")) for r in rs),
        "settled_from_s": _num(settled.get("from_s")),
        "settled_on_time_min": _num(settled.get("on_time_min")),
        "starving": settled.get("starving"),
        "edge_cores": cores("edge"),
        "robot_cores": cores("robot"),
        "router_cores": sum(_num(c.get("cores")) or 0.0 for n, c in cpu.items() if n.startswith("router")),
    }


def aggregate(summaries: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float | int | None]]:
    """Mean ± sample sd over repeats of every numeric figure (booleans: the share that hold)."""
    keys = dict.fromkeys(k for s in summaries for k in s)
    out: dict[str, dict[str, float | int | None]] = {}
    for k in keys:
        vals = [float(v) for v in (s.get(k) for s in summaries)
                if isinstance(v, (int, float)) and math.isfinite(float(v))]
        if vals:
            out[k] = {"mean": statistics.fmean(vals), "sd": statistics.stdev(vals) if len(vals) > 1 else None,
                      "n": len(vals)}
    return out


def ate_ratio(disturbed: Mapping[str, Any], baseline: Mapping[str, Any]) -> float | None:
    d = (disturbed.get("ate_rmse_mean") or {}).get("mean")
    b = (baseline.get("ate_rmse_mean") or {}).get("mean")
    return d / b if d is not None and b else None


def _cell(agg: Mapping[str, Any], key: str, spec: str) -> str:
    a = agg.get(key)
    if not a or a.get("mean") is None:
        return "–"
    text = format(a["mean"], spec)
    return text + (f" ± {format(a['sd'], spec)}" if a.get("sd") is not None else "")


ROWS = (
    ("scans produced (all robots)", "produced", ".0f"),
    ("acked by an edge", "acked", ".0f"),
    ("registered locally", "local", ".0f"),
    ("lost (+ late)", "lost", ".0f"),
    ("dropped or failed by an edge", "edge_dropped", ".0f"),
    ("dropped at the source", "dropped_source", ".0f"),
    ("ledgers balanced (share of runs)", "balanced_all", ".2f"),
    ("ATE RMSE, mean over robots (m)", "ate_rmse_mean", ".3f"),
    ("ATE RMSE, worst robot (m)", "ate_rmse_max", ".3f"),
    ("longest pose gap (scans)", "max_pose_gap_scans", ".1f"),
    ("longest pose gap (s)", "max_pose_gap_s", ".2f"),
    ("pose lag p95, worst robot (ms)", "pose_lag_ms_p95", ".0f"),
    ("pose lag max, worst robot (ms)", "pose_lag_ms_max", ".0f"),
    ("scans bridged (sent and registered locally)", "bridged_scans", ".0f"),
    ("failovers", "failovers", ".1f"),
    ("silences waited out (no other edge to go to)", "silence_stayed", ".1f"),
    ("failover time, mean (s)", "failover_s_mean", ".2f"),
    ("failover time, max (s)", "failover_s_max", ".2f"),
    ("switch jump, mean (m)", "switch_jump_m_mean", ".3f"),
    ("switch jump, max (m)", "switch_jump_m_max", ".3f"),
    ("local odometry CPU (ms/scan)", "local_cpu_ms_per_scan", ".1f"),
    ("robot process CPU (ms/scan)", "robot_cpu_ms_per_scan", ".1f"),
    ("on time (acked ≤ 1 period)", "on_time_mean", ".3f"),
    ("settled phase: starts (s after the start)", "settled_from_s", ".1f"),
    ("settled phase: on time, worst robot", "settled_on_time_min", ".3f"),
    ("settled phase: robots starving (on time < 0.5)", "starving", ".1f"),
    ("edge process CPU (cores)", "edge_cores", ".2f"), ("robot process CPU (cores)", "robot_cores", ".2f"),
    ("router CPU, all routers (cores)", "router_cores", ".2f"),
)


def markdown(title: str, setup: str, disturbed: Mapping[str, Any], baseline: Mapping[str, Any] | None,
             per_robot: Mapping[str, Mapping[str, Any]], ratio: float | None, kill_count: int) -> str:
    """The report: the run-level figures (with the baseline beside them), the ATE ratio against
    the issue's target, then one line per robot."""
    head = "| figure | scripted runs |" + (" baseline (no events) |" if baseline else "")
    lines = [f"# {title}", "", setup, "", head, "|---|---|" + ("---|" if baseline else "")]
    for label, key, spec in ROWS:
        lines.append(f"| {label} | {_cell(disturbed, key, spec)} |"
                     + (f" {_cell(baseline, key, spec)} |" if baseline else ""))
    lines.append("")
    if ratio is not None:
        verdict = (("target ≤ 1.2× with 5 kills: " + ("met" if ratio <= 1.2 else "missed"))
                   if kill_count >= 5 else f"{kill_count} kill(s) scripted; the target, ≤ 1.2×, is for 5")
        lines += [f"ATE ratio scripted / baseline: **{ratio:.2f}×** ({verdict})", ""]
    lines += ["## Per robot (scripted runs)", "",
              "| robot | produced | acked | local | lost | balanced | ATE (m) | max gap (scans) "
              "| failover (s) | switch jump (m) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for robot, agg in per_robot.items():
        lines.append(f"| {robot} | " + " | ".join(_cell(agg, k, s) for k, s in (
            ("produced", ".0f"), ("acked", ".0f"), ("local", ".0f"), ("lost", ".0f"), ("balanced", ".2f"),
            ("ate_rmse", ".3f"), ("max_pose_gap_scans", ".1f"), ("failover_s_mean", ".2f"),
            ("switch_jump_m_max", ".3f"))) + " |")
    return "\n".join(lines) + "\n"


def robot_scalars(fig: Mapping[str, Any]) -> dict[str, Any]:
    """A robot's figures reduced to scalars, for its mean ± sd over repeats."""
    fo, jumps = fig.get("failover_s") or [], fig.get("switch_jumps_m") or []
    return {
        **{k: fig.get(k) for k in ("produced", "acked", "local", "lost", "max_pose_gap_scans",
                                   "max_pose_gap_s", "on_time", "cpu_ms_per_scan", "local_cpu_ms_per_scan")},
        "balanced": 1.0 if fig.get("balanced") else 0.0,
        "ate_rmse": _num((fig.get("trajectory_error") or {}).get("ate_rmse")),
        "failover_s_mean": _mean(fo), "switch_jump_m_max": _max(jumps),
    }
