"""The heavy tail of a type's likelihood (``filter.types.<T>.tail_weight`` ``e``, ``tail_scale`` ``K``;
docs/equations.md, eq. (5) with a scale-mixture tail).

The likelihood of ``z_j`` given one landmark Gaussian ``N(m, P)`` is the Gaussian scale mixture
``(1 - e) N(z_j; zhat, S(P)) + e N(z_j; zhat, S(K P))`` (a Student-t-like tail), built from the two CKF updates of
the Gaussian, with ``P`` and with ``K P`` (:func:`mmslam.slam.phd.gmphd.type_terms`): its log-likelihood
(:func:`tail_loglik`) and its posterior, the two updates moment-matched (:func:`tail_update`, :func:`tail_mixture`).
Units and frames are those of eq. (5): the global frame, m. The posterior of a pair is needed only where the
corrected map keeps that component (:func:`read_pairs`), so the moment match can be restricted to those pairs.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..core.jit import batch_kernel
from .ckf import Innovation


@nb.njit(cache=True, error_model="numpy", inline="always")
def logaddexp(a: float, b: float) -> float:
    """``log(exp(a) + exp(b))`` for ``a, b`` in ``[-inf, inf)``."""
    if a == -np.inf:
        return b
    if b == -np.inf:
        return a
    return max(a, b) + math.log1p(math.exp(-abs(a - b)))


@nb.njit(cache=True, error_model="numpy", inline="always")
def mixture_loglik(l1: float, lK: float, log1me: float, loge: float) -> float:
    """``log[(1 - e) N_1 + e N_K] = logaddexp(log(1 - e) + l1, log(e) + lK)`` from the log-likelihoods ``l1``, ``lK``
    of one measurement under the updates with ``P`` and ``K P``; ``log1me = log(1 - e)``, ``loge = log(e)``."""
    return logaddexp(log1me + l1, loge + lK)


@nb.njit(cache=True, error_model="numpy", inline="always")
def tail_update(l1: float, lK: float, m1: np.ndarray, mK: np.ndarray, P1: np.ndarray, PK: np.ndarray,
                log1me: float, loge: float, m: np.ndarray, P: np.ndarray) -> float:
    """The heavy-tailed update of one Gaussian by one measurement, from its CKF updates with ``P`` and ``K P``.

    The likelihood ``(1 - e) N(z; zhat, S_1) + e N(z; zhat, S_K)``: ``l = logaddexp(log(1 - e) + l1, log(e) + lK)``;
    the posterior, the two updates ``N(m1, P1)``, ``N(mK, PK)`` with weights ``a = (1 - e) exp(l1 - l)`` and
    ``1 - a``, moment-matched: ``m = a m1 + (1 - a) mK``, ``P = a (P1 + d1 d1^T) + (1 - a) (PK + dK dK^T)``,
    ``di = mi - m`` (symmetrised).

    Args: ``l1``, ``lK`` the two log-likelihoods; ``m1``, ``mK`` ``(d,)`` and ``P1``, ``PK`` ``(d, d)`` the two
    posteriors; ``log1me = log(1 - e)`` (``-inf`` for ``e = 1``), ``loge = log(e)``; ``m (d,)``, ``P (d, d)``
    receive the posterior. Returns ``l``.
    """
    ll = mixture_loglik(l1, lK, log1me, loge)
    a = math.exp(log1me + l1 - ll) if ll > -np.inf and ll < np.inf else 0.0
    d = m.shape[0]
    for r in range(d):
        m[r] = a * m1[r] + (1.0 - a) * mK[r]
    for r in range(d):
        for c in range(r + 1):
            v = (a * (P1[r, c] + (m1[r] - m[r]) * (m1[c] - m[c]))
                 + (1.0 - a) * (PK[r, c] + (mK[r] - m[r]) * (mK[c] - m[c])))
            w = (a * (P1[c, r] + (m1[c] - m[c]) * (m1[r] - m[r]))
                 + (1.0 - a) * (PK[c, r] + (mK[c] - m[c]) * (mK[r] - m[r])))
            P[r, c] = P[c, r] = 0.5 * (v + w)
    return ll


@batch_kernel
def _tail_mixture_batch(l1: np.ndarray, lK: np.ndarray, m1: np.ndarray, mK: np.ndarray, P1: np.ndarray,
                        PK: np.ndarray, log1me: float, loge: float, need: np.ndarray, ll: np.ndarray, m: np.ndarray,
                        P: np.ndarray) -> None:
    """:func:`tail_update` for every Gaussian ``n`` and measurement ``j`` with ``need[n, j]`` (``need (0, 0)``:
    every pair; ``P1``, ``PK``: ``(N, 1 or J, d, d)``); a pair not needed gets its likelihood alone and NaN at the
    start of its mean and covariance."""
    N, J = l1.shape
    every = need.shape[0] == 0
    for n in range(N):
        for j in range(J):
            if every or need[n, j]:
                r1 = j if P1.shape[1] > 1 else 0
                rK = j if PK.shape[1] > 1 else 0
                ll[n, j] = tail_update(l1[n, j], lK[n, j], m1[n, j], mK[n, j], P1[n, r1], PK[n, rK], log1me, loge,
                                       m[n, j], P[n, j])
            else:
                ll[n, j] = mixture_loglik(l1[n, j], lK[n, j], log1me, loge)
                m[n, j, 0] = np.nan
                P[n, j, 0, 0] = np.nan


@batch_kernel
def _tail_loglik_batch(l1: np.ndarray, lK: np.ndarray, log1me: float, loge: float, out: np.ndarray) -> None:
    """``out[n, j]``: :func:`mixture_loglik` of the two log-likelihoods ``l1``, ``lK`` ``(N, J)``, the likelihood of
    :func:`tail_update` without its posterior."""
    for n in range(l1.shape[0]):
        for j in range(l1.shape[1]):
            out[n, j] = mixture_loglik(l1[n, j], lK[n, j], log1me, loge)


def _logs(e: float) -> tuple[float, float]:
    """``(log(1 - e), log(e))`` of a tail weight ``e`` in ``(0, 1]``."""
    return (math.log1p(-e) if e < 1.0 else -np.inf), math.log(e)


def tail_loglik(core: np.ndarray, wide: np.ndarray, e: float) -> np.ndarray:
    """The log-likelihood ``(N, J)`` of the mixture from those of the two updates, ``core`` (``P``) and ``wide``
    (``K P``), each ``(N, J)``; ``e`` in ``(0, 1]``."""
    c = np.ascontiguousarray
    out = np.empty(np.shape(core))
    _tail_loglik_batch(c(core, dtype=float), c(wide, dtype=float), *_logs(e), out)
    return out


def tail_mixture(core: Innovation, wide: Innovation, e: float, need: np.ndarray | None = None) -> Innovation:
    """The CKF update of ``N`` Gaussians by ``J`` measurements under the heavy-tailed likelihood (:func:`tail_update`
    for each pair, compiled), from their updates with ``P`` and ``K P``.

    ``K = 1`` gives the Gaussian update (``e = 0`` is no tail: :func:`mmslam.slam.phd.gmphd.type_terms` does not call
    this then).

    Args:
        core, wide: the :class:`~mmslam.slam.phd.ckf.Innovation` of the same ``N`` Gaussians and ``J`` measurements
            with ``P`` and ``K P`` (``loglik (N, J)``, ``m_post (N, J, d)``, ``P_post (N, 1 or J, d, d)``).
        e: the tail's weight in ``(0, 1]``.
        need: ``(N, J)`` bool, the pairs whose posterior is read (:func:`read_pairs`), or None: every pair. A pair not
            needed gets its log-likelihood and NaN as the first entry of its mean and covariance.

    Returns:
        The mixture's :class:`~mmslam.slam.phd.ckf.Innovation`, ``P_post (N, J, d, d)``.
    """
    c = np.ascontiguousarray
    N, J, d = core.m_post.shape
    if need is not None and np.shape(need) != (N, J):
        raise ValueError(f"need has shape {np.shape(need)}; expected ({N}, {J})")
    ll, m, P = np.empty((N, J)), np.empty((N, J, d)), np.empty((N, J, d, d))
    _tail_mixture_batch(c(core.loglik, dtype=float), c(wide.loglik, dtype=float), c(core.m_post, dtype=float),
                        c(wide.m_post, dtype=float), c(core.P_post, dtype=float), c(wide.P_post, dtype=float),
                        *_logs(e), np.zeros((0, 0), bool) if need is None else c(need, dtype=bool), ll, m, P)
    return Innovation(ll, m, P)


def read_pairs(logq: np.ndarray, logpsi: np.ndarray, det_index: np.ndarray, n: int, prune: float | None) -> np.ndarray:
    """``(n, J)`` bool: the pairs (Gaussian ``det_index[p, q]``, measurement ``j``) whose posterior the corrected map
    may keep, by the rule of :func:`mmslam.slam.phd.gmphd.corrected_gm`, ``log q - log psi(z_j) >= log prune``
    (``prune`` None or 0: every pair), with 1e-9 of margin (as :func:`mmslam.slam.phd.gmphd._skip_floors`): a pair
    at the threshold is matched whatever the rounding, so a kept component never reads a mean not computed.

    Args: ``logq (P, Q, J)`` the detected terms, ``logpsi (P, J)``, ``det_index (P, Q)`` (``-1``: no innovation),
    ``n`` the number of innovations, ``prune`` the threshold of the corrected components.
    """
    J = np.shape(logq)[2]
    if prune is None or not prune > 0.0:
        return np.ones((n, J), bool)
    rows = det_index >= 0
    need = np.zeros((n, J), bool)
    need[det_index[rows]] = logq[rows] - logpsi[np.nonzero(rows)[0]] >= math.log(prune) - 1e-9
    return need
