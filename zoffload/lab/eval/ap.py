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

from zoffload.policy.agreement import iou_matrix, match, precision_recall_ap

__all__ = ["average_precision", "iou_matrix"]


def average_precision(dets: Sequence[tuple[np.ndarray, np.ndarray]], gts: Sequence[np.ndarray],
                      iou: float = 0.5) -> float:
    """AP over frames: ``dets[i]`` = (boxes (n, 4), scores (n,)) scored against ``gts[i]`` (m, 4).
    NaN when there is no ground truth at all. (The matching and the pooled AP are the robot's too:
    its dispatcher scores its detector against the edge's answers, policy/agreement.py.)"""
    if len(dets) != len(gts):
        raise ValueError(f"{len(dets)} detection frames for {len(gts)} ground-truth frames")
    matched = [match(boxes, scores, gt, iou) for (boxes, scores), gt in zip(dets, gts, strict=True)
               if len(scores)]
    return precision_recall_ap([m[0] for m in matched], [m[1] for m in matched], sum(len(g) for g in gts))
