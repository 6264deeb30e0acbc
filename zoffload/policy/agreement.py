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
``truth_score``) for the answers to the frames before it, ``s - k``:

* the edge's own earlier answers (``k`` from 1 to ``edge_span``): how the stronger model's answer
  ages, ``A_edge(k)`` (1 at ``k = 0``: an answer agrees with itself);
* the local detector's answers (``k`` from 0, a frame detected locally whose copy went to the
  edge, to ``span``): ``A_local(k)``.

Each is an AP50 over the recent pairs, COCO's way (score-ranked, so the two models' score scales
need not match; ``binned_ap``: the pooled AP of ``precision_recall_ap`` over counts by score
bin). A local answer ``k`` frames old agrees with the edge as much as an edge answer ``j`` frames
old does, where the edge's curve crosses ``A_local(k)``; ``j - k``, averaged over the ``k`` with
enough pairs, is how many frames later the edge may finish and still be the better choice: the
bias. It measures agreement, not accuracy: the edge agrees with itself
better than with the truth (``benchmarks/bench_agreement.py`` prints the estimate on each half of
the COCO clips beside what the ground truth says).

Cost: pairs are matched once, when the second answer of the two arrives (at most ``max_boxes``
boxes each), and counted by score bin as they enter and leave an age's bank (``Bank``); the curves
are re-read every ``every`` edge answers from the bins (``binned_ap``: the pooled AP with the
scores of one bin, 1/256 wide, taken as tied), so a re-read costs the same however many pairs.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

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
    return _interpolated(ctp / n_gt, ctp / np.arange(1, len(tp) + 1))


def _interpolated(recall: np.ndarray, precision: np.ndarray) -> float:
    """COCO's 101-point AP of a precision-recall curve (surest detections first): the precision
    envelope read at recall 0, 0.01, ... 1 (0 beyond the curve's last recall)."""
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # the precision envelope
    idx = np.searchsorted(recall, np.linspace(0, 1, 101), side="left")
    return float(np.where(idx < len(precision), precision[np.minimum(idx, len(precision) - 1)], 0.0).mean())


def crossing(lags: np.ndarray, curve: np.ndarray, a: float) -> float:
    """Where the non-increasing ``curve`` (at ``lags``) falls to ``a``, linearly between its points;
    the middle of a stretch where it equals ``a``; its first or last lag beyond its ends."""
    if a > curve[0]:
        return float(lags[0])
    if a < curve[-1]:
        return float(lags[-1])
    i = int(np.nonzero(curve <= a)[0][0])  # the first point at or below
    if curve[i] == a:  # on a point: the middle of the points equal to it
        return float(lags[curve == a].mean())
    hi, lo = curve[i - 1], curve[i]
    return float(lags[i - 1] + (hi - a) / (hi - lo) * (lags[i] - lags[i - 1]))


SCORE_BINS = 256  # a bank's scores are counted in this many equal bins of [0, 1]


def binned_ap(hits: np.ndarray, misses: np.ndarray, n_gt: int) -> float:
    """``precision_recall_ap`` of detections counted by score bin (``hits``: true positives per
    bin, ``misses``: false positives, lowest bin first): the same curve, with the detections of
    one bin taken as tied. NaN without truth, 0 without detections."""
    if n_gt <= 0:
        return NAN
    tp, fp = np.cumsum(hits[::-1]), np.cumsum(misses[::-1])  # surest bin first
    seen = tp + fp > 0
    if not seen.any():
        return 0.0
    return _interpolated(tp[seen] / n_gt, tp[seen] / (tp[seen] + fp[seen]))


class Bank:
    """The last ``keep`` matched pairs of one age, counted by score bin as they come and go, so that
    their pooled AP costs a pass over the bins, not a sort of every score."""

    def __init__(self, keep: int) -> None:
        # each pair as the codes of its detections (score bin × 2 + whether a true positive: one
        # small array, nothing for the garbage collector to walk) and its truth boxes
        self.pairs: deque[tuple[np.ndarray, int]] = deque()
        self.keep = keep
        self.counts = [0] * (2 * SCORE_BINS)  # per code: detections
        self.n_gt = 0

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def hits(self) -> np.ndarray:
        return np.array(self.counts[1::2])

    @property
    def misses(self) -> np.ndarray:
        return np.array(self.counts[0::2])

    def add(self, scores: np.ndarray, tp: np.ndarray, n_gt: int) -> None:
        bins = np.clip((np.nan_to_num(scores) * SCORE_BINS).astype(np.int16), 0, SCORE_BINS - 1)
        pair = (2 * bins + tp, n_gt)
        self._count(pair, 1)
        self.pairs.append(pair)
        if len(self.pairs) > self.keep:
            self._count(self.pairs.popleft(), -1)

    def _count(self, pair: tuple[np.ndarray, int], sign: int) -> None:
        counts = self.counts
        for code in pair[0].tolist():  # a few boxes: plain Python is quicker than numpy's scatter
            counts[code] += sign
        self.n_gt += sign * pair[1]

    def ap(self) -> float:
        return binned_ap(self.hits, self.misses, self.n_gt)


@dataclass
class Answer:
    """One answer kept while a later (or earlier) one may still pair with it."""

    seq: int
    side: str
    boxes: np.ndarray
    scores: np.ndarray
    truth: np.ndarray | None  # an edge answer's sure boxes (None: a local answer)


class Agreement:
    """The local detector's worth in edge periods (module docstring): feed it every answer
    (``observe``), read ``offset`` (camera periods; NaN until enough pairs).

    Local answers are compared at ages 0 to ``span`` frames, the edge's own at 1 to ``edge_span``
    (longer, so that a local detector much worse than the edge's still crosses its curve; one that
    agrees less than the oldest edge answer measured counts at that age, and ``floor`` says so). A
    pair is made whichever of the two answers comes second (a quarter-core robot's answer often
    comes after the edge's answer to a later frame). ``keep`` pairs of each age at most; the curves
    are re-read every ``every`` edge answers; an answer's ``max_boxes`` surest boxes at most."""

    def __init__(self, span: int = 4, edge_span: int = 12, keep: int = 600, min_pairs: int = 30,
                 every: int = 50, truth_score: float = 0.5, max_boxes: int = 30) -> None:
        if edge_span < span:
            raise ValueError(f"edge_span ({edge_span}) must be at least span ({span})")
        self.span, self.edge_span, self.min_pairs, self.every = span, edge_span, min_pairs, every
        self.truth_score, self.max_boxes = truth_score, max_boxes
        self.recent: deque[Answer] = deque(maxlen=4 * (edge_span + 1))
        self.pairs: dict[tuple[str, int], Bank] = {
            **{(EDGE, k): Bank(keep) for k in range(1, edge_span + 1)},
            **{(LOCAL, k): Bank(keep) for k in range(span + 1)}}
        self.offset = NAN
        self.weight = 0  # the local pairs behind the offset
        self.floor = False  # some local age agreed less than the oldest edge answer measured
        self.curves: tuple[list[float], list[float]] = ([], [])  # the last estimate's A_edge, A_local
        self.answers = 0  # edge answers compared
        self.seq_period = NAN  # s between camera frames (seqs), from the answers' capture times
        self._last: tuple[int, float] | None = None  # the newest (seq, capture) seen

    def observe(self, seq: int, side: str, boxes: np.ndarray, scores: np.ndarray,
                capture: float = NAN) -> None:
        """An answer for frame ``seq`` (captured at ``capture``) from ``side`` (``edge``: a frame's
        or a copy's)."""
        if side not in (EDGE, LOCAL) or len(boxes) != len(scores):
            return
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        scores = np.asarray(scores, np.float64).reshape(-1)
        if len(scores) > self.max_boxes:  # the surest ones: matching is quadratic in the boxes
            top = np.argsort(-scores, kind="stable")[:self.max_boxes]
            boxes, scores = boxes[top], scores[top]
        self._period(seq, capture)
        new = Answer(seq, side, boxes, scores, boxes[scores >= self.truth_score] if side == EDGE else None)
        for old in self.recent:
            self._pair(old, new)
            self._pair(new, old)
        if side == EDGE:
            self.answers += 1
            if self.answers % self.every == 0:
                self.offset = self.estimate()
        self.recent.append(new)
        newest = max(a.seq for a in self.recent)
        while self.recent and self.recent[0].seq < newest - self.edge_span:
            self.recent.popleft()

    def _pair(self, answer: Answer, judge: Answer) -> None:
        """``answer`` scored against ``judge``'s truth, when the judge is an edge answer to the same
        frame or a later one within the answer's side's ages (an edge answer is not its own judge)."""
        if judge.truth is None:
            return
        k = judge.seq - answer.seq
        ages = range(self.span + 1) if answer.side == LOCAL else range(1, self.edge_span + 1)
        if k in ages:
            found, tp = match(answer.boxes, answer.scores, judge.truth)
            self.pairs[answer.side, k].add(found, tp, len(judge.truth))

    def _period(self, seq: int, capture: float) -> None:
        if not math.isfinite(capture):
            return
        if self._last is not None and seq > self._last[0]:
            gap = (capture - self._last[1]) / (seq - self._last[0])
            if 0 < gap < 1.0:  # a clock step or a restart is no sample
                self.seq_period = gap if math.isnan(self.seq_period) else self.seq_period + 0.05 * (
                    gap - self.seq_period)
        if self._last is None or seq > self._last[0]:
            self._last = (seq, capture)

    def ap(self, side: str, k: int) -> float:
        """AP50 (0-1) of ``side``'s answers ``k`` frames old against the edge's (NaN: too few)."""
        if side == EDGE and k == 0:
            return 1.0
        bank = self.pairs[side, k]
        return bank.ap() if len(bank) >= self.min_pairs else NAN

    def estimate(self) -> float:
        """Periods the edge may be later than the local detector and still agree with the edge's
        fresh answers as well: the mean over ``k`` of where the edge's curve (made non-increasing)
        crosses ``A_local(k)``, less ``k``, weighted by the pairs behind each; below the curve's
        last known point, that point (``floor``: the offset is then a lower bound). NaN until both
        are known."""
        edge = [self.ap(EDGE, k) for k in range(self.edge_span + 1)]
        local = [self.ap(LOCAL, k) for k in range(self.span + 1)]
        self.curves = (edge, local)
        known = [(k, a) for k, a in enumerate(edge) if math.isfinite(a)]
        if len(known) < 2:
            return NAN
        lags = np.array([k for k, _ in known], float)
        curve = np.minimum.accumulate(np.array([a for _, a in known]))
        total = weight = 0.0
        self.floor = False
        for k, a in enumerate(local):
            if not math.isfinite(a):
                continue
            self.floor = self.floor or bool(a < curve[-1])
            n = len(self.pairs[LOCAL, k])
            total += (crossing(lags, curve, a) - k) * n
            weight += n
        self.weight = int(weight)
        return total / weight if weight else NAN
