"""Gaussian-mixture reduction: pruning, greedy Mahalanobis merging and capping.

Two public functions, both pure and batched over leading axes:

- :func:`prune_merge`: Vo & Ma 2006 ("The Gaussian mixture probability hypothesis density
  filter"), Table II, applied to every mixture of a batch at once (e.g. the ``P`` particle maps).
- :func:`average_map`: the particle-weighted average map PHD of the paper's eq. (7),
  ``sum_p w_p D^p``, reduced in the spirit of Mullane et al. 2011, Table IV;
- :func:`merge_pairs`: moment matching of given pairs (the fused VS map).

All three use one merge written for one mixture (:func:`greedy_merge`, :func:`moment_match`;
numba ``njit``, ``cache=True``), run over the batch's mixtures.

Shapes follow :mod:`mmslam.slam.gm`: weights ``(*B, Q)``, means ``(*B, Q, d)``, covariances
``(*B, Q, d, d)``, mask ``(*B, Q)``. Means are in the global frame (m; VS also m/s and rad/s).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .detection import beta_pool
from .gm import GM, compact, empty, symmetrize
from .linalg import cholesky, forward_solve


def _live(g: GM, prune: float, max_trace: float | None, pos_dims: int) -> np.ndarray:
    """Mask of components that survive pruning: live, ``w >= prune``, position trace small."""
    keep = g.mask & (g.w >= prune)
    if max_trace is not None:
        tr = np.trace(g.P[..., :pos_dims, :pos_dims], axis1=-2, axis2=-1)
        keep &= tr <= max_trace
    return keep


@nb.njit(cache=True)
def moment_match(w: np.ndarray, m: np.ndarray, P: np.ndarray, members: np.ndarray, ref: int,
                 out_m: np.ndarray, out_P: np.ndarray) -> float:
    """Moment match of the components ``members`` of one mixture (Vo & Ma 2006, Table II, step 2).

    ``W = sum w_i``, ``m = sum w_i m_i / W``, ``P = sum w_i (P_i + (m_i - m)(m_i - m)^T) / W``,
    accumulated as offsets from the component ``ref`` (less cancellation far from the origin);
    ``out_m (d,)`` and ``out_P (d, d)`` (exactly symmetric) are written, ``W`` is returned.
    Shapes: ``w (Q,)``, ``m (Q, d)``, ``P (Q, d, d)``; ``members (K,)`` slot indices.
    """
    d = m.shape[1]
    W = 0.0
    dbar = np.zeros(d)
    S = np.zeros((d, d))
    off = np.empty(d)
    for i in members:
        W += w[i]
        for a in range(d):
            off[a] = m[i, a] - m[ref, a]
            dbar[a] += w[i] * off[a]
        for a in range(d):
            for b in range(d):
                S[a, b] += w[i] * (P[i, a, b] + off[a] * off[b])
    Wsafe = W if W > 0.0 else 1.0
    for a in range(d):
        dbar[a] /= Wsafe
        out_m[a] = m[ref, a] + dbar[a]
    for a in range(d):
        for b in range(a + 1):
            v = 0.5 * (S[a, b] + S[b, a]) / Wsafe - dbar[a] * dbar[b]
            out_P[a, b] = v
            out_P[b, a] = v
    return W


@nb.njit(cache=True)
def greedy_merge(w: np.ndarray, m: np.ndarray, P: np.ndarray, keep: np.ndarray, merge: float,
                 out_w: np.ndarray, out_m: np.ndarray, out_P: np.ndarray, ab: np.ndarray,
                 out_ab: np.ndarray) -> int:
    """Greedy Mahalanobis merging of one mixture (Vo & Ma 2006, Table II, step 2).

    Take the highest-weight remaining component ``j`` (the first on ties); its cluster is every
    remaining ``i`` with ``(m_i - m_j)^T P_i^-1 (m_i - m_j) <= merge`` (squared Mahalanobis
    distance, dimensionless); write the cluster's :func:`moment_match` to the next output slot;
    repeat until none remain. A Euclidean pre-gate skips the distance where
    ``|m_i - m_j|^2 > merge trace(P_i)`` (then the distance exceeds ``merge``: exact).

    Args:
        w: ``(Q,)`` weights; m: ``(Q, d)`` means; P: ``(Q, d, d)`` SPD covariances; keep: ``(Q,)``
            the components to merge (the others are ignored).
        out_w, out_m, out_P: ``(Q,)``, ``(Q, d)``, ``(Q, d, d)`` outputs; slot ``k`` holds cluster
            ``k`` (clusters in the order of their heads' weights).
        ab, out_ab: ``(Q, 2)`` Beta detection parameters ``(s, t)`` and the clusters' moment match
            (:func:`mmslam.slam.detection.beta_pool`), or ``(Q, 0)`` (none).

    Returns:
        The number of clusters ``K``, or ``-1`` if a kept covariance is singular / indefinite.
    """
    q, d = m.shape
    L = np.empty((q, d, d))  # P_i = L_i L_i^T: the distance is |L_i^-1 (m_i - m_j)|^2
    r2 = np.empty(q)
    for i in range(q):
        if keep[i]:
            if not cholesky(P[i], L[i], False):  # no jitter: a singular covariance is an error
                return -1
            tr = 0.0
            for a in range(d):
                tr += P[i, a, a]
            r2[i] = merge * tr * (1.0 + 1e-9) + 1e-12
    remaining = keep.copy()
    members = np.empty(q, np.int64)
    D = np.empty(d)
    K = 0
    while True:
        j = -1
        for i in range(q):
            if remaining[i] and (j < 0 or w[i] > w[j]):
                j = i
        if j < 0:
            return K
        n = 0
        for i in range(q):
            if not remaining[i]:
                continue
            if i != j:  # the head always joins its own cluster
                e2 = 0.0
                for a in range(d):
                    D[a] = m[i, a] - m[j, a]
                    e2 += D[a] * D[a]
                if e2 > r2[i]:
                    continue
                forward_solve(L[i], D, D)
                dist = 0.0
                for a in range(d):
                    dist += D[a] * D[a]
                if not dist <= merge:
                    continue
            remaining[i] = False
            members[n] = i
            n += 1
        out_w[K] = moment_match(w, m, P, members[:n], j, out_m[K], out_P[K])
        if ab.shape[1]:
            beta_pool(w, ab, members[:n], out_ab[K])
        K += 1


@nb.njit(cache=True)
def _merge_batch(w: np.ndarray, m: np.ndarray, P: np.ndarray, keep: np.ndarray, merge: float,
                 out_w: np.ndarray, out_m: np.ndarray, out_P: np.ndarray, count: np.ndarray, ab: np.ndarray,
                 out_ab: np.ndarray) -> int:
    """:func:`greedy_merge` of every mixture ``n`` of a flat batch; the first singular ``n`` or -1."""
    for n in range(w.shape[0]):
        count[n] = greedy_merge(w[n], m[n], P[n], keep[n], merge, out_w[n], out_m[n], out_P[n], ab[n], out_ab[n])
        if count[n] < 0:
            return n
    return -1


def _merge_flat(w: np.ndarray, m: np.ndarray, P: np.ndarray, keep: np.ndarray, merge: float,
                ab: np.ndarray | None = None):
    """:func:`greedy_merge` of a flat batch ``(N, Q, ...)``; returns ``(w, m, P, mask)`` with ``K <= Q``
    slots (``K`` = the largest number of clusters; slot ``k`` holds cluster ``k``, dead slots 0 / I);
    with Beta detection parameters ``ab (N, Q, 2)`` also their cluster moment match ``(N, K, 2)``
    (dead slots (1, 1)) as a fifth item.

    Raises FloatingPointError if a kept covariance is singular or not positive definite.
    """
    n, q, d = m.shape
    out_w = np.zeros((n, q))
    out_m = np.zeros((n, q, d))
    out_P = np.zeros((n, q, d, d))
    count = np.zeros(n, np.int64)
    ab_in = np.ones((n, q, 0)) if ab is None else np.ascontiguousarray(ab, dtype=float).reshape(n, q, 2)
    out_ab = np.ones((n, q, ab_in.shape[2]))
    if n and q:
        bad = _merge_batch(np.ascontiguousarray(w, dtype=float), np.ascontiguousarray(m, dtype=float),
                           np.ascontiguousarray(P, dtype=float), np.ascontiguousarray(keep, dtype=bool),
                           float(merge), out_w, out_m, out_P, count, ab_in, out_ab)
        if bad >= 0:
            raise FloatingPointError("singular or indefinite covariance in Gaussian-mixture merging")
    k = int(count.max(initial=0))
    mask = np.arange(k)[None, :] < count[:, None]
    out_P = out_P[:, :k]
    out_P[~mask] = np.eye(d)
    if ab is None:
        return out_w[:, :k], out_m[:, :k], out_P, mask
    out_ab = out_ab[:, :k]
    out_ab[~mask] = 1.0
    return out_w[:, :k], out_m[:, :k], out_P, mask, out_ab


def prune_merge(g: GM, prune: float, merge: float, cap: int, max_trace: float | None = None,
                pos_dims: int = 3, *, fixed_capacity: bool = False) -> GM:
    """Prune, merge and cap every mixture of a batch (Vo & Ma 2006, Table II).

    Steps, for each mixture of the batch independently (vectorised over the batch):

    1. drop components with ``w < prune``, and, if ``max_trace`` is given, components whose
       position covariance trace ``trace(P[:pos_dims, :pos_dims]) > max_trace`` (m^2);
    2. greedy merging: take the highest-weight remaining component ``j``; the cluster is every
       remaining ``i`` with ``(m_i - m_j)^T P_i^{-1} (m_i - m_j) <= merge`` (squared Mahalanobis
       distance over all ``d`` state dimensions, e.g. ``49 = 7^2``); replace the cluster by its
       moment match ``w = sum w_i``, ``m = sum w_i m_i / w``,
       ``P = sum w_i (P_i + (m - m_i)(m - m_i)^T) / w``; repeat until none remain;
    3. keep the ``cap`` largest merged components.

    Args:
        g: batch of mixtures, batch shape ``B``, ``Q`` slots, dimension ``d``.
        prune: weight threshold (components below it are dropped).
        merge: squared Mahalanobis merging threshold (dimensionless).
        cap: maximum number of components per mixture after reduction.
        max_trace: position-covariance trace limit in m^2, or None for no limit.
        pos_dims: number of leading state dimensions that are the position.
        fixed_capacity: if True the result has exactly ``cap`` slots (padded); otherwise the
            capacity is the largest live count in the batch (at most ``cap``).

    Returns:
        The reduced batch, batch shape ``B``, compacted (live components first, descending
        weight), symmetrised covariances.

    Raises:
        FloatingPointError: a live component has a non-finite weight, mean or covariance, or a
            surviving covariance is singular.
    """
    g.check("in prune_merge input")
    B = g.batch_shape
    keep = _live(g, prune, max_trace, pos_dims)
    # prune first, then trim the slots to the largest surviving count so merging sees no dead slots
    g = compact(GM(np.where(keep, g.w, 0.0), g.m, g.P, keep, g.pd_beta))
    keep = g.mask
    q, d = g.capacity, g.dim
    if q == 0:
        return compact(g, cap) if fixed_capacity else g
    n = int(np.prod(B, dtype=int))
    res = _merge_flat(g.w.reshape(n, q), g.m.reshape(n, q, d), g.P.reshape(n, q, d, d), keep.reshape(n, q),
                      merge, None if g.pd_beta is None else g.pd_beta.reshape(n, q, 2))
    w, m, P, mask = res[:4]
    k = w.shape[-1]
    out = GM(w.reshape(B + (k,)), m.reshape(B + (k, d)), P.reshape(B + (k, d, d)), mask.reshape(B + (k,)),
             None if g.pd_beta is None else res[4].reshape(B + (k, 2)))
    if fixed_capacity:
        out = compact(out, cap)
    else:
        out = compact(out, min(cap, int(out.count().max(initial=0))))
    # covariances are exactly symmetric already (symmetrised cluster moments, I in dead slots)
    out.check("after prune_merge")
    return out


@nb.njit(cache=True)
def _merge_pairs(w: np.ndarray, m: np.ndarray, P: np.ndarray, pairs: np.ndarray,
                 out_w: np.ndarray, out_m: np.ndarray, out_P: np.ndarray, ab: np.ndarray, out_ab: np.ndarray) -> None:
    """:func:`moment_match` of each pair ``(i, j)`` into slot ``i``; slot ``j`` set to ``w = 0, m = 0, P = I``
    (Beta parameters ``ab (Q, 2)``: :func:`~mmslam.slam.detection.beta_pool`; ``(Q, 0)``: none)."""
    d = m.shape[1]
    for k in range(pairs.shape[0]):
        i, j = pairs[k, 0], pairs[k, 1]
        out_w[i] = moment_match(w, m, P, pairs[k], i, out_m[i], out_P[i])
        if ab.shape[1]:
            beta_pool(w, ab, pairs[k], out_ab[i])
        out_w[j] = 0.0
        for a in range(d):
            out_m[j, a] = 0.0
            for b in range(d):
                out_P[j, a, b] = 1.0 if a == b else 0.0


def merge_pairs(g: GM, pairs: np.ndarray) -> GM:
    """Merge given disjoint pairs of components of one mixture by moment matching.

    For a pair ``(i, j)``: ``w = w_i + w_j``, ``m = (w_i m_i + w_j m_j) / w``,
    ``P = sum_{l in (i, j)} w_l (P_l + (m_l - m)(m_l - m)^T) / w`` (Vo & Ma 2006, Table II, step 2,
    for a cluster of two); the merged component takes slot ``i`` and slot ``j`` is freed. Used
    for the fused VS map (``fusion.vs_reduction = "matched"``): only the pairs the fusion operator
    matched are one target; every other component stays as it is.

    Args:
        g: one mixture (batch ``()``), ``Q`` slots, dimension ``d``.
        pairs: ``(n, 2)`` slot indices of live components, each slot in at most one pair.

    Returns:
        A mixture with the same slots (freed slots masked, ``w = 0``, ``m = 0``, ``P = I``).
    """
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    if g.w.ndim != 1:
        raise ValueError(f"merge_pairs works on one mixture (batch shape ()), got {g.batch_shape}")
    if np.unique(pairs).size != pairs.size or not g.mask[pairs].all():
        raise ValueError("merge_pairs: pairs must be disjoint and refer to live components")
    out = g.copy()
    if pairs.shape[0] == 0:
        return out
    ab = np.ones((g.capacity, 0)) if g.pd_beta is None else np.ascontiguousarray(g.pd_beta)
    out_ab = np.ones((g.capacity, 0)) if out.pd_beta is None else out.pd_beta
    _merge_pairs(g.w, np.ascontiguousarray(g.m), np.ascontiguousarray(g.P), pairs, out.w, out.m, out.P, ab, out_ab)
    out.mask[pairs[:, 1]] = False
    if out.pd_beta is not None:
        out.pd_beta[pairs[:, 1]] = 1.0
    out.check("after merge_pairs")
    return out


def average_map(g: GM, particle_weights: np.ndarray, prune: float, merge: float, cap: int,
                max_trace: float | None = None, pos_dims: int = 3) -> GM:
    """Particle-weighted average of per-particle map PHDs, reduced (paper eq. (7)).

    ``D_bar(x) = sum_p w_p D^p(x)``: the union of all particles' components with weights
    ``w_p * eta^{p,q}``, then reduced in the order of Mullane et al. 2011 (Table IV):

    1. *per-particle pruning*: components whose own weight ``eta^{p,q} < prune`` are dropped
       (with the paper's 0.1 this keeps a weak, wide, false Gaussian out of the merge so it
       cannot dilute a true one). Pruning the products ``w_p eta`` instead would drop every
       component (``w_p ~ 1/P``), so the threshold acts on ``eta``, not on the product;
    2. components with position trace above ``max_trace`` (m^2) are dropped;
    3. greedy Mahalanobis merging with ``merge`` (as :func:`prune_merge`) of the weighted union;
    4. merged components with weight ``< prune`` are dropped (a landmark carried by too small a
       share of the particle weight), and the ``cap`` largest are kept.

    Args:
        g: particle maps, batch shape ``(P,)``, ``Q`` slots, dimension ``d``.
        particle_weights: ``(P,)`` non-negative particle weights (normalised to sum 1 here).
        prune, merge, cap, max_trace, pos_dims: as in :func:`prune_merge`.

    Returns:
        A single mixture (batch shape ``()``), compacted.
    """
    if g.w.ndim != 2:
        raise ValueError(f"average_map expects a batch of shape (P,), got batch shape {g.batch_shape}")
    pw = np.asarray(particle_weights, dtype=float)
    if pw.shape != g.batch_shape:
        raise ValueError(f"particle_weights shape {pw.shape} != batch shape {g.batch_shape}")
    if not np.all(np.isfinite(pw)) or np.any(pw < 0) or pw.sum() <= 0:
        raise FloatingPointError("particle weights must be finite, non-negative and not all zero")
    g.check("in average_map input")
    pw = pw / pw.sum()
    keep = _live(g, prune, max_trace, pos_dims) & (pw[:, None] > 0)
    d = g.dim
    sel = keep.reshape(-1)
    if not sel.any():
        return empty((), 0, d, g.pd_beta is not None)
    w = (g.w * pw[:, None]).reshape(-1)[sel]
    m = g.m.reshape(-1, d)[sel]
    P = g.P.reshape(-1, d, d)[sel]
    ab = None if g.pd_beta is None else g.pd_beta.reshape(-1, 2)[sel][None]
    res = _merge_flat(w[None], m[None], P[None], np.ones((1, w.size), bool), merge, ab)
    ow, om, oP, omask = res[:4]
    omask &= ow >= prune
    out = GM(ow[0], om[0], oP[0], omask[0], None if ab is None else res[4][0])
    out = compact(out, min(cap, int(out.count())))
    out.w = np.where(out.mask, out.w, 0.0)
    out.P = symmetrize(out.P)
    out.check("after average_map")
    return out
