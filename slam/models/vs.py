"""Vehicle-scatterer (VS) map PHD: prediction and birth Gaussians (paper Sec. IV-A, V-A).

VS state ``t = [x, y, z, vx, vy, vz, xi]`` (global frame; m, m/s, rad/s), Cartesian coordinated
turn with unknown turn rate (:func:`mmslam.slam.models.dynamics.vs_ct`). Prediction is the extended
Kalman (first-order) propagation of each Gaussian of a padded :class:`~mmslam.slam.core.gm.GM` batch.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .dynamics import VS_DIM, vs_ct_point
from ..core.gm import GM, dead_gaussian, finite_gaussian
from ..core.jit import batch_kernel

DEFAULT_TURN_MEAN = 0.0
"""Mean of the Gaussian birth turn rate (rad/s); see :func:`vs_birth_mean`."""


@nb.njit(cache=True, error_model="numpy", inline="always")
def row_times(x: np.ndarray, M: np.ndarray, out: np.ndarray) -> None:
    """``out (7,) = x^T M`` for ``x (7,)``, ``M (7, 7)``: ``out[k] = sum_a x[a] M[a, k]``, each sum in
    the order ``a = 0..6``, the seven sums side by side (independent accumulators)."""
    t0 = t1 = t2 = t3 = t4 = t5 = t6 = 0.0
    for a in range(VS_DIM):
        f = x[a]
        t0 += f * M[a, 0]
        t1 += f * M[a, 1]
        t2 += f * M[a, 2]
        t3 += f * M[a, 3]
        t4 += f * M[a, 4]
        t5 += f * M[a, 5]
        t6 += f * M[a, 6]
    out[0], out[1], out[2], out[3], out[4], out[5], out[6] = t0, t1, t2, t3, t4, t5, t6


@nb.njit(cache=True, error_model="numpy", inline="always")
def ekf_predict_point(m: np.ndarray, P: np.ndarray, dt: float, add: np.ndarray, m_out: np.ndarray,
                      P_out: np.ndarray, work: np.ndarray) -> None:
    """EKF prediction of one VS Gaussian ``N(m, P)`` (paper eq. (9)): ``m' = f(m)``,
    ``P' = F P F^T + add`` (exactly symmetric: the mean of ``G = F P F^T`` and ``G^T``), with
    ``f``, ``F`` from :func:`~mmslam.slam.models.dynamics.vs_ct_point`. ``m, m_out (7,)``;
    ``P, add, P_out (7, 7)``; ``work (3, 7, 7)`` scratch."""
    F, Ft, FP = work[0], work[1], work[2]
    vs_ct_point(m, dt, m_out, F)
    for i in range(VS_DIM):
        for k in range(VS_DIM):
            Ft[k, i] = F[i, k]
    for i in range(VS_DIM):
        row_times(F[i], P, FP[i])  # (F P)[i, :]
    for i in range(VS_DIM):
        row_times(FP[i], Ft, P_out[i])  # G[i, :] = (F P F^T)[i, :]
    for i in range(VS_DIM):
        for k in range(i + 1):
            v = 0.5 * (P_out[i, k] + P_out[k, i]) + 0.5 * (add[i, k] + add[k, i])
            P_out[i, k] = v
            P_out[k, i] = v


@batch_kernel
def _predict_batch(w: np.ndarray, m: np.ndarray, P: np.ndarray, mask: np.ndarray, dt: float, p_survival: float,
                   add: np.ndarray, off: int, w_out: np.ndarray, m_out: np.ndarray, P_out: np.ndarray,
                   mask_out: np.ndarray, work: np.ndarray) -> bool:
    """:func:`ekf_predict_point` and ``w' = p_survival w`` of every live slot ``(n, q)`` of a flat batch
    ``(N, Q, ...)`` into output slot ``(n, off + q)``; dead slots ``w = 0``, ``m = 0``, ``P = I``.
    ``work (3, 7, 7)``: scratch. Returns False if a live predicted component is not finite."""
    ok = True
    for n in range(w.shape[0]):
        for q in range(w.shape[1]):
            r = off + q
            mask_out[n, r] = mask[n, q]
            if mask[n, q]:
                w_out[n, r] = w[n, q] * p_survival
                ekf_predict_point(m[n, q], P[n, q], dt, add, m_out[n, r], P_out[n, r], work)
                ok &= finite_gaussian(w_out[n, r], m_out[n, r], P_out[n, r])
            else:
                w_out[n, r] = 0.0
                dead_gaussian(m_out[n, r], P_out[n, r])
    return ok


def process_noise(q_std: np.ndarray, dither: np.ndarray | None) -> np.ndarray:
    """``Q + T_d = diag(q_std^2) + diag(dither)`` ``(7, 7)``: the covariance added by :func:`predict_vs`.

    Raises ValueError unless ``q_std`` and ``dither`` (if given) have shape ``(7,)``.
    """
    q_std = np.asarray(q_std, dtype=float)
    if q_std.shape != (VS_DIM,):
        raise ValueError(f"q_std must have shape ({VS_DIM},), got {q_std.shape}")
    add = np.diag(q_std**2)
    if dither is not None:
        dither = np.asarray(dither, dtype=float)
        if dither.shape != (VS_DIM,):
            raise ValueError(f"dither must have shape ({VS_DIM},), got {dither.shape}")
        add = add + np.diag(dither)
    return add


def predict_vs_into(g: GM, dt: float, p_survival: float, add: np.ndarray, out: GM, off: int) -> None:
    """:func:`predict_vs` of ``g`` (batch ``B``, ``Q`` slots) written to the slots ``off .. off + Q`` of
    ``out`` (batch ``B``, contiguous arrays; e.g. a predicted map and its births side by side);
    ``add (7, 7)`` from :func:`process_noise`. ``out.pd_beta`` and ``out.label`` are not touched.

    Raises FloatingPointError if a live predicted component is not finite; ValueError if ``out`` is
    not a contiguous float batch of shape ``B`` with room for ``Q`` slots at ``off``, or ``add`` not
    ``(7, 7)`` (the compiled loop would write past ``out`` or into a copy).
    """
    if g.dim != VS_DIM:
        raise ValueError(f"predict_vs expects {VS_DIM}-D VS states, got dimension {g.dim}")
    B, q = g.batch_shape, g.capacity
    n, k = int(np.prod(B, dtype=int)), out.capacity
    arrays = ((out.w, np.float64), (out.m, np.float64), (out.P, np.float64), (out.mask, np.bool_))
    if (out.batch_shape != B or out.dim != VS_DIM or not 0 <= off <= k - q
            or not all(a.dtype == t and a.flags.c_contiguous for a, t in arrays)
            or np.shape(add) != (VS_DIM, VS_DIM)):
        raise ValueError(f"predict_vs_into: out (batch {out.batch_shape}, {k} slots, dim {out.dim}) cannot take "
                         f"{q} slots of batch {B} at offset {off}, or add {np.shape(add)} is not (7, 7); "
                         f"pass contiguous float arrays of batch {B} with at least off + {q} slots")
    if not _predict_batch(np.ascontiguousarray(g.w, dtype=float).reshape(n, q),
                          np.ascontiguousarray(g.m, dtype=float).reshape(n, q, VS_DIM),
                          np.ascontiguousarray(g.P, dtype=float).reshape(n, q, VS_DIM, VS_DIM),
                          np.ascontiguousarray(g.mask, dtype=bool).reshape(n, q), float(dt), float(p_survival),
                          np.ascontiguousarray(add, dtype=float), int(off), out.w.reshape(n, k),
                          out.m.reshape(n, k, VS_DIM), out.P.reshape(n, k, VS_DIM, VS_DIM), out.mask.reshape(n, k),
                          np.empty((3, VS_DIM, VS_DIM))):
        raise FloatingPointError("non-finite Gaussian component after VS prediction")


def predict_vs(g: GM, dt: float, p_survival: float, q_std: np.ndarray,
               dither: np.ndarray | None) -> GM:
    """Predict a batch of VS Gaussian mixtures one step (paper eq. (9), no birth).

    For every live component: ``m' = vs_ct(m, dt)``, ``P' = J P J^T + Q + T_d`` with
    ``J = d vs_ct / d t`` at ``m``, ``Q = diag(q_std^2)`` (process noise) and ``T_d =
    diag(dither)`` (the paper's dithering covariance added at every prediction), and
    ``w' = p_survival * w`` (:func:`ekf_predict_point`). Masked slots stay ``w = 0, m = 0, P = I``.

    Args:
        g: batch of VS mixtures, any batch shape ``B``, ``Q`` slots, ``d = 7``.
        dt: time step in s.
        p_survival: survival probability ``P_S`` in [0, 1].
        q_std: ``(7,)`` process-noise standard deviations (m, m, m, m/s, m/s, m/s, rad/s).
        dither: ``(7,)`` dithering *variances* (diagonal of ``T_d``), or None for none.

    Returns:
        The predicted batch (same shapes, the same ``pd_beta`` and ``label``), covariances exactly symmetric.
    """
    if g.dim != VS_DIM:
        raise ValueError(f"predict_vs expects {VS_DIM}-D VS states, got dimension {g.dim}")
    add = process_noise(q_std, dither)
    out = GM(np.empty(g.w.shape), np.empty(g.m.shape), np.empty(g.P.shape), np.empty(g.mask.shape, bool),
             g.pd_beta, g.label)
    predict_vs_into(g, dt, p_survival, add, out, 0)
    return out


@nb.njit(cache=True, error_model="numpy", inline="always")
def vs_birth_mean_point(pos: np.ndarray, turn_mean: float, out: np.ndarray) -> None:
    """VS birth mean ``out (7,) = [pos, 0, 0, 0, turn_mean]`` of one birth position ``pos (3,)``
    (m; velocity m/s, turn rate rad/s; see :func:`vs_birth_mean`)."""
    for a in range(3):
        out[a] = pos[a]
        out[3 + a] = 0.0
    out[6] = turn_mean


@nb.njit(cache=True, error_model="numpy", inline="always")
def vs_birth_cov_point(P_pos: np.ndarray, vel_var: np.ndarray, turn_std: float, out: np.ndarray) -> None:
    """VS birth covariance ``out (7, 7) = blkdiag((P_pos + P_pos^T) / 2, diag(vel_var), turn_std^2)``
    of one position covariance ``P_pos (3, 3)`` (m^2); ``vel_var (3,)`` (m/s)^2, ``turn_std`` rad/s."""
    for a in range(VS_DIM):
        for b in range(VS_DIM):
            out[a, b] = 0.0
    for a in range(3):
        for b in range(3):
            out[a, b] = 0.5 * (P_pos[a, b] + P_pos[b, a])
        out[3 + a, 3 + a] = vel_var[a]
    out[6, 6] = turn_std ** 2


@nb.njit(cache=True, error_model="numpy")
def _birth_mean_batch(pos: np.ndarray, turn_mean: float, out: np.ndarray) -> None:
    for n in range(pos.shape[0]):
        vs_birth_mean_point(pos[n], turn_mean, out[n])


@nb.njit(cache=True, error_model="numpy")
def _birth_cov_batch(P_pos: np.ndarray, vel_var: np.ndarray, turn_std: float, out: np.ndarray) -> None:
    for n in range(P_pos.shape[0]):
        vs_birth_cov_point(P_pos[n], vel_var, turn_std, out[n])


def vs_birth_mean(pos: np.ndarray, turn_mean: float = DEFAULT_TURN_MEAN) -> np.ndarray:
    """VS birth means ``(..., 7)`` from birth positions ``pos`` ``(..., 3)`` (global frame, m).

    Velocity mean 0 (``v ~ N(0, V)`` in the paper; :func:`vs_birth_mean_point`). Turn rate: the paper draws
    ``xi ~ U(0, 2 pi]`` "with sigma_xi = pi/2"; a GM-PHD birth needs a Gaussian, and the
    approximation used here is ``xi ~ N(turn_mean, (pi/2)^2)`` with ``turn_mean = 0`` by default.
    Rationale: the turn direction of an unseen vehicle is unknown, so the prior should be
    symmetric about straight driving; a mean of pi (the uniform's mean) would assert a fast
    left turn (pi rad/s) for every new VS, which no road vehicle does. A std of pi/2 rad/s
    (the paper's sigma_xi) keeps realistic turn rates (e.g. the scenario's pi/10) well inside
    one sigma while letting the data decide the sign.
    """
    pos = np.asarray(pos, dtype=float)
    if pos.shape[-1:] != (3,):
        raise ValueError(f"pos must end in (3,), got {pos.shape}")
    out = np.empty(pos.shape[:-1] + (VS_DIM,))
    _birth_mean_batch(np.ascontiguousarray(pos).reshape(-1, 3), float(turn_mean), out.reshape(-1, VS_DIM))
    return out


def vs_birth_covariance(P_pos: np.ndarray, vel_var: np.ndarray,
                        turn_std: float = math.pi / 2) -> np.ndarray:
    """Block-diagonal VS birth covariance ``blkdiag(P_pos, diag(vel_var), turn_std^2)`` (:func:`vs_birth_cov_point`).

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
    out = np.empty(P_pos.shape[:-2] + (VS_DIM, VS_DIM))
    _birth_cov_batch(np.ascontiguousarray(P_pos).reshape(-1, 3, 3), vel_var, float(turn_std),
                     out.reshape(-1, VS_DIM, VS_DIM))
    return out


# ---------------------------------------------------------------------------- the car body of a VS
BODY_POINT = np.zeros(4)
"""The body model of a point VS (:func:`body_specular_point` returns the antenna position itself)."""


@nb.njit(cache=True, error_model="numpy", inline="always")
def body_specular_point(x: tuple[float, float, float], heading: float, b: np.ndarray, u: np.ndarray,
                        body: np.ndarray) -> tuple[float, float, float]:
    """Where a path BS -> car body -> receiver bounces off the body of a VS with antenna at ``x``.

    The body is the ellipsoid ``(p - c)^T M^-1 (p - c) = 1`` with centre ``c = x - (0, 0, depth)`` and
    ``M = R(heading) diag(a^2, b^2, h^2) R(heading)^T``, semi-axes ``(a, b, h) = (length, width,
    height) / 2`` along the car's forward, left and up axes. A specular bounce leaves the surface where
    the outward normal bisects the directions to the BS ``b`` and to the receiver ``u``:
    ``n = (b - c) / |b - c| + (u - c) / |u - c|`` (directions from the centre: both ends are far
    compared with the body), and the point of the ellipsoid with outward normal ``n`` is
    ``p = c + M n / sqrt(n^T M n)``. On the traced city scenes this moves the predicted path length of a VS
    path by 2-3.5 m, onto the traced one (docs/city-slam.md, "Vehicles as extended scatterers").

    Args:
        x: the VS's antenna position (m, global frame; the VS state's position, as the ego Gaussian).
        heading: the car's heading (rad; of a VS Gaussian: its mean velocity's direction).
        b, u: ``(3,)`` BS and receiving-vehicle antenna positions (m).
        body: ``(4,)`` ``[length, width, height, depth]`` (m): the body's size and its centre's depth
            below the antenna; length 0: a point VS, ``p = x``.

    Returns:
        ``p`` (m, global frame).
    """
    if body[0] <= 0.0:
        return x[0], x[1], x[2]
    c0, c1, c2 = x[0], x[1], x[2] - body[3]
    db0, db1, db2 = b[0] - c0, b[1] - c1, b[2] - c2
    du0, du1, du2 = u[0] - c0, u[1] - c1, u[2] - c2
    nb_ = math.sqrt(db0 * db0 + db1 * db1 + db2 * db2)
    nu_ = math.sqrt(du0 * du0 + du1 * du1 + du2 * du2)
    n0 = db0 / nb_ + du0 / nu_
    n1 = db1 / nb_ + du1 / nu_
    n2 = db2 / nb_ + du2 / nu_
    ch, sh = math.cos(heading), math.sin(heading)
    f, l_ = ch * n0 + sh * n1, -sh * n0 + ch * n1  # n in the car frame (forward, left)
    a2, w2, h2 = (0.5 * body[0]) ** 2, (0.5 * body[1]) ** 2, (0.5 * body[2]) ** 2
    mf, ml, mz = a2 * f, w2 * l_, h2 * n2  # M n in the car frame
    s = math.sqrt(f * mf + l_ * ml + n2 * mz)
    if not s > 0.0:  # the BS and the receiver on opposite sides through the centre: no bisector
        return c0, c1, c2
    return c0 + (ch * mf - sh * ml) / s, c1 + (sh * mf + ch * ml) / s, c2 + mz / s


@nb.njit(cache=True, error_model="numpy", inline="always")
def body_centre_offset(p: np.ndarray, b: np.ndarray, u: np.ndarray, body: np.ndarray) -> tuple[float, float, float]:
    """The antenna position of a car whose body a path bounced off at ``p (3,)`` (m), heading unknown: the
    inverse of :func:`body_specular_point` for the heading-averaged body, a spheroid of horizontal
    semi-axis ``r = sqrt((a^2 + b^2) / 2)`` and vertical ``h`` (the normal ``n`` taken at ``p``):
    ``x = p - M n / sqrt(n^T M n) + (0, 0, depth)``, ``M = diag(r^2, r^2, h^2)``. For a VS birth, whose
    velocity (so heading) is not known yet. ``body``: as :func:`body_specular_point` (length 0: ``x = p``)."""
    if body[0] <= 0.0:
        return p[0], p[1], p[2]
    db0, db1, db2 = b[0] - p[0], b[1] - p[1], b[2] - p[2]
    du0, du1, du2 = u[0] - p[0], u[1] - p[1], u[2] - p[2]
    nb_ = math.sqrt(db0 * db0 + db1 * db1 + db2 * db2)
    nu_ = math.sqrt(du0 * du0 + du1 * du1 + du2 * du2)
    n0 = db0 / nb_ + du0 / nu_
    n1 = db1 / nb_ + du1 / nu_
    n2 = db2 / nb_ + du2 / nu_
    r2 = 0.5 * ((0.5 * body[0]) ** 2 + (0.5 * body[1]) ** 2)
    h2 = (0.5 * body[2]) ** 2
    s = math.sqrt(r2 * (n0 * n0 + n1 * n1) + h2 * n2 * n2)
    if not s > 0.0:
        return p[0], p[1], p[2] + body[3]
    return p[0] - r2 * n0 / s, p[1] - r2 * n1 / s, p[2] - h2 * n2 / s + body[3]


@nb.njit(cache=True, error_model="numpy")
def _specular_batch(x: np.ndarray, heading: np.ndarray, b: np.ndarray, u: np.ndarray, body: np.ndarray,
                    out: np.ndarray) -> None:
    for n in range(x.shape[0]):
        out[n, 0], out[n, 1], out[n, 2] = body_specular_point((x[n, 0], x[n, 1], x[n, 2]), heading[n], b, u[n], body)


def body_points(x: np.ndarray, heading: np.ndarray, bs: np.ndarray, u: np.ndarray, body: np.ndarray) -> np.ndarray:
    """:func:`body_specular_point` over rows: antenna positions ``x (n, 3)``, headings ``(n,)`` (rad), receivers
    ``u (n, 3)``, one BS ``(3,)`` and body ``(4,)``; returns ``(n, 3)`` bounce points (m)."""
    x = np.ascontiguousarray(x, float).reshape(-1, 3)
    out = np.empty_like(x)
    _specular_batch(x, np.ascontiguousarray(np.broadcast_to(heading, x.shape[:1]), float), np.asarray(bs, float),
                    np.ascontiguousarray(np.broadcast_to(u, x.shape), float), np.asarray(body, float), out)
    return out


@nb.njit(cache=True, error_model="numpy")
def _centre_batch(p: np.ndarray, u: np.ndarray, b: np.ndarray, body: np.ndarray, out: np.ndarray) -> None:
    for n in range(p.shape[0]):
        out[n, 0], out[n, 1], out[n, 2] = body_centre_offset(p[n], b, u[n], body)


def body_antennas(p: np.ndarray, u: np.ndarray, bs: np.ndarray, body: np.ndarray) -> np.ndarray:
    """:func:`body_centre_offset` over rows: bounce points ``p (..., 3)`` seen from receivers ``u (..., 3)``
    (broadcast), one BS ``(3,)`` and body ``(4,)``; returns the antenna positions ``(..., 3)`` (m)."""
    shape = np.broadcast_shapes(np.shape(p), np.shape(u))
    pf = np.array(np.broadcast_to(p, shape), float).reshape(-1, 3)  # copies: writable, C-contiguous (one signature)
    out = np.empty_like(pf)
    _centre_batch(pf, np.array(np.broadcast_to(u, shape), float).reshape(-1, 3), np.array(bs, float),
                  np.array(body, float), out)
    return out.reshape(shape)
