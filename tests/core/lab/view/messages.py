"""Wire messages a robot and an edge would send, for the live view's tests, and reading back what
the view recorded (Rerun's in-memory recording, or an .rrd file) as entity -> rows."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from zoffload.protocol import wire

R = "r1"


def pose(x: float, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    p = np.eye(4)
    p[:2, :2] = [[c, -s], [s, c]]
    p[:2, 3] = [x, y]
    return p


def status(robot: str, stamp: float, acked: float, **values: float) -> wire.Status:
    return wire.Status(source="robot", id=robot, stamp=stamp,
                       values={"acked": acked, "published": acked, "lost": 1.0, "late": 0.0,
                               "voxel": 0.05, "rtt_ms": 42.0, "map_points": 100.0, **values})


def ack(robot: str, seq: int, p: np.ndarray, map_points: int = 100) -> wire.ScanAck:
    return wire.ScanAck(robot=robot, seq=seq, send_stamp=1.0, status="ok", interarrival=0.1,
                        queue_time=0.001, proc_time=0.02, icp_time=0.015, map_points=map_points,
                        keypoints=50, sigma=0.1, pose=p, epoch=0, edge="e1")


def scan(robot: str, seq: int, points: np.ndarray) -> wire.Scan:
    return wire.Scan(robot=robot, seq=seq, send_stamp=1.0, capture_stamp=1.0, voxel=0.05, voxel_max=0.07,
                     max_range=100.0, n_raw=len(points), points=points.astype(np.float32))


def map_reply(robot: str, n: int, seqs: list[int], edge: str = "e1") -> wire.MapReply:
    pts = np.random.default_rng(0).uniform(-10, 10, (n, 3)).astype(np.float32)
    return wire.MapReply(robot=robot, scans=len(seqs), points=pts, seqs=np.array(seqs, np.int64),
                         poses=np.stack([pose(float(s)) for s in seqs]), edge=edge)


def jpeg(width: int = 64, height: int = 48) -> np.ndarray:
    import cv2

    img = np.zeros((height, width, 3), np.uint8)
    img[:, : width // 2] = (0, 128, 255)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return np.asarray(buf, np.uint8).ravel()


def preview(robot: str, seq: int, side: str, n_boxes: int = 2) -> wire.Preview:
    boxes = np.array([[5, 5, 20, 30], [30, 10, 50, 40]][:n_boxes], np.float32).reshape(-1, 4)
    return wire.Preview(robot=robot, seq=seq, stamp=1.0, side=side, width=64, height=48, jpeg=jpeg(),
                        boxes=boxes, scores=np.linspace(0.9, 0.5, len(boxes)).astype(np.float32))


def frame(robot: str, seq: int) -> wire.Frame:
    data = np.full(48 * 64 * 3, 100, np.uint8)
    return wire.Frame(robot=robot, seq=seq, send_stamp=1.0, capture_stamp=1.0, encoding="bgr8",
                      width=64, height=48, data=data)


def detections(robot: str, seq: int) -> wire.Detections:
    return wire.Detections(robot=robot, seq=seq, send_stamp=1.0, edge="e1", model="picodet-s", status="ok",
                           infer_time=0.03, queue_time=0.0, batch=1, detail="",
                           boxes=np.array([[1, 2, 30, 40]], np.float32), scores=np.array([0.8], np.float32),
                           classes=np.array([0], np.int32))


def entities(rrd: bytes | Path, tmp: Path) -> dict[str, list[dict[str, Any]]]:
    """Entity path -> its logged rows (component columns as Python values), from .rrd bytes or a file."""
    from rerun.chunk import RrdReader

    path = rrd if isinstance(rrd, Path) else tmp / "recording.rrd"
    if not isinstance(rrd, Path):
        path.write_bytes(rrd)
    out: dict[str, list[dict[str, Any]]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        components = [n for n in batch.schema.names if ":" in n]  # not the row ids and times
        rows = batch.select(components).to_pylist()
        out.setdefault(chunk.entity_path, []).extend(rows)
    return out
