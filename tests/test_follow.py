"""The follow offset of a static landmark's update (``filter.types.<T>.follow_std``): the gain and likelihood take
``P + F``, the covariance kept is the estimate's own for that gain (:func:`~mmslam.slam.phd.follow.own_covariance`),
a missed Gaussian keeps ``P``; refused for a moving type."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.model import VA, Bounce
from mmslam.slam.core.gm import GM
from mmslam.slam.models.measurement import measure
from mmslam.slam.phd.follow import own_covariance
from mmslam.slam.phd.gmphd import type_terms
from mmslam.slam.specs.landmarks import landmark_type

BS = np.array([0.0, 0.0, 10.0])
STATE = np.array([5.0, -20.0, 1.5, 0.3, 10.0, 0.0, 2.0])
R = np.diag([0.1, 1e-4, 1e-4, 1e-4, 1e-4])


def _pd(u, x, t):
    return np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.9)


def test_own_covariance_by_hand_for_a_direct_measurement_of_each_axis():
    """z = x + v per axis, P = diag(1, 2, 0.5), F = 3, R = diag(4, 2, 1): the gain K = (P + F) / (P + F + R) = 1/2,
    5/7, 7/9; the estimate's own variance (1 - K)^2 P + K^2 R = 1.25, 58/49, 51/81, where the update on P + F says
    (P + F) R / (P + F + R) = 2, 10/7, 7/9."""
    P, F, Rd = np.array([1.0, 2.0, 0.5]), 3.0, np.array([4.0, 2.0, 1.0])
    Pf_post = (P + F) * Rd / (P + F + Rd)
    np.testing.assert_allclose(Pf_post, [2.0, 10 / 7, 7 / 9], rtol=1e-15)
    out = own_covariance(np.diag(P)[None], np.diag(P + F)[None], np.diag(Pf_post)[None, None])
    assert out.shape == (1, 1, 3, 3)
    np.testing.assert_allclose(out[0, 0], np.diag([1.25, 58 / 49, 51 / 81]), rtol=1e-14, atol=1e-15)


def test_own_covariance_is_the_joseph_form_for_a_linear_measurement_and_f_zero_changes_nothing():
    """A 5 x 3 linear measurement with correlated P and R, two Gaussians, three measurement covariances each:
    own_covariance(P, P + F, P~+) is (I - K H) P (I - K H)^T + K R K^T with the gain K of P + F, computed here
    directly; with F = 0 it is P~+ itself."""
    rng = np.random.default_rng(3)
    H = rng.normal(size=(5, 3))
    A = rng.normal(size=(2, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    B = rng.normal(size=(2, 3, 5, 5))
    Rs = B @ np.swapaxes(B, -1, -2) + np.eye(5)
    Fm = np.diag([0.5, 0.5, 0.5])
    for Pt in (P + Fm, P):
        K = Pt[:, None] @ H.T @ np.linalg.inv(H @ Pt[:, None] @ H.T + Rs)  # (2, 3, 3, 5)
        IKH = np.eye(3) - K @ H
        post = IKH @ Pt[:, None]
        want = IKH @ P[:, None] @ np.swapaxes(IKH, -1, -2) + K @ Rs @ np.swapaxes(K, -1, -2)
        got = own_covariance(P, Pt, post)
        assert got.shape == (2, 3, 3, 3)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(got, np.swapaxes(got, -1, -2))
    np.testing.assert_allclose(own_covariance(P, P, post), post, rtol=1e-9, atol=1e-12)


def test_type_terms_with_follow_updates_from_p_plus_f_and_keeps_p_for_the_missed_term():
    """A VA in two particles: with follow F the likelihoods and posterior means are those of the plain update of
    P + F; the posterior covariances are own_covariance of it; the map handed on (the missed term's) keeps P."""
    x = np.array([40.0, 35.0, 6.0])
    P = np.tile(np.diag([0.2, 0.3, 0.1]), (2, 1, 1, 1))
    g = GM(np.full((2, 1), 0.8), np.tile(x, (2, 1, 1)), P, np.ones((2, 1), bool))
    states = np.stack([STATE, STATE + [0.5, -0.3, 0, 0.01, 0, 0, 0]])
    Z = np.stack([measure(STATE, x + [0.6, -0.4, 0.0], Bounce.MIRROR, BS), measure(STATE, x, Bounce.MIRROR, BS)])
    F = 0.64
    tc = type_terms(g, landmark_type(VA), states, Z, R, BS, _pd, follow=F)
    Pf = P + F * np.eye(3)
    ref = type_terms(GM(g.w, g.m, Pf, g.mask), landmark_type(VA), states, Z, R, BS, _pd)
    np.testing.assert_array_equal(tc.inn.loglik, ref.inn.loglik)
    np.testing.assert_array_equal(tc.inn.m_post, ref.inn.m_post)
    np.testing.assert_array_equal(tc.logq, ref.logq)
    np.testing.assert_allclose(tc.inn.P_post, own_covariance(P[:, 0], Pf[:, 0], ref.inn.P_post), rtol=1e-12)
    np.testing.assert_array_equal(tc.g.P, P)
    assert (np.linalg.eigvalsh(tc.inn.P_post) > 0).all()
    assert (np.trace(tc.inn.P_post, axis1=-2, axis2=-1) < np.trace(ref.inn.P_post, axis1=-2, axis2=-1)).all()


def test_the_kept_covariance_is_the_error_of_the_followed_estimate_of_a_static_va():
    """Monte Carlo, an independent check: a static VA x ~ N(m, P) 55 m away, measured once with noise Rn (angles
    0.03 rad); the update with follow F = 1 m^2 moves the estimate by the gain of P + F. The sample covariance of its
    error (4000 draws) is the kept covariance (within 10% per axis; it is about 0.26 m^2, more than P: the gain follows
    the noise), not the update's own P~+ (1.7-2.5 times larger here)."""
    rng = np.random.default_rng(11)
    m = np.array([40.0, 35.0, 6.0])
    P = np.diag([0.05, 0.08, 0.03])
    n, Rn = 4000, np.diag([1.0, 1e-3, 1e-3, 1e-3, 1e-3])
    x = m + rng.multivariate_normal(np.zeros(3), P, size=n)
    Z = np.stack([measure(STATE, xi, Bounce.MIRROR, BS) for xi in x]) + rng.multivariate_normal(np.zeros(5), Rn, n)
    g = GM(np.ones((1, 1)), m[None, None], P[None, None], np.ones((1, 1), bool))
    tc = type_terms(g, landmark_type(VA), STATE[None], Z, Rn, BS, _pd, follow=1.0)
    err = tc.inn.m_post[0] - x
    sample = np.cov(err.T)
    kept = tc.inn.P_post[0, 0]
    plain = type_terms(GM(g.w, g.m, g.P + np.eye(3), g.mask), landmark_type(VA), STATE[None], Z[:1], Rn, BS,
                       _pd).inn.P_post[0, 0]
    np.testing.assert_allclose(np.diag(sample), np.diag(kept), rtol=0.1)
    assert (np.diag(plain) > 1.5 * np.diag(kept)).all()
    assert np.abs(err.mean(0)).max() < 0.05


def test_follow_with_the_heavy_tail_keeps_a_positive_definite_own_covariance():
    """With the VA heavy tail (e = 0.2, K = 4) the two updates are both made from P + F and moment-matched; the kept
    covariance is own_covariance of that mixture's posterior (whose bracket is clipped to PSD), symmetric, positive
    definite, and no wider than the mixture's own posterior."""
    x = np.array([40.0, 35.0, 6.0])
    P = np.tile(np.diag([0.2, 0.3, 0.1]), (1, 1, 1, 1))
    g = GM(np.full((1, 1), 0.8), x[None, None], P, np.ones((1, 1), bool))
    Z = np.stack([measure(STATE, x + d, Bounce.MIRROR, BS) for d in ([0.0, 0.0, 0.0], [2.5, -1.5, 0.5])])
    F = 0.36
    tc = type_terms(g, landmark_type(VA), STATE[None], Z, R, BS, _pd, tail=(0.2, 4.0), follow=F)
    ref = type_terms(GM(g.w, g.m, P + F * np.eye(3), g.mask), landmark_type(VA), STATE[None], Z, R, BS, _pd,
                     tail=(0.2, 4.0))
    np.testing.assert_array_equal(tc.inn.m_post, ref.inn.m_post)
    np.testing.assert_allclose(tc.inn.P_post, own_covariance(P[:, 0], P[:, 0] + F * np.eye(3), ref.inn.P_post),
                               rtol=1e-12)
    np.testing.assert_array_equal(tc.inn.P_post, np.swapaxes(tc.inn.P_post, -1, -2))
    assert (np.linalg.eigvalsh(tc.inn.P_post) > 0).all()
    assert (np.linalg.eigvalsh(ref.inn.P_post - tc.inn.P_post) > -1e-12).all()


@pytest.mark.parametrize("case", ["no measurement", "no slot", "outside the FOV"])
def test_follow_on_degenerate_shapes_keeps_the_map_as_it_is(case):
    """J = 0 (an empty scan), Q = 0 (an empty map) and n = 0 (every Gaussian outside the FOV, p_D = 0): the
    correction with a follow offset hands on the map's own P for the missed terms and posteriors of the plain
    shape (N, 1, 3, 3), with no error."""
    x = np.array([40.0, 35.0, 6.0])
    P = np.tile(np.diag([0.2, 0.3, 0.1]), (2, 1, 1, 1))
    g = GM(np.full((2, 1), 0.8), np.tile(x, (2, 1, 1)), P, np.ones((2, 1), bool))
    states, Z, pd = np.stack([STATE, STATE]), measure(STATE, x, Bounce.MIRROR, BS)[None], _pd
    if case == "no measurement":
        Z = np.zeros((0, 5))
    elif case == "no slot":
        g = GM(np.zeros((2, 0)), np.zeros((2, 0, 3)), np.zeros((2, 0, 3, 3)), np.zeros((2, 0), bool))
        P = g.P
    else:
        pd = lambda u, x, t: np.zeros(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]))  # noqa: E731
    tc = type_terms(g, landmark_type(VA), states, Z, R, BS, pd, follow=0.36)
    np.testing.assert_array_equal(tc.g.P, P)
    n = 2 if case == "no measurement" else 0
    assert tc.inn.P_post.shape == (n, 1, 3, 3) and tc.inn.m_post.shape == (n, Z.shape[0], 3)
