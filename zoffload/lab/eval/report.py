"""``zoffload report``: experiment folders -> a markdown table in the seed's layout + PNG plots.

Several runs of one experiment make one row: folders named ``run1``, ``run2``, ... under the same
parent (``zoffload experiment scan --repeat N``; pass ``OUT`` or ``OUT/run*``) are averaged, and
the row shows mean ± sd (sample standard deviation) where they differ."""

from __future__ import annotations

import csv
import json
import os
import re
import statistics
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.lab.eval.plots import _plt

# The scale-optimisation paper's Table I (LeGO-LOAM map; "delay" = its bad-link location).
SEED_TABLE_I: list[dict[str, Any]] = [
    {"policy": "Local (paper)", "received": "954", "T_mean": 0.10, "map_points": 229_213},
    {"policy": "Raw offload, bad link (paper)", "received": "528", "T_mean": 0.184, "map_points": 92_644},
    {"policy": "RL offload, bad link (paper)", "received": "823", "T_mean": 0.118, "map_points": 165_184},
]


def load_run(folder: Path) -> dict[str, Any]:
    res = json.loads((folder / "results.json").read_text())
    res["folder"] = folder
    with open(folder / "scans.csv") as f:
        res["records"] = list(csv.DictReader(f))
    if "delivered_skipped_or_local" not in res and res.get("delivered_or_skipped") is not None:
        # a run from before the figure: its records hold what it needs
        from zoffload.lab.scan_experiment import kept_local

        local = kept_local(res["records"])
        res["scans_kept_local"] = local
        res["delivered_skipped_or_local"] = (res["delivered_or_skipped"]
                                             + local / max(1, int(res.get("scans_produced") or 0)))
    if "scans_registered" not in res and res.get("policy") != "local" and res["records"]:
        # a run from before the figure (every run of a row has it, so its mean is over them all)
        from zoffload.lab.scan_experiment import edge_registered

        res["scans_registered"] = edge_registered(res["records"])
    if "on_time_tiny" not in res and res.get("on_time_slot") is not None and res.get("S_kB"):
        # a run from before the figure: from its trace and its stretch of it (lab/link/ceiling.py)
        from zoffload.lab.link.ceiling import run_streams
        from zoffload.lab.link.trace import TraceError

        try:
            res["on_time_tiny"], res["on_time_steady_size"] = run_streams(folder)
        except (OSError, ValueError, KeyError, TypeError, TraceError):
            pass  # unknown (its trace is gone): the report leaves it out
    link = folder / "link.csv"
    if link.exists():
        with open(link) as f:
            res["link"] = list(csv.DictReader(f))
    sample = folder / "map_sample.npy"
    res["map_sample"] = np.load(sample) if sample.exists() else None
    return res


def _fmt(x: Any, spec: str, none: str = "–") -> str:
    return none if x is None else format(x, spec)


RUN_NAME = re.compile(r"^run\d+$")
# Figures averaged over the runs of a row (dotted: nested in results.json)
AVERAGED = ("S_kB", "points_before", "points_after", "scans_produced", "scans_sent", "scans_received",
            "scans_registered",
            "T_mean", "T_le_0.11", "map_points", "trajectory_error.ate_rmse", "robot_cpu_ms",
            "robot_process_cpu_ms", "scans_skipped", "skipped_share", "delivered_or_skipped", "on_time_slot",
            "on_time_tiny",
            "scans_kept_local", "delivered_skipped_or_local", "scans_backfilled",
            "delivered_skipped_or_backfilled")


def expand_runs(folders: list[Path]) -> list[Path]:
    """A folder without results.json that holds ``run*/results.json`` stands for those runs."""
    out: list[Path] = []
    for f in folders:
        found = [d for d in f.glob("run*") if RUN_NAME.match(d.name) and (d / "results.json").exists()]
        runs = sorted(found, key=lambda d: int(d.name[3:]))
        out.extend(runs if not (f / "results.json").is_file() and runs else [f])
    return out


def _get(r: dict[str, Any], key: str) -> Any:
    """``r[key]``, or for ``a.b`` (no such key) ``r[a][b]``."""
    if key in r:
        return r[key]
    head, _, rest = key.partition(".")
    sub = r.get(head)
    return _get(sub, rest) if rest and isinstance(sub, dict) else None


def aggregate(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per experiment: runs in folders ``runN`` under one parent are averaged (``n``,
    ``sd`` per figure); every other folder is its own row."""
    groups: dict[Path, list[dict[str, Any]]] = {}
    for r in runs:
        folder = Path(r["folder"])
        groups.setdefault(folder.parent if RUN_NAME.match(folder.name) else folder, []).append(r)
    rows = []
    for folder, members in groups.items():
        row = dict(members[0], folder=folder, n=len(members), sd={}, known={}, runs=members)
        for key in AVERAGED:
            values = [float(v) for v in (_get(m, key) for m in members) if v is not None]
            if not values:
                continue
            if len(values) < len(members):  # the mean of the runs that know it: said in its cell
                row["known"][key] = len(values)
            mean = statistics.fmean(values)
            if key == "trajectory_error.ate_rmse":
                row["trajectory_error"] = dict(row.get("trajectory_error") or {}, ate_rmse=mean)
            else:
                row[key] = mean
            if len(values) > 1:
                row["sd"][key] = statistics.stdev(values)
        rows.append(row)
    return rows


def _npz_pair(folder: Path | None, name: str, keys: tuple[str, str]) -> tuple[np.ndarray, np.ndarray] | None:
    """Two arrays of ``folder/name`` (None: no folder, no file, or nothing in it)."""
    if folder is None or not (Path(folder) / name).exists():
        return None
    with np.load(Path(folder) / name) as z:
        return (z[keys[0]], z[keys[1]]) if len(z[keys[0]]) else None


def _trajectory(folder: Path | None) -> tuple[np.ndarray, np.ndarray] | None:
    return _npz_pair(folder, "trajectory.npz", ("seqs", "poses"))


def _ground_truth(folder: Path | None) -> tuple[np.ndarray, np.ndarray] | None:
    return _npz_pair(folder, "robot_poses.npz", ("gt_seqs", "gt_poses"))


def same_scans_vs_local(row: dict[str, Any], local: dict[str, Any]) -> tuple[float, float | None] | None:
    """The row's trajectory error over the scans its edge registered, against the local runs'
    error over those same scans: (mean of the runs' ratios − 1, their sd), None without a
    simulator's ground truth or the trajectories. The local run registers every scan and an
    offloaded one only those that reached the edge (an outage's scans are the robot's own, not in
    the edge's trajectory), so their errors over all scans are taken over different stretches of
    the drive: local's last outage-length stretch can pull its figure down or up. (The edge's
    trajectory also holds the robot's own poses an attach handed over, a few a run.)"""
    from zoffload.lab.eval.trajectory import trajectory_error

    found = (_trajectory(m.get("folder")) for m in local.get("runs", [local]))
    local_runs = [t for t in found if t is not None]
    if not local_runs or str(row.get("trajectory_reference", "")) != "simulator ground truth":
        return None
    ratios = []
    for run in row.get("runs", [row]):
        own, gt = _trajectory(run.get("folder")), _ground_truth(run.get("folder"))
        mine = _get(run, "trajectory_error.ate_rmse")  # the experiment's, over these scans and truth
        if own is None or gt is None or mine is None:
            return None
        theirs = []
        for seqs, poses in local_runs:
            keep = np.isin(seqs, own[0])
            err = trajectory_error(seqs[keep], poses[keep], gt[0], gt[1])
            if err is not None:
                theirs.append(err.ate_rmse)
        if not theirs or not statistics.fmean(theirs) > 0:
            return None
        ratios.append(float(mine) / statistics.fmean(theirs) - 1)
    return statistics.fmean(ratios), (statistics.stdev(ratios) if len(ratios) > 1 else None)


def _cell(r: dict[str, Any], key: str, spec: str, scale: float = 1.0, unit: str = "") -> str:
    """The row's figure, ``mean ± sd`` when it has several runs, and over how many of them when
    some did not know it (e.g. "+ backfilled" of a run whose edge summary was unreadable)."""
    x = _get(r, key)
    if x is None:
        return "–"
    sd = r.get("sd", {}).get(key)
    text = format(scale * x, spec)
    text = f"{text} ± {format(scale * sd, spec)}{unit}" if sd is not None else text + unit
    known = r.get("known", {}).get(key)
    return f"{text} ({known} of {r['n']} runs)" if known is not None else text


def _local_key(r: dict[str, Any]) -> tuple[str, int | None]:
    """(scan source, scans the sensor produced): the most of the row's runs (a run cut short
    produced fewer; the row's mean would match no local run)."""
    produced = [float(p) for p in (m.get("scans_produced") for m in r.get("runs", [r])) if p is not None]
    return str(r.get("scans")), round(max(produced)) if produced else None


def table_markdown(runs: list[dict[str, Any]]) -> str:
    rows = [r if "n" in r else dict(r, n=1, sd={}) for r in runs]
    # a run is set against the local run of the same scans: same source and as many of them
    local = {_local_key(r): r for r in rows if r["policy"] == "local"}
    lines = [
        "| run | trace | S (kB/scan) | points before → after | received (registered) / sensor scans (sent) "
        "| T̄ (s) "
        "| T ≤ 0.11 s | map points | vs local | trajectory error (m) | robot CPU (ms/scan) | skipped "
        "| on time for slot | delivered or skipped | + kept local in outages | + backfilled "
        "| trajectory vs local, same scans |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ref = local.get(_local_key(r))
        vs = (f"{100 * (r['map_points'] / ref['map_points'] - 1):+.0f} %"
              if ref and ref is not r and ref.get("map_points") and r.get("map_points") is not None else "")
        same = same_scans_vs_local(r, ref) if ref and ref is not r else None
        same_text = ""
        if same is not None:
            spread = f" ± {100 * same[1]:.0f}" if same[1] is not None else ""
            same_text = f"{100 * same[0]:+.0f}{spread} %"
        short = sum(bool(m.get("cut_short")) for m in r.get("runs", [r]))
        members = r.get("runs", [r])
        env = {json.dumps(m["environment"], sort_keys=True) for m in members if m.get("environment")}
        name = (r["policy"] + (f" ({r['n']} runs)" if r["n"] > 1 else "")
                + (f" ({short} cut short)" if short else "")
                + "".join(f" (environment {e})" for e in sorted(env)))
        received = (_cell(r, "scans_received", ".0f") if r["n"] > 1 else str(r["scans_received"]))
        if _get(r, "scans_registered") is not None and r["policy"] != "local":  # (older results: not kept)
            received += f" ({_cell(r, 'scans_registered', '.0f')})"
        # 1-byte scans every period on the run's emulated link: what its jitter leaves (lab/link/ceiling.py)
        tiny = (f" (1-byte {_cell(r, 'on_time_tiny', '.0f', 100, ' %')})"
                if _get(r, "on_time_tiny") is not None else "")
        lines.append(
            f"| {name} | {r['trace'] if r['policy'] != 'local' else '(no network)'} "
            f"| {_cell(r, 'S_kB', '.0f')} "
            f"| {_fmt(r['points_before'], ',.0f')} → {_cell(r, 'points_after', ',.0f')} "
            f"| {received} / {r.get('scans_produced', r['scans_sent']):.0f} ({r['scans_sent']:.0f}) "
            f"| {_cell(r, 'T_mean', '.3f')} "
            f"| {_cell(r, 'T_le_0.11', '.0f', 100, ' %')} "
            f"| {_cell(r, 'map_points', ',.0f')} | {vs} | {_cell(r, 'trajectory_error.ate_rmse', '.3f')} "
            f"| {_cell(r, 'robot_cpu_ms', '.2f')} | {_cell(r, 'skipped_share', '.0f', 100, ' %')} "
            f"| {_cell(r, 'on_time_slot', '.0f', 100, ' %')}{tiny} "
            f"| {_cell(r, 'delivered_or_skipped', '.0f', 100, ' %')} "
            f"| {_cell(r, 'delivered_skipped_or_local', '.0f', 100, ' %')} "
            f"| {_cell(r, 'delivered_skipped_or_backfilled', '.0f', 100, ' %')} | {same_text} |"
        )
    for s in SEED_TABLE_I:
        vs_paper = 100 * (s["map_points"] / SEED_TABLE_I[0]["map_points"] - 1)
        lines.append(f"| {s['policy']} | | | | {s['received']} | {s['T_mean']:.3f} | | {s['map_points']:,} "
                     f"| {vs_paper:+.0f} % | | | | | | | |")
    return "\n".join(lines)


def _times(r: dict[str, Any]) -> np.ndarray:
    stamps = np.array([float(x["capture_stamp"]) for x in r["records"]])
    return stamps - stamps[0] if len(stamps) else stamps


def _save(plt: Any, fig: Any, path: Path, dpi: int = 100) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_runs(runs: list[dict[str, Any]], out: Path) -> list[Path]:
    plt = _plt()
    paths = []
    # T over time, with the link trace underneath
    fig, (ax, axl) = plt.subplots(2, 1, figsize=(10, 7), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    for r in runs:
        t = _times(r)
        T = np.array([float(x["interarrival"]) if x.get("interarrival") not in (None, "") else np.nan
                      for x in r["records"]])
        ax.plot(t, T, ".", ms=3, label=f"{r['policy']} ({r['trace'] if r['policy'] != 'local' else 'local'})")
        if r.get("link"):
            sec = np.array([int(x["second"]) for x in r["link"]])
            axl.step(sec, [float(x["trace_up_mbps"]) * (1 - int(x["outage"])) for x in r["link"]],
                     where="post", color="0.3", lw=1)
            axl.plot(sec + 0.5, [float(x["up_mbps"]) for x in r["link"]], ".", ms=3,
                     label=f"delivered, {r['policy']}")
    ax.axhline(0.11, color="r", lw=0.8, ls="--", label="T = 0.11 s")
    ax.set_ylabel("inter-arrival T at the edge [s]")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    axl.set_ylabel("link up [Mbps]")
    axl.set_xlabel("time [s]")
    axl.legend(fontsize=7)
    paths.append(_save(plt, fig, out / "T_over_time.png"))
    # Points per scan
    fig, ax = plt.subplots(figsize=(10, 4))
    for r in runs:
        n = [float(x["n_sent"]) if x.get("n_sent") not in (None, "") else np.nan for x in r["records"]]
        ax.plot(_times(r), n, lw=1, label=r["policy"])
    ax.set_xlabel("time [s]")
    ax.set_ylabel("points per scan sent")
    ax.legend(fontsize=8)
    paths.append(_save(plt, fig, out / "points_per_scan.png"))
    # Top view of each map
    with_maps = [r for r in runs if r["map_sample"] is not None and len(r["map_sample"])]
    if with_maps:
        fig, axes = plt.subplots(1, len(with_maps), figsize=(5 * len(with_maps), 5), squeeze=False)
        for ax, r in zip(axes[0], with_maps, strict=True):
            m = r["map_sample"]
            ax.scatter(m[:, 0], m[:, 1], s=0.1, c="0.3", linewidths=0)
            ax.set_aspect("equal")
            ax.set_title(f"{r['policy']}: {r['map_points']:,} pts", fontsize=9)
        paths.append(_save(plt, fig, out / "maps.png", dpi=90))
    return paths


def save_report(out: Path, text: list[str], runs: list[dict[str, Any]], figures: list[Path]) -> Path:
    """``out/report.md``: the text, then the runs it came from and the figures."""
    tail = ["Runs: " + ", ".join(f"`{r['folder']}`" for r in runs), "",
            *[f"![{p.stem}]({p.name})" for p in figures], ""]
    path = out / "report.md"
    path.write_text("\n".join([*text, *tail]))
    return path


def write_report(folders: list[Path], out: Path | None = None) -> Path:
    folders = expand_runs(folders)
    runs = [load_run(f) for f in folders]
    rows = aggregate(runs)
    out = out or Path(os.path.commonpath([str(f.resolve()) for f in folders]))
    if out.resolve() in [f.resolve() for f in folders] and len(folders) == 1:
        out = folders[0]
    out.mkdir(parents=True, exist_ok=True)
    figures = plot_runs([r["runs"][0] for r in rows], out)  # one run per row: readable plots
    refs = sorted({r["trajectory_reference"] for r in runs if r.get("trajectory_reference")})
    text = [
        "# Scan offloading: Table I layout",
        "",
        table_markdown(rows),
        "",
        "S: mean encoded scan size sent; received: scans that reached the edge, of those the sensor",
        "produced (and of those the robot sent: it holds a scan back while 3 are unanswered); T̄: mean",
        "inter-arrival at the edge (edge clock); robot CPU: CPU time of the robot's offload path per",
        "scan sent (median; for local, KISS-ICP and the map per scan); skipped: scans the robot chose",
        "not to send (the next one says so, the edge bridges the gap); on time for slot: received",
        "scans with T ≤ 1.1 × the period the robot meant them to take (1-byte: a stream of 1-byte",
        "scans every period alone on the run's emulated link, what its jitter leaves, the mean of",
        "20 seeds; `python -m zoffload.lab.link.ceiling`);",
        "+ kept local in outages:",
        "delivered or skipped plus the scans the robot registered itself while its link was out;",
        "+ backfilled: delivered or skipped plus the scans the edge registered from the backfill of",
        "an attach after an outage (codec version 9; its `backfilled_seqs`), each scan once; vs local",
        "and trajectory vs local, same scans: against the local run of the same scans (source and",
        "count); the latter (simulator) is each run's trajectory error over the scans in its edge's",
        "trajectory (registered there, or the robot's own poses an attach handed over) against the",
        "local runs' error over those same scans, mean ratio − 1 ± sd. Rows of several runs show",
        "mean ± sd over the runs that have the figure (a run whose final map query went unanswered",
        "has no map or trajectory); runs cut short are named. The paper's rows are its own figures",
        "(LeGO-LOAM map points, a real Wi-Fi link), ours come from the runs listed below.",
        "",
        "Trajectory reference: " + "; ".join(refs) + ".",
        "",
    ]
    return save_report(out, text, runs, figures)
