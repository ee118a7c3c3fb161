"""The heavy-tailed likelihood of a type's Gaussians (``filter.types.<T>.tail_weight``, ``tail_scale``;
slam/phd/tail.py ``tail_mixture``, used by gmphd.type_terms): by hand, against two plain CKF updates, and end to
end (off by default)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mmslam.model import Bounce
from mmslam.slam.core.gm import GM
from mmslam.slam.models.measurement import measure
from mmslam.slam.phd.ckf import Innovation
from mmslam.slam.phd.tail import tail_mixture
from mmslam.slam.phd.gmphd import type_terms
from mmslam.slam.specs.landmarks import landmark_type

BS_POS = np.array([0.0, 0.0, 40.0])
R = np.diag([0.3, 0.03, 0.03, 0.03, 0.03]) ** 2


def test_tail_mixture_by_hand():
    """One Gaussian, one measurement, 1-D state: core N(m=1, P=1) with log-likelihood -2, wide N(m=3, P=4) with
    -3, e = 0.25. Likelihood 0.75 e^-2 + 0.25 e^-3; a = 0.75 e^-2 / that; mean a + 3 (1 - a); covariance
    a (1 + (1 - m')^2) + (1 - a) (4 + (3 - m')^2)."""
    core = Innovation(np.array([[-2.0]]), np.array([[[1.0]]]), np.array([[[[1.0]]]]))
    wide = Innovation(np.array([[-3.0]]), np.array([[[3.0]]]), np.array([[[[4.0]]]]))
    out = tail_mixture(core, wide, 0.25)
    lik = 0.75 * math.exp(-2.0) + 0.25 * math.exp(-3.0)
    a = 0.75 * math.exp(-2.0) / lik
    m = a * 1.0 + (1 - a) * 3.0
    assert out.loglik[0, 0] == pytest.approx(math.log(lik), rel=1e-14)
    assert out.m_post[0, 0, 0] == pytest.approx(m, rel=1e-14)
    assert out.P_post[0, 0, 0, 0] == pytest.approx(a * (1 + (1 - m) ** 2) + (1 - a) * (4 + (3 - m) ** 2), rel=1e-13)


def test_tail_mixture_of_equal_updates_and_all_tail():
    """Equal core and wide updates (K = 1) give them back for any weight; e = 1 gives the wide update."""
    rng = np.random.default_rng(2)
    A = rng.standard_normal((3, 2, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 3 * np.eye(3)
    core = Innovation(rng.standard_normal((3, 2)), rng.standard_normal((3, 2, 3)), P)
    wide = Innovation(rng.standard_normal((3, 2)) - 1.0, rng.standard_normal((3, 2, 3)), 2.0 * P)
    for e in (0.1, 0.5):
        same = tail_mixture(core, core, e)
        np.testing.assert_allclose(same.loglik, core.loglik, rtol=1e-13)
        np.testing.assert_allclose(same.m_post, core.m_post, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(same.P_post, core.P_post, rtol=1e-13)
    allw = tail_mixture(core, wide, 1.0)
    np.testing.assert_allclose(allw.loglik, wide.loglik, rtol=1e-14)
    np.testing.assert_allclose(allw.m_post, wide.m_post, rtol=1e-14)
    np.testing.assert_allclose(allw.P_post, wide.P_post, rtol=1e-14)


def _reference_mixture(core, wide, e):
    """The moment match of :func:`tail_mixture` written out in NumPy, one Gaussian and measurement at a time."""
    N, J, d = core.m_post.shape
    ll, m, P = np.empty((N, J)), np.empty((N, J, d)), np.empty((N, J, d, d))
    for n in range(N):
        for j in range(J):
            P1 = core.P_post[n, j if core.P_post.shape[1] > 1 else 0]
            PK = wide.P_post[n, j if wide.P_post.shape[1] > 1 else 0]
            lc = math.log(1 - e) + core.loglik[n, j] if e < 1 else -math.inf
            ll[n, j] = np.logaddexp(lc, math.log(e) + wide.loglik[n, j])
            a = math.exp(lc - ll[n, j]) if np.isfinite(ll[n, j]) else 0.0
            m[n, j] = a * core.m_post[n, j] + (1 - a) * wide.m_post[n, j]
            d1, dK = core.m_post[n, j] - m[n, j], wide.m_post[n, j] - m[n, j]
            P[n, j] = a * (P1 + np.outer(d1, d1)) + (1 - a) * (PK + np.outer(dK, dK))
    return ll, m, P


@pytest.mark.parametrize("N, J, d, per_meas, e", [(1, 1, 3, False, 0.2), (4, 3, 3, False, 0.2), (4, 3, 7, True, 0.5),
                                                  (0, 2, 3, False, 0.2), (3, 0, 3, True, 0.2), (2, 2, 3, False, 1.0)])
def test_compiled_tail_mixture_against_a_numpy_reference(N, J, d, per_meas, e):
    """The compiled :func:`tail_mixture` against the moment match written out per pair: one covariance for all
    measurements (constant R) or one per measurement, VA and VS dimensions, no Gaussian (N = 0), no measurement
    (J = 0), all tail (e = 1), and a pair whose two log-likelihoods are both -inf (weight 0: the wide update)."""
    rng = np.random.default_rng(11)

    def inn(scale):
        A = rng.standard_normal((N, J if per_meas else 1, d, d))
        return Innovation(rng.standard_normal((N, J)) * 4.0, rng.standard_normal((N, J, d)),
                          scale * (A @ np.swapaxes(A, -1, -2) + np.eye(d)))

    core, wide = inn(1.0), inn(4.0)
    if N and J:
        core.loglik[0, 0] = wide.loglik[0, 0] = -np.inf
    out = tail_mixture(core, wide, e)
    ll, m, P = _reference_mixture(core, wide, e)
    assert out.loglik.shape == (N, J) and out.m_post.shape == (N, J, d) and out.P_post.shape == (N, J, d, d)
    np.testing.assert_allclose(out.loglik, ll, rtol=1e-13)
    np.testing.assert_allclose(out.m_post, m, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(out.P_post, P, rtol=1e-12, atol=1e-13)
    np.testing.assert_array_equal(out.P_post, np.swapaxes(out.P_post, -1, -2))  # symmetric


def _scene(P_=3):
    rng = np.random.default_rng(7)
    s = np.tile([70.0, 5.0, 0.0, np.pi / 2, 20.0, 0.1, 300.0], (P_, 1))
    s[:, 0:2] += rng.standard_normal((P_, 2)) * 0.3
    va = np.array([[200.0, 0.0, 40.0], [0.0, 200.0, 40.0]])
    g = GM(np.tile([0.9, 0.6], (P_, 1)), np.tile(va, (P_, 1, 1)) + rng.standard_normal((P_, 2, 3)),
           np.tile(np.eye(3) * 2.0, (P_, 2, 1, 1)), np.ones((P_, 2), bool))
    Z = np.stack([measure(s[0], va[0], Bounce.MIRROR, BS_POS), measure(s[0], va[1] + 3.0, Bounce.MIRROR, BS_POS)])
    return g, s, Z


def _pd(u, x, t):
    return np.full(np.shape(x)[:-1], 0.9)


def test_type_terms_with_a_tail_against_two_plain_updates():
    """The detection terms with a tail (e, K) against the plain terms of P and K P combined by hand:
    log q = logaddexp(log(1 - e) + log q_P, log(e) + log q_KP); the posterior is tail_mixture of the two."""
    g, s, Z = _scene()
    e, K = 0.2, 4.0
    va = landmark_type("VA")
    t1 = type_terms(g, va, s, Z, R, BS_POS, _pd)
    tK = type_terms(GM(g.w, g.m, g.P * K, g.mask), va, s, Z, R, BS_POS, _pd)
    tt = type_terms(g, va, s, Z, R, BS_POS, _pd, tail=(e, K))
    np.testing.assert_allclose(tt.logq, np.logaddexp(math.log1p(-e) + t1.logq, math.log(e) + tK.logq), rtol=1e-12)
    want = tail_mixture(t1.inn, tK.inn, e)
    np.testing.assert_allclose(tt.inn.m_post, want.m_post, rtol=1e-12)
    np.testing.assert_allclose(tt.inn.P_post, want.P_post, rtol=1e-12)
    np.testing.assert_array_equal(tt.missed_w, t1.missed_w)  # the missed-detection term is the Gaussian's
    # the skip floors of a clutter intensity and a prune threshold do not apply to a mixture: every term is computed
    tp = type_terms(g, va, s, Z, R, BS_POS, _pd, log_clutter=math.log(1e-5), prune=1e-3, tail=(e, K))
    np.testing.assert_array_equal(tp.logq, tt.logq)
    np.testing.assert_array_equal(tp.inn.m_post, tt.inn.m_post)
    # e = 0 is the plain update, bit for bit
    t0 = type_terms(g, va, s, Z, R, BS_POS, _pd, tail=(0.0, K))
    np.testing.assert_array_equal(t0.logq, t1.logq)
    np.testing.assert_array_equal(t0.inn.m_post, t1.inn.m_post)


def test_a_tail_lowers_a_close_fit_and_raises_a_far_one():
    """One particle, one VA Gaussian (covariance 2 I m^2): the measurement it predicts from its mean is less likely
    under the tail (the wide term is flatter at its mode), one of a point 10 m further along the line of sight (its
    range about 7 sigma off) more likely."""
    g, s, _ = _scene(1)
    g = GM(g.w[:, :1], g.m[:, :1], g.P[:, :1], g.mask[:, :1])
    m = g.m[0, 0]
    Z = np.stack([measure(s[0], m, Bounce.MIRROR, BS_POS), measure(s[0], m + [10.0, 0.0, 0.0], Bounce.MIRROR, BS_POS)])
    va = landmark_type("VA")
    plain = type_terms(g, va, s, Z, R, BS_POS, _pd)
    tail = type_terms(g, va, s, Z, R, BS_POS, _pd, tail=(0.2, 4.0))
    assert tail.logq[0, 0, 0] < plain.logq[0, 0, 0]
    assert tail.logq[0, 0, 1] > plain.logq[0, 0, 1] + 5.0


def test_papers_pinned_gaussian_likelihood_and_the_tail_through_set(tmp_path):
    """On ``paper``, which pins tail_weight 0 (the city default is 0.2: test_association), run_slam as it is and with
    --set tail_weight=0 agree to 1e-12; 0.2 changes the run; a weight above its bound 0.5 is a one-line error naming
    the key."""
    from mmslam.errors import ConfigError
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.scenes.scenario import load_preset, with_overrides
    from mmslam.slam.filter.run import run_slam

    scn = load_preset("paper")
    cache = trace_scenario(scn, AnalyticSource(scn), tmp_path / "c", steps=8, progress=False)
    err = [np.asarray(run_slam(cache, "proposed", 20, 1, overrides=o).vehicles["pos_err"], float)
           for o in ((), ("filter.types.VA.tail_weight=0",), ("filter.types.VA.tail_weight=0.2",))]
    np.testing.assert_allclose(err[1], err[0], rtol=1e-12)
    assert not np.allclose(err[2], err[0])
    with pytest.raises(ConfigError, match="filter.types.VA.tail_weight"):
        with_overrides(scn, ["filter.types.VA.tail_weight=0.7"])


@pytest.mark.parametrize("P_, Q, J", [(1, 1, 1), (1, 0, 2), (2, 2, 0), (1, 2, 1)])
def test_tail_on_degenerate_shapes_against_two_plain_updates(P_, Q, J):
    """P = 1, an empty map (Q = 0), an empty scan (J = 0): the tailed terms are the plain ones of P and K P combined
    by hand (nothing to combine where there is no Gaussian or no measurement: the plain terms, unchanged)."""
    g, s, Z = _scene(P_)
    g = GM(g.w[:, :Q], g.m[:, :Q], g.P[:, :Q], g.mask[:, :Q])
    Z = np.concatenate([Z, Z])[:J]
    va, e, K = landmark_type("VA"), 0.3, 3.0
    t1 = type_terms(g, va, s, Z, R, BS_POS, _pd)
    tK = type_terms(GM(g.w, g.m, g.P * K, g.mask), va, s, Z, R, BS_POS, _pd)
    tt = type_terms(g, va, s, Z, R, BS_POS, _pd, tail=(e, K))
    assert tt.logq.shape == (P_, Q, J) and tt.inn.m_post.shape == t1.inn.m_post.shape
    if Q and J:
        np.testing.assert_allclose(tt.logq, np.logaddexp(math.log1p(-e) + t1.logq, math.log(e) + tK.logq),
                                   rtol=1e-12)
        want = tail_mixture(t1.inn, tK.inn, e)
        np.testing.assert_allclose(tt.inn.m_post, want.m_post, rtol=1e-12)
        np.testing.assert_allclose(tt.inn.P_post, want.P_post, rtol=1e-12)
    else:
        np.testing.assert_array_equal(tt.logq, t1.logq)
    np.testing.assert_array_equal(tt.missed_w, t1.missed_w)
    lik = type_terms(g, va, s, Z, R, BS_POS, _pd, tail=(e, K), posteriors=False)  # the weight offset's pass
    np.testing.assert_array_equal(lik.logq, tt.logq)


@pytest.mark.parametrize("tail", [None, (0.2, 4.0), (1.0, 3.0)])
@pytest.mark.parametrize("floors", [False, True])
def test_the_likelihoods_alone_are_the_full_updates_terms(tail, floors):
    """``posteriors=False`` (the weight offset's pass of correct()) gives the terms log q of the full update bit for
    bit, with and without the tail (also all tail, e = 1) and the skip floors, its log-likelihoods those of the
    mixture, and computes no posterior mean (each row starts with NaN)."""
    g, s, Z = _scene()
    va = landmark_type("VA")
    kw = dict(log_clutter=math.log(1e-5), prune=1e-3) if floors else {}
    full = type_terms(g, va, s, Z, R, BS_POS, _pd, tail=tail, **kw)
    lik = type_terms(g, va, s, Z, R, BS_POS, _pd, tail=tail, posteriors=False, **kw)
    np.testing.assert_array_equal(lik.logq, full.logq)
    np.testing.assert_array_equal(lik.inn.loglik, full.inn.loglik)
    np.testing.assert_array_equal(lik.missed_w, full.missed_w)
    np.testing.assert_array_equal(lik.det_index, full.det_index)
    assert lik.inn.m_post.shape[0] == (full.det_index >= 0).sum() > 0
    assert np.isnan(lik.inn.m_post[..., 0]).all()
    assert np.isfinite(full.inn.m_post[..., 0]).any()


def test_the_moment_match_of_the_pairs_needed_only():
    """``tail_mixture(..., need)``: the pairs needed are those of the full match bit for bit (one posterior covariance
    for all measurements, and one per measurement), the others have the mixture's log-likelihood and NaN at the start
    of their mean and covariance; a mask of another shape is refused."""
    rng = np.random.default_rng(5)
    A = rng.standard_normal((4, 3, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(3)
    core = Innovation(rng.standard_normal((4, 3)), rng.standard_normal((4, 3, 3)), P)
    wide = Innovation(rng.standard_normal((4, 3)) - 1.0, rng.standard_normal((4, 3, 3)), 4.0 * P)
    need = rng.random((4, 3)) < 0.5
    need[0, 0], need[0, 1] = True, False
    full, part = tail_mixture(core, wide, 0.2), tail_mixture(core, wide, 0.2, need)
    np.testing.assert_array_equal(part.loglik, full.loglik)
    np.testing.assert_array_equal(part.m_post[need], full.m_post[need])
    np.testing.assert_array_equal(part.P_post[need], full.P_post[need])
    assert np.isnan(part.m_post[~need][:, 0]).all() and np.isnan(part.P_post[~need][:, 0, 0]).all()
    np.testing.assert_array_equal(tail_mixture(core, wide, 0.2, np.ones((4, 3), bool)).m_post, full.m_post)
    with pytest.raises(ValueError, match="need has shape"):
        tail_mixture(core, wide, 0.2, need.T)
    per = Innovation(core.loglik, core.m_post, A @ np.swapaxes(A, -1, -2) + 2 * np.eye(3))  # one R per measurement
    full, part = tail_mixture(per, wide, 0.3), tail_mixture(per, wide, 0.3, need)
    np.testing.assert_array_equal(part.m_post[need], full.m_post[need])
    np.testing.assert_array_equal(part.P_post[need], full.P_post[need])


def test_the_pairs_read_by_hand():
    """:func:`read_pairs` on two particles, two slots, two measurements: particle 0's slots are innovations 0 and 1,
    particle 1's slot 1 is innovation 2 (its slot 0 has none), so innovation and particle numbers differ; a pair is
    read where log q - log psi(z_j) of its own particle is at least log prune (a pair at the threshold too)."""
    from mmslam.slam.phd.tail import read_pairs

    det_index = np.array([[0, 1], [-1, 2]])
    logq = np.array([[[-1.0, -9.0], [-3.0, -2.0]], [[0.0, 0.0], [-2.0, -4.0]]])
    logpsi = np.array([[-0.5, 1.0], [-2.0, -1.0]])
    # log prune = log(0.06) = -2.813; innovation 0: -0.5, -10; 1: -2.5, -3; 2 (particle 1's psi): 0, -3
    np.testing.assert_array_equal(read_pairs(logq, logpsi, det_index, 3, 0.06),
                                  [[True, False], [True, False], [True, False]])
    np.testing.assert_array_equal(read_pairs(logq, logpsi, det_index, 3, None), np.ones((3, 2), bool))
    np.testing.assert_array_equal(read_pairs(logq, logpsi, det_index, 3, 0.0), np.ones((3, 2), bool))
    at = np.exp(-3.0)  # innovation 1's second pair and innovation 2's second pair sit exactly at log prune = -3
    np.testing.assert_array_equal(read_pairs(logq, logpsi, det_index, 3, at)[:, 1], [False, True, True])


@pytest.mark.parametrize("P_, Q, J", [(1, 1, 1), (1, 0, 2), (2, 2, 0), (1, 2, 1)])
def test_the_deferred_match_on_degenerate_shapes(monkeypatch, P_, Q, J):
    """One particle, an empty map (Q = 0), an empty scan (J = 0): correct() with the tail's match deferred gives the
    maps and log psi of the full match in type_terms, array for array (exclusive association, Bernoulli rule)."""
    from mmslam.model import VA
    from mmslam.slam.phd import gmphd

    g, s, Z = _scene(P_)
    g = GM(g.w[:, :Q], g.m[:, :Q], g.P[:, :Q], g.mask[:, :Q])
    Z = np.concatenate([Z, Z])[:J]

    def run():
        return gmphd.correct({VA: g}, s, Z, R, BS_POS, _pd, np.full(P_, 0.5), math.log(1e-4), 1e-5, {VA: None}, 3,
                             {VA: landmark_type("VA")}, association={VA: "exclusive"}, missed={VA: "bernoulli"},
                             tails={VA: (0.2, 4.0)})[:2]

    maps, lpsi = run()
    real_terms = gmphd.type_terms
    monkeypatch.setattr(gmphd, "type_terms", lambda *a, **k: real_terms(*a, **{**k, "defer_tail": False}))
    full_maps, full_lpsi = run()
    assert lpsi.shape == (P_, J)
    np.testing.assert_array_equal(lpsi, full_lpsi)
    for key in ("w", "m", "P", "mask"):
        np.testing.assert_array_equal(getattr(maps[VA], key), getattr(full_maps[VA], key))


@pytest.mark.parametrize("association", ["phd", "exclusive"])
@pytest.mark.parametrize("prune", [1e-5, 0.05, None])
def test_the_correction_matches_the_kept_components_only_and_equals_the_full_match(monkeypatch, association, prune):
    """correct() leaves the tail's moment match to the corrected components (type_terms defer_tail): its corrected
    map and log psi equal, array for array, those of the same correction with every pair matched in type_terms; with a
    prune threshold the deferred match skips the pairs of a measurement and a Gaussian 200 m from its source."""
    from mmslam.model import VA
    from mmslam.slam.phd import gmphd, tail

    g, s, Z = _scene(4)
    Z = np.concatenate([Z, Z + 0.02])
    kw = dict(association={VA: association}, missed={VA: "bernoulli"}, tails={VA: (0.2, 4.0)})

    def run():
        return gmphd.correct({VA: g}, s, Z, R, BS_POS, _pd, np.full(4, 0.5), math.log(1e-4), prune, {VA: None}, 3,
                             {VA: landmark_type("VA")}, **kw)[:2]

    counts, real = [], tail.tail_mixture

    def counting(core, wide, e, need=None):
        counts.append(core.loglik.size if need is None else int(np.sum(need)))
        return real(core, wide, e, need)

    monkeypatch.setattr(gmphd, "tail_mixture", counting)
    maps, lpsi = run()
    deferred = counts.pop()
    real_terms = gmphd.type_terms
    monkeypatch.setattr(gmphd, "type_terms", lambda *a, **k: real_terms(*a, **{**k, "defer_tail": False}))
    full_maps, full_lpsi = run()
    np.testing.assert_array_equal(lpsi, full_lpsi)
    for key in ("w", "m", "P", "mask"):
        np.testing.assert_array_equal(getattr(maps[VA], key), getattr(full_maps[VA], key))
    assert counts == [4 * 2 * 4]  # the full match: every Gaussian of every particle with every measurement
    assert (deferred < counts[0]) == (prune is not None) and deferred > 0  # the far pairs are pruned
