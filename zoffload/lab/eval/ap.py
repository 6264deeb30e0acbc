"""Average precision at IoU 0.5 for one class, COCO's way (greedy matching by score, 101-point
interpolated precision), over a list of frames that each have their own ground truth.

Scoring a frame's detections against *another* frame's ground truth (the asynchronous AP of the
offloading thesis: the truth of the frame current when the robot receives the result) is just a
matter of which ground truth is paired with which detections; frames never answered contribute
their ground truth and no detections, so they lower recall.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box in ``a`` (n, 4) with every box in ``b`` (m, 4), boxes as x1, y1, x2, y2."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    x1 = np.maximum(a[:, None, 0], b[None, :, 0])
    y1 = np.maximum(a[:, None, 1], b[None, :, 1])
    x2 = np.minimum(a[:, None, 2], b[None, :, 2])
    y2 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def average_precision(dets: Sequence[tuple[np.ndarray, np.ndarray]], gts: Sequence[np.ndarray],
                      iou: float = 0.5) -> float:
    """AP over frames: ``dets[i]`` = (boxes (n, 4), scores (n,)) scored against ``gts[i]`` (m, 4).
    NaN when there is no ground truth at all."""
    if len(dets) != len(gts):
        raise ValueError(f"{len(dets)} detection frames for {len(gts)} ground-truth frames")
    n_gt = sum(len(g) for g in gts)
    if n_gt == 0:
        return float("nan")
    scores_all, tp_all = [], []
    for (boxes, scores), gt in zip(dets, gts, strict=True):
        if len(scores) == 0:
            continue
        order = np.argsort(-scores, kind="stable")
        boxes, scores = boxes[order], scores[order]
        ious = iou_matrix(boxes, gt)
        taken = np.zeros(len(gt), bool)
        tp = np.zeros(len(scores), bool)
        for i in range(len(scores)):
            if len(gt) == 0:
                break
            cand = np.where(taken, -1.0, ious[i])
            j = int(cand.argmax())
            if cand[j] >= iou:
                taken[j] = True
                tp[i] = True
        scores_all.append(scores)
        tp_all.append(tp)
    if not scores_all:
        return 0.0
    scores = np.concatenate(scores_all)
    tp = np.concatenate(tp_all)[np.argsort(-scores, kind="stable")]
    ctp = np.cumsum(tp)
    recall = ctp / n_gt
    precision = ctp / np.arange(1, len(tp) + 1)
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # the precision envelope
    points = np.linspace(0, 1, 101)
    idx = np.searchsorted(recall, points, side="left")
    sampled = np.where(idx < len(precision), precision[np.minimum(idx, len(precision) - 1)], 0.0)
    return float(sampled.mean())
