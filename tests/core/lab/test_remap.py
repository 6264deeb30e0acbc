"""``python -m zoffload.lab.remap``: a run's answered scans registered again offline."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from zoffload.lab.remap import main, remap
from zoffload.mapping import mapper
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")


def _run(folder: Path, rows: list[dict[str, object]], recorded: float = 0.1,
         fleet: dict[str, object] | None = None) -> Path:
    folder.mkdir()
    cfg: dict[str, object] = {"scans": "sim", "voxel_range": [0.01, 0.07], "replay": "once", "sim_seed": 0}
    if fleet is not None:
        cfg["fleet"] = fleet
    (folder / "robot_config.yaml").write_text(yaml.safe_dump(cfg))
    with open(folder / "robot_scans.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["seq", "index", "voxel", "coding", "status", "pose_source"])
        w.writeheader()
        w.writerows(rows)
    (folder / "results.json").write_text(json.dumps({"trajectory_error": {"ate_rmse": recorded}}))
    return folder


def test_a_run_is_registered_again_from_its_answered_scans(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                           ) -> None:
    rows: list[dict[str, object]] = []
    for i in range(40):
        lost = 20 <= i < 23  # three scans lost on the way: the mapper bridges the gap
        rows.append({"seq": i, "index": i, "voxel": "" if lost else (0.0 if i % 2 else 0.05),
                     "status": "source:window" if lost else "acked", "pose_source": "" if lost else "edge"})
    out = remap(_run(tmp_path / "run1", rows, recorded=0.123))
    assert out["scans"] == 37 and out["recorded_ate_rmse"] == 0.123
    assert out["reference"] == "simulator ground truth"
    assert out["ate_rmse"] is not None and 0 < out["ate_rmse"] < 0.2, out
    assert out["after_gap"] == 1 and sum(out["gap_guesses_kept"].values()) == 1, out  # one gap

    # the robot's own poses stood in for an outage: without robot_poses.npz nothing to hand over
    rows[30]["pose_source"] = "local"
    with pytest.raises(ValueError, match="local odometry"):
        remap(_run(tmp_path / "run2", rows))
    assert main([str(tmp_path / "run2"), str(tmp_path / "nothing")]) == 1
    err = capsys.readouterr().err
    assert "local odometry" in err and "no robot_config.yaml" in err


def test_an_outage_the_robot_bridged_is_handed_over_from_its_own_poses(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Scans 20-27 were registered by the robot's odometry in an outage (``pose_source`` local):
    the replay predicts scan 28 from the robot's newest pose, as the edge did from its prior. A
    robot pose turned 20 degrees shows in the replay's trajectory (the mapper's spare guesses left
    out: after the failed registration they find the scan again); ``edge_bridges`` ignores it."""
    monkeypatch.setattr(mapper, "GAP_LOST", 0.0)  # no spare guesses
    src = SimulatedSource()
    rows: list[dict[str, object]] = []
    for i in range(45):
        out = 20 <= i < 28
        rows.append({"seq": i, "index": i, "voxel": 0.05, "coding": "q16d",
                     "status": "local" if out else "acked", "pose_source": "local" if out else "edge"})
    truth = [src.read(i).gt_pose for i in range(45)]
    poses = np.array([np.linalg.inv(truth[0]) @ t for t in truth])  # the robot's: the edge's frame
    results = {}
    for name, yaw in (("right", 0.0), ("off", np.radians(20))):
        folder = _run(tmp_path / name, rows)
        own = poses.copy()
        c, s = np.cos(yaw), np.sin(yaw)
        own[27, :3, :3] = own[27, :3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        np.savez(folder / "robot_poses.npz", acked_seqs=np.arange(45), acked_poses=own,
                 gt_seqs=np.arange(45), gt_poses=np.array(truth))
        results[name] = remap(folder)
        assert results[name]["handovers"] == 1 and results[name]["bridged_by"] == "robot"
    assert results["right"]["ate_rmse"] < 0.2, results
    assert results["off"]["ate_rmse"] > results["right"]["ate_rmse"] + 0.3, results
    alone = remap(tmp_path / "off", edge_bridges=True)
    assert alone["handovers"] == 0 and alone["bridged_by"] == "edge" and alone["ate_rmse"] < 0.5, alone


def test_a_backfill_the_robot_kept_is_registered_as_its_edge_did(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``fleet.backfill_scans`` in the run's settings the replay registers the newest of the
    outage's scans at the backfill's grid (here 5 of 8, at the local odometry's 0.8 m), and hands
    over only the gap before them; the robot's own pose of the last, turned 20 degrees, no longer
    matters (the mapper's spare guesses left out, as above). ``backfill=False`` replays it as a
    robot without a backfill."""
    monkeypatch.setattr(mapper, "GAP_LOST", 0.0)
    src = SimulatedSource()
    rows: list[dict[str, object]] = []
    for i in range(45):
        out = 20 <= i < 28
        rows.append({"seq": i, "index": i, "voxel": "" if out else 0.05, "coding": "" if out else "q16d",
                     "status": "local" if out else "acked", "pose_source": "local" if out else "edge"})
    truth = [src.read(i).gt_pose for i in range(45)]
    own = np.array([np.linalg.inv(truth[0]) @ t for t in truth])
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    own[27, :3, :3] = own[27, :3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    folder = _run(tmp_path / "filled", rows, fleet={"attach": True, "backfill_scans": 5})
    np.savez(folder / "robot_poses.npz", acked_seqs=np.arange(45), acked_poses=own,
             gt_seqs=np.arange(45), gt_poses=np.array(truth))
    filled = remap(folder)
    assert filled["backfilled"] == 5 and filled["scans"] == 37 + 5 and filled["handovers"] == 1, filled
    assert filled["ate_rmse"] < 0.2, filled
    jumped = remap(folder, backfill=False)
    assert jumped["backfilled"] == 0 and jumped["scans"] == 37
    assert jumped["ate_rmse"] > filled["ate_rmse"] + 0.2, (filled, jumped)


def test_the_replayed_backfill_is_what_the_edge_registered_when_it_says() -> None:
    """The robot marks the scans of a backfill an edge accepted, and the grid each went at; the
    edge lists those it registered (``backfilled_seqs``): the replay takes the marked ones it
    lists, at their grid (the settings' where a record does not say)."""
    from zoffload.lab.remap import _backfill

    rows = [{"seq": str(i), "index": str(i), "status": "local", "pose_source": "local",
             "backfill": "1" if 20 <= i < 28 else "", "backfill_voxel": "0.2" if 20 <= i < 24 else ""}
            for i in range(30)]
    cfg = {"fleet": {"attach": True, "backfill_scans": 50, "backfill_voxel": 0.8}}
    assert sorted(_backfill(rows, cfg, 40.0)) == list(range(20, 28))
    assert sorted(_backfill(rows, cfg, 40.0, {22, 23, 29})) == [22, 23]
    assert [v for _, v, _ in _backfill(rows, cfg, 40.0).values()] == [0.2] * 4 + [0.8] * 4
