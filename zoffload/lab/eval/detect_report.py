"""``zoffload report`` for ``experiment detect`` runs: the offloading thesis' Tables 6.3–6.5 layout
(one table per link and robot CPU quota) with the thesis' own figures beside ours where the thesis
states them, a summary of our strategy against the best fixed one, and plots like its Figures
6.5–6.12 (AP, RTT, processed frames, CPU, bandwidth against the ratio).

Repeated runs of one experiment (same link, quota, strategy, encoding, images and frame count)
make one row: every figure as mean ± sd (sample standard deviation) over its ``n`` runs.
"""

from __future__ import annotations

import json
import math
import os
import statistics
from pathlib import Path
from typing import Any

from zoffload.lab.eval.plots import _plt
from zoffload.lab.eval.report import save_report

# The thesis' figures this project knows (asynchronous AP50, %); the rest of its tables are not
# restated here rather than guessed.
THESIS_AP: dict[tuple[str, str], float] = {
    ("none", "edge"): 76.5,
    ("none", "thesis"): 77.0,
    ("detect-capped", "ratio:0.5"): 54.0,
    ("detect-capped", "thesis"): 23.0,
}
LINK_NAMES = {"none": "unconstrained (Table 6.3)", "detect-capped": "capped 160 Mbps (Table 6.4)",
              "wifi-locations": "fluctuating Wi-Fi (Table 6.5)",
              "mmwave-blockage": "5G mmWave with blockages (held out until 2026-12-07, tuned on since)"}
ROW_NAMES = {"robot": "Robot only", "edge": "Edge only", "thesis": "Dynamic (thesis rule)",
             "dynamic": "Dynamic (ours, before)", "dispatch": "**Dispatch (ours)**",
             "dynamic@jpeg": "Dynamic (ours, before) + JPEG", "dispatch@jpeg": "Dispatch (ours) + JPEG"}
OURS = "dispatch"
ENCODING_NAMES = {"bgr8": "raw", "jpeg": "JPEG", "auto": "encoding per frame"}
SHRUNK = "+shrunk"  # frames shrunk to the edge detector's input (``run_label``)
FIGURES = ["ap50_async", "ap50_sync", "robot_rtt_ms", "edge_rtt_ms", "processed_pct", "offloaded_pct",
           "skipped_pct", "cpu_process_pct", "power_w", "mbps_out", "mean_lateness_frames"]


def is_detect_run(folder: Path) -> bool:
    try:
        return json.loads((folder / "results.json").read_text()).get("kind") == "detect"
    except (OSError, ValueError):
        return False


def split(strategy: str) -> tuple[str, str]:
    """``ratio:0.7@jpeg`` → (``ratio:0.7``, ``jpeg``); without ``@``, frames go raw (``bgr8``)."""
    base, _, encoding = strategy.partition("@")
    return base, encoding or "bgr8"


def run_label(strategy: str, encoding: str, send_size: str = "camera") -> str:
    """``S`` (raw frames), ``S@jpeg``, ``S@auto``; ``+shrunk`` when frames were shrunk to the edge
    detector's input (``S@bgr8+shrunk`` for raw ones): the report's row names."""
    if send_size == "detector":
        return f"{strategy}@{encoding}{SHRUNK}"
    return strategy if encoding == "bgr8" else f"{strategy}@{encoding}"


def _frames(encoding: str) -> tuple[str, bool]:
    """``jpeg+shrunk`` → (``jpeg``, True): the encoding, and whether frames were shrunk."""
    return encoding.removesuffix(SHRUNK), encoding.endswith(SHRUNK)


def _order(strategy: str) -> float:
    """Robot only 0, ratio r, edge only 1, then the rules; a JPEG variant right after its raw one."""
    base, encoding = split(strategy)
    if base == "robot":
        order = 0.0
    elif base.startswith("ratio:"):
        try:
            order = float(base.split(":", 1)[1])
        except ValueError:
            order = 5.0
    else:
        order = {"edge": 1.0, "thesis": 2.0, "dynamic": 3.0, "dispatch": 4.0}.get(base, 5.0)
    shrunk, kind = _frames_key(encoding)
    return order + 0.001 * (kind + 3 * shrunk)


def offload_ratio(strategy: str) -> float | None:
    """The x position of a static strategy in the thesis' plots (robot 0, ratio r, edge 1)."""
    order = _order(split(strategy)[0])
    return order if order <= 1.0 else None


def is_fixed(strategy: str, encoding: str = "bgr8") -> bool:
    """Robot only, a fixed ratio or edge only, with frames in ``encoding``: the baselines ours must
    beat (ours on raw frames against the raw ones, ours with JPEG frames against the JPEG ones;
    ours choosing the encoding per frame, ``auto``, against both). Frames shrunk to the edge
    detector's input (``+shrunk``) only against fixed strategies whose frames were shrunk too."""
    kind, shrunk = _frames(encoding)
    kinds: tuple[str, ...] = ("bgr8", "jpeg") if kind == "auto" else (kind,)
    if shrunk:
        kinds = tuple(k + SHRUNK for k in kinds)
    base, got = split(strategy)
    # Robot only sends no frames: its plain row stands for every encoding and size
    return offload_ratio(strategy) is not None and (got in kinds or (base == "robot" and got == "bgr8"))


def frames_name(encoding: str) -> str:
    """How ours sent its frames and what it is set against, e.g. for ``jpeg+shrunk`` "JPEG frames,
    shrunk to the edge's input, against the JPEG ones, shrunk"."""
    kind, shrunk = _frames(encoding)
    name = {"bgr8": "raw frames, against the raw ones", "jpeg": "JPEG frames, against the JPEG ones",
            "auto": "encoding per frame, against raw and JPEG ones"}.get(kind, kind)
    if shrunk:
        what, against = name.split(", ", 1) if ", " in name else (name, "")
        return f"{what}, shrunk to the edge's input{', ' + against + ', shrunk' if against else ''}"
    return name


def _frames_key(encoding: str) -> tuple[bool, int]:
    """Whole frames before shrunk ones; raw, JPEG, per frame."""
    kinds = ["bgr8", "jpeg", "auto"]
    kind, shrunk = _frames(encoding)
    return shrunk, kinds.index(kind) if kind in kinds else len(kinds)


def _frames_order(row: dict[str, Any]) -> tuple[bool, int]:
    return _frames_key(split(row["strategy"])[1])


def row_name(strategy: str) -> str:
    if strategy in ROW_NAMES:
        return ROW_NAMES[strategy]
    base, encoding = split(strategy)
    name = ROW_NAMES.get(base, base.replace("ratio:", "Ratio "))
    kind, shrunk = _frames(encoding)
    if shrunk:
        return f"{name} + {ENCODING_NAMES.get(kind, kind)}, shrunk"
    return name if encoding == "bgr8" else f"{name} + {ENCODING_NAMES.get(encoding, encoding)}"


# What a detection run ran with besides its link, strategy and images, and the defaults (the lab's
# DetectExperiment takes its own from here); runs older than 2026-12-06 do not say and ran these,
# but for the settings of RAN_BEFORE, which they ran as it says. ``environment``: the settings
# ZOFFLOAD_ROBOT__* / ZOFFLOAD_EDGE__* variables gave the daemons (recorded since 2026-12-07: an
# older run shows none, though the overflow-off runs of that day had one, in their own folder).
# ``extra`` and ``environment`` are objects, as in a scan or fleet run's results.json; the runs of
# 2026-12-06 and 07 stored them as JSON text, read alike.
RUN_SETTINGS: dict[str, Any] = {"edge_model": "picodet-s", "edge_threads": 1, "local_model": "nanodet-m",
                                "extra": {}, "edge_apart": True, "environment": {}}
# a setting added after runs were made, and what a run that does not name it ran with: the edge
# on the robot's cores (``edge_apart``, the default since 2026-12-06)
RAN_BEFORE: dict[str, Any] = {"edge_apart": False}


def _setting_text(value: Any) -> str:
    """A run setting as compared and shown: an object (or the JSON text older runs stored) as
    sorted JSON, anything else as text."""
    if isinstance(value, str) and value.startswith(("{", "[")):
        try:
            value = json.loads(value)
        except ValueError:
            return value
    if isinstance(value, dict | list):
        return json.dumps(value, sort_keys=True, default=str)
    return str(value)


def run_settings(r: dict[str, Any]) -> tuple[str, ...]:
    return tuple(_setting_text(r.get(k, RAN_BEFORE.get(k, default))) for k, default in RUN_SETTINGS.items())


def settings_note(r: dict[str, Any]) -> str:
    """What a row ran with that is not the defaults ("" for none): named beside it."""
    defaults = map(_setting_text, RUN_SETTINGS.values())
    diff = [f"{k} {v}" for k, v, d in zip(RUN_SETTINGS, run_settings(r), defaults, strict=True) if v != d]
    return f" ({', '.join(diff)})" if diff else ""


def _key(r: dict[str, Any]) -> tuple[str, ...]:
    """What makes runs one experiment: link, quota, strategy, images, frames, and the models, the
    edge's threads and further settings (``run_settings``)."""
    return (r["trace"], str(r.get("cpu_quota")), r["strategy"], str(r.get("images", "coco-clips")),
            str(r.get("max_frames")), *run_settings(r))


def settled(run: dict[str, Any]) -> bool:
    """Every frame of the run in exactly one final bucket: its ledger balanced with none left
    ``pending`` (the ledger counts a pending frame as balanced while the run goes on)."""
    return bool(run.get("balanced")) and not (run.get("balance") or {}).get("pending")


def aggregate(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per experiment: its runs' figures averaged (``n``, ``sd`` per figure, ``runs``)."""
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for r in runs:
        groups.setdefault(_key(r), []).append(r)
    rows = []
    for members in groups.values():
        row = dict(members[0], n=len(members), sd={}, runs=members,
                   balanced=all(settled(m) for m in members))
        for key in FIGURES:
            values = [float(m[key]) for m in members if isinstance(m.get(key), int | float)
                      and not isinstance(m.get(key), bool) and math.isfinite(m[key])]
            row[key] = statistics.fmean(values) if values else None
            if len(values) > 1:
                row["sd"][key] = statistics.stdev(values)
        rows.append(row)
    return rows


def _cell(r: dict[str, Any], key: str, spec: str) -> str:
    value = r.get(key)
    if value is None:
        return "–"
    sd = r.get("sd", {}).get(key)
    return format(value, spec) + (f" ± {format(sd, spec)}" if sd is not None else "")


def _quota(r: dict[str, Any]) -> str:
    return "no quota" if r.get("cpu_quota") in (None, 0) else f"{r['cpu_quota']:g} core"


def table(rows: list[dict[str, Any]], trace: str, quota: str) -> str:
    lines = [
        f"### {LINK_NAMES.get(trace, trace)}, robot {quota}",
        "",
        "| strategy | runs | async AP50 % | thesis async AP % | sync AP50 % | robot RTT ms | edge RTT ms "
        "| processed % | offloaded % | skipped % | robot CPU % | power W | Mbps out |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: _order(r["strategy"])):
        name = row_name(r["strategy"]) + settings_note(r)
        power = _cell(r, "power_w", ".1f") if r.get("power_available") else "n/a"
        lines.append(
            f"| {name} | {r['n']} | {_cell(r, 'ap50_async', '.1f')} "
            f"| {THESIS_AP.get((trace, r['strategy']), '–')} "
            f"| {_cell(r, 'ap50_sync', '.1f')} | {_cell(r, 'robot_rtt_ms', '.0f')} "
            f"| {_cell(r, 'edge_rtt_ms', '.0f')} | {_cell(r, 'processed_pct', '.0f')} "
            f"| {_cell(r, 'offloaded_pct', '.0f')} | {_cell(r, 'skipped_pct', '.0f')} "
            f"| {_cell(r, 'cpu_process_pct', '.0f')} | {power} | {_cell(r, 'mbps_out', '.0f')} |")
    return "\n".join(lines)


def targets(rows: list[dict[str, Any]]) -> str:
    """Ours against the best fixed strategy (any ratio, robot only, edge only) per link and quota."""
    lines = ["### Ours against the best fixed strategy (async AP50 %, mean ± sd over the runs)", "",
             "| link | robot | dispatch (ours) | best fixed | edge only | ours − best fixed "
             "| ours − edge only |",
             "|---|---|---|---|---|---|---|"]
    for (trace, quota), group in _cells(rows):
        for ours in sorted((r for r in group if split(r["strategy"])[0] == OURS), key=_frames_order):
            encoding = split(ours["strategy"])[1]
            fixed = [r for r in group  # run with the same models, threads and settings
                     if is_fixed(r["strategy"], encoding) and r.get("ap50_async") is not None
                     and run_settings(r) == run_settings(ours)]
            if ours.get("ap50_async") is None or not fixed:
                continue
            best = max(fixed, key=lambda r: r["ap50_async"])
            edges = [r for r in fixed if split(r["strategy"])[0] == "edge"]
            edge = max(edges, key=lambda r: r["ap50_async"]) if edges else None
            name = row_name(best["strategy"]).replace("Ratio ", "ratio ")
            vs_edge = f"{ours['ap50_async'] - edge['ap50_async']:+.1f}" if edge else "–"
            frames = "" if encoding == "bgr8" else f" ({frames_name(encoding)})"
            lines.append(f"| {LINK_NAMES.get(trace, trace)}{frames}{settings_note(ours)} | {quota} "
                         f"| {_cell(ours, 'ap50_async', '.1f')} "
                         f"| {name}: {_cell(best, 'ap50_async', '.1f')} "
                         f"| {_cell(edge, 'ap50_async', '.1f') if edge else '–'} "
                         f"| {ours['ap50_async'] - best['ap50_async']:+.1f} | {vs_edge} |")
    lines += ["", "The best fixed strategy is the highest of eleven noisy means, so it is biased upwards; "
              "read a margin within the runs' spread as a tie."]
    return "\n".join(lines)


def _traces(rows: list[dict[str, Any]]) -> list[str]:
    known = list(LINK_NAMES)
    return sorted({r["trace"] for r in rows}, key=lambda t: known.index(t) if t in known else len(known))


def _cells(rows: list[dict[str, Any]]) -> list[tuple[tuple[str, str], list[dict[str, Any]]]]:
    """Rows grouped by link and quota, in the thesis' link order, the weaker robot first."""
    quotas = sorted({_quota(r) for r in rows}, key=lambda q: (q == "no quota", q))
    return [((t, q), [r for r in rows if r["trace"] == t and _quota(r) == q])
            for q in quotas for t in _traces(rows) if any(r["trace"] == t and _quota(r) == q for r in rows)]


def plot(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    plt = _plt()
    metrics = [("ap50_async", "asynchronous AP50 [%]", "ap_vs_ratio"),
               ("edge_rtt_ms", "edge RTT [ms]", "edge_rtt_vs_ratio"),
               ("robot_rtt_ms", "robot RTT [ms]", "robot_rtt_vs_ratio"),
               ("processed_pct", "processed frames [%]", "processed_vs_ratio"),
               ("cpu_process_pct", "robot CPU [%]", "cpu_vs_ratio"),
               ("mbps_out", "robot outgoing [Mbps]", "mbps_vs_ratio")]
    quotas = sorted({_quota(r) for r in rows})
    paths = []
    for quota in quotas:
        rs_q = [r for r in rows if _quota(r) == quota]
        suffix = "" if len(quotas) == 1 else "_" + quota.replace(" ", "")
        for key, label, name in metrics:
            fig, ax = plt.subplots(figsize=(7, 4))
            for i, trace in enumerate(_traces(rs_q)):
                rs = [r for r in rs_q if r["trace"] == trace]
                pts = sorted((x, r[key], r["sd"].get(key, 0.0)) for r in rs
                             if is_fixed(r["strategy"]) and r.get(key) is not None
                             and (x := offload_ratio(r["strategy"])) is not None)
                color = f"C{i}"
                if pts:
                    ax.errorbar([p[0] for p in pts], [p[1] for p in pts], yerr=[p[2] for p in pts], fmt="o-",
                                color=color, capsize=2, label=LINK_NAMES.get(trace, trace))
                for r in rs:  # lines: the rules
                    if r["strategy"] in ("thesis", OURS) and r.get(key) is not None:
                        ax.axhline(r[key], color=color, ls="--" if r["strategy"] == OURS else ":", lw=1)
            ax.set_xlabel("offloading ratio (0 = robot only, 1 = edge only); dashed: ours, "
                          "dotted: thesis rule")
            ax.set_ylabel(label)
            ax.set_title(f"robot {quota}", fontsize=9)
            ax.legend(fontsize=7)
            fig.tight_layout()
            path = out / f"{name}{suffix}.png"
            fig.savefig(path, dpi=100)
            plt.close(fig)
            paths.append(path)
    return paths


def write_detect_report(folders: list[Path], out: Path | None = None) -> Path:
    runs = []
    for f in folders:
        r = json.loads((f / "results.json").read_text())
        r["folder"] = f
        runs.append(r)
    out = out or Path(os.path.commonpath([str(f.resolve()) for f in folders]))
    out.mkdir(parents=True, exist_ok=True)
    rows = aggregate(runs)
    figures = plot(rows, out)
    images = sorted({str(r.get("images", "coco-clips")) for r in rows})
    unbalanced = [str(m["folder"]) for r in rows for m in r["runs"] if not settled(m)]
    text = [
        "# Perception offloading: the thesis' Tables 6.3–6.5 layout",
        "",
        *[table(group, trace, quota) + "\n" for (trace, quota), group in _cells(rows)],
        targets(rows),
        "",
        f"Images: {', '.join(images)}. {len(runs)} runs in {len(rows)} rows; every frame in exactly one "
        f"bucket in {'all of them' if not unbalanced else 'all but ' + ', '.join(unbalanced)}.",
        "Async AP50: person AP at IoU 0.5 over every camera frame, each result scored against the ground",
        "truth of the frame current when the robot received it, frames never processed scoring nothing;",
        "sync AP50: processed frames against their own ground truth. RTT: camera capture to result on",
        "the robot. Skipped: frames no side could finish while fresh (ours). CPU: the robot process",
        "(one core = 100 %) under its CFS quota. Power: RAPL, n/a where the machine has none. Rows of",
        "several runs show mean ± sd. The thesis column holds the figures the thesis states for that",
        "cell; the others are left empty, not guessed.",
        "",
    ]
    return save_report(out, text, runs, figures)
