"""GOSPA metric (Rahmathullah, Garcia-Fernandez & Svensson, FUSION 2017) between point sets.

For a ground-truth set ``X`` (``n`` points) and an estimate set ``Y`` (``m`` points), cut-off
``c > 0``, order ``p >= 1`` and ``alpha in (0, 2]``:

``d^p = min over assignments gamma of  sum_{(i,j) in gamma} min(|x_i - y_j|, c)^p
        + (c^p / alpha) * |n - m|``

(the minimum runs over the ``min(n, m)``-pair assignments; solved exactly with
:func:`scipy.optimize.linear_sum_assignment` on the cut-off cost ``min(dist, c)^p``).

With ``alpha = 2`` (used throughout) the metric splits into interpretable parts: an assigned
pair at distance ``< c`` is a localisation error ``dist^p``; a pair at distance ``>= c`` costs
``c^p = c^p/2 + c^p/2``, i.e. it is counted as one missed target plus one false estimate, like
every unassigned point (``c^p / 2`` each). :class:`GospaResult` reports these parts as
``p``-th-power contributions so that ``d**p == loc + missed + false``. For ``alpha != 2`` there
is no such split: ``loc`` then holds the whole assignment cost (pairs beyond ``c`` included)
and ``missed`` / ``false`` only the cardinality mismatch ``c^p / alpha * |n - m|``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment


@dataclass(frozen=True)
class GospaResult:
    """GOSPA distance and its parts.

    Attributes:
        d: the GOSPA distance (same unit as the points, e.g. m).
        loc: localisation part, ``sum dist^p`` over properly assigned pairs (unit^p).
        missed: ``c^p / alpha`` times the number of missed ground-truth points (unit^p).
        false: ``c^p / alpha`` times the number of false estimates (unit^p).
        n_assigned: number of properly assigned pairs (distance ``< c``; for ``alpha != 2``
            all ``min(n, m)`` assigned pairs).
    """

    d: float
    loc: float
    missed: float
    false: float
    n_assigned: int


def gospa(X: np.ndarray, Y: np.ndarray, c: float = 20.0, p: float = 2.0, alpha: float = 2.0) -> GospaResult:
    """GOSPA between ground truth ``X`` ``(n, dim)`` and estimates ``Y`` ``(m, dim)`` (Euclidean).

    Args:
        X: ground-truth points (e.g. landmark positions in m), ``(n, dim)``; ``n`` may be 0.
        Y: estimated points, ``(m, dim)``; ``m`` may be 0.
        c: cut-off distance (> 0).
        p: order (>= 1).
        alpha: (0, 2]; 2 gives the missed / false decomposition (see module docstring).

    Returns:
        :class:`GospaResult` with ``d ** p == loc + missed + false``.

    Raises:
        ValueError: bad parameters, mismatched dimensions or non-finite points.
    """
    if not (c > 0 and p >= 1 and 0 < alpha <= 2):
        raise ValueError(f"GOSPA needs c > 0, p >= 1, 0 < alpha <= 2; got c={c}, p={p}, alpha={alpha}")
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    if X.ndim != 2 or Y.ndim != 2 or (X.shape[0] and Y.shape[0] and X.shape[1] != Y.shape[1]):
        raise ValueError(f"GOSPA needs point arrays (n, dim) and (m, dim), got {X.shape} and {Y.shape}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
        raise ValueError("GOSPA got NaN or inf in a point set")
    n, m = X.shape[0], Y.shape[0]
    cp = c**p
    unit = cp / alpha
    if n == 0 or m == 0:
        missed, false = unit * n, unit * m
        return GospaResult(float((missed + false) ** (1.0 / p)), 0.0, float(missed), float(false), 0)
    dist = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=-1)
    cost = np.minimum(dist, c) ** p
    ri, ci = linear_sum_assignment(cost)
    pair = dist[ri, ci]
    if alpha == 2:
        ok = pair < c
        k = int(ok.sum())
        loc = float(np.sum(pair[ok] ** p))
        missed = unit * (n - k)
        false = unit * (m - k)
    else:
        k = int(ri.size)
        loc = float(np.sum(cost[ri, ci]))
        missed = unit * max(n - m, 0)
        false = unit * max(m - n, 0)
    total = loc + missed + false
    return GospaResult(float(total ** (1.0 / p)), loc, float(missed), float(false), k)
