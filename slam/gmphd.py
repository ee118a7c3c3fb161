"""GM-PHD map prediction and correction for the RBPF (paper eqs. prevPredPHD, prevCorrPHD, propCorrPHD).

Everything is batched over particles ``P`` x Gaussians ``Q`` x measurements ``J`` with padded
arrays (:class:`~mmslam.slam.gm.GM`, batch shape ``(P,)``). Frames and units: global frame,
metres, radians; a measurement is ``z = [TOA (m, incl. clock bias), AOD az, AOD el, AOA az
(body frame), AOA el]`` (:mod:`mmslam.slam.measurement`).

The measurement update of a landmark Gaussian is a cubature Kalman filter (CKF) step: the
``2d`` cubature points of ``N(m, P)`` are pushed through ``h(s_p, ., type)`` for the particle's
vehicle state ``s_p``; azimuth components are averaged and differenced with wrapping.
VS Gaussians are 7-D ``[x, y, z, vx, vy, vz, xi]``; the measurement sees the position part only
(SP geometry): the cubature rule runs on the position marginal (6 points for every map type)
and the correction reaches velocity and turn rate through the cross-covariance
``P[:, :3] P_pos^-1 Pxz_pos`` (exact for a linear model; see :func:`ckf_moments`).

The known BS is a single fixed landmark (weight 1, no map): it only adds
``p_D N(z; h(s_p, b, BS), R)`` to the normaliser ``psi(z)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .dynamics import wrap_angle
from .gm import GM, symmetrize
from .measurement import AZIMUTH_COMPONENTS, BS, MEAS_DIM, VA, measure

_LOG_2PI = float(np.log(2.0 * np.pi))
_TWO_PI = 2.0 * np.pi


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles to ``[-pi, pi]`` (``a - 2 pi round(a / 2 pi)``): cheaper than
    :func:`~mmslam.slam.dynamics.wrap_angle` where the sign of an exact ``+-pi`` does not matter
    (residuals and deviations; predicted values are wrapped with ``wrap_angle``)."""
    return a - _TWO_PI * np.round(a * (1.0 / _TWO_PI))


def batched_cholesky(A: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors of SPD matrices ``A (..., d, d)``, vectorised over the batch.

    A column-by-column (Cholesky-Crout) loop over ``d`` with array operations on the whole
    batch: for the small ``d`` here (3, 5, 7) this is much faster than LAPACK per matrix.
    A non-positive pivot yields NaN (checked by the caller).
    """
    d = A.shape[-1]
    L = np.zeros_like(A)
    for j in range(d):
        Lj = L[..., j, :j]
        with np.errstate(invalid="ignore"):
            piv = np.sqrt(A[..., j, j] - (Lj * Lj).sum(-1))
        L[..., j, j] = piv
        if j + 1 < d:
            L[..., j + 1:, j] = (A[..., j + 1:, j] - (L[..., j + 1:, :j] * Lj[..., None, :]).sum(-1)) / piv[..., None]
    return L


def tril_inverse(L: np.ndarray) -> np.ndarray:
    """Inverses of lower-triangular ``L (..., d, d)`` by batched forward substitution."""
    d = L.shape[-1]
    X = np.zeros_like(L)
    for i in range(d):
        acc = -(L[..., i, :i, None] * X[..., :i, :]).sum(-2)
        acc[..., i] += 1.0
        X[..., i, :] = acc / L[..., i, i, None]
    return X


def safe_cholesky(P: np.ndarray, stage: str) -> np.ndarray:
    """Batched lower Cholesky factor of ``P (..., d, d)``; FloatingPointError naming ``stage``.

    LAPACK first; if some matrix is not numerically positive definite, one retry with a
    relative jitter of ``1e-10`` of the largest diagonal entry (round-off on near-singular but
    valid matrices), then FloatingPointError.
    """
    if not np.isfinite(P).all():
        raise FloatingPointError(f"non-finite covariance in {stage}")
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        pass
    d = P.shape[-1]
    scale = np.maximum(np.abs(np.diagonal(P, axis1=-2, axis2=-1)).max(-1), 1e-12)
    L = batched_cholesky(P + (1e-10 * scale)[..., None, None] * np.eye(d))
    diag = np.diagonal(L, axis1=-2, axis2=-1)
    if not (np.isfinite(diag).all() and (diag > 0).all()):
        raise FloatingPointError(f"covariance not positive definite in {stage}")
    return L


def cubature_points(m: np.ndarray, P: np.ndarray, stage: str = "cubature points") -> np.ndarray:
    """Third-degree spherical-radial cubature points of ``N(m, P)``.

    Args:
        m: means ``(..., d)``; P: covariances ``(..., d, d)`` (SPD).

    Returns:
        ``(..., 2d, d)``: ``m + sqrt(d) L e_i`` for ``i < d`` and ``m - sqrt(d) L e_i`` after,
        with ``L`` the lower Cholesky factor of ``P``. All points carry weight ``1 / (2d)``.
    """
    d = m.shape[-1]
    L = safe_cholesky(P, stage) * np.sqrt(d)
    cols = np.swapaxes(L, -1, -2)  # (..., d, d): row i = L e_i
    return np.concatenate([m[..., None, :] + cols, m[..., None, :] - cols], axis=-2)


def ckf_moments(m: np.ndarray, P: np.ndarray, h: Callable[[np.ndarray], np.ndarray],
                wrap: tuple[int, ...] = AZIMUTH_COMPONENTS, stage: str = "CKF",
                obs_dims: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cubature estimates of the predicted measurement moments of ``z = h(x)``, ``x ~ N(m, P)``.

    Args:
        m: ``(..., d)`` means; P: ``(..., d, d)`` covariances.
        h: maps points ``(..., 2 d_o, d_o)`` to measurements ``(..., 2 d_o, nz)`` (broadcasting
            over the leading axes of ``m``), ``d_o = obs_dims or d``.
        wrap: measurement components that are angles on the circle (averaged and differenced
            modulo ``2 pi``; the predicted value is wrapped to ``(-pi, pi]``).
        obs_dims: if ``h`` depends only on the first ``d_o < d`` state components (VS: the
            position), the cubature rule is applied to that marginal (``2 d_o`` points) and the
            cross-covariance with the full state follows from the Gaussian conditional:
            ``Pxz = P[:, :d_o] P_oo^-1 Pxz_o`` (exact for linear ``h``, and the same
            third-degree accuracy as the full-state rule).

    Returns:
        ``zhat (..., nz)``, ``Pzz (..., nz, nz)`` (no noise added) and ``Pxz (..., d, nz)``.
    """
    d = m.shape[-1]
    do = d if obs_dims is None else int(obs_dims)
    mo = m[..., :do]
    Lo = safe_cholesky(P[..., :do, :do], stage) * np.sqrt(do)
    cols = np.swapaxes(Lo, -1, -2)  # row i = sqrt(d_o) L e_i
    pts = np.concatenate([mo[..., None, :] + cols, mo[..., None, :] - cols], axis=-2)
    hz = h(pts)
    n = 2 * do
    ref = hz[..., :1, :]
    dev = hz - ref
    for c in wrap:
        dev[..., c] = _wrap(dev[..., c])
    mdev = dev.mean(axis=-2)
    zhat = ref[..., 0, :] + mdev
    for c in wrap:
        zhat[..., c] = wrap_angle(zhat[..., c])
    Dz = dev - mdev[..., None, :]
    Pzz = (np.swapaxes(Dz, -1, -2) @ Dz) / n
    # Pxz_o = (1/n) sum_i (+-c_i) Dz_i^T = (1/n) Lo^T-rows times (Dz_plus - Dz_minus)
    G = (Dz[..., :do, :] - Dz[..., do:, :]) / n  # (..., d_o, nz): Pxz_o = Lo @ G
    if do == d:
        Pxz = Lo @ G
    else:
        # P[:, :do] P_oo^-1 Lo G = P[:, :do] (Lo Lo^T / d_o)^-1 Lo G = d_o P[:, :do] Lo^-T G
        Pxz = do * (P[..., :, :do] @ (np.swapaxes(tril_inverse(Lo), -1, -2) @ G))
    return zhat, Pzz, Pxz


@dataclass
class Innovation:
    """Per-Gaussian innovation statistics against a measurement set (shapes with ``(P, Q)`` lead).

    ``loglik (P, Q, J)``: ``log N(z_j; zhat, S)``; ``gain_sqrt (P, Q, d, 5)``: ``A = Pxz L^-T``
    with ``S = L L^T`` (so ``K = A L^-1``, ``K r = A y``); ``y (P, Q, J, 5)``: whitened
    residuals ``L^-1 (z_j - zhat)`` (azimuths wrapped); ``P_post (P, Q, d, d) = P - A A^T``.
    """

    loglik: np.ndarray
    y: np.ndarray
    gain_sqrt: np.ndarray
    P_post: np.ndarray


def innovation(m: np.ndarray, P: np.ndarray, Z: np.ndarray, R: np.ndarray,
               h: Callable[[np.ndarray], np.ndarray], stage: str, obs_dims: int | None = None) -> Innovation:
    """CKF innovation of every Gaussian ``N(m, P)`` (``(..., d)``) against every ``z`` in ``Z (J, 5)``.

    ``R (5, 5)`` is the filter's measurement covariance. Works for any leading batch shape.
    ``obs_dims``: see :func:`ckf_moments` (3 for landmark maps: ``h`` sees the position only).
    """
    zhat, Pzz, Pxz = ckf_moments(m, P, h, stage=stage, obs_dims=obs_dims)
    S = symmetrize(Pzz + R)
    L = safe_cholesky(S, stage + " (innovation covariance)")
    Linv = tril_inverse(L)
    r = Z - zhat[..., None, :]  # (..., J, 5)
    for c in AZIMUTH_COMPONENTS:
        r[..., c] = _wrap(r[..., c])
    LinvT = np.swapaxes(Linv, -1, -2)
    y = r @ LinvT  # (..., J, 5): rows L^-1 r_j
    half_logdet = np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
    nz = Z.shape[-1]
    loglik = -0.5 * np.einsum("...i,...i->...", y, y) - half_logdet[..., None] - 0.5 * nz * _LOG_2PI
    A = Pxz @ LinvT  # Pxz L^-T
    P_post = symmetrize(P - A @ np.swapaxes(A, -1, -2))
    return Innovation(loglik, y, A, P_post)


def kalman_update(m: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray,
                  h: Callable[[np.ndarray], np.ndarray], obs_dims: int | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Single CKF update of ``N(m, P)`` by one measurement ``z (nz,)``: ``(m_post, P_post, log N(z))``.

    A convenience wrapper over :func:`innovation` (used by tests and for a single Gaussian).
    """
    inn = innovation(m, P, np.asarray(z, float)[None, :], R, h, "kalman_update", obs_dims)
    m_post = m + np.einsum("...da,...a->...d", inn.gain_sqrt, inn.y[..., 0, :])
    return m_post, inn.P_post, inn.loglik[..., 0]


def landmark_h(states: np.ndarray, lm_type: int, bs: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Measurement function of landmark points for per-particle vehicle states.

    The same model as :func:`mmslam.slam.measurement.measure` (DESIGN.md section 4), written
    component-wise for speed (this is the filter's hot path); body-frame AOA azimuths are
    wrapped to ``[-pi, pi]``.

    Args:
        states: ``(P, 7)`` vehicle states.
        lm_type: VA, SP or VS (VS: SP geometry on the first three state components).

    Returns:
        ``h(pts)`` mapping ``(P, Q, K, >= 3)`` landmark points (positions first) to
        ``(P, Q, K, 5)`` measurements.
    """
    s = states[:, None, None, :]
    ux, uy, uz, head, bias = s[..., 0], s[..., 1], s[..., 2], s[..., 3], s[..., 6]
    bx, by, bz = (float(c) for c in np.asarray(bs, float))

    def _norm(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        return np.sqrt(x * x + y * y + z * z)

    def _el(z: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.arcsin(np.clip(z / np.where(r > 0, r, 1.0), -1.0, 1.0))

    def h(pts: np.ndarray) -> np.ndarray:
        x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
        out = np.empty(pts.shape[:-1] + (5,))
        if lm_type == VA:
            # v = image source; arrival direction u -> v; departure = (u - v) mirrored in the wall
            ax, ay, az = x - ux, y - uy, z - uz
            ra = _norm(ax, ay, az)
            nx, ny, nz = x - bx, y - by, z - bz
            nn = _norm(nx, ny, nz)
            nn = np.where(nn > 0, nn, 1.0)
            nx, ny, nz = nx / nn, ny / nn, nz / nn
            proj = -(ax * nx + ay * ny + az * nz)  # (u - v) . n
            dx, dy, dz = -ax - 2.0 * proj * nx, -ay - 2.0 * proj * ny, -az - 2.0 * proj * nz
            out[..., 0] = ra + bias
            out[..., 1] = np.arctan2(dy, dx)
            out[..., 2] = _el(dz, ra)  # |d_dep| = |u - v| (a mirror keeps the length)
        else:  # SP, VS: single scatter at the point
            dx, dy, dz = x - bx, y - by, z - bz
            rd = _norm(dx, dy, dz)
            ax, ay, az = x - ux, y - uy, z - uz
            ra = _norm(ax, ay, az)
            out[..., 0] = rd + ra + bias
            out[..., 1] = np.arctan2(dy, dx)
            out[..., 2] = _el(dz, rd)
        out[..., 3] = _wrap(np.arctan2(ay, ax) - head)
        out[..., 4] = _el(az, ra)
        return out

    return h


# ====================================================================== fast flat (SoA) kernel
# The filter's hot path. Gaussians are flattened to one axis ``N`` (only those that can be
# detected) and every small matrix is stored "structure of arrays": the batch axis is the last,
# contiguous axis (``(d, d, N)``), so each arithmetic step of a closed-form Cholesky factor or
# triangular solve is one vectorised operation over all ``N`` Gaussians instead of one tiny
# LAPACK / BLAS call per matrix.

def soa_cholesky(A: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors of SPD matrices stored batch-last: ``A (d, d, N) -> L (d, d, N)``.

    Reads the lower triangle of ``A`` only.
    Cholesky-Crout, one column at a time, each step vectorised over ``N`` (the same arithmetic
    as LAPACK's unblocked algorithm up to summation order). A non-positive pivot yields NaN or
    a zero diagonal entry; the caller checks the diagonal.
    """
    d = A.shape[0]
    L = np.zeros_like(A)
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(d):
            Lj = L[j, :j]  # (j, N)
            piv = np.sqrt(A[j, j] - np.einsum("kn,kn->n", Lj, Lj)) if j else np.sqrt(A[j, j])
            L[j, j] = piv
            if j + 1 < d:
                rest = A[j + 1:, j]
                if j:
                    rest = rest - np.einsum("ikn,kn->in", L[j + 1:, :j], Lj)
                L[j + 1:, j] = rest / piv
    return L


def _soa_safe_cholesky(A: np.ndarray, stage: str) -> np.ndarray:
    """:func:`soa_cholesky` with the checks and jitter retry of :func:`safe_cholesky` (``(d, d, N)``).

    Only the lower triangle of ``A`` is read (the upper one may be unset).
    """
    L = soa_cholesky(A)
    diag = np.einsum("iin->in", L)
    if np.isfinite(diag).all() and (diag > 0).all():
        return L
    # rare path: the generic routine raises with the stage name or retries with jitter
    full = np.array(A)
    for i in range(full.shape[0]):
        full[:i, i] = full[i, :i]  # mirror the lower triangle
    return np.ascontiguousarray(safe_cholesky(np.moveaxis(full, -1, 0), stage).transpose(1, 2, 0))


def soa_forward_solve(L: np.ndarray, B: np.ndarray, overwrite: bool = False) -> np.ndarray:
    """``X = L^-1 B`` for lower-triangular ``L (d, d, N)`` and ``B (d, ..., N)`` (batch last).

    ``B``'s first axis is the one multiplied by ``L``; the middle axes (e.g. ``J`` measurements)
    broadcast against ``L``'s batch axis ``N``. With ``overwrite=True`` (``B`` a float array of
    the full result shape) the solution is written into ``B`` and returned.
    """
    d = L.shape[0]
    if overwrite:
        X = B
    else:
        X = np.empty((d,) + np.broadcast_shapes(B.shape[1:], L.shape[2:]))
        X[...] = B
    tmp = np.empty(X.shape[1:])
    for a in range(d):  # in place, the same operations as X[a] = (B[a] - sum_b L[a, b] X[b]) / L[a, a]
        Xa = X[a]
        for b in range(a):
            np.multiply(L[a, b], X[b], out=tmp)
            np.subtract(Xa, tmp, out=Xa)
        np.divide(Xa, L[a, a], out=Xa)
    return X


def _h_soa(x: np.ndarray, y: np.ndarray, z: np.ndarray, u: np.ndarray, lm_type: int,
           bs: np.ndarray) -> np.ndarray:
    """Measurement model of landmark points, batch last: ``x, y, z (K, N)`` (m), ``u (7, N)``
    vehicle states -> ``(5, K, N)``. Same formulas as :func:`landmark_h`."""
    ux, uy, uz, head, bias = u[0], u[1], u[2], u[3], u[6]
    bx, by, bz = (float(c) for c in np.asarray(bs, float))
    out = np.empty((5,) + x.shape)

    def _el(zc: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.arcsin(np.clip(zc / np.where(r > 0, r, 1.0), -1.0, 1.0))

    ax, ay, az = x - ux, y - uy, z - uz
    ra = np.sqrt(ax * ax + ay * ay + az * az)
    if lm_type == VA:
        nx, ny, nz = x - bx, y - by, z - bz
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        nn = np.where(nn > 0, nn, 1.0)
        nx, ny, nz = nx / nn, ny / nn, nz / nn
        proj = -(ax * nx + ay * ny + az * nz)
        dx, dy, dz = -ax - 2.0 * proj * nx, -ay - 2.0 * proj * ny, -az - 2.0 * proj * nz
        out[0] = ra + bias
        out[1] = np.arctan2(dy, dx)
        out[2] = _el(dz, ra)
    else:
        dx, dy, dz = x - bx, y - by, z - bz
        rd = np.sqrt(dx * dx + dy * dy + dz * dz)
        out[0] = rd + ra + bias
        out[1] = np.arctan2(dy, dx)
        out[2] = _el(dz, rd)
    out[3] = _wrap(np.arctan2(ay, ax) - head)
    out[4] = _el(az, ra)
    return out


@dataclass
class FlatInnovation:
    """CKF innovation of ``N`` flattened Gaussians against ``J`` measurements, batch axis last.

    ``loglik (J, N)``: ``log N(z_j; zhat, S)``; ``y (5, J, N)``: whitened residuals
    ``L^-1 (z_j - zhat)`` (``S = L L^T``); ``gain (d, 5, N)``: ``A = Pxz L^-T`` (``K r = A y``);
    ``P_post (d, d, N) = P - A A^T``. With one covariance per measurement (``R (J, 5, 5)``),
    ``S``, the gain and the posterior depend on the measurement: ``gain (d, 5, J, N)`` and
    ``P_post (d, d, J, N)`` (see :meth:`gain_of` / :meth:`post_of`).
    """

    loglik: np.ndarray
    y: np.ndarray
    gain: np.ndarray
    P_post: np.ndarray

    def gain_of(self, j: np.ndarray, n: np.ndarray) -> np.ndarray:
        """``(d, 5, K)`` gains of the pairs (measurement ``j[k]``, Gaussian ``n[k]``)."""
        return self.gain[:, :, j, n] if self.gain.ndim == 4 else self.gain[:, :, n]

    def post_of(self, j: np.ndarray, n: np.ndarray) -> np.ndarray:
        """``(d, d, K)`` posterior covariances of the pairs (measurement ``j[k]``, Gaussian ``n[k]``)."""
        return self.P_post[:, :, j, n] if self.P_post.ndim == 4 else self.P_post[:, :, n]


def flat_innovation(m: np.ndarray, P: np.ndarray, states: np.ndarray, lm_type: int, bs: np.ndarray,
                    Z: np.ndarray, R: np.ndarray, stage: str, extent: np.ndarray | None = None) -> FlatInnovation:
    """CKF innovation of landmark Gaussians ``N(m, P)`` seen from per-Gaussian vehicle states.

    The same computation as :func:`innovation` with ``h = landmark_h`` and ``obs_dims = 3``
    (cubature rule on the position marginal, 6 points), written batch-last with closed-form
    small-matrix kernels (:func:`soa_cholesky`, :func:`soa_forward_solve`).

    Args:
        m: ``(N, d)`` means (d = 3 for VA/SP, 7 for VS; position first, m).
        P: ``(N, d, d)`` SPD covariances.
        states: ``(N, 7)`` vehicle state of each Gaussian's particle.
        Z: ``(J, 5)`` measurements; R: ``(5, 5)`` filter measurement covariance, or ``(J, 5, 5)``
            one per measurement (power-aware sensor model: the CRB covariance of each path).
        extent: ``(3, 3)`` covariance (m^2, global frame) of the scatter point about the landmark
            position, or None for a point landmark. The measurement is ``z = h(x + e) + n`` with
            ``e ~ N(0, extent)`` independent of the state (a vehicle body reflects from anywhere on
            it): the predicted measurement and ``S`` come from cubature on ``N(m, P_pos + extent)``
            and the cross-covariance ``Pxz = P[:, :3] (P_pos + extent)^-1 Cov(x + e, z)``.

    Raises:
        FloatingPointError: a non-finite or non-positive-definite covariance (naming ``stage``).
    """
    n, d = m.shape
    if extent is not None:
        extent = np.asarray(extent, float).reshape(3, 3)
        if not np.any(extent):
            extent = None
    R = np.asarray(R, float)
    if R.ndim == 3:  # one covariance per measurement: one innovation per (measurement, Gaussian)
        if R.shape != (Z.shape[0], 5, 5):
            raise ValueError(f"R has shape {R.shape}; expected (5, 5) or ({Z.shape[0]}, 5, 5)")
        parts = [flat_innovation(m, P, states, lm_type, bs, Z[j:j + 1], R[j], stage, extent)
                 for j in range(Z.shape[0])]
        if not parts:
            return flat_innovation(m, P, states, lm_type, bs, Z, np.eye(5), stage, extent)
        return FlatInnovation(np.concatenate([p.loglik for p in parts], axis=0),
                              np.concatenate([p.y for p in parts], axis=1),
                              np.stack([p.gain for p in parts], axis=2),
                              np.stack([p.P_post for p in parts], axis=2))
    if not (np.isfinite(m).all() and np.isfinite(P).all()):
        raise FloatingPointError(f"non-finite covariance in {stage}")
    if n <= INNOVATION_BLOCK:
        return _flat_innovation_block(m, P, states, lm_type, bs, Z, R, stage, extent)
    # blocks of Gaussians: the temporaries stay small (fewer page faults from large short-lived
    # allocations); every Gaussian's arithmetic is the same as in one pass
    blocks = [_flat_innovation_block(m[i:i + INNOVATION_BLOCK], P[i:i + INNOVATION_BLOCK],
                                     states[i:i + INNOVATION_BLOCK], lm_type, bs, Z, R, stage, extent)
              for i in range(0, n, INNOVATION_BLOCK)]
    return FlatInnovation(*(np.concatenate([getattr(b, f) for b in blocks], axis=-1)
                            for f in ("loglik", "y", "gain", "P_post")))


INNOVATION_BLOCK = 1024
"""Gaussians per block in :func:`flat_innovation` (a speed setting; results do not depend on it)."""


def _flat_innovation_block(m: np.ndarray, P: np.ndarray, states: np.ndarray, lm_type: int, bs: np.ndarray,
                           Z: np.ndarray, R: np.ndarray, stage: str,
                           extent: np.ndarray | None = None) -> FlatInnovation:
    """:func:`flat_innovation` of one block of Gaussians (inputs already checked finite)."""
    n, d = m.shape
    mT = m.T  # (d, N)
    PT = np.ascontiguousarray(P.transpose(1, 2, 0))  # (d, d, N)
    # cubature on the scatter point x + e: covariance P_pos (+ extent)
    Lo = _soa_safe_cholesky(PT[:3, :3] if extent is None else PT[:3, :3] + extent[:, :, None], stage)
    c = Lo * np.sqrt(3.0)  # c[:, i] = sqrt(3) L e_i
    pts = np.concatenate([mT[:3, None, :] + c, mT[:3, None, :] - c], axis=1)  # (3, 6, N)
    hz = _h_soa(pts[0], pts[1], pts[2], np.ascontiguousarray(states.T), lm_type, bs)  # (5, 6, N)
    # in place where a fresh (5, 6, N) temporary would be allocated (same values; fewer page faults)
    h0 = hz[:, 0].copy()  # (5, N)
    dev = np.subtract(hz, h0[:, None], out=hz)  # hz - hz[:, :1]
    for a in AZIMUTH_COMPONENTS:
        dev[a] = _wrap(dev[a])
    mdev = dev.mean(axis=1)  # (5, N)
    zhat = h0 + mdev
    for a in AZIMUTH_COMPONENTS:
        zhat[a] = wrap_angle(zhat[a])
    Dz = np.subtract(dev, mdev[:, None], out=dev)  # dev - mdev
    # innovation covariance, lower triangle only (all soa_cholesky reads; row-wise einsum is much
    # faster than one "akn,bkn->abn" einsum over the whole matrix)
    S = np.empty((5, 5, n))
    for a in range(5):
        S[a, :a + 1] = np.einsum("kn,bkn->bn", Dz[a], Dz[:a + 1])
    S *= 1.0 / 6.0
    S += R[:, :, None]
    G = Dz[:, :3] - Dz[:, 3:]  # (5, 3, N): G[a, k]
    G *= 1.0 / 6.0
    if d == 3 and extent is None:
        Pxz = np.einsum("ikn,akn->ian", c, G)  # sqrt(3) L G
    else:
        # Pxz = 3 P[:, :3] (sqrt(3) L)^-T G = sqrt(3) P[:, :3] L^-T G (see ckf_moments); with an
        # extent L L^T = P_pos + extent, and the same formula gives Cov(x, z) = P[:, :3] (L L^T)^-1 Cov(x + e, z)
        W = np.empty_like(G)  # W[a, k] = (L^-T G)[k, a]: back substitution with L^T
        for k in (2, 1, 0):
            acc = G[:, k]
            for i in range(k + 1, 3):
                acc = acc - Lo[i, k] * W[:, i]
            W[:, k] = acc / Lo[k, k]
        Pxz = np.sqrt(3.0) * (PT[:, 0, None] * W[None, :, 0] + PT[:, 1, None] * W[None, :, 1]
                              + PT[:, 2, None] * W[None, :, 2])  # (d, 5, N)
    Ls = _soa_safe_cholesky(S, stage + " (innovation covariance)")
    # one triangular solve for the residuals and the gain: L^-1 [r_1 .. r_J, Pxz^T], in one buffer
    J = Z.shape[0]
    X = np.empty((5, J + d, n))
    r = X[:, :J]
    np.subtract(Z.T[:, :, None], zhat[:, None, :], out=r)  # (5, J, N) residuals
    for a in AZIMUTH_COMPONENTS:
        r[a] = _wrap(r[a])
    X[:, J:] = Pxz.transpose(1, 0, 2)
    soa_forward_solve(Ls, X, overwrite=True)  # (5, J + d, N)
    y = X[:, :J]
    half_logdet = np.log(np.einsum("iin->in", Ls)).sum(0)  # (N,)
    loglik = -0.5 * np.einsum("ajn,ajn->jn", y, y) - half_logdet - 0.5 * Z.shape[1] * _LOG_2PI
    gain = np.ascontiguousarray(X[:, J:].transpose(1, 0, 2))  # (d, 5, N): A = Pxz L^-T
    P_post = PT - np.einsum("ian,jan->ijn", gain, gain)
    return FlatInnovation(loglik, y, gain, P_post)


def predict_static(g: GM, p_survival: float) -> GM:
    """Static landmark prediction (identity dynamics): weights times ``p_survival``."""
    return GM(g.w * p_survival, g.m, g.P, g.mask)


@dataclass
class TypeCorrection:
    """Intermediate per-type correction terms: detection terms and innovation.

    ``logq (P, Q, J)``: ``log(p_D w N(z_j; zhat, S))`` (``-inf`` where masked or ``p_D = 0``);
    ``missed_w (P, Q)``: ``(1 - p_D) w``; ``det_index (P, Q)``: index of the Gaussian in the
    flat innovation ``inn`` (``-1`` where masked or ``p_D = 0``: no innovation is computed for
    a Gaussian that cannot be detected, its detection terms are exactly zero).
    """

    g: GM
    lm_type: int
    logq: np.ndarray
    missed_w: np.ndarray
    inn: FlatInnovation
    det_index: np.ndarray


def type_terms(g: GM, lm_type: int, states: np.ndarray, Z: np.ndarray, R: np.ndarray,
               bs: np.ndarray, pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
               extent: np.ndarray | None = None) -> TypeCorrection:
    """Detection terms of one map type (batched over particles, Gaussians and measurements).

    Only the live Gaussians with ``p_D > 0`` (inside the FOV) go through the CKF innovation
    (:func:`flat_innovation`, flattened over particles x Gaussians); the others keep
    ``logq = -inf`` and their full weight as missed detection, exactly as the dense formula
    gives with ``p_D = 0``.

    Args:
        g: predicted map of this type, batch ``(P,)``, ``Q`` slots, dim 3 (VA/SP) or 7 (VS).
        states: ``(P, 7)`` particle vehicle states.
        Z: ``(J, 5)`` measurements of this vehicle and step.
        pd_fn: ``pd_fn(vehicle_pos (P, Q, 3), lm_pos (P, Q, 3), lm_type) -> (P, Q)`` detection
            probability evaluated at the Gaussian means.
        extent: ``(3, 3)`` scatter-point covariance of an extended landmark (VS: a car body), see
            :func:`flat_innovation`; None for point landmarks.

    Raises:
        FloatingPointError: a non-finite mean or covariance in the map (also outside the FOV),
            or a covariance that is not positive definite.
    """
    stage = f"{_tname(lm_type)} correction"
    if not (np.isfinite(g.m).all() and np.isfinite(g.P).all()):  # masked slots hold 0 / I
        raise FloatingPointError(f"non-finite mean or covariance in {stage}")
    P_, Q = g.w.shape
    J = Z.shape[0]
    pd = pd_fn(np.broadcast_to(states[:, None, 0:3], g.m.shape[:-1] + (3,)), g.m[..., 0:3], lm_type)
    pd = np.where(g.mask, pd, 0.0)
    det = pd > 0.0
    pidx, qidx = np.nonzero(det)
    det_index = np.full((P_, Q), -1)
    det_index[pidx, qidx] = np.arange(pidx.size)
    inn = flat_innovation(g.m[pidx, qidx], g.P[pidx, qidx], states[pidx], lm_type, bs, Z, R, stage, extent)
    logq = np.full((P_, Q, J), -np.inf)
    logq[pidx, qidx] = np.log(pd[pidx, qidx] * g.w[pidx, qidx])[:, None] + inn.loglik.T
    return TypeCorrection(g, lm_type, logq, (1.0 - pd) * g.w, inn, det_index)


def bs_logterm(states: np.ndarray, Z: np.ndarray, R: np.ndarray, bs: np.ndarray,
               p_d: np.ndarray) -> np.ndarray:
    """``log(p_D N(z_j; h(s_p, b, BS), R))`` for the known BS, shape ``(P, J)``.

    ``p_d`` is ``(P,)``: the BS detection probability for each particle. ``R``: ``(5, 5)``, or
    ``(J, 5, 5)`` one covariance per measurement.
    """
    zhat = measure(states, bs, BS, bs)  # (P, 5)
    r = Z[None, :, :] - zhat[:, None, :]
    for c in AZIMUTH_COMPONENTS:
        r[..., c] = wrap_angle(r[..., c])
    R = np.asarray(R, float)
    Rj = np.broadcast_to(R, (Z.shape[0], MEAS_DIM, MEAS_DIM)) if R.ndim == 2 else R
    L = np.array([safe_cholesky(Rj[j], "BS likelihood") for j in range(Z.shape[0])]).reshape(-1, MEAS_DIM, MEAS_DIM)
    if L.shape[0] == 0:  # no measurements
        return np.zeros((states.shape[0], 0))
    y = np.linalg.solve(L[None], r[..., None])[..., 0]  # (P, J, 5): whitened residuals, one batched solve
    half_logdet = np.log(np.diagonal(L, axis1=1, axis2=2)).sum(-1)  # (J,)
    ll = -0.5 * np.einsum("pja,pja->pj", y, y) - half_logdet[None] - 0.5 * MEAS_DIM * _LOG_2PI
    with np.errstate(divide="ignore"):
        return np.log(p_d)[:, None] + ll


def log_psi(terms: list[TypeCorrection], bs_term: np.ndarray | None, log_clutter: float,
            shape: tuple[int, int]) -> np.ndarray:
    """``log psi(z_j) = log(c(z) + sum_types sum_q q + BS term)``, shape ``(P, J)`` (log-sum-exp).

    Raises FloatingPointError if some ``psi(z)`` is zero or non-finite (e.g. no clutter and no
    landmark can explain a measurement).
    """
    parts = [np.full(shape, float(log_clutter))]
    if bs_term is not None:
        parts.append(bs_term)
    for t in terms:
        if t.logq.shape[1]:
            parts.append(_logsumexp_slots(t.logq))
    stacked = np.stack(parts, axis=0)
    mx = stacked.max(axis=0)
    if not np.isfinite(mx).all() or np.isnan(stacked).any():
        raise FloatingPointError("psi(z) is zero or non-finite in the PHD correction "
                                 "(no clutter and no landmark explains a measurement)")
    return mx + np.log(np.exp(stacked - mx).sum(axis=0))


def _logsumexp_slots(logq: np.ndarray) -> np.ndarray:
    """``log sum_q exp(logq[:, q, :])`` of ``logq (P, Q, J)`` -> ``(P, J)`` (``-inf`` if all are).

    For ``J > 1`` the slots are moved to the front into a fresh buffer so that the max and the
    sum run over contiguous ``(P, J)`` slabs. ``logq`` is never written: the caller
    (:func:`corrected_gm`) reads it again. ``np.ascontiguousarray`` must not be used here, since
    it returns a *view* when ``P == 1`` or ``Q == 1`` and the in-place exp below then rewrote
    ``logq`` (landmark weights of ~1/clutter intensity on city scenes).
    """
    if logq.shape[2] == 1:
        mx = logq.max(axis=1)
        safe = np.where(np.isfinite(mx), mx, 0.0)
        with np.errstate(divide="ignore"):
            return safe + np.log(np.exp(logq - safe[:, None, :]).sum(axis=1))
    t = logq.transpose(1, 0, 2).copy()  # (Q, P, J), always a new array
    mx = t.max(axis=0)
    safe = np.where(np.isfinite(mx), mx, 0.0)
    t -= safe
    np.exp(t, out=t)
    with np.errstate(divide="ignore"):
        return safe + np.log(t.sum(axis=0))


def corrected_gm(t: TypeCorrection, Z: np.ndarray, logpsi: np.ndarray, prune: float | None = None) -> GM:
    """Corrected PHD of one type: missed-detection part plus one updated Gaussian per (q, z).

    With ``prune=None`` the result has the dense layout: batch ``(P,)`` and ``Q (1 + J)``
    slots, the first ``Q`` holding ``(1 - p_D) w`` with the predicted moments, then ``Q x J``
    updated components ``(q, j)`` at slot ``Q + q J + j`` (``w = q / psi(z)``, ``m + K r``,
    ``P - K S K^T``; a Gaussian that cannot be detected, ``p_D = 0``, has no innovation: its
    updated slots hold weight 0 and the predicted moments).

    With a ``prune`` threshold only components of weight ``>= prune`` are materialised
    (the same rule as the first step of ``prune_merge``), compacted to the front (slot order:
    missed-detection components first, then updates in ``(q, j)`` order) with as many slots as
    the largest surviving count. This avoids building the ``(P, Q J, d, d)`` arrays.
    """
    g, inn = t.g, t.inn
    P_, Q, d = g.m.shape
    J = Z.shape[0]
    w_det = np.subtract(t.logq, logpsi[:, None, :])
    np.exp(w_det, out=w_det)  # (P, Q, J); 0 where masked (logq = -inf); in place: no second buffer
    w_all = np.concatenate([np.where(g.mask, t.missed_w, 0.0), w_det.reshape(P_, Q * J)], axis=1)
    mask_all = np.concatenate([g.mask, np.repeat(g.mask, J, axis=1)], axis=1)
    if prune is None:
        keep = mask_all
        order = np.broadcast_to(np.arange(Q * (1 + J)), (P_, Q * (1 + J)))
        live = keep
        w = np.where(live, w_all, 0.0)
    else:
        # stable compaction of the kept slots to the front of each row (slot order kept)
        keep = mask_all & (w_all >= prune)
        cnt = keep.sum(1)
        K = int(cnt.max(initial=0))
        pp, cc = np.nonzero(keep)  # row-major: ascending slot within each row
        rank = np.arange(pp.size) - (np.cumsum(cnt) - cnt)[pp]
        order = np.zeros((P_, K), dtype=np.intp)  # dead slots point at slot 0 (zeroed below)
        order[pp, rank] = cc
        live = np.arange(K)[None, :] < cnt[:, None]
        w = np.zeros((P_, K))
        w[pp, rank] = w_all[pp, cc]
    is_det = order >= Q
    q_idx = np.where(is_det, (order - Q) // max(J, 1), order)
    j_idx = np.where(is_det, (order - Q) % max(J, 1), 0)
    pi = np.arange(P_)[:, None]
    m = g.m[pi, q_idx]  # (P, K, d) predicted moments (missed detections; undetectable updates)
    Pc = g.P[pi, q_idx]
    n_idx = t.det_index[pi, q_idx]
    upd = live & is_det & (n_idx >= 0)  # updated components with an innovation
    if upd.any():
        n_u, j_u = n_idx[upd], j_idx[upd]
        m[upd] += np.einsum("iak,ak->ki", inn.gain_of(j_u, n_u), inn.y[:, j_u, n_u])
        Pc[upd] = symmetrize(inn.post_of(j_u, n_u).transpose(2, 0, 1))
    m[~live] = 0.0
    Pc[~live] = np.eye(d)
    out = GM(w, m, Pc, live)
    if not np.isfinite(out.w.sum() + out.m.sum() + out.P.sum()):  # masked slots are 0 / I
        out.check(f"after the {_tname(t.lm_type)} correction")
        raise FloatingPointError(f"non-finite values after the {_tname(t.lm_type)} correction")
    return out


PHD_MASS_RTOL = 1e-9
"""Relative float tolerance of :func:`check_phd_mass` (the bound is exact in real arithmetic)."""


def check_phd_mass(predicted: GM, corrected: GM, n_meas: int, lm_type: int, step: int) -> None:
    """Invariant of the PHD correction: per particle, corrected mass <= predicted mass + ``J``.

    The corrected intensity is ``(1 - p_D) D(x) + sum_j p_D g_j(x) D(x) / psi(z_j)`` and every
    ``psi(z_j)`` contains the clutter, the BS and all landmark terms of ``z_j``, so each
    measurement adds at most 1 to the mass: ``sum_q w_q^+ <= sum_q w_q + J`` (pruning only
    lowers the left side). A kernel that corrupts the log-weights breaks it at once (the
    ``_logsumexp_slots`` bug gave weights of ~1/clutter intensity). Cost: two sums over
    ``(P, Q)``.

    Args:
        predicted: the map of one type before the correction, batch ``(P,)``.
        corrected: the same map after :func:`corrected_gm`, batch ``(P,)``.
        n_meas: the number of measurements ``J`` of the correction.
        lm_type: the map's landmark type (for the message); step: the time step ``k``.

    Raises:
        FloatingPointError: naming the type, step, particle and both masses, if the bound is
            exceeded beyond a relative ``PHD_MASS_RTOL`` (or a mass is NaN).
    """
    pred = np.where(predicted.mask, predicted.w, 0.0).sum(axis=-1)
    corr = np.where(corrected.mask, corrected.w, 0.0).sum(axis=-1)
    bound = pred + n_meas
    bad = ~(corr <= bound * (1.0 + PHD_MASS_RTOL))  # NaN fails too
    if bad.any():
        p = int(np.argmax(np.where(bad, np.nan_to_num(corr - bound, nan=np.inf), -np.inf)))
        raise FloatingPointError(
            f"PHD mass invariant violated in the {_tname(lm_type)} correction at step {step}, particle {p}: "
            f"corrected mass {corr[p]:.6g} > predicted mass {pred[p]:.6g} + {n_meas} measurements "
            f"({int(bad.sum())} of {bad.size} particles); a correction kernel corrupted the weights")


def _tname(t: int) -> str:
    return {1: "VA", 2: "SP", 3: "VS"}.get(t, str(t))
