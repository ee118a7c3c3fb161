"""Tests of slam/fusion/operators.py: MSM distance, accumulated FOV, F_AA and F'_AA with hand-built maps."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.slam.fusion.operators import (ego_vs_average, fuse_aa, fuse_vs, in_accumulated_fov, msm_distance,
                                predict_bs_vs)
from mmslam.slam.core.gm import GM, empty
from mmslam.slam.models.vs import predict_vs

Q_STD = np.array([1, 1, 0.1, 3, 3, 0.1, 0.05])


def _gm(w, m, P):
    w = np.asarray(w, float)
    return GM(w, np.asarray(m, float), np.asarray(P, float), np.ones(w.shape, bool))


def _iso(means, var):
    means = np.asarray(means, float)
    return np.broadcast_to(np.eye(means.shape[-1]) * var, means.shape + (means.shape[-1],)).copy()


def _find(g, mean):
    """Weight of the live component with this mean (must exist exactly once)."""
    hit = g.mask & np.all(np.isclose(g.m, mean), axis=-1)
    assert hit.sum() == 1, (mean, g.m[g.mask])
    return float(g.w[hit][0])


def test_msm_distance_by_hand():
    m1 = np.array([[0.0, 0.0]])
    P1 = np.array([np.diag([1.0, 4.0])])
    m2 = np.array([[2.0, 2.0], [0.0, 0.0]])
    P2 = np.array([np.diag([4.0, 1.0]), np.eye(2)])
    d = msm_distance(m1, P1, m2, P2)
    # D = (-2, -2): D^T P1^-1 D = 4 + 1 = 5, D^T P2^-1 D = 1 + 4 = 5 -> 5; identical means -> 0
    np.testing.assert_allclose(d, [[5.0, 0.0]])
    P2b = np.array([np.diag([0.5, 0.5]), np.eye(2)])
    np.testing.assert_allclose(msm_distance(m1, P1, m2, P2b)[0, 0], 16.0)  # max(5, 8 + 8)
    assert msm_distance(m1, P1, np.zeros((0, 2)), np.zeros((0, 2, 2))).shape == (1, 0)


def test_msm_symmetric_and_asymmetric_mahalanobis_cross_check():
    rng = np.random.default_rng(0)
    m1, m2 = rng.standard_normal((4, 3)), rng.standard_normal((5, 3))
    A = rng.standard_normal((9, 3, 3))
    P = A @ A.transpose(0, 2, 1) + 0.2 * np.eye(3)
    d12 = msm_distance(m1, P[:4], m2, P[4:])
    np.testing.assert_allclose(d12, msm_distance(m2, P[4:], m1, P[:4]).T)
    i, j = 2, 3
    D = m1[i] - m2[j]
    assert d12[i, j] == pytest.approx(max(D @ np.linalg.solve(P[i], D), D @ np.linalg.solve(P[4 + j], D)))


def test_in_accumulated_fov():
    pts = np.array([[0, 0, 0], [60, 0, 0], [200, 0, 0]], float)
    traj = np.array([[10, 0, 0], [40, 0, 0]], float)
    np.testing.assert_array_equal(in_accumulated_fov(pts, traj, 50.0), [True, True, False])
    np.testing.assert_array_equal(in_accumulated_fov(pts, traj, np.inf), [True, True, True])
    np.testing.assert_array_equal(in_accumulated_fov(pts, np.zeros((0, 3)), 50.0), [False] * 3)
    assert in_accumulated_fov(np.zeros((0, 3)), traj, 50.0).shape == (0,)


def test_fuse_aa_matched_unmatched_fov():
    # BS map: A (matched), B (unmatched, inside FOV), C (unmatched, outside FOV), + a masked slot
    bs = empty((), 4, 3)
    bs.mask[:3] = True
    bs.w[:3] = [0.8, 0.6, 0.9]
    bs.m[:3] = [[0, 0, 0], [30, 0, 0], [90, 0, 0]]
    bs.P[:3] = np.eye(3)
    # upload: A' near A (MSM 1), D new
    ue = _gm([0.7, 0.5], [[1, 0, 0], [0, 60, 0]], _iso([[1, 0, 0], [0, 60, 0]], 1.0))
    inside = np.array([True, True, False, True])
    out = fuse_aa(bs, ue, inside, match_threshold=20.0)
    assert out.count() == 5
    assert _find(out, [0, 0, 0]) == pytest.approx(0.4)
    assert _find(out, [1, 0, 0]) == pytest.approx(0.35)
    assert _find(out, [30, 0, 0]) == pytest.approx(0.3)  # inside FOV, unmatched: 1/2
    assert _find(out, [90, 0, 0]) == pytest.approx(0.9)  # outside FOV: 1
    assert _find(out, [0, 60, 0]) == pytest.approx(0.5)  # new from the vehicle: 1
    assert np.all(np.diff(out.w) <= 0)


def test_fuse_aa_threshold_and_one_to_one():
    bs = _gm([0.5], [[0, 0, 0]], _iso([[0, 0, 0]], 1.0))
    # two uploaded components both proximate to the single BS component; the closer is matched
    ue = _gm([0.6, 0.4], [[2, 0, 0], [1, 0, 0]], _iso([[2, 0, 0], [1, 0, 0]], 1.0))
    out = fuse_aa(bs, ue, np.array([False]), 20.0)
    assert _find(out, [0, 0, 0]) == pytest.approx(0.25)
    assert _find(out, [1, 0, 0]) == pytest.approx(0.2)  # matched (MSM 1 < 4)
    assert _find(out, [2, 0, 0]) == pytest.approx(0.6)  # left over: unmatched upload, beta 1
    # MSM exactly at / above the threshold: not proximate (strict <)
    ue2 = _gm([0.6], [[np.sqrt(20.0), 0, 0]], _iso([[0, 0, 0]], 1.0))
    out = fuse_aa(bs, ue2, np.array([True]), 20.0)
    assert _find(out, [0, 0, 0]) == pytest.approx(0.25) and out.w.max() == pytest.approx(0.6)


def test_fuse_aa_empty_sides():
    ue = _gm([0.6, 0.4], [[2, 0, 0], [1, 0, 0]], _iso([[2, 0, 0], [1, 0, 0]], 1.0))
    out = fuse_aa(empty((), 0, 3), ue, np.zeros(0, bool), 20.0)
    np.testing.assert_allclose(np.sort(out.w), [0.4, 0.6])
    out = fuse_aa(ue, empty((), 0, 3), np.array([True, False]), 20.0)
    np.testing.assert_allclose(np.sort(out.w), [0.3, 0.4])  # 0.6 inside -> 1/2, 0.4 outside -> 1
    with pytest.raises(ValueError):
        fuse_aa(ue, ue, np.array([True]), 20.0)  # wrong inside length


def test_ego_vs_average():
    d = 7
    ego_m = np.array([10, 0, 0, 0, 20, 0, 0.3])
    ego_P = np.diag([0.1, 0.1, 0.01, 1, 1, 0.01, 0.01])
    means = np.array([[10.5, 0, 0, 0, 0, 0, 0], [40, 0, 0, 0, 0, 0, 0]])
    avg = _gm([0.9, 0.7], means, _iso(means, 1.0))
    out = ego_vs_average(avg, ego_m, ego_P, threshold=20.0)
    # first component: position MSM = max(0.25/1, 0.25/0.1) = 2.5 < 20 -> removed
    assert out.count() == 2
    assert _find(out, ego_m) == pytest.approx(1.0)
    np.testing.assert_allclose(out.P[np.all(np.isclose(out.m, ego_m), -1)][0], ego_P)
    assert _find(out, means[1]) == pytest.approx(0.7)
    # nothing close: all kept, ego appended
    out = ego_vs_average(avg, ego_m + np.array([0, 100, 0, 0, 0, 0, 0]), ego_P, 20.0)
    assert out.count() == 3
    # empty averaged map: just the ego vehicle
    out = ego_vs_average(empty((), 0, d), ego_m, ego_P, 20.0)
    assert out.count() == 1 and out.w[0] == 1.0


def test_predict_bs_vs_equals_repeated_predict():
    m = np.array([[0, 0, 0, 5, 1, 0, 0.2]])
    g = _gm([0.8], m, _iso(m, 2.0))
    two = predict_bs_vs(g, 0.5, 0.99, Q_STD, 2)
    ref = predict_vs(predict_vs(g, 0.5, 0.99, Q_STD, None), 0.5, 0.99, Q_STD, None)
    np.testing.assert_allclose(two.m, ref.m)
    np.testing.assert_allclose(two.P, ref.P)
    np.testing.assert_allclose(two.w, [0.8 * 0.99**2])
    zero = predict_bs_vs(g, 0.5, 0.99, Q_STD, 0)
    np.testing.assert_array_equal(zero.m, g.m)


def test_fuse_vs_weights():
    d = 7
    mb = np.array([[0, 0, 0, 10, 0, 0, 0],      # A: matched to A'
                   [0, 30, 0, 0, 0, 0, 0],      # B: same position as B' but velocity far -> unmatched
                   [0, 80, 0, 0, 0, 0, 0],      # C: unmatched, inside FOV
                   [0, -80, 0, 0, 0, 0, 0]], float)  # D: unmatched, outside FOV
    Pb = _iso(mb, 2.0)  # rho = 2
    bs = _gm([0.8, 0.6, 0.5, 0.4], mb, Pb)
    mu = np.array([[1, 0, 0, 11, 0, 0, 0], [0, 30, 0, 20, 0, 0, 0], [50, 50, 0, 0, 0, 0, 0]], float)
    Pu = _iso(mu, 1.0)
    Pu[0] = np.eye(d) * 6.0  # rho = 6 for A'
    ue = _gm([0.9, 0.7, 0.3], mu, Pu)
    inside = np.array([True, True, True, False])
    out = fuse_vs(bs, ue, inside, t_pos=20.0, t_vel=20.0, beta_inside_fov=0.25)
    # A/A': 1/rho = 1/2 and 1/6 -> beta 3/4 and 1/4
    assert _find(out, mb[0]) == pytest.approx(0.8 * 0.75)
    assert _find(out, mu[0]) == pytest.approx(0.9 * 0.25)
    assert _find(out, mb[1]) == pytest.approx(0.6 * 0.25)  # unmatched (velocity MSM 200), inside
    assert _find(out, mu[1]) == pytest.approx(0.7)  # unmatched upload: 1
    assert _find(out, mb[2]) == pytest.approx(0.5 * 0.25)
    assert _find(out, mb[3]) == pytest.approx(0.4)  # outside FOV: 1
    assert _find(out, mu[2]) == pytest.approx(0.3)
    assert out.count() == 7


def test_fuse_vs_matched_weights_sum_to_one_and_equal_rho_half():
    m = np.array([[0, 0, 0, 1, 1, 0, 0.1]])
    bs = _gm([0.6], m, _iso(m, 3.0))
    ue = _gm([0.6], m + 0.1, _iso(m, 3.0))
    out = fuse_vs(bs, ue, np.array([True]), 20.0, 20.0, 0.25)
    np.testing.assert_allclose(np.sort(out.w), [0.3, 0.3])


def test_fuse_vs_with_pairs_names_the_union_slots_of_each_matched_pair():
    mb = np.array([[0, 0, 0, 10, 0, 0, 0], [0, 80, 0, 0, 0, 0, 0]], float)
    mu = np.array([[50, 50, 0, 0, 0, 0, 0], [1, 0, 0, 11, 0, 0, 0]], float)
    bs, ue = _gm([0.8, 0.5], mb, _iso(mb, 2.0)), _gm([0.3, 0.9], mu, _iso(mu, 2.0))
    out, pairs = fuse_vs(bs, ue, np.array([True, True]), 20.0, 20.0, 0.25, with_pairs=True)
    plain = fuse_vs(bs, ue, np.array([True, True]), 20.0, 20.0, 0.25)
    np.testing.assert_array_equal(out.w, plain.w)  # the flag changes nothing but the extra output
    assert pairs.shape == (1, 2)
    np.testing.assert_allclose(out.m[pairs[0, 0]], mb[0])  # BS member of the pair
    np.testing.assert_allclose(out.m[pairs[0, 1]], mu[1])  # uploaded member
    out_aa, pairs_aa = fuse_aa(bs, ue, np.array([True, True]), 20.0, with_pairs=True)
    assert pairs_aa.shape == (1, 2)
    np.testing.assert_allclose(out_aa.m[pairs_aa[0]], [mb[0], mu[1]])


def test_merge_pairs_is_the_moment_match_of_each_pair_and_leaves_the_rest():
    from mmslam.slam.phd.reduction import merge_pairs, prune_merge

    m = np.array([[0.0, 0, 0], [2.0, 0, 0], [10.0, 0, 0], [11.0, 0, 0]])
    P = _iso(m, 1.0)
    g = _gm([1.0, 3.0, 0.5, 0.5], m, P)
    out = merge_pairs(g, np.array([[0, 1]]))
    # by hand: w = 4, mean x = (0*1 + 2*3)/4 = 1.5, var x = (1*(1 + 1.5^2) + 3*(1 + 0.5^2))/4 = 1.75
    assert out.count() == 3 and out.w[0] == pytest.approx(4.0)
    np.testing.assert_allclose(out.m[0], [1.5, 0, 0])
    np.testing.assert_allclose(np.diag(out.P[0]), [1.75, 1.0, 1.0])
    assert not out.mask[1]
    np.testing.assert_array_equal(out.m[2:], m[2:])  # 10 and 11 are 1 sigma apart but not a pair
    # the same pair through prune_merge (gate wide enough for exactly that cluster) agrees
    ref = prune_merge(_gm([1.0, 3.0], m[:2], P[:2]), 0.0, 100.0, 10)
    np.testing.assert_allclose(ref.m[0], out.m[0])
    np.testing.assert_allclose(ref.P[0], out.P[0])
    with pytest.raises(ValueError, match="disjoint"):
        merge_pairs(g, np.array([[0, 1], [1, 2]]))


def _with_beta(g, ab):
    return GM(g.w, g.m, g.P, g.mask, np.asarray(ab, float))


def test_fuse_aa_visibility_weights_by_hand():
    """fusion.aa_weights = visibility: a matched pair weighted by each member's E[p_D] = s / (s + t).

    BS copy: w 1.0, Beta (3, 1) -> pi 0.75 (seen); upload: w 0.2, Beta (0.2, 3.8) -> pi 0.05 (a car
    that never saw it, its copy decayed by misses). beta_b = 0.75 / 0.8, beta_u = 0.05 / 0.8: the pair
    sums to 0.9375 + 0.0125 = 0.95 instead of (1.0 + 0.2) / 2 = 0.6 with the paper's 1/2."""
    bs = _with_beta(_gm([1.0], [[0, 0, 0]], _iso([[0, 0, 0]], 1.0)), [[3.0, 1.0]])
    ue = _with_beta(_gm([0.2, 0.5], [[0.5, 0, 0], [0, 60, 0]], _iso([[0, 0, 0], [0, 60, 0]], 1.0)),
                    [[0.2, 3.8], [1.0, 1.0]])
    vis = fuse_aa(bs, ue, np.array([False]), 20.0, weights="visibility")
    assert _find(vis, [0, 0, 0]) == pytest.approx(0.9375)
    assert _find(vis, [0.5, 0, 0]) == pytest.approx(0.0125)
    assert _find(vis, [0, 60, 0]) == pytest.approx(0.5)  # unmatched upload: 1 either way
    eq = fuse_aa(bs, ue, np.array([False]), 20.0, weights="equal")
    assert _find(eq, [0, 0, 0]) == pytest.approx(0.5) and _find(eq, [0.5, 0, 0]) == pytest.approx(0.1)


def test_fuse_aa_visibility_weights_reduce_to_the_paper_rule():
    """Equal E[p_D] on both sides, or no Beta (a fixed p_D): beta = 1/2 exactly, as eq. (8)."""
    bs = _gm([0.8, 0.6], [[0, 0, 0], [30, 0, 0]], _iso([[0, 0, 0], [30, 0, 0]], 1.0))
    ue = _gm([0.7], [[1, 0, 0]], _iso([[1, 0, 0]], 1.0))
    inside = np.array([True, True])
    ref = fuse_aa(bs, ue, inside, 20.0)
    for b, u in ((bs, ue), (_with_beta(bs, [[1.0, 9.0], [2.0, 2.0]]), _with_beta(ue, [[3.0, 27.0]]))):
        out = fuse_aa(b, u, inside, 20.0, weights="visibility")
        np.testing.assert_allclose(out.w, ref.w, rtol=1e-12)
        np.testing.assert_allclose(out.m, ref.m, rtol=1e-12)
    with pytest.raises(ValueError, match="fusion weights"):
        fuse_aa(bs, ue, inside, 20.0, weights="max")


def test_a_matched_pair_keeps_both_shares_with_visibility_weights():
    """The fused weight of a matched pair is beta_b w_b + beta_u w_u, however small the upload's share.

    Canyon's case (seed 5001, step 9): the BS holds a VA one car saw, w_b 1.12 with Beta (4.35, 1.96), pi_b
    0.689; a car that never saw it uploads its copy, w_u 1.26 with the prior Beta (0.2, 3.8), pi_u 0.05. beta_u =
    0.05 / 0.739 = 0.0677, so the upload's share 0.0852 is below average_prune 0.1: pruned before the merge it was
    lost (w 1.044, 7% of the landmark per fusion). Merged first, the pair gives 0.9323 * 1.12 + 0.0677 * 1.26 =
    1.1295 at the weighted mean of the two; the paper's equal weights keep its published reduction (the upload's
    half, 0.63, is above the threshold there, so a weak copy, w_u 0.15, shows the paper's rule: 0.5 w_b only)."""
    from mmslam.scenes.scenario import load_preset, with_overrides
    from mmslam.slam.specs.landmarks import landmark_type
    from mmslam.slam.models.measurement import VA

    spec = landmark_type(VA)
    bs = _with_beta(_gm([1.12], [[-33.0, 31.18, 25.0]], _iso([[0, 0, 0]], 0.5)), [[4.35, 1.96]])
    ue = _with_beta(_gm([1.26], [[-33.0, 31.25, 25.0]], _iso([[0, 0, 0]], 0.5)), [[0.2, 3.8]])
    city = with_overrides(load_preset("canyon"), [])
    assert city.fusion.aa_weights == "visibility" and city.fusion.average_prune == 0.1
    fused, pairs = fuse_aa(bs, ue, np.array([False]), 20.0, with_pairs=True, weights="visibility")
    out = spec.reduce_fused(fused, pairs, city, spec)
    pi_b, pi_u = 4.35 / 6.31, 0.2 / 4.0
    b_b, b_u = pi_b / (pi_b + pi_u), pi_u / (pi_b + pi_u)
    assert b_u * 1.26 < 0.1  # the share the pruning used to drop
    assert out.mask.sum() == 1
    live = out.mask
    assert out.w[live][0] == pytest.approx(b_b * 1.12 + b_u * 1.26, rel=1e-12)
    y = (b_b * 1.12 * 31.18 + b_u * 1.26 * 31.25) / (b_b * 1.12 + b_u * 1.26)
    assert out.m[live][0][1] == pytest.approx(y, rel=1e-12)
    paper = load_preset("paper")
    weak = _with_beta(_gm([0.15], [[-33.0, 31.25, 25.0]], _iso([[0, 0, 0]], 0.5)), [[0.2, 3.8]])
    fused, pairs = fuse_aa(bs, weak, np.array([False]), 20.0, with_pairs=True, weights=paper.fusion.aa_weights)
    out = spec.reduce_fused(fused, pairs, paper, spec)
    assert out.w[out.mask].tolist() == pytest.approx([0.5 * 1.12], rel=1e-12)
    # visibility asked for but no Beta on the maps (pd_model fixed): fuse_aa weighs 1/2 each, and the reduction is
    # the published one too
    plain = [GM(g.w, g.m, g.P, g.mask) for g in (bs, weak)]
    fused, pairs = fuse_aa(*plain, np.array([False]), 20.0, with_pairs=True, weights="visibility")
    out = spec.reduce_fused(fused, pairs, city, spec)
    assert out.w[out.mask].tolist() == pytest.approx([0.5 * 1.12], rel=1e-12)


def test_a_matched_pair_is_one_landmark_whatever_the_merge_gate():
    """With visibility weights a pair the fusion matched (MSM distance below fusion.msm_position) is merged even where
    the type's merge gate would keep its members apart: two VAs 2 m apart in x, variance 0.5 m^2 per axis, weight 1
    each, equal Betas (shares 1/2): squared Mahalanobis distance 4 / 0.5 = 8 > the VA gate 6, MSM matched. One
    component of weight 1 at the midpoint; with equal weights (the paper's reduction) the two halves stay two."""
    from mmslam.scenes.scenario import load_preset, with_overrides
    from mmslam.slam.specs.landmarks import landmark_type
    from mmslam.slam.models.measurement import VA

    spec = landmark_type(VA)
    city = with_overrides(load_preset("canyon"), [])
    assert spec.merge_gate(city) == 6.0
    bs = _with_beta(_gm([1.0], [[0.0, 0.0, 0.0]], _iso([[0, 0, 0]], 0.5)), [[1.0, 1.0]])
    ue = _with_beta(_gm([1.0], [[2.0, 0.0, 0.0]], _iso([[0, 0, 0]], 0.5)), [[1.0, 1.0]])
    for weights, want in (("visibility", [(1.0, 1.0)]), ("equal", [(0.5, 0.0), (0.5, 2.0)])):
        fused, pairs = fuse_aa(bs, ue, np.array([False]), 20.0, with_pairs=True, weights=weights)
        assert len(pairs) == 1
        scn = with_overrides(city, [f'fusion.aa_weights="{weights}"'])
        out = spec.reduce_fused(fused, pairs, scn, spec)
        got = sorted((float(w), float(m[0])) for w, m in zip(out.w[out.mask], out.m[out.mask]))
        assert got == [pytest.approx(x, rel=1e-12, abs=1e-12) for x in want]
