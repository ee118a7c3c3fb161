"""Tests of slam/phd/reduction.py: hand-computed merges, the exact merge criterion, batching."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.slam.core.gm import GM, empty, select
from mmslam.slam.phd.reduction import average_map, prune_merge
from mmslam.slam.reference.reduction import greedy_merge


def _gm(w, m, P=None):
    w = np.asarray(w, float)
    m = np.asarray(m, float)
    d = m.shape[-1]
    if P is None:
        P = np.broadcast_to(np.eye(d), m.shape + (d,)).copy()
    return GM(w, m, np.asarray(P, float), np.ones(w.shape, bool))


def _live(g):
    return g.w[g.mask], g.m[g.mask], g.P[g.mask]


def test_merge_two_by_hand_and_keep_far_one():
    g = _gm([0.6, 0.4, 0.3, 1e-5], [[0, 0], [1, 0], [10, 0], [0.2, 0]])
    out = prune_merge(g, prune=1e-4, merge=4.0, cap=10)
    w, m, P = _live(out)
    assert w.shape == (2,)
    np.testing.assert_allclose(w, [1.0, 0.3])
    np.testing.assert_allclose(m[0], [0.4, 0.0])
    # 0.6 (I + diag(0.4^2, 0)) + 0.4 (I + diag(0.6^2, 0)) = diag(1.24, 1)
    np.testing.assert_allclose(P[0], np.diag([1.24, 1.0]))
    np.testing.assert_allclose(m[1], [10.0, 0.0])
    np.testing.assert_allclose(P[1], np.eye(2))


def test_merge_criterion_uses_candidate_covariance():
    # j (highest weight) is sharp, i is wide: (m_i - m_j)^T P_i^{-1} (m_i - m_j) = 9 / 100 < 1.
    P = [np.eye(2) * 0.01, np.eye(2) * 100.0]
    g = _gm([0.9, 0.5], [[0, 0], [3, 0]], P)
    assert prune_merge(g, 0.0, 1.0, 5).count() == 1
    # reversed roles: now the candidate is sharp -> distance 900 > 1, no merge
    g2 = _gm([0.5, 0.9], [[0, 0], [3, 0]], P)
    assert prune_merge(g2, 0.0, 1.0, 5).count() == 2


def test_boundary_distance_equal_threshold_merges():
    g = _gm([0.5, 0.5 - 1e-9], [[0.0], [7.0]])
    assert prune_merge(g, 0.0, 49.0, 5).count() == 1
    g = _gm([0.5, 0.5 - 1e-9], [[0.0], [7.01]])
    assert prune_merge(g, 0.0, 49.0, 5).count() == 2


def test_max_trace_and_cap():
    P = [np.eye(3), np.eye(3) * 20.0, np.eye(3), np.eye(3)]  # trace 60 > 50 for the second
    m = [[0, 0, 0], [50, 0, 0], [100, 0, 0], [200, 0, 0]]
    g = _gm([0.2, 0.9, 0.5, 0.4], m, P)
    out = prune_merge(g, 1e-4, 49.0, cap=2, max_trace=50.0)
    w, m_, _ = _live(out)
    np.testing.assert_allclose(w, [0.5, 0.4])
    np.testing.assert_allclose(m_[:, 0], [100, 200])
    out = prune_merge(g, 1e-4, 49.0, cap=2, max_trace=50.0, fixed_capacity=True)
    assert out.capacity == 2
    # pos_dims limits the trace to the first dims: trace of 1 dim = 20 <= 50 -> kept
    out = prune_merge(g, 1e-4, 49.0, cap=5, max_trace=50.0, pos_dims=1)
    assert out.count() == 4


def test_weight_conserved_and_covariance_spd():
    rng = np.random.default_rng(3)
    Q, d = 30, 7
    A = rng.standard_normal((Q, d, d))
    P = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(d)
    g = _gm(rng.uniform(0.01, 1, Q), rng.standard_normal((Q, d)) * 2, P)
    out = prune_merge(g, 0.0, 49.0, cap=Q)
    np.testing.assert_allclose(out.w[out.mask].sum(), g.w.sum())
    w, m, Pm = _live(out)
    np.testing.assert_allclose(Pm, np.swapaxes(Pm, -1, -2))
    assert np.all(np.linalg.eigvalsh(Pm) > 0)
    # weighted mean of all components is preserved by moment matching
    np.testing.assert_allclose((w[:, None] * m).sum(0), (g.w[:, None] * g.m).sum(0), atol=1e-9)


def test_batched_equals_per_mixture():
    rng = np.random.default_rng(0)
    B, Q, d = (4, 3), 9, 3
    w = rng.uniform(0, 1, B + (Q,))
    m = rng.uniform(-4, 4, B + (Q, d))
    A = rng.standard_normal(B + (Q, d, d)) * 0.7
    P = A @ np.swapaxes(A, -1, -2) + 0.3 * np.eye(d)
    mask = rng.uniform(size=B + (Q,)) < 0.8
    w = np.where(mask, w, 0.0)
    g = GM(w, m, P, mask)
    out = prune_merge(g, 0.05, 4.0, cap=5)
    for idx in np.ndindex(*B):
        single = prune_merge(select(g, idx), 0.05, 4.0, cap=5)
        k = int(single.count())
        assert int(out.count()[idx]) == k
        o = select(out, idx)
        np.testing.assert_allclose(o.w[:k], single.w[:k])
        np.testing.assert_allclose(o.m[:k], single.m[:k])
        np.testing.assert_allclose(o.P[:k], single.P[:k])
    assert (out.count() <= 5).all() and out.count().max() > 0


def test_empty_and_all_pruned():
    g = empty((3,), 4, 2)
    out = prune_merge(g, 1e-4, 49.0, 5)
    assert out.batch_shape == (3,) and (out.count() == 0).all()
    g = _gm([1e-6, 1e-7], [[0, 0], [1, 1]])
    assert prune_merge(g, 1e-4, 49.0, 5).count() == 0


def test_nan_raises():
    g = _gm([0.5, 0.5], [[0, np.nan], [1, 1]])
    with pytest.raises(FloatingPointError):
        prune_merge(g, 1e-4, 49.0, 5)


def test_average_map_weights_and_prune():
    # 2 particles, both see a landmark near (0,0); only particle 0 sees one at (50, 0).
    m = np.array([[[0, 0, 0], [50, 0, 0]], [[0.3, 0, 0], [90, 0, 0]]], float)
    w = np.array([[0.9, 0.8], [0.9, 0.05]])  # particle 1's second component: eta < 0.1 -> dropped
    g = GM(w, m, np.broadcast_to(np.eye(3), (2, 2, 3, 3)).copy(), np.ones((2, 2), bool))
    out = average_map(g, np.array([3.0, 1.0]), prune=0.1, merge=49.0, cap=10)
    assert out.batch_shape == ()
    wl, ml, _ = _live(out)
    np.testing.assert_allclose(wl, [0.9, 0.6])  # 0.75*0.9 + 0.25*0.9; 0.75*0.8
    np.testing.assert_allclose(ml[0], [0.25 * 0.3, 0, 0])
    np.testing.assert_allclose(ml[1], [50, 0, 0])
    # with particle 0 weight small, the (50,0,0) landmark's averaged weight < 0.1 -> dropped
    out = average_map(g, np.array([0.1, 0.9]), prune=0.1, merge=49.0, cap=10)
    assert out.count() == 1
    np.testing.assert_allclose(out.w[0], 0.9)


def test_average_map_identical_particles_equal_prune_merge():
    rng = np.random.default_rng(1)
    Q = 6
    single = _gm(rng.uniform(0.2, 1, Q), rng.uniform(-30, 30, (Q, 3)))
    P = 5
    g = GM(np.tile(single.w, (P, 1)), np.tile(single.m, (P, 1, 1)), np.tile(single.P, (P, 1, 1, 1)),
           np.ones((P, Q), bool))
    out = average_map(g, rng.uniform(0.1, 1, P), 0.1, 4.0, 10)
    ref = prune_merge(single, 0.1, 4.0, 10)
    k = int(ref.count())
    assert out.count() == k
    np.testing.assert_allclose(out.w[:k], ref.w[:k])
    np.testing.assert_allclose(out.m[:k], ref.m[:k], atol=1e-9)
    np.testing.assert_allclose(out.P[:k], ref.P[:k], atol=1e-9)


def _ref_greedy(w, m, P, merge):
    """Plain greedy Vo & Ma merge of one mixture (:func:`mmslam.slam.reference.reduction.greedy_merge`:
    LAPACK inverse per component, lower index heads ties): ``(W, mean, cov)`` per cluster."""
    return [(W, mu, C) for _, W, mu, C in greedy_merge(w, m, P, range(len(w)), merge)[0]]


def test_batched_prune_merge_equals_each_mixture_alone():
    """7-D batch: every mixture's result equals prune_merge of that mixture alone (1e-9 relative)."""
    rng = np.random.default_rng(5)
    B, Q, d = (6,), 12, 7
    A = rng.standard_normal(B + (Q, d, d))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(d)
    g = GM(rng.uniform(0, 1, B + (Q,)), rng.uniform(-3, 3, B + (Q, d)) + 100.0, P, np.ones(B + (Q,), bool))
    ref = prune_merge(g, 0.01, 9.0, 8)
    for i in range(B[0]):
        one = prune_merge(select(g, i), 0.01, 9.0, 8)
        k = int(one.count())
        assert int(ref.count()[i]) == k
        np.testing.assert_allclose(ref.w[i, :k], one.w[:k], rtol=1e-9)
        np.testing.assert_allclose(ref.m[i, :k], one.m[:k], rtol=1e-9)
        np.testing.assert_allclose(ref.P[i, :k], one.P[:k], rtol=1e-9, atol=1e-9 * np.abs(one.P[:k]).max())
    assert (ref.count() < Q).any()  # some merging happened


def test_singular_covariance_raises():
    g = _gm([0.5, 0.5], [[0, 0, 0], [1, 1, 1]], [np.eye(3), np.zeros((3, 3))])
    with pytest.raises(FloatingPointError):
        prune_merge(g, 1e-4, 49.0, 5)


def test_single_mixture_merge_equals_the_plain_greedy_reference():
    rng = np.random.default_rng(6)
    Q, d = 40, 7
    A = rng.standard_normal((Q, d, d))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(d)
    centres = rng.uniform(-20, 20, (5, d))
    m = centres[rng.integers(0, 5, Q)] + rng.standard_normal((Q, d))
    w = rng.uniform(0, 1, Q)
    w[3] = w[7]  # a weight tie: the lower index must head the cluster
    g = _gm(w, m, P)
    out = prune_merge(g, 0.01, 16.0, Q)
    ref = sorted(_ref_greedy(w, m, P, 16.0), key=lambda c: -c[0])
    assert int(out.count()) == len(ref) and 1 < len(ref) < Q
    for k, (W, mu, C) in enumerate(ref):
        np.testing.assert_allclose(out.w[k], W, rtol=1e-9)
        np.testing.assert_allclose(out.m[k], mu, rtol=1e-9, atol=1e-9 * np.abs(mu).max())
        np.testing.assert_allclose(out.P[k], C, rtol=1e-9, atol=1e-9 * np.abs(C).max())


def test_spd_inverse_matches_lapack_inverse():
    from mmslam.slam.core.linalg import spd_inv

    rng = np.random.default_rng(17)
    for d in (2, 3, 4, 5, 7):
        X = rng.standard_normal((2, 6, d, d + 2))
        P = X @ np.swapaxes(X, -1, -2) + 1e-3 * np.eye(d)
        inv = spd_inv(P, "test")
        ref = np.linalg.inv(P)
        np.testing.assert_allclose(inv, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        assert np.array_equal(inv, np.swapaxes(inv, -1, -2))
    for bad in (np.diag([1.0, -1.0, 1.0]), np.diag([1.0, -1.0, 1.0, 1.0]), np.zeros((3, 3))):
        with pytest.raises(FloatingPointError, match="singular or indefinite covariance in test"):
            spd_inv(bad[None], "test")


def test_merge_flat_moments_equal_the_plain_reference():
    """Every mixture of a flat batch (random keep masks) equals the plain greedy reference."""
    import mmslam.slam.phd.reduction as red

    rng = np.random.default_rng(18)
    n, q, d = 40, 6, 7
    w = rng.uniform(0.01, 1.0, (n, q))
    m = rng.standard_normal((n, q, d)) * 2.0
    X = rng.standard_normal((n, q, d, d))
    P = X @ np.swapaxes(X, -1, -2) + np.eye(d)
    keep = rng.random((n, q)) < 0.8
    ow, om, oP, omask = red._merge_flat(w, m, P, keep, 49.0)
    for i in range(n):
        k = np.nonzero(keep[i])[0]
        ref = _ref_greedy(w[i, k], m[i, k], P[i, k], 49.0)
        assert int(omask[i].sum()) == len(ref) and omask[i, :len(ref)].all()
        for c, (W, mu, C) in enumerate(ref):
            np.testing.assert_allclose(ow[i, c], W, rtol=1e-9)
            np.testing.assert_allclose(om[i, c], mu, rtol=1e-9, atol=1e-9 * np.abs(mu).max())
            np.testing.assert_allclose(oP[i, c], C, rtol=1e-9, atol=1e-9 * np.abs(C).max())
        assert (oP[i, len(ref):] == np.eye(d)).all() and (ow[i, len(ref):] == 0).all()


@pytest.mark.parametrize("presorted", [False, True])
def test_compact_equals_stable_argsort_gather(presorted):
    from mmslam.slam.core.gm import compact

    rng = np.random.default_rng(19)
    B, q, d = (3, 4), 6, 3
    w = rng.choice([0.1, 0.5, 0.7], (*B, q))  # ties
    mask = rng.random((*B, q)) < 0.7
    g = GM(np.where(mask, w, 0.0), rng.standard_normal((*B, q, d)), rng.standard_normal((*B, q, d, d)), mask)
    if presorted:
        g = compact(g, q)
    for cap in (None, 2, q, q + 2):
        out = compact(g, cap)
        key = np.where(g.mask, -g.w, np.inf)
        order = np.argsort(key, axis=-1, kind="stable")[..., : (int(g.count().max()) if cap is None else cap)]
        k = order.shape[-1]
        assert out.capacity == (k if cap is None or cap <= q else cap)
        assert np.array_equal(out.mask[..., :k], np.take_along_axis(g.mask, order, -1))
        assert np.array_equal(out.w[..., :k], np.where(out.mask[..., :k], np.take_along_axis(g.w, order, -1), 0.0))
        assert np.array_equal(out.m[..., :k, :], np.take_along_axis(g.m, order[..., None], -2))
        assert np.array_equal(out.P[..., :k, :, :], np.take_along_axis(g.P, order[..., None, None], -3))



def test_compact_zeroes_the_weights_of_masked_slots_at_every_capacity():
    # a mixture whose masked slots still hold weights (the keep_tentative downlink builds one: GM(own.w, ..., tentative));
    # the padding branch (capacity above the slots) used to return them unzeroed
    from mmslam.slam.core.gm import compact

    w = np.array([[0.2, 0.9, 0.5]])
    mask = np.array([[True, False, True]])
    g = GM(w, np.zeros((1, 3, 3)), np.broadcast_to(np.eye(3), (1, 3, 3, 3)).copy(), mask)
    for cap in (None, 2, 3, 5):
        out = compact(g, cap)
        assert (out.w[~out.mask] == 0.0).all(), cap
        assert np.array_equal(out.w[out.mask], [0.5, 0.2])


def test_moment_match_equals_the_textbook_formula():
    from mmslam.slam.phd.reduction import moment_match

    rng = np.random.default_rng(2)
    Q, d = 5, 7
    w = rng.uniform(0.1, 1.0, Q)
    m = rng.normal(size=(Q, d)) + 50.0
    X = rng.normal(size=(Q, d, d))
    P = X @ np.swapaxes(X, -1, -2) + np.eye(d)
    members = np.array([0, 2, 3])
    out_m, out_P = np.empty(d), np.empty((d, d))
    W = moment_match(w, m, P, members, 2, out_m, out_P)
    mu = (w[members, None] * m[members]).sum(0) / w[members].sum()
    C = sum(w[i] * (P[i] + np.outer(m[i] - mu, m[i] - mu)) for i in members) / w[members].sum()
    assert np.isclose(W, w[members].sum(), rtol=1e-12)
    np.testing.assert_allclose(out_m, mu, rtol=1e-12)
    np.testing.assert_allclose(out_P, C, rtol=1e-9, atol=1e-9 * np.abs(C).max())
    assert np.array_equal(out_P, out_P.T)


def test_non_finite_components_raise_only_where_live():
    """A NaN in a masked slot is ignored; in a live component it raises even when that component would be
    pruned (prune_merge) or belongs to a particle of weight 0 (average_map), naming the stage."""
    g = _gm([0.5, 0.5, 1e-6], [[0, 0], [1, 1], [2, np.nan]])
    with pytest.raises(FloatingPointError, match="in prune_merge input"):
        prune_merge(g, 1e-4, 49.0, 5)
    g.mask[2] = False
    assert prune_merge(g, 1e-4, 49.0, 5).count() == 1
    two = GM(np.array([[0.5, 0.5], [0.5, np.inf]]), np.zeros((2, 2, 2)), np.broadcast_to(np.eye(2), (2, 2, 2, 2)).copy(),
             np.ones((2, 2), bool))
    with pytest.raises(FloatingPointError, match="in average_map input"):
        average_map(two, np.array([1.0, 0.0]), 0.1, 49.0, 5)
    two.mask[1, 1] = False
    out = average_map(two, np.array([1.0, 0.0]), 0.1, 49.0, 5)
    assert out.count() == 1 and np.isclose(out.w[0], 1.0)  # particle 0's two Gaussians merged


def test_average_map_rejects_bad_particle_weights_and_drops_zero_weight_particles():
    """NaN, +-inf, negative or all-zero particle weights raise; a particle of weight 0 contributes no
    component even when its own weight eta passes the prune threshold (the path without NaN placement
    for all-positive weights gives the same map as one with an explicit zero)."""
    m = np.array([[[0, 0, 0]], [[100, 0, 0]]], float)
    g = GM(np.array([[0.9], [0.9]]), m, np.broadcast_to(np.eye(3), (2, 1, 3, 3)).copy(), np.ones((2, 1), bool))
    for bad in ([np.nan, 1.0], [np.inf, 1.0], [-np.inf, 1.0], [-0.5, 1.0], [0.0, 0.0], [np.inf, -np.inf]):
        with pytest.raises(FloatingPointError, match="particle weights must be finite, non-negative"):
            average_map(g, np.array(bad), 0.1, 49.0, 5)
    out = average_map(g, np.array([1.0, 0.0]), 0.1, 49.0, 5)
    assert out.count() == 1 and np.array_equal(out.m[0], [0.0, 0.0, 0.0]) and out.w[0] == 0.9
    both = average_map(g, np.array([1.0, 1.0]), 0.1, 49.0, 5)
    assert both.count() == 2 and np.allclose(np.sort(both.w[both.mask]), [0.45, 0.45])


def test_fixed_capacity_pads_with_dead_slots():
    g = _gm([[0.6, 0.4, 0.3], [0.2, 0.0, 0.0]], [[[0, 0], [1, 0], [10, 0]], [[5, 5], [0, 0], [0, 0]]])
    g.mask[1, 1:] = False
    out = prune_merge(g, 1e-4, 4.0, 4, fixed_capacity=True)
    assert out.capacity == 4 and out.count().tolist() == [2, 1]
    dead = ~out.mask
    assert (out.w[dead] == 0).all() and (out.m[dead] == 0).all() and (out.P[dead] == np.eye(2)).all()
    assert prune_merge(g, 1e-4, 4.0, 4).capacity == 2


def test_drop_dead_slots_keeps_the_live_columns_in_order():
    from mmslam.slam.core.gm import drop_dead_slots

    rng = np.random.default_rng(3)
    mask = np.array([[True, False, False, True], [False, False, False, True]])
    g = GM(np.where(mask, 0.5, 0.0), rng.normal(size=(2, 4, 3)), rng.normal(size=(2, 4, 3, 3)), mask,
           rng.uniform(1, 5, (2, 4, 2)))
    out = drop_dead_slots(g)
    assert out.capacity == 2
    for a, b in ((out.w, g.w), (out.mask, g.mask), (out.pd_beta, g.pd_beta)):
        assert np.array_equal(a, b[:, [0, 3]])
    assert np.array_equal(out.m, g.m[:, [0, 3]]) and np.array_equal(out.P, g.P[:, [0, 3]])
    full = GM(g.w, g.m, g.P, np.ones((2, 4), bool))
    assert drop_dead_slots(full) is full
    assert drop_dead_slots(empty((2,), 3, 3)).capacity == 0
    none = empty((2,), 0, 3)
    assert drop_dead_slots(none) is none
    assert drop_dead_slots(empty((), 2, 3)).capacity == 0


def test_drop_dead_slots_rejects_a_mask_of_another_shape():
    """The compiled live-slot search reads ``mask (N, Q)`` with ``Q`` from the weights: a mask of another
    shape raises a one-line ValueError first."""
    from mmslam.slam.core.gm import GM, drop_dead_slots

    g = GM(np.zeros((2, 3)), np.zeros((2, 3, 3)), np.broadcast_to(np.eye(3), (2, 3, 3, 3)).copy(),
           np.zeros((2, 2), bool))
    with pytest.raises(ValueError, match="mask"):
        drop_dead_slots(g)


def test_merge_without_pruning_zero_and_subnormal_weights():
    """prune = 0 keeps every live component: a cluster of zero weights gets its head's moments (it had a
    zero covariance, which broke the next merge's Cholesky), and subnormal weights merge to the same
    moments as the same weights scaled to normal numbers (``w_i P_i`` had lost its digits: an indefinite P)."""
    P0 = np.array([[2e-4, 1e-5], [1e-5, 1e-4]])
    m = [[0.0, 0.0], [0.01, 0.0], [5.0, 5.0], [5.01, 5.0]]
    ref = prune_merge(_gm([1.0, 0.5, 0.0, 0.0], m, [P0] * 4), prune=0.0, merge=4.0, cap=10)
    w, mm, P = _live(ref)
    assert w.tolist() == [1.5, 0.0]
    np.testing.assert_array_equal(mm[1], [5.0, 5.0])  # the head of the zero-weight cluster (first on ties)
    np.testing.assert_array_equal(P[1], P0)
    tiny = prune_merge(_gm([2 * 5e-324, 5e-324, 0.0, 0.0], m, [P0] * 4), prune=0.0, merge=4.0, cap=10)
    wt, mt, Pt = _live(tiny)
    np.testing.assert_allclose(mt, mm, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Pt, P, rtol=1e-9)
    assert np.all(np.linalg.eigvalsh(Pt) > 0)
    # and again: the merged map merges (it raised "singular or indefinite covariance")
    prune_merge(tiny, prune=0.0, merge=4.0, cap=10)
