"""Correlation coefficients and the multi-relation (Eq. 9)."""
from __future__ import annotations

import math

import numpy as np
from scipy import stats
import pytest

from topometric_ros.correlation import kendall, multi_relation, pearson, spearman

# three zero-mean, mutually orthogonal ±1 patterns of equal norm
A = np.array([1.0, 1, -1, -1])
B = np.array([1.0, -1, 1, -1])
C = np.array([1.0, -1, -1, 1])


def test_multi_relation_hand_value():
    # corr(A, A+B) = 1/√2, C uncorrelated: R = [[1, s, 0], [s, 1, 0], [0, 0, 1]], s = 1/√2,
    # eigenvalues 1 ± s and 1, so MR = 1 − (1 − s) = 1/√2
    assert multi_relation(A, A + B, C) == pytest.approx(1 / math.sqrt(2), rel=1e-12)
    assert multi_relation(A, B, C) == pytest.approx(0.0, abs=1e-12)


def test_exactly_dependent_variables_give_one(rng):
    x, y = rng.normal(size=200), rng.normal(size=200)
    assert multi_relation(x, y, 3 * x - 2 * y + 7) == pytest.approx(1.0, abs=1e-9)
    assert multi_relation(x, -2 * x) == pytest.approx(1.0, abs=1e-12)


def test_independent_large_samples_give_small_value(rng):
    x, y, z = rng.normal(size=(3, 20000))
    assert multi_relation(x, y, z) < 0.05
    assert abs(pearson(x, y)) < 0.05


def test_rank_correlations_of_monotone_transform_are_one(rng):
    x = rng.normal(size=300)
    assert spearman(x, np.exp(x)) == pytest.approx(1.0)
    assert kendall(x, np.exp(x)) == pytest.approx(1.0)
    assert spearman(x, -x**3) == pytest.approx(-1.0)
    assert pearson(x, np.exp(x)) < 0.99  # not linear


def test_rank_multi_relation_is_one_for_monotone_dependence(rng):
    x = rng.normal(size=300)
    assert multi_relation(x, np.exp(x)) < 0.99  # Eq. 9 is linear
    assert multi_relation(x, np.exp(x), ranks=True) == pytest.approx(1.0, abs=1e-12)
    assert multi_relation(A, A + B, C, ranks=True) == pytest.approx(
        multi_relation(*(stats.rankdata(v) for v in (A, A + B, C))), rel=1e-12)


def test_pearson_hand_value():
    assert pearson(A, A + B) == pytest.approx(1 / math.sqrt(2), rel=1e-12)


def test_constant_or_too_short_input_gives_nan():
    for fn in (pearson, spearman, kendall):
        assert math.isnan(fn([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]))
        assert math.isnan(fn([1.0], [2.0]))
    assert math.isnan(multi_relation([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]))


def test_nan_pairs_are_dropped():
    x = np.array([1.0, 2.0, np.nan, 4.0, 5.0])
    y = np.array([2.0, 4.0, 1.0, 8.0, np.nan])
    assert pearson(x, y) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="length"):
        pearson([1.0, 2.0], [1.0, 2.0, 3.0])
