"""Reading a run's frames.csv back: every column the robot writes, words kept as words."""

from __future__ import annotations

import csv
from pathlib import Path

from zoffload.lab.eval.detection import load_frames
from zoffload.robot.framelog import FRAME_FIELDS


def test_frames_csv_with_every_column_the_robot_writes_loads(tmp_path: Path) -> None:
    # the detect sweep died on the "edge" column (the answering edge's id) once it was added
    row = {k: "1.5" for k in FRAME_FIELDS}
    row.update(side="edge", status="edge_done", edge="edge1", probe="0")
    with open(tmp_path / "frames.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[*FRAME_FIELDS, "later_column"])
        w.writeheader()
        w.writerow({**row, "later_column": "some-text"})
        w.writerow({**row, "seq": "2", "edge": "", "later_column": ""})
    first, second = load_frames(tmp_path)
    assert "edge" in FRAME_FIELDS and first["edge"] == "edge1" and first["status"] == "edge_done"
    assert first["seq"] == 1.5 and first["probe"] == 0.0 and first["later_column"] == "some-text"
    assert second["seq"] == 2.0 and second["edge"] == ""
