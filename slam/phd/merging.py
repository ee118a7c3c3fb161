"""The per-mixture steps of Gaussian-mixture reduction, written once for one mixture (numba ``njit``,
``inline="always"``), run over a batch by :mod:`mmslam.slam.phd.reduction`:

:func:`survivors` (Vo & Ma 2006, Table II, step 1: pruning), :func:`greedy_clusters` (step 2: the
clusters within the merge gate of the heaviest remaining component), :func:`moment_match_at` /
:func:`moment_match` (step 2: one cluster's moments) and :func:`cluster_order` (step 3: the largest
``cap``), plus :func:`sort_descending`. Shapes: weights ``(Q,)``, means ``(Q, d)``, covariances
``(Q, d, d)``; means in the global frame (m; VS also m/s and rad/s).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..core.gm import finite_gaussian
from ..core.linalg import _cholesky_once, forward_solve

# linalg's Cholesky factor (no jitter: a singular covariance is an error; finiteness is checked
# before) and forward solve, inlined into the per-component loops below: a call of a separately
# compiled kernel per 3 x 3 matrix costs about as much as the factorisation itself
_cholesky = nb.njit(inline="always", error_model="numpy")(_cholesky_once.py_func)
_forward_solve = nb.njit(inline="always", error_model="numpy")(forward_solve.py_func)


@nb.njit(cache=True, error_model="numpy", inline="always")
def survivors(w_prune: np.ndarray, w: np.ndarray, m: np.ndarray, P: np.ndarray, mask: np.ndarray, prune: float,
              max_trace: float, pos_dims: int, out: np.ndarray) -> int:
    """Vo & Ma 2006, Table II, step 1, for one mixture: the components that survive pruning.

    Survivor ``i``: ``mask[i]``, ``w_prune[i] >= prune`` and ``trace(P[i, :pos_dims, :pos_dims]) <=
    max_trace`` (m^2; ``inf`` for no limit). ``w_prune, w (Q,)``, ``m (Q, d)``, ``P (Q, d, d)``,
    ``mask (Q,)``. Their slot indices are written, in slot order, to ``out[:n]``; returns ``n``, or -1
    if a live component (``mask``) has a non-finite weight ``w``, mean or covariance
    (:func:`finite_gaussian`; pruned ones too).
    """
    n = 0
    k = min(pos_dims, P.shape[1])
    for i in range(w.shape[0]):
        if not mask[i]:
            continue
        if not finite_gaussian(w[i], m[i], P[i]):
            return -1
        if w_prune[i] >= prune:
            tr = 0.0
            for a in range(k):
                tr += P[i, a, a]
            if tr <= max_trace:
                out[n] = i
                n += 1
    return n


@nb.njit(cache=True, error_model="numpy", inline="always")
def sort_descending(key: np.ndarray, idx: np.ndarray, n: int) -> None:
    """Stable sort of ``idx[:n]`` by descending ``key[idx]`` in place (insertion sort: ``n`` is small;
    equal keys keep their order, as ``np.argsort(-key, kind="stable")``)."""
    for a in range(1, n):
        v = idx[a]
        b = a
        while b > 0 and key[idx[b - 1]] < key[v]:
            idx[b] = idx[b - 1]
            b -= 1
        idx[b] = v


@nb.njit(cache=True, error_model="numpy", inline="always")
def moment_match_at(w: np.ndarray, m: np.ndarray, P: np.ndarray, n: int, members: np.ndarray, lo: int, hi: int,
                    ref: int, out_m: np.ndarray, out_P: np.ndarray, r: int) -> float:
    """Moment match of the components ``members[n, lo:hi]`` of mixture ``n`` of a batch (Vo & Ma 2006,
    Table II, step 2), written to slot ``r`` of mixture ``n`` of ``out_m (N, R, d)``, ``out_P (N, R, d, d)``.

    ``W = sum w_i``, ``m = sum w_i m_i / W``, ``P = sum w_i (P_i + (m_i - m)(m_i - m)^T) / W``,
    accumulated as offsets ``o_i = m_i - m_ref`` from the component ``ref`` (less cancellation far
    from the origin): ``dbar = sum w_i o_i / W``, ``m = m_ref + dbar``,
    ``P = sum w_i (P_i + o_i o_i^T) / W - dbar dbar^T``. ``out_m[n, r]`` and ``out_P[n, r]``
    (exactly symmetric) hold the sums meanwhile (no scratch); ``W`` is returned. The sums use the
    weights relative to the cluster's largest, ``w_i / w_max`` (the same moments: without pruning,
    ``prune = 0``, subnormal weights made ``w_i P_i`` lose its digits and the merged covariance
    indefinite). A cluster whose members all weigh 0 (kept only without pruning) has no weighted
    moments: it gets the moments of ``ref`` (a zero covariance would break the next merge's Cholesky).
    Shapes: ``w (N, Q)``, ``m (N, Q, d)``, ``P (N, Q, d, d)``, ``members (N, K)`` slot indices.
    Indexed on the batch arrays, not on per-mixture views: numba's inlined views cost about as
    much as the arithmetic here.
    """
    d = m.shape[2]
    W = wmax = 0.0
    for t in range(lo, hi):
        W += w[n, members[n, t]]
        wmax = max(wmax, w[n, members[n, t]])
    if not wmax > 0.0:  # every member weighs 0 (no pruning, prune = 0): no moments to match; the head's own
        for a in range(d):
            out_m[n, r, a] = m[n, ref, a]
            for b in range(d):
                out_P[n, r, a, b] = 0.5 * (P[n, ref, a, b] + P[n, ref, b, a])
        return W
    U = 0.0  # the sums in weights relative to the largest, u_i = w_i / w_max in (0, 1]: no subnormal products
    for a in range(d):
        out_m[n, r, a] = 0.0  # sum u_i o_i
        for b in range(d):
            out_P[n, r, a, b] = 0.0  # sum u_i (P_i + o_i o_i^T)
    for t in range(lo, hi):
        i = members[n, t]
        u = w[n, i] / wmax
        U += u
        for a in range(d):
            oa = m[n, i, a] - m[n, ref, a]
            out_m[n, r, a] += u * oa
            for b in range(d):
                out_P[n, r, a, b] += u * (P[n, i, a, b] + oa * (m[n, i, b] - m[n, ref, b]))
    for a in range(d):
        out_m[n, r, a] /= U  # dbar
    for a in range(d):
        for b in range(a + 1):
            v = 0.5 * (out_P[n, r, a, b] + out_P[n, r, b, a]) / U - out_m[n, r, a] * out_m[n, r, b]
            out_P[n, r, a, b] = v
            out_P[n, r, b, a] = v
    for a in range(d):
        out_m[n, r, a] += m[n, ref, a]
    return W


@nb.njit(cache=True, error_model="numpy", inline="always")
def moment_match(w: np.ndarray, m: np.ndarray, P: np.ndarray, members: np.ndarray, ref: int,
                 out_m: np.ndarray, out_P: np.ndarray) -> float:
    """:func:`moment_match_at` of the components ``members (K,)`` of one mixture ``w (Q,)``, ``m (Q, d)``,
    ``P (Q, d, d)`` (offsets from the component ``ref``) into ``out_m (d,)``, ``out_P (d, d)``; returns ``W``.
    (``a[None, ...]``, not ``a[None]``: numba 0.60 and 0.61 have no lowering of a bare ``None`` index, numba#10370.)"""
    return moment_match_at(w[None, ...], m[None, ...], P[None, ...], 0, members[None, ...], 0, members.shape[0], ref,
                           out_m[None, None, ...], out_P[None, None, ...], 0)


@nb.njit(cache=True, error_model="numpy", inline="always")
def greedy_clusters(w: np.ndarray, m: np.ndarray, P: np.ndarray, rem: np.ndarray, n: int, merge: float,
                    by_weight: bool, L: np.ndarray, r2: np.ndarray, D: np.ndarray, members: np.ndarray,
                    heads: np.ndarray, starts: np.ndarray, W: np.ndarray) -> int:
    """Greedy Mahalanobis clusters of one mixture (Vo & Ma 2006, Table II, step 2).

    Take the highest-weight remaining component ``j`` (the first in ``rem`` order on ties); its
    cluster is every remaining ``i`` with ``(m_i - m_j)^T P_i^-1 (m_i - m_j) <= merge`` (squared
    Mahalanobis distance, dimensionless); repeat until none remain. A Euclidean pre-gate skips the
    distance where ``|m_i - m_j|^2 > merge trace(P_i)`` (then the distance exceeds ``merge``: exact).

    Args:
        w: ``(Q,)`` weights; m: ``(Q, d)`` means; P: ``(Q, d, d)`` SPD covariances.
        rem: ``(>= n,)`` the slots to merge in ``rem[:n]``, in priority order (overwritten).
        merge: the gate ``U``.
        by_weight: ``rem`` is sorted by descending weight (ties in slot order): the head is the first.
        L, r2, D: scratch ``(Q, d, d)``, ``(Q,)``, ``(d,)`` (Cholesky factors, pre-gate radii).
        members: ``(>= n,)`` receives the slots grouped by cluster (each cluster in ``rem`` order);
            cluster ``k`` is ``members[starts[k]:starts[k + 1]]``, its head ``heads[k]``, its weight
            ``W[k] = sum w_i`` (summed in that order). ``starts (>= n + 1,)``, ``heads``, ``W (>= n,)``.

    Returns:
        The number of clusters ``K`` (in the order of their heads' weights), or -1 if a covariance
        to merge is singular or indefinite.
    """
    d = m.shape[1]
    for t in range(n):
        i = rem[t]
        if not _cholesky(P[i], L[i], 0.0):  # no jitter: a singular covariance is an error
            return -1
        tr = 0.0
        for a in range(d):
            tr += P[i, a, a]
        r2[i] = merge * tr * (1.0 + 1e-9) + 1e-12
    K = 0
    pos = 0
    while n > 0:
        jj = 0
        for t in range(1, 1 if by_weight else n):
            if w[rem[t]] > w[rem[jj]]:
                jj = t
        j = rem[jj]
        heads[K] = j
        starts[K] = pos
        Wk = 0.0
        left = 0
        for t in range(n):
            i = rem[t]
            if i != j:  # the head always joins its own cluster
                e2 = 0.0
                for a in range(d):
                    D[a] = m[i, a] - m[j, a]
                    e2 += D[a] * D[a]
                member = e2 <= r2[i]
                if member:
                    _forward_solve(L[i], D, D)
                    dist = 0.0
                    for a in range(d):
                        dist += D[a] * D[a]
                    member = dist <= merge
                if not member:
                    rem[left] = i  # stays, in order (left <= t)
                    left += 1
                    continue
            members[pos] = i
            pos += 1
            Wk += w[i]
        W[K] = Wk
        K += 1
        n = left
    starts[K] = pos
    return K


@nb.njit(cache=True, error_model="numpy", inline="always")
def cluster_order(W: np.ndarray, K: int, min_weight: float, by_weight: bool, order: np.ndarray) -> int:
    """Which clusters a reduction keeps, in output order (Vo & Ma 2006, Table II, step 3).

    Clusters ``k < K`` with ``W[k] >= min_weight`` (``-inf``: all), by descending ``W`` (stable:
    creation order on ties) if ``by_weight``, else in creation order. Writes ``order[:n]``,
    returns ``n`` (the caller keeps the first ``cap``).
    """
    n = 0
    for k in range(K):
        if W[k] >= min_weight:
            order[n] = k
            n += 1
    if by_weight:
        sort_descending(W, order, n)
    return n
