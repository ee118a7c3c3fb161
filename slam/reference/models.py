"""Textbook measurement model and measurement inversion of one point (paper eq. (3); TWC 2020 births).

Plain NumPy, one landmark point and one vehicle state at a time: the references of
:func:`mmslam.slam.models.measurement.measure_point` / :func:`~mmslam.slam.models.measurement.measure`
and :func:`mmslam.slam.phd.birth.invert_point` / :func:`~mmslam.slam.phd.birth.birth_moments`.
Global frame, metres, radians; a state is ``[x, y, z, heading, speed, turn rate, clock bias]``.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from mmslam.model import Bounce

AZIMUTHS = (1, 3)
"""Azimuth components of a measurement ``[TOA, AOD az, AOD el, AOA az, AOA el]`` (wrapped)."""


def wrap(a: np.ndarray | float) -> np.ndarray:
    """Textbook angle wrap to ``(-pi, pi]`` (rad)."""
    return np.angle(np.exp(1j * np.asarray(a, float)))


def measure(state: np.ndarray, x: np.ndarray, geometry: int, bs: np.ndarray) -> np.ndarray:
    """Measurement ``(5,)`` of one landmark point ``x (3,)`` from one vehicle ``state (7,)`` (eq. 3):
    vectors, norms, angles. DIRECT: the BS (``x`` unused); MIRROR: ``x`` is the image source (the wall
    is the perpendicular bisector of ``bs`` and ``x``); SCATTER: a point BS -> ``x`` -> vehicle."""
    u, b = state[:3], np.asarray(bs, float)

    def angles(v: np.ndarray) -> tuple[float, float]:
        return np.arctan2(v[1], v[0]), np.arcsin(v[2] / np.linalg.norm(v))

    if geometry == Bounce.DIRECT:
        dep, arr, toa = u - b, b - u, np.linalg.norm(u - b)
    elif geometry == Bounce.MIRROR:
        nrm = (x - b) / np.linalg.norm(x - b)
        dep = (u - x) - 2.0 * ((u - x) @ nrm) * nrm
        arr, toa = x - u, np.linalg.norm(u - x)
    else:
        dep, arr, toa = x - b, x - u, np.linalg.norm(x - b) + np.linalg.norm(x - u)
    (a1, e1), (a2, e2) = angles(dep), angles(arr)
    return np.array([toa + state[6], a1, e1, wrap(a2 - state[3]), e2])


def measurement_function(state: np.ndarray, geometry: int, bs: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """``h(x)``: the measurement of one vehicle state as a function of a landmark state (position first)."""
    return lambda x: measure(state, x[:3], geometry, bs)


def body_bounce(x: np.ndarray, heading: float, b: np.ndarray, u: np.ndarray, body: np.ndarray) -> np.ndarray:
    """Specular point of the ellipsoidal car body (reference of :func:`mmslam.slam.models.vs.body_specular_point`):
    ``c = x - (0, 0, depth)``, ``M = R diag(a^2, w^2, h^2) R^T`` (``(a, w, h) = body[:3] / 2``, ``R`` the rotation by
    ``heading`` about z), ``n = (b - c)/|b - c| + (u - c)/|u - c|``, ``p = c + M n / sqrt(n^T M n)``; a point VS
    (``body[0] <= 0``): ``x``."""
    x = np.asarray(x, float)
    if body[0] <= 0:
        return x.copy()
    c = x - np.array([0.0, 0.0, body[3]])
    ch, sh = np.cos(heading), np.sin(heading)
    Rz = np.array([[ch, -sh, 0.0], [sh, ch, 0.0], [0.0, 0.0, 1.0]])
    M = Rz @ np.diag((np.asarray(body[:3], float) / 2) ** 2) @ Rz.T
    n = (b - c) / np.linalg.norm(b - c) + (u - c) / np.linalg.norm(u - c)
    return c + M @ n / np.sqrt(n @ M @ n)


def invert(state: np.ndarray, z: np.ndarray, geometry: int, bs: np.ndarray) -> tuple[np.ndarray, bool]:
    """Textbook inversion of one measurement: the AOA ray from the antenna, at range ``TOA - B``
    (MIRROR: the image source) or where it meets the ellipsoid with foci BS and antenna (SCATTER);
    returns ``(x (3,), valid)``."""
    u, L = state[:3], z[0] - state[6]
    az, el = z[3] + state[3], z[4]
    d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    if geometry == Bounce.MIRROR:
        return u + L * d, L > 0
    bu = np.asarray(bs, float) - u
    if not (L > np.linalg.norm(bu) and L - d @ bu > 0):
        return u, False
    r = (L * L - bu @ bu) / (2.0 * (L - d @ bu))
    return u + r * d, r > 0


def birth_moments(states: np.ndarray, Z: np.ndarray, R: np.ndarray, geometry: int, bs: np.ndarray
                  ) -> tuple[np.ndarray, ...]:
    """The 10 cubature points of ``N(z_j, R)`` one by one, inverted with :func:`invert`, equal-weight
    mean and ``np.cov(bias=True)``; ok = every image valid, finite and ``det(cov) > 0``.

    Returns ``mean (P, J, 3)``, ``cov (P, J, 3, 3)``, ``ok (P, J)`` and every image ``(10, J, P, 3)``
    with its validity ``(10, J, P)``.
    """
    Lr = np.linalg.cholesky(R)
    P_, J = states.shape[0], Z.shape[0]
    mean, cov, ok = np.zeros((P_, J, 3)), np.zeros((P_, J, 3, 3)), np.zeros((P_, J), bool)
    pos_all, valid_all = np.zeros((10, J, P_, 3)), np.zeros((10, J, P_), bool)
    for j in range(J):
        pts = [Z[j] + np.sqrt(5) * Lr[:, i] for i in range(5)] + [Z[j] - np.sqrt(5) * Lr[:, i] for i in range(5)]
        for p in range(P_):
            imgs, valid = zip(*(invert(states[p], z, geometry, bs) for z in pts))
            imgs, valid = np.array(imgs), np.array(valid)
            pos_all[:, j, p], valid_all[:, j, p] = imgs, valid
            mean[p, j] = imgs.mean(0)
            cov[p, j] = np.cov(imgs.T, bias=True)
            ok[p, j] = valid.all() and np.isfinite(mean[p, j]).all() and np.linalg.det(cov[p, j]) > 0
    return mean, cov, ok, pos_all, valid_all
