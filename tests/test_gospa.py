"""Tests of slam/eval/gospa.py: hand cases and a brute-force cross-check."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from mmslam.slam.eval.gospa import gospa


def test_both_empty_is_zero():
    r = gospa(np.zeros((0, 3)), np.zeros((0, 3)))
    assert r.d == 0 and r.loc == 0 and r.missed == 0 and r.false == 0 and r.n_assigned == 0


def test_all_missed_and_all_false():
    X = np.array([[0, 0, 0], [1, 2, 3], [5, 5, 5]], float)
    r = gospa(X, np.zeros((0, 3)), c=20, p=2, alpha=2)
    assert r.missed == pytest.approx(400 / 2 * 3) and r.false == 0
    assert r.d == pytest.approx(math.sqrt(600))
    r = gospa(np.zeros((0, 3)), X[:2], c=10, p=1, alpha=2)
    assert r.false == pytest.approx(10 / 2 * 2) and r.d == pytest.approx(10)


def test_localisation_only():
    X = np.array([[0, 0, 0], [10, 0, 0]], float)
    Y = np.array([[10, 3, 0], [0, 0, 4]], float)  # order swapped: the assignment must find 3 and 4
    r = gospa(X, Y, c=20, p=2)
    assert r.loc == pytest.approx(9 + 16) and r.missed == 0 and r.false == 0 and r.n_assigned == 2
    assert r.d == pytest.approx(5.0)


def test_pair_beyond_cutoff_is_missed_plus_false():
    X = np.array([[0, 0, 0]], float)
    Y = np.array([[25, 0, 0]], float)
    r = gospa(X, Y, c=20, p=2)
    assert r.n_assigned == 0 and r.loc == 0
    assert r.missed == pytest.approx(200) and r.false == pytest.approx(200)
    assert r.d == pytest.approx(20.0)  # (c^p/2 * 2)^(1/p) = c
    # exactly at c: not a proper assignment either, same value
    assert gospa(X, np.array([[20.0, 0, 0]]), c=20).d == pytest.approx(20.0)


def test_mixed_case():
    X = np.array([[0, 0, 0], [50, 0, 0], [100, 0, 0]], float)
    Y = np.array([[1, 1, 0], [50, 30, 0]], float)  # one at sqrt(2), one at 30 (> c), truth 3 missed
    r = gospa(X, Y, c=20, p=2)
    assert r.loc == pytest.approx(2.0)
    assert r.n_assigned == 1
    assert r.missed == pytest.approx(2 * 200) and r.false == pytest.approx(200)
    assert r.d**2 == pytest.approx(r.loc + r.missed + r.false)
    assert r.d == pytest.approx(math.sqrt(2 + 600))


def _brute(X, Y, c, p, alpha):
    n, m = len(X), len(Y)
    best = math.inf
    if n <= m:
        for perm in itertools.permutations(range(m), n):
            s = sum(min(np.linalg.norm(X[i] - Y[j]), c) ** p for i, j in enumerate(perm))
            best = min(best, s)
    else:
        for perm in itertools.permutations(range(n), m):
            s = sum(min(np.linalg.norm(X[i] - Y[j]), c) ** p for j, i in enumerate(perm))
            best = min(best, s)
    return (best + c**p / alpha * abs(n - m)) ** (1 / p)


@pytest.mark.parametrize("alpha", [2.0, 1.0])
def test_matches_brute_force(alpha):
    rng = np.random.default_rng(4)
    for _ in range(20):
        n, m = rng.integers(1, 5, size=2)
        X = rng.uniform(0, 40, (n, 2))
        Y = rng.uniform(0, 40, (m, 2))
        r = gospa(X, Y, c=15, p=2, alpha=alpha)
        assert r.d == pytest.approx(_brute(X, Y, 15, 2, alpha))
        assert r.d**2 == pytest.approx(r.loc + r.missed + r.false)


def test_bad_input():
    with pytest.raises(ValueError):
        gospa(np.array([[np.nan, 0, 0]]), np.zeros((1, 3)))
    with pytest.raises(ValueError):
        gospa(np.zeros((1, 3)), np.zeros((1, 2)))
    with pytest.raises(ValueError):
        gospa(np.zeros((1, 3)), np.zeros((1, 3)), alpha=3)
