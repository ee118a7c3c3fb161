"""Textbook Gaussian-mixture reduction (Vo & Ma 2006, Table II; the averaged map of paper eq. (7)).

The reference of :func:`mmslam.slam.phd.reduction.prune_merge` and the kernels of
:mod:`mmslam.slam.phd.merging`: prune by weight (and position-covariance trace), merge greedily the
components within a squared Mahalanobis gate of the heaviest remaining one (moment matching), cap at
the largest ``cap``. Plain NumPy, one mixture ``w (Q,)``, ``m (Q, d)``, ``P (Q, d, d)``.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np


def greedy_merge(w: np.ndarray, m: np.ndarray, P: np.ndarray, idx: Iterable[int], merge: float
                 ) -> tuple[list[tuple[list[int], float, np.ndarray, np.ndarray]], list[float]]:
    """Table II step 2 over the components ``idx`` of one mixture, one at a time.

    Returns the clusters in creation order as ``(members, W, mean, cov)`` and every squared
    Mahalanobis distance evaluated (to reject examples sitting on the threshold).
    """
    idx = list(idx)
    clusters, dists = [], []
    while idx:
        j = max(idx, key=lambda i: w[i])  # first of the largest weights in slot order
        members = []
        for i in idx:
            dm = m[i] - m[j]
            dist = dm @ np.linalg.inv(P[i]) @ dm
            if i != j:
                dists.append(dist)
            if i == j or dist <= merge:
                members.append(i)
        W = sum(w[i] for i in members)
        mean = sum(w[i] * m[i] for i in members) / W
        cov = sum(w[i] * (P[i] + np.outer(mean - m[i], mean - m[i])) for i in members) / W
        clusters.append((members, W, mean, cov))
        idx = [i for i in idx if i not in members]
    return clusters, dists


def reduce(w: np.ndarray, m: np.ndarray, P: np.ndarray, mask: np.ndarray, prune: float, merge: float, cap: int,
           max_trace: float | None, pos_dims: int, final_prune: float | None = None
           ) -> tuple[list[tuple[list[int], float, np.ndarray, np.ndarray]], list[float]]:
    """Prune (weight, trace) -> :func:`greedy_merge` -> [final prune] -> the ``cap`` largest, sorted by weight."""
    idx = [i for i in range(len(w)) if mask[i] and w[i] >= prune
           and (max_trace is None or np.trace(P[i][:pos_dims, :pos_dims]) <= max_trace)]
    clusters, dists = greedy_merge(w, m, P, idx, merge)
    if final_prune is not None:
        clusters = [c for c in clusters if c[1] >= final_prune]
    clusters = sorted(clusters, key=lambda c: -c[1])[:cap]  # stable: creation order on ties
    return clusters, dists
