"""Textbook GM-PHD correction, one particle, Gaussian and measurement at a time (paper eqs. (5), (10)).

The reference of :func:`mmslam.slam.phd.gmphd.type_terms`, :func:`~mmslam.slam.phd.gmphd.log_psi` and
:func:`~mmslam.slam.phd.gmphd.corrected_gm`: the missed-detection weights ``(1 - p_D) w``, the
detection terms ``log(p_D w N(z_j; zhat, S))`` by :func:`mmslam.slam.reference.ckf.kalman_update`,
``log psi(z_j)`` by ``scipy.special.logsumexp`` over clutter, the BS term and every Gaussian.
"""
from __future__ import annotations

from typing import Callable, Mapping

import numpy as np
from scipy.special import logsumexp

from mmslam.slam.core.gm import GM

from .ckf import kalman_update
from .models import measurement_function


def correction(maps: Mapping[int, GM], geometries: Mapping[int, int], s: np.ndarray, Z: np.ndarray, R: np.ndarray,
               bs: np.ndarray, pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
               bs_term: np.ndarray | None, log_clutter: float) -> tuple[dict, np.ndarray]:
    """Per-particle, per-Gaussian detection terms and ``log psi (P, J)``.

    ``maps``: type code -> map, batch ``(P,)``; ``geometries``: type code -> path geometry;
    ``s (P, 7)`` particle states; ``Z (J, 5)``; ``R (5, 5)``; ``bs_term (P, J)`` the BS's log term or
    None. Returns ``{code: (logq (P, Q, J), missed (P, Q), {(p, q): kalman_update result})}`` and
    ``log psi``.
    """
    P_, J = s.shape[0], Z.shape[0]
    out = {}
    for t, g in maps.items():
        Q = g.capacity
        logq = np.full((P_, Q, J), -np.inf)
        missed = np.zeros((P_, Q))
        upd = {}
        for p in range(P_):
            for q in range(Q):
                if not g.mask[p, q]:
                    continue
                pd = float(pd_fn(s[p, :3], g.m[p, q, :3], t))
                missed[p, q] = (1.0 - pd) * g.w[p, q]
                if pd > 0:
                    r = kalman_update(g.m[p, q], g.P[p, q], measurement_function(s[p], geometries[t], bs), Z, R)
                    logq[p, q] = np.log(pd * g.w[p, q]) + r["loglik"]
                    upd[p, q] = r
        out[t] = (logq, missed, upd)
    lpsi = np.empty((P_, J))
    for p in range(P_):
        for j in range(J):
            parts = [log_clutter] + ([bs_term[p, j]] if bs_term is not None else [])
            parts += [out[t][0][p, q, j] for t in maps for q in range(maps[t].capacity)]
            lpsi[p, j] = logsumexp(parts)
    return out, lpsi


def corrected_components(g: GM, logq: np.ndarray, missed: np.ndarray, upd: dict, lpsi: np.ndarray, p: int,
                         J: int) -> list[tuple[int, float, np.ndarray, np.ndarray]]:
    """Dense slot list of particle ``p``: ``(slot, w, m, P)`` for every live slot of
    :func:`~mmslam.slam.phd.gmphd.corrected_gm`'s layout (missed first, then ``Q + q J + j``)."""
    Q = g.capacity
    comps = [(q, missed[p, q], g.m[p, q], g.P[p, q]) for q in range(Q) if g.mask[p, q]]
    for q in range(Q):
        if not g.mask[p, q]:
            continue
        for j in range(J):
            if (p, q) in upd:
                r = upd[p, q]
                comps.append((Q + q * J + j, np.exp(logq[p, q, j] - lpsi[p, j]), r["m_post"][j], r["P_post"]))
            else:
                comps.append((Q + q * J + j, 0.0, g.m[p, q], g.P[p, q]))
    return sorted(comps, key=lambda c: c[0])
