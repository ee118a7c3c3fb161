"""Offsets of a static landmark's position in its correction, shapes as stated, position in the global frame, m:

- the follow offset (``filter.types.<T>.follow_std``): the update of a detected Gaussian takes its gain and likelihood
  from ``P + F`` (:func:`offset_position`, :func:`mmslam.slam.phd.gmphd.type_terms`), and the covariance kept is the
  estimate's own for that gain (:func:`own_covariance`);
- the weight offset (``weight_std``): only the particle weight sees the map with ``P + F_w``
  (:func:`offset_position`, :func:`mmslam.slam.phd.gmphd.correct`), at a share ``lambda`` of its likelihood
  (``weight_share``, :func:`weight_mixture`)."""
from __future__ import annotations

import math

import numpy as np

from ..core.gm import GM


def own_covariance(P: np.ndarray, P_follow: np.ndarray, P_follow_post: np.ndarray) -> np.ndarray:
    """The covariance of a landmark estimate updated with a gain that follows the image point seen
    (``filter.types.<T>.follow_std``, docs/city-slam.md "A map that follows the facet seen").

    The update took its gain and likelihood from ``P~ = P + F`` (``F = follow_std^2 I`` on the position): the
    image point seen at a scan departs from the mapped one by a fresh offset the estimate follows. For a landmark
    that does not move, the estimate's own error after that gain ``K`` is the Joseph form on ``P``,
    ``(I - K H) P (I - K H)^T + K R K^T``. With ``A = I - K H = P~+ P~^-1`` and ``K R K^T = P~+ - A P~ A^T``
    (the Joseph form of the update on ``P~``, whose gain is optimal) it needs neither ``H`` nor ``K``:

        ``P+ = A P A^T + [P~+ - A P~ A^T]_+``

    (``[.]_+``: eigenvalues below 0 set to 0, as the CKF and the heavy tail's moment match make the bracket only
    nearly positive semi-definite). ``F = 0`` gives ``P+ = P~+``; a linear update gives ``P+ = P~+ - A F A^T``.

    Args:
        P: ``(N, d, d)`` prior covariances (m^2 on the position block).
        P_follow: ``(N, d, d)`` the same with ``F`` added, from which the update was made.
        P_follow_post: ``(N, 1 or J, d, d)`` the update's posterior covariances.

    Returns:
        ``(N, 1 or J, d, d)`` the estimates' own posterior covariances, exactly symmetric.
    """
    Pf = np.asarray(P_follow, float)[:, None]
    Pp = np.asarray(P_follow_post, float)
    At = np.linalg.solve(Pf, Pp)  # A^T = P~^-1 P~+ (both symmetric)
    A = np.swapaxes(At, -1, -2)
    noise = Pp - A @ Pf @ At
    ev, V = np.linalg.eigh(0.5 * (noise + np.swapaxes(noise, -1, -2)))
    out = A @ np.asarray(P, float)[:, None] @ At + (V * np.clip(ev, 0.0, None)[..., None, :]) @ np.swapaxes(V, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def offset_position(g: GM, f: float) -> GM:
    """The map ``g`` (batch ``(*B, Q)``, dim ``d >= 3``) with ``f`` (m^2) added to the variance of x, y and z of every
    Gaussian: the follow offset's ``P + F`` (``follow_std``) and the weight offset's ``P + F_w`` (``weight_std``,
    :func:`mmslam.slam.phd.gmphd.correct`). ``f = 0``: ``g`` itself."""
    if f <= 0.0:
        return g
    P = np.array(g.P, float)
    P[..., :3, :3] += f * np.eye(3)
    return GM(g.w, g.m, P, g.mask, g.pd_beta, g.label)


def weight_mixture(logq: np.ndarray, logq_offset: np.ndarray, share: float) -> np.ndarray:
    """The detected terms of one type in the particle weight with the weight offset at a share ``lambda``
    (``filter.types.<T>.weight_share``; docs/equations.md, eq. (6) with the weight offset):

        ``log[(1 - lambda) p_D w N(z_j; zhat, S(P)) + lambda p_D w N(z_j; zhat, S(P + F_w))]``

    the image point seen departing from the mapped one by the offset ``N(0, F_w)`` at a share ``lambda`` of the
    detections. With this type the only one offset, summed over the Gaussians with the clutter, the BS and the other
    types, ``psi_lambda(z_j) = (1 - lambda) psi(z_j) + lambda psi_w(z_j)``.

    Args:
        logq: ``(P, Q, J)`` ``log(p_D w N(z_j; zhat, S(P)))`` of the map's own covariances (``-inf``: no term).
        logq_offset: ``(P, Q, J)`` the same with ``P + F_w``.
        share: ``lambda`` in ``[0, 1]``; 1 gives ``logq_offset``, 0 gives ``logq`` (the arrays themselves).

    Returns:
        ``(P, Q, J)`` the mixed log terms (``-inf`` where neither has a term).

    Raises:
        ValueError: ``share`` outside ``[0, 1]``.
    """
    lam = float(share)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"weight share {share!r}: expected a number in [0, 1]")
    if lam == 1.0:
        return logq_offset
    if lam == 0.0:
        return logq
    return np.logaddexp(math.log1p(-lam) + logq, math.log(lam) + logq_offset)
