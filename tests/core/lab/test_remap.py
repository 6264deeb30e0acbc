"""``python -m zoffload.lab.remap``: a run's answered scans registered again offline."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import yaml

from zoffload.lab.remap import main, remap

pytest.importorskip("kiss_icp")


def _run(folder: Path, rows: list[dict[str, object]], recorded: float = 0.1) -> Path:
    folder.mkdir()
    (folder / "robot_config.yaml").write_text(yaml.safe_dump({"scans": "sim", "voxel_range": [0.01, 0.07],
                                                              "replay": "once", "sim_seed": 0}))
    with open(folder / "robot_scans.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["seq", "index", "voxel", "status", "pose_source"])
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

    # the robot's own poses stood in for an outage: not replayable from the CSV, refused
    rows[30]["pose_source"] = "local"
    with pytest.raises(ValueError, match="local odometry"):
        remap(_run(tmp_path / "run2", rows))
    assert main([str(tmp_path / "run2"), str(tmp_path / "nothing")]) == 1
    err = capsys.readouterr().err
    assert "local odometry" in err and "no robot_config.yaml" in err
