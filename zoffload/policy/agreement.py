"""How many camera periods late an edge answer may be and still be worth a fresh answer of the
robot's own detector, measured online from the answers themselves.

The dispatcher (policy/dispatch.py) gives a frame to the local detector only when it finishes
sooner by a *bias*: the robot's model is the lighter one. The right bias depends on the two models
and on the images: on the tuning half of the COCO clips NanoDet-m on a fresh frame scored what
PicoDet-S scored one period late (78.3 against 78.2 AP50), on the held-out half what PicoDet-S
scored more than two periods late (58.1 against 59.1 two late). A constant tuned on one set of
images is wrong on the other (docs/perception-log.md: "The local bias, measured online").

Without ground truth the robot still has a judge it trusts more than its own detector: the edge's.
Every edge answer for frame ``s`` stands as the truth (its detections scored at least
``truth_score``) for the answers to the frames just before it, ``s - k`` for ``k`` up to ``span``:

* the edge's own earlier answers: how the stronger model's answer ages, ``A_edge(k)`` (100 % at
  ``k = 0``: an answer agrees with itself);
* the local detector's answers (and, at ``k = 0``, the frames detected locally whose copy went to
  the edge): ``A_local(k)``.

Each is an AP50 over the recent pairs, COCO's way (``average_precision``: score-ranked, so the two
models' score scales need not match). A local answer ``k`` frames old agrees with the edge as much
as an edge answer ``j`` frames old does, where the edge's curve crosses ``A_local(k)``; ``j - k``,
averaged over the ``k`` with enough pairs, is how many periods later the edge may finish and still
be the better choice: the bias. Offline on the cached detections of both halves the estimate is
2.5-2.9 periods (the edge agrees with itself better than with the truth, so it overstates the
edge's lead where the models are close; on the tuning half a bias of 0.1 s, 2.5 periods, scored as
the tuned 0.04 s did).

Cost: pairs are matched once, when the later answer arrives (a few boxes each); the curves are
re-read every ``every`` edge answers from the kept pairs (a sort of a few thousand scores).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

EDGE, LOCAL = "edge", "local"
NAN = float("nan")


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


def match(boxes: np.ndarray, scores: np.ndarray, gt: np.ndarray, iou: float = 0.5
          ) -> tuple[np.ndarray, np.ndarray]:
    """One frame's detections against its truth, COCO's way: by descending score, each takes the
    untaken truth box it overlaps most if that overlap is at least ``iou``. Returns the scores
    (sorted) and whether each is a true positive."""
    order = np.argsort(-scores, kind="stable")
    boxes, scores = boxes[order], scores[order]
    tp = np.zeros(len(scores), bool)
    if len(gt) == 0 or len(scores) == 0:
        return scores, tp
    ious = iou_matrix(boxes, gt)
    taken = np.zeros(len(gt), bool)
    for i in range(len(scores)):
        cand = np.where(taken, -1.0, ious[i])
        j = int(cand.argmax())
        if cand[j] >= iou:
            taken[j] = True
            tp[i] = True
    return scores, tp


def precision_recall_ap(scores: Sequence[np.ndarray], tps: Sequence[np.ndarray], n_gt: int) -> float:
    """AP (0-1, 101-point interpolated) of matched frames pooled: NaN without truth, 0 without
    detections."""
    if n_gt == 0:
        return NAN
    if not scores or sum(len(s) for s in scores) == 0:
        return 0.0
    s = np.concatenate(scores)
    tp = np.concatenate(tps)[np.argsort(-s, kind="stable")]
    ctp = np.cumsum(tp)
    recall = ctp / n_gt
    precision = ctp / np.arange(1, len(tp) + 1)
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # the precision envelope
    points = np.linspace(0, 1, 101)
    idx = np.searchsorted(recall, points, side="left")
    sampled = np.where(idx < len(precision), precision[np.minimum(idx, len(precision) - 1)], 0.0)
    return float(sampled.mean())


def crossing(lags: np.ndarray, curve: np.ndarray, a: float) -> float:
    """Where the non-increasing ``curve`` (at ``lags``) falls to ``a``, linearly between its points;
    the middle of a stretch where it equals ``a``; its first or last lag beyond its ends."""
    if a >= curve[0]:
        return float(lags[0])
    if a <= curve[-1]:
        flat = np.nonzero(curve == curve[-1])[0]
        return float(lags[flat].mean()) if a == curve[-1] else float(lags[-1])
    i = int(np.nonzero(curve <= a)[0][0])  # the first point at or below (i >= 1)
    if curve[i] == a:  # on a point: the middle of the points equal to it
        return float(lags[curve == a].mean())
    hi, lo = curve[i - 1], curve[i]
    return float(lags[i - 1] + (hi - a) / (hi - lo) * (lags[i] - lags[i - 1]))


Pair = tuple[np.ndarray, np.ndarray, int]  # matched scores, true positives, truth boxes


class Agreement:
    """The local detector's worth in edge periods (module docstring): feed it every answer
    (``observe``), read ``offset`` (camera periods; NaN until enough pairs)."""

    def __init__(self, span: int = 5, keep: int = 200, min_pairs: int = 40, every: int = 25,
                 truth_score: float = 0.5, max_boxes: int = 100) -> None:
        self.span, self.min_pairs, self.every, self.truth_score = span, min_pairs, every, truth_score
        self.max_boxes = max_boxes
        self.recent: deque[tuple[int, str, np.ndarray, np.ndarray]] = deque(maxlen=4 * (span + 1))
        self.pairs: dict[tuple[str, int], deque[Pair]] = {
            (side, k): deque(maxlen=keep) for side in (EDGE, LOCAL) for k in range(span + 1)}
        self.offset = NAN
        self.weight = 0  # the local pairs behind the offset
        self.curves: tuple[list[float], list[float]] = ([], [])  # the last estimate's A_edge, A_local
        self.answers = 0

    def observe(self, seq: int, side: str, boxes: np.ndarray, scores: np.ndarray) -> None:
        """An answer for frame ``seq`` from ``side`` (``edge``: a frame's or a copy's)."""
        if side not in (EDGE, LOCAL) or len(boxes) != len(scores):
            return
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        scores = np.asarray(scores, np.float64).reshape(-1)
        if len(scores) > self.max_boxes:  # the surest ones: matching is quadratic in the boxes
            top = np.argsort(-scores, kind="stable")[:self.max_boxes]
            boxes, scores = boxes[top], scores[top]
        if side == EDGE:
            truth = boxes[scores >= self.truth_score]
            for s, other, b, sc in self.recent:
                k = seq - s
                if 0 <= k <= self.span and not (k == 0 and other == EDGE):
                    found, tp = match(b, sc, truth)
                    self.pairs[other, k].append((found, tp, len(truth)))
            self.answers += 1
            if self.answers % self.every == 0:
                self.offset = self.estimate()
        self.recent.append((seq, side, boxes, scores))

    def ap(self, side: str, k: int) -> float:
        """AP50 (0-1) of ``side``'s answers ``k`` frames old against the edge's (NaN: too few)."""
        if side == EDGE and k == 0:
            return 1.0
        pairs = self.pairs[side, k]
        if len(pairs) < self.min_pairs:
            return NAN
        return precision_recall_ap([p[0] for p in pairs], [p[1] for p in pairs], sum(p[2] for p in pairs))

    def estimate(self) -> float:
        """Periods the edge may be later than the local detector and still agree with the edge's
        fresh answers as well: the mean over ``k`` of where the edge's curve (made non-increasing)
        crosses ``A_local(k)``, less ``k``, weighted by the pairs behind each; beyond the curve's
        last known point, that point (the offset is then a floor). NaN until both are known."""
        edge = [self.ap(EDGE, k) for k in range(self.span + 1)]
        local = [self.ap(LOCAL, k) for k in range(self.span + 1)]
        self.curves = (edge, local)
        known = [(k, a) for k, a in enumerate(edge) if math.isfinite(a)]
        if len(known) < 2:
            return NAN
        lags = np.array([k for k, _ in known], float)
        curve = np.minimum.accumulate(np.array([a for _, a in known]))
        total = weight = 0.0
        for k, a in enumerate(local):
            if not math.isfinite(a):
                continue
            lag = crossing(lags, curve, a)
            n = len(self.pairs[LOCAL, k])
            total += (lag - k) * n
            weight += n
        self.weight = int(weight)
        return total / weight if weight else NAN
