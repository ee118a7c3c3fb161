"""Measurement-driven birth of landmark Gaussians (TWC2020 App. D-A; paper Sec. IV-A for VS).

For every particle ``p`` and measurement ``z_j`` the ``2 x 5 = 10`` cubature points of
``N(z_j, R)`` (``R`` the filter's measurement covariance) are each mapped to a landmark position
by geometric inversion given the particle's vehicle state ``s_p = [x, y, z, alpha, zeta, xi, B]``;
the birth Gaussian is the mean and covariance of the 10 images (all in the global frame, m).

- VA: from the vehicle ``u`` along the AOA direction (body azimuth + heading ``alpha``,
  elevation) at range ``TOA - B``: ``v = u + (TOA - B) d``.
- SP (and the position part of VS): the point ``s = u + r d`` on the AOA ray with
  ``TOA - B = |b - s| + |s - u|`` (an ellipsoid with foci ``b`` and ``u`` intersected with the
  ray): ``r = (L^2 - |b - u|^2) / (2 (L - d . (b - u)))`` with ``L = TOA - B``; it needs
  ``L > |b - u|``.

AOD components do not enter the inversion (the AOA ray and the TOA determine the point).
A birth is dropped when any of its cubature images is invalid (non-positive range, ``L <= |b - u|``)
and, for SP and VS, when its mean lies outside the sensor FOV (``p_D = 0`` there).
"""
from __future__ import annotations

import math
from typing import Callable

import numba as nb
import numpy as np

from mmslam.model import Bounce

from .ckf import cubature_factor, cubature_point_set
from ..core.gm import GM, dead_gaussian, live_slots
from ..core.jit import batch_kernel
from ..models.dynamics import VS_DIM
from ..models.measurement import MEAS_DIM, LandmarkKind, check_geometry
from ..models.vs import DEFAULT_TURN_MEAN, vs_birth_cov_point, vs_birth_mean_point


_MIRROR, _SCATTER = int(Bounce.MIRROR), int(Bounce.SCATTER)


@nb.njit(cache=True, error_model="numpy", inline="always")
def invert_ray(geometry: int, s: np.ndarray, d0: float, d1: float, d2: float, L: float, b: np.ndarray,
               out: np.ndarray) -> bool:
    """Landmark point ``x`` on the AOA ray ``u + r d`` of vehicle state ``s`` with path length ``L``.

    Paper eq. (3) inverted for the TOA and AOA (the AOD does not enter):

    - MIRROR (VA): ``x = u + L d`` (the image source lies on the ray at the path length);
    - SCATTER (SP, VS): ``x = u + r d`` on the ellipsoid ``|b - x| + |x - u| = L``:
      ``r = (L^2 - |b - u|^2) / (2 (L - d . (b - u)))``, which needs ``L > |b - u|``.

    Args: ``geometry`` (:class:`mmslam.model.Bounce`), ``s (7,)`` vehicle state (antenna ``u =
    s[:3]``), ``d = (d0, d1, d2)`` global unit AOA direction, ``L = TOA - B`` (m), ``b (3,)`` BS
    position; ``out (3,)`` receives ``x`` (global frame, m). Returns False for an invalid image
    (non-positive range, ``L <= |b - u|``).
    """
    if geometry == _MIRROR:
        r = L
        valid = L > 0.0
    else:
        b0, b1, b2 = b[0] - s[0], b[1] - s[1], b[2] - s[2]
        nbu2 = b0 * b0 + b1 * b1 + b2 * b2
        den = 2.0 * (L - (d0 * b0 + d1 * b1 + d2 * b2))
        valid = L * L > nbu2 and L > 0.0 and den > 0.0
        r = (L * L - nbu2) / den if valid else 0.0
        valid = valid and r > 0.0
    out[0] = s[0] + r * d0
    out[1] = s[1] + r * d1
    out[2] = s[2] + r * d2
    return valid


@nb.njit(cache=True, error_model="numpy")
def invert_point(geometry: int, s: np.ndarray, z: np.ndarray, b: np.ndarray, out: np.ndarray) -> bool:
    """:func:`invert_ray` of measurement ``z (5,)``: global AOA direction (body azimuth ``z[3]`` plus
    heading ``s[3]``, elevation ``z[4]``) and ``L = z[0] - s[6]``."""
    az = z[3] + s[3]
    ce = math.cos(z[4])
    return invert_ray(geometry, s, ce * math.cos(az), ce * math.sin(az), math.sin(z[4]), z[0] - s[6], b, out)


@nb.njit(cache=True, error_model="numpy")
def _invert_loop(geometry: int, s: np.ndarray, z: np.ndarray, b: np.ndarray, out: np.ndarray,
                 valid: np.ndarray) -> None:
    for n in range(s.shape[0]):
        valid[n] = invert_point(geometry, s[n], z[n], b, out[n])


def _invert(geometry: int, state: np.ndarray, z: np.ndarray, bs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    state, z = np.asarray(state, float), np.asarray(z, float)
    shape = np.broadcast_shapes(state.shape[:-1], z.shape[:-1])
    out, valid = np.empty(shape + (3,)), np.empty(shape, bool)
    _invert_loop(check_geometry(geometry), np.ascontiguousarray(np.broadcast_to(state, shape + (state.shape[-1],))).reshape(-1, state.shape[-1]),
                 np.ascontiguousarray(np.broadcast_to(z, shape + (5,))).reshape(-1, 5),
                 np.ascontiguousarray(bs, dtype=float), out.reshape(-1, 3), valid.reshape(-1))
    return out, valid


def invert_va(state: np.ndarray, z: np.ndarray, bs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """VA image-source position from a measurement: ``(position (..., 3), valid (...))``.

    ``state (..., 7)`` vehicle states and ``z (..., 5)`` measurements broadcast together
    (:func:`invert_point`, MIRROR). ``bs`` is unused (kept for a uniform signature).
    """
    return _invert(Bounce.MIRROR, state, z, bs)


def invert_sp(state: np.ndarray, z: np.ndarray, bs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Single-scatter point from a measurement: ``(position (..., 3), valid (...))`` (:func:`invert_point`, SCATTER)."""
    return _invert(Bounce.SCATTER, state, z, bs)


@nb.njit(cache=True, error_model="numpy", inline="always")
def image_moments(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> bool:
    """Equal-weight moments of the images ``x (K, 3)`` of one measurement's cubature points.

    ``mean (3,) = sum x_k / K``, ``cov (3, 3) = sum (x_k - mean)(x_k - mean)^T / K`` are written.
    Returns False if a moment is not finite or the spread is degenerate (``det(cov) <= 0``).
    """
    K = x.shape[0]
    # one pass per moment order, the sums (each over k in order) side by side
    s0 = s1 = s2 = 0.0
    for k in range(K):
        s0 += x[k, 0]
        s1 += x[k, 1]
        s2 += x[k, 2]
    m0, m1, m2 = s0 / K, s1 / K, s2 / K
    c00 = c10 = c11 = c20 = c21 = c22 = 0.0
    for k in range(K):
        e0, e1, e2 = x[k, 0] - m0, x[k, 1] - m1, x[k, 2] - m2
        c00 += e0 * e0
        c10 += e1 * e0
        c11 += e1 * e1
        c20 += e2 * e0
        c21 += e2 * e1
        c22 += e2 * e2
    mean[0], mean[1], mean[2] = m0, m1, m2
    cov[0, 0], cov[1, 1], cov[2, 2] = c00 / K, c11 / K, c22 / K
    cov[1, 0] = cov[0, 1] = c10 / K
    cov[2, 0] = cov[0, 2] = c20 / K
    cov[2, 1] = cov[1, 2] = c21 / K
    ok = True
    for a in range(3):
        ok &= np.isfinite(mean[a])
        for c in range(3):
            ok &= np.isfinite(cov[a, c])
    if not ok:
        return False
    det = (cov[0, 0] * (cov[1, 1] * cov[2, 2] - cov[1, 2] * cov[1, 2])
           - cov[0, 1] * (cov[0, 1] * cov[2, 2] - cov[0, 2] * cov[1, 2])
           + cov[0, 2] * (cov[0, 1] * cov[1, 2] - cov[0, 2] * cov[1, 1]))
    return det > 0.0


@batch_kernel
def _moments_batch(geometries: np.ndarray, states: np.ndarray, Z: np.ndarray, Ls: np.ndarray, b: np.ndarray,
                   mean: np.ndarray, cov: np.ndarray, ok: np.ndarray, scratch: tuple) -> None:
    """Birth moments of every geometry ``g``, particle ``p`` and measurement ``j`` from the ``K = 10``
    cubature points of ``N(Z[j], R)`` (:func:`~mmslam.slam.phd.ckf.cubature_point_set`; ``Ls (1, 5, 5)``
    the factor of one ``R`` for all, or ``(J, 5, 5)`` one per measurement): ``Z (J, 5)``,
    ``geometries (G,)`` (:class:`mmslam.model.Bounce` codes), ``states (P, 7)``, ``b (3,)``;
    writes ``mean (G, P, J, 3)``, ``cov (G, P, J, 3, 3)``, ``ok (G, P, J)``.

    The AOA direction of point ``k`` seen with heading ``h_p`` uses ``cos(a + h) = cos a cos h -
    sin a sin h`` (and the same for sin): the trigonometric functions are evaluated once per
    point and once per particle instead of per pair, and each direction once for all geometries.
    ``scratch``: :func:`_moments_scratch` (a runtime-free kernel allocates nothing, :mod:`mmslam.slam.core.jit`).
    """
    J, K, G = Z.shape[0], 2 * Z.shape[1], geometries.shape[0]
    zpts, ca, sa, ce, se, x, valid = scratch
    for j in range(J):
        cubature_point_set(Z[j], Ls[j if Ls.shape[0] > 1 else 0], zpts[j])
        for k in range(K):
            ca[j, k], sa[j, k] = math.cos(zpts[j, k, 3]), math.sin(zpts[j, k, 3])
            ce[j, k], se[j, k] = math.cos(zpts[j, k, 4]), math.sin(zpts[j, k, 4])
    for p in range(states.shape[0]):
        s = states[p]
        ch, sh = math.cos(s[3]), math.sin(s[3])
        for j in range(J):
            valid[:] = True
            for k in range(K):
                d0 = ce[j, k] * (ca[j, k] * ch - sa[j, k] * sh)
                d1 = ce[j, k] * (sa[j, k] * ch + ca[j, k] * sh)
                L = zpts[j, k, 0] - s[6]
                for g in range(G):
                    # constant geometry at each call site: the inlined inversion is specialised (~8x faster)
                    if geometries[g] == _MIRROR:
                        valid[g] = invert_ray(_MIRROR, s, d0, d1, se[j, k], L, b, x[g, k]) and valid[g]
                    else:
                        valid[g] = invert_ray(_SCATTER, s, d0, d1, se[j, k], L, b, x[g, k]) and valid[g]
            for g in range(G):
                ok[g, p, j] = image_moments(x[g], mean[g, p, j], cov[g, p, j]) and valid[g]


def _moments_scratch(J: int, G: int) -> tuple[np.ndarray, ...]:
    """Scratch of :func:`_moments_batch` for ``J`` measurements and ``G`` geometries: the ``K = 10``
    cubature points ``(J, K, 5)``, cos / sin of their AOA azimuth and elevation ``(J, K)`` each, the
    images ``(G, K, 3)`` and their validity ``(G,)``."""
    K = 2 * MEAS_DIM
    return (np.empty((J, K, MEAS_DIM)), np.empty((J, K)), np.empty((J, K)), np.empty((J, K)), np.empty((J, K)),
            np.empty((G, K, 3)), np.empty(G, np.bool_))


def birth_moments_by_kind(states: np.ndarray, Z: np.ndarray, R: np.ndarray, kinds: tuple[int, ...],
                          bs: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`birth_moments` for several path geometries sharing the cubature points (one kernel pass).

    ``kinds``: :class:`mmslam.model.Bounce` codes (MIRROR, SCATTER; types of one geometry share
    the inversion). Returns ``{geometry: (mean (P, J, 3), cov (P, J, 3, 3), ok (P, J))}``.
    """
    J, P_ = Z.shape[0], states.shape[0]
    R = np.asarray(R, dtype=float)
    if (np.shape(Z) != (J, MEAS_DIM) or R.shape not in ((MEAS_DIM, MEAS_DIM), (J, MEAS_DIM, MEAS_DIM))
            or np.shape(states)[1:] != (7,) or np.shape(bs) != (3,)):
        raise ValueError(f"birth moments: Z {np.shape(Z)}, R {R.shape}, states {np.shape(states)}, bs "
                         f"{np.shape(bs)}; expected (J, {MEAS_DIM}), ({MEAS_DIM}, {MEAS_DIM}) or (J, {MEAS_DIM}, "
                         f"{MEAS_DIM}), (P, 7), (3,)")
    # a single R: one Cholesky factor for every measurement
    Ls = np.ascontiguousarray(cubature_factor(R[None] if R.ndim == 2 else R, "birth cubature"))
    s = np.ascontiguousarray(states, dtype=float)
    b = np.ascontiguousarray(bs, dtype=float)
    geos = np.array([int(k) for k in kinds], dtype=np.int64)
    G = geos.shape[0]
    mean, cov, ok = np.empty((G, P_, J, 3)), np.empty((G, P_, J, 3, 3)), np.empty((G, P_, J), bool)
    _moments_batch(geos, s, np.ascontiguousarray(Z, dtype=float), Ls, b, mean, cov, ok, _moments_scratch(J, G))
    return {int(k): (mean[g], cov[g], ok[g]) for g, k in enumerate(geos)}


def birth_moments(states: np.ndarray, Z: np.ndarray, R: np.ndarray, geometry: int,
                  bs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Birth position moments by cubature inversion: ``mean (P, J, 3)``, ``cov (P, J, 3, 3)``, ``ok (P, J)``.

    The 10 cubature points of ``N(z_j, R)`` are inverted for every particle with the type's
    path ``geometry`` (:class:`mmslam.model.Bounce`: MIRROR or SCATTER, :func:`invert_ray`) and summarised by
    :func:`image_moments`. No FOV gating here; ``ok`` is False for an invalid image, a non-finite
    moment or a covariance with a non-positive determinant.
    """
    geo = check_geometry(geometry)
    return birth_moments_by_kind(states, Z, R, (geo,), bs)[geo]


@batch_kernel
def _births(mean: np.ndarray, cov: np.ndarray, ok: np.ndarray, cols: np.ndarray, weight: np.ndarray, moving: bool,
            vel_var: np.ndarray, turn_std: float, turn_mean: float, w: np.ndarray, m: np.ndarray, P: np.ndarray,
            mask: np.ndarray) -> None:
    """Birth Gaussians of every particle ``p`` and kept measurement ``j = cols[c]`` (``cols (C,)``) in slot
    ``c``: where ``ok[p, j]`` weight ``weight[p, j]`` (``(P, J)``) at the position moments ``mean[p, j] (3,)``,
    ``cov[p, j] (3, 3)`` (``moving``: the 7-D VS birth :func:`~mmslam.slam.models.vs.vs_birth_mean_point`,
    :func:`~mmslam.slam.models.vs.vs_birth_cov_point`), else ``w = 0``, ``m = 0``, ``P = I``.
    Writes ``w (P, C)``, ``m (P, C, d)``, ``P (P, C, d, d)``, ``mask (P, C) = ok[:, cols]``."""
    for p in range(ok.shape[0]):
        for c in range(cols.shape[0]):
            j = cols[c]
            mask[p, c] = ok[p, j]
            if not ok[p, j]:
                w[p, c] = 0.0
                dead_gaussian(m[p, c], P[p, c])
                continue
            w[p, c] = weight[p, j]
            if moving:
                vs_birth_mean_point(mean[p, j], turn_mean, m[p, c])
                vs_birth_cov_point(cov[p, j], vel_var, turn_std, P[p, c])
            else:  # the position moments
                for a in range(3):
                    m[p, c, a] = mean[p, j, a]
                    for b in range(3):
                        P[p, c, a, b] = cov[p, j, a, b]


def birth_from_moments(states: np.ndarray, mean: np.ndarray, cov: np.ndarray, ok: np.ndarray,
                       kind: LandmarkKind, birth_weight: float | np.ndarray,
                       pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
                       vs_velocity_var: tuple[float, float, float] = (100.0, 100.0, 0.09),
                       vs_turn_std: float = np.pi / 2, *, drop_dead: bool = False) -> GM:
    """Birth GM of one type from :func:`birth_moments` output (see :func:`birth_gm`).

    ``states (P, 7)``, ``mean (P, J, 3)``, ``cov (P, J, 3, 3)``, ``ok (P, J)``; ``birth_weight``: one weight for
    every birth, or ``(P, J)`` the weight of the birth of ``z_j`` in particle ``p`` (an adaptive birth). The type
    (``kind``, :class:`~mmslam.slam.models.measurement.LandmarkKind`, e.g. its spec) decides: a range-gated type's
    births need ``p_D > 0`` at their mean (``pd_fn (P, J)``, or an array that broadcasts to it); a 7-D (moving, VS)
    type gets the velocity / turn-rate prior (:func:`~mmslam.slam.models.vs.vs_birth_mean`,
    :func:`~mmslam.slam.models.vs.vs_birth_covariance`). Slot ``j`` holds the births of ``z_j``; with ``drop_dead``
    the measurements without a birth in any particle have no slot (the others keep their order).
    Raises ValueError if the shapes do not fit (the compiled loop reads them unchecked).
    """
    spec = kind
    shape = np.shape(ok)
    if (len(shape) != 2 or np.shape(mean) != shape + (3,) or np.shape(cov) != shape + (3, 3)
            or np.shape(states)[:1] != shape[:1]):
        raise ValueError(f"birth_from_moments: states {np.shape(states)}, mean {np.shape(mean)}, cov {np.shape(cov)} "
                         f"and ok {shape} do not fit; expected (P, 7), (P, J, 3), (P, J, 3, 3), (P, J)")
    ok = np.ascontiguousarray(ok, dtype=bool)
    if spec.range_gated:  # e.g. not a VA: its image lies behind the wall
        pd = pd_fn(np.broadcast_to(states[:, None, 0:3], mean.shape), mean, spec.code)
        if np.shape(pd) != shape:
            try:
                pd = np.broadcast_to(pd, shape)
            except ValueError:
                raise ValueError(f"pd_fn returned shape {np.shape(pd)} for {shape} births; return one p_D "
                                 f"per birth") from None
        ok = ok & (pd > 0.0)
    cols = np.arange(shape[1])
    if drop_dead and shape[1]:
        cols = cols[:live_slots(ok.reshape(-1, shape[1]), cols)]
    moving = spec.state_dim == VS_DIM
    vel_var = np.asarray(vs_velocity_var, dtype=float)
    if moving and vel_var.shape != (3,):
        raise ValueError(f"vel_var must have shape (3,), got {vel_var.shape}")
    d = VS_DIM if moving else 3
    out = (shape[0], cols.shape[0])
    w, m, P, mask = np.empty(out), np.empty(out + (d,)), np.empty(out + (d, d)), np.empty(out, bool)
    try:
        weight = np.array(np.broadcast_to(np.asarray(birth_weight, dtype=float), shape), order="C")  # writable
    except ValueError:
        raise ValueError(f"birth_weight has shape {np.shape(birth_weight)}; expected one weight or {shape}") from None
    _births(np.ascontiguousarray(mean, dtype=float), np.ascontiguousarray(cov, dtype=float), ok, cols,
            weight, moving, vel_var, float(vs_turn_std), DEFAULT_TURN_MEAN, w, m, P, mask)
    return GM(w, m, P, mask)


def birth_gm(states: np.ndarray, Z: np.ndarray, R: np.ndarray, kind: LandmarkKind, bs: np.ndarray,
             birth_weight: float,
             pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
             vs_velocity_var: tuple[float, float, float] = (100.0, 100.0, 0.09),
             vs_turn_std: float = np.pi / 2) -> GM:
    """Birth PHD of one landmark type from a measurement set, batched over particles.

    Args:
        states: ``(P, 7)`` particle vehicle states at the measurement time.
        Z: ``(J, 5)`` measurements (body-frame AOA).
        R: ``(5, 5)`` filter measurement covariance (cubature spread of each ``z``).
        kind: the type (:class:`~mmslam.slam.models.measurement.LandmarkKind`, e.g. the spec of
            ``VA``, ``SP`` or ``VS``): its geometry, dimension and FOV gate.
        bs: ``(3,)`` BS position.
        birth_weight: weight of every birth Gaussian.
        pd_fn: ``pd_fn(vehicle_pos (P, J, 3), lm_pos (P, J, 3), lm_type) -> (P, J)``; SP and VS
            births whose mean has ``p_D = 0`` (outside the FOV) are dropped.
        vs_velocity_var, vs_turn_std: VS birth velocity variances ``(m/s)^2`` and turn-rate std
            (rad/s), passed to :func:`mmslam.slam.models.vs.vs_birth_covariance`.

    Returns:
        GM with batch ``(P,)``, ``J`` slots (slot ``j`` from ``z_j``), dim 3 (VA, SP) or 7 (VS).
    """
    P_, J = states.shape[0], Z.shape[0]
    if J == 0:
        d = kind.state_dim
        return GM(np.zeros((P_, 0)), np.zeros((P_, 0, d)), np.zeros((P_, 0, d, d)), np.zeros((P_, 0), bool))
    mean, cov, ok = birth_moments(states, Z, R, kind.geometry, bs)
    return birth_from_moments(states, mean, cov, ok, kind, birth_weight, pd_fn, vs_velocity_var, vs_turn_std)
