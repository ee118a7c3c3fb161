"""GM-PHD map correction for the RBPF: paper eqs. (5), (10) and the particle weight (6).

Everything is batched over particles ``P`` x Gaussians ``Q`` x measurements ``J`` with padded
arrays (:class:`~mmslam.slam.core.gm.GM`, batch shape ``(P,)``). Frames and units: global frame,
metres, radians; a measurement is ``z = [TOA (m, incl. clock bias), AOD az, AOD el, AOA az
(body frame), AOA el]`` (:mod:`mmslam.slam.models.measurement`).

:func:`correct` is the whole correction. The measurement update of one landmark Gaussian is the
cubature Kalman filter step of :func:`mmslam.slam.phd.ckf.ckf_update` (6 cubature points of the
position marginal for every map type; a 7-D VS Gaussian ``[x, y, z, vx, vy, vz, xi]`` is
corrected in velocity and turn rate through the cross-covariance). The known BS is a single
fixed landmark (weight 1, no map): it only adds ``p_D N(z; h(s_p, b), R)`` to ``psi(z)``.

The loops over particles, Gaussians and measurements are compiled (numba ``njit``,
``cache=True``), one kernel per stage and map type: :func:`type_terms` (the CKF of every
detectable Gaussian, compiled once per path geometry like :data:`mmslam.slam.phd.ckf._CKF_BATCH`, since
a kernel inlining :func:`~mmslam.slam.phd.ckf.ckf_update` for every geometry takes ~18 s to compile),
:func:`_logsumexp_slots` / :func:`log_psi` and :func:`corrected_gm`. Only ``pd_fn`` (NumPy) and
the error messages run in Python.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Mapping

import numpy as np

from ..core.gm import GM
from ..core.linalg import safe_cholesky
from ..models.measurement import MEAS_DIM, LandmarkKind, check_geometry
from .ckf import BAD_INNOVATION_COV, BAD_POSITION_COV, Innovation, body_array, workspace
from .association import exclusive_terms
from .detection import bernoulli_missed_weight, detection_shares, expected_pd
from .follow import offset_position, own_covariance, weight_mixture
from .invariant import PHD_MASS_RTOL, check_phd_mass  # noqa: F401 (gmphd.check_phd_mass: correct() calls it)
from .tail import read_pairs, tail_loglik, tail_mixture
from .terms import (_TYPE_TERMS, _bs_loglik, _corrected_components, _detection_slots,  # noqa: F401
                    _log_psi_parts, _lse_slots_kernel, _write_corrected)


def correct(maps: dict[int, GM], states: np.ndarray, Z: np.ndarray, R: np.ndarray, bs: np.ndarray,
            pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray], p_bs: np.ndarray, log_clutter: float,
            prune: float | None, extents: dict[int, np.ndarray | None], step: int,
            kinds: Mapping[int, LandmarkKind],
            bodies: Mapping[int, np.ndarray | None] | None = None,
            missed: Mapping[int, str] | None = None,
            association: Mapping[int, str] | None = None,
            tails: Mapping[int, tuple[float, float]] | None = None,
            follows: Mapping[int, float] | None = None,
            weight_offsets: Mapping[int, float] | None = None,
            weight_shares: Mapping[int, float] | None = None) -> tuple[dict[int, GM], np.ndarray, np.ndarray]:
    """The PHD correction of every map of every particle with one measurement set.

    For each particle ``p`` with vehicle state ``s_p`` and each map type ``t`` (predicted
    intensity ``D_t``, a Gaussian mixture), paper eq. (5) (the static maps; the VS map, eq. (10),
    has the same form):

        ``D_t^+(x) = (1 - p_D(x)) D_t(x) + sum_j p_D(x) N(z_j; h_t(s_p, x), R_j) D_t(x) / psi(z_j)``,
        ``psi(z_j) = c(z_j) + p_D,BS N(z_j; h(s_p, b), R_j) + sum_t int p_D N(z_j; h_t(s_p, x), R_j) D_t(x) dx``.

    Steps:

    1. detection probabilities ``p_D`` at the Gaussian means (``pd_fn``, NumPy, once per type);
       with a Beta model (``g.pd_beta``) ``E[p_D] = s / (s + t)`` inside the FOV;
    2. per particle, type and live Gaussian with ``p_D > 0``: the CKF update by every measurement
       (:func:`mmslam.slam.phd.ckf.ckf_update`) and ``log(p_D w N(z_j; zhat, S))``
       (:func:`type_terms`); the BS term ``log(p_D,BS N(z_j; h(s_p, b), R_j))`` (:func:`bs_logterm`);
       a Gaussian with ``p_D = 0`` gets no update and keeps its whole weight as missed detection;
    3. ``log psi(z_j)`` per particle: log-sum-exp over clutter, BS and every Gaussian of every type
       (:func:`log_psi`);
    4. the corrected components, the two terms of ``D_t^+``: ``(1 - p_D) w`` (or, for a type with
       ``missed[t] = "bernoulli"``, :func:`~mmslam.slam.phd.detection.bernoulli_missed_weight` with the Gaussian's
       detection shares ``p_D w N(z_j) / psi(z_j)`` of this scan) with the predicted
       moments and ``p_D w N(z_j) / psi(z_j)`` with the CKF posterior, those below ``prune`` never
       materialised (:func:`corrected_gm`; Beta model: missed ``(s, t + 1)``, detected ``(s + 1, t)``);
    5. the PHD-mass invariant ``sum w^+ <= sum w + J`` per particle (:func:`check_phd_mass`);
    6. the particle weight, eq. (6): the paper writes ``sum_j psi(z_j)``; mmslam multiplies the
       weight by ``prod_j psi(z_j)`` as the authors' code does (docs/implementation-notes.md): the
       caller adds ``log psi(z).sum(1)`` (returned here) to the log-weights. With a weight offset
       ``F_w`` of a type (``weight_offsets``), the ``psi`` returned takes that type's detected terms with
       ``P + F_w`` on the position (:func:`type_terms` of the map so widened), mixed with the map's own at a
       share ``lambda`` (``weight_shares``, :func:`~mmslam.slam.phd.follow.weight_mixture`; one type offset:
       ``psi_lambda = (1 - lambda) psi + lambda psi_w``; the likelihoods only, ``posteriors=False``); steps 3-4
       use the map's own.

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
        kinds: type code -> its :class:`~mmslam.slam.models.measurement.LandmarkKind` (e.g. its spec):
            the geometry of its measurement kernel and its name in messages (every key of ``maps``).
        bodies: type code -> ``(4,)`` car body of :func:`type_terms` or None (point landmark; None: every type).
        missed: type code -> the missed-detection rule of :func:`type_terms` (``phd`` or ``bernoulli``;
            None or a type not in it: ``phd``).
        association: type code -> ``phd`` (the shares of eq. (5)) or ``exclusive`` (each Gaussian one landmark
            with at most one measurement: the detected and missed weights of
            :func:`~mmslam.slam.phd.association.exclusive_terms`; None or a type not in it: ``phd``).
        tails: type code -> ``(e, K)``, the heavy tail of the type's likelihood
            (:func:`~mmslam.slam.phd.tail.tail_mixture`; None or a type not in it or ``e = 0``: Gaussian; without a
            follow offset its moment match is made in step 4, for the components kept only).
        follows: type code -> ``F`` (m^2), the follow offset of the type's update (:func:`type_terms`; None or a
            type not in it: 0).
        weight_offsets: type code -> ``F_w`` (m^2 per axis, ``filter.types.<T>.weight_std`` squared): the offset
            of the type's detected terms in the particle weight only (step 6; None or a type not in it: 0).
        weight_shares: type code -> ``lambda`` in ``[0, 1]`` (``filter.types.<T>.weight_share``), the share of that
            offset in the weight's likelihood of the type (None or a type not in it: 1, the offset alone; 0: the
            offset's terms are not computed).

    Returns:
        The corrected maps (same keys), ``log psi (P, J)`` of the particle weight (step 6) and ``log psi (P, J)`` of
        the maps' own terms (step 3; the same array without a weight offset).

    Raises:
        FloatingPointError: a non-finite or non-positive-definite covariance, ``psi(z) = 0``, or a
            broken PHD-mass invariant.
        ValueError: ``R``, ``Z``, ``states``, ``bs`` or an array of a map of another shape.
    """
    J = Z.shape[0]
    bs_term = bs_logterm(states, Z, R, bs, np.asarray(p_bs, float))  # 2. (BS)
    bodies, missed, association, tails = bodies or {}, missed or {}, association or {}, tails or {}
    follows = follows or {}
    for t in maps:
        if association.get(t, "phd") not in ("phd", "exclusive"):
            raise ValueError(f"association {association[t]!r}: expected 'phd' or 'exclusive'")
    exclusive = {t for t in maps if association.get(t, "phd") == "exclusive"}
    # an exclusive type's detected weights are not the shares: no skip floors (a tail's match waits for them, step 4)
    terms = [type_terms(g, kinds[t], states, Z, R, bs, pd_fn, extents.get(t), log_clutter,
                        None if t in exclusive else prune, bodies.get(t), missed.get(t, "phd"), tails.get(t),
                        follows.get(t, 0.0), defer_tail=True)
             for t, g in maps.items()]  # 1.-2.
    lpsi = log_psi(terms, bs_term, log_clutter, (states.shape[0], J))  # 3.
    shares = weight_shares or {}
    offsets = {t: float(f) for t, f in (weight_offsets or {}).items()
               if t in maps and f > 0.0 and shares.get(t, 1.0) > 0.0}  # a share 0: the weight without the offset
    lpsi_w = lpsi
    if offsets and J:  # 6. the weight's terms of those types, before step 4 rewrites the exclusive ones
        off = {t: type_terms(offset_position(maps[t], follows.get(t, 0.0) + f), kinds[t], states, Z, R, bs, pd_fn,
                             extents.get(t), log_clutter, None if t in exclusive else prune, bodies.get(t),
                             missed.get(t, "phd"), tails.get(t), posteriors=False) for t, f in offsets.items()}
        lpsi_w = log_psi([tc if tc.lm_type not in off else
                          replace(off[tc.lm_type], logq=weight_mixture(tc.logq, off[tc.lm_type].logq,
                                                                       shares.get(tc.lm_type, 1.0)))
                          for tc in terms], bs_term, log_clutter, lpsi.shape)
    out = {}  # 4. each exclusive type's other explanations from every type's own terms, before any is rewritten
    others = {tc.lm_type: _log_others(terms, tc, bs_term, log_clutter, lpsi.shape) for tc in terms
              if tc.lm_type in exclusive and J}
    for tc in terms:
        if tc.lm_type in others:  # 4. one measurement per landmark: BP marginals as detected weights
            det, miss = exclusive_terms(np.where(tc.g.mask, tc.g.w, 0.0), np.where(tc.g.mask, tc.pd, 0.0), tc.logq,
                                        others[tc.lm_type], lpsi, tc.missed)
            with np.errstate(divide="ignore"):
                tc.logq = np.where(det > 0.0, np.log(np.where(det > 0.0, det, 1.0)), -np.inf) + lpsi[:, None, :]
            tc.missed_w = np.where(tc.g.mask, miss, tc.missed_w)
        elif tc.missed == "bernoulli":  # 4. a confirmed landmark (w >= 1) keeps its mass through the scan
            tc.missed_w = np.where(tc.g.mask, bernoulli_missed_weight(tc.g.w, tc.pd, detection_shares(tc.logq, lpsi)),
                                   tc.missed_w)
        g, mass = _corrected_gm(tc, Z, lpsi, prune, (J, tc.name, step))  # 4.
        check_phd_mass(tc.g, g, J, tc.name, step,
                       masses=None if tc.pred_mass is None else (tc.pred_mass, mass))  # 5.
        out[tc.lm_type] = g
    return out, lpsi_w, lpsi


def _log_others(terms: list[TypeCorrection], tc: TypeCorrection, bs_term: np.ndarray | None, log_clutter: float,
                shape: tuple[int, int]) -> np.ndarray:
    """``log c_j (P, J)``: every explanation of ``z_j`` but ``tc``'s Gaussians (clutter, BS, the other types),
    ``-inf`` where there is none (the exclusive association's clutter)."""
    out = np.full(shape, float(log_clutter))
    if bs_term is not None:
        out = np.logaddexp(out, np.asarray(bs_term, float))
    for t in terms:
        if t is not tc and t.logq.shape[1]:
            out = np.logaddexp(out, _logsumexp_slots(t.logq))
    return out


def _per_measurement_cov(R: np.ndarray, J: int) -> np.ndarray:
    """``R`` as a C-contiguous ``(1, 5, 5)`` (one covariance for all) or ``(J, 5, 5)`` array; ValueError else."""
    R = np.asarray(R, float)
    if R.shape == (MEAS_DIM, MEAS_DIM):
        R = R[None]
    elif R.shape != (J, MEAS_DIM, MEAS_DIM):
        raise ValueError(f"R has shape {R.shape}; expected (5, 5) or ({J}, 5, 5)")
    return np.ascontiguousarray(R)


@dataclass
class TypeCorrection:
    """Intermediate per-type correction terms: detection terms and innovation.

    ``logq (P, Q, J)``: ``log(p_D w N(z_j; zhat, S))`` (``-inf`` where masked or ``p_D = 0``);
    ``missed_w (P, Q)``: ``(1 - p_D) w`` (``missed = "bernoulli"``: :func:`~mmslam.slam.phd.detection.bernoulli_missed_weight`
    without the scan; :func:`correct` gives it the scan's detection shares); ``pd (P, Q)``: the ``p_D`` of each
    Gaussian; ``det_index (P, Q)``: index of the Gaussian in the innovation ``inn`` (``-1`` where masked or
    ``p_D = 0``: no innovation is computed for a Gaussian that cannot be detected, its detection terms are exactly
    zero); ``deferred_tail``: None, or the heavy tail's update with ``K P`` (an :class:`Innovation` shaped as ``inn``)
    and ``e``, moment-matched with ``inn`` (then the update with ``P``) by :func:`corrected_gm` (``defer_tail``).

    ``pred_mass (P,)``: the predicted mass ``sum_q w`` of the live slots (:func:`check_phd_mass`),
    computed by :func:`type_terms` (None for a hand-made one). ``lm_type``: the type's code (as
    passed to ``pd_fn``, the key of its map); ``name``: its name in messages.
    """

    g: GM
    lm_type: int
    logq: np.ndarray
    missed_w: np.ndarray
    inn: Innovation
    det_index: np.ndarray
    pred_mass: np.ndarray | None = None
    name: str = ""
    pd: np.ndarray | None = None
    missed: str = "phd"
    deferred_tail: tuple[Innovation, float] | None = None

    def __post_init__(self) -> None:
        if not self.name:
            self.name = f"type {self.lm_type}"


def type_terms(g: GM, kind: LandmarkKind, states: np.ndarray, Z: np.ndarray, R: np.ndarray,
               bs: np.ndarray, pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
               extent: np.ndarray | None = None, log_clutter: float = -np.inf,
               prune: float | None = None, body: np.ndarray | None = None, missed: str = "phd",
               tail: tuple[float, float] | None = None, follow: float = 0.0,
               posteriors: bool = True, defer_tail: bool = False) -> TypeCorrection:
    """Detection terms of one map type (compiled loop over particles, Gaussians and measurements).

    Only the live Gaussians with ``p_D > 0`` (inside the FOV) get the CKF update
    (:func:`mmslam.slam.phd.ckf.ckf_update`, in the kernel of the type's geometry; numbered ``n`` in
    particle-major order, ``det_index``); the others keep ``logq = -inf`` and their full weight as
    missed detection, exactly as the dense formula gives with ``p_D = 0``.

    Args:
        g: predicted map of this type, batch ``(P,)``, ``Q`` slots, dim 3 (VA/SP) or 7 (VS).
        kind: the type (:class:`~mmslam.slam.models.measurement.LandmarkKind`, e.g. its spec): its
            ``geometry`` picks the kernel, its ``code`` goes to ``pd_fn``, its ``name`` to messages.
        states: ``(P, 7)`` particle vehicle states.
        Z: ``(J, 5)`` measurements of this vehicle and step; R: ``(5, 5)`` or ``(J, 5, 5)``.
        bs: ``(3,)`` BS position (m).
        pd_fn: ``pd_fn(vehicle_pos (P, Q, 3), lm_pos (P, Q, 3), lm_type) -> (P, Q)`` detection
            probability evaluated at the Gaussian means; with ``g.pd_beta`` (``filter.pd_model =
            "beta"``) only its FOV gate (``> 0``) is used and ``p_D = s / (s + t)`` of each
            Gaussian's own Beta (:func:`mmslam.slam.phd.detection.expected_pd`).
        extent: ``(3, 3)`` scatter-point covariance of an extended landmark (VS: a car body), see
            :func:`mmslam.slam.phd.ckf.ckf_update`; None for point landmarks.
        body: ``(4,)`` car body ``[length, width, height, depth]`` (m) of a VS, the path bouncing at its
            specular point (:func:`mmslam.slam.models.vs.body_specular_point`); None for point landmarks.
        log_clutter, prune: with a clutter intensity (``log_clutter > -inf``) and a prune threshold
            ``> 0`` of the corrected components (:func:`corrected_gm`), work whose result cannot
            matter is skipped (:func:`_skip_floors`): a term ``log(p_D w N(z_j))`` below
            ``log c(z) - 40`` (less than ``4.3e-18`` of ``psi(z_j) >= c(z)``) is set to ``-inf``,
            and the posterior mean of a term that :func:`corrected_gm` will prune is not computed
            (its ``m_post`` row starts with NaN). The defaults compute everything.
        missed: the missed-detection weight: ``phd``, ``(1 - p_D) w`` (eq. (5)), or ``bernoulli``, the Gaussian
            as one landmark that exists with probability ``min(w, 1)``
            (:func:`~mmslam.slam.phd.detection.bernoulli_missed_weight`).
        tail: ``(e, K)`` with ``e > 0``: the likelihood of ``z_j`` given the Gaussian is the scale mixture
            ``(1 - e) N(z_j; zhat, S(P)) + e N(z_j; zhat, S(K P))`` (:func:`~mmslam.slam.phd.tail.tail_mixture`;
            ``filter.types.<T>.tail_weight``, ``tail_scale``); None or ``e = 0``: the Gaussian likelihood of eq. (5).
        follow: ``F`` (m^2 per axis, ``filter.types.<T>.follow_std`` squared): the update's gain and likelihood
            take the position covariance ``P + F I``, the image point seen departing from the mapped one by a fresh
            offset the estimate follows; the posterior covariance is the estimate's own for that gain
            (:func:`~mmslam.slam.phd.follow.own_covariance`), a missed Gaussian keeps ``P``. 0: the update of eq. (5).
        posteriors: False: only the terms ``logq`` (the particle weight's, :func:`correct` step 6); no posterior mean
            is computed (``m_post`` rows start with NaN) and the heavy tail gives its likelihood alone
            (:func:`~mmslam.slam.phd.tail.tail_loglik`: ``inn.P_post`` is the core update's).
        defer_tail: with a tail and no ``follow``: the tail's moment match is left to :func:`corrected_gm` (the
            components it keeps only); ``inn`` is the update with ``P``, ``deferred_tail`` the one with ``K P``.

    Returns:
        The :class:`TypeCorrection`; its ``g`` holds C-contiguous copies (or the arrays themselves)
        of the map (with its ``pd_beta`` and ``label``: :func:`corrected_gm` carries them), its ``inn``
        the posteriors of the ``N`` detectable Gaussians: ``loglik (N, J)``, ``m_post (N, J, d)``,
        ``P_post (N, 1 or J, d, d)`` (``posteriors=False``: means NaN; ``defer_tail``: the update with ``P``);
        its ``pred_mass (P,)``.

    Raises:
        FloatingPointError: a non-finite mean or covariance in the map (also outside the FOV and in
            masked slots, which hold 0 / I; checked after ``pd_fn``, which may see it),
            or a covariance that is not positive definite.
        ValueError: ``R`` or an array of the map, ``states`` or ``bs`` of another shape.
    """
    lm_type, name, geometry = int(kind.code), str(kind.name), check_geometry(kind.geometry)
    J = Z.shape[0]
    R = _per_measurement_cov(R, J)
    c = np.ascontiguousarray
    g = GM(c(g.w, dtype=float), c(g.m, dtype=float), c(g.P, dtype=float), c(g.mask, dtype=bool), g.pd_beta,
           g.label)
    P_, Q, d = g.m.shape
    own = g  # the map as it is: a missed Gaussian keeps it; the update below may see it with the follow offset
    g = offset_position(own, follow)
    beta_shape = None if g.pd_beta is None else np.shape(g.pd_beta)
    label_shape = None if g.label is None else np.shape(g.label)
    if (d < 3 or g.P.shape != (P_, Q, d, d) or g.w.shape != (P_, Q) or g.mask.shape != (P_, Q)
            or np.shape(states) != (P_, 7) or np.shape(bs) != (3,) or beta_shape not in (None, (P_, Q, 2))
            or label_shape not in (None, (P_, Q))):
        raise ValueError(f"{name} correction: shapes w {g.w.shape}, m {g.m.shape}, P {g.P.shape}, "
                         f"states {np.shape(states)}, bs {np.shape(bs)}, pd_beta {beta_shape}, label {label_shape}; "
                         f"expected (P, Q), (P, Q, d >= 3), (P, Q, d, d), (P, 7), (3,), None or (P, Q, 2), "
                         f"None or (P, Q)")
    pd = pd_fn(np.broadcast_to(states[:, None, 0:3], g.m.shape[:-1] + (3,)), g.m[..., 0:3], lm_type)
    if g.pd_beta is not None:  # the Beta-Gaussian PHD: E[p_D] = s / (s + t) inside the FOV
        pd = expected_pd(pd, g.pd_beta)
    pd = np.asarray(pd, dtype=float)
    pd = c(pd if pd.shape == g.w.shape else np.broadcast_to(pd, g.w.shape))
    ext = np.zeros((3, 3)) if extent is None else c(np.asarray(extent, float).reshape(3, 3))
    det_index, missed_w, logq = np.empty((P_, Q), np.int64), np.empty((P_, Q)), np.empty((P_, Q, J))
    pred_mass = np.empty(P_)
    n = _detection_slots(g.mask, g.w, pd, g.m, g.P, det_index, missed_w, logq, pred_mass)
    if n < 0:
        raise FloatingPointError(f"non-finite mean or covariance in {name} correction")
    if missed == "bernoulli":  # without the scan; correct() takes a confirmed one's detection shares out of it
        missed_w = np.where(g.mask, bernoulli_missed_weight(g.w, pd), missed_w)
    elif missed != "phd":
        raise ValueError(f"missed-detection rule {missed!r}: expected 'phd' or 'bernoulli'")
    loglik, m_post, P_post = np.empty((n, J)), np.empty((n, J, d)), np.empty((n, R.shape[0], d, d))
    tailed = tail is not None and tail[0] > 0.0
    floor_q, floor_post = (-np.inf, -np.inf) if tailed else _skip_floors(log_clutter, prune)  # a mixture: no skips
    floor_post = floor_post if posteriors else np.inf
    code = _TYPE_TERMS[geometry](g.w, pd, g.m, g.P, c(states, dtype=float), c(bs, dtype=float), ext, body_array(body),
                                             c(np.reshape(Z, (J, MEAS_DIM)), dtype=float), R, det_index, logq,
                                             loglik, m_post, P_post, floor_q, floor_post, workspace(d))
    _raise_on(code, name)
    inn, pending = Innovation(loglik, m_post, P_post), None
    if tailed and n and J:
        e, K = float(tail[0]), float(tail[1])
        wide = Innovation(np.empty((n, J)), np.empty((n, J, d)), np.empty((n, R.shape[0], d, d)))
        _raise_on(_TYPE_TERMS[geometry](g.w, pd, g.m, c(g.P * K), c(states, dtype=float), c(bs, dtype=float), ext,
                                        body_array(body), c(np.reshape(Z, (J, MEAS_DIM)), dtype=float), R, det_index,
                                        np.empty((P_, Q, J)), wide.loglik, wide.m_post, wide.P_post, -np.inf,
                                        floor_post, workspace(d)), name)
        mixed = tail_loglik(loglik, wide.loglik, e)  # logq = log(p_D w) + log of the mixture likelihood
        if posteriors and defer_tail and follow == 0.0:  # corrected_gm moment-matches the components it keeps
            pending = (wide, e)
        else:
            inn = tail_mixture(inn, wide, e) if posteriors else Innovation(mixed, m_post, P_post)
        logq[det_index >= 0] += (mixed - loglik)[det_index[det_index >= 0]]
    if follow > 0.0 and n and J:  # J = 0: no detected term reads the posteriors
        rows = det_index >= 0
        P0, Pf = np.empty((n, d, d)), np.empty((n, d, d))
        P0[det_index[rows]], Pf[det_index[rows]] = own.P[rows], g.P[rows]
        inn = Innovation(inn.loglik, inn.m_post, own_covariance(P0, Pf, inn.P_post))
    return TypeCorrection(own, lm_type, logq, missed_w, inn, det_index, pred_mass, name, pd, missed, pending)


def _raise_on(code: int, name: str) -> None:
    """The FloatingPointError of a failure code of the CKF kernels (``OK``: nothing)."""
    if code == BAD_POSITION_COV:
        raise FloatingPointError(f"covariance not positive definite in {name} correction")
    if code == BAD_INNOVATION_COV:
        raise FloatingPointError(
            f"covariance not positive definite in {name} correction (innovation covariance)")


NEGLIGIBLE_LOG = -40.0
"""A detection term ``q`` with ``log q < log c(z) + NEGLIGIBLE_LOG`` is dropped from ``psi(z) >= c(z)``
(``e^-40 = 4.2e-18``: far below the 1e-9 relative tolerance of results, even summed over a map)."""


def _skip_floors(log_clutter: float, prune: float | None) -> tuple[float, float]:
    """``(floor_q, floor_post)`` of :func:`_type_terms_loop`: the ``log q`` below which a term is
    negligible in ``psi`` (set to ``-inf``) and below which its posterior mean is never read.

    A corrected component ``(q, j)`` is kept iff ``log q - log psi(z_j) >= log prune``
    (:func:`_corrected_components`) and ``psi >= c``, so ``log q < log c + log prune`` is
    pruned; 1e-9 of margin covers the rounding of ``log psi`` (a few ulp). Without clutter, or
    without pruning (``prune`` None or 0: every component is materialised, its moments read),
    both floors are ``-inf``.
    """
    if prune is None or not prune > 0.0 or not log_clutter > -np.inf:
        return -np.inf, -np.inf
    return log_clutter + NEGLIGIBLE_LOG, log_clutter + math.log(prune) - 1e-9


def bs_logterm(states: np.ndarray, Z: np.ndarray, R: np.ndarray, bs: np.ndarray,
               p_d: np.ndarray) -> np.ndarray:
    """``log(p_D N(z_j; h(s_p, b, BS), R))`` for the known BS, shape ``(P, J)``.

    ``p_d`` is ``(P,)``: the BS detection probability for each particle. ``states (P, 7)``,
    ``Z (J, 5)``, ``bs (3,)``; ``R``: ``(5, 5)``, or ``(J, 5, 5)`` one covariance per measurement.

    Raises:
        ValueError: an array of another shape (checked before the compiled loop, which reads
            ``R[j]``, ``states[p]`` and ``bs`` unchecked).
    """
    J = Z.shape[0]
    R = _per_measurement_cov(R, J)
    if (np.ndim(states) != 2 or np.shape(states)[1] != 7 or np.shape(bs) != (3,)
            or (J and np.shape(Z) != (J, MEAS_DIM))):  # an empty Z of any shape is no measurement
        raise ValueError(f"BS likelihood: shapes states {np.shape(states)}, Z {np.shape(Z)}, bs {np.shape(bs)}; "
                         f"expected (P, 7), (J, 5), (3,)")
    if J == 0:  # no measurements
        return np.zeros((states.shape[0], 0))
    L = safe_cholesky(R, "BS likelihood")
    ll = np.empty((states.shape[0], J))
    _bs_loglik(np.ascontiguousarray(states, dtype=float), np.ascontiguousarray(Z, dtype=float), L,
               np.ascontiguousarray(bs, dtype=float), ll, np.empty(MEAS_DIM), np.empty(MEAS_DIM), np.empty(len(L)))
    with np.errstate(divide="ignore"):
        return np.log(p_d)[:, None] + ll


def log_psi(terms: list[TypeCorrection], bs_term: np.ndarray | None, log_clutter: float,
            shape: tuple[int, int]) -> np.ndarray:
    """``log psi(z_j) = log(c(z) + sum_types sum_q q + BS term)``, shape ``(P, J)`` (log-sum-exp).

    The sum over the Gaussians of each type is :func:`_logsumexp_slots`; then the parts (clutter,
    BS, types) are combined by a stable log-sum-exp (their maximum factored out).

    Raises FloatingPointError if some ``psi(z)`` is zero or non-finite (e.g. no clutter and no
    landmark can explain a measurement).
    """
    parts = [_logsumexp_slots(t.logq) for t in terms if t.logq.shape[1]]
    if bs_term is not None:
        parts.insert(0, np.asarray(bs_term, float))
    out = np.empty(shape)
    if not _log_psi_parts(float(log_clutter), np.stack(parts) if parts else np.empty((0,) + tuple(shape)), out):
        raise FloatingPointError("psi(z) is zero or non-finite in the PHD correction "
                                 "(no clutter and no landmark explains a measurement)")
    return out


def _logsumexp_slots(logq: np.ndarray) -> np.ndarray:
    """``log sum_q exp(logq[:, q, :])`` of ``logq (P, Q, J)`` -> ``(P, J)`` (``-inf`` if all are).

    Compiled (:func:`_lse_slots_kernel`); ``logq`` is never written (the caller,
    :func:`corrected_gm`, reads it again). Bit for bit NumPy's ``max`` / ``exp`` / ``sum(axis=1)``
    (pairwise summation for ``J = 1``, where NumPy's sum runs along the slots); the terms whose
    ``exp`` underflows to 0 (most: the measurements a Gaussian does not explain) skip the ``exp``.
    """
    P_, Q, J = logq.shape
    out = np.empty((P_, J))
    _lse_slots_kernel(np.ascontiguousarray(logq, dtype=float), out)
    return out


def corrected_gm(t: TypeCorrection, Z: np.ndarray, logpsi: np.ndarray, prune: float | None = None,
                 mass_check: tuple[int, str, int] | None = None) -> GM:
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
    (:func:`mmslam.slam.phd.detection.missed_beta`: ``(s, t + 1)`` inside the FOV, ``(s, t)``
    outside; :func:`~mmslam.slam.phd.detection.detected_beta`: ``(s + 1, t)``; dead slots (1, 1)).
    A map with labels (``g.label``): every corrected component, missed or ``(q, j)``, inherits the
    label of its predicted slot ``q`` (dead slots -1).

    ``mass_check = (J, type name, step)``: if a corrected component is not finite, the PHD-mass
    invariant (:func:`check_phd_mass`) is checked first (its message is the more specific one).

    Raises:
        FloatingPointError: a non-finite weight, mean or covariance of a corrected component.
        ValueError: ``logpsi`` not ``(P, J)``.
    """
    return _corrected_gm(t, Z, logpsi, prune, mass_check)[0]


def _corrected_gm(t: TypeCorrection, Z: np.ndarray, logpsi: np.ndarray, prune: float | None,
                  mass_check: tuple[int, str, int] | None) -> tuple[GM, np.ndarray]:
    """:func:`corrected_gm` and the corrected mass ``(P,)`` per particle (live weights summed as
    :func:`check_phd_mass` sums them)."""
    g, inn = t.g, t.inn
    if np.shape(logpsi) != t.logq.shape[::2]:  # the kernel reads logpsi[p, j] unchecked
        raise ValueError(f"logpsi has shape {np.shape(logpsi)}; expected {t.logq.shape[::2]} (P, J)")
    if t.deferred_tail is not None:  # the heavy tail's moment match, of the components kept only
        inn = tail_mixture(inn, *t.deferred_tail, read_pairs(t.logq, logpsi, t.det_index, inn.loglik.shape[0], prune))
    if g.label is not None and np.shape(g.label) != g.w.shape:  # the kernel reads label[p, q] unchecked
        raise ValueError(f"label has shape {np.shape(g.label)}; expected the map's {g.w.shape} (P, Q)")
    c = np.ascontiguousarray
    beta = g.pd_beta is not None
    w, m, Pc, live, pd_beta, label, mass, finite = _corrected_components(
        c(g.mask, dtype=bool), c(t.missed_w, dtype=float), c(t.logq, dtype=float), c(logpsi, dtype=float),
        c(g.m, dtype=float), c(g.P, dtype=float), c(t.det_index, dtype=np.int64), inn.m_post, inn.P_post,
        c(g.pd_beta, dtype=float) if beta else np.ones((0, 0, 2)), beta, 0.0 if prune is None else float(prune),
        prune is None, np.empty((0, 0), np.int64) if g.label is None else c(g.label, dtype=np.int64))
    out = GM(w, m, Pc, live, pd_beta if beta else None, None if g.label is None else label)
    if not finite:
        if mass_check is not None:  # the weights' invariant first: it names the broken step and particle
            check_phd_mass(t.g, out, *mass_check, masses=None if t.pred_mass is None else (t.pred_mass, mass))
        out.check(f"after the {t.name} correction")
        raise FloatingPointError(f"non-finite values after the {t.name} correction")
    return out, mass
