"""Average precision against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.lab.eval.ap import average_precision, iou_matrix


def test_ap_of_perfect_missing_and_ranked_detections() -> None:
    gt = [np.array([[0, 0, 10, 10]], np.float32), np.array([[20, 20, 30, 30]], np.float32)]
    perfect = [(g.copy(), np.array([0.9], np.float32)) for g in gt]
    assert average_precision(perfect, gt) == pytest.approx(1.0)
    none = [(np.zeros((0, 4), np.float32), np.zeros(0, np.float32))] * 2
    assert average_precision(none, gt) == 0.0
    # frame 0: a false positive scored above the true positive; frame 1 missed entirely
    fp_first = [(np.array([[50, 50, 60, 60], [0, 0, 10, 10]], np.float32), np.array([0.9, 0.8], np.float32)),
                none[0]]
    # precision envelope: 0.5 up to recall 0.5, nothing beyond -> 51 of 101 points at 0.5
    assert average_precision(fp_first, gt) == pytest.approx(51 * 0.5 / 101)
    # a duplicate of a matched box is a false positive
    dup = [(np.array([[0, 0, 10, 10], [0, 0, 10, 10]], np.float32), np.array([0.9, 0.8], np.float32))]
    assert average_precision(dup, gt[:1]) == pytest.approx(1.0)  # the duplicate ranks after recall 1
    assert iou_matrix(gt[0], gt[1])[0, 0] == 0.0
