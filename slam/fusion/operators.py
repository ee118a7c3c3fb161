"""Map fusion at the BS (paper Sec. III-B and IV-B) on single Gaussian mixtures.

All mixtures here are single (batch shape ``()``) padded :class:`~mmslam.slam.core.gm.GM`s; only
live slots (``mask``) take part. Positions are the first three state dimensions (global frame,
m); VS states are ``[x, y, z, vx, vy, vz, xi]``. The fusion operators return the *union* of the
two mixtures with fusion weights ``beta`` applied (``w <- beta * w``; ``beta = 0`` drops a
component); the caller reduces the union with :func:`mmslam.slam.phd.reduction.prune_merge`.

Matching. Both operators first form a binary proximity matrix ``C`` (``Q_bs x Q_ue``) from
maximum symmetric Mahalanobis (MSM) distances, then choose a *one-to-one* matching among the
entries with ``C = 1`` with the Hungarian algorithm (:func:`scipy.optimize.linear_sum_assignment`,
maximum number of matched pairs first, then minimum total MSM distance; the paper's footnote
suggests the MSM metric in a Hungarian algorithm). A BS component proximate to several uploaded
components is therefore matched to at most one of them; the others are treated as *unmatched*
(uploaded: weight kept, ``beta = 1``; BS side: the accumulated-FOV rule). Near-duplicates created
that way sit within the merge gate of each other and are merged by the subsequent reduction.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..core.gm import GM, NO_LABEL, symmetrize
from ..core.linalg import spd_inv
from ..models.vs import predict_vs

POS = slice(0, 3)
VEL = slice(3, 6)


def msm_distance(m1: np.ndarray, P1: np.ndarray, m2: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """Maximum symmetric Mahalanobis distance between two sets of Gaussians (paper's ``d_MSM``).

    ``d(q1, q2) = max(D^T P1[q1]^{-1} D, D^T P2[q2]^{-1} D)`` with ``D = m1[q1] - m2[q2]``
    (squared distances, dimensionless).

    Args:
        m1: ``(Q1, d)`` means; P1: ``(Q1, d, d)`` covariances (SPD).
        m2: ``(Q2, d)`` means; P2: ``(Q2, d, d)`` covariances (SPD).

    Returns:
        ``(Q1, Q2)`` distances.
    """
    m1, m2 = np.asarray(m1, float), np.asarray(m2, float)
    q1, q2 = m1.shape[0], m2.shape[0]
    if q1 == 0 or q2 == 0:
        return np.zeros((q1, q2))
    A1, A2 = spd_inv(P1, "MSM distance"), spd_inv(P2, "MSM distance")
    D = m1[:, None, :] - m2[None, :, :]  # (Q1, Q2, d)
    d1 = np.einsum("abi,aij,abj->ab", D, A1, D)
    d2 = np.einsum("abi,bij,abj->ab", D, A2, D)
    return np.maximum(d1, d2)


def in_accumulated_fov(points: np.ndarray, vehicle_positions: np.ndarray, radius: float) -> np.ndarray:
    """Whether points lie in a vehicle's accumulated FOV (paper footnote to eq. (7)).

    With ``p_D`` constant inside the range gate and 0 outside, the accumulated FOV since the
    last upload is the union of balls of radius ``radius`` (m) around the vehicle positions
    visited since then.

    Args:
        points: ``(N, 3)`` positions (global frame, m).
        vehicle_positions: ``(K, 3)`` vehicle positions since the last upload (``K`` may be 0).
        radius: FOV radius in m; ``inf`` (BS / VA types) means every point is inside.

    Returns:
        ``(N,)`` bool.
    """
    pts = np.asarray(points, float).reshape(-1, 3)
    if np.isinf(radius):
        return np.ones(pts.shape[0], bool)
    u = np.asarray(vehicle_positions, float).reshape(-1, 3)
    if u.shape[0] == 0:
        return np.zeros(pts.shape[0], bool)
    d2 = np.sum((pts[:, None, :] - u[None, :, :]) ** 2, axis=-1)
    return np.any(d2 <= radius**2, axis=-1)


def _live(g: GM) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if g.w.ndim != 1:
        raise ValueError(f"fusion works on single mixtures (batch shape ()), got batch shape {g.batch_shape}")
    g.check("in map fusion input")
    idx = np.nonzero(g.mask)[0]
    return idx, g.w[idx], g.m[idx], g.P[idx]


def _match(C: np.ndarray, cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching among ``C == True`` entries: most pairs, then least total ``cost``."""
    if not C.any():
        return np.zeros(0, int), np.zeros(0, int)
    rows = np.nonzero(C.any(1))[0]
    cols = np.nonzero(C.any(0))[0]
    Cs = C[np.ix_(rows, cols)]
    cs = cost[np.ix_(rows, cols)]
    big = 1.0 + float(np.sum(cs[Cs]))  # one forbidden pair costs more than all allowed ones
    r, c = linear_sum_assignment(np.where(Cs, cs, big))
    ok = Cs[r, c]
    return rows[r[ok]], cols[c[ok]]


def _pd_beta(g: GM, n: int) -> np.ndarray | None:
    """The live components' Beta detection parameters ``(n, 2)`` (``GM.pd_beta``), or None."""
    return None if g.pd_beta is None else g.pd_beta[g.mask].reshape(n, 2)


def _label(g: GM, n: int) -> np.ndarray | None:
    """The live components' labels ``(n,)`` (``GM.label``), or None."""
    return None if g.label is None else np.asarray(g.label)[g.mask].reshape(n)


def _join(a: np.ndarray | None, b: np.ndarray | None, na: int, nb: int, fill: np.ndarray, what: str
          ) -> np.ndarray | None:
    """``a`` and ``b`` (per-component arrays of two sets of ``na``, ``nb`` components, or None) joined; None
    if both are; an empty set without one takes ``fill``'s shape. ValueError if a non-empty set lacks it."""
    if a is None and b is None:
        return None
    if (a is None and na) or (b is None and nb):
        raise ValueError(f"cannot fuse a mixture with {what} and one without")
    return np.concatenate([fill if x is None else x for x in (a, b)])


def _union(wb, mb, Pb, beta_b, wu, mu, Pu, beta_u, d, pairs=None, ab_b=None, ab_u=None, lab_b=None, lab_u=None):
    """Union of the two weighted sets, live components only, sorted by weight.

    ``ab_b``, ``ab_u``: the two sets' Beta detection parameters ``(n, 2)`` (or None), ``lab_b``,
    ``lab_u`` their labels ``(n,)`` (or None), carried with their components (an empty set without
    them takes the other's).

    With ``pairs = (r, c)`` (matched BS / uploaded indices into ``wb`` / ``wu``) also returns the
    ``(n, 2)`` slots of each matched pair in the output (pairs with a dropped member are left out).
    """
    w = np.concatenate([wb * beta_b, wu * beta_u])
    m = np.concatenate([mb.reshape(-1, d), mu.reshape(-1, d)])
    P = np.concatenate([Pb.reshape(-1, d, d), Pu.reshape(-1, d, d)])
    keep = w > 0
    order = np.argsort(-w[keep], kind="stable")
    nb_, nu_ = wb.shape[0], wu.shape[0]
    ab = _join(ab_b, ab_u, nb_, nu_, np.ones((0, 2)), "Beta detection parameters")
    lab = _join(lab_b, lab_u, nb_, nu_, np.zeros(0, np.int64), "component labels")
    out = GM(w[keep][order], m[keep][order], symmetrize(P[keep][order]), np.ones(int(keep.sum()), bool),
             None if ab is None else ab[keep][order], None if lab is None else lab[keep][order])
    out.check("after map fusion")
    if pairs is None:
        return out
    slot = np.full(w.shape[0], -1)
    slot[np.nonzero(keep)[0][order]] = np.arange(order.shape[0])
    r, c = (np.asarray(a, int) for a in pairs)
    sp = np.stack([slot[r], slot[wb.shape[0] + c]], axis=1).reshape(-1, 2)
    return out, sp[(sp >= 0).all(axis=1)]


def _check_inside(bs: GM, inside: np.ndarray) -> np.ndarray:
    inside = np.asarray(inside, bool).reshape(-1)
    if inside.shape[0] != bs.capacity:
        raise ValueError(f"ue_fov_inside has {inside.shape[0]} entries, expected one per BS-map slot ({bs.capacity})")
    return inside


def _check_dims(bs: GM, ue: GM) -> int:
    if bs.dim != ue.dim:
        raise ValueError(f"cannot fuse mixtures of dimension {bs.dim} and {ue.dim}")
    return bs.dim


def fuse_aa(bs: GM, ue: GM, ue_fov_inside: np.ndarray, match_threshold: float,
            with_pairs: bool = False, weights: str = "equal") -> GM | tuple[GM, np.ndarray]:
    """TWC2020 arithmetic-average fusion ``F_AA`` of the BS map and an uploaded averaged map.

    Proximity: ``C[q1, q2] = 1`` iff the MSM distance of the *position* marginals (first three
    dims) is ``< match_threshold``; one-to-one matching among those (module docstring).
    Fusion weights:

    - matched pair: ``beta = 1/2`` for both components; with ``weights = "visibility"`` and a
      Beta detection model on both sides (``GM.pd_beta``, ``filter.pd_model = "beta"``), the
      detection-weighted average ``beta_b = pi_b / (pi_b + pi_u)``, ``beta_u = pi_u / (pi_b + pi_u)``,
      ``pi = E[p_D] = s / (s + t)`` of each member (:func:`visibility_weights`): a vehicle's copy
      carries information only as far as it could detect the landmark (with one ``p_D`` for both,
      ``beta = 1/2``, the paper's rule);
    - unmatched uploaded component: ``beta = 1`` (a landmark new to the BS map);
    - unmatched BS component: ``beta = 1/2`` if inside the uploading vehicle's accumulated FOV
      (it should have been seen: a possible false alarm), else ``beta = 1``.

    Args:
        bs: the BS's fused map of one type (batch ``()``, ``d >= 3``).
        ue: the vehicle's averaged map of the same type (batch ``()``).
        ue_fov_inside: ``(bs.capacity,)`` bool, per BS-map slot, inside the accumulated FOV
            (see :func:`in_accumulated_fov`); masked slots are ignored.
        match_threshold: MSM threshold (dimensionless).
        with_pairs: also return the matched pairs (see Returns).
        weights: ``"equal"`` (eq. 8) or ``"visibility"`` (matched pairs weighted by ``E[p_D]``
            where both maps carry a Beta detection model; equal otherwise).

    Returns:
        The union with weights ``beta * w`` (live components only, sorted by weight); with
        ``with_pairs``, ``(union, pairs)`` where ``pairs (n, 2)`` are the union slots of the BS and
        the uploaded member of each matched pair (for :func:`~mmslam.slam.phd.reduction.merge_pairs`).
    """
    if weights not in ("equal", "visibility"):
        raise ValueError(f"fusion weights {weights!r}: expected 'equal' or 'visibility'")
    d = _check_dims(bs, ue)
    inside = _check_inside(bs, ue_fov_inside)
    ib, wb, mb, Pb = _live(bs)
    _, wu, mu, Pu = _live(ue)
    dist = msm_distance(mb[:, POS], Pb[:, POS, POS], mu[:, POS], Pu[:, POS, POS])
    r, c = _match(dist < match_threshold, dist)
    beta_b = np.where(inside[ib], 0.5, 1.0)
    beta_u = np.ones(wu.shape[0])
    ab_b, ab_u = _pd_beta(bs, wb.shape[0]), _pd_beta(ue, wu.shape[0])
    if weights == "visibility" and ab_b is not None and ab_u is not None:
        beta_b[r], beta_u[c] = visibility_weights(ab_b[r], ab_u[c])
    else:
        beta_b[r] = 0.5
        beta_u[c] = 0.5
    return _union(wb, mb, Pb, beta_b, wu, mu, Pu, beta_u, d, (r, c) if with_pairs else None,
                  ab_b, ab_u, _label(bs, wb.shape[0]), _label(ue, wu.shape[0]))


def visibility_weights(ab_b: np.ndarray, ab_u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fusion weights of matched pairs by detection: ``beta_i = pi_i / (pi_b + pi_u)``, ``pi = s / (s + t)``.

    The AA fusion of eq. (8) with weights proportional to each member's expected detection
    probability (its Beta ``(s, t)``, ``(n, 2)`` per side): the FOV rule of eqs. (8) and (16)-(20)
    (weight 1 to the map that could see a landmark, 0 to one that could not, 1/2 each where both
    could) with the binary FOV indicator replaced by the learnt ``E[p_D]`` (docs/city-slam.md).
    Equal ``pi`` give 1/2 each. Returns ``(beta_b (n,), beta_u (n,))``.
    """
    pb = ab_b[:, 0] / (ab_b[:, 0] + ab_b[:, 1])
    pu = ab_u[:, 0] / (ab_u[:, 0] + ab_u[:, 1])
    tot = pb + pu
    return pb / tot, pu / tot


def _ego_match(m: np.ndarray, P: np.ndarray, ego_mean: np.ndarray, ego_cov: np.ndarray,
               threshold: float) -> np.ndarray:
    """``c_q`` of eq. (12): position-marginal MSM distance to the ego Gaussian ``< threshold``."""
    return msm_distance(m[:, POS], P[:, POS, POS], ego_mean[None, POS], ego_cov[None, POS, POS])[:, 0] < threshold


def _ego(ego_mean: np.ndarray, ego_cov: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    ego_mean = np.asarray(ego_mean, float).reshape(d)
    ego_cov = symmetrize(np.asarray(ego_cov, float).reshape(d, d))
    if not (np.all(np.isfinite(ego_mean)) and np.all(np.isfinite(ego_cov))):
        raise FloatingPointError("non-finite ego Gaussian")
    return ego_mean, ego_cov


def remove_ego(vs: GM, ego_mean: np.ndarray, ego_cov: np.ndarray, threshold: float) -> GM:
    """The VS map without the components matched to the ego vehicle (``c_q = 1``, ``beta_1 = 0``).

    The first half of ``F'_AA`` (:func:`ego_vs_average`) on its own: used on the fused VS map a
    vehicle receives (``fusion.downlink_ego = "remove"``), where the vehicle's own Gaussian,
    uploaded by itself, is not a scatterer of its own paths.

    Args:
        vs: one VS mixture (batch ``()``, ``d = 7``).
        ego_mean, ego_cov: ``(7,)`` / ``(7, 7)`` the ego state as a VS Gaussian.
        threshold: ``T_MD^L`` (dimensionless).
    """
    ego_mean, ego_cov = _ego(ego_mean, ego_cov, vs.dim)
    _, w, m, P = _live(vs)
    keep = ~_ego_match(m, P, ego_mean, ego_cov, threshold)
    ab, lab = _pd_beta(vs, w.shape[0]), _label(vs, w.shape[0])
    out = GM(w[keep], m[keep], P[keep], np.ones(int(keep.sum()), bool), None if ab is None else ab[keep],
             None if lab is None else lab[keep])
    out.check("after remove_ego")
    return out


def ego_vs_average(avg_vs: GM, ego_mean: np.ndarray, ego_cov: np.ndarray, threshold: float,
                   ego_label: int = NO_LABEL) -> GM:
    """``F'_AA`` placing the ego vehicle in its averaged VS map (paper eqs. (11)-(14)).

    ``c_q = 1`` iff the MSM distance between the position marginals of component ``q`` and of
    the ego Gaussian is ``< threshold`` (``T_MD^L``). Components with ``c_q = 1`` get
    ``beta_1 = 0`` (removed: they are the ego vehicle seen as a VS by itself, e.g. through
    another vehicle's upload); the others keep their weight (``beta_1 = 1``); the ego Gaussian
    is appended with weight 1 (``beta_2 = 1``, a PHD of one unit-weight Gaussian; with labels, the
    label ``ego_label``, :func:`mmslam.slam.core.gm.ego_label` of the vehicle: the same in each of its
    uploads, so that the particles of another vehicle that receive it in the fused map pool their
    copies of it).

    Args:
        avg_vs: averaged VS map of the vehicle (batch ``()``, ``d = 7``).
        ego_mean: ``(7,)`` ego state as a VS state ``[x, y, z, vx, vy, vz, xi]``.
        ego_cov: ``(7, 7)`` its covariance (SPD).
        threshold: ``T_MD^L`` (dimensionless).
        ego_label: the ego Gaussian's label where ``avg_vs`` has labels.

    Returns:
        The resulting mixture (live components only, sorted by weight).
    """
    d = avg_vs.dim
    ego_mean, ego_cov = _ego(ego_mean, ego_cov, d)
    _, w, m, P = _live(avg_vs)
    beta = np.where(_ego_match(m, P, ego_mean, ego_cov, threshold), 0.0, 1.0)
    lab = _label(avg_vs, w.shape[0])
    return _union(w, m, P, beta, np.ones(1), ego_mean[None], ego_cov[None], np.ones(1), d,
                  lab_b=lab,
                  lab_u=None if lab is None else np.array([ego_label], np.int64))


def predict_bs_vs(g: GM, dt: float, p_survival: float, q_std: np.ndarray, n_steps: int,
                  dither: np.ndarray | None = None) -> GM:
    """Predict the BS's fused VS map ``n_steps`` steps without birth (paper eq. (15)).

    ``n_steps`` applications of :func:`mmslam.slam.models.vs.predict_vs` (weights ``* p_S`` each step,
    CT mean, ``J P J^T + diag(q_std^2)``). No dithering by default: dithering is the local
    filter's remedy for over-confident CKF corrections; the BS performs no correction.
    """
    if n_steps < 0:
        raise ValueError(f"n_steps must be >= 0, got {n_steps}")
    out = g.copy()
    for _ in range(n_steps):
        out = predict_vs(out, dt, p_survival, q_std, dither)
    return out


def fuse_vs(bs_pred: GM, ue: GM, ue_fov_inside: np.ndarray, t_pos: float, t_vel: float,
            beta_inside_fov: float, with_pairs: bool = False) -> GM | tuple[GM, np.ndarray]:
    """``F'_AA`` at the BS for the VS map (paper eqs. (16)-(20)).

    Proximity: ``C[q1, q2] = 1`` iff the MSM distance of the position marginals (dims 0:3) is
    ``< t_pos`` (``T_MD^L``) and that of the velocity marginals (dims 3:6) is ``< t_vel``
    (``T_MD^V``). One-to-one matching among ``C = 1`` entries by the Hungarian algorithm on the
    cost ``MSM_pos + MSM_vel`` (module docstring). Fusion weights:

    - matched pair: ``rho = trace(T) / 7`` per component, ``beta_1 = (1/rho_1) / (1/rho_1 +
      1/rho_2)``, ``beta_2 = (1/rho_2) / (1/rho_1 + 1/rho_2)`` (the more certain one dominates);
    - unmatched uploaded component: ``beta_2 = 1`` (new target or false alarm; keep it to avoid
      missed detections);
    - unmatched BS component: ``beta_1 = 1`` outside the vehicle's accumulated FOV (a target
      seen by others), ``beta_inside_fov`` (e.g. 0.25) inside (a possible earlier false alarm).

    Args:
        bs_pred: the BS's VS map predicted to the upload time (:func:`predict_bs_vs`), ``d = 7``.
        ue: the vehicle's VS map after :func:`ego_vs_average`, ``d = 7``.
        ue_fov_inside: ``(bs_pred.capacity,)`` bool per BS-map slot (masked slots ignored).
        t_pos, t_vel: MSM thresholds (dimensionless).
        beta_inside_fov: weight factor of unmatched BS components inside the accumulated FOV.
        with_pairs: also return the matched pairs, as :func:`fuse_aa`.

    Returns:
        The union with weights ``beta * w`` (live components only, sorted by weight), and with
        ``with_pairs`` the ``(n, 2)`` union slots of each matched pair. The paper: matched
        densities "need to be merged"; unmatched ones are distinct targets.
    """
    d = _check_dims(bs_pred, ue)
    if d < 6:
        raise ValueError(f"fuse_vs needs VS states with velocity (d >= 6), got d = {d}")
    inside = _check_inside(bs_pred, ue_fov_inside)
    ib, wb, mb, Pb = _live(bs_pred)
    _, wu, mu, Pu = _live(ue)
    dp = msm_distance(mb[:, POS], Pb[:, POS, POS], mu[:, POS], Pu[:, POS, POS])
    dv = msm_distance(mb[:, VEL], Pb[:, VEL, VEL], mu[:, VEL], Pu[:, VEL, VEL])
    r, c = _match((dp < t_pos) & (dv < t_vel), dp + dv)
    beta_b = np.where(inside[ib], float(beta_inside_fov), 1.0)
    beta_u = np.ones(wu.shape[0])
    rho_b = np.trace(Pb, axis1=-2, axis2=-1) / d
    rho_u = np.trace(Pu, axis1=-2, axis2=-1) / d
    ib_inv, iu_inv = 1.0 / rho_b[r], 1.0 / rho_u[c]
    beta_b[r] = ib_inv / (ib_inv + iu_inv)
    beta_u[c] = iu_inv / (ib_inv + iu_inv)
    return _union(wb, mb, Pb, beta_b, wu, mu, Pu, beta_u, d, (r, c) if with_pairs else None,
                  _pd_beta(bs_pred, wb.shape[0]), _pd_beta(ue, wu.shape[0]), _label(bs_pred, wb.shape[0]),
                  _label(ue, wu.shape[0]))


def ego_gaussian(mean: np.ndarray, cov: np.ndarray, q_std: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The ego vehicle posterior as a 7-D VS Gaussian ``[x, y, z, vx, vy, vz, xi]``.

    Mean: position, velocity ``zeta [cos alpha, sin alpha, 0]``, turn rate ``xi`` (so the
    Cartesian CT of the VS model reproduces the polar CT exactly). Covariance: the particle
    covariance mapped linearly (velocity from the heading variance) plus ``diag(q_std^2)``,
    one step of the VS process noise, as a floor (the particle covariance is singular: z,
    speed and turn rate are the car's readings, the same in every particle; with noisy odometry,
    ``sensor.odometry_noise_std``, their error, a few 0.1 m/s at most, is below that floor).
    """
    a, v = mean[3], mean[4]
    m = np.array([mean[0], mean[1], mean[2], v * np.cos(a), v * np.sin(a), 0.0, mean[5]])
    J = np.zeros((7, 7))
    J[0, 0] = J[1, 1] = J[2, 2] = 1.0
    J[3, 3], J[3, 4] = -v * np.sin(a), np.cos(a)
    J[4, 3], J[4, 4] = v * np.cos(a), np.sin(a)
    J[6, 5] = 1.0
    C = J @ cov @ J.T + np.diag(np.asarray(q_std, float) ** 2)
    return m, 0.5 * (C + C.T)
