"""Births that are new landmarks by their own measurement (``filter.types.<T>.birth_existence``, docs/city-slam.md).

A measurement-driven birth (:mod:`mmslam.slam.phd.birth`) places a landmark on the AOA ray at the TOA's path
length; the measurement's AOD is left over: two more numbers that a path of the type's geometry must match. A
measurement that matches them, that no car body could have made and that no Gaussian of the particle's map (nor
another birth of the scan) would absorb is a new landmark with high probability from its first detection on: uniform
clutter almost never matches the AOD (and its TOA mostly lies below the clock bias, no birth at all). Such a birth
takes the type's ``birth_existence`` as its weight instead of ``filter.birth_weight``
(:func:`mmslam.slam.specs.landmarks.birth_point`), times ``c(z) / psi(z)`` with ``filter.adaptive_birth``.

Three stages, each ``(P, J)`` over particles ``p`` and measurements ``z_j`` (:func:`new_landmark_births`):

1. the AOD fit (:func:`aod_fit`): ``q = e^T S^-1 e`` of the AOD residual ``e`` of ``z_j`` against the AOD the birth
   Gaussian predicts, ``S`` its cubature covariance through ``h`` plus the AOD block of ``R``; within
   :data:`FIT_GATE` (the 99.9 % point of chi-square with 2 degrees of freedom);
2. off the car band (:func:`bounce_height`): the path bounces (the single-scatter point of ``z_j``) more than
   ``band`` (``filter.vs_birth_height``) above or below the antenna; within it the path may come off a car body, a
   VS the filter cannot tell from a wall at its first detection, unless no car is near the point
   (:func:`off_every_car`, ``filter.band_cars``: the cars the caller knows of);
3. resolved (:func:`within_merge_gate`, :func:`los_fit`): no Gaussian of the particle's map and no other birth of the
   scan lies within the type's merge gate of the birth (the squared Mahalanobis distance under the birth's covariance,
   the candidate's covariance as in the reduction's test: the reduction would merge it into one of them), and the
   BS's line of sight, a known landmark, does not explain the measurement within :data:`LOS_GATE` (the line of sight
   births a VA at the BS, whose AOD fits any; with ``filter.adaptive_birth`` its ``c / psi`` is ~0 anyway).
"""
from __future__ import annotations

import numpy as np

from mmslam.model import Bounce

from ..core.gm import GM
from ..models.measurement import measure, residual
from .birth import invert_sp

FIT_GATE = 13.8155
"""The 99.9 % point of chi-square with 2 degrees of freedom (``-2 ln 0.001``): the AOD fit's gate."""
LOS_GATE = 20.515
"""The 99.9 % point of chi-square with 5 degrees of freedom: a measurement the line of sight explains."""


def aod_fit(states: np.ndarray, Z: np.ndarray, R: np.ndarray, mean: np.ndarray, cov: np.ndarray,
            geometry: int, bs: np.ndarray) -> np.ndarray:
    """``q (P, J)``: the squared Mahalanobis distance of each measurement's AOD from the AOD its birth predicts.

    The birth Gaussian ``N(mean[p, j], cov[p, j])`` (position, m, global frame) goes through ``h`` (paper eq. (3),
    :func:`~mmslam.slam.models.measurement.measure` with ``geometry``) at its 6 cubature points
    ``mean +- sqrt(3) L e_k`` (``L L^T = cov``) seen from ``states[p]``: their mean AOD (azimuth as a wrapped deviation
    from the mean's) ``a`` and covariance ``A``; ``S = A + R_aod`` (``R[1:3, 1:3]``, rad^2; ``R (5, 5)`` or one per
    measurement ``(J, 5, 5)``), ``e = z_j[1:3] - a`` (azimuth wrapped), ``q = e^T S^-1 e``.

    Args: ``states (P, 7)``, ``Z (J, 5)``, ``mean (P, J, 3)``, ``cov (P, J, 3, 3)`` (SPD where used; a birth that
    failed, ``ok`` False in its moments, may hold anything: its ``q`` is then meaningless and the caller masks it),
    ``bs (3,)``.
    """
    eye = np.eye(3)
    good = np.isfinite(cov).all((-1, -2)) & np.isfinite(mean).all(-1)
    cov = np.where(good[..., None, None], cov, eye)
    mean = np.where(good[..., None], mean, 0.0)
    L = np.linalg.cholesky(cov + 1e-12 * eye)  # (P, J, 3, 3); the jitter keeps a degenerate spread factorable
    cols = np.sqrt(3.0) * np.swapaxes(L, -1, -2)  # row k: sqrt(3) L e_k
    pts = np.concatenate([mean[..., None, :] + cols, mean[..., None, :] - cols], axis=-2)  # (P, J, 6, 3)
    h0 = measure(states[:, None, :], mean, int(geometry), bs)  # (P, J, 5)
    hk = measure(states[:, None, None, :], pts, int(geometry), bs)  # (P, J, 6, 5)
    dk = residual(hk, h0[..., None, :])[..., 1:3]  # deviations from the mean's AOD, azimuth wrapped
    dm = dk.mean(-2)
    dev = dk - dm[..., None, :]
    R = np.asarray(R, float)
    R_aod = (R[1:3, 1:3] if R.ndim == 2 else R[None, :, 1:3, 1:3])
    S = np.einsum("pjka,pjkb->pjab", dev, dev) / 6.0 + R_aod
    zhat = h0.copy()
    zhat[..., 1:3] += dm
    e = residual(np.broadcast_to(Z, h0.shape), zhat)[..., 1:3]
    return np.einsum("pja,pjab,pjb->pj", e, np.linalg.inv(S), e)


def bounce_height(states: np.ndarray, Z: np.ndarray, bs: np.ndarray) -> np.ndarray:
    """``(P, J)`` m: the height above the antenna of the single-scatter point of each measurement (where the AOA ray
    meets the ellipsoid of its TOA path length about the BS and the antenna,
    :func:`~mmslam.slam.phd.birth.invert_point` with SCATTER: the bounce point of a single-bounce path, a specular
    one included); NaN where the measurement has none (path length not above the BS distance)."""
    x, valid = invert_sp(states[:, None, :], Z[None, :, :], bs)
    return np.where(valid, x[..., 2] - states[:, None, 2], np.nan)


def off_every_car(scatter: tuple[np.ndarray, np.ndarray, np.ndarray], cars: GM, reach: float) -> np.ndarray:
    """``(P, J)`` bool: whether the single-scatter point of each measurement lies horizontally farther than
    ``reach + 3 sqrt(sigma_q^2 + sigma_j^2)`` (m) from the mean of every live Gaussian ``q`` of particle ``p``'s car
    map ``cars`` (batch ``(P,)``: the cars the caller knows of, e.g. the particle's VS map and the fleet as the
    downlinks told it), i.e. that no car the particle knows of could have made it.

    ``scatter = (mean (P, J, 3), cov (P, J, 3, 3), ok (P, J))``: the point's moments by the cubature inversion of
    ``N(z_j, R)`` with SCATTER (:func:`~mmslam.slam.phd.birth.birth_moments_by_kind`; the bounce point of a
    single-bounce path, a specular one included, m, global frame). ``sigma_q``, ``sigma_j``: the square root of the
    larger of the x and y variances of the car Gaussian and of the point (the measurement's angle noise spreads the
    point across the ray by its range times the angle std: about 1 m at 100 m with 0.01 rad). ``reach``: how far a
    body's surface lies from its centre (half a car's length). False where the measurement has no such point
    (``ok`` False: the test does not act, and the band's own test, :func:`bounce_height`, decides)."""
    mean, cov, valid = (np.asarray(a) for a in scatter)
    if not cars.capacity:
        return valid.copy()
    d = np.linalg.norm(mean[:, :, None, 0:2] - cars.m[:, None, :, 0:2], axis=-1)  # (P, J, Q)
    var_q = np.maximum(cars.P[..., 0, 0], cars.P[..., 1, 1])[:, None, :]  # (P, 1, Q)
    with np.errstate(invalid="ignore"):
        var_j = np.where(valid, np.maximum(cov[..., 0, 0], cov[..., 1, 1]), 0.0)[:, :, None]  # (P, J, 1)
        near = cars.mask[:, None, :] & (d <= reach + 3.0 * np.sqrt(var_q + var_j))
    return valid & ~near.any(-1)


def los_fit(states: np.ndarray, Z: np.ndarray, R: np.ndarray, bs: np.ndarray) -> np.ndarray:
    """``(P, J)``: ``r^T R^-1 r`` of each measurement's residual ``r`` against the line of sight ``h(s_p, b)``
    (:func:`~mmslam.slam.models.measurement.measure`, DIRECT; azimuths wrapped; ``R (5, 5)`` or ``(J, 5, 5)``)."""
    zhat = measure(states[:, None, :], np.asarray(bs, float), int(Bounce.DIRECT), bs)  # (P, 1, 5)
    r = residual(Z[None, :, :], zhat)
    Rinv = np.linalg.inv(np.asarray(R, float))
    return np.einsum("pja,...jab,pjb->pj", r, Rinv if Rinv.ndim == 3 else Rinv[None], r)


def within_merge_gate(mean: np.ndarray, cov: np.ndarray, m: np.ndarray, live: np.ndarray, gate: float) -> np.ndarray:
    """``(P, J)``: whether some point ``m[p, q]`` (``(P, Q, 3)``, ``live (P, Q)``) lies within ``gate`` of birth
    ``N(mean[p, j], cov[p, j])``: ``(m - mean)^T cov^-1 (m - mean) <= gate`` (the reduction's merge test,
    :func:`~mmslam.slam.phd.reduction.prune_merge`, with the birth as the candidate)."""
    if m.shape[1] == 0:
        return np.zeros(mean.shape[:2], bool)
    good = np.isfinite(cov).all((-1, -2))
    inv = np.linalg.inv(np.where(good[..., None, None], cov, np.eye(3)))
    D = m[:, None, :, :] - mean[:, :, None, :]  # (P, J, Q, 3)
    d2 = np.einsum("pjqa,pjab,pjqb->pjq", D, inv, D)
    return (live[:, None, :] & (d2 <= gate)).any(-1)


def new_landmark_births(states: np.ndarray, Z: np.ndarray, R: np.ndarray,
                        moments: tuple[np.ndarray, np.ndarray, np.ndarray], geometry: int, bs: np.ndarray,
                        band: float, gate: float, g: GM | None, cars: GM | None = None,
                        reach: float = 0.0,
                        scatter: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``(P, J)`` bool: the births of ``Z (J, 5)`` (``moments = (mean (P, J, 3), cov (P, J, 3, 3), ok (P, J))`` of
    :func:`~mmslam.slam.phd.birth.birth_moments_by_kind` for ``geometry``) that are new landmarks by their own
    measurement: the module's three stages (AOD fit within :data:`FIT_GATE`, bounce more than ``band`` m off the
    antenna height, no Gaussian of the particle's map ``g`` (batch ``(P,)``; None: none) nor another birth of the
    scan within the merge ``gate``, the line of sight from ``bs (3,)`` not explaining it). With ``cars`` (batch
    ``(P,)``: the cars each particle knows of) a bounce in the band passes stage 2 too where no car of it is near
    (:func:`off_every_car` with ``reach``, m, and ``scatter``, the measurements' SCATTER moments, needed then;
    ``filter.band_cars``)."""
    mean, cov, ok = (np.asarray(a) for a in moments)
    states, Z = np.asarray(states, float), np.asarray(Z, float)
    out = ok.copy()
    if not out.any():
        return out
    # a failed birth (its path length not above the BS distance: every image at the antenna) may hold a singular or
    # non-finite spread; it is never new, and never another birth's neighbour (masked below): a unit stand-in
    mean = np.where(ok[..., None], mean, 0.0)
    cov = np.where(ok[..., None, None], cov, np.eye(3))
    out &= aod_fit(states, Z, R, mean, cov, geometry, bs) <= FIT_GATE  # 1.
    with np.errstate(invalid="ignore"):
        off_band = np.abs(bounce_height(states, Z, bs)) > band  # 2. (NaN: False)
    if cars is not None:  # in the band, but no car the particle knows of is there: a wall's
        if scatter is None:
            raise ValueError("new_landmark_births: cars given without the measurements' SCATTER moments")
        off_band |= off_every_car(scatter, cars, reach)
    out &= off_band
    # 3. the other births of the scan (birth j against every live j' != j, under j's covariance), the line of sight
    # and the particle's map
    others = ok[:, None, :] & ~np.eye(Z.shape[0], dtype=bool)  # (P, J, J')
    D = mean[:, None, :, :] - mean[:, :, None, :]  # (P, J, J', 3): j' relative to j
    d2 = np.einsum("pjqa,pjab,pjqb->pjq", D, np.linalg.inv(cov), D)
    out &= ~(others & (d2 <= gate)).any(-1)
    out &= los_fit(states, Z, R, bs) > LOS_GATE
    if g is not None and g.capacity:
        out &= ~within_merge_gate(mean, cov, g.m[..., 0:3], g.mask, gate)
    return out
