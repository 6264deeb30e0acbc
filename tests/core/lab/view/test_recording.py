"""The live view's logging layer: which Rerun entities each message becomes, read back from
Rerun's in-memory recording."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.core.lab.view.messages import (
    R,
    ack,
    detections,
    entities,
    frame,
    map_reply,
    pose,
    preview,
    status,
)
from zoffload.protocol import wire

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install 'zoffload[view]')")

from zoffload.lab.view.recording import EDGE_COLOR, LOCAL_COLOR, Recording  # noqa: E402


@pytest.fixture
def rec() -> Iterator[Any]:
    stream = rr.RecordingStream("zoffload-test", recording_id=uuid.uuid4())
    memory = stream.memory_recording()
    recording = Recording(stream, scan_period=0.5, trajectory_period=1.0, max_map_points=1000)
    recording.memory = memory  # type: ignore[attr-defined]
    yield recording
    memory.drain_as_bytes()  # what a test did not read (a sink dropped full warns)


def read(rec: Any, tmp: Path) -> dict[str, list[dict[str, Any]]]:
    rec.stream.flush()
    return entities(rec.memory.drain_as_bytes(), tmp)


def column(rows: list[dict[str, Any]], suffix: str) -> list[Any]:
    return [v for row in rows for k, v in row.items() if k.endswith(suffix) and v is not None]


def test_a_robot_session_becomes_the_documented_entities(rec: Any, tmp_path: Path) -> None:
    t = 1000.0
    rec.status(status(R, 10.0, acked=0, local_done=0, edge_done=0), t)
    rec.status(status(R, 11.0, acked=8, local_done=5, edge_done=20, cpu_process=30.0, mbps_out=12.0,
                      fallback=0.0, edges=1.0, ping_ms=3.0), t + 1)
    rec.scan(R, 5, np.array([[1.0, 0, 0], [0, 2.0, 0]]), t + 1.1)  # before its ack: waits for the pose
    for seq in range(1, 6):
        rec.ack(ack(R, seq, pose(float(seq), yaw=np.pi / 2)), t + 1.1 + seq * 0.1)
    rec.map(map_reply(R, 5000, [1, 2, 3, 4, 5]), t + 2)
    rec.preview(preview(R, 1, "local"), t + 2.1)
    rec.preview(preview(R, 2, "edge"), t + 2.2)
    rec.frame(frame(R, 7), t + 2.3)
    rec.detections(detections(R, 7), t + 2.4)
    rec.status(wire.Status(source="edge", id="e1", stamp=5.0, values={"mapping_robots": 1.0, "bad key": 2.0}),
               t + 2.5)
    got = read(rec, tmp_path)

    robot = {p.removeprefix(f"/robots/{R}/") for p in got if p.startswith(f"/robots/{R}/")}
    assert {"map", "trajectory", "pose", "scan", "camera", "camera/persons", "edge_frame",
            "edge_frame/detections"} <= robot
    assert {f"link/{n}" for n in ("rate_hz", "T_s", "rtt_ms", "voxel_m", "lost", "late", "edges", "fallback",
                                  "mbps_out", "ping_ms")} <= robot
    assert {f"perception/{n}" for n in ("on_edge", "local_fps", "edge_fps", "cpu_process",
                                        "edge_infer_ms")} <= robot
    assert {"mapping/proc_ms", "mapping/queue_ms", "mapping/map_points"} <= robot
    assert "/edges/e1/mapping_robots" in got and not any("bad" in p for p in got)

    # rate: 8 scans acked in the 1 s between the two statuses; the frames' sides likewise
    assert column(got[f"/robots/{R}/link/rate_hz"], "scalars") == [[8.0]]
    assert column(got[f"/robots/{R}/perception/edge_fps"], "scalars") == [[20.0]]
    # the scan placed by ITS ack's pose (x = 5, yaw 90°): (1,0,0) -> (5,1,0), (0,2,0) -> (3,0,0)
    (scan_xyz,) = column(got[f"/robots/{R}/scan"], "positions")
    np.testing.assert_allclose(scan_xyz, [[5, 1, 0], [3, 0, 0]], atol=1e-5)
    # the map decimated to max_map_points; the trajectory through the registered poses
    (map_xyz,) = column(got[f"/robots/{R}/map"], "positions")
    assert len(map_xyz) == 1000
    strips = column(got[f"/robots/{R}/trajectory"], "strips")
    np.testing.assert_allclose(strips[-1][0], [[s, 0, 0] for s in range(1, 6)], atol=1e-6)
    # where each frame ran: label and colour of its boxes, and the on_edge series
    labels = column(got[f"/robots/{R}/camera/persons"], "labels")
    assert labels == [["local 0.90", "local 0.50"], ["edge 0.90", "edge 0.50"]]
    colors = column(got[f"/robots/{R}/camera/persons"], "colors")
    rgba = [((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) for c in (colors[0][0], colors[1][0])]
    assert rgba == [LOCAL_COLOR, EDGE_COLOR]
    assert column(got[f"/robots/{R}/perception/on_edge"], "scalars") == [[0.0], [1.0]]
    assert column(got[f"/robots/{R}/camera"], "media_type") == [["image/jpeg"], ["image/jpeg"]]


def test_heavy_entities_are_throttled_and_a_scan_without_pose_waits(rec: Any, tmp_path: Path) -> None:
    t = 0.0
    rec.ack(ack(R, 1, pose(0.0)), t)
    rec.scan(R, 1, np.zeros((3, 3)), t)
    rec.scan(R, 1, np.zeros((3, 3)), t + 0.1)  # within scan_period: skipped
    rec.scan(R, 9, np.zeros((3, 3)), t + 1.0)  # no pose for seq 9 yet: kept, not logged
    for seq in range(2, 6):
        rec.ack(ack(R, seq, pose(float(seq))), t + seq * 0.1)  # trajectory at most once per second
    rec.ack(ack(R, 6, np.full((4, 4), np.nan)), t + 0.7)  # no pose: T logged, no trajectory point
    got = read(rec, tmp_path)
    assert len(column(got[f"/robots/{R}/scan"], "positions")) == 1
    assert len(column(got[f"/robots/{R}/trajectory"], "strips")) == 1
    assert len(column(got[f"/robots/{R}/link/T_s"], "scalars")) == 6
    assert list(rec.robots[R].track) == [1, 2, 3, 4, 5]
    rec.ack(ack(R, 9, pose(9.0)), t + 2.0)  # the waiting scan's pose: now it is logged
    assert len(column(read(rec, tmp_path)[f"/robots/{R}/scan"], "positions")) == 1


def test_a_preview_whose_boxes_and_scores_disagree_is_refused(rec: Any) -> None:
    p = preview(R, 1, "edge")
    bad = wire.Preview(robot=p.robot, seq=1, stamp=1.0, side="edge", width=64, height=48, jpeg=p.jpeg,
                       boxes=p.boxes, scores=p.scores[:1])
    with pytest.raises(ValueError, match="2 boxes, 1 scores"):
        rec.preview(bad, 0.0)


def test_the_layout_has_a_camera_and_link_view_per_robot(rec: Any) -> None:
    rec.robot("a")
    rec.robot("b")
    names: list[str] = []

    def walk(part: Any) -> None:
        if getattr(part, "name", None):
            names.append(str(part.name))
        for child in getattr(part, "contents", None) or []:
            walk(child)

    walk(rec.blueprint().root_container)
    assert {"world", "a camera", "a link", "a perception", "b camera", "b link"} <= set(names)
    assert "a edge frame" not in names
    rec.frame(frame("a", 1), 0.0)
    rec.detections(detections("a", 1), 0.0)  # the first edge frame adds its view
    names.clear()
    walk(rec.blueprint().root_container)
    assert "a edge frame" in names and "b edge frame" not in names


def test_edge_boxes_are_drawn_on_a_shrunk_frame_at_its_scale(rec: Any, tmp_path: Path) -> None:
    """The edge answers in the camera's pixels; a frame that travelled shrunk (here a 128 x 96
    camera frame sent at 64 x 48) is drawn as it travelled, so its boxes are scaled down to it."""
    import dataclasses

    shrunk = dataclasses.replace(frame(R, 7), camera_width=128, camera_height=96)
    rec.frame(shrunk, 1.0)
    rec.detections(detections(R, 7), 1.1)  # boxes [1, 2, 30, 40] in the camera's pixels
    got = read(rec, tmp_path)
    (boxes,) = [b for b in column(got[f"/robots/{R}/edge_frame/detections"], "half_sizes")]
    (centres,) = column(got[f"/robots/{R}/edge_frame/detections"], "centers")
    np.testing.assert_allclose(centres, [[(1 + 30) / 4, (2 + 40) / 4]], atol=1e-5)
    np.testing.assert_allclose(boxes, [[(30 - 1) / 4, (40 - 2) / 4]], atol=1e-5)
