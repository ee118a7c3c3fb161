"""Gaussian-mixture reduction: pruning, greedy Mahalanobis merging and capping.

Two public functions, both pure and batched over leading axes:

- :func:`prune_merge`: Vo & Ma 2006 ("The Gaussian mixture probability hypothesis density
  filter"), Table II, applied to every mixture of a batch at once (e.g. the ``P`` particle maps).
- :func:`average_map`: the particle-weighted average map PHD of the paper's eq. (prevMFave),
  ``sum_p w_p D^p``, reduced in the spirit of Mullane et al. 2011, Table IV.

Shapes follow :mod:`mmslam.slam.gm`: weights ``(*B, Q)``, means ``(*B, Q, d)``, covariances
``(*B, Q, d, d)``, mask ``(*B, Q)``. Means are in the global frame (m; VS also m/s and rad/s).
"""
from __future__ import annotations

import numpy as np

from .gm import GM, compact, empty, symmetrize
from .gmphd import soa_cholesky, soa_forward_solve


def _live(g: GM, prune: float, max_trace: float | None, pos_dims: int) -> np.ndarray:
    """Mask of components that survive pruning: live, ``w >= prune``, position trace small."""
    keep = g.mask & (g.w >= prune)
    if max_trace is not None:
        tr = np.trace(g.P[..., :pos_dims, :pos_dims], axis1=-2, axis2=-1)
        keep &= tr <= max_trace
    return keep


def _inv_spd(P: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive-definite matrices ``(..., d, d)`` (closed form for d <= 3).

    Raises FloatingPointError if a matrix is singular or not positive definite (non-positive
    determinant or non-finite inverse).
    """
    d = P.shape[-1]
    if d == 3:
        # closed form on contiguous entry rows (batch last): the same arithmetic as on the
        # strided (..., 3, 3) views, faster
        T = P.reshape(-1, 9).T  # (9, N) view
        a, b, c, e, f, i = (np.ascontiguousarray(T[k]) for k in (0, 1, 2, 4, 5, 8))
        A0, A1, A2 = e * i - f * f, c * f - b * i, b * f - c * e
        det = a * A0 + b * A1 + c * A2
        if not np.all(det > 0):
            raise FloatingPointError("singular or indefinite covariance in Gaussian-mixture merging")
        iT = np.empty((9, T.shape[1]))
        iT[0] = A0
        iT[1] = iT[3] = A1
        iT[2] = iT[6] = A2
        iT[4] = a * i - c * c
        iT[5] = iT[7] = b * c - a * f
        iT[8] = a * e - b * b
        iT /= det
        inv = np.ascontiguousarray(iT.T).reshape(P.shape)
    else:
        inv = _inv_spd_cholesky(P)
        if inv is None:  # not numerically positive definite: the generic inverse decides
            try:
                inv = symmetrize(np.linalg.inv(P))
            except np.linalg.LinAlgError:
                raise FloatingPointError("singular covariance in Gaussian-mixture merging") from None
    if not np.all(np.isfinite(inv)):
        raise FloatingPointError("singular covariance in Gaussian-mixture merging")
    return inv


def _inv_spd_cholesky(P: np.ndarray) -> np.ndarray | None:
    """``P^-1 = L^-T L^-1`` for SPD ``P (..., d, d)`` with batch-last closed-form kernels.

    Returns None if some Cholesky pivot is not positive (the caller falls back to LAPACK).
    The result is exactly symmetric (lower triangle computed, mirrored).
    """
    sh, d = P.shape[:-2], P.shape[-1]
    if P.size == 0:
        return np.empty_like(P)
    A = np.moveaxis(P.reshape(-1, d, d), 0, -1)  # (d, d, N)
    L = soa_cholesky(np.ascontiguousarray(A))
    diag = np.einsum("iin->in", L)
    if not (np.isfinite(diag).all() and (diag > 0).all()):
        return None
    Linv = soa_tril_inverse(L)  # (d, d, N), exact zeros above the diagonal
    # (L^-T L^-1)[i, j] = sum_k Linv[k, i] Linv[k, j]: only k >= max(i, j) is non-zero
    inv = np.empty_like(Linv)
    for i in range(d):
        inv[i, :i + 1] = np.einsum("kn,kbn->bn", Linv[i:, i], Linv[i:, :i + 1])
        inv[:i, i] = inv[i, :i]
    return inv.transpose(2, 0, 1).reshape(sh + (d, d))


def soa_tril_inverse(L: np.ndarray) -> np.ndarray:
    """Inverses of lower-triangular ``L (d, d, N)`` (batch last) by forward substitution.

    The same operations as ``soa_forward_solve(L, I)`` restricted to the lower triangle (the
    entries above the diagonal are exactly 0 there too), so the result is bit-identical to it
    at about half the cost. Returns ``(d, d, N)``, lower triangular.
    """
    d = L.shape[0]
    X = np.zeros_like(L)
    tmp = np.empty(L.shape[1:])
    for a in range(d):
        Xa = X[a, :a + 1]  # row a of L^-1, columns 0..a
        Xa[a] = 1.0
        for b in range(a):  # row b is non-zero in columns 0..b only
            t = tmp[:b + 1]
            np.multiply(L[a, b], X[b, :b + 1], out=t)
            np.subtract(Xa[:b + 1], t, out=Xa[:b + 1])
        np.divide(Xa, L[a, a], out=Xa)
    return X


_PAIRWISE_BUDGET = 8_000_000  # max N*Q*Q entries (64 MB) of the precomputed pairwise distances
_ONEHOT_BUDGET = 2_000_000  # max N*K*Q entries of the one-hot cluster-weight matrix
_ONEHOT_MAX_CLUSTERS = 64  # beyond, the O(K Q d^2) products cost more than the scatter-add


def _label_single(w: np.ndarray, mc: np.ndarray, Aflat: np.ndarray, b: np.ndarray, c: np.ndarray,
                  tr: np.ndarray, keep: np.ndarray, merge: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy cluster labels of one mixture, shrinking the candidate set as clusters are taken.

    Same rule and tie-breaking as the batched loop (head = first index of maximal weight).
    ``tr (Q,)`` are the covariance traces, used for an exact Euclidean pre-gate.
    Returns ``label (Q,)`` (-1 for pruned) and ``heads (K,)``.
    """
    d = mc.shape[-1]
    label = np.full(w.shape[0], -1)
    heads = []
    alive = np.nonzero(keep)[0]
    alive = alive[np.argsort(-w[alive], kind="stable")]
    # Euclidean gate: D^T A_i D <= merge implies |D|^2 <= merge * lambda_max(P_i) <= merge * trace(P_i)
    r2 = merge * tr * (1.0 + 1e-9) + 1e-12
    cols = np.ascontiguousarray(mc.T)  # (d, Q): the gate's squared distance summed column by column
    while alive.size:
        j = alive[0]
        mj = mc[j]
        ca = cols[:, alive]  # (d, A)
        e2 = ca[0] - mj[0]
        e2 *= e2
        for k in range(1, d):  # the same sequential sum as np.sum(..., axis=-1) over d < 8 terms
            t = ca[k] - mj[k]
            t *= t
            e2 += t
        near = np.nonzero(e2 <= r2[alive])[0]
        cand = alive[near]
        dist = Aflat[cand] @ np.outer(mj, mj).reshape(d * d) - 2.0 * (b[cand] @ mj) + c[cand]
        L = np.zeros(alive.size, bool)
        L[near] = dist <= merge
        L[0] = True
        label[alive[L]] = len(heads)
        heads.append(j)
        alive = alive[~L]
    return label, np.asarray(heads, dtype=int)


def _outer(a: np.ndarray) -> np.ndarray:
    """Outer products ``a a^T``: ``(..., d) -> (..., d, d)``, one multiplication per entry (the same
    values as ``a[..., :, None] * a[..., None, :]``, without broadcasting loops over ``d``)."""
    return np.einsum("...i,...j->...ij", a, a)


def _merge_flat(w: np.ndarray, m: np.ndarray, P: np.ndarray, keep: np.ndarray,
                merge: float, pairwise: bool | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Greedy merging on a flat batch ``(N, Q, ...)``; returns ``(w, m, P, mask)`` with ``K <= Q``
    slots (``K`` = the largest number of clusters; slot ``k`` holds cluster ``k``, dead slots 0 / I).

    The loop runs over merge iterations (at most ``Q``), never over batch members: iteration
    ``it`` picks every member's current highest-weight remaining component (the cluster head)
    and labels its cluster ``it``. The squared distance of candidate ``i`` to head ``j`` is
    expanded as ``m_j^T A_i m_j - 2 m_j^T A_i m_i + m_i^T A_i m_i`` (``A_i = P_i^{-1}``, means
    centred per mixture first to limit cancellation); for small problems the full ``(N, Q, Q)``
    matrix is formed once with batched matrix products. After labelling, all clusters' moments
    are computed at once (one-hot matrix products), spreads taken relative to the cluster head.
    """
    n, q, d = m.shape
    if n == 0 or q == 0 or not keep.any():
        return np.zeros((n, 0)), np.zeros((n, 0, d)), np.zeros((n, 0, d, d)), np.zeros((n, 0), bool)
    out_mask = np.zeros((n, q), bool)
    cnt = keep.sum(-1, keepdims=True)
    centre = np.where(keep[..., None], m, 0.0).sum(-2) / np.maximum(cnt, 1)  # (N, d)
    mc = np.where(keep[..., None], m - centre[:, None, :], 0.0)
    if 2 * int(keep.sum()) >= keep.size:  # mostly live: invert in place (identity in dead slots)
        A = _inv_spd(np.where(keep[..., None, None], P, np.eye(d)))
    else:
        A = np.broadcast_to(np.eye(d), (n, q, d, d)).copy()
        A[keep] = _inv_spd(P[keep])
    Aflat = A.reshape(n, q, d * d)
    b = np.einsum("nqij,nqj->nqi", A, mc)  # (N, Q, d)  A_i m_i
    c = np.einsum("nqi,nqi->nq", b, mc)  # (N, Q)     m_i^T A_i m_i
    if pairwise is None:
        pairwise = n * q * q <= _PAIRWISE_BUDGET
    if pairwise:
        outer_all = _outer(mc).reshape(n, q, d * d)
        # Dt[n, j, i] = distance of candidate i to head j (P_i used); head-major for contiguous rows
        Dt = outer_all @ np.swapaxes(Aflat, -1, -2) - 2.0 * (mc @ np.swapaxes(b, -1, -2)) + c[:, None, :]
    remaining = keep.copy()
    label = np.full((n, q), -1)
    heads = np.zeros((n, q), int)
    rows = np.arange(n)
    n_it = 0
    if n == 1 and not pairwise:
        tr = np.trace(P[0], axis1=-2, axis2=-1)
        lab, hd = _label_single(w[0], mc[0], Aflat[0], b[0], c[0], tr, keep[0], merge)
        label[0], n_it = lab, hd.size
        heads[0, :n_it] = hd
        out_mask[0, :n_it] = True
        remaining[:] = False
    for it in range(q if remaining.any() else 0):
        active = remaining.any(-1)  # (N,)
        if not active.any():
            break
        j = np.argmax(np.where(remaining, w, -np.inf), axis=-1)  # (N,)
        if pairwise:
            dist = Dt[rows, j]
        else:
            mj = mc[rows, j]
            outer = (mj[:, :, None] * mj[:, None, :]).reshape(n, 1, d * d)
            dist = (Aflat * outer).sum(-1) - 2.0 * (b * mj[:, None, :]).sum(-1) + c
        L = remaining & (dist <= merge)
        L[rows, j] = remaining[rows, j]  # the head always joins its own cluster
        np.copyto(label, it, where=L)
        heads[:, it] = j
        out_mask[:, it] = active
        remaining &= ~L
        n_it = it + 1
    # ---- moments of all clusters at once (scatter-add by cluster label)
    valid = label >= 0
    flat = (rows[:, None] * n_it + label)[valid]  # (M,) cluster index in the flattened (N, K)
    wv = w[valid]
    W = np.bincount(flat, weights=wv, minlength=n * n_it).reshape(n, n_it)
    Wsafe = np.where(W > 0, W, 1.0)
    head_of = heads[rows[:, None], np.maximum(label, 0)]  # (N, Q)
    diff_all = np.where(valid[..., None], mc - mc[rows[:, None], head_of], 0.0)  # (N, Q, d) offset from head
    if n_it <= _ONEHOT_MAX_CLUSTERS and n * n_it * q <= _ONEHOT_BUDGET:
        # few clusters per mixture (the usual case): weighted one-hot matrix products instead
        # of the slower unbuffered scatter-add (the same sums up to summation order)
        Wm = np.where(label[:, None, :] == np.arange(n_it)[None, :, None], w[:, None, :], 0.0)  # (N, K, Q)
        acc1 = Wm @ diff_all  # (N, K, d)
        second = _outer(diff_all)
        second += P
        second[~valid] = 0.0
        acc2 = Wm @ second.reshape(n, q, d * d)  # (N, K, d * d)
    else:
        diff = diff_all[valid]  # (M, d)
        acc1 = np.zeros((n * n_it, d))
        np.add.at(acc1, flat, wv[:, None] * diff)
        second = P[valid] + diff[:, :, None] * diff[:, None, :]  # (M, d, d)
        acc2 = np.zeros((n * n_it, d, d))
        np.add.at(acc2, flat, wv[:, None, None] * second)
    dbar = acc1.reshape(n, n_it, d) / Wsafe[..., None]  # mean offset from the head
    S = acc2.reshape(n, n_it, d, d) / Wsafe[..., None, None]
    Pbar = S - _outer(dbar)
    mhead = mc[rows[:, None], heads[:, :n_it]]  # (N, K, d)
    act = out_mask[:, :n_it].copy()
    out_w = np.where(act, W, 0.0)
    out_m = np.where(act[..., None], mhead + dbar + centre[:, None, :], 0.0)
    out_P = np.where(act[..., None, None], symmetrize(Pbar), np.eye(d))
    return out_w, out_m, out_P, act


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
    g = compact(GM(np.where(keep, g.w, 0.0), g.m, g.P, keep))
    keep = g.mask
    q, d = g.capacity, g.dim
    if q == 0:
        return compact(g, cap) if fixed_capacity else g
    n = int(np.prod(B, dtype=int))
    w, m, P, mask = _merge_flat(g.w.reshape(n, q), g.m.reshape(n, q, d), g.P.reshape(n, q, d, d),
                                keep.reshape(n, q), merge)
    k = w.shape[-1]
    out = GM(w.reshape(B + (k,)), m.reshape(B + (k, d)), P.reshape(B + (k, d, d)), mask.reshape(B + (k,)))
    if fixed_capacity:
        out = compact(out, cap)
    else:
        out = compact(out, min(cap, int(out.count().max(initial=0))))
    # covariances are exactly symmetric already (symmetrised cluster moments, I in dead slots)
    out.check("after prune_merge")
    return out


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
    i, j = pairs[:, 0], pairs[:, 1]
    wi, wj = g.w[i], g.w[j]
    w = wi + wj
    m = (wi[:, None] * g.m[i] + wj[:, None] * g.m[j]) / w[:, None]
    di, dj = g.m[i] - m, g.m[j] - m
    P = (wi[:, None, None] * (g.P[i] + di[:, :, None] * di[:, None, :])
         + wj[:, None, None] * (g.P[j] + dj[:, :, None] * dj[:, None, :])) / w[:, None, None]
    out.w[i], out.m[i], out.P[i] = w, m, symmetrize(P)
    out.w[j], out.m[j], out.P[j], out.mask[j] = 0.0, 0.0, np.eye(g.dim), False
    out.check("after merge_pairs")
    return out


def average_map(g: GM, particle_weights: np.ndarray, prune: float, merge: float, cap: int,
                max_trace: float | None = None, pos_dims: int = 3) -> GM:
    """Particle-weighted average of per-particle map PHDs, reduced (paper eq. (prevMFave)).

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
        return empty((), 0, d)
    w = (g.w * pw[:, None]).reshape(-1)[sel]
    m = g.m.reshape(-1, d)[sel]
    P = g.P.reshape(-1, d, d)[sel]
    ow, om, oP, omask = _merge_flat(w[None], m[None], P[None], np.ones((1, w.size), bool), merge,
                                    pairwise=False)
    omask &= ow >= prune
    out = GM(ow[0], om[0], oP[0], omask[0])
    out = compact(out, min(cap, int(out.count())))
    out.w = np.where(out.mask, out.w, 0.0)
    out.P = symmetrize(out.P)
    out.check("after average_map")
    return out
