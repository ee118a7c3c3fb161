"""The weight offset of a static landmark type (``filter.types.<T>.weight_std``): the particle weight, eq. (6), takes
the type's detected terms with ``P + F_w`` on the position, the map's update (eq. (5)) keeps its own; refused for a
moving type."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.errors import ConfigError
from mmslam.model import SP, VA, Bounce
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.core.gm import GM
from mmslam.slam.filter.local_filter import LocalFilter
from mmslam.slam.models.measurement import measure, residual
from mmslam.slam.phd.follow import weight_mixture
from mmslam.slam.phd.gmphd import correct
from mmslam.slam.specs.landmarks import landmark_type

BS = np.array([0.0, 0.0, 10.0])
STATE = np.array([5.0, -20.0, 1.5, 0.3, 10.0, 0.0, 2.0])
R = np.diag([0.01, 1e-4, 1e-4, 1e-4, 1e-4])
X = np.array([40.0, 35.0, 6.0])
P0 = np.diag([0.04, 0.09, 0.02])
LOG_C = -12.0
CITY = dict(missed={VA: "bernoulli"}, association={VA: "exclusive"}, tails={VA: (0.2, 4.0)})


def _pd(u, x, t):
    return np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.9)


def _map(P: np.ndarray = P0, n: int = 2) -> GM:
    return GM(np.full((n, 1), 1.2), np.tile(X, (n, 1, 1)), np.tile(P, (n, 1, 1, 1)), np.ones((n, 1), bool),
              np.tile([3.0, 1.0], (n, 1, 1)), np.arange(n)[:, None].astype(np.int64))


def _correct(g: GM, states: np.ndarray, Z: np.ndarray, city: bool, own: bool = False, **kw):
    """``correct``'s maps and the weight's ``log psi`` (with ``own``: also the maps' own ``log psi``)."""
    out = correct({VA: g}, states, Z, R, BS, _pd, np.zeros(states.shape[0]), LOG_C, 1e-5, {VA: None}, 3,
                  {VA: landmark_type(VA)}, **(CITY if city else {}), **kw)
    return out if own else out[:2]


@pytest.mark.parametrize("city", [False, True], ids=["paper row", "city row (exclusive, Bernoulli, tail)"])
def test_the_weight_offset_changes_the_weight_only(city):
    """Two particles (one at the true pose, one 0.6 m off), one VA, two measurements (the VA's and one 1 m off it):
    with F_w = 0.5 m^2 the corrected maps are those without it (every array equal), and log psi is that of the same
    correction of the map widened to P + F_w (computed the plain way), which differs from the map's own; the third
    output, the maps' own log psi, is that of the plain correction."""
    states = np.stack([STATE, STATE + [0.6, -0.2, 0.0, 0.0, 0.0, 0.0, 0.0]])
    Z = np.stack([measure(STATE, X, Bounce.MIRROR, BS), measure(STATE, X + [0.8, 0.6, 0.0], Bounce.MIRROR, BS)])
    F = 0.5
    plain_maps, plain_lpsi = _correct(_map(), states, Z, city)
    maps, lpsi, own = _correct(_map(), states, Z, city, own=True, weight_offsets={VA: F})
    np.testing.assert_array_equal(own, plain_lpsi)
    for key in ("w", "m", "P", "mask", "pd_beta", "label"):
        np.testing.assert_array_equal(getattr(maps[VA], key), getattr(plain_maps[VA], key))
    _, wide_lpsi = _correct(_map(P0 + F * np.eye(3)), states, Z, city)
    np.testing.assert_array_equal(lpsi, wide_lpsi)
    assert np.abs(lpsi - plain_lpsi).min() > 1e-3
    _, zero_lpsi = _correct(_map(), states, Z, city, weight_offsets={VA: 0.0})
    np.testing.assert_array_equal(zero_lpsi, plain_lpsi)


def test_the_weight_offset_is_the_likelihood_of_p_plus_f_by_a_linearised_hand_computation():
    """One particle, one VA of weight w, one measurement z 0.5 m off the VA's image: psi(z) = c + p_D w N(z; h(m), S)
    (p_D = 0.75, the mean of the VA's Beta (3, 1))
    with S = H (P + F_w) H^T + R, H the Jacobian of h at the mean (central differences, not the cubature rule):
    log psi agrees within 2e-3 (the cubature's departure from the linearisation at 55 m); without the offset, the
    same with P (a different value); and where z is the VA's own image from the true pose, a particle 0.6 m off
    falls less far behind the true one with the offset."""
    F = 0.3
    Z = measure(STATE, X + [0.3, -0.4, 0.0], Bounce.MIRROR, BS)[None]
    H = np.empty((5, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1e-5
        H[:, a] = residual(measure(STATE, X + e, Bounce.MIRROR, BS), measure(STATE, X - e, Bounce.MIRROR, BS)) / 2e-5
    r = residual(Z[0], measure(STATE, X, Bounce.MIRROR, BS))
    for Pm, kw in ((P0 + F * np.eye(3), {"weight_offsets": {VA: F}}), (P0, {})):
        S = H @ Pm @ H.T + R
        logn = -0.5 * (r @ np.linalg.solve(S, r) + np.linalg.slogdet(2 * np.pi * S)[1])
        want = np.logaddexp(LOG_C, np.log(0.75 * 1.2) + logn)  # p_D: the Beta (3, 1)'s mean
        _, lpsi = _correct(_map(n=1), STATE[None], Z, False, **kw)
        assert abs(lpsi[0, 0] - want) < 2e-3
    off = np.stack([STATE, STATE + [0.6, -0.2, 0.0, 0.0, 0.0, 0.0, 0.0]])
    Z0 = measure(STATE, X, Bounce.MIRROR, BS)[None]  # the VA's own image seen from the true pose
    gap = [np.subtract(*_correct(_map(), off, Z0, True, **kw)[1][:, 0]) for kw in ({}, {"weight_offsets": {VA: F}})]
    assert gap[0] > gap[1] > 0.0


def test_the_offset_of_one_type_leaves_the_other_types_terms_and_adds_to_the_follow():
    """A VA map (exclusive association, no offset) and an SP map (weight offset 0.5 m^2) at the same point: log psi is
    that of the VA map as it is plus the SP map widened (the VA's exclusive terms are rewritten after the weight's are
    read: a weight read after that would differ); with a follow of 0.2 m^2 and a weight offset of 0.5 m^2 on the VA,
    log psi is that of the VA map widened by 0.7 m^2 without the follow, and the maps are those of the follow alone."""
    states = np.stack([STATE, STATE + [0.6, -0.2, 0.0, 0.0, 0.0, 0.0, 0.0]])
    Z = np.stack([measure(STATE, X, Bounce.MIRROR, BS), measure(STATE, X + [0.8, 0.6, 0.0], Bounce.MIRROR, BS)])
    kinds = {VA: landmark_type(VA), SP: landmark_type(SP)}

    def run(va: GM, sp: GM, **kw):
        return correct({VA: va, SP: sp}, states, Z, R, BS, _pd, np.zeros(2), LOG_C, 1e-5, {VA: None, SP: None}, 3,
                       kinds, association={VA: "exclusive"}, missed={VA: "bernoulli"}, **kw)[:2]

    _, lpsi = run(_map(), _map(), weight_offsets={SP: 0.5})
    _, want = run(_map(), _map(P0 + 0.5 * np.eye(3)))
    np.testing.assert_array_equal(lpsi, want)
    maps, lpsi = _correct(_map(), states, Z, True, follows={VA: 0.2}, weight_offsets={VA: 0.5})
    follow_maps, _ = _correct(_map(), states, Z, True, follows={VA: 0.2})
    _, want = _correct(_map(P0 + 0.7 * np.eye(3)), states, Z, True)
    np.testing.assert_allclose(lpsi, want, rtol=1e-12)
    for key in ("w", "m", "P"):
        np.testing.assert_array_equal(getattr(maps[VA], key), getattr(follow_maps[VA], key))


def test_the_local_filter_hands_the_offset_to_the_correction(monkeypatch):
    """LocalFilter.correct passes its squared weight_std per type to gmphd.correct (0.25 for the VA at 0.5 m)."""
    import mmslam.slam.filter.local_filter as lf

    seen = {}
    real = lf.correct

    def spy(*a, **kw):
        seen["offsets"] = a[17] if len(a) > 17 else kw.get("weight_offsets")
        seen["shares"] = a[18] if len(a) > 18 else kw.get("weight_shares")
        return real(*a, **kw)

    monkeypatch.setattr(lf, "correct", spy)
    f = _filter(["filter.types.VA.weight_std=0.5"])
    f.correct(np.zeros((0, 5)))
    assert seen["offsets"][VA] == 0.25 and seen["offsets"][SP] == 0.0
    assert seen["shares"][VA] == 0.2 and seen["shares"][SP] == 1.0  # the built-in VA row's share; the offset alone
    _filter(["filter.types.VA.weight_std=0.5", "filter.types.VA.weight_share=0.7"]).correct(np.zeros((0, 5)))
    assert seen["shares"][VA] == 0.7 and seen["shares"][SP] == 1.0


def test_the_weight_mixture_by_hand():
    """weight_mixture: log((1 - e) q + e q_w) on hand values (q = 2, q_w = 6, e = 0.25: log 3; a term only the offset
    map has, -inf and log 4 at e = 0.5: log 2); e = 1 is the offset's terms, e = 0 the map's own; e outside [0, 1]
    is refused."""
    q, qw = np.log([[[2.0, 1.0]]]), np.log([[[6.0, 4.0]]])
    q[0, 0, 1] = -np.inf
    np.testing.assert_allclose(weight_mixture(q, qw, 0.25)[0, 0, 0], np.log(3.0), rtol=1e-14)
    np.testing.assert_allclose(weight_mixture(q, qw, 0.5)[0, 0, 1], np.log(2.0), rtol=1e-14)
    assert weight_mixture(q, qw, 1.0) is qw and weight_mixture(q, qw, 0.0) is q
    none = np.full((1, 1, 2), -np.inf)  # a masked slot or p_D = 0: no term in either map
    with np.errstate(all="raise"):
        assert np.all(weight_mixture(none, none, 0.3) == -np.inf)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="weight share"):
            weight_mixture(q, qw, bad)


@pytest.mark.parametrize("city", [False, True], ids=["paper row", "city row (exclusive, Bernoulli, tail)"])
def test_a_share_of_the_offset_mixes_psi_and_leaves_the_maps(city):
    """The two-particle scene of the first test with F_w = 0.5 m^2 at a share e = 0.3: the weight's psi is
    0.7 psi + 0.3 psi_w, with psi the weight without the offset and psi_w that of the offset alone (the clutter and
    BS terms are the same in both), and the corrected maps are those without the offset; an absent share is 1."""
    states = np.stack([STATE, STATE + [0.6, -0.2, 0.0, 0.0, 0.0, 0.0, 0.0]])
    Z = np.stack([measure(STATE, X, Bounce.MIRROR, BS), measure(STATE, X + [0.8, 0.6, 0.0], Bounce.MIRROR, BS)])
    plain_maps, plain = _correct(_map(), states, Z, city)
    _, alone = _correct(_map(), states, Z, city, weight_offsets={VA: 0.5})
    maps, mixed = _correct(_map(), states, Z, city, weight_offsets={VA: 0.5}, weight_shares={VA: 0.3})
    np.testing.assert_allclose(mixed, np.log(0.7 * np.exp(plain) + 0.3 * np.exp(alone)), rtol=1e-12)
    assert np.abs(mixed - plain).min() > 1e-4 and np.abs(mixed - alone).min() > 1e-4
    for key in ("w", "m", "P", "mask", "pd_beta", "label"):
        np.testing.assert_array_equal(getattr(maps[VA], key), getattr(plain_maps[VA], key))
    _, other = _correct(_map(), states, Z, city, weight_offsets={VA: 0.5}, weight_shares={SP: 0.3})
    np.testing.assert_array_equal(other, alone)
    _, zero = _correct(_map(), states, Z, city, weight_offsets={VA: 0.5}, weight_shares={VA: 0.0})
    np.testing.assert_array_equal(zero, plain)  # a share 0: the weight without the offset


def test_an_empty_scan_leaves_the_weight_empty():
    """J = 0: log psi has shape (P, 0) with or without the offset (an empty product of eq. (6))."""
    _, lpsi = _correct(_map(), np.stack([STATE, STATE]), np.zeros((0, 5)), True, weight_offsets={VA: 0.5})
    assert lpsi.shape == (2, 0)


def _filter(rows: list[str], variant: str = "cm1") -> LocalFilter:
    scn = with_overrides(load_preset("paper"), rows)
    return LocalFilter(scn, variant, 2, np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5]), np.eye(5), 1e-3, _pd,
                       np.random.default_rng(0))


@pytest.mark.parametrize("key, attr", [("follow_std", "_follow"), ("weight_std", "_weight_offset")])
def test_an_offset_is_zero_in_the_paper_squared_by_the_filter_and_refused_on_a_moving_type(key, attr):
    """paper and twc2020 pin follow_std and weight_std 0 (the paper's update and weight); the filter squares the row's
    value; either on the moving VS is a one-line ConfigError naming the key and the fix, for every variant; a negative
    value is refused."""
    assert getattr(load_preset("paper").filter.type_params("VA"), key) == 0.0
    assert getattr(load_preset("twc2020").filter.type_params("VA"), key) == 0.0
    assert getattr(_filter([f"filter.types.VA.{key}=0.5"]), attr)[VA] == 0.25
    for variant in ("cm1", "baseline", "proposed"):
        with pytest.raises(ConfigError, match=rf"^filter\.types\.VS\.{key}: .*set {key} = 0$"):
            _filter([f"filter.types.VS.{key}=0.1"], variant)
    with pytest.raises(ConfigError, match=key):
        with_overrides(load_preset("paper"), [f"filter.types.VA.{key}=-1"])


def test_a_share_on_degenerate_shapes():
    """One particle: an empty VA map (Q = 0) gives the weight of clutter and BS alone with or without the share; one
    Gaussian and one measurement (P = Q = J = 1) give psi_lambda = (1 - lambda) psi + lambda psi_w; no measurement
    (J = 0) an empty weight."""
    one = STATE[None]
    Z = measure(STATE, X + [0.8, 0.6, 0.0], Bounce.MIRROR, BS)[None]
    empty = GM(np.zeros((1, 0)), np.zeros((1, 0, 3)), np.zeros((1, 0, 3, 3)), np.zeros((1, 0), bool),
               np.zeros((1, 0, 2)), np.zeros((1, 0), np.int64))
    for city in (False, True):
        _, plain = _correct(empty, one, Z, city)
        _, mixed = _correct(empty, one, Z, city, weight_offsets={VA: 0.5}, weight_shares={VA: 0.3})
        np.testing.assert_array_equal(mixed, plain)
        np.testing.assert_allclose(plain, LOG_C, rtol=1e-12)  # the BS is not detectable (p_bs = 0): clutter only
        _, plain = _correct(_map(n=1), one, Z, city)
        _, alone = _correct(_map(n=1), one, Z, city, weight_offsets={VA: 0.5})
        _, mixed = _correct(_map(n=1), one, Z, city, weight_offsets={VA: 0.5}, weight_shares={VA: 0.3})
        np.testing.assert_allclose(mixed, np.log(0.7 * np.exp(plain) + 0.3 * np.exp(alone)), rtol=1e-12)
        _, none = _correct(_map(n=1), one, np.zeros((0, 5)), city, weight_offsets={VA: 0.5}, weight_shares={VA: 0.3})
        assert none.shape == (1, 0)
