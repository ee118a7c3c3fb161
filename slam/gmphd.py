"""GM-PHD map correction for the RBPF: paper eqs. (5), (10) and the particle weight (6).

Everything is batched over particles ``P`` x Gaussians ``Q`` x measurements ``J`` with padded
arrays (:class:`~mmslam.slam.gm.GM`, batch shape ``(P,)``). Frames and units: global frame,
metres, radians; a measurement is ``z = [TOA (m, incl. clock bias), AOD az, AOD el, AOA az
(body frame), AOA el]`` (:mod:`mmslam.slam.measurement`).

:func:`correct` is the whole correction. The measurement update of one landmark Gaussian is the
cubature Kalman filter step of :func:`mmslam.slam.ckf.ckf_update` (6 cubature points of the
position marginal for every map type; a 7-D VS Gaussian ``[x, y, z, vx, vy, vz, xi]`` is
corrected in velocity and turn rate through the cross-covariance). The known BS is a single
fixed landmark (weight 1, no map): it only adds ``p_D N(z; h(s_p, b), R)`` to ``psi(z)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numba as nb
import numpy as np

from .ckf import Innovation, gaussian_loglik, innovate
from .detection import corrected_pd_beta, expected_pd
from .gm import GM
from .linalg import safe_cholesky
from .measurement import BS, MEAS_DIM, TYPE_NAMES, geometry_of, measure_point



def correct(maps: dict[int, GM], states: np.ndarray, Z: np.ndarray, R: np.ndarray, bs: np.ndarray,
            pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray], p_bs: np.ndarray, log_clutter: float,
            prune: float | None, extents: dict[int, np.ndarray | None], step: int
            ) -> tuple[dict[int, GM], np.ndarray]:
    """The PHD correction of every map of every particle with one measurement set.

    Paper eq. (5) (with the VS map, eq. (10)): for each particle ``p``
    with vehicle state ``s_p`` and each map type ``t`` (predicted intensity ``D_t``),

        ``D_t^+(x) = (1 - p_D(x)) D_t(x) + sum_j p_D(x) N(z_j; h_t(s_p, x), R) D_t(x) / psi(z_j)``,
        ``psi(z_j) = c(z_j) + p_D,BS N(z_j; h(s_p, b), R) + sum_t int p_D N(z_j; h_t(s_p, x), R) D_t(x) dx``,

    and eq. (6), the particle weight: the paper writes ``sum_j psi(z_j)``; mmslam multiplies the
    weight by ``prod_j psi(z_j)`` as the authors' code does (docs/implementation-notes.md), i.e. the
    caller adds ``log psi(z).sum(1)`` to the log-weights.

    Steps:

    1. detection probabilities ``p_D`` at the Gaussian means (``pd_fn``); a Gaussian with
       ``p_D = 0`` gets no innovation and keeps its whole weight as missed detection;
    2. innovations: CKF update of every detectable Gaussian by every measurement
       (:func:`mmslam.slam.ckf.innovate`; :func:`type_terms`), and the BS term (:func:`bs_logterm`);
    3. ``log psi(z_j)`` per particle (:func:`log_psi`, log-sum-exp over clutter, BS and all types);
    4. corrected components: ``(1 - p_D) w`` with the predicted moments and
       ``p_D w N(z_j) / psi(z_j)`` with the updated moments, pruned at ``prune`` (:func:`corrected_gm`);
    5. the PHD-mass invariant ``sum w^+ <= sum w + J`` per particle (:func:`check_phd_mass`).

    Args:
        maps: type code -> predicted map, batch ``(P,)`` (dim 3, VS 7).
        states: ``(P, 7)`` particle vehicle states.
        Z: ``(J, 5)`` measurements; R: ``(5, 5)`` or ``(J, 5, 5)`` (one per measurement).
        bs: ``(3,)`` BS position (m).
        pd_fn: ``pd_fn(vehicle_pos (P, Q, 3), lm_pos (P, Q, 3), lm_type) -> (P, Q)``.
        p_bs: ``(P,)`` BS detection probability per particle.
        log_clutter: ``log c(z)`` (clutter intensity, uniform).
        prune: weight threshold of the materialised components, or None (dense layout).
        extents: type code -> ``(3, 3)`` scatter-point covariance (m^2) or None (point landmark).
        step: time step ``k`` (for messages).

    Returns:
        The corrected maps (same keys) and ``log psi (P, J)``.

    Raises:
        FloatingPointError: a non-finite or non-positive-definite covariance, ``psi(z) = 0``, or a
            broken PHD-mass invariant.
    """
    J = Z.shape[0]
    bs_term = bs_logterm(states, Z, R, bs, np.asarray(p_bs, float))  # 1.-2. (BS)
    terms = [type_terms(g, t, states, Z, R, bs, pd_fn, extents.get(t)) for t, g in maps.items()]  # 1.-2.
    lpsi = log_psi(terms, bs_term, log_clutter, (states.shape[0], J))  # 3.
    out = {}
    for tc in terms:
        g = corrected_gm(tc, Z, lpsi, prune=prune)  # 4.
        check_phd_mass(tc.g, g, J, tc.lm_type, step)  # 5.
        out[tc.lm_type] = g
    return out, lpsi


def predict_static(g: GM, p_survival: float) -> GM:
    """Static landmark prediction (identity dynamics): weights times ``p_survival`` (a Beta detection
    history ``pd_beta`` is kept as it is)."""
    return GM(g.w * p_survival, g.m, g.P, g.mask, g.pd_beta)


@dataclass
class TypeCorrection:
    """Intermediate per-type correction terms: detection terms and innovation.

    ``logq (P, Q, J)``: ``log(p_D w N(z_j; zhat, S))`` (``-inf`` where masked or ``p_D = 0``);
    ``missed_w (P, Q)``: ``(1 - p_D) w``; ``det_index (P, Q)``: index of the Gaussian in the
    innovation ``inn`` (``-1`` where masked or ``p_D = 0``: no innovation is computed for
    a Gaussian that cannot be detected, its detection terms are exactly zero).
    """

    g: GM
    lm_type: int
    logq: np.ndarray
    missed_w: np.ndarray
    inn: Innovation
    det_index: np.ndarray


def type_terms(g: GM, lm_type: int, states: np.ndarray, Z: np.ndarray, R: np.ndarray,
               bs: np.ndarray, pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
               extent: np.ndarray | None = None) -> TypeCorrection:
    """Detection terms of one map type (batched over particles, Gaussians and measurements).

    Only the live Gaussians with ``p_D > 0`` (inside the FOV) go through the CKF innovation
    (:func:`mmslam.slam.ckf.innovate`, flattened over particles x Gaussians); the others keep
    ``logq = -inf`` and their full weight as missed detection, exactly as the dense formula
    gives with ``p_D = 0``.

    Args:
        g: predicted map of this type, batch ``(P,)``, ``Q`` slots, dim 3 (VA/SP) or 7 (VS).
        states: ``(P, 7)`` particle vehicle states.
        Z: ``(J, 5)`` measurements of this vehicle and step.
        pd_fn: ``pd_fn(vehicle_pos (P, Q, 3), lm_pos (P, Q, 3), lm_type) -> (P, Q)`` detection
            probability evaluated at the Gaussian means; with ``g.pd_beta`` (``filter.pd_model =
            "beta"``) only its FOV gate (``> 0``) is used and ``p_D = s / (s + t)`` of each
            Gaussian's own Beta (:func:`mmslam.slam.detection.expected_pd`).
        extent: ``(3, 3)`` scatter-point covariance of an extended landmark (VS: a car body), see
            :func:`mmslam.slam.ckf.ckf_update`; None for point landmarks.

    Raises:
        FloatingPointError: a non-finite mean or covariance in the map (also outside the FOV),
            or a covariance that is not positive definite.
    """
    stage = f"{_tname(lm_type)} correction"
    if not (np.isfinite(g.m).all() and np.isfinite(g.P).all()):  # masked slots hold 0 / I
        raise FloatingPointError(f"non-finite mean or covariance in {stage}")
    P_, Q = g.w.shape
    J = Z.shape[0]
    pd = pd_fn(np.broadcast_to(states[:, None, 0:3], g.m.shape[:-1] + (3,)), g.m[..., 0:3], lm_type)
    if g.pd_beta is not None:  # the Beta-Gaussian PHD: E[p_D] = s / (s + t) inside the FOV
        pd = expected_pd(pd, g.pd_beta)
    pd = np.where(g.mask, pd, 0.0)
    det = pd > 0.0
    pidx, qidx = np.nonzero(det)
    det_index = np.full((P_, Q), -1)
    det_index[pidx, qidx] = np.arange(pidx.size)
    inn = innovate(g.m[pidx, qidx], g.P[pidx, qidx], states[pidx], geometry_of(lm_type), bs, Z, R, stage, extent)
    logq = np.full((P_, Q, J), -np.inf)
    logq[pidx, qidx] = np.log(pd[pidx, qidx] * g.w[pidx, qidx])[:, None] + inn.loglik
    return TypeCorrection(g, lm_type, logq, (1.0 - pd) * g.w, inn, det_index)


@nb.njit(cache=True)
def _bs_loglik(states: np.ndarray, Z: np.ndarray, L: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out[p, j] = log N(z_j; h(s_p, b), R_j)`` (line of sight), ``R_j = L_j L_j^T`` (``L (1 or J, 5, 5)``)."""
    zhat = np.empty(MEAS_DIM)
    y = np.empty(MEAS_DIM)
    for p in range(states.shape[0]):
        zhat[0], zhat[1], zhat[2], zhat[3], zhat[4] = measure_point(0, states[p], b, b)  # Bounce.DIRECT
        for j in range(Z.shape[0]):
            Lj = L[j if L.shape[0] > 1 else 0]
            half_logdet = 0.0
            for a in range(MEAS_DIM):
                half_logdet += math.log(Lj[a, a])
            out[p, j] = gaussian_loglik(Z[j], zhat, Lj, half_logdet, y)


def bs_logterm(states: np.ndarray, Z: np.ndarray, R: np.ndarray, bs: np.ndarray,
               p_d: np.ndarray) -> np.ndarray:
    """``log(p_D N(z_j; h(s_p, b, BS), R))`` for the known BS, shape ``(P, J)``.

    ``p_d`` is ``(P,)``: the BS detection probability for each particle. ``R``: ``(5, 5)``, or
    ``(J, 5, 5)`` one covariance per measurement.
    """
    J = Z.shape[0]
    if J == 0:  # no measurements
        return np.zeros((states.shape[0], 0))
    R = np.asarray(R, float)
    L = safe_cholesky(R.reshape(-1, MEAS_DIM, MEAS_DIM), "BS likelihood")
    ll = np.empty((states.shape[0], J))
    _bs_loglik(np.ascontiguousarray(states, dtype=float), np.ascontiguousarray(Z, dtype=float), L,
               np.ascontiguousarray(bs, dtype=float), ll)
    with np.errstate(divide="ignore"):
        return np.log(p_d)[:, None] + ll


def log_psi(terms: list[TypeCorrection], bs_term: np.ndarray | None, log_clutter: float,
            shape: tuple[int, int]) -> np.ndarray:
    """``log psi(z_j) = log(c(z) + sum_types sum_q q + BS term)``, shape ``(P, J)`` (log-sum-exp).

    Raises FloatingPointError if some ``psi(z)`` is zero or non-finite (e.g. no clutter and no
    landmark can explain a measurement).
    """
    parts = [np.full(shape, float(log_clutter))]
    if bs_term is not None:
        parts.append(bs_term)
    for t in terms:
        if t.logq.shape[1]:
            parts.append(_logsumexp_slots(t.logq))
    stacked = np.stack(parts, axis=0)
    mx = stacked.max(axis=0)
    if not np.isfinite(mx).all() or np.isnan(stacked).any():
        raise FloatingPointError("psi(z) is zero or non-finite in the PHD correction "
                                 "(no clutter and no landmark explains a measurement)")
    return mx + np.log(np.exp(stacked - mx).sum(axis=0))


def _logsumexp_slots(logq: np.ndarray) -> np.ndarray:
    """``log sum_q exp(logq[:, q, :])`` of ``logq (P, Q, J)`` -> ``(P, J)`` (``-inf`` if all are).

    For ``J > 1`` the slots are moved to the front into a fresh buffer so that the max and the
    sum run over contiguous ``(P, J)`` slabs. ``logq`` is never written: the caller
    (:func:`corrected_gm`) reads it again. ``np.ascontiguousarray`` must not be used here, since
    it returns a *view* when ``P == 1`` or ``Q == 1`` and the in-place exp below then rewrote
    ``logq`` (landmark weights of ~1/clutter intensity on city scenes).
    """
    if logq.shape[2] == 1:
        mx = logq.max(axis=1)
        safe = np.where(np.isfinite(mx), mx, 0.0)
        with np.errstate(divide="ignore"):
            return safe + np.log(np.exp(logq - safe[:, None, :]).sum(axis=1))
    t = logq.transpose(1, 0, 2).copy()  # (Q, P, J), always a new array
    mx = t.max(axis=0)
    safe = np.where(np.isfinite(mx), mx, 0.0)
    t -= safe
    np.exp(t, out=t)
    with np.errstate(divide="ignore"):
        return safe + np.log(t.sum(axis=0))


def corrected_gm(t: TypeCorrection, Z: np.ndarray, logpsi: np.ndarray, prune: float | None = None) -> GM:
    """Corrected PHD of one type: missed-detection part plus one updated Gaussian per (q, z).

    With ``prune=None`` the result has the dense layout: batch ``(P,)`` and ``Q (1 + J)``
    slots, the first ``Q`` holding ``(1 - p_D) w`` with the predicted moments, then ``Q x J``
    updated components ``(q, j)`` at slot ``Q + q J + j`` (``w = q / psi(z)``, ``m + K r``,
    ``P - K S K^T``; a Gaussian that cannot be detected, ``p_D = 0``, has no innovation: its
    updated slots hold weight 0 and the predicted moments).

    With a ``prune`` threshold only components of weight ``>= prune`` are materialised
    (the same rule as the first step of ``prune_merge``), compacted to the front (slot order:
    missed-detection components first, then updates in ``(q, j)`` order) with as many slots as
    the largest surviving count. This avoids building the ``(P, Q J, d, d)`` arrays.

    A map with Beta detection parameters (``g.pd_beta``) gets them updated per component
    (:func:`mmslam.slam.detection.corrected_pd_beta`: missed ``(s, t + 1)`` inside the FOV,
    detected ``(s + 1, t)``).
    """
    g, inn = t.g, t.inn
    P_, Q, d = g.m.shape
    J = Z.shape[0]
    dense = prune is None
    args = (g.mask, t.missed_w, t.logq, logpsi, g.m, g.P, t.det_index, inn.m_post, inn.P_post,
            0.0 if dense else float(prune), dense)
    K = Q * (1 + J)
    if not dense:  # a first pass counts the kept components
        none = (np.zeros((0, 0)), np.zeros((0, 0, d)), np.zeros((0, 0, d, d)), np.zeros((0, 0), bool),
                np.zeros((0, 0), np.int64))
        K = int(_corrected_components(*args, True, *none).max(initial=0))
    w, m, Pc, live = np.zeros((P_, K)), np.zeros((P_, K, d)), np.empty((P_, K, d, d)), np.zeros((P_, K), bool)
    src = np.zeros((P_, K), np.int64)
    Pc[...] = np.eye(d)
    _corrected_components(*args, False, w, m, Pc, live, src)
    pd_beta = None if g.pd_beta is None else corrected_pd_beta(g.pd_beta, t.det_index, src, live, Q, J)
    out = GM(w, m, Pc, live, pd_beta)
    if not np.isfinite(out.w.sum() + out.m.sum() + out.P.sum()):  # masked slots are 0 / I
        out.check(f"after the {_tname(t.lm_type)} correction")
        raise FloatingPointError(f"non-finite values after the {_tname(t.lm_type)} correction")
    return out


@nb.njit(cache=True, error_model="numpy")
def _corrected_components(mask: np.ndarray, missed_w: np.ndarray, logq: np.ndarray, lpsi: np.ndarray,
                          m: np.ndarray, P: np.ndarray, det_index: np.ndarray, m_post: np.ndarray,
                          P_post: np.ndarray, prune: float, dense: bool, count_only: bool,
                          out_w: np.ndarray, out_m: np.ndarray, out_P: np.ndarray, out_mask: np.ndarray,
                          out_src: np.ndarray) -> np.ndarray:
    """The components of paper eq. (5) for each particle ``p`` (see :func:`corrected_gm`).

    Missed detections ``(1 - p_D) w`` with the predicted moments (slots ``q``), then one updated
    Gaussian per ``(q, j)``: weight ``exp(logq - log psi(z_j)) = p_D w N(z_j) / psi(z_j)``, moments
    from the innovation (``det_index[p, q] >= 0``) or the predicted ones (``p_D = 0``). ``dense``:
    every live slot at its fixed place ``q`` / ``Q + q J + j``; else only weights ``>= prune``,
    compacted in that order; ``out_src`` gets each written component's dense slot (its source).
    Returns the number of components of each particle (``count_only``: nothing is written).
    """
    Pn, Q, d = m.shape
    J = logq.shape[2]
    log_prune = math.log(prune) if prune > 0.0 else -np.inf
    counts = np.zeros(Pn, np.int64)
    for p in range(Pn):
        k = 0
        for slot in range(Q * (1 + J)):
            q = slot if slot < Q else (slot - Q) // J
            if not mask[p, q]:
                continue
            if slot < Q:
                wk = missed_w[p, q]
                if not (dense or wk >= prune):
                    continue
            else:
                j = (slot - Q) % J
                logw = logq[p, q, j] - lpsi[p, j]
                if not (dense or logw >= log_prune):  # the prune test in the log domain: exp only when kept
                    continue
                wk = math.exp(logw)
            if not count_only:
                at = slot if dense else k
                out_w[p, at] = wk
                out_mask[p, at] = True
                out_src[p, at] = slot
                n = det_index[p, q]
                if slot >= Q and n >= 0:
                    out_m[p, at] = m_post[n, j]
                    out_P[p, at] = P_post[n, j if P_post.shape[1] > 1 else 0]
                else:
                    out_m[p, at] = m[p, q]
                    out_P[p, at] = P[p, q]
            k += 1
        counts[p] = k
    return counts


PHD_MASS_RTOL = 1e-9
"""Relative float tolerance of :func:`check_phd_mass` (the bound is exact in real arithmetic)."""


def check_phd_mass(predicted: GM, corrected: GM, n_meas: int, lm_type: int, step: int) -> None:
    """Invariant of the PHD correction: per particle, corrected mass <= predicted mass + ``J``.

    The corrected intensity is ``(1 - p_D) D(x) + sum_j p_D g_j(x) D(x) / psi(z_j)`` and every
    ``psi(z_j)`` contains the clutter, the BS and all landmark terms of ``z_j``, so each
    measurement adds at most 1 to the mass: ``sum_q w_q^+ <= sum_q w_q + J`` (pruning only
    lowers the left side). A kernel that corrupts the log-weights breaks it at once (the
    ``_logsumexp_slots`` bug gave weights of ~1/clutter intensity). Cost: two sums over
    ``(P, Q)``.

    Args:
        predicted: the map of one type before the correction, batch ``(P,)``.
        corrected: the same map after :func:`corrected_gm`, batch ``(P,)``.
        n_meas: the number of measurements ``J`` of the correction.
        lm_type: the map's landmark type (for the message); step: the time step ``k``.

    Raises:
        FloatingPointError: naming the type, step, particle and both masses, if the bound is
            exceeded beyond a relative ``PHD_MASS_RTOL`` (or a mass is NaN).
    """
    pred = np.where(predicted.mask, predicted.w, 0.0).sum(axis=-1)
    corr = np.where(corrected.mask, corrected.w, 0.0).sum(axis=-1)
    bound = pred + n_meas
    bad = ~(corr <= bound * (1.0 + PHD_MASS_RTOL))  # NaN fails too
    if bad.any():
        p = int(np.argmax(np.where(bad, np.nan_to_num(corr - bound, nan=np.inf), -np.inf)))
        raise FloatingPointError(
            f"PHD mass invariant violated in the {_tname(lm_type)} correction at step {step}, particle {p}: "
            f"corrected mass {corr[p]:.6g} > predicted mass {pred[p]:.6g} + {n_meas} measurements "
            f"({int(bad.sum())} of {bad.size} particles); a correction kernel corrupted the weights")


def _tname(t: int) -> str:
    return TYPE_NAMES.get(t, str(t))
