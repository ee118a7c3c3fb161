"""The cubature Kalman filter (CKF) update of one landmark Gaussian by one measurement set.

The measurement update of the map PHD, paper eqs. (5) and (10), needs, for every landmark
Gaussian ``N(m, P)`` of every particle and every measurement ``z_j``, the likelihood
``N(z_j; zhat, S)`` and the updated moments ``m + K (z_j - zhat)``, ``P - K S K^T``. The
measurement function :func:`~mmslam.slam.models.measurement.measure_point` (paper eq. (3)) is
non-linear; the third-degree spherical-radial cubature rule (Arasaratnam & Haykin 2009) gives
``zhat``, ``S`` and the cross-covariance ``Pxz`` from ``2 x 3 = 6`` points of the *position*
marginal: ``h`` sees the landmark position only (a VS Gaussian is 7-D ``[x, y, z, vx, vy, vz,
xi]``; the correction reaches velocity and turn rate through the Gaussian conditional
``Pxz = P[:, :3] P_pos^-1 Pxz_pos``, exact for a linear model).

:func:`ckf_update` is written for one Gaussian and one vehicle state, like the textbook
equations; :func:`innovate` runs it over ``N`` Gaussians (numba ``njit``, ``cache=True``).
Frames and units: global frame, m (VS also m/s, rad/s); measurements as in
:mod:`~mmslam.slam.models.measurement`, azimuth residuals wrapped to ``(-pi, pi]``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..core.jit import batch_kernel
from ..core.linalg import cholesky, forward_solve, safe_cholesky
from ..models.measurement import AZIMUTH_COMPONENTS, MEAS_DIM, angle_arguments, body_frame, measure_point, path_vectors, wrap
from ..core.trig import atan2
from ..models.vs import BODY_POINT, body_specular_point

_LOG_2PI = math.log(2.0 * math.pi)
_SIXTH = 1.0 / 6.0  # the cubature weight (a multiplication, not 35 divisions per Gaussian)
_IS_AZIMUTH = np.array([c in AZIMUTH_COMPONENTS for c in range(MEAS_DIM)])
OK, BAD_POSITION_COV, BAD_INNOVATION_COV = 0, 1, 2
"""Return codes of :func:`ckf_update`."""


@nb.njit(cache=True, error_model="numpy")
def residual_component(a: int, z: float, zhat: float) -> float:
    """Component ``a`` of the residual ``z - zhat`` of a measurement (m or rad), azimuths wrapped to ``(-pi, pi]``."""
    res = z - zhat
    return wrap(res) if _IS_AZIMUTH[a] else res


@nb.njit(cache=True, error_model="numpy")
def whitened_loglik(q: float, half_logdet: float) -> float:
    """``log N(z; zhat, S) = -q / 2 - log det L_S - 5/2 log 2 pi`` from the squared whitened residual
    ``q = |L_S^-1 (z - zhat)|^2`` and ``half_logdet = log det L_S`` (``S = L_S L_S^T``)."""
    return -0.5 * q - half_logdet - 0.5 * MEAS_DIM * _LOG_2PI


@nb.njit(cache=True, error_model="numpy")
def gaussian_loglik(z: np.ndarray, zhat: np.ndarray, LS: np.ndarray, half_logdet: float, y: np.ndarray) -> float:
    """``log N(z; zhat, S)`` of one measurement ``z (5,)`` (paper eqs. (5), (10): the likelihood ``g``).

    ``S = LS LS^T`` with ``LS (5, 5)`` its lower Cholesky factor and ``half_logdet = sum log diag LS``;
    the azimuth residuals are wrapped to ``(-pi, pi]``. ``y (5,)`` receives the whitened residual
    ``LS^-1 (z - zhat)`` (the Kalman mean update uses it). Units: as the measurement (m, rad).
    """
    for a in range(MEAS_DIM):
        y[a] = residual_component(a, z[a], zhat[a])
    forward_solve(LS, y, y)
    q = 0.0
    for a in range(MEAS_DIM):
        q += y[a] * y[a]
    return whitened_loglik(q, half_logdet)


@nb.njit(cache=True, error_model="numpy", inline="always")
def ckf_update(geometry: int, m: np.ndarray, P: np.ndarray, s: np.ndarray, b: np.ndarray,
               extent: np.ndarray, body: np.ndarray, Z: np.ndarray, R: np.ndarray,
               loglik: np.ndarray, m_post: np.ndarray, P_post: np.ndarray, work: tuple,
               floor_lik: float = -math.inf, floor_post: float = -math.inf) -> int:
    """CKF update of one landmark Gaussian ``N(m, P)`` seen from one vehicle state ``s``.

    The measurement is ``z = h(s, x + e) + n`` (paper eq. (3), :func:`measure_point` with
    ``geometry``), ``n ~ N(0, R)``, ``e ~ N(0, extent)`` the scatter point's offset about the
    landmark position (an extended landmark such as a car body; zeros for a point landmark). With a
    ``body`` (a VS), the path bounces at the specular point of the car body,
    :func:`~mmslam.slam.models.vs.body_specular_point` of the position (the antenna) and the heading of
    the Gaussian's mean velocity ``atan2(m[4], m[3])``: ``z = h(s, p(x + e)) + n``.

    1. cubature points ``x_k = m_pos +- sqrt(3) L e_k`` (``L L^T = P_pos + extent``), weight 1/6
       (with a ``body``: ``x_k`` <- its specular point);
    2. ``h(s, x_k)``: :func:`measure_point` split in its parts (:func:`path_vectors`, then the 24
       angles of the 6 points in one loop of :func:`~mmslam.slam.core.trig.atan2`, which vectorises,
       then :func:`body_frame`); ``zhat = mean h(s, x_k)`` (azimuths averaged as deviations from
       the first point, wrapped); ``Pzz = mean (h_k - zhat)(h_k - zhat)^T``;
       ``Cov(x + e, z) = sqrt(3) L G`` with ``G = (Dz_+ - Dz_-) / 6``;
       ``Pxz = P[:, :3] (L L^T)^-1 Cov(x + e, z)`` (``= sqrt(3) L G`` for a 3-D point landmark);
    3. per measurement covariance ``R_r``: ``S = Pzz + R_r = L_S L_S^T``, ``A = Pxz L_S^-T``
       (so ``K = A L_S^-1``), ``P_post = P - A A^T``;
    4. per measurement ``z_j`` (paper eqs. (5), (10)): whitened residual ``y = L_S^-1 (z_j - zhat)``,
       ``log N(z_j; zhat, S) = -|y|^2 / 2 - log det L_S - 5/2 log 2 pi``, ``m_post = m + A y``.
       Two optional floors skip work whose result the caller never uses: if already the bound
       ``-y_0^2 / 2 - log det L_S - 5/2 log 2 pi`` from the first component (``|y|^2 >= y_0^2``)
       is below ``floor_lik``, ``loglik[j] = -inf`` and nothing else is computed for ``z_j``;
       if ``loglik[j] < floor_post``, ``m_post[j]`` is not computed. Either way ``m_post[j, 0]`` is
       NaN: a caller that reads a skipped mean fails its finiteness check instead of using stale memory.

    Args:
        geometry: :class:`mmslam.model.Bounce` code of the landmark type.
        m: ``(d,)`` mean, position first (d = 3, or 7 for a VS); P: ``(d, d)`` SPD covariance.
        s: ``(7,)`` vehicle state; b: ``(3,)`` BS position (m).
        extent: ``(3, 3)`` scatter-point covariance (m^2), zeros for a point landmark.
        body: ``(4,)`` the car body ``[length, width, height, depth]`` (m) of
            :func:`~mmslam.slam.models.vs.body_specular_point`; zeros (:data:`~mmslam.slam.models.vs.BODY_POINT`)
            for a point landmark.
        Z: ``(J, 5)`` measurements; R: ``(1, 5, 5)`` one covariance for all, or ``(J, 5, 5)`` one
            per measurement.
        loglik: ``(J,)`` out; m_post: ``(J, d)`` out; P_post: ``(len(R), d, d)`` out
            (exactly symmetric).
        work: scratch arrays from :func:`workspace` (allocated once per batch, not per Gaussian).
        floor_lik, floor_post: the floors of step 4 (``-inf``: every likelihood and mean computed).

    Returns:
        ``OK``, or ``BAD_POSITION_COV`` / ``BAD_INNOVATION_COV`` if that covariance is not
        positive definite (after the jitter retry of :func:`~mmslam.slam.core.linalg.cholesky`).
    """
    d = m.shape[0]
    J = Z.shape[0]
    Ppos, L, ya, xa, toa, hz, Dz, zhat, Pzz, S, LS, inv, Pxz, A, M = work
    point = True
    for i in range(3):
        for k in range(3):
            Ppos[i, k] = P[i, k] + extent[i, k]
            point = point and extent[i, k] == 0.0
    if not cholesky(Ppos, L):
        return BAD_POSITION_COV
    # 1.-2. cubature points r = k (+) and k + 3 (-) through h: path vectors, the 24 angles (az, el of
    # departure, az, el of arrival per point: ya[4 r + i] = atan2(ya, xa)), the body frame
    c = math.sqrt(3.0)
    heading = math.atan2(m[4], m[3]) if body[0] > 0.0 and d >= 5 else 0.0  # a VS body faces along the velocity
    for r in range(6):
        sign, k = (c, r) if r < 3 else (-c, r - 3)
        xr = (m[0] + sign * L[0, k], m[1] + sign * L[1, k], m[2] + sign * L[2, k])
        if body[0] > 0.0:
            xr = body_specular_point(xr, heading, b, s, body)
        toa[r], dep0, dep1, dep2, arr0, arr1, arr2 = path_vectors(geometry, s, xr, b)
        ya[4 * r], xa[4 * r], ya[4 * r + 1], xa[4 * r + 1] = angle_arguments(dep0, dep1, dep2)
        ya[4 * r + 2], xa[4 * r + 2], ya[4 * r + 3], xa[4 * r + 3] = angle_arguments(arr0, arr1, arr2)
    for i in range(24):
        ya[i] = atan2(ya[i], xa[i])
    for r in range(6):
        hz[r, 0], hz[r, 1], hz[r, 2], hz[r, 3], hz[r, 4] = body_frame(
            s, toa[r], ya[4 * r], ya[4 * r + 1], ya[4 * r + 2], ya[4 * r + 3])
    for a in range(MEAS_DIM):
        h0, mean = hz[0, a], 0.0
        for k in range(6):
            dev = residual_component(a, hz[k, a], h0)
            Dz[k, a] = dev
            mean += dev
        mean *= _SIXTH
        for k in range(6):
            Dz[k, a] -= mean
        zhat[a] = wrap(h0 + mean) if _IS_AZIMUTH[a] else h0 + mean
    for a in range(MEAS_DIM):
        for e in range(a + 1):
            t = 0.0
            for k in range(6):
                t += Dz[k, a] * Dz[k, e]
            Pzz[a, e] = t * _SIXTH
    point = d == 3 and point
    if not point:  # M = P[:, :3] L^-T: row i solves L M_i^T = P[i, :3]^T
        rl = (1.0 / L[0, 0], 1.0 / L[1, 1], 1.0 / L[2, 2])
        for i in range(d):
            for k in range(3):
                t = P[i, k]
                for e in range(k):
                    t -= L[k, e] * M[i, e]
                M[i, k] = t * rl[k]
    for a in range(MEAS_DIM):  # column a of G: (g0, g1, g2)
        g0 = (Dz[0, a] - Dz[3, a]) * _SIXTH
        g1 = (Dz[1, a] - Dz[4, a]) * _SIXTH
        g2 = (Dz[2, a] - Dz[5, a]) * _SIXTH
        if point:  # Pxz = sqrt(3) L G
            Pxz[0, a] = c * (L[0, 0] * g0)
            Pxz[1, a] = c * (L[1, 0] * g0 + L[1, 1] * g1)
            Pxz[2, a] = c * (L[2, 0] * g0 + L[2, 1] * g1 + L[2, 2] * g2)
        else:  # Pxz = sqrt(3) P[:, :3] L^-T G = sqrt(3) M G
            for i in range(d):
                Pxz[i, a] = c * (M[i, 0] * g0 + M[i, 1] * g1 + M[i, 2] * g2)
    # 3.-4. per measurement covariance: gain and posterior covariance; per measurement: likelihood, mean
    for r in range(R.shape[0]):
        for a in range(MEAS_DIM):
            for e in range(a + 1):
                S[a, e] = Pzz[a, e] + R[r, a, e]
        if not cholesky(S, LS):
            return BAD_INNOVATION_COV
        det = 1.0
        for a in range(MEAS_DIM):
            inv[a] = 1.0 / LS[a, a]
            det *= LS[a, a]
        if 0.0 < det < math.inf:  # log det L_S, one logarithm
            half_logdet = math.log(det)
        else:
            half_logdet = 0.0
            for a in range(MEAS_DIM):
                half_logdet += math.log(LS[a, a])
        for i in range(d):  # A = Pxz L_S^-T: forward substitution along each row
            for a in range(MEAS_DIM):
                t = Pxz[i, a]
                for e in range(a):
                    t -= LS[a, e] * A[i, e]
                A[i, a] = t * inv[a]
        for i in range(d):
            for k in range(i + 1):
                t = 0.5 * (P[i, k] + P[k, i])
                for a in range(MEAS_DIM):
                    t -= A[i, a] * A[k, a]
                P_post[r, i, k] = t
                P_post[r, k, i] = t
        j0, j1 = (0, J) if R.shape[0] == 1 else (r, r + 1)
        for j in range(j0, j1):
            y0 = residual_component(0, Z[j, 0], zhat[0]) * inv[0]  # y = L_S^-1 r by forward substitution
            if whitened_loglik(y0 * y0, half_logdet) < floor_lik:  # an upper bound of loglik[j]
                loglik[j] = -math.inf
                m_post[j, 0] = math.nan  # not computed: a reader that keeps it fails the finiteness check
                continue
            r1 = residual_component(1, Z[j, 1], zhat[1])
            r2 = residual_component(2, Z[j, 2], zhat[2])
            r3 = residual_component(3, Z[j, 3], zhat[3])
            r4 = residual_component(4, Z[j, 4], zhat[4])
            y1 = (r1 - LS[1, 0] * y0) * inv[1]
            y2 = (r2 - LS[2, 0] * y0 - LS[2, 1] * y1) * inv[2]
            y3 = (r3 - LS[3, 0] * y0 - LS[3, 1] * y1 - LS[3, 2] * y2) * inv[3]
            y4 = (r4 - LS[4, 0] * y0 - LS[4, 1] * y1 - LS[4, 2] * y2 - LS[4, 3] * y3) * inv[4]
            loglik[j] = whitened_loglik(y0 * y0 + y1 * y1 + y2 * y2 + y3 * y3 + y4 * y4, half_logdet)
            if loglik[j] < floor_post:
                m_post[j, 0] = math.nan
                continue
            for i in range(d):
                m_post[j, i] = m[i] + A[i, 0] * y0 + A[i, 1] * y1 + A[i, 2] * y2 + A[i, 3] * y3 + A[i, 4] * y4
    return OK


def workspace(d: int) -> tuple:
    """Scratch arrays of :func:`ckf_update` for a ``d``-dimensional Gaussian (allocated by the Python
    caller of a :func:`~mmslam.slam.core.jit.batch_kernel`, once per batch)."""
    return (np.empty((3, 3)), np.empty((3, 3)), np.empty(24), np.empty(24), np.empty(6),
            np.empty((6, MEAS_DIM)), np.empty((6, MEAS_DIM)), np.empty(MEAS_DIM), np.empty((MEAS_DIM, MEAS_DIM)),
            np.empty((MEAS_DIM, MEAS_DIM)), np.empty((MEAS_DIM, MEAS_DIM)), np.empty(MEAS_DIM),
            np.empty((d, MEAS_DIM)), np.empty((d, MEAS_DIM)), np.empty((d, 3)))


@nb.njit(cache=True, error_model="numpy", inline="always")
def _ckf_loop(geometry: int, m: np.ndarray, P: np.ndarray, s: np.ndarray, b: np.ndarray,
              extent: np.ndarray, body: np.ndarray, Z: np.ndarray, R: np.ndarray,
              loglik: np.ndarray, m_post: np.ndarray, P_post: np.ndarray, work: tuple) -> tuple[int, int]:
    """:func:`ckf_update` of every Gaussian ``n``; returns ``(n, code)`` of the first failure or ``(-1, OK)``."""
    for n in range(m.shape[0]):
        code = ckf_update(geometry, m[n], P[n], s[n], b, extent, body, Z, R, loglik[n], m_post[n], P_post[n], work)
        if code != OK:
            return n, code
    return -1, OK


# One compiled batch per path geometry: each inlines :func:`ckf_update` with a constant geometry
# (~1.4x faster than a run-time branch) and is compiled only when a map of that geometry is first
# corrected (one function with all three call sites took ~18 s to compile on a cold cache).
# Only ckf_update and this loop are inlined at numba IR level (inline="always"); the per-point
# functions it calls (measurement, trig, linalg, the log-likelihood) are left to LLVM: IR-inlining them
# too made each geometry's kernel take ~20 s instead of ~6 s to compile cold, for 3% of CKF speed.
@batch_kernel
def _ckf_batch_direct(m, P, s, b, extent, body, Z, R, loglik, m_post, P_post, work):  # noqa: ANN001, ANN202
    return _ckf_loop(0, m, P, s, b, extent, body, Z, R, loglik, m_post, P_post, work)  # Bounce.DIRECT


@batch_kernel
def _ckf_batch_mirror(m, P, s, b, extent, body, Z, R, loglik, m_post, P_post, work):  # noqa: ANN001, ANN202
    return _ckf_loop(1, m, P, s, b, extent, body, Z, R, loglik, m_post, P_post, work)  # Bounce.MIRROR


@batch_kernel
def _ckf_batch_scatter(m, P, s, b, extent, body, Z, R, loglik, m_post, P_post, work):  # noqa: ANN001, ANN202
    return _ckf_loop(2, m, P, s, b, extent, body, Z, R, loglik, m_post, P_post, work)  # Bounce.SCATTER


_CKF_BATCH = (_ckf_batch_direct, _ckf_batch_mirror, _ckf_batch_scatter)
"""The compiled batch of each :class:`mmslam.model.Bounce` code."""


@dataclass
class Innovation:
    """CKF update of ``N`` Gaussians against ``J`` measurements (:func:`innovate`).

    ``loglik (N, J)``: ``log N(z_j; zhat_n, S_n)``; ``m_post (N, J, d)``: updated means;
    ``P_post (N, 1, d, d)`` (one ``R``) or ``(N, J, d, d)`` (one ``R`` per measurement): updated
    covariances (use :meth:`post`).
    """

    loglik: np.ndarray
    m_post: np.ndarray
    P_post: np.ndarray

    def post(self, n: np.ndarray, j: np.ndarray) -> np.ndarray:
        """``(K, d, d)`` posterior covariances of the pairs (Gaussian ``n[k]``, measurement ``j[k]``)."""
        return self.P_post[n, j if self.P_post.shape[1] > 1 else 0]


def body_array(body: np.ndarray | None) -> np.ndarray:
    """``(4,)`` float body ``[length, width, height, depth]`` (m) for the kernels; None: a point landmark."""
    if body is None:
        return BODY_POINT
    out = np.ascontiguousarray(body, dtype=float).reshape(-1)
    if out.shape != (4,):
        raise ValueError(f"body has shape {np.shape(body)}; expected (4,) [length, width, height, depth] (m)")
    return out


def innovate(m: np.ndarray, P: np.ndarray, states: np.ndarray, geometry: int, bs: np.ndarray,
             Z: np.ndarray, R: np.ndarray, stage: str, extent: np.ndarray | None = None,
             body: np.ndarray | None = None) -> Innovation:
    """:func:`ckf_update` of Gaussians ``N(m[n], P[n])`` seen from vehicle states ``states[n]``.

    Args:
        m: ``(N, d)`` means; P: ``(N, d, d)`` covariances; states: ``(N, 7)`` the vehicle state of
            each Gaussian's particle.
        geometry: :class:`mmslam.model.Bounce` code (the type's ``LandmarkSpec.geometry``, handed over by
            the caller).
        bs: ``(3,)`` BS position (m).
        Z: ``(J, 5)`` measurements; R: ``(5, 5)`` one covariance, or ``(J, 5, 5)`` one per measurement.
        stage: named in errors.
        extent: ``(3, 3)`` scatter-point covariance (m^2), or None for a point landmark.
        body: ``(4,)`` car body of a VS (:func:`ckf_update`), or None for a point landmark.

    Raises:
        FloatingPointError: a non-finite or non-positive-definite covariance (naming ``stage``).
        ValueError: ``R`` of another shape.
    """
    m = np.ascontiguousarray(m, dtype=float)
    P = np.ascontiguousarray(P, dtype=float)
    n, d = m.shape
    Z = np.ascontiguousarray(np.asarray(Z, float).reshape(-1, MEAS_DIM))
    J = Z.shape[0]
    R = np.asarray(R, float)
    if R.shape == (MEAS_DIM, MEAS_DIM):
        R = R[None]
    elif R.shape != (J, MEAS_DIM, MEAS_DIM):
        raise ValueError(f"R has shape {R.shape}; expected (5, 5) or ({J}, 5, 5)")
    if d < 3 or P.shape != (n, d, d) or np.shape(states) != (n, 7) or np.shape(bs) != (3,):
        raise ValueError(f"{stage}: shapes m {m.shape}, P {P.shape}, states {np.shape(states)}, bs {np.shape(bs)}; "
                         f"expected (N, d >= 3), (N, d, d), (N, 7), (3,)")
    if not (np.isfinite(m).all() and np.isfinite(P).all()):
        raise FloatingPointError(f"non-finite covariance in {stage}")
    ext = np.zeros((3, 3)) if extent is None else np.asarray(extent, float).reshape(3, 3)
    loglik = np.empty((n, J))
    m_post = np.empty((n, J, d))
    P_post = np.empty((n, R.shape[0], d, d))
    bad, code = _CKF_BATCH[int(geometry)](m, P, np.ascontiguousarray(states, dtype=float),
                           np.ascontiguousarray(bs, dtype=float), ext, body_array(body), Z, np.ascontiguousarray(R),
                           loglik, m_post, P_post, workspace(d))
    if code == BAD_POSITION_COV:
        raise FloatingPointError(f"covariance not positive definite in {stage}")
    if code == BAD_INNOVATION_COV:
        raise FloatingPointError(f"covariance not positive definite in {stage} (innovation covariance)")
    return Innovation(loglik, m_post, P_post)


def cubature_factor(P: np.ndarray, stage: str = "cubature points") -> np.ndarray:
    """``sqrt(d) L`` ``(..., d, d)`` of covariances ``P (..., d, d)`` (``L`` the lower Cholesky factor):
    the spread of the cubature points (:func:`cubature_point_set`). FloatingPointError naming ``stage``
    if some ``P`` is not SPD."""
    return safe_cholesky(P, stage) * np.sqrt(P.shape[-1])


@nb.njit(cache=True, error_model="numpy", inline="always")
def cubature_point_set(m: np.ndarray, Ls: np.ndarray, out: np.ndarray) -> None:
    """Third-degree spherical-radial cubature points of ``N(m, P)`` (Arasaratnam & Haykin 2009):
    ``out[i] = m + Ls e_i`` and ``out[d + i] = m - Ls e_i`` for ``i < d``, with ``Ls = sqrt(d) L``
    (:func:`cubature_factor`). ``m (d,)``, ``Ls (d, d)``, ``out (2d, d)``; every point has weight ``1 / (2d)``."""
    d = m.shape[0]
    for i in range(d):
        for a in range(d):
            out[i, a] = m[a] + Ls[a, i]
            out[d + i, a] = m[a] - Ls[a, i]


@nb.njit(cache=True, error_model="numpy")
def _cubature_batch(m: np.ndarray, Ls: np.ndarray, out: np.ndarray) -> None:
    for n in range(m.shape[0]):
        cubature_point_set(m[n], Ls[n], out[n])


def cubature_points(m: np.ndarray, P: np.ndarray, stage: str = "cubature points") -> np.ndarray:
    """Third-degree spherical-radial cubature points of ``N(m, P)`` (:func:`cubature_point_set`).

    Args:
        m: means ``(..., d)``; P: covariances ``(..., d, d)`` (SPD); the batch shapes broadcast.

    Returns:
        ``(..., 2d, d)``: ``m + sqrt(d) L e_i`` for ``i < d`` and ``m - sqrt(d) L e_i`` after,
        with ``L`` the lower Cholesky factor of ``P``. All points carry weight ``1 / (2d)``.
    """
    m = np.asarray(m, dtype=float)
    d = m.shape[-1]
    if np.shape(P)[-2:] != (d, d):
        raise ValueError(f"cubature_points: means {m.shape} and covariances {np.shape(P)}; expected (..., d) and "
                         f"(..., d, d)")
    Ls = cubature_factor(np.asarray(P, dtype=float), stage)
    batch = np.broadcast_shapes(m.shape[:-1], Ls.shape[:-2])
    out = np.empty(batch + (2 * d, d))
    _cubature_batch(np.ascontiguousarray(np.broadcast_to(m, batch + (d,))).reshape(-1, d),
                    np.ascontiguousarray(np.broadcast_to(Ls, batch + (d, d))).reshape(-1, d, d),
                    out.reshape(-1, 2 * d, d))
    return out


def kalman_update(m: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, state: np.ndarray, geometry: int,
                  bs: np.ndarray, extent: np.ndarray | None = None,
                  body: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """CKF update of one Gaussian ``N(m (d,), P (d, d))`` by one measurement ``z (5,)`` seen from ``state (7,)``.

    A thin wrapper over :func:`innovate` (tests, single Gaussians): ``(m_post, P_post, log N(z; zhat, S))``.
    """
    inn = innovate(np.asarray(m, float)[None], np.asarray(P, float)[None], np.asarray(state, float)[None],
                   geometry, bs, np.asarray(z, float)[None], R, "kalman_update", extent, body)
    return inn.m_post[0, 0], inn.P_post[0, 0], float(inn.loglik[0, 0])
