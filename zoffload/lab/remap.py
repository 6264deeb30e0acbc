"""``python -m zoffload.lab.remap RUN...``: a scan experiment's run registered again, offline, by the
edge's mapper of this code: the scans the edge answered (``robot_scans.csv`` status ``acked``), in
sequence order, each voxel-downsampled at the size the robot sent it and, for a q16 coding, through
the codec at the robot's step (a tenth of the voxel, at least 5 mm), into a ``RobotMapper`` sized
as the edge sizes it (``MapperRecipe.mapper``), and its trajectory error against the run's reference
(the simulator's ground truth, or KISS-ICP locally on every raw scan). It answers "would the
mapper of now have kept this run?" for a run that broke, without its link, and is deterministic
where a live run is not (which scans a link loses varies from run to run).

Outages an ``--attach`` run bridged (scans with ``pose_source`` local) are handed over as the run
did: before the first answered scan after one, the mapper predicts from the robot's own newest pose
in the outage and its motion per scan then (``RobotMapper.predict_from``, what a ``Scan.prior`` or
an attach's local poses make the edge do), taken from ``robot_poses.npz`` relative to the robot's
record of the edge's pose before the outage (the replay's frame drifts from the run's). With
``--edge-bridges`` the mapper bridges those gaps itself instead (constant velocity and the gap
guesses), which separates what the robot's odometry handed over from what the scans carried.
A run whose robot kept a backfill (``fleet.backfill_scans`` in its settings, codec version 9)
handed its edge the scans it registered itself in each outage at a coarse grid with the attach
after it: the replay registers the newest ``backfill_scans`` of each stretch of such scans that
includes scans kept ``local`` (the robot was detached, so an attach followed) at that grid
(``fleet.backfill_voxel``, else the local odometry's voxel), as the edge did, or, where the
robot's records mark them (``backfill``), exactly those (of them, only those the edge registered
when its ``<robot>_edge.json`` lists them), at the grid each went at where the records say
(``backfill_voxel``: the link's room chose it since 2026-12-06), and registered from the grid the
edge registers a backfilled scan from (``BACKFILL_REGISTER_GRID`` times the mapper's voxel; the
edge's map takes all of its points, the replay measures only the trajectory). ``--no-backfill``
replays the run as a robot without it would have gone.
Per-point times (deskew) are left out.
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

from zoffload.edge.export import registered_backfill
from zoffload.edge.recipe import MapperRecipe
from zoffload.lab.eval.trajectory import trajectory_error
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.mapper import MOTION_SPAN, motion_per_scan
from zoffload.mapping.se3 import as_rigid
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol.coding import DECODERS, decode_q16d, encode_q16d, quant_step
from zoffload.robot.odometry import local_voxel_size
from zoffload.sources.base import open_scan_source


def _settings(folder: Path) -> dict[str, Any]:
    for name in ("robot_config.yaml", "robot.yaml"):  # the robot's effective settings, else the given
        path = folder / name
        if path.exists():
            loaded = yaml.safe_load(path.read_text())
            if isinstance(loaded, dict):
                return loaded
    raise ValueError(f"{folder}: no robot_config.yaml or robot.yaml (not a scan experiment's run)")


def _robot_poses(folder: Path, local: set[int]) -> dict[int, np.ndarray]:
    """Every pose the robot had per scan (``robot_poses.npz``: the edge's acked ones and its own);
    ``ValueError`` when the run bridged outages (``local``) and the file is not there."""
    path = folder / "robot_poses.npz"
    if not path.exists():
        if local:
            raise ValueError(f"{folder}: {len(local)} scans have poses from the robot's local odometry "
                             "(an outage it bridged) and there is no robot_poses.npz to hand them over from")
        return {}
    with np.load(path) as z:
        return dict(zip(z["acked_seqs"].tolist(), z["acked_poses"], strict=True))


def _as_sent(points: np.ndarray, voxel: float, coding: str, fraction: float) -> np.ndarray:
    """The scan as the edge got it: downsampled at ``voxel`` and, for a q16 coding, on the codec's
    grid (the robot's step: ``fraction`` of the voxel, at least 5 mm)."""
    cloud = voxel_downsample(points, voxel) if voxel > 0 else points
    if coding not in DECODERS or not len(cloud):
        return cloud
    origin, step, packed = encode_q16d(cloud, quant_step(voxel, fraction), level=None, widen=True)
    return decode_q16d(packed, len(cloud), origin, step)[0]


def _backfill(rows: list[dict[str, str]], cfg: dict[str, Any], max_range: float,
              registered: set[int] | None = None) -> dict[int, tuple[int, float, str]]:
    """The scans a backfill handed over (module docstring): seq -> (index, voxel, coding); of
    the marked ones only those the run's edge registered when it says which (``registered``)."""
    fleet = cfg.get("fleet") or {}
    keep = int(fleet.get("backfill_scans") or 0)
    if keep <= 0 or not fleet.get("attach", True):
        return {}
    voxel = float(fleet.get("backfill_voxel")
                  or min(local_voxel_size(max_range, fleet.get("local_voxel")), 10.0))
    if rows and "backfill" in rows[0]:  # the robot marked the scans an edge took in a backfill
        return {int(r["seq"]): (int(r["index"]), float(r.get("backfill_voxel") or voxel), "q16d")
                for r in rows if r.get("backfill") == "1" and r.get("status") != "acked"
                and (registered is None or int(r["seq"]) in registered)}
    stretches: list[list[dict[str, str]]] = []
    for r in sorted(rows, key=lambda r: int(r["seq"])):
        if r.get("pose_source") == "local" and r.get("status") != "acked":
            if stretches and int(stretches[-1][-1]["seq"]) == int(r["seq"]) - 1:
                stretches[-1].append(r)
            else:
                stretches.append([r])
    # a stretch handed over with an attach: one the robot spent detached (status local), not a bridge
    # its edge answered again (the ring is forgotten then)
    attached_after = [st for st in stretches if any(r.get("status") == "local" for r in st)]
    return {int(r["seq"]): (int(r["index"]), voxel, "q16d") for st in attached_after for r in st[-keep:]}


def _registered(folder: Path) -> set[int] | None:
    """The backfilled scans the run's edge registered (its ``<robot>_edge.json``), None when it
    does not say."""
    for path in sorted(folder.glob("*_edge.json")):
        try:
            registered = registered_backfill(json.loads(path.read_text()))
        except (OSError, ValueError):
            continue
        if registered is not None:
            return registered
    return None


def remap(folder: Path, edge_bridges: bool = False, backfill: bool = True) -> dict[str, Any]:
    """The run in ``folder`` registered again (module docstring): its trajectory error then, and
    the one the run recorded (``results.json``) beside it. ``edge_bridges``: the mapper bridges
    the outages the robot bridged in the run itself, from its own motion; ``backfill``: the
    mapper registers a backfill where the run's robot kept one."""
    cfg = _settings(folder)
    scans_csv = folder / "robot_scans.csv"
    if not scans_csv.exists():
        raise ValueError(f"{folder}: no robot_scans.csv")
    with open(scans_csv) as f:
        rows = list(csv.DictReader(f))
    local = {int(r["seq"]) for r in rows if r.get("pose_source") == "local"}
    robot = _robot_poses(folder, local)
    sent = {int(r["seq"]): (int(r["index"]), float(r["voxel"]), str(r.get("coding") or "f32")) for r in rows
            if r.get("status") == "acked" and r.get("voxel") not in (None, "")}
    if len(sent) < 2:
        raise ValueError(f"{folder}: {len(sent)} answered scans, nothing to register")
    source = open_scan_source(str(cfg["scans"]), sim_seed=int(cfg.get("sim_seed") or 0))
    voxel_max = float((cfg.get("voxel_range") or [0.0, cfg.get("voxel") or 0.0])[1])
    fraction = float(cfg.get("quant_fraction") or 0.1)
    mapper = MapperRecipe().mapper(source.max_range, voxel_max)  # the edge's defaults
    filled = (_backfill(rows, cfg, source.max_range, _registered(folder)) if backfill and not edge_bridges
              else {})
    sent.update(filled)
    truth: dict[int, np.ndarray] = {}
    kept: dict[str, int] = {}
    handovers, last = 0, None
    for seq in sorted(sent):
        index, voxel, coding = sent[seq]
        if last is not None and not edge_bridges and _hand_over(mapper, robot, local, last, seq):
            handovers += 1
        frame = source.read(index)
        if frame.gt_pose is not None:
            truth[seq] = frame.gt_pose
        points = _as_sent(drop_non_finite(frame.points)[0], voxel, coding, fraction)
        if seq in filled:  # registered as the edge registers a backfilled scan
            points = mapper.backfill_points(points)
        reg = mapper.register(seq, points)
        last = seq
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
            "after_gap": mapper.after_gap, "guessed": mapper.guessed, "gap_guesses_kept": kept,
            "handovers": handovers, "bridged_by": "edge" if edge_bridges or not local else "robot",
            "backfilled": len(filled)}


def _hand_over(mapper: Any, robot: dict[int, np.ndarray], local: set[int], last: int, seq: int) -> bool:
    """Before ``seq``, after a gap since ``last`` that the robot bridged: predict ``seq`` from the
    robot's newest own pose in the gap, moved into this replay's frame by the robot's record of
    the edge's pose of ``last``. Returns whether it was taken."""
    bridged = [q for q in local if last < q < seq and q in robot]
    if not bridged or last not in robot:
        return False
    q = max(bridged)
    seqs, poses = mapper.trajectory()
    if not len(seqs) or seqs[-1] != last:
        return False
    frame = poses[-1] @ np.linalg.inv(robot[last])  # the run's world into the replay's
    span = sorted(s for s in robot if q - MOTION_SPAN <= s <= q)
    delta = motion_per_scan(np.array(span), np.array([robot[s] for s in span]))
    if delta is None:
        return False
    return bool(mapper.predict_from(seq, q, as_rigid(frame @ robot[q]), delta, contest=True))  # as the edge


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m zoffload.lab.remap", description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="a scan experiment's run folder (OUT/runN)")
    p.add_argument("--json", action="store_true", help="one JSON object per run instead of a line")
    p.add_argument("--edge-bridges", action="store_true",
                   help="the mapper bridges the outages the robot bridged in the run itself (no handover)")
    p.add_argument("--no-backfill", action="store_true",
                   help="leave out the backfill the run's robot handed over (as a robot without one)")
    a = p.parse_args(argv)
    failed = 0
    for folder in a.runs:
        try:
            out = remap(folder, a.edge_bridges, not a.no_backfill)
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
              f"{out['gap_guesses_kept'] or 'none'}; outages bridged by the {out['bridged_by']}, "
              f"{out['handovers']} handed over, {out['backfilled']} scans backfilled)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
