"""filter.pd_model = "beta": a Beta(s, t) of each Gaussian's own detection probability (slam/phd/detection.py).

Hand-computed Beta updates of one Gaussian (missed, detected, outside the FOV), the merge rule,
its carriage through the reduction / fusion, and the model off = the fixed model.
"""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.analytic import AnalyticSource
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.scenes.trajectory import true_trajectories
from mmslam.slam.fusion import operators as fusion
from mmslam.slam.phd.detection import beta_pool, expected_pd, predict_beta, prior_beta
from mmslam.slam.filter import run_filter
from mmslam.slam.core.gm import GM, concat, empty
from mmslam.slam.phd.gmphd import correct
from mmslam.slam.models.measurement import SP, VA, measure
from mmslam.slam.phd.reduction import average_map, merge_pairs, prune_merge
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import landmark_type

KINDS = {t.code: t for t in (landmark_type("VA"), landmark_type("SP"), landmark_type("VS"))}
"""Type code -> spec: what gmphd.correct is handed about each map's type."""

BS = np.array([0.0, 0.0, 10.0])
STATE = np.array([5.0, -20.0, 1.5, 0.3, 10.0, 0.0, 2.0])  # x, y, z, heading, speed, turn, clock bias
R = np.diag([0.1, 1e-4, 1e-4, 1e-4, 1e-4])
LOG_CLUTTER = np.log(1e-3)


def _one(x, w=0.5, ab=(2.0, 3.0)) -> GM:
    """One particle, one 3-D Gaussian at ``x`` (covariance 0.25 I) with Beta ``ab``."""
    return GM(np.array([[w]]), np.asarray(x, float).reshape(1, 1, 3), 0.25 * np.eye(3)[None, None],
              np.ones((1, 1), bool), None if ab is None else np.array([[ab]], float))


def _pd_const(p, fov=np.inf):
    def pd_fn(u, x, t):
        d = np.linalg.norm(np.asarray(x) - np.asarray(u), axis=-1)
        return np.where(d <= fov, p, 0.0)
    return pd_fn


def _correct(g: GM, lm_type: int, pd_fn, Z: np.ndarray):
    maps, _, _ = correct({lm_type: g}, STATE[None], Z, R, BS, pd_fn, np.zeros(1), LOG_CLUTTER, None, {}, 0, KINDS)
    return maps[lm_type]


def test_detected_and_missed_beta_of_one_gaussian_by_hand():
    """Beta(2, 3): E[p_D] = 0.4. Missed slot: (1 - 0.4) w = 0.3, Beta(2, 4); detected slot:
    Beta(3, 2); every weight and moment equals the fixed model's with p_D = 0.4."""
    x = np.array([-30.0, 25.0, 3.0])
    Z = measure(STATE, x, Bounce.MIRROR, BS)[None]
    out = _correct(_one(x), VA, _pd_const(0.95), Z)  # with a Beta only the gate (> 0) of pd_fn counts
    fixed = _correct(_one(x, ab=None), VA, _pd_const(0.4), Z)
    assert out.w[0, 0] == pytest.approx(0.3, rel=1e-12)
    np.testing.assert_allclose(out.pd_beta[0, 0], [2.0, 4.0])
    np.testing.assert_allclose(out.pd_beta[0, 1], [3.0, 3.0])
    assert out.w[0, 1] > 0.1  # the measurement is at the Gaussian's mean: a real detection term
    np.testing.assert_allclose(out.w, fixed.w, rtol=1e-12)
    np.testing.assert_allclose(out.m, fixed.m, rtol=1e-12)
    np.testing.assert_allclose(out.P, fixed.P, rtol=1e-12, atol=1e-15)
    assert fixed.pd_beta is None


def test_outside_the_fov_the_beta_and_weight_are_unchanged():
    """An SP beyond the range gate: p_D = 0, weight w, Beta (2, 3) kept; no detection slot has weight."""
    x = np.array([-30.0, 25.0, 3.0])  # ~56 m from the vehicle
    Z = measure(STATE, np.array([10.0, -18.0, 1.0]), Bounce.SCATTER, BS)[None]
    out = _correct(_one(x), SP, _pd_const(0.95, fov=20.0), Z)
    assert out.w[0, 0] == 0.5
    np.testing.assert_array_equal(out.pd_beta[0, 0], [2.0, 3.0])
    assert out.w[0, 1] == 0.0


def test_pooled_beta_of_a_merge_by_hand():
    """Two Gaussians at one point, w 1 and 3, Beta (2, 4) and (6, 2) -> w 4, Beta ((2 + 18) / 4,
    (4 + 6) / 4) = (5, 2.5), in prune_merge, average_map and merge_pairs alike."""
    m = np.zeros((1, 2, 3))
    P = np.broadcast_to(np.eye(3), (1, 2, 3, 3)).copy()
    g = GM(np.array([[1.0, 3.0]]), m, P, np.ones((1, 2), bool), np.array([[[2.0, 4.0], [6.0, 2.0]]]))
    r = prune_merge(g, 1e-4, 4.0, 10)
    assert r.count()[0] == 1 and r.w[0, 0] == pytest.approx(4.0)
    np.testing.assert_allclose(r.pd_beta[0, 0], [5.0, 2.5])
    a = average_map(g, np.ones(1), 0.1, 4.0, 10)
    np.testing.assert_allclose(a.pd_beta[0], [5.0, 2.5])
    p = merge_pairs(g.take(0), np.array([[0, 1]]))
    np.testing.assert_allclose(p.pd_beta[0], [5.0, 2.5])
    np.testing.assert_array_equal(p.pd_beta[1], [1.0, 1.0])  # the freed slot
    out = np.empty(2)
    beta_pool(np.zeros(2), np.array([[2.0, 4.0], [6.0, 2.0]]), np.array([0, 1]), out)
    np.testing.assert_allclose(out, [4.0, 3.0])  # zero weights: the plain average
    # a missed (s, t + 1) and a detected (s + 1, t) copy of one Gaussian pool to one step of evidence
    beta_pool(np.array([0.25, 0.75]), np.array([[2.0, 4.0], [3.0, 3.0]]), np.array([0, 1]), out)
    np.testing.assert_allclose(out, [2.75, 3.25])
    assert out.sum() == pytest.approx(2.0 + 3.0 + 1.0)


def test_distinct_gaussians_keep_their_own_beta_through_reduction_and_fusion():
    m = np.array([[[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 80.0, 0.0]]])
    P = np.broadcast_to(np.eye(3), (1, 3, 3, 3)).copy()
    ab = np.array([[[1.0, 9.0], [7.0, 1.0], [3.0, 3.0]]])
    g = GM(np.array([[0.9, 2.0, 0.5]]), m, P, np.ones((1, 3), bool), ab)
    r = prune_merge(g, 1e-4, 4.0, 10)  # sorted by weight: slots 1, 0, 2
    np.testing.assert_array_equal(r.pd_beta[0], ab[0][[1, 0, 2]])
    bs = r.take(0)
    ue = GM(np.array([1.0]), np.array([[0.0, 80.0, 0.0]]), np.eye(3)[None], np.ones(1, bool), np.array([[5.0, 1.0]]))
    fused, pairs = fusion.fuse_aa(bs, ue, np.zeros(3, bool), 20.0, with_pairs=True)
    by_pos = {tuple(np.round(fused.m[i])): fused.pd_beta[i] for i in range(fused.capacity)}
    np.testing.assert_array_equal(by_pos[(50.0, 0.0, 0.0)], [7.0, 1.0])
    np.testing.assert_array_equal(by_pos[(0.0, 0.0, 0.0)], [1.0, 9.0])
    assert len(pairs) == 1  # the (0, 80, 0) pair: both members present with their own Betas
    i, j = pairs[0]
    assert {tuple(fused.pd_beta[i]), tuple(fused.pd_beta[j])} == {(3.0, 3.0), (5.0, 1.0)}


def test_gm_operations_carry_beta_and_refuse_to_drop_it():
    g = _one([1.0, 2.0, 3.0])
    assert concat(empty((1,), 0, 3), g).pd_beta.shape == (1, 1, 2)  # an empty map takes it
    with pytest.raises(ValueError, match="Beta"):
        concat(_one([0.0, 0.0, 0.0], ab=None), g)
    np.testing.assert_array_equal(g.take((None,)).take(np.zeros(3, int)).pd_beta[:, 0, 0], [[2.0, 3.0]] * 3)


def test_prior_prediction_and_expected_pd():
    assert prior_beta(0.1, 2.0) == pytest.approx((0.2, 1.8))
    with pytest.raises(ValueError):
        prior_beta(1.0, 2.0)
    np.testing.assert_allclose(predict_beta(np.array([4.0, 6.0]), 0.5), [2.0, 3.0])
    np.testing.assert_allclose(expected_pd(np.array([0.9, 0.0]), np.array([[1.0, 3.0], [1.0, 3.0]])), [0.25, 0.0])


@pytest.fixture(scope="module")
def paper6():
    scn = load_preset("paper")
    states = true_trajectories(scn)[:6]
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(6)]
    return scn, states, {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


def test_a_beta_of_huge_count_is_the_fixed_model(paper6):
    """A Beta with s + t = 1e9 barely moves: E[p_D] stays p_detect_<type> to 1e-8, so a whole cooperative
    run (births, corrections, merges, averaged maps, fusion, downlink) equals the fixed model's."""
    scn, states, paths = paper6
    a = run_filter(scn, states, paths, variant="proposed", particles=20, seed=3)
    b = run_filter(with_overrides(scn, ["filter.pd_model=beta", "filter.pd_beta_count=1e9"]), states, paths,
                   variant="proposed", particles=20, seed=3)
    c = run_filter(with_overrides(scn, ["filter.pd_model=beta"]), states, paths, variant="proposed",
                   particles=20, seed=3)
    np.testing.assert_allclose(a.vehicles["x"], b.vehicles["x"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a.metrics["gospa"], b.metrics["gospa"], rtol=1e-6, atol=1e-6)
    assert not np.allclose(a.metrics["gospa"], c.metrics["gospa"])  # a learnt p_D changes the maps


def test_a_beta_prior_of_mean_one_is_a_one_line_config_error():
    from mmslam.errors import ConfigError

    with pytest.raises(ConfigError, match="filter.types.SP.p_detect.*0 < p_detect < 1"):
        with_overrides(load_preset("paper"), ["filter.pd_model=beta", "filter.p_detect_sp=1.0"])
    with_overrides(load_preset("paper"), ["filter.pd_model=fixed", "filter.p_detect_sp=1.0"])  # fine when fixed
