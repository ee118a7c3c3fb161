"""A detection probability per Gaussian, learnt from its own detection history (Beta-Gaussian PHD).

``filter.pd_model = "beta"`` (off by default: ``"fixed"``): each component of a map of a type
with :attr:`~mmslam.slam.specs.landmarks.LandmarkSpec.learns_pd` carries the parameters ``(s, t)`` of a
Beta distribution of its own detection probability inside the FOV (``GM.pd_beta``, shape
``(*B, Q, 2)``), as in the Beta-Gaussian mixture PHD filter of Mahler, Vo & Vo, "CPHD filtering
with unknown clutter rate and detection profile", IEEE TSP 59(8), 2011 (Sec. IV). The equations,
for one Gaussian of weight ``w`` and Beta ``(s, t)`` with the FOV gate ``g`` (1 inside, 0 outside
the type's range gate; :meth:`~mmslam.slam.specs.landmarks.LandmarkSpec.fov_radius`):

- detection probability used by the correction: ``p_D = g E[p_D] = g s / (s + t)``
  (:func:`expected_pd`);
- missed-detection term (inside the FOV): weight ``(1 - E[p_D]) w = t / (s + t) w`` and
  ``Beta(s, t + 1)``; outside the FOV ``p_D = 0``: weight ``w`` and ``Beta(s, t)`` unchanged
  (:func:`missed_beta`);
- detection term of ``z_j``: weight ``E[p_D] w N(z_j) / psi(z_j)`` and ``Beta(s + 1, t)``
  (:func:`detected_beta`; both called per component inside the correction kernel of
  :func:`mmslam.slam.phd.gmphd.corrected_gm`);
- birth: the prior ``Beta(n0 p_D,type, n0 (1 - p_D,type))`` (mean ``filter.p_detect_<type>``, the
  fixed model's value; pseudo-count ``n0 = filter.pd_beta_count``, :func:`prior_beta`);
- prediction: unchanged (the Gaussian's survival ``p_S`` does not touch its detection history);
- merging (reduction, averaged map, fused map): the cluster's Beta is the weight average of the
  members' ``(s, t)`` (:func:`beta_pool`).

The products ``E[p_D] w`` and ``(1 - E[p_D]) w`` are exact: ``int p Beta(p; s, t) dp = s / (s + t)``
and ``(1 - p) Beta(p; s, t) = t / (s + t) Beta(p; s, t + 1)``.
"""
from __future__ import annotations

import numba as nb
import numpy as np


def prior_beta(p_detect: float, count: float) -> tuple[float, float]:
    """Birth prior ``(s0, t0) = (n0 p_D, n0 (1 - p_D))`` of mean ``p_detect`` and pseudo-count ``count``.

    Raises ValueError unless ``0 < p_detect < 1`` and ``count > 0`` (a Beta needs ``s, t > 0``).
    """
    if not (0.0 < p_detect < 1.0) or not count > 0.0:
        raise ValueError(f"a Beta detection prior needs 0 < p_detect < 1 and a count > 0, got {p_detect}, {count}")
    return count * p_detect, count * (1.0 - p_detect)


def predict_beta(pd_beta: np.ndarray, forget: float) -> np.ndarray:
    """Prediction of the Beta from k-1 to k: ``(s, t) -> (f s, f t)``, ``f = forget`` in (0, 1].

    The mean ``s / (s + t)`` is kept and the pseudo-count shrinks (the variance grows), so old
    evidence fades with weight ``f^age`` (a landmark's visibility changes as the vehicle moves);
    ``f = 1``: no forgetting (Mahler, Vo & Vo's static detection profile).
    """
    return pd_beta if forget == 1.0 else pd_beta * forget


def bernoulli_missed_weight(w: np.ndarray, p_d: np.ndarray, shares: np.ndarray | None = None) -> np.ndarray:
    """Weight of a Gaussian's missed-detection term, the Gaussian read as one Bernoulli landmark.

    A component of weight ``w`` (``filter.types.<T>.missed = "bernoulli"``) is taken as a landmark that exists
    with probability ``r = min(w, 1)``:

    - ``w < 1``: a missed detection with probability ``p_D`` gives the Bernoulli posterior
      ``r' = r (1 - p_D) / (1 - r p_D)`` (the missed-detection update of a (multi-)Bernoulli filter, as in
      BP-SLAM, Leitinger et al. 2019): ``w' = w (1 - p_D) / (1 - w p_D)``. The PHD's detection terms
      (eq. (5)) are added to it, so a landmark detected at two or three steps crosses 1: it is confirmed.
    - ``w >= 1`` (confirmed, sure to exist): its mass is kept through the scan. A miss does not lower it
      (``p_S`` still decays it) and the detection terms take their shares ``s_j = p_D w N(z_j) / psi(z_j)``
      of measurement ``z_j`` out of it: ``w' = max(w - sum_j s_j, 0)``, so the corrected mass stays ``w``
      (``sum_j s_j`` if larger) instead of growing by one per detection.

    It tends to the PHD's ``(1 - p_D) w`` as ``w -> 0``, lies above it for ``0 < w < 1`` and never above ``w``;
    the corrected mass is at most ``w + sum_j s_j`` (``w < 1``) or ``max(w, sum_j s_j)``: the correction's
    bound (predicted mass + ``J``) holds.

    Args:
        w: ``(...)`` predicted weights (>= 0).
        p_d: ``(...)`` detection probabilities in ``[0, 1]`` (0 outside the FOV: ``w' = w`` for ``w < 1``).
        shares: ``(..., J)`` the Gaussian's detection shares ``s_j`` in ``[0, 1]`` (:func:`detection_shares`);
            None: no measurement.

    Returns:
        ``(...)`` missed-detection weights.
    """
    w, p_d = np.asarray(w, float), np.asarray(p_d, float)
    taken = 0.0 if shares is None else np.sum(np.asarray(shares, float), axis=-1)
    sure = w >= 1.0
    lo = np.where(sure, 0.0, w)
    return np.where(sure, np.maximum(w - taken, 0.0), lo * (1.0 - p_d) / (1.0 - lo * p_d))


def detection_shares(logq: np.ndarray, logpsi: np.ndarray) -> np.ndarray:
    """``s_j = q_j / psi(z_j)``: each Gaussian's share of each measurement, its PHD detection weight (eq. (5)).

    ``logq (P, Q, J)``: ``log(p_D w N(z_j))`` of each Gaussian (``-inf`` where it cannot be detected);
    ``logpsi (P, J)``. Returns ``(P, Q, J)`` in ``[0, 1]``.
    """
    return np.exp(np.minimum(logq - logpsi[:, None, :], 0.0))


def expected_pd(gate_pd: np.ndarray, pd_beta: np.ndarray) -> np.ndarray:
    """``p_D = E[p_D] = s / (s + t)`` where the FOV gate passes (``gate_pd > 0``), else 0.

    ``gate_pd (...)``: the fixed model's ``p_D`` (only its sign is used); ``pd_beta (..., 2)``.
    """
    s, t = pd_beta[..., 0], pd_beta[..., 1]
    return np.where(gate_pd > 0.0, s / (s + t), 0.0)


@nb.njit(cache=True)
def missed_beta(s: float, t: float, in_fov: bool) -> tuple[float, float]:
    """Beta of a missed-detection component: ``(s, t + 1)`` inside the FOV, ``(s, t)`` outside."""
    return (s, t + 1.0) if in_fov else (s, t)


@nb.njit(cache=True)
def detected_beta(s: float, t: float) -> tuple[float, float]:
    """Beta of a component updated by a measurement: ``(s + 1, t)``."""
    return s + 1.0, t


@nb.njit(cache=True)
def beta_pool(w: np.ndarray, ab: np.ndarray, members: np.ndarray, out: np.ndarray) -> None:
    """Beta of a merged cluster: the weight average of the members' ``(s, t)``.

    ``w (Q,)``, ``ab (Q, 2)`` the ``(s, t)`` of each slot, ``members (K,)``; writes ``out (2,)``:
    ``s = sum w_i s_i / W``, ``t = sum w_i t_i / W`` (``W = sum w_i``; equal weights if ``W = 0``).
    This is the normalised geometric pool ``prod_i Beta(p; s_i, t_i)^(w_i / W)`` (a Beta again)
    and keeps the pseudo-counts: the missed ``(s, t + 1)`` and detected ``(s + 1, t)`` copies of
    one Gaussian merge to ``(s + a, t + 1 - a)``, ``a`` the detected share of the weight, one
    step of evidence. (A moment match of the Beta mixture would give back about ``(s, t)`` there,
    and no Gaussian would learn.)
    """
    W = 0.0
    for i in members:
        W += w[i]
    equal = not W > 0.0
    s = 0.0
    t = 0.0
    for i in members:
        wi = 1.0 if equal else w[i]
        s += wi * ab[i, 0]
        t += wi * ab[i, 1]
    n = float(members.shape[0]) if equal else W
    out[0] = s / n
    out[1] = t / n
