"""Every optimised kernel in ``slam/`` against a plain, obviously-correct reference (issue 10).

The kernels (batch-last closed-form Cholesky factors and solves, flattened CKF innovation,
padded GM layouts, batched greedy merging, component-wise birth inversion) are fast and
intricate; a slip in one of them (e.g. ``_logsumexp_slots`` writing into the ``logq`` it was
given when ``P == 1`` or ``Q == 1``) changes the filter's results silently. Each test here draws
random inputs with hypothesis, *including the degenerate shapes* (``P = 1``, ``Q = 0`` and ``1``,
``J = 0``, ``1`` and ``2``, an empty landmark type, an empty batch, SPD matrices with condition
numbers up to ``1e6``), and compares the kernel with a plain reference: a few lines of
per-matrix / per-Gaussian loops over textbook NumPy / SciPy (the measurement model, its inversion,
the CKF, the PHD correction and the reduction live in :mod:`mmslam.slam.reference`, named beside
the fast functions in docs/equations.md; the small linear-algebra ones stay here) (``np.linalg.cholesky``,
``np.linalg.inv``, ``scipy.linalg.solve_triangular``, ``scipy.special.logsumexp``, the CKF of
Arasaratnam & Haykin 2009 one Gaussian at a time, the greedy Vo & Ma 2006 merge one component at
a time, :func:`mmslam.slam.models.measurement.measure` for the geometry).

Tolerance: ``1e-9`` relative, normwise per compared object: ``|a - r| <= 1e-9 * max|r|`` over
each matrix / vector of the batch (``max(|r|, 1)`` for log-likelihoods and log-sums, ``|r|``
elementwise for weights; plus ``1e-300`` for underflowed terms); angles are compared modulo
``2 pi``. Every test also asserts that the kernel left its inputs unchanged (copies taken before
the call, compared bit for bit after), since the filter reuses them. Other modules covered the
same way: ``fov_detect_prob``, ``predict_vs`` and the particle-weight kernels of ``rbpf``.

The hypothesis profile (``tests/conftest.py``) is deterministic (``derandomize=True``).
Examples draw a shape and a seed; the arrays come from ``numpy.random.default_rng(seed)``.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, example, given
from hypothesis import strategies as st
from scipy.linalg import solve_triangular
from scipy.special import logsumexp

from mmslam.slam.phd import birth as birth_mod
from mmslam.slam.phd import ckf
from mmslam.slam.core import gm as gm_mod
from mmslam.slam.phd import gmphd
from mmslam.slam.core import linalg
from mmslam.slam.phd import reduction as red
from mmslam.slam.core.gm import GM
from mmslam.slam.models.measurement import BS, SP, VA, VS, channel_params, measure, measure_point
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import geometry_of
from mmslam.slam.specs.landmarks import landmark_type
from mmslam.slam.reference import ckf as ref_ckf_mod
from mmslam.slam.reference import models as ref_models
from mmslam.slam.reference import phd as ref_phd
from mmslam.slam.reference import reduction as ref_red

KINDS = {t.code: t for t in (landmark_type("VA"), landmark_type("SP"), landmark_type("VS"))}
"""Type code -> spec: what gmphd.correct is handed about each map's type."""

RTOL = 1e-9
TINY = 1e-300  # absolute floor: below it, values are round-off of underflowed terms
BS_POS = np.array([3.0, -4.0, 40.0])
FOV = 50.0
P_DETECT = 0.9
AZ = (1, 3)  # azimuth components of a measurement

seeds = st.integers(0, 2**32 - 1)
conds = st.sampled_from([0.0, 1.0, 3.0, 6.0])  # log10 of the condition number of the SPD inputs


# ====================================================================== helpers
def _wrap(a):
    """Textbook angle wrap to (-pi, pi]."""
    return np.angle(np.exp(1j * np.asarray(a, float)))


def _close(actual, ref, core: int, what: str = "") -> None:
    """``|a - r| <= RTOL * max|r|`` over each batch member's trailing ``core`` axes (normwise)."""
    actual, ref = np.asarray(actual, float), np.asarray(ref, float)
    assert actual.shape == ref.shape, f"{what}: shape {actual.shape} != reference {ref.shape}"
    if ref.size == 0:
        return
    assert np.isfinite(ref).all(), f"{what}: non-finite reference"
    axes = tuple(range(ref.ndim - core, ref.ndim))
    scale = np.abs(ref).max(axis=axes, keepdims=True) if core else np.abs(ref)
    err = np.abs(actual - ref)
    bad = ~(err <= RTOL * scale + TINY)
    assert not bad.any(), (f"{what}: max error {np.nanmax(err):.3g}, "
                           f"{int(bad.sum())} of {ref.size} entries beyond {RTOL} relative")


def _close_scalar(actual, ref, what: str = "") -> None:
    """Log-likelihoods / log-sums: ``|a - r| <= RTOL * max(|r|, 1)``; ``-inf`` where the reference is."""
    actual, ref = np.asarray(actual, float), np.asarray(ref, float)
    assert actual.shape == ref.shape, f"{what}: shape {actual.shape} != reference {ref.shape}"
    assert np.array_equal(np.isneginf(actual), np.isneginf(ref)), f"{what}: -inf pattern differs"
    f = np.isfinite(ref)
    err = np.abs(actual[f] - ref[f])
    assert np.all(err <= RTOL * np.maximum(np.abs(ref[f]), 1.0)), f"{what}: max error {err.max():.3g}"


def _close_weights(actual, ref, what: str = "") -> None:
    """Weights: elementwise ``|a - r| <= RTOL * |r|`` (exact zeros where the reference is 0)."""
    actual, ref = np.asarray(actual, float), np.asarray(ref, float)
    assert actual.shape == ref.shape, f"{what}: shape {actual.shape} != reference {ref.shape}"
    err = np.abs(actual - ref)
    assert np.all(err <= RTOL * np.abs(ref) + TINY), f"{what}: max relative error {np.max(err / np.maximum(np.abs(ref), 1e-300)):.3g}"


def _close_angles(actual, ref, core: int, what: str = "") -> None:
    """Measurements ``(..., 5)``: azimuths compared modulo 2 pi, everything normwise as :func:`_close`."""
    actual, ref = np.array(actual, float), np.asarray(ref, float)
    for c in AZ:
        actual[..., c] = ref[..., c] + _wrap(actual[..., c] - ref[..., c])
    _close(actual, ref, core, what)


def _snapshot(*arrays):
    return [(a, np.array(a, copy=True)) for a in arrays]


def _unchanged(snap, what: str = "") -> None:
    for i, (a, before) in enumerate(snap):
        assert np.array_equal(np.asarray(a), before, equal_nan=True), f"{what}: input #{i} was modified"


def _gm_snapshot(g: GM):
    return _snapshot(g.w, g.m, g.P, g.mask)


def rand_spd(rng, batch: tuple[int, ...], d: int, log10_cond: float, lo: float = 1e-2, hi: float = 1e2) -> np.ndarray:
    """Random SPD matrices ``batch + (d, d)``: random rotation, eigenvalues log-uniform with the
    given condition number (both extremes present for ``d >= 2``), overall scale in ``[lo, hi]``."""
    n = int(np.prod(batch, dtype=int))
    Qm, _ = np.linalg.qr(rng.standard_normal((n, d, d)))
    ev = 10.0 ** (log10_cond * rng.uniform(0.0, 1.0, (n, d)))
    ev[:, 0] = 1.0
    if d > 1:
        ev[:, -1] = 10.0 ** log10_cond
    ev *= 10.0 ** rng.uniform(np.log10(lo), np.log10(hi), (n, 1))
    A = (Qm * ev[:, None, :]) @ np.swapaxes(Qm, -1, -2)
    A = 0.5 * (A + np.swapaxes(A, -1, -2))
    return A.reshape(tuple(batch) + (d, d))


def rand_R(rng) -> np.ndarray:
    """A filter measurement covariance: TOA std 0.05..1 m, angle stds 5..50 mrad, random correlation."""
    std = np.concatenate([rng.uniform(0.05, 1.0, 1), rng.uniform(0.005, 0.05, 4)])
    C = rand_spd(rng, (), 5, 1.0, 1.0, 1.0)
    dc = np.sqrt(np.diag(C))
    C = C / dc[:, None] / dc[None, :]
    return C * std[:, None] * std[None, :]


def rand_states(rng, n: int) -> np.ndarray:
    s = np.empty((n, 7))
    s[:, 0:2] = rng.uniform(-80, 80, (n, 2))
    s[:, 2] = rng.uniform(0, 2, n)
    s[:, 3] = rng.uniform(-np.pi, np.pi, n)
    s[:, 4] = rng.uniform(0, 25, n)
    s[:, 5] = rng.uniform(-0.5, 0.5, n)
    s[:, 6] = rng.uniform(-50, 300, n)
    return s


def rand_dirs(rng, shape) -> np.ndarray:
    v = rng.standard_normal(tuple(shape) + (3,))
    v[..., 2] *= 0.3  # mostly horizontal, like the scenes
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rand_landmarks(rng, u: np.ndarray, lm_type: int) -> np.ndarray:
    """Landmark positions around vehicle positions ``u (..., 3)``; some beyond the FOV (``FOV`` m)."""
    r = rng.uniform(20, 200, u.shape[:-1]) if lm_type == VA else rng.uniform(3, 80, u.shape[:-1])
    return u + r[..., None] * rand_dirs(rng, u.shape[:-1])


def rand_landmark_gm(rng, states: np.ndarray, lm_type: int, Q: int, log10_cond: float, p_live: float = 0.8) -> GM:
    """A padded map of one type for ``P = len(states)`` particles with ``Q`` slots (dead slots 0 / I)."""
    P_ = states.shape[0]
    d = 7 if lm_type == VS else 3
    mask = rng.random((P_, Q)) < p_live
    m = np.zeros((P_, Q, d))
    m[..., :3] = rand_landmarks(rng, np.broadcast_to(states[:, None, :3], (P_, Q, 3)), lm_type)
    if d == 7:
        m[..., 3:6] = rng.normal(0, 5, (P_, Q, 3))
        m[..., 6] = rng.normal(0, 0.3, (P_, Q))
    Pm = rand_spd(rng, (P_, Q), d, log10_cond, 1e-3, 1.0)
    w = rng.uniform(0.05, 1.0, (P_, Q))
    w = np.where(mask, w, 0.0)
    m[~mask] = 0.0
    Pm[~mask] = np.eye(d)
    return GM(w, m, Pm, mask)


def rand_Z(rng, states: np.ndarray, J: int) -> np.ndarray:
    """``J`` measurements: landmark-like rows seen from the first vehicle state, with noise."""
    if J == 0:
        return np.zeros((0, 5))
    s0 = states[0]
    lm = rand_landmarks(rng, np.broadcast_to(s0[:3], (J, 3)), SP)
    Z = measure(s0, lm, Bounce.SCATTER, BS_POS) + rng.normal(0, 1, (J, 5)) * [1.0, 0.05, 0.05, 0.05, 0.05]
    Z[:, AZ] = _wrap(Z[:, AZ])
    return Z


def pd_fn(u, x, t):
    """A detection probability with zeros: ``P_DETECT`` within ``FOV`` m of the vehicle, else 0."""
    u, x = np.asarray(u, float), np.asarray(x, float)
    return np.where(np.linalg.norm(x - u, axis=-1) <= FOV, P_DETECT, 0.0)


# ---------------------------------------------------------------- the textbook references (mmslam.slam.reference)
def ref_measure(state, x, lm_type):
    """Textbook measurement of one landmark point (docs/design.md section 4): :func:`reference.models.measure`."""
    return ref_models.measure(state, x, geometry_of(lm_type), BS_POS)


def ref_h(state, lm_type):
    """The measurement model of one vehicle state as a function of a landmark point (position first)."""
    return ref_models.measurement_function(state, geometry_of(lm_type), BS_POS)


ref_ckf = ref_ckf_mod.cubature_moments
ref_update = ref_ckf_mod.kalman_update
_ref_greedy = ref_red.greedy_merge
_ref_reduce = ref_red.reduce
_ref_corrected_components = ref_phd.corrected_components


def _ref_correction(maps: dict[int, GM], s, Z, R, bs_term, log_clutter):
    """Per-particle, per-Gaussian reference of type_terms + log_psi: ``logq``, ``missed``, updates."""
    return ref_phd.correction(maps, {t: geometry_of(t) for t in maps}, s, Z, R, BS_POS, pd_fn, bs_term, log_clutter)


def _ref_birth(states, Z, R, lm_type):
    """Cubature points of ``N(z_j, R)`` inverted one by one (:func:`reference.models.birth_moments`)."""
    return ref_models.birth_moments(states, Z, R, geometry_of(lm_type), BS_POS)


# ---------------------------------------------------------------- reference model and CKF (one Gaussian)


def test_reference_ckf_is_the_kalman_filter_for_a_linear_measurement():
    """The reference CKF (and so, by the tests below, the kernel) is exact for linear ``h``: 3-D and
    7-D (position marginal + conditional cross-covariance) equal the Kalman update."""
    rng = np.random.default_rng(0)
    for d in (3, 7):
        m = rng.normal(0, 3, d)
        P = rand_spd(rng, (), d, 2.0, 1e-2, 1.0)
        H = 0.05 * rng.normal(size=(5, 3))  # small values: no azimuth wraps
        R = rand_R(rng)
        z = rng.normal(size=5) * 0.1
        r = ref_update(m, P, lambda x: H @ x, z[None], R)
        Hf = np.zeros((5, d))
        Hf[:, :3] = H
        S = Hf @ P @ Hf.T + R
        K = P @ Hf.T @ np.linalg.inv(S)
        res = z - Hf @ m
        res[list(AZ)] = _wrap(res[list(AZ)])
        np.testing.assert_allclose(r["m_post"][0], m + K @ res, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r["P_post"], P - K @ S @ K.T, rtol=1e-9, atol=1e-12)


# ====================================================================== linalg: Cholesky, solves, inverses
batch_shapes = st.lists(st.integers(0, 3), min_size=0, max_size=2).map(tuple)


@given(seed=seeds, batch=batch_shapes, d=st.sampled_from([1, 2, 3, 5, 7]), cond=conds)
def test_cholesky_kernels_equal_lapack_per_matrix(seed, batch, d, cond):
    rng = np.random.default_rng(seed)
    A = rand_spd(rng, batch, d, cond)
    flat = A.reshape(-1, d, d)
    ref = np.array([np.linalg.cholesky(a) for a in flat]).reshape(A.shape)
    snap = _snapshot(A)
    _close(linalg.safe_cholesky(A, "test"), ref, 2, "safe_cholesky")
    _unchanged(snap, "safe_cholesky")
    # the per-matrix kernel reads the lower triangle only
    low = flat.copy()
    for i in range(d):
        low[:, :i, i] = np.nan
    L = np.full_like(low, 7.0)
    for a, l in zip(low, L):
        assert linalg.cholesky(a, l)
    _close(L.reshape(A.shape), ref, 2, "cholesky (lower triangle only)")


@given(seed=seeds, n=st.integers(0, 4), d=st.sampled_from([2, 3, 5, 7]))
def test_safe_cholesky_jitters_a_singular_psd_matrix_and_rejects_indefinite_or_nan(seed, n, d):
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((n, d, d - 1))
    A = B @ np.swapaxes(B, -1, -2)  # PSD of rank d - 1
    snap = _snapshot(A)
    L = linalg.safe_cholesky(A, "test")
    _unchanged(snap, "safe_cholesky")
    assert np.all(np.tril(L) == L)
    _close(L @ np.swapaxes(L, -1, -2), A, 2, "safe_cholesky of a singular PSD matrix (jitter 1e-10 relative)")
    if n:
        assert not linalg.cholesky(np.zeros((d, d)), np.empty((d, d)), False)  # without the retry: rejected
        assert linalg.cholesky(np.zeros((d, d)), np.empty((d, d)))  # with it: 1e-22 I
        bad = A.copy()
        bad[-1] -= 2.0 * np.abs(bad[-1]).max() * np.eye(d)  # indefinite
        with pytest.raises(FloatingPointError, match="not positive definite in test"):
            linalg.safe_cholesky(bad, "test")
        bad = A.copy()
        bad[0, 0, 0] = np.nan
        with pytest.raises(FloatingPointError, match="non-finite covariance in test"):
            linalg.safe_cholesky(bad, "test")


@given(seed=seeds, batch=batch_shapes, d=st.sampled_from([1, 2, 3, 5, 7]), cond=conds,
       J=st.sampled_from([None, 0, 1, 2, 4]))
def test_triangular_solves_equal_solve_triangular(seed, batch, d, cond, J):
    rng = np.random.default_rng(seed)
    L = np.linalg.cholesky(rand_spd(rng, batch, d, cond))
    flat = L.reshape(-1, d, d)
    n = flat.shape[0]
    B = rng.standard_normal((n, 1 if J is None else J, d))
    snap = _snapshot(L, B)
    for k in range(n):
        for j in range(B.shape[1]):
            x = np.empty(d)
            linalg.forward_solve(flat[k], B[k, j], x)
            _close(x, solve_triangular(flat[k], B[k, j], lower=True), 1, "forward_solve")
            linalg.back_solve(flat[k], B[k, j], x)
            _close(x, solve_triangular(flat[k].T, B[k, j], lower=False), 1, "back_solve")
            y = B[k, j].copy()
            linalg.forward_solve(flat[k], y, y)  # in place
            _close(y, solve_triangular(flat[k], B[k, j], lower=True), 1, "forward_solve in place")
    _unchanged(snap, "forward_solve / back_solve")


@given(seed=seeds, batch=batch_shapes, d=st.sampled_from([1, 2, 3, 5, 7]), cond=conds)
def test_spd_inverses_equal_numpy_inv(seed, batch, d, cond):
    rng = np.random.default_rng(seed)
    A = rand_spd(rng, batch, d, cond)
    ref = np.array([np.linalg.inv(a) for a in A.reshape(-1, d, d)]).reshape(A.shape)
    snap = _snapshot(A)
    got = linalg.spd_inv(A, "merging")
    _close(got, ref, 2, "spd_inv")
    assert np.array_equal(got, np.swapaxes(got, -1, -2))
    _unchanged(snap, "spd_inv")
    if A.size:
        bad = A.reshape(-1, d, d).copy()
        bad[0] = 0.0  # singular
        with pytest.raises(FloatingPointError, match="singular"):
            linalg.spd_inv(bad, "merging")
        bad[0] = -A.reshape(-1, d, d)[0]  # negative definite
        with pytest.raises(FloatingPointError, match="indefinite"):
            linalg.spd_inv(bad, "merging")


# ====================================================================== measurement model and CKF
@given(seed=seeds, batch=batch_shapes, d=st.sampled_from([1, 3, 5, 7]), cond=conds)
def test_cubature_points_equal_the_per_gaussian_rule(seed, batch, d, cond):
    rng = np.random.default_rng(seed)
    m = rng.normal(0, 10, tuple(batch) + (d,))
    P = rand_spd(rng, batch, d, cond)
    snap = _snapshot(m, P)
    got = ckf.cubature_points(m, P)
    _unchanged(snap, "cubature_points")
    ref = []
    for mi, Pi in zip(m.reshape(-1, d), P.reshape(-1, d, d)):
        Lc = np.linalg.cholesky(Pi)
        ref.append([mi + np.sqrt(d) * Lc[:, i] for i in range(d)] + [mi - np.sqrt(d) * Lc[:, i] for i in range(d)])
    ref = np.array(ref).reshape(tuple(batch) + (2 * d, d))
    _close(got - m[..., None, :], ref - m[..., None, :], 2, "cubature_points (offsets)")
    _close(got, ref, 1, "cubature_points")


@given(seed=seeds, P_=st.integers(1, 3), Q=st.integers(0, 3), K=st.integers(1, 6), lm_type=st.sampled_from([BS, VA, SP, VS]))
def test_measurement_kernels_equal_the_textbook_geometry(seed, P_, Q, K, lm_type):
    rng = np.random.default_rng(seed)
    s = rand_states(rng, P_)
    pts = rand_landmarks(rng, np.broadcast_to(s[:, None, None, :3], (P_, Q, K, 3)), SP if lm_type == BS else lm_type)
    snap = _snapshot(s, pts)
    ref = np.array([[[ref_measure(s[p], pts[p, q, k], lm_type) for k in range(K)] for q in range(Q)]
                    for p in range(P_)]).reshape(P_, Q, K, 5)
    got = measure(np.broadcast_to(s[:, None, None, :], (P_, Q, K, 7)), pts, geometry_of(lm_type), BS_POS)  # BS: pts unused
    _close_angles(got, ref, 1, "measure")
    geo = geometry_of(lm_type)
    for p in range(P_):
        for q in range(Q):
            for k in range(K):
                _close_angles(np.array(measure_point(geo, s[p], pts[p, q, k], BS_POS)), ref[p, q, k], 1, "measure_point")
    glob = channel_params(np.broadcast_to(s[:, None, None, :3], pts.shape), pts, geometry_of(lm_type), BS_POS)
    body = glob.copy()
    body[..., 0] += s[:, None, None, 6]
    body[..., 3] = _wrap(body[..., 3] - s[:, None, None, 3])
    _close_angles(body, ref, 1, "channel_params (to body frame)")
    _unchanged(snap, "measure / measure_point / channel_params")


CAR = np.array([4.5, 1.8, 1.5, 0.8])  # a VS car body: length, width, height, centre depth below the antenna (m)


def ref_h_body(state, lm_type, m, body):
    """``ref_h`` through the car body's specular point (the body facing along ``m``'s velocity for a VS)."""
    h = ref_h(state, lm_type)
    if body is None:
        return h
    heading = float(np.arctan2(m[4], m[3])) if m.shape[0] >= 5 else 0.0
    return lambda x: h(ref_models.body_bounce(x, heading, BS_POS, state[:3], body))


@given(seed=seeds, lm_type=st.sampled_from([VA, SP, VS]), cond=st.sampled_from([0.0, 2.0, 4.0]),
       J=st.sampled_from([0, 1, 2, 3]), extent=st.booleans(), per_meas_R=st.booleans(), body=st.booleans())
def test_ckf_update_and_kalman_update_equal_the_per_gaussian_ckf(seed, lm_type, cond, J, extent, per_meas_R, body):
    """One Gaussian (3-D, or 7-D VS through the position marginal), optional scatter-point extent, optional car
    body (the path through its specular point), one R or one R per measurement: loglik, posterior means and
    covariances equal the textbook CKF."""
    rng = np.random.default_rng(seed)
    s = rand_states(rng, 1)
    g = rand_landmark_gm(rng, s, lm_type, 1, cond, p_live=1.0)
    m, P = g.m[0, 0], g.P[0, 0]
    d = m.shape[0]
    Z = rand_Z(rng, s, J)
    R = np.array([rand_R(rng) for _ in range(J)]).reshape(J, 5, 5) if per_meas_R else rand_R(rng)
    E = rand_spd(rng, (), 3, 1.0, 0.1, 1.0) if extent else None
    B = CAR if body else None
    snap = _snapshot(m, P, s, Z, R)
    inn = ckf.innovate(m[None], P[None], s, geometry_of(lm_type), BS_POS, Z, R, "test", E, B)
    _unchanged(snap, "innovate")
    assert inn.loglik.shape == (1, J) and inn.m_post.shape == (1, J, d)
    for j in range(J):
        r = ref_update(m, P, ref_h_body(s[0], lm_type, m, B), Z[j:j + 1], R[j] if per_meas_R else R, E)
        _close_scalar(inn.loglik[0, j:j + 1], r["loglik"], "loglik")
        _close(inn.m_post[0, j], r["m_post"][0], 1, "posterior mean")
        _close(inn.post(np.array([0]), np.array([j]))[0], r["P_post"], 2, "posterior covariance")
        mk, Pk, llk = ckf.kalman_update(m, P, Z[j], R[j] if per_meas_R else R, s[0], geometry_of(lm_type), BS_POS, E,
                                        B)
        _close(mk, r["m_post"][0], 1, "kalman_update mean")
        _close(Pk, r["P_post"], 2, "kalman_update covariance")
        _close_scalar(llk, r["loglik"][0], "kalman_update loglik")
    _unchanged(snap, "kalman_update")


@given(seed=seeds, n=st.sampled_from([0, 1, 2, 5]), J=st.sampled_from([0, 1, 2, 3]), lm_type=st.sampled_from([VA, SP, VS]),
       cond=st.sampled_from([0.0, 2.0, 4.0]), body=st.booleans())
@example(seed=1, n=0, J=2, lm_type=VA, cond=0.0, body=False).via("no Gaussian")
@example(seed=2, n=1, J=0, lm_type=VS, cond=2.0, body=False).via("no measurement")
@example(seed=3, n=1, J=1, lm_type=SP, cond=4.0, body=False).via("one of each")
@example(seed=4, n=5, J=2, lm_type=VS, cond=4.0, body=False).via("several Gaussians, several measurements")
@example(seed=5, n=1, J=1, lm_type=VS, cond=2.0, body=True).via("car body, one of each")
@example(seed=6, n=0, J=1, lm_type=VS, cond=2.0, body=True).via("car body, no Gaussian")
@example(seed=7, n=2, J=0, lm_type=VS, cond=2.0, body=True).via("car body, no measurement")
def test_innovate_equals_the_per_gaussian_ckf(seed, n, J, lm_type, cond, body):
    rng = np.random.default_rng(seed)
    s = rand_states(rng, max(n, 1))[:n] if n else np.zeros((0, 7))
    g = rand_landmark_gm(rng, s if n else rand_states(rng, 1), lm_type, 1, cond, p_live=1.0)
    m, P = g.m[:n, 0], g.P[:n, 0]
    d = m.shape[-1]
    Z = rand_Z(rng, s if n else rand_states(rng, 1), J)
    R = rand_R(rng)
    snap = _snapshot(m, P, s, Z, R)
    B = CAR if body else None
    inn = ckf.innovate(m, P, s, geometry_of(lm_type), BS_POS, Z, R, "test", body=B)
    _unchanged(snap, "innovate")
    assert inn.loglik.shape == (n, J) and inn.m_post.shape == (n, J, d) and inn.P_post.shape == (n, 1, d, d)
    for i in range(n):
        r = ref_update(m[i], P[i], ref_h_body(s[i], lm_type, m[i], B), Z, R)
        _close_scalar(inn.loglik[i], r["loglik"], "innovate loglik")
        _close(inn.m_post[i], r["m_post"], 1, "innovate posterior mean")
        _close(inn.P_post[i, 0], r["P_post"], 2, "innovate P_post")


# ====================================================================== gmphd: PHD correction
@given(seed=seeds, P_=st.integers(1, 3), Q=st.integers(1, 4), J=st.integers(0, 4))
@example(seed=1, P_=1, Q=3, J=2).via("P == 1: the old slot-first copy was a view")
@example(seed=2, P_=3, Q=1, J=2).via("Q == 1: the old slot-first copy was a view")
@example(seed=3, P_=1, Q=1, J=1).via("degenerate")
@example(seed=4, P_=2, Q=2, J=0).via("no measurement")
def test_logsumexp_slots_equals_scipy_and_leaves_logq_alone(seed, P_, Q, J):
    rng = np.random.default_rng(seed)
    logq = rng.normal(-20.0, 30.0, (P_, Q, J))
    logq[rng.random(logq.shape) < 0.3] = -np.inf
    if J:
        logq[:, :, rng.integers(J)] = -np.inf if rng.random() < 0.5 else logq[:, :, 0]
    snap = _snapshot(logq)
    got = gmphd._logsumexp_slots(logq)
    _unchanged(snap, "_logsumexp_slots")
    with np.errstate(divide="ignore"):
        ref = logsumexp(logq, axis=1)
    _close_scalar(got, ref, "_logsumexp_slots")


@given(seed=seeds, P_=st.integers(1, 3), J=st.integers(0, 3), with_bs=st.booleans())
def test_bs_logterm_equals_the_gaussian_log_density(seed, P_, J, with_bs):
    rng = np.random.default_rng(seed)
    s = rand_states(rng, P_)
    R = rand_R(rng)
    Z = measure(s[:1], BS_POS, Bounce.DIRECT, BS_POS) + rng.normal(0, 1, (J, 5)) * np.sqrt(np.diag(R)) * 3
    p_d = np.where(rng.random(P_) < 0.3, 0.0, rng.uniform(0.1, 1.0, P_))
    snap = _snapshot(s, Z, R, p_d)
    got = gmphd.bs_logterm(s, Z, R, BS_POS, p_d)
    _unchanged(snap, "bs_logterm")
    _, logdet = np.linalg.slogdet(2 * np.pi * R)
    ref = np.full((P_, J), -np.inf)
    for p in range(P_):
        for j in range(J):
            r = Z[j] - ref_measure(s[p], BS_POS, BS)
            r[list(AZ)] = _wrap(r[list(AZ)])
            if p_d[p] > 0:
                ref[p, j] = np.log(p_d[p]) - 0.5 * (r @ np.linalg.solve(R, r) + logdet)
    _close_scalar(got, ref, "bs_logterm")


@given(seed=seeds, P_=st.integers(1, 3), types=st.sampled_from([(VA,), (SP,), (VS,), (VA, SP), (VA, SP, VS)]),
       Qs=st.lists(st.integers(0, 3), min_size=3, max_size=3), J=st.integers(0, 3), with_bs=st.booleans(),
       cond=st.sampled_from([0.0, 2.0, 4.0]), prune=st.sampled_from([None, 1e-3, 0.05]))
@example(seed=5, P_=1, types=(VA, SP, VS), Qs=[1, 0, 2], J=2, with_bs=True, cond=2.0, prune=None).via("P == 1, one type empty")
@example(seed=6, P_=3, types=(VA, SP), Qs=[1, 1, 0], J=2, with_bs=False, cond=4.0, prune=1e-3).via("Q == 1")
@example(seed=7, P_=2, types=(VA, SP, VS), Qs=[0, 0, 0], J=1, with_bs=True, cond=0.0, prune=None).via("all maps empty")
@example(seed=8, P_=2, types=(VA, SP, VS), Qs=[2, 1, 1], J=0, with_bs=False, cond=0.0, prune=None).via("J == 0")
def test_type_terms_log_psi_and_corrected_gm_equal_the_per_gaussian_phd_update(seed, P_, types, Qs, J, with_bs, cond,
                                                                                prune):
    rng = np.random.default_rng(seed)
    s = rand_states(rng, P_)
    maps = {t: rand_landmark_gm(rng, s, t, Q, cond) for t, Q in zip(types, Qs)}
    Z = rand_Z(rng, s, J)
    R = rand_R(rng)
    log_clutter = float(np.log(10.0 ** rng.uniform(-8, -3)))
    bs_term = None
    if with_bs:
        bs_term = gmphd.bs_logterm(s, Z, R, BS_POS, np.full(P_, P_DETECT))
    snaps = [_gm_snapshot(g) for g in maps.values()] + [_snapshot(s, Z, R)]
    terms = [gmphd.type_terms(maps[t], landmark_type(t), s, Z, R, BS_POS, pd_fn) for t in types]
    for sn in snaps:
        _unchanged(sn, "type_terms")
    lpsi = gmphd.log_psi(terms, bs_term, log_clutter, (P_, J))
    ref, ref_lpsi = _ref_correction(maps, s, Z, R, bs_term, log_clutter)
    _close_scalar(lpsi, ref_lpsi, "log_psi")
    for tc in terms:
        logq, missed, upd = ref[tc.lm_type]
        _close_scalar(tc.logq, logq, "type_terms logq")
        _close_weights(tc.missed_w, missed, "type_terms missed_w")
        g = maps[tc.lm_type]  # the predicted mass of the live slots (the PHD-mass check's left side)
        _close_weights(tc.pred_mass, [sum(g.w[p, q] for q in range(g.capacity) if g.mask[p, q]) for p in range(P_)],
                       "type_terms pred_mass")
        detectable = np.array([[(p, q) in upd for q in range(tc.g.capacity)] for p in range(P_)], bool)
        assert np.array_equal(tc.det_index >= 0, detectable.reshape(P_, tc.g.capacity))
        for (p, q), r in upd.items():  # the flat innovation entry of each detectable Gaussian
            i = tc.det_index[p, q]
            _close_scalar(tc.inn.loglik[i], r["loglik"], "type_terms innovation loglik")
            _close(tc.inn.m_post[i], r["m_post"], 1, "type_terms innovation m_post")
            _close(tc.inn.P_post[i, 0], r["P_post"], 2, "type_terms innovation P_post")
    term_snaps = [_snapshot(tc.logq, tc.missed_w, tc.det_index, tc.inn.loglik, tc.inn.m_post, tc.inn.P_post,
                            tc.pred_mass) for tc in terms]
    lpsi_snap = _snapshot(lpsi)
    for tc in terms:
        g = maps[tc.lm_type]
        logq, missed, upd = ref[tc.lm_type]
        out = gmphd.corrected_gm(tc, Z, lpsi, prune=prune)
        out2, mass = gmphd._corrected_gm(tc, Z, lpsi, prune, None)  # with the corrected mass per particle
        assert np.array_equal(out2.w, out.w) and np.array_equal(out2.mask, out.mask)
        assert np.array_equal(mass, np.where(out.mask, out.w, 0.0).sum(-1))  # NumPy's sums, bit for bit
        for p in range(P_):
            comps = _ref_corrected_components(g, logq, missed, upd, ref_lpsi, p, J)
            if prune is None:
                assert out.capacity == g.capacity * (1 + J)
                assert [c[0] for c in comps] == list(np.nonzero(out.mask[p])[0])
                assert np.all(out.w[p][~out.mask[p]] == 0.0)
            else:
                assume(all(abs(c[1] - prune) > 1e-6 * prune for c in comps))
                comps = [c for c in comps if c[1] >= prune]
                assert out.mask[p].sum() == len(comps) and out.mask[p, :len(comps)].all()
            live = np.nonzero(out.mask[p])[0]
            if comps:
                _close_weights(out.w[p, live], np.array([c[1] for c in comps]), "corrected_gm weights")
                _close(out.m[p, live], np.array([c[2] for c in comps]), 1, "corrected_gm means")
                _close(out.P[p, live], np.array([c[3] for c in comps]), 2, "corrected_gm covariances")
            # the invariant the filter checks: corrected mass <= predicted mass + J
            assert out.w[p].sum() <= g.w[p].sum() + J + 1e-9 * (g.w[p].sum() + J)
        for sn in term_snaps:
            _unchanged(sn, "corrected_gm (TypeCorrection)")
        _unchanged(lpsi_snap, "corrected_gm (log psi)")
    # the whole correction in one call (gmphd.correct) gives the same maps and log psi
    with np.errstate(divide="ignore"):
        maps_c, lpsi_c, _ = gmphd.correct(maps, s, Z, R, BS_POS, pd_fn, np.full(P_, P_DETECT if with_bs else 0.0),
                                       log_clutter, prune, {}, 0, KINDS)
    for sn in snaps:
        _unchanged(sn, "correct")
    _close_scalar(lpsi_c, ref_lpsi, "correct log psi")
    for tc in terms:
        out = gmphd.corrected_gm(tc, Z, lpsi, prune=prune)
        got = maps_c[tc.lm_type]
        assert np.array_equal(got.mask, out.mask)
        _close_weights(got.w, out.w, "correct weights")
        _close(got.m, out.m, 1, "correct means")
        _close(got.P, out.P, 2, "correct covariances")


def test_log_psi_raises_when_nothing_explains_a_measurement():
    logq = np.full((2, 3, 2), -np.inf)
    tc = gmphd.TypeCorrection(None, VA, logq, None, None, None)
    with pytest.raises(FloatingPointError, match="psi"):
        gmphd.log_psi([tc], None, -np.inf, (2, 2))
    with np.errstate(divide="ignore"):
        assert np.allclose(gmphd.log_psi([tc], None, np.log(0.5), (2, 2)), np.log(0.5))


# ====================================================================== reduction


def _clustered_mixtures(rng, n, Q, d, cond, merge=4.0):
    """``n`` mixtures of ``Q`` components around a few centres, each offset from its centre by
    ``0..0.8 sqrt(merge)`` in its own Mahalanobis metric: pairwise distances spread around the
    merging threshold, so that both outcomes of the merge test occur."""
    centres = rng.normal(0, 50, (n, 3, d))
    which = rng.integers(0, 3, (n, Q))
    P = rand_spd(rng, (n, Q), d, cond, 0.05, 2.0)
    u = rand_dirs(rng, (n, Q)) if d == 3 else rng.standard_normal((n, Q, d))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    off = np.einsum("nqij,nqj->nqi", np.linalg.cholesky(P), u) * (rng.uniform(0, 0.8, (n, Q, 1)) * np.sqrt(merge))
    m = centres[np.arange(n)[:, None], which] + off
    w = rng.uniform(0.01, 1.0, (n, Q))
    return w, m, P


def _assume_off_threshold(dists, merge):
    assume(all(abs(x - merge) > 1e-6 * merge for x in dists))


@given(seed=seeds, n=st.integers(1, 3), Q=st.integers(1, 6), d=st.sampled_from([2, 3, 7]), cond=conds,
       merge=st.sampled_from([1.0, 4.0, 49.0]))
@example(seed=1, n=1, Q=1, d=3, cond=0.0, merge=4.0).via("one component, single mixture")
@example(seed=2, n=1, Q=6, d=7, cond=3.0, merge=49.0).via("single 7-D mixture")
def test_merge_flat_equals_the_greedy_vo_ma_merge(seed, n, Q, d, cond, merge):
    rng = np.random.default_rng(seed)
    w, m, P = _clustered_mixtures(rng, n, Q, d, min(cond, 4.0), merge)
    keep = rng.random((n, Q)) < 0.85
    m[~keep] = 0.0
    P[~keep] = np.eye(d)
    snap = _snapshot(w, m, P, keep)
    ow, om, oP, omask = red._merge_flat(w, m, P, keep, merge)
    _unchanged(snap, "_merge_flat")
    for k in range(n):
        clusters, dists = _ref_greedy(w[k], m[k], P[k], np.nonzero(keep[k])[0], merge)
        _assume_off_threshold(dists, merge)
        nc = len(clusters)
        assert omask[k].sum() == nc and omask[k, :nc].all()
        if nc:
            _close_weights(ow[k, :nc], [c[1] for c in clusters], "_merge_flat weights")
            _close(om[k, :nc], np.array([c[2] for c in clusters]), 1, "_merge_flat means")
            _close(oP[k, :nc], np.array([c[3] for c in clusters]), 2, "_merge_flat covariances")
        assert np.all(ow[k, nc:] == 0.0)


def _assert_reduced(out_w, out_m, out_P, out_mask, clusters, what):
    k = len(clusters)
    assert out_mask.sum() == k and out_mask[:k].all(), what
    assert np.all(out_w[k:] == 0.0), what
    if k:
        _close_weights(out_w[:k], [c[1] for c in clusters], what + " weights")
        _close(out_m[:k], np.array([c[2] for c in clusters]), 1, what + " means")
        _close(out_P[:k], np.array([c[3] for c in clusters]), 2, what + " covariances")


@given(seed=seeds, batch=st.sampled_from([(), (1,), (2,), (3,), (2, 2)]), Q=st.integers(0, 6), d=st.sampled_from([3, 7]),
       cond=st.sampled_from([0.0, 2.0, 4.0]), merge=st.sampled_from([4.0, 49.0]), cap=st.integers(1, 4),
       max_trace=st.sampled_from([None, 3.0]), fixed=st.booleans())
@example(seed=1, batch=(1,), Q=0, d=3, cond=0.0, merge=4.0, cap=2, max_trace=None, fixed=True)
@example(seed=2, batch=(1,), Q=1, d=7, cond=2.0, merge=49.0, cap=1, max_trace=None, fixed=False)
def test_prune_merge_equals_the_per_mixture_reference(seed, batch, Q, d, cond, merge, cap, max_trace, fixed):
    rng = np.random.default_rng(seed)
    n = int(np.prod(batch, dtype=int))
    w, m, P = _clustered_mixtures(rng, n, Q, d, cond, merge)
    w *= 10.0 ** rng.uniform(-3, 0, (n, Q))
    mask = rng.random((n, Q)) < 0.85
    w[~mask] = 0.0
    m[~mask] = 0.0
    P[~mask] = np.eye(d)
    g = GM(w.reshape(batch + (Q,)), m.reshape(batch + (Q, d)), P.reshape(batch + (Q, d, d)), mask.reshape(batch + (Q,)))
    prune = 1e-2
    assume(np.all(np.abs(w[mask] - prune) > 1e-6 * prune))
    snap = _gm_snapshot(g)
    out = red.prune_merge(g, prune, merge, cap, max_trace, pos_dims=3, fixed_capacity=fixed)
    _unchanged(snap, "prune_merge")
    assert out.batch_shape == batch
    if fixed:
        assert out.capacity == cap
    ow, om, oP, omask = (a.reshape((n,) + a.shape[len(batch):]) for a in (out.w, out.m, out.P, out.mask))
    for k in range(n):
        clusters, dists = _ref_reduce(w[k], m[k], P[k], mask[k], prune, merge, cap, max_trace, 3)
        _assume_off_threshold(dists, merge)
        _assert_reduced(ow[k], om[k], oP[k], omask[k], clusters, "prune_merge")
    assert np.all(oP[~omask] == np.eye(d)) and np.all(om[~omask] == 0.0)


@given(seed=seeds, P_=st.integers(1, 4), Q=st.integers(0, 5), d=st.sampled_from([3, 7]), cond=st.sampled_from([0.0, 2.0]),
       merge=st.sampled_from([4.0, 49.0]), cap=st.integers(1, 5), max_trace=st.sampled_from([None, 3.0]),
       zero_particle=st.booleans())
def test_average_map_equals_the_weighted_union_reference(seed, P_, Q, d, cond, merge, cap, max_trace, zero_particle):
    rng = np.random.default_rng(seed)
    w, m, P = _clustered_mixtures(rng, 1, Q, d, cond, merge)
    # every particle's map: the same clusters, perturbed
    w = np.repeat(w, P_, 0) * rng.uniform(0.5, 1.5, (P_, Q))
    m = np.repeat(m, P_, 0) + rng.normal(0, 0.3, (P_, Q, d))
    P = np.repeat(P, P_, 0)
    mask = rng.random((P_, Q)) < 0.85
    w[~mask], m[~mask], P[~mask] = 0.0, 0.0, np.eye(d)
    g = GM(w, m, P, mask)
    pw = rng.uniform(0.1, 1.0, P_)
    if zero_particle and P_ > 1:
        pw[0] = 0.0
    prune = 0.1
    snap = _gm_snapshot(g) + _snapshot(pw)
    out = red.average_map(g, pw, prune, merge, cap, max_trace, pos_dims=3)
    _unchanged(snap, "average_map")
    pn = pw / pw.sum()
    sel = [(p, q) for p in range(P_) for q in range(Q) if mask[p, q] and w[p, q] >= prune and pn[p] > 0
           and (max_trace is None or np.trace(P[p, q][:3, :3]) <= max_trace)]
    uw = np.array([pn[p] * w[p, q] for p, q in sel])
    um = np.array([m[p, q] for p, q in sel]).reshape(-1, d)
    uP = np.array([P[p, q] for p, q in sel]).reshape(-1, d, d)
    clusters, dists = _ref_reduce(uw, um, uP, np.ones(len(sel), bool), -np.inf, merge, cap, None, 3, final_prune=prune)
    _assume_off_threshold(dists, merge)
    assume(all(abs(c - prune) > 1e-6 for c in [cl[1] for cl in _ref_greedy(uw, um, uP, range(len(sel)), merge)[0]]))
    assert out.batch_shape == ()
    _assert_reduced(out.w, out.m, out.P, out.mask, clusters, "average_map")


@given(seed=seeds, Q=st.integers(0, 7), d=st.sampled_from([3, 7]), n_pairs=st.integers(0, 3))
def test_merge_pairs_equals_the_pairwise_moment_match(seed, Q, d, n_pairs):
    rng = np.random.default_rng(seed)
    w, m, P = _clustered_mixtures(rng, 1, Q, d, 2.0)
    g = GM(w[0], m[0], P[0], np.ones(Q, bool))
    slots = rng.permutation(Q)
    n_pairs = min(n_pairs, Q // 2)
    pairs = slots[:2 * n_pairs].reshape(n_pairs, 2)
    snap = _gm_snapshot(g) + _snapshot(pairs)
    out = red.merge_pairs(g, pairs)
    _unchanged(snap, "merge_pairs")
    ref_w, ref_m, ref_P, ref_mask = g.w.copy(), g.m.copy(), g.P.copy(), g.mask.copy()
    for i, j in pairs:
        (_, W, mean, cov), = _ref_greedy(np.array([g.w[i], g.w[j]]), np.array([g.m[i], g.m[j]]),
                                         np.array([g.P[i], g.P[j]]), [0, 1], np.inf)[0]
        ref_w[i], ref_m[i], ref_P[i] = W, mean, cov
        ref_w[j], ref_m[j], ref_P[j], ref_mask[j] = 0.0, 0.0, np.eye(d), False
    assert np.array_equal(out.mask, ref_mask)
    _close_weights(out.w, ref_w, "merge_pairs weights")
    _close(out.m, ref_m, 1, "merge_pairs means")
    _close(out.P, ref_P, 2, "merge_pairs covariances")


# ====================================================================== gm layout
@given(seed=seeds, batch=st.sampled_from([(), (1,), (3,), (2, 2)]), Q=st.integers(0, 6), d=st.sampled_from([1, 3]),
       cap=st.sampled_from([None, 0, 1, 2, 8]), ties=st.booleans())
def test_compact_and_concat_equal_per_mixture_reference(seed, batch, Q, d, cap, ties):
    rng = np.random.default_rng(seed)
    n = int(np.prod(batch, dtype=int))
    w = rng.choice([0.2, 0.5, 0.7], (n, Q)) if ties else rng.uniform(0, 1, (n, Q))
    mask = rng.random((n, Q)) < 0.7
    w[~mask] = 0.0
    m = rng.normal(0, 1, (n, Q, d))
    P = rand_spd(rng, (n, Q), d, 1.0)
    m[~mask], P[~mask] = 0.0, np.eye(d)
    g = GM(w.reshape(batch + (Q,)), m.reshape(batch + (Q, d)), P.reshape(batch + (Q, d, d)), mask.reshape(batch + (Q,)))
    snap = _gm_snapshot(g)
    out = gm_mod.compact(g, cap)
    again = gm_mod.compact(out, cap)  # already in order: the view path
    _unchanged(snap, "compact")
    want_cap = int(mask.sum(1).max(initial=0)) if cap is None else cap
    for res in (out, again):
        assert res.batch_shape == batch and res.capacity == want_cap and res.dim == d
        rw, rm, rP, rmask = (a.reshape((n,) + a.shape[len(batch):]) for a in (res.w, res.m, res.P, res.mask))
        for k in range(n):
            order = sorted(np.nonzero(mask[k])[0], key=lambda i: -w[k, i])[:want_cap]  # stable
            L = len(order)
            assert rmask[k, :L].all() and not rmask[k, L:].any()
            assert np.all(rw[k, L:] == 0.0)
            assert np.array_equal(rw[k, :L], w[k, order])
            assert np.array_equal(rm[k, :L], m[k, order]) and np.array_equal(rP[k, :L], P[k, order])
    h = gm_mod.concat(g, out)
    _unchanged(snap, "concat")
    hw, hm, hP, hmask = (a.reshape((n,) + a.shape[len(batch):]) for a in (h.w, h.m, h.P, h.mask))
    ow, om, oP, omask = (a.reshape((n,) + a.shape[len(batch):]) for a in (out.w, out.m, out.P, out.mask))
    for k in range(n):
        assert np.array_equal(hw[k], list(w[k]) + list(ow[k]))
        assert np.array_equal(hmask[k], list(mask[k]) + list(omask[k]))
        assert np.array_equal(hm[k].reshape(-1, d), np.array(list(m[k]) + list(om[k])).reshape(-1, d))
        assert np.array_equal(hP[k].reshape(-1, d, d), np.array(list(P[k]) + list(oP[k])).reshape(-1, d, d))


# ====================================================================== birth


@given(seed=seeds, P_=st.integers(1, 3), J=st.integers(0, 3), lm_type=st.sampled_from([VA, SP]))
@example(seed=1, P_=1, J=0, lm_type=SP).via("no measurement")
@example(seed=2, P_=1, J=1, lm_type=VA).via("P == 1, J == 1")
def test_birth_kernels_equal_the_per_point_inversion(seed, P_, J, lm_type):
    rng = np.random.default_rng(seed)
    s = rand_states(rng, P_)
    R = rand_R(rng)
    # TOA - B from 0.3 to 3 times the BS distance: some SP inversions are invalid (L <= |b - u|)
    lm = rand_landmarks(rng, np.broadcast_to(s[0, :3], (J, 3)), lm_type)
    Z = measure(s[0], lm, Bounce.SCATTER, BS_POS)
    Z[:, 0] = s[0, 6] + np.linalg.norm(BS_POS - s[0, :3]) * rng.uniform(0.3, 3.0, J)
    snap = _snapshot(s, Z, R)
    ref_mean, ref_cov, ref_ok, ref_pos, ref_valid = _ref_birth(s, Z, R, lm_type)
    mean, cov, ok = birth_mod.birth_moments(s, Z, R, geometry_of(lm_type), BS_POS)
    both = birth_mod.birth_moments_by_kind(s, Z, R, (geometry_of(VA), geometry_of(SP)), BS_POS)  # keyed by geometry
    _unchanged(snap, "birth_moments")
    assert np.array_equal(ok, ref_ok)
    _close(mean[ok], ref_mean[ok], 1, "birth mean")
    _close(cov[ok], ref_cov[ok], 2, "birth covariance")
    for a, b in zip(both[geometry_of(lm_type)], (mean, cov, ok)):
        assert np.array_equal(a, b)
    # the inversion of every cubature point x particle (the per-point kernel and its NumPy API)
    zpts = ckf.cubature_points(Z, np.broadcast_to(R, (J, 5, 5)))  # (J, 10, 5)
    inv = birth_mod.invert_va if lm_type == VA else birth_mod.invert_sp
    pos, valid = inv(s[None, None, :, :], zpts.transpose(1, 0, 2)[:, :, None, :], BS_POS)  # (10, J, P)
    assert np.array_equal(valid, ref_valid)
    _close(pos[valid], ref_pos[valid], 1, "invert_* positions")


# ====================================================================== detection, VS prediction, particles
@given(seed=seeds, shape=st.sampled_from([(0,), (1,), (4,), (2, 3)]), lm_type=st.sampled_from([BS, VA, SP, VS]))
def test_fov_detect_prob_equals_the_norm_rule(seed, shape, lm_type):
    from mmslam.scenes.scenario import load_preset
    from mmslam.slam.sim.sensor import fov_detect_prob

    sp = load_preset("paper").sensor
    rng = np.random.default_rng(seed)
    u = rng.uniform(-50, 50, shape + (3,))
    x = u + rand_dirs(rng, shape) * rng.uniform(0, 2 * sp.fov_range, shape)[..., None]
    snap = _snapshot(u, x)
    got = fov_detect_prob(u, x, lm_type, sp)
    _unchanged(snap, "fov_detect_prob")
    ref = np.array([sp.p_detect if lm_type in (BS, VA) or np.linalg.norm(xi - ui) <= sp.fov_range else 0.0
                    for ui, xi in zip(u.reshape(-1, 3), x.reshape(-1, 3))]).reshape(shape)
    assert np.array_equal(got, ref)


@given(seed=seeds, batch=st.sampled_from([(), (1,), (3,)]), Q=st.integers(0, 4), dither=st.booleans(),
       cond=st.sampled_from([0.0, 2.0, 4.0]))
def test_predict_vs_equals_the_per_component_ekf_prediction(seed, batch, Q, dither, cond):
    from mmslam.slam.models.dynamics import vs_ct, vs_ct_jacobian
    from mmslam.slam.models.vs import predict_vs

    rng = np.random.default_rng(seed)
    n = int(np.prod(batch, dtype=int))
    s = rand_states(rng, max(n, 1))
    g = rand_landmark_gm(rng, s, VS, Q, cond)
    g = GM(g.w[:n].reshape(batch + (Q,)), g.m[:n].reshape(batch + (Q, 7)), g.P[:n].reshape(batch + (Q, 7, 7)),
           g.mask[:n].reshape(batch + (Q,)))
    dt, ps = 0.1, 0.97
    q_std = rng.uniform(0.01, 1.0, 7)
    dith = rng.uniform(0.0, 0.5, 7) if dither else None
    snap = _gm_snapshot(g)
    out = predict_vs(g, dt, ps, q_std, dith)
    _unchanged(snap, "predict_vs")
    add = np.diag(q_std**2) + (np.diag(dith) if dither else 0.0)
    for idx in np.ndindex(*(batch + (Q,))):
        if not g.mask[idx]:
            assert not out.mask[idx] and out.w[idx] == 0.0
            assert np.all(out.m[idx] == 0.0) and np.array_equal(out.P[idx], np.eye(7))
            continue
        Jm = vs_ct_jacobian(g.m[idx][None], dt)[0]
        assert out.mask[idx] and out.w[idx] == ps * g.w[idx]
        _close(out.m[idx], vs_ct(g.m[idx][None], dt)[0], 1, "predict_vs mean")
        _close(out.P[idx], Jm @ g.P[idx] @ Jm.T + add, 2, "predict_vs covariance")


@given(seed=seeds, P_=st.integers(1, 6), spread=st.sampled_from([0.0, 1.0, 50.0, 800.0]))
def test_particle_weight_kernels_equal_their_textbook_forms(seed, P_, spread):
    from mmslam.slam.models.dynamics import wrap_angle
    from mmslam.slam.filter.rbpf import (normalise_log_weights, systematic_resample, weighted_state_cov,
                                  weighted_state_mean)

    rng = np.random.default_rng(seed)
    logw = rng.normal(0.0, 1.0, P_) * spread - 300.0
    snap = _snapshot(logw)
    lw, w = normalise_log_weights(logw)
    _unchanged(snap, "normalise_log_weights")
    _close_scalar(lw, logw - logsumexp(logw), "normalised log-weights")
    _close_weights(w, np.exp(logw - logsumexp(logw)), "normalised weights")
    u0 = np.random.default_rng(seed).random()
    idx = systematic_resample(w, np.random.default_rng(seed))
    c = np.cumsum(w)
    c[-1] = 1.0
    ref = [min(int(np.sum(c <= (u0 + i) / P_)), P_ - 1) for i in range(P_)]  # first k with c[k] > u_i
    assert list(idx) == ref
    s = rand_states(rng, P_)
    snap = _snapshot(s, w)
    mean = weighted_state_mean(s, w)
    cov = weighted_state_cov(s, w, mean)
    _unchanged(snap, "weighted_state_mean / cov")
    ref_mean = np.array([sum(w[p] * s[p, i] for p in range(P_)) for i in range(7)])
    ref_mean[3] = np.angle(sum(w[p] * np.exp(1j * s[p, 3]) for p in range(P_)))
    lin = [0, 1, 2, 4, 5, 6]  # all but the heading (a circular mean)
    _close(mean[lin], ref_mean[lin], 1, "weighted mean")
    assert abs(_wrap(mean[3] - ref_mean[3])) <= RTOL * np.pi
    dev = s - ref_mean
    dev[:, 3] = wrap_angle(dev[:, 3])
    _close(cov, sum(w[p] * np.outer(dev[p], dev[p]) for p in range(P_)), 2, "weighted covariance")
