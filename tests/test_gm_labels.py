"""Identity labels per Gaussian (``GM.label``, ``fusion.average_by_label``).

A birth's label is the same in every particle, a corrected component inherits its predicted slot's,
a merged one its cluster leader's (the largest weight), fusion and the downlink carry them, and the
averaged map (eq. (7)) pools the particles' copies of one label before the gated merge. With the
option off nothing changes.
"""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.model import VA, VS
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.fusion import operators as fusion
from mmslam.slam.core.gm import GM, NO_LABEL, compact, concat, drop_dead_slots, ego_label, empty, with_labels
from mmslam.slam.phd.gmphd import correct, corrected_gm, type_terms
from mmslam.slam.filter.local_filter import LABEL_BITS, LocalFilter
from mmslam.slam.models.measurement import measure
from mmslam.slam.phd.reduction import average_map, merge_pairs, prune_merge
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import landmark_type

KINDS = {t.code: t for t in (landmark_type("VA"), landmark_type("SP"), landmark_type("VS"))}
"""Type code -> spec: what gmphd.correct is handed about each map's type."""

BS = np.array([0.0, 0.0, 10.0])
STATE = np.array([5.0, -20.0, 1.5, 0.3, 10.0, 0.0, 2.0])
R = np.diag([0.1, 1e-4, 1e-4, 1e-4, 1e-4])
LOG_CLUTTER = np.log(1e-3)


def _gm(w, m, var=0.01, label=None) -> GM:
    """A batch of 3-D mixtures: ``w (*B, Q)``, ``m (*B, Q, 3)``, covariances ``var I``."""
    w = np.asarray(w, float)
    m = np.asarray(m, float)
    P = np.broadcast_to(var * np.eye(3), m.shape + (3,)).copy()
    return GM(w, m, P, np.ones(w.shape, bool), label=None if label is None else np.asarray(label, np.int64))


def _pd(p):
    return lambda u, x, t: np.full(np.shape(x)[:-1], p)


# ------------------------------------------------------------------ the GM operations
def test_gm_operations_carry_labels():
    g = _gm([[1.0, 0.5, 2.0]], [[[0, 0, 0], [1, 0, 0], [2, 0, 0]]], label=[[4, 5, 6]])
    g.mask[0, 1] = False
    np.testing.assert_array_equal(compact(g).label, [[6, 4]])  # by weight; the masked slot is gone
    np.testing.assert_array_equal(compact(g, 4).label, [[6, 4, NO_LABEL, NO_LABEL]])  # padding: no label
    np.testing.assert_array_equal(g.take(np.array([0, 0])).label, [[4, 5, 6]] * 2)  # resampling's _take
    np.testing.assert_array_equal(g.copy().label, g.label)
    assert g.copy().label is not g.label
    dead = _gm([[1.0, 0.0], [1.0, 0.0]], np.zeros((2, 2, 3)), label=[[1, 2], [1, 3]])
    dead.mask[:, 1] = False
    np.testing.assert_array_equal(drop_dead_slots(dead).label, [[1], [1]])
    e = empty((2,), 0, 3)
    np.testing.assert_array_equal(concat(e, dead).label, dead.label)  # an empty map takes the labels
    assert empty((2,), 3, 3, with_label=True).label.tolist() == [[NO_LABEL] * 3] * 2
    with pytest.raises(ValueError, match="component labels and one without"):
        concat(_gm([[1.0]], [[[0, 0, 0]]]), _gm([[1.0]], [[[0, 0, 0]]], label=[[1]]))


def test_births_get_one_label_per_column_in_every_particle():
    b = _gm([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]], np.zeros((2, 3, 3)))
    b.mask[1, 2] = False  # no birth of z_2 in particle 1
    out, nxt = with_labels(b, 100)
    np.testing.assert_array_equal(out.label, [[100, 101, 102], [100, 101, NO_LABEL]])
    assert nxt == 103


# ------------------------------------------------------------------ correction
def test_corrected_components_inherit_their_predicted_slots_label():
    """Dense layout: missed slots q = 0, 1, then (q, j) at Q + q J + j; every one takes slot q's label.
    With pruning (compacted) each kept component still has the label of the slot it came from."""
    x0, x1 = np.array([-30.0, 25.0, 3.0]), np.array([40.0, 35.0, 6.0])
    g = _gm([[0.8, 0.6]], [[x0, x1]], var=0.25, label=[[7, 9]])
    Z = np.stack([measure(STATE, x0, Bounce.MIRROR, BS), measure(STATE, x1, Bounce.MIRROR, BS)])
    tc = type_terms(g, landmark_type(VA), STATE[None], Z, R, BS, _pd(0.9))
    tc.g.label = g.label
    lpsi = np.zeros((1, 2))
    dense = corrected_gm(tc, Z, lpsi)
    np.testing.assert_array_equal(dense.label, [[7, 9, 7, 7, 9, 9]])
    maps, _, _ = correct({VA: g}, STATE[None], Z, R, BS, _pd(0.9), np.zeros(1), LOG_CLUTTER, 1e-3, {}, 0, KINDS)
    c = maps[VA]
    live = c.mask[0]
    near0 = np.linalg.norm(c.m[0, :, :3] - x0, axis=-1) < np.linalg.norm(c.m[0, :, :3] - x1, axis=-1)
    assert live.sum() >= 3
    np.testing.assert_array_equal(c.label[0, live], np.where(near0[live], 7, 9))
    np.testing.assert_array_equal(c.label[0, ~live], NO_LABEL)
    unlabelled, _, _ = correct({VA: GM(g.w, g.m, g.P, g.mask)}, STATE[None], Z, R, BS, _pd(0.9), np.zeros(1),
                            LOG_CLUTTER, 1e-3, {}, 0, KINDS)
    assert unlabelled[VA].label is None
    np.testing.assert_array_equal(unlabelled[VA].w, c.w)


def test_a_label_array_of_the_wrong_shape_is_refused_before_the_kernel():
    g = _gm([[0.8, 0.6]], [[[-30.0, 25.0, 3.0], [40.0, 35.0, 6.0]]], label=[[7, 9]])
    Z = measure(STATE, g.m[0, 0], Bounce.MIRROR, BS)[None]
    tc = type_terms(g, landmark_type(VA), STATE[None], Z, R, BS, _pd(0.9))
    tc.g.label = np.array([[7]])
    with pytest.raises(ValueError, match=r"label has shape \(1, 1\); expected the map's \(1, 2\)"):
        corrected_gm(tc, Z, np.zeros((1, 1)))
    with pytest.raises(ValueError, match=r"GM.label has shape \(1, 1\)"):
        prune_merge(GM(g.w, g.m, g.P, g.mask, label=np.array([[7]])), 0.1, 4.0, 10)


# ------------------------------------------------------------------ merging
def test_a_merged_component_takes_its_cluster_leaders_label():
    """Slots 0 and 1 are 0.05 m apart (merged at gate 4 with variance 0.01: squared distance 0.25);
    the heavier (slot 1, w 3) leads in particle 0, slot 0 in particle 1; slot 2 is 10 m away."""
    m = [[[0, 0, 0], [0.05, 0, 0], [10, 0, 0]]] * 2
    g = _gm([[1.0, 3.0, 0.5], [3.0, 1.0, 0.5]], m, label=[[3, 5, 8], [3, 5, 8]])
    r = prune_merge(g, 0.1, 4.0, 10)
    np.testing.assert_allclose(r.w, [[4.0, 0.5], [4.0, 0.5]])
    np.testing.assert_array_equal(r.label, [[5, 8], [3, 8]])
    assert prune_merge(GM(g.w, g.m, g.P, g.mask), 0.1, 4.0, 10).label is None


def test_merge_pairs_keeps_the_heavier_label():
    g = _gm([1.0, 3.0, 2.0], [[0, 0, 0], [0.1, 0, 0], [5, 0, 0]], label=[11, 12, 13])
    r = merge_pairs(g, np.array([[0, 1]]))
    assert r.label.tolist() == [12, NO_LABEL, 13]
    assert r.w[0] == pytest.approx(4.0)


# ------------------------------------------------------------------ fusion and downlink
def test_fusion_and_ego_average_carry_labels():
    bs = _gm([0.8, 0.9], [[0, 0, 0], [30, 0, 0]], label=[1, 2])
    ue = _gm([0.7, 0.6], [[0.01, 0, 0], [60, 0, 0]], label=[(3 << LABEL_BITS) + 1, (3 << LABEL_BITS) + 2])
    u, pairs = fusion.fuse_aa(bs, ue, np.array([True, False]), 20.0, with_pairs=True)
    by_pos = {round(float(x), 2): int(lab) for x, lab in zip(u.m[:, 0], u.label)}
    assert by_pos == {0.0: 1, 0.01: (3 << LABEL_BITS) + 1, 30.0: 2, 60.0: (3 << LABEL_BITS) + 2}
    fused = prune_merge(u, 0.1, 4.0, 10)
    assert int(fused.label[np.argmin(np.abs(fused.m[:, 0]))]) == 1  # 0.4 (BS, leader) + 0.35 (upload)
    vs = GM(np.array([0.9]), np.zeros((1, 7)) + [[20, 0, 0, 1, 0, 0, 0]], np.eye(7)[None], np.ones(1, bool),
            None, np.array([42]))
    out = fusion.ego_vs_average(vs, np.zeros(7), np.eye(7), 20.0)
    assert sorted(out.label.tolist()) == [NO_LABEL, 42]  # the ego Gaussian has no particle copies to pool


def _filter(particles=3, on=True):
    scn = with_overrides(load_preset("paper"), [f"fusion.average_by_label={'true' if on else 'false'}"])
    return LocalFilter(scn, "cm1", particles, np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]), R, 1e-3, _pd(0.5),
                       np.random.default_rng(0), vehicle=2)


def test_downlink_and_resampling_give_every_particle_the_labels():
    f = _filter()
    fused = _gm([0.9, 0.8], [[50, 60, 10], [-40, 20, 10]], label=[17, 23])
    f.downlink({VA: fused})
    np.testing.assert_array_equal(f.maps[VA].label, [[17, 23]] * 3)
    f.maps[VA].label[1] = [31, 37]  # particle 1's own labels
    f.resample(np.array([0.0, 1.0, 0.0]))  # ESS 1 < resample_ess P: every particle becomes particle 1
    np.testing.assert_array_equal(f.maps[VA].label, [[31, 37]] * 3)


def test_local_filter_births_are_labelled_per_vehicle_and_only_with_the_option():
    x = np.array([-30.0, 25.0, 3.0])
    for on in (True, False):
        f = _filter(on=on)
        f.step(measure(f.s[0], x, Bounce.MIRROR, BS)[None])
        f.predict(10.0, 0.0)  # the births of the first step's measurement (weight birth_weight, 1.5e-5)
        g = f.maps[VA]
        if not on:
            assert g.label is None and f.maps[VS].label is None
            continue
        live = g.label[g.mask]
        assert live.size and (live >> LABEL_BITS == 2).all()  # vehicle 2's labels
        assert len(set(live.tolist())) == 1  # one birth column: one label in every particle


# ------------------------------------------------------------------ the averaged map, eq. (7)
def _two_particles(labels):
    """Two particles, each one thin Gaussian (variance 0.01 m^2), at x = 0 and x = 0.5 m."""
    return _gm([[1.0], [1.0]], [[[0.0, 0, 0]], [[0.5, 0, 0]]], label=labels)


def test_average_map_pools_the_copies_of_one_label_that_the_gate_splits():
    """Squared distance 0.25 / 0.01 = 25 > gate 4: without pooling two components of weights 0.75 and
    0.25. Pooled (particle weights 0.75, 0.25): W = 1, mean x = 0.25 * 0.5 = 0.125, variance along x
    0.01 + 0.75 * 0.125^2 + 0.25 * 0.375^2 = 0.056875, across 0.01."""
    pw = np.array([3.0, 1.0])
    g = _two_particles([[5], [5]])
    plain = average_map(g, pw, 0.1, 4.0, 10)
    np.testing.assert_allclose(plain.w, [0.75, 0.25])
    np.testing.assert_array_equal(plain.label, [5, 5])
    pooled = average_map(g, pw, 0.1, 4.0, 10, by_label=True)
    assert pooled.count() == 1
    assert pooled.w[0] == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(pooled.m[0], [0.125, 0.0, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(pooled.P[0], np.diag([0.056875, 0.01, 0.01]), rtol=1e-12, atol=1e-18)
    assert pooled.label[0] == 5
    apart = average_map(_two_particles([[5], [6]]), pw, 0.1, 4.0, 10, by_label=True)  # two labels: as before
    np.testing.assert_allclose(apart.w, plain.w, rtol=1e-12)
    np.testing.assert_allclose(apart.m, plain.m, rtol=1e-12)
    np.testing.assert_array_equal(apart.label, [5, 6])


def test_average_map_pools_one_copy_per_particle_the_heaviest():
    """Particle 0 holds two Gaussians of label 5 (x = 0, w 0.9; x = 3, w 0.4: slot 5 corrected by another
    landmark's measurement): only the heavier is its copy; the other stays apart. Unlabelled components
    (NO_LABEL) are never pooled."""
    g = _gm([[0.9, 0.4], [0.9, 0.0]], [[[0.0, 0, 0], [3.0, 0, 0]], [[0.5, 0, 0], [0, 0, 0]]],
            label=[[5, 5], [5, NO_LABEL]])
    g.mask[1, 1] = False
    r = average_map(g, np.array([0.5, 0.5]), 0.1, 4.0, 10, by_label=True)
    np.testing.assert_allclose(r.w, [0.9, 0.2])
    np.testing.assert_allclose(r.m[:, 0], [0.25, 3.0])
    np.testing.assert_array_equal(r.label, [5, NO_LABEL])
    u = _two_particles([[NO_LABEL], [NO_LABEL]])
    np.testing.assert_allclose(average_map(u, np.ones(2), 0.1, 4.0, 10, by_label=True).w, [0.5, 0.5])


def test_average_map_pooling_prunes_each_copy_first():
    """A copy below average_prune (0.05 in particle 1) is dropped before the pooling, as without labels."""
    g = _gm([[1.0], [0.05]], [[[0.0, 0, 0]], [[0.5, 0, 0]]], label=[[5], [5]])
    r = average_map(g, np.ones(2), 0.1, 4.0, 10, by_label=True)
    np.testing.assert_allclose(r.w, [0.5])
    np.testing.assert_allclose(r.m[0], [0.0, 0, 0])


def test_average_map_without_pooling_equals_the_unlabelled_result():
    rng = np.random.default_rng(4)
    P_, Q = 6, 8
    m = rng.normal(scale=2.0, size=(P_, Q, 3))
    g = _gm(rng.uniform(0.05, 1.0, (P_, Q)), m, var=0.3, label=rng.integers(0, 4, (P_, Q)))
    pw = rng.uniform(0.1, 1.0, P_)
    a = average_map(g, pw, 0.1, 4.0, 10)
    b = average_map(GM(g.w, g.m, g.P, g.mask), pw, 0.1, 4.0, 10)
    for x, y in ((a.w, b.w), (a.m, b.m), (a.P, b.P), (a.mask, b.mask)):
        np.testing.assert_array_equal(x, y)
    assert b.label is None and a.label.shape == a.w.shape
    with pytest.raises(ValueError, match="needs component labels"):
        average_map(GM(g.w, g.m, g.P, g.mask), pw, 0.1, 4.0, 10, by_label=True)


def test_a_cooperative_run_with_labels_keeps_them_in_every_map():
    """paper, 8 analytic steps, proposed: every local and fused map of every type carries labels from the
    first birth on (the VS map's ego Gaussians: NO_LABEL), and live labels are those of some vehicle."""
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.scenes.trajectory import true_trajectories
    from mmslam.slam.filter.run import CooperativeRun

    scn = with_overrides(load_preset("paper"), ["fusion.average_by_label=true"])
    states = true_trajectories(scn)[:8]
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(8)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    run = CooperativeRun(scn, states, paths, "proposed", 10, 3)
    for k in range(8):
        run.step(k)
    maps = [g for f in run.filters for g in f.maps.values()] + list(run.center.maps.values())
    assert all(g.label is not None and g.label.shape == g.w.shape for g in maps)
    live = np.concatenate([g.label[g.mask] for g in maps])
    assert live.size and np.isin(live[live >= 0] >> LABEL_BITS, np.arange(len(scn.vehicles))).all()
    vs = run.center.maps[VS].label[run.center.maps[VS].mask]
    assert np.isin([ego_label(n) for n in range(len(scn.vehicles))], vs).any()  # an uploaded ego Gaussian


def test_average_map_pooling_survives_a_particle_of_subnormal_weight():
    """Particle 1's normalised weight is subnormal (its log-weight ~745 below the best one's): w_p eta
    is 0 for eta = 0.3 (5e-324 * 0.3 rounds to 0) and keeps a few bits for 1e-320. Particle 1's
    Gaussians (its own labels, a thin correlated covariance) carry no measurable mass: the result is
    the unlabelled one, particle 0's Gaussian alone (the pooling once moment-matched w_i P_i / W in
    subnormal arithmetic: a zero or indefinite covariance, FloatingPointError in the gated merge)."""
    C = np.array([[1.0, 0.999, 0.0], [0.999, 1.0, 0.0], [0.0, 0.0, 1e-6]])
    P = np.stack([np.broadcast_to(0.01 * np.eye(3), (1, 3, 3)), C[None]])
    g = GM(np.array([[0.9], [0.3]]), np.array([[[0.0, 0, 0]], [[5.0, 0, 0]]]), P, np.ones((2, 1), bool),
           label=np.array([[1], [2]]))
    for p1 in (5e-324, 1e-320):
        pw = np.array([1.0, p1])
        plain = average_map(g, pw, 0.1, 4.0, 10)
        pooled = average_map(g, pw, 0.1, 4.0, 10, by_label=True)
        assert pooled.count() == plain.count() == 1
        np.testing.assert_allclose(pooled.w[pooled.mask], [0.9], rtol=1e-15)
        np.testing.assert_allclose(pooled.m[pooled.mask], plain.m[plain.mask], rtol=0, atol=1e-15)
        np.testing.assert_allclose(pooled.P[pooled.mask], plain.P[plain.mask], rtol=1e-15, atol=0)
        assert pooled.label[pooled.mask].tolist() == [1]


def test_type_terms_carries_the_labels_to_corrected_gm():
    """corrected_gm(type_terms(g, ...)) of a labelled map has the labels without a caller putting them
    on the contiguous copy (type_terms once dropped them: label None); a label array of another shape
    is refused by type_terms with the other shapes."""
    x0, x1 = np.array([-30.0, 25.0, 3.0]), np.array([40.0, 35.0, 6.0])
    g = _gm([[0.8, 0.6]], [[x0, x1]], var=0.25, label=[[7, 9]])
    Z = np.stack([measure(STATE, x0, Bounce.MIRROR, BS), measure(STATE, x1, Bounce.MIRROR, BS)])
    tc = type_terms(g, landmark_type(VA), STATE[None], Z, R, BS, _pd(0.9))
    np.testing.assert_array_equal(corrected_gm(tc, Z, np.zeros((1, 2))).label, [[7, 9, 7, 7, 9, 9]])
    with pytest.raises(ValueError, match=r"VA correction: shapes .* label \(1, 1\); expected .*None or \(P, Q\)"):
        type_terms(GM(g.w, g.m, g.P, g.mask, label=np.array([[7]])), landmark_type(VA), STATE[None], Z, R, BS, _pd(0.9))


def test_a_vehicle_index_outside_the_label_range_is_refused():
    """vehicle = -1 once labelled its births from -2^40 (negative: treated as NO_LABEL, never pooled,
    silently); 2^23 overflows int64. Both: a one-line error naming the index."""
    from mmslam.errors import MmslamError

    scn = with_overrides(load_preset("paper"), ["fusion.average_by_label=true"])
    for bad in (-1, 1 << 23):
        with pytest.raises(MmslamError, match=rf"vehicle={bad}: expected a vehicle index in \[0, 8388608\)"):
            LocalFilter(scn, "cm1", 2, np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]), R, 1e-3, _pd(0.5),
                        np.random.default_rng(0), vehicle=bad)
    assert LocalFilter(scn, "cm1", 2, np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]), R, 1e-3, _pd(0.5),
                       np.random.default_rng(0), vehicle=(1 << 23) - 1)._next_label == ((1 << 23) - 1) << LABEL_BITS


def test_average_map_pooling_ignores_a_particle_of_weight_zero_and_works_for_one_particle():
    """Particle 1 (weight 0) holds a copy of label 5 at x = 40: it is no copy (its eta is NaN to the
    prune rule), the result is particle 0's Gaussian. P = 1: the map itself, reduced."""
    g = _gm([[0.6], [1.0]], [[[1.0, 2, 3]], [[40.0, 0, 0]]], label=[[5], [5]])
    r = average_map(g, np.array([2.0, 0.0]), 0.1, 4.0, 10, by_label=True)
    np.testing.assert_allclose(r.w[r.mask], [0.6], rtol=1e-15)
    np.testing.assert_allclose(r.m[r.mask], [[1.0, 2, 3]], rtol=1e-15)
    np.testing.assert_allclose(r.P[r.mask], [0.01 * np.eye(3)], rtol=1e-15)
    assert r.label[r.mask].tolist() == [5]
    one = average_map(g.take(np.array([0])), np.ones(1), 0.1, 4.0, 10, by_label=True)
    np.testing.assert_allclose(one.w[one.mask], [0.6], rtol=1e-15)
    assert one.label[one.mask].tolist() == [5]


def test_an_ego_gaussian_keeps_its_vehicles_label_into_the_other_vehicles_averaged_maps():
    """paper, proposed, P = 6, 12 analytic steps: the ego Gaussian that F'_AA (eq. 11) appends to a
    vehicle's upload carries ego_label(vehicle) (the last label of its range), so the other vehicle's
    particles, which hold it after the downlink, pool their copies of it in eq. (7): one Gaussian of
    that label in its averaged VS map. It once had NO_LABEL: after the first downlink the receiving
    vehicle's VS map was unlabelled (copies never pooled)."""
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.scenes.trajectory import true_trajectories
    from mmslam.slam.filter.run import CooperativeRun

    assert ego_label(0) == (1 << LABEL_BITS) - 1 and ego_label(3) == (4 << LABEL_BITS) - 1
    vs = GM(np.array([0.9]), np.zeros((1, 7)) + [[20, 0, 0, 1, 0, 0, 0]], np.eye(7)[None], np.ones(1, bool),
            None, np.array([42]))
    out = fusion.ego_vs_average(vs, np.zeros(7), np.eye(7), 20.0, ego_label(2))
    assert sorted(out.label.tolist()) == [42, ego_label(2)]
    scn = with_overrides(load_preset("paper"), ["fusion.average_by_label=true"])
    K = 12
    states = true_trajectories(scn)[:K]
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(K)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    run = CooperativeRun(scn, states, paths, "proposed", 6, 3)
    seen = 0
    for k in range(K):
        run.step(k)
        for n, f in enumerate(run.filters):
            g = f.maps[VS]
            others = [ego_label(m) for m in range(len(scn.vehicles)) if m != n]
            held = np.isin(g.label, others) & g.mask
            if not held.any():
                continue
            seen += 1
            assert (g.label[g.mask] != NO_LABEL).all()  # no unlabelled Gaussian in a VS map
            lab = g.label[held][0]
            avg = f.estimate(np.full(f.P, 1.0 / f.P))[2][VS]
            assert (avg.label[avg.mask] == lab).sum() <= 1  # its copies pooled (at most one per label)
    assert seen  # some vehicle received another's ego Gaussian


def test_compact_refuses_a_label_array_of_another_shape():
    """A (P, 1) label once broadcast silently over every slot of a compacted (P, Q) map (its fast path's
    np.where): every Gaussian of a particle got one label. Now a ValueError naming both shapes."""
    g = _gm([[1.0, 0.5, 0.2]] * 2, np.zeros((2, 3, 3)), label=[[7], [8]])
    with pytest.raises(ValueError, match=r"GM.label has shape \(2, 1\); expected the weights' \(2, 3\)"):
        compact(g)


def test_fused_others_scores_the_vs_map_without_the_ego_uploads():
    """MapScorer.record_others: the fused VS map's Gaussians labelled ego_label(n) (each car's own upload,
    eq. 11) are left out, the rest scored against the cars some other car can see (within fov_range).
    Cars 0 and 1 are 10 m apart, car 2 is 500 m away: truth {car 0, car 1}; estimates: car 1 found by a
    measurement (label 7) and the three ego Gaussians; only car 1 is an estimate, car 0 is missed."""
    from mmslam.slam.eval.evaluation import MapScorer
    from mmslam.slam.core.gm import GM, ego_label
    from mmslam.slam.specs.landmarks import VS_SPEC

    scn = load_preset("paper")
    true = np.zeros((1, 3, 7))
    true[0, :, 0] = [0.0, 10.0, 500.0]
    e = np.zeros(0)
    paths = {"step": e.astype(int), "rx": e.astype(int), "type": e.astype(int), "landmark_id": e.astype(str),
             "lm_x": e, "lm_y": e, "lm_z": e}
    sc = MapScorer(scn, paths, true, ["a", "b", "c"])
    m = np.zeros((4, 7))
    m[:, 0] = [10.0, 0.0, 10.0, 500.0]
    lab = np.array([7, ego_label(0), ego_label(1), ego_label(2)], np.int64)
    g = GM(np.ones(4), m, np.broadcast_to(np.eye(7), (4, 7, 7)).copy(), np.ones(4, bool), None, lab)
    sc.record_others(0, {VS_SPEC.code: g})
    mt = sc.metrics.cols
    assert mt["map"] == ["fused_others"] and mt["type"] == ["VS"]
    assert mt["n_est"] == [1] and mt["n_true"] == [2]
    c = scn.evaluation.gospa_c
    assert mt["missed"][0] == pytest.approx(c ** 2 / 2) and mt["loc"][0] == pytest.approx(0.0)
    sc.record_others(0, {VS_SPEC.code: GM(g.w, g.m, g.P, g.mask)})  # no labels: nothing recorded
    assert len(sc.metrics.cols["map"]) == 1


def test_downlink_keeps_the_tentative_gaussians_only_with_the_option():
    """filter.types.VA.keep_tentative: after a downlink each particle holds the fused map and, after it, its own VA
    Gaussians lighter than fusion.average_prune (0.1), with their labels; the confirmed ones (here 0.8) are replaced by
    the fused map as in the paper. Without the option (the default) only the fused map is left."""
    for keep in (False, True):
        scn = with_overrides(load_preset("paper"), [f"filter.types.VA.keep_tentative={'true' if keep else 'false'}"])
        f = LocalFilter(scn, "cm1", 3, np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]), R, 1e-3, _pd(0.5),
                        np.random.default_rng(0), vehicle=2)
        own = _gm([0.8, 0.05, 0.02], [[0, 0, 10], [30, 0, 10], [60, 0, 10]], label=[5, 6, 7])
        f.maps[VA] = own.take((None,)).take(np.zeros(3, int))
        f.maps[VA].w[1, 2] = 0.5  # particle 1's third Gaussian is not tentative: the fused map replaces it
        f.downlink({VA: _gm([0.9], [[1.0, 0, 10]], label=[17])})
        g = f.maps[VA]
        live = [sorted(zip(g.w[p][g.mask[p]].round(3).tolist(), g.label[p][g.mask[p]].tolist())) for p in range(3)]
        if not keep:
            assert live == [[(0.9, 17)]] * 3
        else:
            assert live == [[(0.02, 7), (0.05, 6), (0.9, 17)], [(0.05, 6), (0.9, 17)], [(0.02, 7), (0.05, 6), (0.9, 17)]]


def test_downlink_keeps_a_tentative_gaussians_own_beta_and_gives_the_fused_ones_the_prior():
    """With learnt p_D (filter.pd_model = beta, pd_beta_downlink = prior, the city defaults): the kept tentative
    Gaussian carries its own Beta (s, t) through the downlink, the fused Gaussian gets the type's birth prior, and a
    particle with no tentative Gaussian (P = 1 here too: the batch of one) holds the fused map alone."""
    scn = with_overrides(load_preset("paper"), ["filter.types.VA.keep_tentative=true", "filter.pd_model=beta",
                                                "filter.pd_beta_downlink=prior"])
    prior = landmark_type("VA").pd_beta_prior(scn)
    for P in (1, 2):
        f = LocalFilter(scn, "cm1", P, np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]), R, 1e-3, _pd(0.5),
                        np.random.default_rng(0), vehicle=2)
        own = _gm([[0.05]] * P, [[[30, 0, 10]]] * P, label=[[6]] * P)
        own.pd_beta = np.array([[[3.0, 1.0]]] * P)
        if P == 2:
            own.w[1, 0] = 0.5  # particle 1's Gaussian is confirmed: not kept
        f.maps[VA] = own
        fused = _gm([0.9], [[1.0, 0, 10]], label=[17])
        fused.pd_beta = np.array([[7.0, 2.0]])
        f.downlink({VA: fused})
        g = f.maps[VA]
        for p in range(P):
            rows = sorted((round(float(w), 3), tuple(b)) for w, b, k in zip(g.w[p], g.pd_beta[p], g.mask[p]) if k)
            want = [(0.05, (3.0, 1.0)), (0.9, tuple(prior))] if p == 0 else [(0.9, tuple(prior))]
            assert rows == want
