"""Small-matrix linear algebra for the filter: one Cholesky factor and one pair of triangular solves.

Every ``d x d`` covariance of the filter is small (d = 3, 5 or 7), so a textbook loop compiled by
numba (``njit``, ``cache=True``: compiled once, cached across processes in ``__pycache__``) beats
a LAPACK call per matrix by far; the kernels of :mod:`~mmslam.slam.phd.ckf`,
:mod:`~mmslam.slam.phd.reduction` and :mod:`~mmslam.slam.phd.birth` call these per matrix inside their
own compiled loops. :func:`safe_cholesky` is the NumPy entry point (any batch shape).

Numerical contract (tested against LAPACK / SciPy in ``tests/test_kernels_reference.py``): the
results equal LAPACK's to ``1e-9`` relative (normwise), not bit for bit.

numba's on-disk cache is invalidated per source file only; :mod:`mmslam.slam` (``__init__``) drops the
cached kernels of every module when any kernel source, this one included, changes.
"""
from __future__ import annotations

import numba as nb
import numpy as np

JITTER = 1e-10
"""Relative diagonal jitter of the one retry of :func:`cholesky` (times the largest diagonal entry)."""


@nb.njit(cache=True, error_model="numpy")
def _cholesky_once(A: np.ndarray, L: np.ndarray, jitter: float) -> bool:
    """Cholesky-Crout factor of ``A + jitter I`` into ``L`` (lower triangle of ``A`` read); False if
    not SPD or not finite (a non-finite entry reaches some pivot as NaN or infinity)."""
    d = A.shape[0]
    for j in range(d):
        for i in range(j):
            L[i, j] = 0.0
        s = A[j, j] + jitter
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not 0.0 < s < np.inf:  # also NaN
            return False
        piv = np.sqrt(s)
        inv = 1.0 / piv
        L[j, j] = piv
        for i in range(j + 1, d):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t * inv
    return True


@nb.njit(cache=True, error_model="numpy")
def cholesky(A: np.ndarray, L: np.ndarray, retry: bool = True) -> bool:
    """Lower Cholesky factor ``A = L L^T`` of one SPD matrix ``A (d, d)`` written into ``L (d, d)``.

    Reads the lower triangle of ``A``; writes the whole of ``L`` (zeros above the diagonal). If
    ``A`` is not numerically positive definite and ``retry``, one retry with ``JITTER`` times its
    largest absolute diagonal entry (at least ``1e-12``) added to the diagonal (round-off on a
    near-singular but valid covariance). Returns False if that fails too or ``A`` is not finite.
    """
    d = A.shape[0]
    if _cholesky_once(A, L, 0.0):
        return True
    for i in range(d):
        for j in range(i + 1):
            if not np.isfinite(A[i, j]):
                return False
    if not retry:
        return False
    scale = 1e-12
    for i in range(d):
        scale = max(scale, abs(A[i, i]))
    return _cholesky_once(A, L, JITTER * scale)


@nb.njit(cache=True, error_model="numpy")
def forward_solve(L: np.ndarray, b: np.ndarray, x: np.ndarray) -> None:
    """``x = L^-1 b`` for lower-triangular ``L (d, d)`` and ``b, x (d,)`` (``x`` may be ``b``)."""
    d = L.shape[0]
    for i in range(d):
        t = b[i]
        for k in range(i):
            t -= L[i, k] * x[k]
        x[i] = t / L[i, i]


@nb.njit(cache=True, error_model="numpy")
def back_solve(L: np.ndarray, b: np.ndarray, x: np.ndarray) -> None:
    """``x = L^-T b`` for lower-triangular ``L (d, d)`` and ``b, x (d,)`` (``x`` may be ``b``)."""
    d = L.shape[0]
    for i in range(d - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, d):
            t -= L[k, i] * x[k]
        x[i] = t / L[i, i]


@nb.njit(cache=True, error_model="numpy")
def spd_inverse(A: np.ndarray, out: np.ndarray) -> bool:
    """``out = A^-1 = L^-T L^-1`` of one SPD ``A (d, d)`` (exactly symmetric); False if not SPD."""
    d = A.shape[0]
    L = np.empty((d, d))
    if not cholesky(A, L, False):
        return False
    e = np.zeros(d)
    for j in range(d):  # column j: L^-T L^-1 e_j
        for i in range(d):
            e[i] = 1.0 if i == j else 0.0
        forward_solve(L, e, e)
        back_solve(L, e, e)
        for i in range(j, d):
            out[i, j] = e[i]
            out[j, i] = e[i]
    return True


@nb.njit(cache=True, error_model="numpy")
def _cholesky_batch(A: np.ndarray, L: np.ndarray) -> int:
    """:func:`cholesky` of every ``A[n] (d, d)``; returns the first failing index or -1."""
    for n in range(A.shape[0]):
        if not cholesky(A[n], L[n]):
            return n
    return -1


@nb.njit(cache=True, error_model="numpy")
def _inverse_batch(A: np.ndarray, out: np.ndarray) -> int:
    """:func:`spd_inverse` of every ``A[n] (d, d)``; returns the first failing index or -1."""
    for n in range(A.shape[0]):
        if not spd_inverse(A[n], out[n]):
            return n
    return -1


def _per_matrix(kernel, P: np.ndarray, stage: str, failure: str) -> np.ndarray:
    """Run a per-matrix kernel (``_cholesky_batch`` / ``_inverse_batch``) over ``P (..., d, d)``."""
    P = np.asarray(P, dtype=float)
    if not np.isfinite(P).all():
        raise FloatingPointError(f"non-finite covariance in {stage}")
    d = P.shape[-1]
    A = np.ascontiguousarray(P.reshape(-1, d, d))
    out = np.empty_like(A)
    if kernel(A, out) >= 0:
        raise FloatingPointError(f"{failure} in {stage}")
    return out.reshape(P.shape)


def safe_cholesky(P: np.ndarray, stage: str) -> np.ndarray:
    """Lower Cholesky factors of SPD matrices ``P (..., d, d)``; FloatingPointError naming ``stage``.

    The jitter retry of :func:`cholesky` applies; a non-finite matrix or one that stays
    indefinite raises ``FloatingPointError`` (non-finite / not positive definite in ``stage``).
    """
    return _per_matrix(_cholesky_batch, P, stage, "covariance not positive definite")


def spd_inv(P: np.ndarray, stage: str) -> np.ndarray:
    """Inverses ``P^-1`` of SPD matrices ``P (..., d, d)`` (exactly symmetric), via :func:`cholesky`.

    Raises FloatingPointError naming ``stage`` if some matrix is non-finite or not positive definite.
    """
    return _per_matrix(_inverse_batch, P, stage, "singular or indefinite covariance")
