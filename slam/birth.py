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

from typing import Callable

import numpy as np

from .gm import GM, symmetrize
from .ckf import cubature_points
from .measurement import SP, VA, VS
from .vs import vs_birth_covariance, vs_birth_mean


def aoa_direction(state: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Global unit AOA direction ``(..., 3)`` from body-frame AOA in ``z (..., 5)`` and heading."""
    az = z[..., 3] + state[..., 3]
    az, el = np.broadcast_arrays(az, z[..., 4])
    ce = np.cos(el)
    return np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=-1)


def invert_va(state: np.ndarray, z: np.ndarray, bs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """VA image-source position from a measurement: ``(position (..., 3), valid (...))``.

    ``state (..., 7)`` vehicle states and ``z (..., 5)`` measurements broadcast together.
    ``bs`` is unused (kept for a uniform signature).
    """
    r = z[..., 0] - state[..., 6]
    pos = state[..., 0:3] + r[..., None] * aoa_direction(state, z)
    return pos, r > 0.0


def invert_sp(state: np.ndarray, z: np.ndarray, bs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Single-scatter point from a measurement: ``(position (..., 3), valid (...))``.

    The point on the AOA ray from ``u`` whose bistatic range ``|b - s| + |s - u|`` equals
    ``TOA - B`` (closed form, see module docstring).
    """
    u = state[..., 0:3]
    d = aoa_direction(state, z)
    L = z[..., 0] - state[..., 6]
    bu = np.asarray(bs, float) - u
    nbu2 = np.einsum("...i,...i->...", bu, bu)
    den = 2.0 * (L - np.einsum("...i,...i->...", d, bu))
    valid = (L * L > nbu2) & (L > 0.0) & (den > 0.0)
    r = np.where(valid, (L * L - nbu2) / np.where(den > 0.0, den, 1.0), 0.0)
    valid &= r > 0.0
    return u + r[..., None] * d, valid


def _image_moments(pts: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equal-weight mean ``(..., 3)`` and covariance ``(..., 3, 3)`` of images ``(..., K, 3)``."""
    mean = pts.mean(axis=-2)
    dev = pts - mean[..., None, :]
    cov = symmetrize(np.einsum("...ka,...kb->...ab", dev, dev) / pts.shape[-2])
    ok = valid.all(axis=-1) & np.isfinite(mean).all(-1) & np.isfinite(cov).all((-1, -2))
    # guard against a degenerate (rank-deficient) spread: the minimum eigenvalue must be > 0
    ok &= np.linalg.det(np.where(ok[..., None, None], cov, np.eye(3))) > 0.0
    return mean, cov, ok


def _aoa_rays(states: np.ndarray, zpts: np.ndarray) -> tuple[np.ndarray, ...]:
    """Global AOA unit directions and ``L = TOA - B`` for every cubature point x particle.

    ``states (P, 7)``, ``zpts (J, K, 5)`` -> ``dx, dy, dz, L`` each ``(K, J, P)`` (the
    components of :func:`aoa_direction`, not stacked; cubature point first so that the
    moments over the ``K`` points are sums of contiguous ``(J, P)`` slabs, particles last so
    that every elementwise loop runs over ``P``).
    """
    zk = zpts.transpose(1, 0, 2)[..., None]  # (K, J, 5, 1)
    az = zk[:, :, 3] + states[:, 3]
    el = zk[:, :, 4]  # (K, J, 1): the elevation does not depend on the particle
    ce = np.cos(el)
    dx, dy, dz = ce * np.cos(az), ce * np.sin(az), np.sin(el)
    L = zk[:, :, 0] - states[:, 6]
    return dx, dy, dz, L


def _invert_batch_last(states: np.ndarray, rays: tuple[np.ndarray, ...], lm_type: int,
                       bs: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """:func:`invert_va` / :func:`invert_sp` of every cubature point x particle, component-wise.

    ``states (P, 7)``, ``rays`` from :func:`_aoa_rays` -> positions ``(x, y, z)`` each
    ``(K, J, P)`` (m) and ``valid (K, J, P)``; the same formulas as the public functions,
    without stacking the 3-vectors (the birth's hot path).
    """
    dx, dy, dz, L = rays
    ux, uy, uz = (states[:, i] for i in range(3))
    if lm_type == VA:
        return (ux + L * dx, uy + L * dy, uz + L * dz), L > 0.0
    b = np.asarray(bs, float)
    bx, by, bz = b[0] - ux, b[1] - uy, b[2] - uz
    nbu2 = bx * bx + by * by + bz * bz
    den = 2.0 * (L - (dx * bx + dy * by + dz * bz))
    valid = (L * L > nbu2) & (L > 0.0) & (den > 0.0)
    r = np.where(valid, (L * L - nbu2) / np.where(den > 0.0, den, 1.0), 0.0)
    valid &= r > 0.0
    return (ux + r * dx, uy + r * dy, uz + r * dz), valid


def _sum_first(a: np.ndarray) -> np.ndarray:
    """``a.sum(axis=0)`` for ``a (K, ...)`` as whole-slab additions, in NumPy's order for a
    contiguous reduction of ``K`` values (sequential below 8; from 8 to 128 eight partial sums
    combined pairwise, then the remainder in sequence), so the result equals
    ``np.moveaxis(a, 0, -1).sum(-1)`` bit for bit for ``K <= 128`` (NumPy's pairwise summation;
    beyond, ``a.sum(axis=0)``, equal up to rounding). Here ``K = 10`` cubature points."""
    k = a.shape[0]
    if k < 8 or k > 128:
        return a.sum(axis=0) if k > 128 else _seq_sum(a)
    r = [a[j].copy() for j in range(8)]
    i = 8
    while i + 8 <= k:
        for j in range(8):
            r[j] += a[i + j]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    for j in range(i, k):
        res += a[j]
    return res


def _seq_sum(a: np.ndarray) -> np.ndarray:
    res = a[0].copy() if a.shape[0] else np.zeros(a.shape[1:])
    for j in range(1, a.shape[0]):
        res += a[j]
    return res


def _moments_batch_last(xyz: tuple[np.ndarray, np.ndarray, np.ndarray],
                        valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equal-weight moments of images given component-wise (``3 x (K, J, P)``, ``valid (K, J, P)``);
    see :func:`birth_moments`. Returns ``mean (P, J, 3)``, ``cov (P, J, 3, 3)``, ``ok (P, J)``."""
    K = valid.shape[0]
    mean_t = [_sum_first(c) / K for c in xyz]  # 3 x (J, P)
    dev = [c - mt for c, mt in zip(xyz, mean_t)]
    mean = np.stack(mean_t, axis=-1).transpose(1, 0, 2)  # (P, J, 3)
    cov = np.empty(mean.shape + (3,))
    for i in range(3):
        for j in range(i + 1):
            cov[..., i, j] = cov[..., j, i] = (_sum_first(dev[i] * dev[j]) / K).T
    ok = valid.all(axis=0).T & np.isfinite(mean).all(-1) & np.isfinite(cov).all((-1, -2))
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 0, 2]
    e, f, i_ = cov[..., 1, 1], cov[..., 1, 2], cov[..., 2, 2]
    with np.errstate(invalid="ignore", over="ignore"):
        det = a * (e * i_ - f * f) - b * (b * i_ - c * f) + c * (b * f - c * e)
    # guard against a degenerate (rank-deficient) spread: the determinant must be > 0
    ok &= np.where(ok, det, 0.0) > 0.0
    return mean, cov, ok


def birth_moments_by_kind(states: np.ndarray, Z: np.ndarray, R: np.ndarray, kinds: tuple[int, ...],
                          bs: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`birth_moments` for several inversion kinds (VA, SP) sharing the cubature points
    and AOA rays: ``{kind: (mean (P, J, 3), cov (P, J, 3, 3), ok (P, J))}``."""
    J = Z.shape[0]
    zpts = cubature_points(Z, np.broadcast_to(R, (J, 5, 5)), "birth cubature")  # (J, 10, 5)
    rays = _aoa_rays(states, zpts)
    return {k: _moments_batch_last(*_invert_batch_last(states, rays, VA if k == VA else SP, bs))
            for k in kinds}


def birth_moments(states: np.ndarray, Z: np.ndarray, R: np.ndarray, lm_type: int,
                  bs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Birth position moments by cubature inversion: ``mean (P, J, 3)``, ``cov (P, J, 3, 3)``, ``ok (P, J)``.

    ``lm_type`` VA uses :func:`invert_va`, SP and VS :func:`invert_sp` (the same images: compute
    once and pass to :func:`birth_from_moments` for both). No FOV gating here. The equal-weight
    moments of the 10 images are computed component-wise (closed-form 3x3 determinant for the
    degeneracy check); ``ok`` is False for an invalid image, a non-finite moment or a
    covariance with a non-positive determinant.
    """
    return birth_moments_by_kind(states, Z, R, (lm_type,), bs)[lm_type]


def birth_from_moments(states: np.ndarray, mean: np.ndarray, cov: np.ndarray, ok: np.ndarray,
                       lm_type: int, birth_weight: float,
                       pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
                       vs_velocity_var: tuple[float, float, float] = (100.0, 100.0, 0.09),
                       vs_turn_std: float = np.pi / 2) -> GM:
    """Birth GM of one type from :func:`birth_moments` output (see :func:`birth_gm`)."""
    if lm_type in (SP, VS):
        pd = pd_fn(np.broadcast_to(states[:, None, 0:3], mean.shape), mean, lm_type)
        ok = ok & (pd > 0.0)
    mean = np.where(ok[..., None], mean, 0.0)
    cov = np.where(ok[..., None, None], cov, np.eye(3))
    if lm_type == VS:
        m7 = np.asarray(vs_birth_mean(mean), float)
        c7 = np.asarray(vs_birth_covariance(cov, vs_velocity_var, vs_turn_std), float)
        mean = np.where(ok[..., None], m7, 0.0)
        cov = np.where(ok[..., None, None], c7, np.eye(7))
    w = np.where(ok, birth_weight, 0.0)
    return GM(w, mean, cov, ok)


def birth_gm(states: np.ndarray, Z: np.ndarray, R: np.ndarray, lm_type: int, bs: np.ndarray,
             birth_weight: float,
             pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
             vs_velocity_var: tuple[float, float, float] = (100.0, 100.0, 0.09),
             vs_turn_std: float = np.pi / 2) -> GM:
    """Birth PHD of one landmark type from a measurement set, batched over particles.

    Args:
        states: ``(P, 7)`` particle vehicle states at the measurement time.
        Z: ``(J, 5)`` measurements (body-frame AOA).
        R: ``(5, 5)`` filter measurement covariance (cubature spread of each ``z``).
        lm_type: ``VA``, ``SP`` or ``VS``.
        bs: ``(3,)`` BS position.
        birth_weight: weight of every birth Gaussian.
        pd_fn: ``pd_fn(vehicle_pos (P, J, 3), lm_pos (P, J, 3), lm_type) -> (P, J)``; SP and VS
            births whose mean has ``p_D = 0`` (outside the FOV) are dropped.
        vs_velocity_var, vs_turn_std: VS birth velocity variances ``(m/s)^2`` and turn-rate std
            (rad/s), passed to :func:`mmslam.slam.vs.vs_birth_covariance`.

    Returns:
        GM with batch ``(P,)``, ``J`` slots (slot ``j`` from ``z_j``), dim 3 (VA, SP) or 7 (VS).
    """
    P_, J = states.shape[0], Z.shape[0]
    if J == 0:
        d = 7 if lm_type == VS else 3
        return GM(np.zeros((P_, 0)), np.zeros((P_, 0, d)), np.zeros((P_, 0, d, d)), np.zeros((P_, 0), bool))
    mean, cov, ok = birth_moments(states, Z, R, lm_type, bs)
    return birth_from_moments(states, mean, cov, ok, lm_type, birth_weight, pd_fn, vs_velocity_var, vs_turn_std)
