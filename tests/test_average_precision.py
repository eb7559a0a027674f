"""Average precision of a relevancy map against a mask: a hand-worked case with ties, the
tie rule, a constant map, and scikit-learn's definition on random maps."""

from __future__ import annotations

import numpy as np
import pytest

from n2f2.eval.metrics import average_precision


def test_ap_by_hand_with_ties():
    # Scores, highest first, and whether the pixel is in the mask (4 positives of 7):
    #   0.9 +  | 0.8 -  0.8 +  0.8 +  | 0.3 -  0.3 +  | 0.1 -
    # The distinct scores are the thresholds; the tied pixels enter together:
    #   t = 0.9: 1 predicted, tp 1 -> P = 1,         R = 1/4
    #   t = 0.8: 4 predicted, tp 3 -> P = 3/4,       R = 3/4
    #   t = 0.3: 6 predicted, tp 4 -> P = 4/6 = 2/3, R = 1
    #   t = 0.1: 7 predicted, tp 4 -> P = 4/7,       R = 1 (no recall gained: adds 0)
    # AP = 1/4 * 1 + (3/4 - 1/4) * 3/4 + (1 - 3/4) * 2/3 = 6/24 + 9/24 + 4/24 = 19/24.
    scores = np.array([0.9, 0.8, 0.8, 0.8, 0.3, 0.3, 0.1])
    mask = np.array([1, 0, 1, 1, 0, 1, 0], bool)
    assert average_precision(scores, mask) == pytest.approx(19 / 24, abs=1e-12)
    # Order inside a tie does not matter (a per-pixel ranking would give 0.8 - then 0.8 + ...
    # a different number), nor does the layout of the pixels.
    perm = np.array([6, 3, 1, 5, 0, 2, 4])
    assert average_precision(scores[perm], mask[perm]) == pytest.approx(19 / 24, abs=1e-12)
    assert average_precision(scores.reshape(1, 7), mask.reshape(1, 7)) == pytest.approx(19 / 24, abs=1e-12)


def test_ap_perfect_constant_and_inverted():
    mask = np.zeros((4, 5), bool)
    mask[1:3, 1:4] = True  # 6 of 20 pixels
    assert average_precision(mask.astype(float), mask) == 1.0
    # one threshold holding every pixel: precision = prevalence, recall 1
    assert average_precision(np.full((4, 5), 0.7), mask) == pytest.approx(6 / 20)
    # the mask ranked last: thresholds 1 (14 negatives) then 0 (all 20): AP = 1 * 6 / 20
    assert average_precision(1.0 - mask, mask) == pytest.approx(6 / 20)


def test_ap_equals_sklearn_on_random_maps_with_ties():
    sklearn_metrics = pytest.importorskip("sklearn.metrics")
    rng = np.random.default_rng(3)
    for _ in range(20):
        scores = np.round(rng.random((12, 9)), 1)  # 11 distinct values: many ties
        mask = rng.random((12, 9)) < 0.3
        mask[0, 0] = True
        want = sklearn_metrics.average_precision_score(mask.ravel(), scores.ravel())
        assert average_precision(scores, mask) == pytest.approx(want, abs=1e-12)


def test_ap_bad_input():
    with pytest.raises(ValueError, match="positive"):
        average_precision(np.ones(3), np.zeros(3, bool))
    with pytest.raises(ValueError, match="shape"):
        average_precision(np.ones(3), np.ones(4, bool))
    with pytest.raises(ValueError, match="NaN"):
        average_precision(np.array([0.1, np.nan]), np.array([True, False]))
