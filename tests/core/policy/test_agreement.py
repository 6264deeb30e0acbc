"""The local detector's worth measured against the edge's answers (policy/agreement.py), and the
dispatcher's use of it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.policy.agreement import EDGE, LOCAL, Agreement, crossing, match, precision_recall_ap
from zoffload.policy.dispatch import Dispatcher

SPEEDS = np.arange(0, 50, 5)  # px per frame: ten people, from still to fast


def scene(seq: int, every: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Ten 100 px boxes, each moving at its own speed (a detector that sees every ``every``-th)."""
    x = 20.0 + SPEEDS * seq
    rows = np.arange(len(SPEEDS)) * 120.0
    boxes = np.stack([x, rows, x + 100, rows + 100], axis=1)[::every]
    return boxes, np.linspace(0.9, 0.6, len(boxes))


def feed(agreement: Agreement, local: int | None, frames: int = 600) -> None:
    """Every third frame to the local detector (``local``: which boxes it sees; None: none), the rest
    to the edge, which sees them all."""
    for seq in range(frames):
        if seq % 3 == 0 and local is not None:
            agreement.observe(seq, LOCAL, *scene(seq, local))
        else:
            agreement.observe(seq, EDGE, *scene(seq))


def test_matching_is_cocos_greedy_by_score() -> None:
    truth = np.array([[0, 0, 10, 10], [20, 0, 30, 10]], float)
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 0, 30, 10]], float)
    scores, tp = match(boxes, np.array([0.5, 0.9, 0.7]), truth)
    # the surest box takes the first truth box, the exact one is then a duplicate
    assert scores.tolist() == [0.9, 0.7, 0.5] and tp.tolist() == [True, True, False]
    assert precision_recall_ap([scores], [tp], 2) == pytest.approx(1.0)
    assert math.isnan(precision_recall_ap([scores], [tp], 0))
    assert precision_recall_ap([], [], 3) == 0.0


def test_a_local_detector_as_good_as_the_edges_needs_no_bias() -> None:
    a = Agreement(min_pairs=20, every=10)
    feed(a, local=1)
    edge, local = a.curves
    assert edge[0] == 1.0 and edge[1] > edge[3]  # older answers agree less
    assert local[1] == pytest.approx(edge[1], abs=0.02)
    assert a.offset == pytest.approx(0.0, abs=0.1)


def test_a_local_detector_that_misses_people_must_finish_periods_sooner() -> None:
    a = Agreement(min_pairs=20, every=10)
    feed(a, local=2)  # sees every other person
    edge, local = a.curves
    assert all(lo < e for lo, e in zip(local[1:], edge[1:], strict=True) if math.isfinite(lo))
    assert 0.5 < a.offset <= a.span


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
    assert all(len(p) <= 50 for p in a.pairs.values())
    assert len(a.recent) <= a.recent.maxlen  # type: ignore[operator]
    before = a.offset
    a.observe(3000, EDGE, np.zeros((2, 4)), np.zeros(3))  # boxes and scores that do not pair up
    a.observe(3001, "elsewhere", *scene(3001))
    a.observe(3002, LOCAL, np.full((1, 4), np.nan), np.array([np.nan]))  # NaN boxes match nothing
    crowd = np.tile(scene(3003)[0], (100, 1)), np.linspace(1.0, 0.01, 1000)  # a thousand boxes
    a.observe(3003, EDGE, *crowd)
    assert len(a.recent[-1][3]) == a.max_boxes and a.recent[-1][3][0] == 1.0  # the surest hundred kept
    for seq in range(3004, 3004 + 300):  # the crowd's pairs leave the banks in time
        a.observe(seq, LOCAL if seq % 3 == 0 else EDGE, *scene(seq))
    assert math.isfinite(a.offset) and a.offset == pytest.approx(before, abs=0.1)


def test_the_dispatcher_weighs_the_learnt_bias_by_the_pairs_behind_it() -> None:
    d = Dispatcher(local_bias=0.04, learn_bias=True, bias_prior=100)
    assert d.bias(0.04) == 0.04  # nothing learnt yet: as set
    d.agreement.offset, d.agreement.weight = 3.0, 100
    assert d.bias(0.04) == pytest.approx(0.08)  # three periods (0.12 s) on 100 pairs, half and half
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
    fixed = Dispatcher(local_bias=0.04)  # the default: the bias as set, nothing measured
    fixed.agreement.offset, fixed.agreement.weight = 2.0, 1000
    assert fixed.bias(0.04) == 0.04
    fixed.observe(1, EDGE, *scene(1))
    assert not fixed.agreement.recent
    assert fixed.bias_summary()["learnt_periods"] == 2.0 and not fixed.bias_summary()["learn"]


def test_the_crossing_interpolates_and_takes_the_middle_of_a_plateau() -> None:
    lags, curve = np.arange(4.0), np.array([1.0, 0.8, 0.8, 0.5])
    assert crossing(lags, curve, 0.9) == pytest.approx(0.5)
    assert crossing(lags, curve, 0.8) == pytest.approx(1.5)
    assert crossing(lags, curve, 0.65) == pytest.approx(2.5)
    assert crossing(lags, curve, 0.4) == 3.0 and crossing(lags, curve, 1.2) == 0.0
