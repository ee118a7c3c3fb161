"""The Bernoulli missed-detection rule of a landmark type (``filter.types.<T>.missed``, docs/city-slam.md)."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.errors import ConfigError
from mmslam.model import VA, VS
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.core.gm import GM
from mmslam.slam.filter.local_filter import LocalFilter
from mmslam.slam.phd.detection import bernoulli_missed_weight


def test_bernoulli_missed_weight_by_hand_and_as_bayes_rule():
    w = np.array([0.0, 0.2, 0.5, 0.9, 0.999, 1.0, 1.7, 0.5, 0.5])
    p = np.array([0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.0, 1.0])
    got = bernoulli_missed_weight(w, p)
    assert got[2] == pytest.approx(0.5 * 0.9 / 0.95, rel=1e-15)  # 0.47368...
    assert got[5] == 1.0 and got[6] == 1.7  # a landmark sure to exist is not made less likely by a miss
    assert got[7] == 0.5 and got[8] == 0.0  # p_D = 0 (outside the FOV): kept; p_D = 1: a miss rules it out
    # Bayes' rule on the two hypotheses "exists and missed" (r (1 - p)) and "does not exist" (1 - r)
    r = w[:5]
    bayes = r * (1 - p[:5]) / (r * (1 - p[:5]) + (1 - r))
    np.testing.assert_allclose(got[:5], bayes, rtol=1e-13, atol=0)
    phd = (1 - p) * w
    assert np.all(got >= phd) and np.all(got <= w)  # above the PHD's term, never above the prior weight
    assert bernoulli_missed_weight(1e-9, 0.3) / (0.7e-9) == pytest.approx(1.0, rel=1e-8)  # the PHD's for w -> 0


def _filter(missed: str) -> LocalFilter:
    scn = with_overrides(load_preset("paper"), [f'filter.types.VA.missed="{missed}"'])
    s0 = np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5])

    def pd_fn(u, x, t):  # VS: 0.9 within 30 m, 0 beyond; VAs 0.2 everywhere
        d = np.linalg.norm(np.asarray(x) - np.asarray(u), axis=-1)
        return np.where(d < 30.0, 0.9, 0.0) if t == VS else np.full(d.shape, 0.2)

    f = LocalFilter(scn, "cm1", 2, s0, np.eye(5), 1e-3, pd_fn, np.random.default_rng(0))
    f.maps[VA] = GM(np.tile([0.8, 1.3], (2, 1)), np.tile([[50.0, 60.0, 10.0], [-40.0, 10.0, 8.0]], (2, 1, 1)),
                    np.broadcast_to(np.eye(3), (2, 2, 3, 3)).copy(), np.ones((2, 2), bool))
    f.maps[VS] = GM(np.tile([0.5], (2, 1)), np.tile(np.r_[s0[:3] + [10.0, 0, 0], np.zeros(4)], (2, 1, 1)),
                    np.broadcast_to(np.eye(7), (2, 1, 7, 7)).copy(), np.ones((2, 1), bool))
    return f


def test_a_missed_va_keeps_more_weight_under_the_bernoulli_rule_and_other_types_are_unchanged():
    phd, bern = _filter("phd"), _filter("bernoulli")
    for f in (phd, bern):
        f.correct(np.zeros((0, 5)))  # an empty scan: every Gaussian in the FOV was missed
    np.testing.assert_allclose(phd.maps[VA].w, np.tile([0.64, 1.04], (2, 1)), rtol=1e-12)  # (1 - 0.2) w
    np.testing.assert_allclose(bern.maps[VA].w, np.tile([0.8 * 0.8 / (1 - 0.16), 1.3], (2, 1)), rtol=1e-12)
    np.testing.assert_array_equal(bern.maps[VA].m, phd.maps[VA].m)
    np.testing.assert_allclose(bern.maps[VS].w, phd.maps[VS].w, rtol=0, atol=0)  # VS keeps the PHD's rule (0.05)
    assert phd.maps[VS].w[0, 0] == pytest.approx(0.05, rel=1e-12)


def test_defaults_and_presets():
    assert load_preset("canyon").filter.type_params("VA").missed == "bernoulli"  # the city default
    for name in ("paper", "twc2020"):  # published configurations keep the PHD's term
        assert load_preset(name).filter.type_params("VA").missed == "phd"
    for t in ("SP", "VS"):
        assert load_preset("munich").filter.type_params(t).missed == "phd"
    with pytest.raises(ConfigError, match=r"filter\.types\.VA\.missed.*phd.*bernoulli"):
        with_overrides(load_preset("canyon"), ['filter.types.VA.missed="lmb"'])


def test_with_measurements_only_the_missed_terms_change_and_degenerate_shapes_hold():
    """J = 1 measurement of a VA: the detected components are the PHD's exactly (same psi, same CKF posterior),
    the missed ones take the Bernoulli weight; P = 1 with Q = 0 (an empty VA map) gives the same empty map."""
    from mmslam.slam.models.measurement import measure
    from mmslam.slam.phd.gmphd import correct

    scn = load_preset("paper")
    s = np.array([[20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]])
    va = np.array([50.0, 60.0, 10.0])
    pd_fn = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.3)  # noqa: E731
    kinds = {VA: _filter("phd").specs[VA]}
    z = measure(s[0], va, int(kinds[VA].geometry), np.asarray(scn.bs, float))[None] + [0.05, 0.01, 0.0, -0.01, 0.0]

    def run(missed, q):
        g = GM(np.full((1, q), 0.8), np.tile(va, (1, q, 1)), np.broadcast_to(np.eye(3), (1, q, 3, 3)).copy(),
               np.ones((1, q), bool))
        out, lpsi, _ = correct({VA: g}, s, z, np.eye(5) * 0.01, np.asarray(scn.bs, float), pd_fn, np.zeros(1),
                            np.log(1e-3), None, {VA: None}, 0, kinds, missed={VA: missed})
        return out[VA], lpsi

    (gp, lp), (gb, lb) = run("phd", 1), run("bernoulli", 1)
    np.testing.assert_array_equal(lb, lp)  # psi (particle weights) unchanged
    live_p, live_b = gp.w[gp.mask], gb.w[gb.mask]
    assert live_p.shape == live_b.shape == (2,)  # dense layout: the missed component first, then z's
    assert live_p[1] > 0.1  # the measurement is the VA's: a real detection term
    assert live_p[0] == pytest.approx(0.7 * 0.8, rel=1e-12) and live_b[0] == pytest.approx(0.8 * 0.7 / 0.76, rel=1e-12)
    assert live_b[1] == live_p[1]  # the detected term is the PHD's
    np.testing.assert_array_equal(gb.m, gp.m)
    (ep, lep), (eb, leb) = run("phd", 0), run("bernoulli", 0)  # Q = 0
    assert eb.w.shape == ep.w.shape and not eb.mask.any()
    np.testing.assert_array_equal(leb, lep)


def test_a_confirmed_landmark_gives_its_detection_shares_out_of_its_missed_term():
    """w >= 1: w' = max(w - sum_j s_j, 0) by hand; w < 1 ignores the shares (Bayes on the miss alone)."""
    w = np.array([2.0, 1.0, 1.0, 0.5])
    p = np.full(4, 0.3)
    shares = np.array([[0.3, 0.5], [0.9, 0.0], [0.8, 0.7], [0.6, 0.0]])
    got = bernoulli_missed_weight(w, p, shares)
    np.testing.assert_allclose(got, [1.2, 0.1, 0.0, 0.5 * 0.7 / 0.85], rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(bernoulli_missed_weight(w, p, np.zeros((4, 3))), bernoulli_missed_weight(w, p))


def test_a_confirmed_va_detected_at_every_step_keeps_its_mass():
    """One VA of weight 1 detected by a measurement (psi from a small clutter and this VA): the corrected VA mass
    stays 1 (missed 1 - s plus detected s; merged it is one landmark), so it is 1 again at every later detection.
    The previous rule kept the whole w as the missed term and added s: the mass grew by about 1 per detection
    (munich: one VA at weight 12-17, the fused VA map's PHD mass 5x its landmarks)."""
    from mmslam.slam.models.measurement import measure
    from mmslam.slam.phd.gmphd import correct

    scn = load_preset("paper")
    s = np.array([[20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]])
    va = np.array([50.0, 60.0, 10.0])
    pd_fn = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.5)  # noqa: E731
    kinds = {VA: _filter("phd").specs[VA]}
    z = measure(s[0], va, int(kinds[VA].geometry), np.asarray(scn.bs, float))[None]
    g = GM(np.array([[1.0]]), va[None, None], np.eye(3)[None, None] * 0.25, np.ones((1, 1), bool))
    out, _, _ = correct({VA: g}, s, z, np.eye(5) * 0.01, np.asarray(scn.bs, float), pd_fn, np.zeros(1),
                     np.log(1e-6), None, {VA: None}, 0, kinds, missed={VA: "bernoulli"})
    live = out[VA].w[out[VA].mask]
    share = live[1]  # the PHD's detection term s
    assert 0.9 < share < 1.0  # the measurement is this VA's: psi = clutter + s psi
    assert live[0] == pytest.approx(1.0 - share, rel=1e-12)  # the missed term gives the share out
    assert live.sum() == pytest.approx(1.0, rel=1e-12)  # the previous rule: 1 + s
