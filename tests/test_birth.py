"""Birth by geometric inversion of measurements (slam/phd/birth.py)."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.slam.phd.birth import birth_gm, invert_sp, invert_va
from mmslam.slam.models.measurement import SP, VA, VS, measure
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import geometry_of
from mmslam.slam.specs.landmarks import landmark_type

BS_POS = np.array([0.0, 0.0, 40.0])
R = np.diag([0.3, 0.03, 0.03, 0.03, 0.03]) ** 2


def _pd(u, x, t):
    inside = (t == VA) | (np.linalg.norm(np.asarray(u) - np.asarray(x), axis=-1) <= 50.0)
    return np.where(inside, 0.95, 0.0)


def _random_states(rng, n):
    s = np.zeros((n, 7))
    s[:, 0:2] = rng.uniform(-80, 80, (n, 2))
    s[:, 2] = rng.uniform(0, 2, n)
    s[:, 3] = rng.uniform(-np.pi, np.pi, n)
    s[:, 4] = 20.0
    s[:, 5] = 0.3
    s[:, 6] = rng.uniform(-50, 300, n)
    return s


def test_va_inversion_of_exact_measurement_returns_the_image_source():
    rng = np.random.default_rng(1)
    s = _random_states(rng, 200)
    vas = np.array([[200.0, 0, 40], [-200.0, 0, 40], [0, 200.0, 40], [0, -200.0, 40]])
    lm = vas[rng.integers(0, 4, 200)]
    z = measure(s, lm, Bounce.MIRROR, BS_POS)
    pos, ok = invert_va(s, z, BS_POS)
    assert ok.all()
    assert np.abs(pos - lm).max() < 1e-6


def test_sp_inversion_of_exact_measurement_returns_the_scatter_point():
    rng = np.random.default_rng(2)
    s = _random_states(rng, 200)
    lm = np.column_stack([rng.uniform(-90, 90, (200, 2)), rng.uniform(0, 40, 200)])
    z = measure(s, lm, Bounce.SCATTER, BS_POS)
    pos, ok = invert_sp(s, z, BS_POS)
    assert ok.all()
    assert np.abs(pos - lm).max() < 1e-6


def test_sp_inversion_rejects_a_bistatic_range_shorter_than_the_direct_path():
    s = np.array([50.0, 0, 0, 0, 20, 0.3, 10.0])
    z = measure(s, np.array([60.0, 10.0, 5.0]), Bounce.SCATTER, BS_POS)
    z[0] = np.linalg.norm(BS_POS - s[:3]) + s[6] - 1.0  # 1 m shorter than LOS: impossible
    _, ok = invert_sp(s, z, BS_POS)
    assert not ok


def test_birth_gm_centres_on_the_landmark_and_drops_sp_outside_fov():
    s = np.array([[70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0],
                  [70.0, 1.0, 0, np.pi / 2 + 0.01, 22.22, np.pi / 10, 299.5]])
    near = np.array([60.0, 20.0, 10.0])   # ~24 m away: inside the 50 m FOV
    far = np.array([-55.0, 55.0, 10.0])   # ~138 m away: outside
    Z = np.stack([measure(s[0], near, Bounce.SCATTER, BS_POS), measure(s[0], far, Bounce.SCATTER, BS_POS)])
    g = birth_gm(s, Z, R, landmark_type(SP), BS_POS, 1.5e-5, _pd)
    assert g.w.shape == (2, 2)
    assert g.mask[:, 0].all() and not g.mask[:, 1].any()
    assert np.allclose(g.w[:, 0], 1.5e-5) and np.all(g.w[:, 1] == 0)
    # particle 0 is the true state: birth mean within a fraction of the spread of the truth
    assert np.linalg.norm(g.m[0, 0] - near) < 0.5
    assert np.all(np.linalg.eigvalsh(g.P[0, 0]) > 0)
    # particle 1 is displaced: its birth lands elsewhere (the map is conditioned on the particle)
    assert np.linalg.norm(g.m[1, 0] - g.m[0, 0]) > 0.5


def test_va_births_are_kept_at_any_range_and_vs_births_are_7d():
    s = np.array([[70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0]])
    va = np.array([200.0, 0, 40])
    vs = np.array([60.73, 0.0, 0.0])
    far = np.array([-55.0, 55.0, 10.0])
    Z = np.stack([measure(s[0], far, Bounce.SCATTER, BS_POS), measure(s[0], vs, Bounce.SCATTER, BS_POS)])
    gva = birth_gm(s, np.stack([measure(s[0], va, Bounce.MIRROR, BS_POS)] * 2), R, landmark_type(VA), BS_POS, 1.5e-5, _pd)
    assert gva.mask.all()  # VA births have no range gate (the VA is 135 m away)
    assert np.linalg.norm(gva.m[0, 0] - va) < 1.0
    gvs = birth_gm(s, Z, R, landmark_type(VS), BS_POS, 1.5e-5, _pd, (100.0, 100.0, 0.09), np.pi / 2)
    assert gvs.dim == 7
    assert gvs.mask[0, 1] and not gvs.mask[0, 0]  # the far SP's image is outside the FOV: no VS birth
    assert np.linalg.norm(gvs.m[0, 1, :3] - vs) < 1.0
    assert np.allclose(np.diag(gvs.P[0, 1])[3:], [100.0, 100.0, 0.09, (np.pi / 2) ** 2])
    assert np.all(gvs.m[0, 1, 3:6] == 0.0)


def test_birth_with_no_measurements_is_empty():
    s = np.zeros((3, 7))
    g = birth_gm(s, np.zeros((0, 5)), R, landmark_type(SP), BS_POS, 1.5e-5, _pd)
    assert g.w.shape == (3, 0) and g.m.shape == (3, 0, 3)


@pytest.mark.parametrize("lm_type", [VA, SP])
def test_birth_moments_equal_the_stacked_reference(lm_type):
    """birth_moments == invert_* on the stacked cubature points + np.mean / np.cov (1e-9)."""
    from mmslam.slam.phd.birth import birth_moments
    from mmslam.slam.phd.ckf import cubature_points

    rng = np.random.default_rng(4 + lm_type)
    s = np.tile([70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0], (5, 1))
    s[:, 0:2] += rng.standard_normal((5, 2))
    R = np.diag([0.3, 0.03, 0.03, 0.03, 0.03]) ** 2
    Z = np.stack([measure(s[0], p, geometry_of(lm_type), BS_POS) for p in
                  ([60.0, 20.0, 5.0], [-30.0, 50.0, 2.0], [200.0, 0.0, 40.0])])
    Z = np.concatenate([Z, [[10.0, 0.1, 0.1, 0.2, 0.1]]])  # invalid for SP (TOA too short)
    mean, cov, ok = birth_moments(s, Z, R, geometry_of(lm_type), BS_POS)
    zpts = cubature_points(Z, np.broadcast_to(R, (4, 5, 5)))
    inv = invert_va if lm_type == VA else invert_sp
    pts, valid = inv(s[:, None, None, :], zpts[None], BS_POS)  # (5, 4, 10, 3)
    rm = pts.mean(axis=2)
    rc = np.array([[np.cov(pts[p, j].T, bias=True) for j in range(4)] for p in range(5)])
    rok = valid.all(-1) & (np.linalg.det(rc) > 0)
    assert np.array_equal(ok, rok) and ok.any()
    np.testing.assert_allclose(mean[ok], rm[ok], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(cov[ok], rc[ok], rtol=1e-9, atol=1e-9 * np.abs(rc[ok]).max())


@pytest.mark.parametrize("lm_type", [VA, SP, VS])
def test_birth_from_moments_equals_the_masked_formula(lm_type):
    """Every slot of the birth kernel, bit for bit: weight / moments (VS: blkdiag(P, V, sigma_xi^2), mean
    [pos, 0, 0, 0, 0]) where the moments are valid (and p_D > 0 for SP / VS), else w = 0, m = 0, P = I."""
    from mmslam.slam.phd.birth import birth_from_moments, birth_moments
    from mmslam.slam.models.vs import vs_birth_covariance, vs_birth_mean

    rng = np.random.default_rng(4)
    s = _random_states(rng, 6)
    Z = np.stack([measure(s[0], rng.uniform(-60, 60, 3) + [0, 0, 5], Bounce.SCATTER, BS_POS) for _ in range(5)])
    mean, cov, ok = birth_moments(s, Z, R, geometry_of(lm_type), BS_POS)
    ok[0, 0] = False  # an invalid inversion stays dead whatever its moments
    ok[:, 3] = False  # and a measurement without a birth in any particle
    g = birth_from_moments(s, mean, cov, ok, landmark_type(lm_type), 2e-5, _pd, (100.0, 100.0, 0.09), 1.5)
    live = ok & ((lm_type == VA) | (_pd(s[:, None, :3], mean, lm_type) > 0))
    assert np.array_equal(g.mask, live) and 0 < live.sum() < live.size
    assert np.array_equal(g.w, np.where(live, 2e-5, 0.0))
    d = 7 if lm_type == VS else 3
    m_ref = vs_birth_mean(mean) if d == 7 else mean
    P_ref = vs_birth_covariance(cov, np.array([100.0, 100.0, 0.09]), 1.5) if d == 7 else cov
    assert np.array_equal(g.m, np.where(live[..., None], m_ref, 0.0))
    assert np.array_equal(g.P, np.where(live[..., None, None], P_ref, np.eye(d)))
    # drop_dead: only the measurements with a birth in some particle keep a slot, in order
    cols = live.any(axis=0)
    assert not cols.all()
    short = birth_from_moments(s, mean, cov, ok, landmark_type(lm_type), 2e-5, _pd, (100.0, 100.0, 0.09), 1.5, drop_dead=True)
    for a, b in ((short.w, g.w), (short.m, g.m), (short.P, g.P), (short.mask, g.mask)):
        assert np.array_equal(a, b[:, cols])


def test_birth_kernels_reject_shapes_that_do_not_fit():
    """The compiled birth loops read their arrays unchecked (a short ``bs`` or ``mean``, a ``pd_fn``
    answer of another shape read past the arrays): a one-line ValueError naming the shapes first."""
    from mmslam.slam.phd.birth import birth_from_moments, birth_moments, birth_moments_by_kind

    rng = np.random.default_rng(5)
    s = _random_states(rng, 4)
    Z = np.stack([measure(s[0], rng.uniform(-60, 60, 3) + [0, 0, 5], Bounce.SCATTER, BS_POS) for _ in range(3)])
    with pytest.raises(ValueError, match="bs"):
        birth_moments_by_kind(s, Z, R, (1, 2), BS_POS[:2])
    with pytest.raises(ValueError, match="Z"):
        birth_moments(s, Z[:, :4], R, Bounce.SCATTER, BS_POS)
    mean, cov, ok = birth_moments(s, Z, R, Bounce.SCATTER, BS_POS)
    with pytest.raises(ValueError, match="birth_from_moments"):
        birth_from_moments(s, mean[:, :2], cov, ok, landmark_type(SP), 1e-4, _pd)
    with pytest.raises(ValueError, match="pd_fn"):
        birth_from_moments(s, mean, cov, ok, landmark_type(SP), 1e-4, lambda u, x, t: np.ones((4, 3, 2)))
    with pytest.raises(ValueError, match="birth_weight has shape"):  # per-birth weights of another shape
        birth_from_moments(s, mean, cov, ok, landmark_type(SP), np.ones((4, 2)), _pd)


@pytest.mark.parametrize("P, J", [(1, 1), (1, 3), (5, 1), (3, 0)])
def test_per_birth_weights_equal_the_scalar_birth_times_the_weights(P, J):
    """A ``(P, J)`` weight (the adaptive birth's) gives the scalar kernel's births with each live slot's weight
    replaced by its own, every other array bit for bit, on degenerate shapes too (one particle, one or no
    measurement); dead slots keep weight 0; the caller's weight array is not written."""
    from mmslam.slam.phd.birth import birth_from_moments, birth_moments

    rng = np.random.default_rng(6)
    s = _random_states(rng, P)
    Z = np.array([measure(s[0], rng.uniform(-60, 60, 3) + [0, 0, 5], Bounce.MIRROR, BS_POS)
                  for _ in range(J)], float).reshape(J, 5)
    mean, cov, ok = birth_moments(s, Z, R, Bounce.MIRROR, BS_POS)
    if J > 1:
        ok[0, 1] = False
    share = rng.uniform(0.0, 1.0, (P, J))
    keep = share.copy()
    plain = birth_from_moments(s, mean, cov, ok, landmark_type(VA), 2e-5, _pd)
    per = birth_from_moments(s, mean, cov, ok, landmark_type(VA), 2e-5 * share, _pd)
    assert per.w.shape == (P, J) and np.array_equal(share, keep)
    assert np.array_equal(per.w, np.where(plain.mask, 2e-5 * share, 0.0))
    for a, b in ((per.m, plain.m), (per.P, plain.P), (per.mask, plain.mask)):
        assert np.array_equal(a, b)


def test_birth_moments_of_one_r_equal_those_of_r_per_measurement():
    """One Cholesky factor of ``R`` for every measurement gives the same bits as a stacked ``(J, 5, 5)`` R."""
    from mmslam.slam.phd.birth import birth_moments_by_kind

    rng = np.random.default_rng(6)
    s = _random_states(rng, 9)
    Z = np.stack([measure(s[0], rng.uniform(-60, 60, 3) + [0, 0, 5], Bounce.SCATTER, BS_POS) for _ in range(4)])
    one = birth_moments_by_kind(s, Z, R, (1, 2), BS_POS)
    per = birth_moments_by_kind(s, Z, np.broadcast_to(R, (4, 5, 5)), (1, 2), BS_POS)
    for g in (1, 2):
        for a, b in zip(one[g], per[g]):
            assert np.array_equal(a, b)


def test_cubature_points_equal_the_numpy_form_bit_for_bit():
    """The compiled cubature point set (:func:`mmslam.slam.phd.ckf.cubature_point_set`) gives the bits of
    the NumPy form it replaced, ``m +- sqrt(d) L e_i``, also when one ``P`` broadcasts over the means."""
    from mmslam.slam.phd.ckf import cubature_points
    from mmslam.slam.core.linalg import safe_cholesky

    rng = np.random.default_rng(7)
    m = rng.normal(0, 30, (6, 5))
    A = rng.normal(size=(6, 5, 5))
    for P in (A @ np.swapaxes(A, -1, -2) + np.eye(5), R[None], R):
        L = safe_cholesky(P, "test") * np.sqrt(5)
        cols = np.swapaxes(L, -1, -2)
        ref = np.concatenate([m[..., None, :] + cols, m[..., None, :] - cols], axis=-2)
        assert np.array_equal(cubature_points(m, P), ref)
    with pytest.raises(ValueError, match="cubature_points"):
        cubature_points(m, R[:3, :3])
