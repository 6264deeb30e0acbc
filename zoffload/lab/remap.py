"""``python -m zoffload.lab.remap RUN...``: a scan experiment's run registered again, offline, by the
edge's mapper of this code: the scans the edge answered (``robot_scans.csv`` status ``acked``), in
sequence order, each voxel-downsampled at the size the robot sent it, into a ``RobotMapper`` sized
as the edge sizes it (``MapperRecipe.mapper``), and its trajectory error against the run's reference
(the simulator's ground truth, or KISS-ICP locally on every raw scan). It answers "would the
mapper of now have kept this run?" for a run that broke, without its link, and is deterministic
where a live run is not (which scans a link loses varies from run to run).

It leaves out what the run's messages carried besides the points: the q16 quantisation (a tenth of
the voxel, at least 5 mm), per-point times (deskew), and the robot's own poses while it bridged an
outage (``--attach`` runs send them as priors): a run with poses from local odometry is refused,
since its replay would not be the run. Remapping the run a mapper change is meant for shows the
change; remapping the runs it was not meant for shows what else it changes (README, the scale
policy's defaults rows).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from zoffload.edge.recipe import MapperRecipe
from zoffload.lab.eval.trajectory import trajectory_error
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.voxel import voxel_downsample
from zoffload.sources.base import open_scan_source


def _settings(folder: Path) -> dict[str, Any]:
    for name in ("robot_config.yaml", "robot.yaml"):  # the robot's effective settings, else the given
        path = folder / name
        if path.exists():
            loaded = yaml.safe_load(path.read_text())
            if isinstance(loaded, dict):
                return loaded
    raise ValueError(f"{folder}: no robot_config.yaml or robot.yaml (not a scan experiment's run)")


def remap(folder: Path) -> dict[str, Any]:
    """The run in ``folder`` registered again (module docstring): its trajectory error then, and
    the one the run recorded (``results.json``) beside it."""
    cfg = _settings(folder)
    scans_csv = folder / "robot_scans.csv"
    if not scans_csv.exists():
        raise ValueError(f"{folder}: no robot_scans.csv")
    with open(scans_csv) as f:
        rows = list(csv.DictReader(f))
    local = sum(1 for r in rows if r.get("pose_source") == "local")
    if local:
        raise ValueError(f"{folder}: {local} scans have poses from the robot's local odometry (an "
                         "outage it bridged): their priors are not in robot_scans.csv, so a replay would "
                         "not be the run")
    sent = {int(r["seq"]): (int(r["index"]), float(r["voxel"])) for r in rows
            if r.get("status") == "acked" and r.get("voxel") not in (None, "")}
    if len(sent) < 2:
        raise ValueError(f"{folder}: {len(sent)} answered scans, nothing to register")
    source = open_scan_source(str(cfg["scans"]), sim_seed=int(cfg.get("sim_seed") or 0))
    voxel_max = float((cfg.get("voxel_range") or [0.0, cfg.get("voxel") or 0.0])[1])
    mapper = MapperRecipe().mapper(source.max_range, voxel_max)  # the edge's defaults
    truth: dict[int, np.ndarray] = {}
    kept: dict[str, int] = {}
    for seq in sorted(sent):
        index, voxel = sent[seq]
        frame = source.read(index)
        if frame.gt_pose is not None:
            truth[seq] = frame.gt_pose
        points = drop_non_finite(frame.points)[0]
        reg = mapper.register(seq, voxel_downsample(points, voxel) if voxel > 0 else points)
        if reg.gap_motion:
            kept[reg.gap_motion] = kept.get(reg.gap_motion, 0) + 1
    if truth and len(truth) == len(sent):
        ref_seqs = np.array(sorted(truth), np.int64)
        ref_poses = np.array([truth[s] for s in ref_seqs])
        reference = "simulator ground truth"
    else:
        from zoffload.lab.scan_experiment import reference_trajectory

        ref_seqs, ref_poses = reference_trajectory(source, str(cfg.get("replay") or "once"), max(sent))
        reference = "KISS-ICP locally on every raw scan"
    seqs, poses = mapper.trajectory()
    err = trajectory_error(seqs, poses, ref_seqs, ref_poses)
    recorded = None
    results = folder / "results.json"
    if results.exists():
        recorded = (json.loads(results.read_text()).get("trajectory_error") or {}).get("ate_rmse")
    return {"run": str(folder), "scans": len(sent), "reference": reference,
            "ate_rmse": None if err is None else err.ate_rmse, "recorded_ate_rmse": recorded,
            "after_gap": mapper.after_gap, "guessed": mapper.guessed, "gap_guesses_kept": kept}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m zoffload.lab.remap", description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="a scan experiment's run folder (OUT/runN)")
    p.add_argument("--json", action="store_true", help="one JSON object per run instead of a line")
    a = p.parse_args(argv)
    failed = 0
    for folder in a.runs:
        try:
            out = remap(folder)
        except (ValueError, OSError) as exc:
            print(f"{folder}: {exc}", file=sys.stderr)
            failed += 1
            continue
        if a.json:
            print(json.dumps(out))
            continue

        def m(x: float | None) -> str:
            return "n/a" if x is None else f"{x:.3f} m"

        print(f"{folder}: {out['scans']} scans, trajectory error {m(out['ate_rmse'])} (the run recorded "
              f"{m(out['recorded_ate_rmse'])}; reference: {out['reference']}; {out['after_gap']} scans "
              f"after a gap, {out['guessed']} of them from several guesses, kept "
              f"{out['gap_guesses_kept'] or 'none'})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
