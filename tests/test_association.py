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
    # shares: Gaussian 0 explains z1 alone and 90% of z2's psi; the weak one 9.99%; clutter 1e-6 and 1e-4
    s = np.array([[[1.0 - 1e-6, 0.9], [0.0, 0.0999]]])
    w, p = np.array([[1.0, 1e-3]]), np.array([[0.5, 0.5]])
    det, miss = exclusive_terms(w, p, s, "bernoulli")
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
        res, _ = correct({VA: g.copy()}, s, Z, R, bs, pd_fn, np.zeros(1), np.log(1e-6), None, {VA: None}, 0,
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
    assert va.association == "exclusive" and va.merge == 9.0  # the city default
    for name in ("paper", "twc2020"):  # published configurations keep the PHD's update and gate
        tp = load_preset(name).filter.type_params("VA")
        assert tp.association == "phd" and tp.merge == 49.0
    for t in ("SP", "VS"):
        assert load_preset("munich").filter.type_params(t).association == "phd"
    with pytest.raises(ConfigError, match=r"filter\.types\.VA\.association.*phd.*exclusive"):
        with_overrides(load_preset("canyon"), ['filter.types.VA.association="jpda"'])
