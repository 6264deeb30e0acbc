"""The local detector's worth measured against the edge's answers (policy/agreement.py), and the
dispatcher's use of it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from zoffload.policy.agreement import (
    EDGE,
    LOCAL,
    Agreement,
    Bank,
    binned_ap,
    crossing,
    match,
    precision_recall_ap,
)
from zoffload.policy.dispatch import Dispatcher

# px per frame of 28 people 100 px wide: two still, and 26 whose box overlaps its old place by
# IoU 0.5 for 0.75, 1.25, ... 13.25 frames (an answer about them agrees for that long), so the
# agreement falls at every age and has no plateau to be read either way
SPEEDS = np.concatenate([[0.0, 0.0], 100 / (3 * (0.75 + 0.5 * np.arange(26)))])


def scene(seq: int, every: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The people's boxes in frame ``seq``, each moving at its own speed (a detector that sees every
    ``every``-th)."""
    x = 20.0 + SPEEDS * seq
    rows = np.arange(len(SPEEDS)) * 120.0
    boxes = np.stack([x, rows, x + 100, rows + 100], axis=1)[::every]
    return boxes, np.linspace(0.9, 0.6, len(boxes))


def feed(agreement: Agreement, local: int | None, frames: int = 600, late: int = 0) -> None:
    """Every third frame to the local detector (``local``: which boxes it sees; None: none; ``late``:
    it sees the scene that many frames back), the rest to the edge, which sees them all."""
    for seq in range(frames):
        if seq % 3 == 0 and local is not None:
            agreement.observe(seq, LOCAL, *scene(seq - late, local), capture=0.04 * seq)
        else:
            agreement.observe(seq, EDGE, *scene(seq), capture=0.04 * seq)


def test_matching_is_cocos_greedy_by_score() -> None:
    truth = np.array([[0, 0, 10, 10], [20, 0, 30, 10]], float)
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 0, 30, 10]], float)
    scores, tp = match(boxes, np.array([0.5, 0.9, 0.7]), truth)
    # the surest box takes the first truth box, the exact one is then a duplicate
    assert scores.tolist() == [0.9, 0.7, 0.5] and tp.tolist() == [True, True, False]
    assert precision_recall_ap([scores], [tp], 2) == pytest.approx(1.0)
    assert math.isnan(precision_recall_ap([scores], [tp], 0))
    assert precision_recall_ap([], [], 3) == 0.0


def test_the_binned_ap_is_the_pooled_ap_within_a_point() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        frames = [(rng.random(rng.integers(0, 12)), rng.random(12) < 0.6) for _ in range(200)]
        scores = [s for s, _ in frames]
        tps = [tp[:len(s)] for s, tp in frames]
        n_gt = sum(int(tp.sum()) for tp in tps) + int(rng.integers(0, 100))
        bank = Bank(keep=1000)
        for s, tp in zip(scores, tps, strict=True):
            bank.add(s, tp, 0)
        bank.n_gt = n_gt
        assert bank.ap() == pytest.approx(precision_recall_ap(scores, tps, n_gt), abs=0.01)
    assert math.isnan(Bank(5).ap()) and binned_ap(np.zeros(4), np.zeros(4), 3) == 0.0


def test_a_local_detector_as_good_as_the_edges_needs_no_bias() -> None:
    a = Agreement(min_pairs=20, every=10)
    feed(a, local=1)
    edge, local = a.curves
    assert edge[0] == 1.0 and edge[1] > edge[3]  # older answers agree less
    assert local[1] == pytest.approx(edge[1], abs=0.02)
    assert a.offset == pytest.approx(0.0, abs=0.1) and not a.floor
    assert a.seq_period == pytest.approx(0.04)


def test_a_local_detector_that_misses_people_must_finish_periods_sooner() -> None:
    a = Agreement(min_pairs=20, every=10)
    feed(a, local=2)  # sees every other person
    edge, local = a.curves
    assert all(lo < e for lo, e in zip(local[1:], edge[1:], strict=False) if math.isfinite(lo))
    assert a.span < a.offset < a.edge_span and not a.floor  # beyond the ages local answers are compared at


@pytest.mark.parametrize("late", [1, 2, 4, 6])
def test_a_local_detector_that_sees_the_scene_late_is_worth_that_many_frames(late: int) -> None:
    # the robot's answers are the edge's view of ``late`` frames before: the estimate finds the lag,
    # beyond the ages the local answers are compared at (4)
    a = Agreement(min_pairs=20, every=10)
    feed(a, local=1, frames=900, late=late)
    assert a.offset == pytest.approx(late, abs=0.35) and not a.floor


def test_a_local_answer_that_comes_after_the_edges_later_one_is_still_compared() -> None:
    a = Agreement(min_pairs=1, every=1)
    a.observe(11, EDGE, *scene(11))  # the edge answers frame 11 first
    a.observe(10, LOCAL, *scene(10))  # the robot's answer to frame 10 comes after
    a.observe(10, EDGE, *scene(10))  # and a copy of frame 10: the edge's view of the same frame
    assert len(a.pairs[LOCAL, 1]) == 1 and len(a.pairs[LOCAL, 0]) == 1 and len(a.pairs[EDGE, 1]) == 1
    assert len(a.pairs[EDGE, 1].pairs[0][0]) == len(SPEEDS)  # frame 10's edge answer judged by frame 11's


def test_no_estimate_without_enough_pairs_of_both() -> None:
    a = Agreement(min_pairs=20, every=10)
    feed(a, local=None)  # the edge alone: its own curve, nothing to compare with
    assert math.isnan(a.offset) and a.curves[0][1] > 0
    b = Agreement(min_pairs=20, every=10)
    feed(b, local=1, frames=20)
    assert math.isnan(b.offset)


def test_memory_is_bounded_and_bad_answers_are_ignored() -> None:
    a = Agreement(keep=50, min_pairs=10, every=5)
    feed(a, local=1, frames=2000)
    # a bank's counts are those of the pairs it holds (the evicted ones taken off)
    bank = a.pairs[EDGE, 1]
    assert len(bank) == 50 and bank.hits.sum() + bank.misses.sum() == sum(len(p[0]) for p in bank.pairs)
    assert bank.hits.sum() == sum(int((p[0] % 2).sum()) for p in bank.pairs)
    assert bank.n_gt == sum(p[1] for p in bank.pairs)
    seqs = [x.seq for x in a.recent]
    assert max(seqs) - min(seqs) <= a.edge_span  # only the answers that can still pair are kept
    before, answers, kept = a.offset, a.answers, len(a.recent)
    a.observe(3000, EDGE, np.zeros((2, 4)), np.zeros(3))  # boxes and scores that do not pair up
    a.observe(3001, "elsewhere", *scene(3001))
    assert (a.answers, len(a.recent)) == (answers, kept)  # both ignored
    a.observe(3002, LOCAL, np.full((1, 4), np.nan), np.array([np.nan]))  # NaN boxes match nothing
    crowd = np.resize(scene(3003)[0], (1000, 4)), np.linspace(1.0, 0.01, 1000)  # a thousand boxes
    a.observe(3003, EDGE, *crowd)
    assert len(a.recent[-1].scores) == a.max_boxes and a.recent[-1].scores[0] == 1.0  # the surest kept
    for seq in range(3004, 3004 + 300):  # the crowd's pairs leave the banks in time
        a.observe(seq, LOCAL if seq % 3 == 0 else EDGE, *scene(seq))
    assert math.isfinite(a.offset) and a.offset == pytest.approx(before, abs=0.1)


def test_the_dispatcher_weighs_the_learnt_bias_by_the_pairs_behind_it() -> None:
    d = Dispatcher(local_bias=0.04, learn_bias=True, bias_prior=100)
    assert d.bias(0.04) == 0.04  # nothing learnt yet: as set
    d.agreement.offset, d.agreement.weight = 3.0, 100
    assert d.bias(0.04) == pytest.approx(0.08)  # three periods (0.12 s) on 100 pairs, half and half
    d.agreement.seq_period = 0.02  # the frame numbers say 50 a second (the loop saw every other)
    assert d.bias(0.04) == pytest.approx(0.05)
    d.agreement.seq_period = float("nan")
    d.agreement.weight = 100_000
    assert d.bias(0.04) == pytest.approx(0.12, abs=1e-4)
    d.agreement.offset = 100.0
    assert d.bias(0.04) == pytest.approx(0.5 * d.max_age)  # at most half of max_age
    d.agreement.offset = -10.0
    assert d.bias(0.04) == 0.0
    summary = d.bias_summary()
    assert summary["learnt_periods"] == -10.0 and summary["used_s"] == 0.0 and summary["set_s"] == 0.04
    d.observe(1, EDGE, *scene(1))
    assert d.agreement.recent
    learnt = Dispatcher(learn_bias=True)  # a real estimate's summary is JSON (numpy values are not)
    feed(learnt.agreement, local=2, frames=300)
    learnt.bias(0.04)
    out = json.loads(json.dumps(learnt.bias_summary(), allow_nan=False))
    assert out["learnt_periods"] > 0 and out["below_the_edge_curve"] is False and len(out["edge_curve"]) == 13
    fixed = Dispatcher(local_bias=0.04)  # the default: the bias as set, nothing measured
    fixed.agreement.offset, fixed.agreement.weight = 2.0, 1000
    assert fixed.bias(0.04) == 0.04
    assert Dispatcher(local_bias=0.5).bias(0.04) == 0.5  # a bias as set is not capped
    fixed.observe(1, EDGE, *scene(1))
    assert not fixed.agreement.recent
    assert fixed.bias_summary()["learnt_periods"] == 2.0 and not fixed.bias_summary()["learn"]


def test_the_crossing_interpolates_and_takes_the_middle_of_a_plateau() -> None:
    lags, curve = np.arange(4.0), np.array([1.0, 0.8, 0.8, 0.5])
    assert crossing(lags, curve, 0.9) == pytest.approx(0.5)
    assert crossing(lags, curve, 0.8) == pytest.approx(1.5)
    assert crossing(lags, curve, 0.65) == pytest.approx(2.5)
    assert crossing(lags, curve, 0.4) == 3.0 and crossing(lags, curve, 1.2) == 0.0
    flat = np.array([1.0, 1.0, 0.5, 0.5])  # a still scene: the edge agrees with itself a while
    assert crossing(lags, flat, 1.0) == pytest.approx(0.5) and crossing(lags, flat, 0.5) == pytest.approx(2.5)
