"""Vehicle-scatterer (VS) map PHD: prediction and birth Gaussians (paper Sec. IV-A, V-A).

VS state ``t = [x, y, z, vx, vy, vz, xi]`` (global frame; m, m/s, rad/s), Cartesian coordinated
turn with unknown turn rate (:func:`mmslam.slam.dynamics.vs_ct`). Prediction is the extended
Kalman (first-order) propagation of each Gaussian of a padded :class:`~mmslam.slam.gm.GM` batch.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .dynamics import VS_DIM, vs_ct_point
from .gm import GM, symmetrize

DEFAULT_TURN_MEAN = 0.0
"""Mean of the Gaussian birth turn rate (rad/s); see :func:`vs_birth_mean`."""


@nb.njit(cache=True, error_model="numpy")
def _ekf_predict(m: np.ndarray, P: np.ndarray, dt: float, add: np.ndarray, m_out: np.ndarray,
                 P_out: np.ndarray) -> None:
    """EKF prediction of each Gaussian ``N(m[n], P[n])`` (7-D VS): ``m' = f(m)``, ``P' = F P F^T + add``
    (exactly symmetric), with ``f``, ``F`` from :func:`~mmslam.slam.dynamics.vs_ct_point`."""
    F = np.empty((VS_DIM, VS_DIM))
    FP = np.empty((VS_DIM, VS_DIM))
    for n in range(m.shape[0]):
        vs_ct_point(m[n], dt, m_out[n], F)
        for i in range(VS_DIM):
            for k in range(VS_DIM):
                t = 0.0
                for a in range(VS_DIM):
                    t += F[i, a] * P[n, a, k]
                FP[i, k] = t
        for i in range(VS_DIM):
            for k in range(i + 1):
                t1 = 0.0
                t2 = 0.0
                for a in range(VS_DIM):
                    t1 += FP[i, a] * F[k, a]
                    t2 += FP[k, a] * F[i, a]
                v = 0.5 * (t1 + t2) + 0.5 * (add[i, k] + add[k, i])
                P_out[n, i, k] = v
                P_out[n, k, i] = v


def predict_vs(g: GM, dt: float, p_survival: float, q_std: np.ndarray,
               dither: np.ndarray | None) -> GM:
    """Predict a batch of VS Gaussian mixtures one step (paper eq. (9), no birth).

    For every live component: ``m' = vs_ct(m, dt)``, ``P' = J P J^T + Q + T_d`` with
    ``J = d vs_ct / d t`` at ``m``, ``Q = diag(q_std^2)`` (process noise) and ``T_d =
    diag(dither)`` (the paper's dithering covariance added at every prediction), and
    ``w' = p_survival * w``. Masked slots stay ``w = 0, m = 0, P = I``.

    Args:
        g: batch of VS mixtures, any batch shape ``B``, ``Q`` slots, ``d = 7``.
        dt: time step in s.
        p_survival: survival probability ``P_S`` in [0, 1].
        q_std: ``(7,)`` process-noise standard deviations (m, m, m, m/s, m/s, m/s, rad/s).
        dither: ``(7,)`` dithering *variances* (diagonal of ``T_d``), or None for none.

    Returns:
        The predicted batch (same shapes), covariances symmetrised.
    """
    if g.dim != VS_DIM:
        raise ValueError(f"predict_vs expects {VS_DIM}-D VS states, got dimension {g.dim}")
    q_std = np.asarray(q_std, dtype=float)
    if q_std.shape != (VS_DIM,):
        raise ValueError(f"q_std must have shape ({VS_DIM},), got {q_std.shape}")
    add = np.diag(q_std**2)
    if dither is not None:
        dither = np.asarray(dither, dtype=float)
        if dither.shape != (VS_DIM,):
            raise ValueError(f"dither must have shape ({VS_DIM},), got {dither.shape}")
        add = add + np.diag(dither)
    live = g.mask
    idx = np.nonzero(live)  # only live components are propagated (masked slots: 0 / I)
    m, P = np.ascontiguousarray(g.m[idx]), np.ascontiguousarray(g.P[idx])
    m_pred, P_pred = np.empty_like(m), np.empty_like(P)
    _ekf_predict(m, P, float(dt), add, m_pred, P_pred)
    m_new = np.zeros_like(g.m)
    m_new[idx] = m_pred
    P_new = np.broadcast_to(np.eye(VS_DIM), g.P.shape).copy()
    P_new[idx] = P_pred
    w_new = np.where(live, g.w * p_survival, 0.0)
    out = GM(w_new, m_new, P_new, live.copy(), g.pd_beta)
    out.check("after VS prediction")
    return out


def vs_birth_mean(pos: np.ndarray, turn_mean: float = DEFAULT_TURN_MEAN) -> np.ndarray:
    """VS birth means ``(..., 7)`` from birth positions ``pos`` ``(..., 3)`` (global frame, m).

    Velocity mean 0 (``v ~ N(0, V)`` in the paper). Turn rate: the paper draws
    ``xi ~ U(0, 2 pi]`` "with sigma_xi = pi/2"; a GM-PHD birth needs a Gaussian, and the
    approximation used here is ``xi ~ N(turn_mean, (pi/2)^2)`` with ``turn_mean = 0`` by default.
    Rationale: the turn direction of an unseen vehicle is unknown, so the prior should be
    symmetric about straight driving; a mean of pi (the uniform's mean) would assert a fast
    left turn (pi rad/s) for every new VS, which no road vehicle does. A std of pi/2 rad/s
    (the paper's sigma_xi) keeps realistic turn rates (e.g. the scenario's pi/10) well inside
    one sigma while letting the data decide the sign.
    """
    pos = np.asarray(pos, dtype=float)
    out = np.zeros(pos.shape[:-1] + (VS_DIM,))
    out[..., 0:3] = pos
    out[..., 6] = turn_mean
    return out


def vs_birth_covariance(P_pos: np.ndarray, vel_var: np.ndarray,
                        turn_std: float = math.pi / 2) -> np.ndarray:
    """Block-diagonal VS birth covariance ``blkdiag(P_pos, diag(vel_var), turn_std^2)``.

    Args:
        P_pos: ``(..., 3, 3)`` position covariance (m^2), e.g. from the CKF birth of an SP.
        vel_var: ``(3,)`` velocity variances (m^2/s^2), the paper's ``V = diag(100, 100, 0.09)``.
        turn_std: turn-rate std (rad/s), the paper's ``sigma_xi = pi/2``.

    Returns:
        ``(..., 7, 7)`` symmetric covariances.
    """
    P_pos = np.asarray(P_pos, dtype=float)
    vel_var = np.asarray(vel_var, dtype=float)
    if P_pos.shape[-2:] != (3, 3):
        raise ValueError(f"P_pos must end in (3, 3), got {P_pos.shape}")
    if vel_var.shape != (3,):
        raise ValueError(f"vel_var must have shape (3,), got {vel_var.shape}")
    out = np.zeros(P_pos.shape[:-2] + (VS_DIM, VS_DIM))
    out[..., 0:3, 0:3] = symmetrize(P_pos)
    out[..., 3:6, 3:6] = np.diag(vel_var)
    out[..., 6, 6] = float(turn_std) ** 2
    return out
