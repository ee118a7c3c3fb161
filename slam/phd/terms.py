"""The compiled loops of the GM-PHD correction (:mod:`mmslam.slam.phd.gmphd`, paper eqs. (5), (6), (10)).

One kernel per stage, over particles ``P`` x Gaussians ``Q`` x measurements ``J`` of padded
arrays: the detectable slots and predicted masses (:func:`_detection_slots`), the CKF detection
terms ``log(p_D w N(z_j; zhat, S))`` compiled once per path geometry (:data:`_TYPE_TERMS`), the BS
log-likelihood (:func:`_bs_loglik`), the log-sum-exp of ``psi(z)`` (:func:`_log_psi_parts`,
:func:`_lse_slots_kernel`, with the pairwise sums NumPy uses, :func:`_pairwise_sum`), the corrected
components (:func:`_corrected_components`, :func:`_write_corrected`) and the PHD-mass bound
(:func:`_mass_bound_holds`). :mod:`mmslam.slam.phd.gmphd` checks the inputs, calls them and raises
the errors; nothing here allocates inside a loop or raises.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..core.jit import batch_kernel
from ..models.measurement import MEAS_DIM, measure_point
from .ckf import OK, ckf_update, gaussian_loglik
from .detection import detected_beta, missed_beta


_EXP_UNDERFLOW = -746.0
"""``exp(x)`` is exactly 0 below this (``e^-746 < 2^-1075``, half the smallest subnormal): such
terms of a sum are skipped without calling ``exp`` (also ``-inf``, the undetectable slots)."""


@nb.njit(cache=True, error_model="numpy")
def _detection_slots(mask: np.ndarray, w: np.ndarray, pd: np.ndarray, m: np.ndarray, P: np.ndarray,
                     det_index: np.ndarray, missed_w: np.ndarray, logq: np.ndarray, pred_mass: np.ndarray) -> int:
    """The geometry-free part of :func:`type_terms`: returns the number ``N`` of detectable Gaussians,
    or -1 if some mean ``m (P, Q, d)`` or covariance ``P (P, Q, d, d)`` (live or not; both
    C-contiguous) is not finite.

    For each particle ``p`` and Gaussian ``q``: ``p_D = pd`` where live, else 0; missed weight
    ``missed_w = (1 - p_D) w``; ``det_index[p, q]``: the number ``n`` of its CKF update if
    ``p_D > 0`` (particle-major order), else -1; ``logq[p, q] = -inf`` for ``n = -1`` (the
    detectable Gaussians' terms are written by :func:`_type_terms_loop`); ``pred_mass[p] = sum_q w``
    over the live slots (NumPy's ``np.where(mask, w, 0).sum(-1)``, :func:`_pairwise_sum`).
    """
    Pn, Q, d = m.shape
    if not (_all_finite(m.reshape(-1)) and _all_finite(P.reshape(-1))):
        return -1
    n = 0
    row = np.empty(Q)
    for p in range(Pn):
        for q in range(Q):
            pdq = pd[p, q] if mask[p, q] else 0.0
            missed_w[p, q] = (1.0 - pdq) * w[p, q]
            row[q] = w[p, q] if mask[p, q] else 0.0
            if pdq > 0.0:
                det_index[p, q] = n
                n += 1
            else:
                det_index[p, q] = -1
                for j in range(logq.shape[2]):
                    logq[p, q, j] = -np.inf
        pred_mass[p] = _pairwise_sum(row)
    return n


@nb.njit(cache=True, inline="always")
def _all_finite(a: np.ndarray) -> bool:
    """Whether every element of the 1-D ``a`` is finite (no early exit: the loop vectorises, ~5x faster)."""
    ok = True
    for i in range(a.shape[0]):
        ok &= np.isfinite(a[i])
    return ok


@nb.njit(cache=True, error_model="numpy", inline="always")
def _type_terms_loop(geometry: int, w: np.ndarray, pd: np.ndarray, m: np.ndarray, P: np.ndarray,
                     states: np.ndarray, b: np.ndarray, extent: np.ndarray, body: np.ndarray, Z: np.ndarray, R: np.ndarray,
                     det_index: np.ndarray, logq: np.ndarray, loglik: np.ndarray, m_post: np.ndarray,
                     P_post: np.ndarray, floor_q: float, floor_post: float, work: tuple) -> int:
    """The CKF loop of :func:`type_terms` (after :func:`_detection_slots`); returns ``OK`` or the
    failure code of :func:`~mmslam.slam.phd.ckf.ckf_update`. ``work``: the scratch arrays of
    :func:`~mmslam.slam.phd.ckf.workspace` (``d``), allocated by the caller (a :func:`~mmslam.slam.core.jit.batch_kernel`).

    For each particle ``p`` and Gaussian ``q`` with ``n = det_index[p, q] >= 0``: the CKF update
    into ``loglik[n]``, ``m_post[n]``, ``P_post[n]`` and ``logq[p, q, j] = log(p_D w) + log N(z_j; zhat, S)``;
    a term below ``floor_q`` is ``-inf``, the mean of one below ``floor_post`` is not written
    (:func:`_skip_floors`; the floors of :func:`~mmslam.slam.phd.ckf.ckf_update` less ``log(p_D w)``).
    """
    Pn, Q, d = m.shape
    for p in range(Pn):
        for q in range(Q):
            n = det_index[p, q]
            if n < 0:
                continue
            lw = math.log(pd[p, q] * w[p, q])
            code = ckf_update(geometry, m[p, q], P[p, q], states[p], b, extent, body, Z, R, loglik[n], m_post[n],
                              P_post[n], work, floor_q - lw, floor_post - lw)
            if code != OK:
                return code
            for j in range(Z.shape[0]):
                logq[p, q, j] = lw + loglik[n, j]
    return OK


@batch_kernel
def _type_terms_direct(w, pd, m, P, states, b, extent, body, Z, R, det_index, logq, loglik, m_post, P_post, fq, fp, work):  # noqa
    return _type_terms_loop(0, w, pd, m, P, states, b, extent, body, Z, R, det_index, logq, loglik, m_post, P_post,
                            fq, fp, work)  # Bounce.DIRECT


@batch_kernel
def _type_terms_mirror(w, pd, m, P, states, b, extent, body, Z, R, det_index, logq, loglik, m_post, P_post, fq, fp, work):  # noqa
    return _type_terms_loop(1, w, pd, m, P, states, b, extent, body, Z, R, det_index, logq, loglik, m_post, P_post,
                            fq, fp, work)  # Bounce.MIRROR


@batch_kernel
def _type_terms_scatter(w, pd, m, P, states, b, extent, body, Z, R, det_index, logq, loglik, m_post, P_post, fq, fp, work):  # noqa
    return _type_terms_loop(2, w, pd, m, P, states, b, extent, body, Z, R, det_index, logq, loglik, m_post, P_post,
                            fq, fp, work)  # Bounce.SCATTER


_TYPE_TERMS = (_type_terms_direct, _type_terms_mirror, _type_terms_scatter)
"""The :func:`type_terms` kernel of each :class:`mmslam.model.Bounce` code."""


@batch_kernel(error_model="python")
def _bs_loglik(states: np.ndarray, Z: np.ndarray, L: np.ndarray, b: np.ndarray, out: np.ndarray,
               zhat: np.ndarray, y: np.ndarray, half_logdet: np.ndarray) -> None:
    """``out[p, j] = log N(z_j; h(s_p, b), R_j)`` (line of sight), ``R_j = L_j L_j^T`` (``L (1 or J, 5, 5)``).
    Scratch: ``zhat, y (5,)``, ``half_logdet (1 or J,)``."""
    for r in range(L.shape[0]):
        half_logdet[r] = 0.0
        for a in range(MEAS_DIM):
            half_logdet[r] += math.log(L[r, a, a])
    for p in range(states.shape[0]):
        zhat[0], zhat[1], zhat[2], zhat[3], zhat[4] = measure_point(0, states[p], b, b)  # Bounce.DIRECT
        for j in range(Z.shape[0]):
            r = j if L.shape[0] > 1 else 0
            out[p, j] = gaussian_loglik(Z[j], zhat, L[r], half_logdet[r], y)


@nb.njit(cache=True)
def _log_psi_parts(log_clutter: float, parts: np.ndarray, out: np.ndarray) -> bool:
    """``out = log(exp(log_clutter) + sum_i exp(parts[i]))`` of ``parts (n, P, J)``, ``out (P, J)``.

    The same arithmetic as NumPy's ``mx + log(sum(exp(stacked - mx)))`` over the stacked parts
    (clutter first). False if some maximum is not finite or some part is NaN.
    """
    n, Pn, J = parts.shape
    ok = True
    for p in range(Pn):
        for j in range(J):
            mx = log_clutter
            nan = False
            for i in range(n):
                v = parts[i, p, j]
                nan = nan or np.isnan(v)
                mx = v if v > mx else mx
            if nan or not np.isfinite(mx):
                ok = False
                continue
            x = log_clutter - mx
            s = 0.0 + (0.0 if x < _EXP_UNDERFLOW else math.exp(x))
            for i in range(n):
                x = parts[i, p, j] - mx
                if not x < _EXP_UNDERFLOW:  # adding an exact 0 changes nothing: no exp
                    s += math.exp(x)
            out[p, j] = mx + math.log(s)
    return ok


@nb.njit(cache=True, error_model="numpy")
def _pairwise_block(a: np.ndarray, lo: int, n: int) -> float:
    """``sum(a[lo:lo + n])``, ``n <= 128``, in NumPy's order: sequential below 8 terms, else 8 partial sums."""
    if n < 8:
        r = 0.0
        for i in range(lo, lo + n):
            r += a[i]
        return r
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@nb.njit(cache=True, error_model="numpy")
def _pairwise_sum(a: np.ndarray) -> float:
    """``sum(a)`` in NumPy's order (``pairwise_sum`` of its ``add.reduce``): blocks of at most 128
    terms (:func:`_pairwise_block`), above that the sum of the two halves (split at a multiple of 8).

    The recursion runs on an explicit stack (numba's on-disk cache of a self-recursive function is
    not reliable)."""
    n = a.shape[0]
    if n <= 128:
        return _pairwise_block(a, 0, n)
    f_lo = np.empty(64, np.int64)  # frames (lo, n, stage): stage 0 -> left half, 1 -> right, 2 -> add
    f_n = np.empty(64, np.int64)
    f_stage = np.empty(64, np.int64)
    vals = np.empty(64)
    f_lo[0], f_n[0], f_stage[0] = 0, n, 0
    top, vt = 1, 0
    while top > 0:
        lo, m, stage = f_lo[top - 1], f_n[top - 1], f_stage[top - 1]
        if m <= 128:
            vals[vt] = _pairwise_block(a, lo, m)
            vt += 1
            top -= 1
            continue
        m2 = m // 2
        m2 -= m2 % 8
        if stage == 2:
            vals[vt - 2] = vals[vt - 2] + vals[vt - 1]
            vt -= 1
            top -= 1
            continue
        f_stage[top - 1] = stage + 1
        f_lo[top], f_n[top], f_stage[top] = (lo, m2, 0) if stage == 0 else (lo + m2, m - m2, 0)
        top += 1
    return vals[0]


@nb.njit(cache=True, error_model="numpy")
def _lse_slots_kernel(logq: np.ndarray, out: np.ndarray) -> None:
    """``out[p, j] = m + log sum_q exp(logq[p, q, j] - m)``, ``m`` the slot maximum (0 if not finite)."""
    Pn, Q, J = logq.shape
    e = np.empty(Q)
    mx = np.empty(J)
    s = np.empty(J)
    for p in range(Pn):
        mx[:] = -np.inf
        for q in range(Q):
            for j in range(J):
                v = logq[p, q, j]
                if v > mx[j] or np.isnan(v):  # NaN propagates, as in NumPy's max
                    mx[j] = v
        for j in range(J):
            if not np.isfinite(mx[j]):
                mx[j] = 0.0
        if J == 1:  # NumPy sums along the contiguous slot axis: pairwise
            for q in range(Q):
                x = logq[p, q, 0] - mx[0]
                e[q] = 0.0 if x < _EXP_UNDERFLOW else math.exp(x)
            s[0] = _pairwise_sum(e)
        else:  # NumPy adds slot after slot
            s[:] = 0.0
            for q in range(Q):
                for j in range(J):
                    x = logq[p, q, j] - mx[j]
                    if not x < _EXP_UNDERFLOW:  # adding an exact 0 changes nothing: no exp
                        s[j] += math.exp(x)
        for j in range(J):
            out[p, j] = mx[j] + math.log(s[j])


@nb.njit(cache=True, error_model="numpy")
def _corrected_components(mask: np.ndarray, missed_w: np.ndarray, logq: np.ndarray, lpsi: np.ndarray,
                          m: np.ndarray, P: np.ndarray, det_index: np.ndarray, m_post: np.ndarray,
                          P_post: np.ndarray, pd_beta: np.ndarray, beta: bool, prune: float, dense: bool,
                          label: np.ndarray) -> tuple:
    """The components of paper eq. (5) for each particle ``p`` (see :func:`corrected_gm`).

    Missed detections ``(1 - p_D) w`` with the predicted moments (slots ``q``), then one updated
    Gaussian per ``(q, j)``: weight ``exp(logq - log psi(z_j)) = p_D w N(z_j) / psi(z_j)``, moments
    from the innovation (``det_index[p, q] >= 0``) or the predicted ones (``p_D = 0``). ``dense``:
    every live slot at its fixed place ``q`` / ``Q + q J + j``; else only weights ``>= prune``,
    compacted in that order (a first pass counts them). ``label (P, Q)``: slot labels, or ``(0, 0)``
    for none. Returns ``(w, m, P, mask, pd_beta, label, mass, finite)``: dead slots hold 0 / I / (1, 1) / -1
    (``label (P, K)``, each component its slot ``q``'s; ``(0, K)`` without labels); ``mass (P,)``: the
    sum of each particle's weights (NumPy's ``w.sum(-1)``, :func:`_pairwise_sum`; dead slots hold 0);
    ``finite`` is False if a written value is not.
    """
    Pn, Q, d = m.shape
    J = logq.shape[2]
    log_prune = math.log(prune) if prune > 0.0 else -np.inf
    K = Q * (1 + J)
    if not dense:
        K = 0
        for p in range(Pn):
            k = 0
            for q in range(Q):
                if mask[p, q]:
                    k += missed_w[p, q] >= prune
                    for j in range(J):
                        k += logq[p, q, j] - lpsi[p, j] >= log_prune
            K = max(K, k)
    out_w = np.zeros((Pn, K))
    out_m = np.zeros((Pn, K, d))
    out_P = np.empty((Pn, K, d, d))
    out_mask = np.zeros((Pn, K), np.bool_)
    out_beta = np.ones((Pn if beta else 0, K, 2))
    lab = label.shape[0] > 0
    out_label = np.full((Pn if lab else 0, K), -1, np.int64)
    mass = np.empty(Pn)
    finite = _write_corrected(mask, missed_w, logq, lpsi, m, P, det_index, m_post, P_post, pd_beta, beta, prune,
                              dense, label, out_w, out_m, out_P, out_mask, out_beta, out_label)
    for p in range(Pn):
        mass[p] = _pairwise_sum(out_w[p])
    return out_w, out_m, out_P, out_mask, out_beta, out_label, mass, finite


@batch_kernel
def _write_corrected(mask: np.ndarray, missed_w: np.ndarray, logq: np.ndarray, lpsi: np.ndarray, m: np.ndarray,
                     P: np.ndarray, det_index: np.ndarray, m_post: np.ndarray, P_post: np.ndarray,
                     pd_beta: np.ndarray, beta: bool, prune: float, dense: bool, label: np.ndarray,
                     out_w: np.ndarray, out_m: np.ndarray, out_P: np.ndarray, out_mask: np.ndarray,
                     out_beta: np.ndarray, out_label: np.ndarray) -> bool:
    """The component loop of :func:`_corrected_components` into its allocated outputs (``out_w``,
    ``out_m``, ``out_mask`` zeroed, ``out_beta`` ones, ``out_label`` -1); returns ``finite``."""
    Pn, Q, d = m.shape
    J = logq.shape[2]
    K = out_w.shape[1]
    log_prune = math.log(prune) if prune > 0.0 else -np.inf
    lab = label.shape[0] > 0
    finite = True
    jr = P_post.shape[1] > 1  # one posterior covariance per measurement
    for p in range(Pn):
        k = 0
        for q in range(Q):  # missed detections, predicted moments
            if not mask[p, q] or not (dense or missed_w[p, q] >= prune):
                continue
            at = q if dense else k
            finite &= _put(out_w, out_m, out_P, out_mask, p, at, missed_w[p, q], m[p, q], P[p, q])
            if beta:
                out_beta[p, at, 0], out_beta[p, at, 1] = missed_beta(pd_beta[p, q, 0], pd_beta[p, q, 1],
                                                                     det_index[p, q] >= 0)
            if lab:
                out_label[p, at] = label[p, q]
            k += 1
        for q in range(Q):  # detections of z_j, CKF posterior (predicted moments and weight 0 if p_D = 0)
            if not mask[p, q]:
                continue
            n = det_index[p, q]
            for j in range(J):
                logw = logq[p, q, j] - lpsi[p, j]
                if not (dense or logw >= log_prune):  # the prune test in the log domain: exp only when kept
                    continue
                at = Q + q * J + j if dense else k
                if n >= 0:
                    finite &= _put(out_w, out_m, out_P, out_mask, p, at, math.exp(logw), m_post[n, j],
                                   P_post[n, j if jr else 0])
                else:
                    finite &= _put(out_w, out_m, out_P, out_mask, p, at, math.exp(logw), m[p, q], P[p, q])
                if beta:
                    out_beta[p, at, 0], out_beta[p, at, 1] = detected_beta(pd_beta[p, q, 0], pd_beta[p, q, 1])
                if lab:
                    out_label[p, at] = label[p, q]
                k += 1
        for at in range(K):  # dead slots: identity covariance
            if not out_mask[p, at]:
                for i in range(d):
                    for e in range(d):
                        out_P[p, at, i, e] = 1.0 if i == e else 0.0
    return finite


@nb.njit(cache=True, error_model="numpy", inline="always")
def _put(out_w: np.ndarray, out_m: np.ndarray, out_P: np.ndarray, out_mask: np.ndarray, p: int, at: int,
         w: float, m: np.ndarray, P: np.ndarray) -> bool:
    """Write component ``(w, m, P)`` at slot ``at`` of particle ``p``; False if a value is not finite."""
    out_w[p, at] = w
    out_mask[p, at] = True
    ok = np.isfinite(w)
    for i in range(m.shape[0]):
        out_m[p, at, i] = m[i]
        ok = ok and np.isfinite(m[i])
        for e in range(m.shape[0]):
            out_P[p, at, i, e] = P[i, e]
            ok = ok and np.isfinite(P[i, e])
    return ok


@nb.njit(cache=True)
def _mass_bound_holds(pred: np.ndarray, corr: np.ndarray, n_meas: float, rtol: float) -> bool:
    """Whether ``corr[p] <= (pred[p] + n_meas) (1 + rtol)`` for every particle (``(P,)`` masses; NaN
    fails): the test of :func:`check_phd_mass`, same arithmetic, without its NumPy temporaries."""
    for p in range(pred.shape[0]):
        if not corr[p] <= (pred[p] + n_meas) * (1.0 + rtol):
            return False
    return True
