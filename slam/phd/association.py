"""Exclusive measurement association for the landmark Gaussians of one type (``filter.types.<T>.association``).

The PHD update (paper eq. (5)) shares every measurement ``z_j`` among all Gaussians in proportion to their terms
``q_ij = p_D w N(z_j)``: a Gaussian can take part of several measurements of one scan, and a measurement near a
strong Gaussian is taken by it even when another measurement fits that Gaussian better. In a street this joins
landmarks: canyon's two image sources 1.53 m apart are seen together by one car, and the stronger Gaussian takes
both measurements, so the second VA's birth (weight ``filter.birth_weight``) never gains weight.

``association = "exclusive"`` reads each Gaussian of weight ``w`` as one landmark that exists with probability
``r = min(w, 1)`` (as the Bernoulli missed rule, :func:`~mmslam.slam.phd.detection.bernoulli_missed_weight`) and
each landmark as producing at most one measurement, each measurement coming from at most one landmark (the
point-target model of multi-Bernoulli / BP-SLAM filters, Leitinger et al. 2019). The marginal association
probabilities of that joint problem are computed by loopy belief propagation on the bipartite graph of
Gaussians and measurements (Williams & Lau, "Approximate evaluation of marginal association probabilities with
belief propagation", IEEE TAES 50(4), 2014). Every other explanation of ``z_j`` (clutter, the BS, the Gaussians of
the other types) is its clutter ``c_j = psi(z_j) - sum_i q_ij``, so the likelihood ratio of Gaussian ``i`` and
``z_j`` and the weight of "no measurement" are

    ``L_ij = r_i p_D,i N_i(z_j) / c_j = (r_i / w_i) q_ij / c_j``,   ``l_i0 = 1 - r_i p_D,i``,

and the messages, from ``nu = 1``, iterated to convergence:

    ``mu_ij = L_ij / (l_i0 + sum_{j' != j} L_ij' nu_ij')``,   ``nu_ij = 1 / (1 + sum_{i' != i} mu_i'j)``.

The marginals ``P(i <-> j) = L_ij nu_ij / D_i``, ``D_i = l_i0 + sum_j L_ij nu_ij``, replace the PHD's shares as
the detected terms (scaled by the mass ``w_i / r_i``): the same CKF posteriors, other weights. The particle weights
(``psi``) are the paper's.
"""
from __future__ import annotations

import numpy as np

BP_TOL = 1e-10
"""Convergence of the messages ``nu`` (largest absolute change)."""
BP_MAX_ITER = 200
L_NEGLIGIBLE = 1e-12
"""A likelihood ratio below this is no association (its probability would be below it)."""
L0_FLOOR = 1e-12
"""Floor of the no-measurement weight ``l_i0`` in the messages (``p_D = 1`` and ``r = 1`` make it 0)."""
LOG_L_MAX = 575.0
"""``log L_ij`` is clipped here (``c_j >= e^-575 psi(z_j)``: no overflow, even divided by :data:`L0_FLOOR`)."""


def _others(x: np.ndarray, axis: int) -> np.ndarray:
    """``sum_{k != i} x_k`` along ``axis`` for every ``i``, from prefix and suffix sums (no cancellation)."""
    zero = np.zeros_like(np.take(x, [0], axis=axis))
    pre = np.concatenate([zero, np.cumsum(x, axis=axis)], axis=axis)
    suf = np.flip(np.concatenate([zero, np.cumsum(np.flip(x, axis=axis), axis=axis)], axis=axis), axis=axis)
    n = x.shape[axis]
    return np.take(pre, np.arange(n), axis=axis) + np.take(suf, np.arange(1, n + 1), axis=axis)


def exclusive_association(L: np.ndarray, l0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Marginal association probabilities by loopy belief propagation (Williams & Lau 2014).

    Args:
        L: ``(P, Q, J)`` finite likelihood ratios ``L_ij >= 0`` of Gaussian ``i`` and measurement ``j`` (0: none).
        l0: ``(P, Q)`` weights ``> 0`` of "Gaussian ``i`` produced no measurement".

    Returns:
        ``(assoc (P, Q, J), D (P, Q))``: ``P(i <-> j)`` and the normaliser ``D_i = l_i0 + sum_j L_ij nu_ij``, so
        ``P(i produced none) = l_i0 / D_i``. Exact where the graph is a tree (one Gaussian, or one measurement);
        per measurement the marginals are scaled to sum to at most 1 (loopy BP's marginals may not).
    """
    L = np.asarray(L, float)
    l0 = np.asarray(l0, float)
    nu = np.ones_like(L)
    for _ in range(BP_MAX_ITER):
        mu = L / (l0[:, :, None] + _others(L * nu, axis=2))  # L_ij / (l_i0 + sum_{j' != j} L_ij' nu_ij')
        new = 1.0 / (1.0 + _others(mu, axis=1))  # 1 / (1 + sum_{i' != i} mu_i'j)
        done = not L.size or float(np.max(np.abs(new - nu))) < BP_TOL
        nu = new
        if done:
            break
    Ln = L * nu
    D = l0 + Ln.sum(axis=2)
    assoc = Ln / D[:, :, None]
    col = assoc.sum(axis=1, keepdims=True)  # per measurement: at most one landmark
    return np.where(col > 1.0, assoc / np.where(col > 1.0, col, 1.0), assoc), D


def exclusive_terms(w: np.ndarray, p_d: np.ndarray, logq: np.ndarray, log_others: np.ndarray, logpsi: np.ndarray,
                    missed: str) -> tuple[np.ndarray, np.ndarray]:
    """Detected and missed weights of one type's Gaussians under exclusive association (module docstring).

    Args:
        w: ``(P, Q)`` predicted weights (0 in dead slots); p_d: ``(P, Q)`` their detection probabilities.
        logq: ``(P, Q, J)`` ``log(p_D w N(z_j))`` of each Gaussian (``-inf``: cannot be detected).
        log_others: ``(P, J)`` ``log c_j``, every other explanation of ``z_j`` (clutter, BS, other types;
            ``-inf`` if none); floored at ``log psi(z_j) - 575``, so every ``L_ij`` is finite.
        logpsi: ``(P, J)`` ``log psi(z_j)`` (:func:`~mmslam.slam.phd.gmphd.log_psi`: ``c_j`` plus this type's terms).
        missed: the type's missed rule. ``bernoulli``: ``w >= 1`` keeps its mass, ``w (1 - p_D) / D_i`` missed
            and ``w P(i <-> j)`` detected; ``w < 1``: ``w (1 - p_D) / (1 - w p_D)``
            (:func:`~mmslam.slam.phd.detection.bernoulli_missed_weight` without the scan), the detections on top
            (a VA detected at two or three steps crosses 1). ``phd``: the BP posterior's missed part,
            ``(w / r) r (1 - p_D) / D_i``, for every ``w`` (the detected and missed parts then sum to ``w r' / r``).
            Where nothing is associated with a sure landmark of ``p_D = 1`` (``D_i = 0``) the missed part is ``w``.

    Returns:
        ``(detected (P, Q, J), missed_w (P, Q))``: the weight of Gaussian ``i`` updated by ``z_j``
        (``(w_i / r_i) P(i <-> j)``) and of its missed-detection term; both finite.
    """
    from .detection import bernoulli_missed_weight

    w, p_d = np.asarray(w, float), np.asarray(p_d, float)
    r = np.minimum(w, 1.0)
    live = w > 0.0
    per_mass = np.where(live, r / np.where(live, w, 1.0), 0.0)  # r / w
    logc = np.maximum(log_others, np.asarray(logpsi, float) - LOG_L_MAX)
    with np.errstate(divide="ignore"):
        logL = np.minimum(np.log(np.where(live, per_mass, 1.0))[:, :, None] + logq - logc[:, None, :], LOG_L_MAX)
    L = np.where(live[:, :, None] & np.isfinite(logq), np.exp(logL), 0.0)
    L = np.where(L > L_NEGLIGIBLE, L, 0.0)
    l0 = 1.0 - r * p_d
    rows, cols = np.nonzero(L.any(axis=(0, 2)))[0], np.nonzero(L.any(axis=(0, 1)))[0]  # the Gaussians and
    assoc, S = np.zeros_like(L), np.zeros_like(w)  # measurements in some pair; the rest are not associated at all
    if rows.size:
        l0f = np.maximum(l0[:, rows], L0_FLOOR)
        a, d = exclusive_association(L[:, rows][:, :, cols], l0f)
        assoc[np.ix_(np.arange(L.shape[0]), rows, cols)] = a
        S[:, rows] = d - l0f  # sum_j L_ij nu_ij
    detected = np.where(live, 1.0 / np.where(live, per_mass, 1.0), 0.0)[:, :, None] * assoc
    den = l0 + S
    posterior = np.where(den > 0.0, w * (1.0 - p_d) / np.where(den > 0.0, den, 1.0), w)  # (w / r) r (1 - p) / D
    if missed == "bernoulli":
        missed_w = np.where(w >= 1.0, posterior, bernoulli_missed_weight(w, p_d))
    else:
        missed_w = posterior
    return detected, np.where(live, missed_w, 0.0)

