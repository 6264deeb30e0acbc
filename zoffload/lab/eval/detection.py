"""The offloading thesis' detection metrics, from a robot run's ``frames.csv`` and
``detections.npz`` and the clip source's ground truth.

* asynchronous AP50 (person): every camera frame counts once. A processed frame's detections are
  scored against the ground truth of the frame that was *current when the robot received them*
  (the newest frame captured by then); a frame never processed (dropped at the camera, stale,
  lost on the link, refused by the edge) contributes its ground truth and no detections.
* synchronous AP50: processed frames only, each against its own ground truth (the detector's
  accuracy without the cost of latency or of the frames it never saw).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.lab.eval.ap import average_precision
from zoffload.sources.images import coco_person_boxes

TEXT_COLUMNS = ("side", "status", "edge")  # frames.csv columns that are words, not numbers


def _cell(key: str, value: str | None) -> Any:
    if value in ("", None) or key in TEXT_COLUMNS:
        return value
    try:
        return float(value)
    except ValueError:  # a column added later (as "edge" was): kept as text, not a crash
        return value


def load_frames(run: Path) -> list[dict[str, Any]]:
    with open(run / "frames.csv", newline="") as f:
        return [{k: _cell(k, v) for k, v in r.items()} for r in csv.DictReader(f)]


def load_persons(run: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    z = np.load(run / "detections.npz")
    seqs, counts = z["seqs"], z["counts"]
    ends = np.cumsum(counts)
    starts = ends - counts
    return {int(s): (z["boxes"][a:b], z["scores"][a:b]) for s, a, b in zip(seqs, starts, ends, strict=True)}


def camera_schedule(frames: list[dict[str, Any]], period: float) -> float:
    """Capture time of frame 0 on the robot's clock, fitted to the frames the loop saw (the camera
    delivers frame k at start + (k + 1) · period)."""
    offs = [f["capture"] - (f["seq"] + 1) * period for f in frames if isinstance(f.get("capture"), float)]
    if not offs:
        raise ValueError("no frame with a capture time")
    return float(np.median(offs))


def detection_metrics(run: Path, gt_boxes: Any, n_frames: int | None = None) -> dict[str, float]:
    """Async and sync AP50 of a run; ``gt_boxes(index)`` gives a frame's person boxes."""
    return score_frames(*load_run(run), gt_boxes, n_frames)


def load_run(run: Path) -> tuple[list[dict[str, Any]], dict[int, tuple[np.ndarray, np.ndarray]], float]:
    """A run's frames (``load_frames``), its processed frames' persons (``load_persons``) and the
    camera period."""
    return load_frames(run), load_persons(run), float(np.load(run / "detections.npz")["period"])


def score_frames(frames: list[dict[str, Any]], persons: dict[int, tuple[np.ndarray, np.ndarray]],
                 period: float, gt_boxes: Any, n_frames: int | None = None) -> dict[str, float]:
    """``detection_metrics`` of a run already read (``load_run``)."""
    start = camera_schedule(frames, period)
    by_seq = {int(f["seq"]): f for f in frames}
    n = n_frames if n_frames is not None else (max(by_seq) + 1 if by_seq else 0)
    empty = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))
    async_dets, async_gts, sync_dets, sync_gts = [], [], [], []
    lateness = []
    for seq in range(n):
        f = by_seq.get(seq)
        if f is not None and seq in persons and f["status"] in ("local_done", "edge_done"):
            det = persons[seq]
            current = int(math.floor((f["result"] - start) / period)) - 1  # newest frame by then
            current = min(max(current, seq), n - 1)
            lateness.append(current - seq)
            async_dets.append(det)
            async_gts.append(gt_boxes(current))
            sync_dets.append(det)
            sync_gts.append(gt_boxes(seq))
        else:
            async_dets.append(empty)
            async_gts.append(gt_boxes(seq))
    return {
        "ap50_async": 100 * average_precision(async_dets, async_gts),
        "ap50_sync": 100 * average_precision(sync_dets, sync_gts) if sync_dets else 0.0,
        "frames": n,
        "processed": len(sync_dets),
        "mean_lateness_frames": float(np.mean(lateness)) if lateness else float("nan"),
    }


def person_ap50(detector: Any, root: Path) -> float:
    """Person AP50 of ``detector`` (a ``detect.Detector``) on the annotated COCO images in
    ``root`` (``person_gt.json``), each image scored against its own boxes."""
    import cv2

    dets, gts = [], []
    for path, _, _, boxes in coco_person_boxes(root):
        d = detector.detect(cv2.imread(str(path))).of_class(0)
        dets.append((d.boxes, d.scores))
        gts.append(boxes)
    return average_precision(dets, gts)
