"""CKF machinery and GM-PHD correction (slam/phd/gmphd.py); Jacobians used by the filter."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.slam.models.dynamics import vs_ct, vs_ct_jacobian
from mmslam.slam.core.gm import GM
from mmslam.slam.phd.ckf import cubature_points, innovate, kalman_update
from mmslam.slam.phd.gmphd import bs_logterm, corrected_gm, log_psi, type_terms
from mmslam.slam.models.measurement import SP, VA, VS, measure
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import geometry_of
from mmslam.slam.specs.landmarks import landmark_type

KINDS = {t.code: t for t in (landmark_type("VA"), landmark_type("SP"), landmark_type("VS"))}
"""Type code -> spec: what gmphd.correct is handed about each map's type."""

BS_POS = np.array([0.0, 0.0, 40.0])
R = np.diag([0.3, 0.03, 0.03, 0.03, 0.03]) ** 2


def _spd(rng, d, scale=1.0):
    A = rng.standard_normal((d, d))
    return scale * (A @ A.T + d * np.eye(d))


# The CKF is exact for a linear measurement (3-D and 7-D through the position marginal):
# tests/test_kernels_reference.py::test_reference_ckf_is_the_kalman_filter_for_a_linear_measurement,
# with the kernel equal to that reference to 1e-9 (test_ckf_update_and_kalman_update_equal_the_per_gaussian_ckf).


def test_cubature_points_reproduce_mean_and_covariance():
    rng = np.random.default_rng(0)
    m = rng.standard_normal((4, 7))
    P = np.stack([_spd(rng, 7) for _ in range(4)])
    X = cubature_points(m, P)
    assert X.shape == (4, 14, 7)
    assert np.allclose(X.mean(1), m)
    D = X - m[:, None]
    assert np.allclose(np.einsum("nka,nkb->nab", D, D) / 14, P)


def test_ckf_handles_azimuth_wrap_at_pi():
    # vehicle heading 0, SP straight behind it: body AOA azimuth ~ +-pi
    s = np.array([50.0, 0.0, 0.0, 0.0, 20.0, 0.3, 0.0])
    lm = np.array([30.0, 0.0, 5.0])
    P = np.eye(3) * 0.5
    ztrue = measure(s, lm, Bounce.SCATTER, BS_POS)
    assert abs(abs(ztrue[3]) - np.pi) < 0.1
    m_post, P_post, ll = kalman_update(lm, P, ztrue, R, s, geometry_of(SP), BS_POS)
    # a naive mean over +-pi would give zhat ~ 0, a residual ~ pi and a log-likelihood ~ -pi^2 / (2 0.03^2)
    assert ll > -20.0
    assert np.abs(m_post - lm).max() < 0.5 and np.all(np.linalg.eigvalsh(P_post) > 0)


def test_vs_ct_jacobian_matches_finite_differences():
    # used by predict_vs inside the VS map prediction
    rng = np.random.default_rng(3)
    for xi in (0.3, -0.7, 1e-7, 0.0):
        t = np.array([10.0, -5.0, 1.0, 12.0, -3.0, 0.2, xi]) + np.r_[rng.standard_normal(6), 0.0]
        J = vs_ct_jacobian(t, 0.5)
        eps = 1e-6
        Jfd = np.stack([(vs_ct(t + eps * e, 0.5) - vs_ct(t - eps * e, 0.5)) / (2 * eps) for e in np.eye(7)], 1)
        assert np.allclose(J, Jfd, atol=1e-6)


def _pd(u, x, t):
    inside = (t == VA) | (np.linalg.norm(np.asarray(u) - np.asarray(x), axis=-1) <= 50.0)
    return np.where(inside, 0.95, 0.0)


def test_phd_correction_weights_partition_each_measurement():
    """For every z: sum of updated weights + (c + BS term)/psi = 1 (eq. prevCorrPHD)."""
    rng = np.random.default_rng(5)
    P_, Q = 4, 3
    s = np.tile([70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0], (P_, 1))
    s[:, 0:2] += rng.standard_normal((P_, 2)) * 0.3
    sp = np.array([[60.0, 40.0, 5.0], [60.0, 20.0, 5.0], [-55.0, 55, 10.0]])
    g = GM(np.tile([0.9, 0.5, 0.7], (P_, 1)), np.tile(sp, (P_, 1, 1)) + rng.standard_normal((P_, Q, 3)),
           np.tile(np.eye(3), (P_, Q, 1, 1)), np.ones((P_, Q), bool))
    Z = np.stack([measure(s[0], sp[1], Bounce.SCATTER, BS_POS), measure(s[0], BS_POS, Bounce.DIRECT, BS_POS),
                  np.array([150.0, 1.0, 0.1, -2.0, 0.2])])
    tc = type_terms(g, landmark_type(SP), s, Z, R, BS_POS, _pd)
    bt = bs_logterm(s, Z, R, BS_POS, np.full(P_, 0.95))
    lc = np.log(1.2832e-5)
    lp = log_psi([tc], bt, lc, (P_, 3))
    out = corrected_gm(tc, Z, lp)
    assert out.w.shape == (P_, Q * 4)
    det = out.w[:, Q:].reshape(P_, Q, 3).sum(1)
    total = det + np.exp(lc - lp) + np.exp(bt - lp)
    assert np.allclose(total, 1.0)
    # the SP outside the 50 m FOV (third) is not detected: its missed weight is its full weight
    assert np.allclose(out.w[:, 2], 0.7)
    assert np.allclose(out.w[:, 0], 0.05 * 0.9)
    # the measurement of SP 2 is explained by it, the BS measurement by the BS, the third by clutter
    assert np.all(out.w[:, Q:].reshape(P_, Q, 3)[:, 1, 0] > 0.5)
    assert np.all(np.exp(bt[:, 1] - lp[:, 1]) > 0.99)
    assert np.all(np.exp(lc - lp[:, 2]) > 0.99)


def test_vs_correction_moves_velocity_only_through_correlation():
    s = np.array([[70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0]])
    t_true = np.array([60.73, 0.0, 0.0])
    m = np.array([[[61.5, 0.5, 0.3, 0.0, 19.0, 0.0, 0.3]]])
    P = np.diag([4.0, 4.0, 1.0, 9.0, 9.0, 0.1, 0.2])
    P[0, 3] = P[3, 0] = 3.0  # x correlated with vx
    g = GM(np.array([[1.0]]), m, P[None, None], np.ones((1, 1), bool))
    Z = measure(s[0], t_true, Bounce.SCATTER, BS_POS)[None]
    tc = type_terms(g, landmark_type(VS), s, Z, R, BS_POS, _pd)
    lp = log_psi([tc], None, np.log(1.2832e-5), (1, 1))
    out = corrected_gm(tc, Z, lp)
    upd = out.m[0, 1]
    assert np.linalg.norm(upd[:3] - t_true) < np.linalg.norm(m[0, 0, :3] - t_true)
    assert upd[3] != m[0, 0, 3]          # correlated velocity component moved
    assert np.isclose(upd[4], m[0, 0, 4])  # uncorrelated one did not
    assert np.all(np.linalg.eigvalsh(out.P[0, 1]) > 0)


def test_nan_in_a_map_raises_floating_point_error():
    s = np.array([[70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0]])
    g = GM(np.array([[1.0]]), np.array([[[np.nan, 0.0, 0.0]]]), np.eye(3)[None, None], np.ones((1, 1), bool))
    with pytest.raises(FloatingPointError):
        type_terms(g, landmark_type(SP), s, np.zeros((1, 5)), R, BS_POS, _pd)


def test_a_non_finite_mean_anywhere_in_a_map_raises():
    """A NaN / inf mean in a masked slot or in a slot outside the FOV (no CKF update) is refused
    too (the check runs in the compiled slot pass, over every slot)."""
    s = np.array([[70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0]])
    m = np.zeros((1, 3, 3)) + 10.0
    m[0, 2] = 1e4  # far outside the SP range gate: p_D = 0
    for slot, bad in ((1, np.nan), (2, np.inf)):
        mb = m.copy()
        mb[0, slot, 1] = bad
        g = GM(np.ones((1, 3)), mb, np.broadcast_to(np.eye(3), (1, 3, 3, 3)).copy(), np.array([[True, False, True]]))
        with pytest.raises(FloatingPointError, match="non-finite mean or covariance in SP correction"):
            type_terms(g, landmark_type(SP), s, np.zeros((1, 5)), R, BS_POS, lambda u, x, t: np.where(np.abs(x[..., 0]) < 100, 0.9, 0.0))


def test_cholesky_and_triangular_solves_match_lapack():
    from scipy.linalg import solve_triangular

    from mmslam.slam.core.linalg import back_solve, forward_solve, safe_cholesky

    rng = np.random.default_rng(9)
    for d in (3, 5, 7):
        A = np.stack([_spd(rng, d) for _ in range(6)]).reshape(2, 3, d, d)
        L = safe_cholesky(A, "test")
        np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-9, atol=1e-12)
        b, x = rng.standard_normal(d), np.empty(d)
        forward_solve(L[0, 0], b, x)
        np.testing.assert_allclose(x, solve_triangular(L[0, 0], b, lower=True), rtol=1e-9, atol=1e-12)
        back_solve(L[0, 0], b, x)
        np.testing.assert_allclose(x, solve_triangular(L[0, 0].T, b), rtol=1e-9, atol=1e-12)
    bad = np.diag([1.0, -1.0, 1.0])[None]
    with pytest.raises(FloatingPointError, match="not positive definite in test stage"):
        safe_cholesky(bad, "test stage")


def test_pruned_correction_equals_dense_correction_after_pruning():
    rng = np.random.default_rng(11)
    P_, Q = 5, 4
    s = np.tile([70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0], (P_, 1))
    s[:, 0:2] += rng.standard_normal((P_, 2)) * 0.3
    m = np.array([60.0, 20.0, 5.0]) + rng.standard_normal((P_, Q, 3)) * 2
    g = GM(rng.uniform(0.01, 1, (P_, Q)), m, np.tile(np.eye(3) * 2, (P_, Q, 1, 1)), rng.random((P_, Q)) < 0.8)
    Z = np.stack([measure(s[0], np.array([60.0, 20.0, 5.0]), Bounce.SCATTER, BS_POS), measure(s[0], np.array([61.0, 22.0, 4.0]), Bounce.SCATTER, BS_POS)])
    tc = type_terms(g, landmark_type(SP), s, Z, R, BS_POS, _pd)
    lp = log_psi([tc], None, np.log(1.2832e-5), (P_, 2))
    dense = corrected_gm(tc, Z, lp)
    pruned = corrected_gm(tc, Z, lp, prune=0.05)
    for p in range(P_):
        keep = dense.mask[p] & (dense.w[p] >= 0.05)
        assert pruned.mask[p].sum() == keep.sum()
        n = keep.sum()
        assert np.allclose(pruned.w[p, :n], dense.w[p][keep])
        assert np.allclose(pruned.m[p, :n], dense.m[p][keep])
        assert np.allclose(pruned.P[p, :n], dense.P[p][keep])
    assert pruned.capacity < dense.capacity


@pytest.mark.parametrize("lm_type", [VA, SP, VS])
def test_measure_equals_channel_params_in_the_body_frame(lm_type):
    from mmslam.slam.models.dynamics import wrap_angle
    from mmslam.slam.models.measurement import channel_params, to_body

    rng = np.random.default_rng(lm_type)
    s = np.column_stack([rng.uniform(-80, 80, (6, 2)), rng.uniform(0, 2, 6), rng.uniform(-4, 4, 6),
                         np.full(6, 20.0), np.full(6, 0.3), rng.uniform(0, 300, 6)])
    if lm_type == VA:
        pts = np.array([[200.0, 0, 40], [0, -200.0, 40], [-200.0, 0, 40]])[rng.integers(0, 3, (6, 4, 5))]
        pts = pts + rng.standard_normal(pts.shape)
    else:
        pts = np.concatenate([rng.uniform(-90, 90, (6, 4, 5, 2)), rng.uniform(0, 40, (6, 4, 5, 1))], -1)
    got = measure(s[:, None, None, :], pts, geometry_of(lm_type), BS_POS)
    u = np.broadcast_to(s[:, None, None, :3], pts.shape)
    ref = to_body(channel_params(u, pts, geometry_of(lm_type), BS_POS), s[:, None, None, 3], s[:, None, None, 6])
    d = got - ref
    d[..., 3] = wrap_angle(d[..., 3])
    assert np.abs(d).max() < 1e-9


def test_cholesky_without_retry_rejects_indefinite_and_singular():
    from mmslam.slam.core.linalg import cholesky

    L = np.empty((3, 3))
    assert not cholesky(np.diag([1.0, -1.0, 1.0]), L, False)
    assert not cholesky(np.zeros((3, 3)), L, False)
    assert not cholesky(np.diag([1.0, np.nan, 1.0]), L)
    assert cholesky(np.diag([4.0, 1.0, 9.0]), L, False) and np.array_equal(L, np.diag([2.0, 1.0, 3.0]))


@pytest.mark.parametrize("lm_type", [VA, SP, VS])
def test_innovate_on_a_padded_batch_equals_kalman_update_per_gaussian(lm_type):
    """The batched kernel gives each Gaussian the result of the single-Gaussian update."""
    rng = np.random.default_rng(30 + lm_type)
    P_, Q, d = 3, 4, (7 if lm_type == VS else 3)
    s = np.tile([70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0], (P_, 1))
    s[:, 0:2] += rng.standard_normal((P_, 2))
    s[:, 3] += 0.05 * rng.standard_normal(P_)
    base = np.array([200.0, 10.0, 30.0]) if lm_type == VA else np.array([60.0, 20.0, 5.0])
    m = np.zeros((P_, Q, d))
    m[..., :3] = base + rng.standard_normal((P_, Q, 3)) * 3
    if d == 7:
        m[..., 3:] = rng.standard_normal((P_, Q, 4))
    Pm = np.stack([_spd(rng, d, 0.3) for _ in range(P_ * Q)]).reshape(P_, Q, d, d)
    Z = np.stack([measure(s[0], base + rng.standard_normal(3), geometry_of(lm_type), BS_POS) for _ in range(3)])
    inn = innovate(m.reshape(-1, d), Pm.reshape(-1, d, d), np.repeat(s, Q, 0), geometry_of(lm_type), BS_POS, Z, R, "test")
    for n in range(P_ * Q):
        for j in range(3):
            mk, Pk, llk = kalman_update(m.reshape(-1, d)[n], Pm.reshape(-1, d, d)[n], Z[j], R, s[n // Q],
                                        geometry_of(lm_type), BS_POS)
            np.testing.assert_allclose(inn.loglik[n, j], llk, rtol=1e-12)
            np.testing.assert_allclose(inn.m_post[n, j], mk, rtol=1e-12)
            np.testing.assert_allclose(inn.P_post[n, 0], Pk, rtol=1e-12, atol=1e-15)


def test_correction_skips_undetectable_gaussians_exactly():
    """Gaussians with p_D = 0 get no innovation: weights and kept components are unchanged vs the
    dense formula (pD = 0 -> detection weight 0, missed weight = w), the others are updated."""
    rng = np.random.default_rng(12)
    P_, Q = 3, 4
    s = np.tile([70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0], (P_, 1))
    near = np.array([60.0, 20.0, 5.0])
    m = np.where(np.arange(Q)[None, :, None] % 2 == 0, near, np.array([-60.0, -40.0, 5.0]))
    m = m + rng.standard_normal((P_, Q, 3))
    g = GM(np.full((P_, Q), 0.8), m, np.tile(np.eye(3), (P_, Q, 1, 1)), np.ones((P_, Q), bool))
    Z = measure(s[0], near, Bounce.SCATTER, BS_POS)[None]
    tc = type_terms(g, landmark_type(SP), s, Z, R, BS_POS, _pd)
    assert np.all(tc.det_index[:, 1::2] == -1) and np.all(tc.det_index[:, 0::2] >= 0)
    assert np.all(np.isneginf(tc.logq[:, 1::2]))
    lp = log_psi([tc], None, np.log(1.2832e-5), (P_, 1))
    out = corrected_gm(tc, Z, lp)
    assert np.allclose(out.w[:, 1:Q:2], 0.8)  # missed weight = full weight
    det_w = out.w[:, Q:].reshape(P_, Q)
    assert np.all(det_w[:, 1::2] == 0.0) and np.all(det_w[:, 0::2] > 0)


LSE_ULPS = 4
"""The compiled kernel takes exp / log from libm, NumPy from its own SIMD routines, which differ by an ulp on some
CPUs (AVX-512) and NumPy builds (measured: at most 1): the two forms agree to :data:`LSE_ULPS` ulps of the larger
of the two summands ``max`` and ``log(sum exp(. - max))``, not bit for bit."""


def _same_lse(got: np.ndarray, ref: np.ndarray, safe: np.ndarray) -> None:
    np.testing.assert_array_equal(np.isneginf(got), np.isneginf(ref))  # the empty rows exactly
    fin = np.isfinite(ref)
    ulp = np.spacing(np.maximum(np.abs(safe), np.abs(ref - safe))[fin])
    assert np.all(np.abs(got[fin] - ref[fin]) <= LSE_ULPS * ulp), np.max(np.abs(got[fin] - ref[fin]) / ulp)


@pytest.mark.parametrize("Q,J", [(1, 1), (5, 1), (12, 1), (3, 2), (11, 3), (18, 7), (40, 9)])
def test_logsumexp_slots_equals_direct_form(Q, J):
    """_logsumexp_slots == the direct max / exp / sum over axis 1 to a few ulps (:data:`LSE_ULPS`; -inf rows kept
    exactly)."""
    from mmslam.slam.phd.gmphd import _logsumexp_slots

    rng = np.random.default_rng(Q * 10 + J)
    lq = rng.normal(size=(50, Q, J)) * 20.0
    lq[rng.random(lq.shape) < 0.4] = -np.inf
    lq[0] = -np.inf
    mx = lq.max(axis=1)
    safe = np.where(np.isfinite(mx), mx, 0.0)
    with np.errstate(divide="ignore"):
        ref = safe + np.log(np.exp(lq - safe[:, None, :]).sum(axis=1))
    _same_lse(_logsumexp_slots(lq), ref, safe)


@pytest.mark.parametrize("Q,J", [(129, 1), (300, 1), (1000, 1), (300, 3)])
def test_logsumexp_slots_equals_direct_form_on_long_slot_axes(Q, J):
    """NumPy's max / exp / sum to a few ulps (:data:`LSE_ULPS`) also where its sum splits the slots into halves
    (J = 1, more than 128 terms), with terms ~800 below the maximum whose exp underflows to 0
    (the kernel skips them) and with rows of one finite slot."""
    from mmslam.slam.phd.gmphd import _logsumexp_slots

    rng = np.random.default_rng(Q + J)
    lq = rng.normal(size=(6, Q, J)) * 30.0
    lq[rng.random(lq.shape) < 0.3] -= 800.0
    lq[rng.random(lq.shape) < 0.2] = -np.inf
    lq[1] = -np.inf
    lq[1, Q // 2] = -3.0
    mx = lq.max(axis=1)
    safe = np.where(np.isfinite(mx), mx, 0.0)
    with np.errstate(divide="ignore"):
        ref = safe + np.log(np.exp(lq - safe[:, None, :]).sum(axis=1))
    _same_lse(_logsumexp_slots(lq), ref, safe)
    np.testing.assert_array_equal(ref[1], -3.0)


@pytest.mark.parametrize("shape", [(1, 3, 4), (5, 1, 2), (1, 1, 3), (4, 3, 2), (3, 2, 1), (1, 1, 1)])
def test_logsumexp_slots_equals_reference_and_leaves_its_input_alone(shape):
    """Regression: P == 1 or Q == 1 with J >= 2 made the slot-first copy a view of ``logq`` and
    the in-place exp rewrote it (corrected_gm reads it afterwards: weights of ~1/clutter)."""
    from scipy.special import logsumexp

    from mmslam.slam.phd.gmphd import _logsumexp_slots

    rng = np.random.default_rng(sum(shape))
    logq = rng.normal(-20.0, 5.0, size=shape)
    logq[rng.random(shape) < 0.2] = -np.inf
    before = logq.copy()
    with np.errstate(divide="ignore"):
        ref = logsumexp(logq, axis=1)
    got = _logsumexp_slots(logq)
    assert np.array_equal(logq, before)
    assert np.allclose(got, ref, rtol=1e-12, atol=0.0) or np.array_equal(got, ref)
    assert np.array_equal(np.isneginf(got), np.isneginf(ref))


def test_extent_is_the_scatter_point_model_z_equals_h_of_x_plus_e():
    """Extended VS (a car body): z = h(x + e) + n, e ~ N(0, E) independent of the 7-D state x.
    (1) the likelihood is that of a point landmark with position covariance P_pos + E (same cubature);
    (2) the posterior correction P - P_post = Pxz S^-1 Pxz^T agrees with a Monte Carlo estimate from
    400k samples (and differs from the point model's)."""
    rng = np.random.default_rng(4)
    bs = np.array([0.0, 0.0, 40.0])
    m = np.array([[30.0, 12.0, 0.5, 3.0, -2.0, 0.0, 0.1]])
    A = rng.normal(size=(7, 7)) * 0.3
    P = (A @ A.T + np.diag([0.5, 0.5, 0.05, 1.0, 1.0, 0.01, 0.01]))[None]
    E = np.diag([1.0, 1.0, 0.09])
    st = np.array([[20.0, 5.0, 0.0, 0.3, 10.0, 0.0, 2.0]])
    Rm = np.diag([0.09, 1e-3, 1e-3, 1e-3, 1e-3])
    Z = np.array([[55.0, 0.4, -0.5, 0.6, -0.01]])
    geo = geometry_of(VS)
    ext = innovate(m, P, st, geo, bs, Z, Rm, "test", extent=E)
    Pi = P.copy()
    Pi[0, :3, :3] += E
    infl = innovate(m, Pi, st, geo, bs, Z, Rm, "test")
    np.testing.assert_allclose(ext.loglik, infl.loglik, rtol=1e-12)
    # Pxz_ext = P[:, :3] (P_pos + E)^-1 Pxz_infl[:3] with the same S: so are the mean corrections
    np.testing.assert_allclose(ext.m_post[0, 0] - m[0], P[0][:, :3] @ np.linalg.solve(Pi[0][:3, :3], infl.m_post[0, 0, :3] - m[0, :3]),
                               rtol=1e-9, atol=1e-12)
    x = rng.multivariate_normal(m[0], P[0], size=400_000)
    e = rng.multivariate_normal(np.zeros(3), E, size=400_000)
    z = measure(np.broadcast_to(st[0], (len(x), 7)), x[:, :3] + e, Bounce.SCATTER, bs)
    mc = (x - x.mean(0)).T @ (z - z.mean(0)) / len(x)  # (7, 5)
    S_mc = np.cov(z.T, bias=True) + Rm
    red_mc = mc @ np.linalg.solve(S_mc, mc.T)
    red_ext = P[0] - ext.P_post[0, 0]
    red_pt = P[0] - infl.P_post[0, 0]
    np.testing.assert_allclose(red_ext, red_mc, atol=0.05 * np.abs(red_ext).max())
    assert np.abs(red_ext - red_pt[:7, :7]).max() > 0.2 * np.abs(red_ext).max()  # the point model differs


@pytest.mark.parametrize("lm_type", [VA, VS])
def test_per_measurement_R_equal_to_the_shared_R_gives_the_shared_innovation(lm_type):
    """R (J, 5, 5) with every R_j = R is the constant model: same likelihoods and residuals, and each
    measurement's gain / posterior equals the shared one; a larger R_j lowers that likelihood peak."""
    rng = np.random.default_rng(1)
    d = 7 if lm_type == VS else 3
    bs = np.array([0.0, 0.0, 40.0])
    m = np.c_[rng.uniform(20, 60, (4, 2)), rng.uniform(0, 5, (4, 1)), rng.normal(size=(4, d - 3))]
    A = rng.normal(size=(4, d, d)) * 0.3
    P = A @ A.transpose(0, 2, 1) + np.eye(d) * 0.5
    st = np.c_[rng.uniform(-5, 5, (4, 3)), rng.uniform(-1, 1, (4, 1)), np.full((4, 2), 5.0), np.full((4, 1), 2.0)]
    R = np.diag([0.09, 1e-3, 1e-3, 1e-3, 1e-3])
    Z = np.array([[70.0, 0.3, -0.4, 0.5, -0.1], [90.0, 1.0, -0.2, 1.1, 0.0], [60.0, 0.1, -0.5, 0.2, 0.05]])
    geo = geometry_of(lm_type)
    shared = innovate(m, P, st, geo, bs, Z, R, "t")
    per = innovate(m, P, st, geo, bs, Z, np.stack([R] * 3), "t")
    np.testing.assert_allclose(per.loglik, shared.loglik, rtol=1e-12)
    np.testing.assert_allclose(per.m_post, shared.m_post, rtol=1e-12, atol=1e-15)
    for j in range(3):
        np.testing.assert_allclose(per.post(np.arange(4), np.full(4, j)), shared.P_post[:, 0], rtol=1e-12)
    wide = innovate(m, P, st, geo, bs, Z, np.stack([R, 4 * R, R]), "t")
    np.testing.assert_allclose(wide.loglik[:, [0, 2]], shared.loglik[:, [0, 2]], rtol=1e-12)
    assert not np.allclose(wide.loglik[:, 1], shared.loglik[:, 1])
    bs_shared = bs_logterm(st, Z, R, bs, np.full(4, 0.9))
    np.testing.assert_allclose(bs_logterm(st, Z, np.stack([R] * 3), bs, np.full(4, 0.9)), bs_shared, rtol=1e-12)


@pytest.mark.parametrize("prune", [None, 1e-3])
def test_correct_with_per_measurement_R_extent_and_beta_equals_per_gaussian_innovations(prune):
    """gmphd.correct (the compiled type kernels) against a per-Gaussian reference built on
    ckf.innovate (its own compiled batch) and scipy's logsumexp: one R_j per measurement, a VS
    extent (car body), Beta detection parameters (E[p_D] = s / (s + t); missed (s, t + 1) in the
    FOV, (s, t) outside; detected (s + 1, t)), a Gaussian outside the FOV and a dead slot; dense
    layout and pruned (the dense components of weight >= prune, in order)."""
    from scipy.special import logsumexp

    from mmslam.slam.phd.gmphd import correct

    rng = np.random.default_rng(11)
    P_, J = 3, 3
    s = np.c_[rng.uniform(10, 30, (P_, 2)), np.zeros(P_), rng.uniform(-1, 1, P_), np.full(P_, 10.0),
              np.zeros(P_), rng.uniform(0, 3, P_)]
    far = 400.0  # beyond the range gate of pd_fn below
    maps, truth = {}, {}
    for t, d, Q in ((VA, 3, 3), (VS, 7, 2)):
        lm = np.c_[rng.uniform(30, 60, (P_, Q, 2)), rng.uniform(0, 4, (P_, Q, 1))]
        m = np.concatenate([lm + rng.normal(0, 0.5, lm.shape), rng.normal(0, 1, (P_, Q, d - 3))], -1)
        m[0, 0, :2] = far
        A = rng.normal(size=(P_, Q, d, d)) * 0.2
        P = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(d)
        mask = np.ones((P_, Q), bool)
        mask[1, Q - 1] = False
        w = np.where(mask, rng.uniform(0.2, 1.0, (P_, Q)), 0.0)
        P[~mask] = np.eye(d)
        m[~mask] = 0.0
        beta = np.where(mask[..., None], rng.uniform(1.0, 5.0, (P_, Q, 2)), 1.0)
        maps[t] = GM(w, m, P, mask, beta)
        truth[t] = lm[0, 1]
    Z = np.stack([measure(s[0], truth[VA], Bounce.MIRROR, BS_POS), measure(s[0], truth[VS], Bounce.SCATTER, BS_POS),
                  measure(s[0], np.array([45.0, 20.0, 1.0]), Bounce.MIRROR, BS_POS)])
    Rz = np.stack([R, 2.0 * R, 0.5 * R])
    ext = {VS: np.diag([1.0, 0.5, 0.09]), VA: None}
    lc = np.log(1e-5)
    p_bs = np.full(P_, 0.9)

    def pd_fn(u, x, t):
        return np.where(np.linalg.norm(x - u, axis=-1) < 200.0, 0.8, 0.0)

    out, lpsi, _ = correct(maps, s, Z, Rz, BS_POS, pd_fn, p_bs, lc, prune, ext, 3, KINDS)
    # reference: every live Gaussian with p_D > 0 on its own through ckf.innovate
    ref = {}
    for t, g in maps.items():
        Q, d = g.capacity, g.dim
        logq = np.full((P_, Q, J), -np.inf)
        post = {}
        for p in range(P_):
            for q in range(Q):
                sp, tp = g.pd_beta[p, q]
                inside = g.mask[p, q] and np.linalg.norm(g.m[p, q, :3] - s[p, :3]) < 200.0
                if inside:
                    inn = innovate(g.m[p, q][None], g.P[p, q][None], s[p][None], geometry_of(t), BS_POS, Z, Rz,
                                   "ref", ext[t])
                    logq[p, q] = np.log(sp / (sp + tp) * g.w[p, q]) + inn.loglik[0]
                    post[p, q] = inn
        ref[t] = (logq, post)
    assert (0, 0) not in ref[VA][1] and (1, 2) not in ref[VA][1]  # outside the FOV, dead slot
    bs_t = bs_logterm(s, Z, Rz, BS_POS, p_bs)
    ref_lpsi = np.array([[logsumexp([lc, bs_t[p, j]] + [ref[t][0][p, q, j] for t in maps
                                                        for q in range(maps[t].capacity)])
                          for j in range(J)] for p in range(P_)])
    np.testing.assert_allclose(lpsi, ref_lpsi, rtol=1e-12)
    for t, g in maps.items():
        Q, d = g.capacity, g.dim
        logq, post = ref[t]
        o = out[t]
        for p in range(P_):
            comps = []  # (w, m, P, beta) in the dense slot order
            for q in range(Q):
                if g.mask[p, q]:
                    sp, tp = g.pd_beta[p, q]
                    det = (p, q) in post
                    pd = sp / (sp + tp) if det else 0.0
                    comps.append(((1 - pd) * g.w[p, q], g.m[p, q], g.P[p, q], (sp, tp + 1) if det else (sp, tp)))
            for q in range(Q):
                if g.mask[p, q]:
                    sp, tp = g.pd_beta[p, q]
                    for j in range(J):
                        wj = np.exp(logq[p, q, j] - ref_lpsi[p, j])
                        if (p, q) in post:
                            comps.append((wj, post[p, q].m_post[0, j], post[p, q].P_post[0, j], (sp + 1, tp)))
                        else:
                            comps.append((0.0, g.m[p, q], g.P[p, q], (sp + 1, tp)))
            if prune is None:
                assert o.capacity == Q * (1 + J)
                live = np.nonzero(o.mask[p])[0]
                assert len(live) == len(comps) == g.mask[p].sum() * (1 + J)
            else:
                comps = [c for c in comps if c[0] >= prune]
                live = np.arange(len(comps))
                assert o.mask[p].sum() == len(comps) and o.mask[p, :len(comps)].all()
            np.testing.assert_allclose(o.w[p, live], [c[0] for c in comps], rtol=1e-9, atol=1e-300)
            np.testing.assert_allclose(o.m[p, live], [c[1] for c in comps], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(o.P[p, live], [c[2] for c in comps], rtol=1e-12, atol=1e-12)
            np.testing.assert_array_equal(o.pd_beta[p, live], [c[3] for c in comps])
            dead = ~o.mask[p]
            assert np.all(o.w[p, dead] == 0.0) and np.all(o.P[p, dead] == np.eye(d)) and np.all(o.pd_beta[p, dead] == 1.0)


@pytest.mark.parametrize("lm_type", [VA, SP, VS])
def test_skipped_work_changes_no_corrected_component(lm_type):
    """With clutter and pruning, type_terms skips negligible terms and the means of pruned ones
    (gmphd._skip_floors); correct() must equal the computation without skipping to 1e-12, and the
    skipping must actually happen (terms set to -inf that were finite without it)."""
    from mmslam.slam.phd.gmphd import _skip_floors, correct

    rng = np.random.default_rng(11)
    P_, Q, d = 5, 6, 3 if lm_type != VS else 7
    s = np.tile([70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0], (P_, 1))
    s[:, 0:2] += rng.standard_normal((P_, 2)) * 0.3
    lm = np.array([[60.0, 40.0, 5.0], [60.0, 20.0, 5.0], [90.0, 30.0, 8.0],
                   [40.0, 60.0, 3.0], [65.0, 25.0, 4.0], [80.0, 45.0, 6.0]])
    m = np.zeros((P_, Q, d))
    m[..., :3] = lm + rng.standard_normal((P_, Q, 3)) * 0.5
    if d == 7:
        m[..., 3:6] = rng.standard_normal((P_, Q, 3))
    Pc = np.stack([[_spd(rng, d, 0.05 if (p + q) % 2 else 1.0) for q in range(Q)] for p in range(P_)])
    g = GM(rng.uniform(0.01, 1.0, (P_, Q)), m, Pc, rng.random((P_, Q)) < 0.9)
    Z = np.stack([measure(s[0], lm[j], geometry_of(lm_type if lm_type != VS else SP), BS_POS) for j in range(4)]
                 + [np.array([150.0, 1.0, 0.1, -2.0, 0.2])])
    lc, prune = np.log(1.2832e-5), 1e-5
    fq, fp = _skip_floors(lc, prune)
    assert fq == lc - 40.0 and np.isclose(fp, lc + np.log(prune)) and _skip_floors(lc, None) == (-np.inf, -np.inf)
    skipped = type_terms(g, landmark_type(lm_type), s, Z, R, BS_POS, _pd, None, lc, prune)
    full = type_terms(g, landmark_type(lm_type), s, Z, R, BS_POS, _pd)
    gated = np.isneginf(skipped.logq) & np.isfinite(full.logq)
    assert gated.any() and (full.logq[gated] < fq).all()  # only negligible terms are dropped
    keep = np.isfinite(skipped.logq)
    assert np.array_equal(skipped.logq[keep], full.logq[keep])
    p_bs = np.full(P_, 0.95)
    out, lpsi, _ = correct({lm_type: g}, s, Z, R, BS_POS, _pd, p_bs, lc, prune, {}, 0, KINDS)
    lpsi_ref = log_psi([full], bs_logterm(s, Z, R, BS_POS, p_bs), lc, (P_, Z.shape[0]))
    ref = corrected_gm(full, Z, lpsi_ref, prune=prune)
    np.testing.assert_allclose(lpsi, lpsi_ref, rtol=1e-12)
    a = out[lm_type]
    assert a.w.shape == ref.w.shape and np.array_equal(a.mask, ref.mask)
    np.testing.assert_allclose(a.w, ref.w, rtol=1e-12, atol=0)
    np.testing.assert_allclose(a.m[a.mask], ref.m[ref.mask], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.P[a.mask], ref.P[ref.mask], rtol=1e-12, atol=1e-12)
