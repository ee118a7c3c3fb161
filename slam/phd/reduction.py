"""Gaussian-mixture reduction: pruning, greedy Mahalanobis merging and capping.

Public functions, all pure:

- :func:`prune_merge`: Vo & Ma 2006 ("The Gaussian mixture probability hypothesis density
  filter"), Table II, applied to every mixture of a batch at once (e.g. the ``P`` particle maps);
- :func:`average_map`: the particle-weighted average map PHD of the paper's eq. (7),
  ``sum_p w_p D^p``, reduced in the spirit of Mullane et al. 2011, Table IV;
- :func:`merge_pairs`: moment matching of given pairs (the fused VS map).

The equations are written once, for one mixture, in :mod:`mmslam.slam.phd.merging` (numba ``njit``,
``cache=True``): :func:`survivors` (Table II, step 1), :func:`greedy_clusters` (step 2, the clusters),
:func:`moment_match` (step 2, one cluster's moments) and :func:`cluster_order` (step 3, the
largest ``cap``). :func:`_plan_batch` and :func:`_write_batch` here run them over every mixture of a
batch with the scratch arrays allocated once per batch, not per mixture.

Shapes follow :mod:`mmslam.slam.core.gm`: weights ``(*B, Q)``, means ``(*B, Q, d)``, covariances
``(*B, Q, d, d)``, mask ``(*B, Q)``. Means are in the global frame (m; VS also m/s and rad/s).
"""
from __future__ import annotations

import math

import numpy as np

from .detection import beta_pool
from ..core.gm import GM, NO_LABEL, dead_gaussian, finite_gaussian  # noqa: F401  (re-exported)
from ..core.jit import batch_kernel
from .merging import (_cholesky, _forward_solve, cluster_order, greedy_clusters, moment_match,  # noqa: F401
                      moment_match_at, sort_descending, survivors)


_OK, _NONFINITE, _SINGULAR = -1, -2, -3
"""Status codes of the batch kernels (``_write_batch``: ``>= 0`` is the index of a mixture whose output
is not finite; ``_plan_batch``: ``>= 0`` is the largest number of clusters kept, no error)."""


@batch_kernel
def _plan_batch(w_prune: np.ndarray, w: np.ndarray, m: np.ndarray, P: np.ndarray, mask: np.ndarray, prune: float,
                max_trace: float, pos_dims: int, merge: float, min_weight: float, cap: int, sort_input: bool,
                sort_output: bool, members: np.ndarray, heads: np.ndarray, starts: np.ndarray, order: np.ndarray,
                count: np.ndarray, scratch: tuple) -> int:
    """Clusters of every mixture ``n`` of a flat batch ``(N, Q, ...)``: :func:`survivors` of
    ``w_prune`` (sorted by descending ``w`` if ``sort_input``: the slot order of a compacted
    mixture), :func:`greedy_clusters` with weights ``w``, :func:`cluster_order` (``min_weight``,
    ``sort_output``), at most ``cap``. Writes ``members, heads, order (N, Q)``, ``starts (N, Q + 1)``,
    ``count (N,)`` (clusters kept). ``scratch``: :func:`_plan_scratch` (a runtime-free kernel
    allocates nothing, :mod:`mmslam.slam.core.jit`).

    Returns the largest ``count`` (0 for ``N = 0``), or ``_NONFINITE`` (a live component, ``mask``, has a non-finite ``w``, ``m`` or ``P``)
    or ``_SINGULAR``.
    """
    N, q, d = m.shape
    L, r2, D, rem, W = scratch
    most = 0
    for n in range(N):
        ns = survivors(w_prune[n], w[n], m[n], P[n], mask[n], prune, max_trace, pos_dims, rem)
        if ns < 0:
            return _NONFINITE
        if sort_input:
            sort_descending(w[n], rem, ns)
        K = greedy_clusters(w[n], m[n], P[n], rem, ns, merge, sort_input, L, r2, D, members[n], heads[n], starts[n],
                            W)
        if K < 0:
            return _SINGULAR
        count[n] = min(cap, cluster_order(W, K, min_weight, sort_output, order[n]))
        most = max(most, count[n])
    return most


@batch_kernel
def _write_batch(w: np.ndarray, m: np.ndarray, P: np.ndarray, ab: np.ndarray, members: np.ndarray,
                 heads: np.ndarray, starts: np.ndarray, order: np.ndarray, count: np.ndarray, out_w: np.ndarray,
                 out_m: np.ndarray, out_P: np.ndarray, out_mask: np.ndarray, out_ab: np.ndarray) -> int:
    """The planned clusters (:func:`_plan_batch`) of every mixture ``n``: slot ``r < count[n]`` gets
    the :func:`moment_match` of cluster ``order[n, r]`` (offsets from its head) and, with Beta
    parameters ``ab (N, Q, 2)``, their :func:`~mmslam.slam.phd.detection.beta_pool` (``(N, Q, 0)``:
    none); the other slots ``w = 0``, ``m = 0``, ``P = I``, ``(s, t) = (1, 1)``, masked.

    Returns ``_OK`` or the first ``n`` with a non-finite merged component.
    """
    for n in range(out_w.shape[0]):
        for r in range(out_w.shape[1]):
            if r < count[n]:
                c = order[n, r]
                out_w[n, r] = moment_match_at(w, m, P, n, members, starts[n, c], starts[n, c + 1], heads[n, c],
                                              out_m, out_P, r)
                if ab.shape[2]:
                    beta_pool(w[n], ab[n], members[n, starts[n, c]:starts[n, c + 1]], out_ab[n, r])
                out_mask[n, r] = True
                if not finite_gaussian(out_w[n, r], out_m[n, r], out_P[n, r]):
                    return n
            else:
                out_w[n, r] = 0.0
                dead_gaussian(out_m[n, r], out_P[n, r])
                out_mask[n, r] = False
                for a in range(out_ab.shape[2]):
                    out_ab[n, r, a] = 1.0
    return _OK


def _plan_scratch(q: int, d: int) -> tuple[np.ndarray, ...]:
    """Scratch of :func:`_plan_batch` for ``Q`` slots of dimension ``d``: ``(L (Q, d, d), r2 (Q,), D (d,),
    rem (Q,) int64, W (Q,))`` (the Cholesky factors, distances, a difference, survivors, cluster weights
    of :func:`greedy_clusters`)."""
    return np.empty((q, d, d)), np.empty(q), np.empty(d), np.empty(q, np.int64), np.empty(q)


def _reduce(w_prune: np.ndarray, w: np.ndarray, m: np.ndarray, P: np.ndarray, mask: np.ndarray,
            ab: np.ndarray | None, prune: float, max_trace: float | None, pos_dims: int, merge: float,
            min_weight: float, cap: int, sort_input: bool, sort_output: bool, stage: str,
            capacity: int | None = None, label: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Reduce every mixture of a flat batch (:func:`_plan_batch`, :func:`_write_batch`).

    ``w_prune, w (N, Q)``: the weights pruned and the weights merged; ``m (N, Q, d)``,
    ``P (N, Q, d, d)``, ``mask (N, Q)``; ``ab (N, Q, 2)`` Beta parameters or None; ``label (N, Q)``
    component labels or None (a merged component takes its cluster head's: the largest weight,
    Vo & Ma's ``j``). The output has ``capacity`` slots (default: the largest number of clusters
    kept): ``(w, m, P, mask, ab or None, label or None)``.

    Raises FloatingPointError (naming ``stage``) for a non-finite live input or output component
    or a singular / indefinite covariance to merge.
    """
    n, q, d = m.shape
    w = np.ascontiguousarray(w, dtype=float)
    m = np.ascontiguousarray(m, dtype=float)
    P = np.ascontiguousarray(P, dtype=float)
    members, heads, order = np.empty((3, n, q), np.int64)  # one allocation
    starts = np.empty((n, q + 1), np.int64)
    count = np.empty(n, np.int64)
    status = _plan_batch(np.ascontiguousarray(w_prune, dtype=float), w, m, P, np.ascontiguousarray(mask, dtype=bool),
                         float(prune), np.inf if max_trace is None else float(max_trace), int(pos_dims),
                         float(merge), float(min_weight), max(int(cap), 0), sort_input, sort_output, members, heads,
                         starts, order, count, _plan_scratch(q, d))
    if status == _NONFINITE:
        raise FloatingPointError(f"non-finite Gaussian component in {stage} input")
    if status == _SINGULAR:
        raise FloatingPointError("singular or indefinite covariance in Gaussian-mixture merging")
    k = status if capacity is None else capacity
    ab_in = np.empty((n, q, 0)) if ab is None else np.ascontiguousarray(ab, dtype=float)
    out = (np.empty((n, k)), np.empty((n, k, d)), np.empty((n, k, d, d)), np.empty((n, k), bool),
           np.empty((n, k, ab_in.shape[2])))
    if _write_batch(w, m, P, ab_in, members, heads, starts, order, count, *out) != _OK:
        raise FloatingPointError(f"non-finite Gaussian component after {stage}")
    return out[:4] + (None if ab is None else out[4], None if label is None else _head_labels(label, heads, order,
                                                                                              count, k))


def _head_labels(label: np.ndarray, heads: np.ndarray, order: np.ndarray, count: np.ndarray, k: int) -> np.ndarray:
    """``(N, k)`` the label of each output slot of :func:`_write_batch`: slot ``r < count[n]`` holds cluster
    ``order[n, r]``, whose head is ``heads[n, order[n, r]]``; the other slots :data:`NO_LABEL`."""
    n = label.shape[0]
    r = min(k, order.shape[1])
    kept = np.arange(r) < count[:, None]  # order[n, r:] and heads of dropped clusters are not written
    head = np.take_along_axis(heads, np.where(kept, order[:, :r], 0), 1)  # (N, r) each kept cluster's head
    lab = np.take_along_axis(np.asarray(label, np.int64), np.where(kept, head, 0), 1)
    out = np.full((n, k), NO_LABEL, np.int64)
    out[:, :r] = np.where(kept, lab, NO_LABEL)
    return out


def _merge_flat(w: np.ndarray, m: np.ndarray, P: np.ndarray, keep: np.ndarray, merge: float,
                ab: np.ndarray | None = None):
    """:func:`greedy_clusters` and :func:`moment_match` of a flat batch ``(N, Q, ...)`` (no pruning,
    sorting or cap); returns ``(w, m, P, mask)`` with ``K <= Q`` slots (``K`` = the largest number of
    clusters; slot ``k`` holds cluster ``k``, dead slots 0 / I); with Beta detection parameters
    ``ab (N, Q, 2)`` also their cluster pool ``(N, K, 2)`` (dead slots (1, 1)) as a fifth item.

    Raises FloatingPointError if a kept covariance is singular or not positive definite.
    """
    n, q, d = np.shape(m)
    res = _reduce(w, w, m, P, keep, None if ab is None else np.reshape(ab, (n, q, 2)), -np.inf, None, d, merge,
                  -np.inf, q, False, False, "merging")
    return res[:4] if ab is None else res[:5]


def prune_merge(g: GM, prune: float, merge: float, cap: int, max_trace: float | None = None,
                pos_dims: int = 3, *, fixed_capacity: bool = False) -> GM:
    """Prune, merge and cap every mixture of a batch (Vo & Ma 2006, Table II).

    Steps, for each mixture of the batch independently (one compiled pass over the batch):

    1. drop components with ``w < prune``, and, if ``max_trace`` is given, components whose
       position covariance trace ``trace(P[:pos_dims, :pos_dims]) > max_trace`` (m^2)
       (:func:`survivors`); the others in descending weight order (stable);
    2. greedy merging: take the highest-weight remaining component ``j``; the cluster is every
       remaining ``i`` with ``(m_i - m_j)^T P_i^{-1} (m_i - m_j) <= merge`` (squared Mahalanobis
       distance over all ``d`` state dimensions, e.g. ``49 = 7^2``); replace the cluster by its
       moment match ``w = sum w_i``, ``m = sum w_i m_i / w``,
       ``P = sum w_i (P_i + (m - m_i)(m - m_i)^T) / w``; repeat until none remain
       (:func:`greedy_clusters`, :func:`moment_match`; Beta parameters: ``beta_pool``; labels:
       the label of ``j``, the cluster's largest weight);
    3. keep the ``cap`` largest merged components (:func:`cluster_order`).

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
        weight; dead slots ``w = 0``, ``m = 0``, ``P = I``), exactly symmetric covariances.

    Raises:
        FloatingPointError: a live component has a non-finite weight, mean or covariance, or a
            surviving covariance is singular.
    """
    B, q, d = g.batch_shape, g.capacity, g.dim
    n = int(np.prod(B, dtype=int))
    w = g.w.reshape(n, q)
    w, m, P, mask, ab, lab = _reduce(w, w, g.m.reshape(n, q, d), g.P.reshape(n, q, d, d), g.mask.reshape(n, q),
                                     None if g.pd_beta is None else g.pd_beta.reshape(n, q, 2), prune, max_trace,
                                     pos_dims, merge, -np.inf, cap, True, True, "prune_merge",
                                     max(int(cap), 0) if fixed_capacity else None,
                                     None if g.label is None else _labels_of(g).reshape(n, q))
    k = w.shape[-1]
    return GM(w.reshape(B + (k,)), m.reshape(B + (k, d)), P.reshape(B + (k, d, d)), mask.reshape(B + (k,)),
              None if ab is None else ab.reshape(B + (k, 2)), None if lab is None else lab.reshape(B + (k,)))


def _labels_of(g: GM) -> np.ndarray:
    """``g.label`` as int64 of the batch's slot shape; ValueError naming both shapes if it is not."""
    if np.shape(g.label) != g.w.shape:
        raise ValueError(f"GM.label has shape {np.shape(g.label)}; expected the weights' {g.w.shape}")
    return np.asarray(g.label, np.int64)


@batch_kernel
def _merge_pairs(w: np.ndarray, m: np.ndarray, P: np.ndarray, pairs: np.ndarray,
                 out_w: np.ndarray, out_m: np.ndarray, out_P: np.ndarray, ab: np.ndarray, out_ab: np.ndarray) -> None:
    """:func:`moment_match` of each pair ``(i, j)`` into slot ``i``; slot ``j`` set to ``w = 0, m = 0, P = I``
    (Beta parameters ``ab (Q, 2)``: :func:`~mmslam.slam.phd.detection.beta_pool`; ``(Q, 0)``: none)."""
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
    for a cluster of two); the merged component takes slot ``i`` (and the label of the heavier of
    the two, ``i`` on a tie) and slot ``j`` is freed. Used
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
    if out.label is not None:
        i, j = pairs[:, 0], pairs[:, 1]
        lab = _labels_of(g)
        out.label[i] = np.where(g.w[i] >= g.w[j], lab[i], lab[j])
        out.label[j] = NO_LABEL
    out.check("after merge_pairs")
    return out


def _pool_labels(w_own: np.ndarray, w: np.ndarray, m: np.ndarray, P: np.ndarray, mask: np.ndarray,
                 ab: np.ndarray | None, label: np.ndarray, slots: int, prune: float, max_trace: float | None,
                 pos_dims: int) -> tuple[np.ndarray, ...]:
    """One component per label of the union of a vehicle's particle maps (:func:`average_map`, ``by_label``).

    The union holds the particles' maps one after the other, ``slots`` components each (component
    ``i`` is of particle ``i // slots``): ``w_own, w (n,)``, ``m (n, d)``, ``P (n, d, d)``,
    ``mask (n,)``, ``ab (n, 2)`` Beta parameters or None, ``label (n,)``. The live components that
    pass the copy rule (``w_own >= prune``, position trace ``<= max_trace``; ``w_own`` NaN, a
    particle of weight 0, never passes) are grouped by label, one copy per particle: a particle's
    heaviest component of the label (a label's other components in that particle, e.g. its Gaussian
    corrected by another landmark's measurement, are other hypotheses; they and the unlabelled ones,
    ``label < 0``, are groups of one). Each group is moment-matched with the weights ``w``
    (:func:`moment_match_at`, offsets from its largest weight; Beta: ``beta_pool``): the copies of
    one landmark in the particles' maps become one component whatever their spread. The moments
    are taken with each group's weights divided by its largest (then ``W`` times it): a particle of
    subnormal weight ``w_p`` would otherwise lose its covariances' digits in ``w_i P_i / W``. A copy
    with ``w = 0`` (``w_p eta`` underflowed) carries no mass and is left out (without labels it
    would fall below ``prune`` as a cluster of its own, or add nothing to a heavier one).

    Returns ``(w (1, G), m (1, G, d), P (1, G, d, d), ab (1, G, 2) or None, label (1, G))``, the groups
    in the order of their keys (labels; groups of one: :data:`NO_LABEL`). Raises FloatingPointError
    for a non-finite live input component.
    """
    n, d = m.shape[0], m.shape[-1]
    ok = np.isfinite(w) & np.isfinite(m).all(-1) & np.isfinite(P).all((-1, -2))
    if not ok[mask].all():
        raise FloatingPointError("non-finite Gaussian component in average_map input")
    keep = mask & (w_own >= prune) & (w > 0)  # NaN (particles of weight 0) fails; w = 0: no mass
    if max_trace is not None:
        k = min(pos_dims, d)
        keep &= np.trace(P[:, :k, :k], axis1=-2, axis2=-1) <= max_trace
    idx = np.flatnonzero(keep)
    lab, part, wk = np.asarray(label, np.int64)[idx], idx // max(slots, 1), w[idx]
    o = np.lexsort((-wk, part, lab))  # by label, particle, then the largest weight first
    later = np.zeros(idx.size, bool)  # not the heaviest of its label in its particle
    later[o[1:]] = (lab[o][1:] == lab[o][:-1]) & (part[o][1:] == part[o][:-1])
    key = np.where(later | (lab < 0), -1 - np.arange(idx.size), lab)  # groups of one: distinct negative keys
    order = np.lexsort((-wk, key))  # by key, the largest weight first (stable on ties)
    members, key = idx[order], key[order]
    heads = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if idx.size else np.zeros(0, np.int64)
    G = heads.size
    starts = np.r_[heads, idx.size].astype(np.int64)
    top = w[members[heads]]  # (G,) each group's largest weight, > 0
    ws = np.zeros(n)
    ws[members] = w[members] / np.repeat(top, np.diff(starts))  # in (0, 1], the head's 1
    wc, mc, Pc = (np.ascontiguousarray(a, dtype=float)[None] for a in (ws, m, P))
    ab_in = np.empty((1, n, 0)) if ab is None else np.ascontiguousarray(ab, dtype=float)[None]
    out = (np.empty((1, G)), np.empty((1, G, d)), np.empty((1, G, d, d)), np.empty((1, G), bool),
           np.empty((1, G, ab_in.shape[2])))
    if _write_batch(wc, mc, Pc, ab_in, members[None], members[heads][None], starts[None],
                    np.arange(G, dtype=np.int64)[None], np.array([G], np.int64), *out) != _OK:
        raise FloatingPointError("non-finite Gaussian component after average_map's label pooling")
    return out[0] * top, out[1], out[2], None if ab is None else out[4], np.maximum(key[heads], NO_LABEL)[None]


def average_map(g: GM, particle_weights: np.ndarray, prune: float, merge: float, cap: int,
                max_trace: float | None = None, pos_dims: int = 3, *, by_label: bool = False) -> GM:
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

    With ``by_label`` (``fusion.average_by_label``; ``g.label`` required), after steps 1-2 the
    copies of one landmark in the particles' maps, each particle's heaviest component of a label,
    are moment-matched into one, particle-weighted and without a gate (:func:`_pool_labels`): their
    means differ along the line of sight by the particles' clock-bias and position spread while
    each covariance is thin there, so the gate of step 3 would split them into clusters that step
    4 drops (docs/implementation-notes.md, "VA 2 and the averaged map"). Steps 3-4 then reduce the
    pooled components; each output component takes its cluster leader's label.

    Args:
        g: particle maps, batch shape ``(P,)``, ``Q`` slots, dimension ``d``.
        particle_weights: ``(P,)`` non-negative particle weights (normalised to sum 1 here).
        prune, merge, cap, max_trace, pos_dims: as in :func:`prune_merge`.
        by_label: the label pooling above.

    Returns:
        A single mixture (batch shape ``()``), compacted.

    Raises:
        ValueError: ``particle_weights`` not of the batch shape, or ``by_label`` without labels.
        FloatingPointError: non-finite or negative particle weights, a non-finite live component.
    """
    if g.w.ndim != 2:
        raise ValueError(f"average_map expects a batch of shape (P,), got batch shape {g.batch_shape}")
    pw = np.asarray(particle_weights, dtype=float)
    if pw.shape != g.batch_shape:
        raise ValueError(f"particle_weights shape {pw.shape} != batch shape {g.batch_shape}")
    # a finite positive sum of non-negative weights: every weight finite (NaN or inf make the sum
    # non-finite, -inf is negative); two reductions instead of four
    with np.errstate(invalid="ignore"):  # inf + -inf: NaN, rejected below
        tot = float(pw.sum())
    if not (math.isfinite(tot) and tot > 0.0):
        raise FloatingPointError("particle weights must be finite, non-negative and not all zero")
    pw = pw / tot
    low = float(pw.min(initial=np.inf))
    if low < 0.0:
        raise FloatingPointError("particle weights must be finite, non-negative and not all zero")
    n, d = g.w.size, g.dim
    # one mixture, the union of the particles' components (particle-major order): pruned on their
    # own weights eta (NaN, never kept, in particles of weight 0), merged with the weights w_p eta
    if low > 0.0:  # no particle of weight 0 (the usual case): no NaN to place, no inf * 0
        w_own = g.w.reshape(1, n)
        w_merge = (g.w * pw[:, None]).reshape(1, n)
    else:
        w_own = np.where(pw[:, None] > 0, g.w, np.nan).reshape(1, n)
        with np.errstate(invalid="ignore"):  # inf * 0: NaN, a non-finite input the kernel reports
            w_merge = (g.w * pw[:, None]).reshape(1, n)
    ab = None if g.pd_beta is None else g.pd_beta.reshape(1, n, 2)
    lab = None if g.label is None else _labels_of(g).reshape(1, n)
    m, P, mask, step1 = g.m.reshape(1, n, d), g.P.reshape(1, n, d, d), g.mask.reshape(1, n), prune
    if by_label:
        if lab is None:
            raise ValueError("average_map(by_label=True) needs component labels (GM.label); the local filter "
                             "labels its births when fusion.average_by_label is on")
        w_merge, m, P, ab, lab = _pool_labels(w_own[0], w_merge[0], m[0], P[0], mask[0],
                                              None if ab is None else ab[0], lab[0], g.capacity, prune, max_trace,
                                              pos_dims)
        mask = np.ones(w_merge.shape, bool)
        w_own, max_trace, step1 = w_merge, None, -np.inf  # steps 1-2 done on the copies
    w, m, P, mask, ab, lab = _reduce(w_own, w_merge, m, P, mask, ab, step1, max_trace, pos_dims, merge, prune, cap,
                                     False, True, "average_map", label=lab)
    return GM(w[0], m[0], P[0], mask[0], None if ab is None else ab[0], None if lab is None else lab[0])
