"""Textbook cubature Kalman update of one Gaussian (TWC 2020; the CKF step of paper eqs. (5), (10)).

The reference of :func:`mmslam.slam.phd.ckf.ckf_update` / :func:`~mmslam.slam.phd.ckf.kalman_update`:
the third-degree spherical-radial rule on the position marginal, point by point, then the Kalman
gain by a linear solve. Plain NumPy; ``m (d,)``, ``P (d, d)`` with the position first.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from .models import AZIMUTHS, wrap


def cubature_moments(m: np.ndarray, P: np.ndarray, h: Callable[[np.ndarray], np.ndarray],
                     E: np.ndarray | None = None, azimuths: Sequence[int] = AZIMUTHS
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Third-degree cubature rule on the position of ``N(m, P)``, point by point.

    ``h`` maps one position ``(3,)`` to ``(5,)``; ``E``: scatter-point covariance (the points are
    drawn from ``N(m_pos, P_pos + E)``). Azimuth components are averaged as deviations from the
    first point's value (wrapped), the textbook way for angles with a small spread. Returns
    ``zhat, Pzz, Pxz`` with ``Pxz = P[:, :3] (P_pos + E)^-1 Cov(x + e, z)``.
    """
    Pp = P[:3, :3] + (0.0 if E is None else E)
    Lc = np.linalg.cholesky(Pp)
    xs = [m[:3] + np.sqrt(3) * Lc[:, i] for i in range(3)] + [m[:3] - np.sqrt(3) * Lc[:, i] for i in range(3)]
    zs = np.array([h(x) for x in xs])
    dev = zs - zs[0]
    for c in azimuths:
        dev[:, c] = wrap(dev[:, c])
    zhat = zs[0] + dev.mean(0)
    for c in azimuths:
        zhat[c] = wrap(zhat[c])
    D = dev - dev.mean(0)  # z_i - zhat, unwrapped
    n = len(xs)
    Pzz = sum(np.outer(Di, Di) for Di in D) / n
    Pxz_o = sum(np.outer(x - m[:3], Di) for x, Di in zip(xs, D)) / n
    Pxz = P[:, :3] @ np.linalg.solve(Pp, Pxz_o)
    return zhat, Pzz, Pxz


def kalman_update(m: np.ndarray, P: np.ndarray, h: Callable[[np.ndarray], np.ndarray], Z: np.ndarray,
                  R: np.ndarray, E: np.ndarray | None = None) -> dict:
    """Kalman update of one Gaussian by each row of ``Z (J, 5)`` with :func:`cubature_moments`;
    returns ``zhat``, ``S``, ``K``, ``P_post``, ``loglik (J,)`` and ``m_post (J, d)``."""
    zhat, Pzz, Pxz = cubature_moments(m, P, h, E)
    S = Pzz + R
    K = np.linalg.solve(S, Pxz.T).T
    _, logdet = np.linalg.slogdet(2 * np.pi * S)
    out = {"zhat": zhat, "S": S, "K": K, "P_post": P - K @ S @ K.T, "loglik": [], "m_post": []}
    for z in Z:
        r = z - zhat
        for c in AZIMUTHS:
            r[c] = wrap(r[c])
        out["loglik"].append(-0.5 * (r @ np.linalg.solve(S, r) + logdet))
        out["m_post"].append(m + K @ r)
    out["loglik"] = np.array(out["loglik"]).reshape(len(Z))
    out["m_post"] = np.array(out["m_post"]).reshape(len(Z), m.shape[0])
    return out
