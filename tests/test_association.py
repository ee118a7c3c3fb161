"""Exclusive measurement association of a landmark type (``filter.types.<T>.association``, docs/city-slam.md)."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from mmslam.errors import ConfigError
from mmslam.model import VA
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.core.gm import GM
from mmslam.slam.phd.association import exclusive_association, exclusive_terms


def brute_force(L: np.ndarray, l0: np.ndarray) -> np.ndarray:
    """Exact marginals ``P(i <-> j)`` of one ``(Q, J)`` problem by enumerating every one-to-one association:
    weight prod_i (L_ij if i takes j else l_i0) (an unused measurement: factor 1, clutter)."""
    Q, J = L.shape
    num, tot = np.zeros((Q, J)), 0.0
    for a in itertools.product(range(-1, J), repeat=Q):  # a[i] = measurement of Gaussian i, -1 none
        used = [j for j in a if j >= 0]
        if len(used) != len(set(used)):
            continue
        wgt = np.prod([L[i, j] if j >= 0 else l0[i] for i, j in enumerate(a)])
        tot += wgt
        for i, j in enumerate(a):
            if j >= 0:
                num[i, j] += wgt
    return num / tot


def test_bp_is_exact_on_trees_and_close_on_small_loopy_problems():
    rng = np.random.default_rng(3)
    for shape in ((1, 4), (4, 1)):  # one Gaussian or one measurement: a tree, BP is exact
        L, l0 = rng.exponential(3.0, shape), rng.uniform(0.2, 1.0, shape[0])
        got, D = exclusive_association(L[None], l0[None])
        np.testing.assert_allclose(got[0], brute_force(L, l0), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(l0 / D[0] + got[0].sum(axis=1), 1.0, rtol=1e-12)  # none + some = 1
    worst, errs = 0.0, []
    for _ in range(20):  # 3 x 3, loopy: Williams & Lau's approximation
        L, l0 = rng.exponential(2.0, (3, 3)) * (rng.uniform(size=(3, 3)) < 0.7), rng.uniform(0.2, 1.0, 3)
        got, _ = exclusive_association(L[None], l0[None])
        err = np.abs(got[0] - brute_force(L, l0))
        worst, errs = max(worst, float(err.max())), errs + [float(err.mean())]
        assert np.all(got[0].sum(axis=0) <= 1.0 + 1e-12) and np.all(got[0].sum(axis=1) <= 1.0 + 1e-12)
    assert worst < 0.1 and np.mean(errs) < 0.02, (worst, np.mean(errs))  # dense, ambiguous 3 x 3 problems


def test_a_measurement_taken_by_a_better_fit_goes_to_its_own_gaussian():
    """Two measurements, one Gaussian that fits the first far better: exclusively it takes that one, and a weak
    second Gaussian fitting the second takes it; the PHD gives the second measurement to the strong one."""
    # psi = 1: Gaussian 0 explains z1 alone and 90% of z2; the weak one 9.99%; the clutter 1e-6 and 1e-4
    with np.errstate(divide="ignore"):
        logq = np.log(np.array([[[1.0 - 1e-6, 0.9], [0.0, 0.0999]]]))
    w, p = np.array([[1.0, 1e-3]]), np.array([[0.5, 0.5]])
    det, miss = exclusive_terms(w, p, logq, np.log(np.array([[1e-6, 1e-4]])), np.zeros((1, 2)), "bernoulli")
    assert det[0, 0, 0] > 0.95 and det[0, 0, 1] < 0.1  # the strong Gaussian keeps the measurement it fits
    assert det[0, 1, 1] > 0.5  # the weak one takes the other: a second landmark
    assert det[0, 0].sum() + miss[0, 0] == pytest.approx(1.0, rel=1e-12)  # a confirmed one keeps its mass


def test_canyon_like_pair_in_the_correction():
    """An existing VA Gaussian and a fresh birth 1.5 m across it, each with its own measurement in one scan: under
    the PHD the existing one takes both and the birth stays negligible; under exclusive association the birth
    takes its measurement (a second landmark); the confirmed one keeps its mass, the PHD-mass bound holds."""
    from mmslam.slam.filter.local_filter import LocalFilter  # noqa: F401  (registry import order)
    from mmslam.slam.models.measurement import measure
    from mmslam.slam.phd.gmphd import correct
    from mmslam.slam.specs.landmarks import VA_SPEC

    scn = load_preset("paper")
    bs = np.asarray(scn.bs, float)
    s = np.array([[0.0, 0.0, 1.5, 0.0, 10.0, 0.0, 0.0]])
    va1, va2 = np.array([60.0, 30.0, 10.0]), np.array([60.0, 31.5, 10.0])
    Z = np.stack([measure(s[0], v, int(VA_SPEC.geometry), bs) for v in (va1, va2)])
    g = GM(np.array([[1.0, 1.5e-5]]), np.stack([va1, va2])[None], np.stack([np.eye(3) * 0.25, np.eye(3)])[None],
           np.ones((1, 2), bool))
    pd_fn = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.5)  # noqa: E731
    R = np.diag([0.1, 0.01, 0.01, 0.01, 0.01]) ** 2
    out = {}
    for assoc in ("phd", "exclusive"):
        res, _, _ = correct({VA: g.copy()}, s, Z, R, bs, pd_fn, np.zeros(1), np.log(1e-6), None, {VA: None}, 0,
                         {VA: VA_SPEC}, missed={VA: "bernoulli"}, association={VA: assoc})
        out[assoc] = res[VA]
    # dense layout: Q missed slots, then (q, j) at Q + q J + j
    birth_z2 = {a: float(o.w[0, 2 + 1 * 2 + 1]) for a, o in out.items()}
    assert birth_z2["phd"] < 0.1 and birth_z2["exclusive"] > 0.5
    ex = out["exclusive"].w[0]
    assert ex[0] + ex[2] + ex[3] == pytest.approx(1.0, rel=1e-9)  # the confirmed VA: missed + z1 + z2 = 1
    assert ex[2] > 0.9  # and it keeps z1


def test_defaults_and_presets():
    va = load_preset("canyon").filter.type_params("VA")
    assert va.association == "exclusive" and va.merge == 6.0 and va.tail_weight == 0.2  # the city defaults
    for name in ("paper", "twc2020"):  # published configurations keep the PHD's update and gate
        tp = load_preset(name).filter.type_params("VA")
        assert tp.association == "phd" and tp.merge == 49.0 and tp.tail_weight == 0.0
    for t in ("SP", "VS"):
        assert load_preset("munich").filter.type_params(t).association == "phd"
    with pytest.raises(ConfigError, match=r"filter\.types\.VA\.association.*phd.*exclusive"):
        with_overrides(load_preset("canyon"), ['filter.types.VA.association="jpda"'])


def test_bp_stays_exact_over_a_huge_dynamic_range():
    """Likelihood ratios from 1e-3 to 1e20 (a clutter-free street): the leave-one-out sums are built without
    cancellation, so the marginals match the enumeration (G0 takes z1 and G1 takes z0: 1e36 against 1e17)."""
    L, l0 = np.array([[1e20, 1e18], [1e18, 1e-3]]), np.array([1.0, 1.0])
    got, _ = exclusive_association(L[None], l0[None])
    np.testing.assert_allclose(got[0], brute_force(L, l0), atol=1e-6)
    assert got[0, 0, 1] > 0.999 and got[0, 1, 0] > 0.999


def test_extremes_stay_finite_and_a_sure_unseen_landmark_keeps_its_mass():
    """p_D = 1 and no other explanation of a measurement (c_j = 0): finite weights; a sure landmark (w >= 1) with
    p_D = 1 and no measurement near it keeps w (a miss of a confirmed landmark is no evidence against it)."""
    w, p = np.array([[2.0, 1.0]]), np.array([[1.0, 1.0]])
    logq = np.array([[[0.0], [-np.inf]]])  # only Gaussian 0 can explain z0
    for missed in ("bernoulli", "phd"):
        det, miss = exclusive_terms(w, p, logq, np.array([[-np.inf]]), np.zeros((1, 1)), missed)
        assert np.isfinite(det).all() and np.isfinite(miss).all()
        assert det[0, 0, 0] == pytest.approx(2.0) and miss[0, 0] == pytest.approx(0.0, abs=1e-12)  # it was seen
        assert miss[0, 1] == 1.0 and det[0, 1, 0] == 0.0  # nothing near: kept


def test_exclusive_association_keeps_the_mass_bound_with_either_missed_rule():
    """A Gaussian of weight 5 detected once: the corrected mass stays 5 under both missed rules (the PHD-mass
    check inside correct() would raise otherwise); a weight below 1 ends at most at 1 + its missed part."""
    from mmslam.slam.models.measurement import measure
    from mmslam.slam.phd.gmphd import correct
    from mmslam.slam.specs.landmarks import VA_SPEC

    scn = load_preset("paper")
    bs = np.asarray(scn.bs, float)
    s = np.array([[0.0, 0.0, 1.5, 0.0, 10.0, 0.0, 0.0]])
    va = np.array([60.0, 30.0, 10.0])
    Z = measure(s[0], va, int(VA_SPEC.geometry), bs)[None]
    pd_fn = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.5)  # noqa: E731
    for w0 in (5.0, 0.4):
        for missed in ("bernoulli", "phd"):
            g = GM(np.array([[w0]]), va[None, None], np.eye(3)[None, None] * 0.25, np.ones((1, 1), bool))
            for prune in (None, 1e-5):
                out, _, _ = correct({VA: g.copy()}, s, Z, np.diag([0.1, 0.01, 0.01, 0.01, 0.01]) ** 2, bs, pd_fn,
                                 np.zeros(1), np.log(1e-6), prune, {VA: None}, 0, {VA: VA_SPEC},
                                 missed={VA: missed}, association={VA: "exclusive"})
                mass = float(out[VA].w[out[VA].mask].sum())
                if w0 >= 1.0:
                    assert mass == pytest.approx(w0, rel=1e-9)
                else:
                    assert w0 < mass <= 1.0 + w0


def test_a_stored_scenario_without_a_va_gate_keeps_filter_merge():
    """A scenario resolved before the VA gate had a default stores ``merge: null`` (then: filter.merge); it loads
    as -1 (filter.merge), not as today's default 6."""
    from mmslam.scenes.scenario import scenario_from_resolved

    d = load_preset("canyon").to_dict()
    d["filter"]["types"]["VA"]["merge"] = None
    scn = scenario_from_resolved(d)
    assert scn.filter.types["VA"].merge == -1.0 and scn.filter.type_params("VA").merge_gate(scn.filter.merge) == 49.0
    assert scenario_from_resolved(load_preset("canyon").to_dict()).filter.types["VA"].merge == 6.0


@pytest.mark.parametrize("missed", ["bernoulli", "phd"])
def test_degenerate_shapes_against_the_closed_form(missed):
    """Q = 0 (an empty map): nothing; Q = 1, J = 1 (one Gaussian, one measurement): the Bernoulli update written
    out, P(1 <-> z) = L / (l0 + L), L = r p N / c, with r = min(w, 1); several particles are independent."""
    det, miss = exclusive_terms(np.zeros((2, 0)), np.zeros((2, 0)), np.zeros((2, 0, 3)), np.zeros((2, 3)),
                                np.zeros((2, 3)), missed)
    assert det.shape == (2, 0, 3) and miss.shape == (2, 0)
    w, p = np.array([[0.4], [2.0], [0.0]]), np.array([[0.3], [0.6], [0.5]])  # P = 3: w < 1, w >= 1, a dead slot
    pN, c = np.array([0.05, 0.02, 0.0]), np.array([0.01, 0.03, 0.01])  # p_D N(z) per particle; the clutter c
    logq = np.log(np.maximum(w[:, 0] * pN, 1e-300))[:, None, None]
    logq[2] = -np.inf
    det, miss = exclusive_terms(w, p, logq, np.log(c)[:, None], np.log(c + w[:, 0] * pN)[:, None], missed)
    for k in range(2):
        r = min(w[k, 0], 1.0)
        L = r * pN[k] / c[k]
        l0 = 1.0 - r * p[k, 0]
        assert det[k, 0, 0] == pytest.approx(w[k, 0] / r * L / (l0 + L), rel=1e-9)
        exp_miss = (w[k, 0] * (1 - p[k, 0]) / (l0 + L) if (missed == "phd" or w[k, 0] >= 1)
                    else w[k, 0] * (1 - p[k, 0]) / (1 - w[k, 0] * p[k, 0]))
        assert miss[k, 0] == pytest.approx(exp_miss, rel=1e-9)
    assert det[2, 0, 0] == 0.0 and miss[2, 0] == 0.0


def test_two_exclusive_types_each_see_the_others_own_terms_whatever_their_order():
    """With VA and SP both exclusive, each type's other explanations (clutter, BS, the other type) are the other
    type's own detection terms, not its rewritten BP marginals: the correction is the same in either order of the
    maps, and SP's result does not depend on whether VA is exclusive or not (it used to, in one of the orders)."""
    from mmslam.model import SP
    from mmslam.slam.models.measurement import measure
    from mmslam.slam.phd.gmphd import correct
    from mmslam.slam.specs.landmarks import SP_SPEC, VA_SPEC

    scn = load_preset("paper")
    bs = np.asarray(scn.bs, float)
    s = np.array([[0.0, 0.0, 1.5, 0.0, 10.0, 0.0, 0.0], [0.3, -0.2, 1.5, 0.01, 10.0, 0.0, 0.0]])
    va, sp = np.array([60.0, 30.0, 10.0]), np.array([40.0, 12.0, 2.0])
    z_va = measure(s[0], va, int(VA_SPEC.geometry), bs)
    Z = np.stack([z_va, measure(s[0], sp, int(SP_SPEC.geometry), bs), z_va + 0.02])
    g_va = GM(np.array([[0.8, 0.3]] * 2), np.stack([va, va + 1.0])[None].repeat(2, 0),
              np.stack([np.eye(3) * 4.0, np.eye(3)])[None].repeat(2, 0), np.ones((2, 2), bool))
    # a wide SP Gaussian whose terms reach the VA's measurements too
    g_sp = GM(np.array([[0.9]] * 2), sp[None, None].repeat(2, 0), (np.eye(3) * 400.0)[None, None].repeat(2, 0),
              np.ones((2, 1), bool))
    pd_fn = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.6)  # noqa: E731
    R = np.diag([0.1, 0.01, 0.01, 0.01, 0.01]) ** 2
    specs = {VA: VA_SPEC, SP: SP_SPEC}

    def run(order, va_assoc):
        maps = {t: {VA: g_va, SP: g_sp}[t].copy() for t in order}
        out, lw, _ = correct(maps, s, Z, R, bs, pd_fn, np.zeros(2), np.log(1e-6), None, {VA: None, SP: None}, 0,
                             {t: specs[t] for t in order}, missed={VA: "bernoulli", SP: "phd"},
                             association={VA: va_assoc, SP: "exclusive"})
        return out, lw

    a, la = run((VA, SP), "exclusive")
    b, lb = run((SP, VA), "exclusive")
    c, _ = run((VA, SP), "phd")
    np.testing.assert_allclose(la, lb, rtol=1e-12)
    for t in (VA, SP):
        np.testing.assert_allclose(a[t].w, b[t].w, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(a[SP].w, c[SP].w, rtol=1e-12, atol=1e-300)
    # the SP Gaussian does compete for the VA's measurements (else the check above tests nothing)
    # the SP Gaussian does reach the VA's measurements (1e-11 of its mass each), so its other explanations there matter
    assert (a[SP].w[:, [1, 3]] > 1e-12).all() and (a[SP].w[:, 2] > 0.99).all()
