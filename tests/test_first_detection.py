"""Births that are new landmarks by their own measurement (``filter.types.<T>.birth_existence``,
``slam/phd/first_detection.py``): the AOD fit, the bounce height, the merge gate, and the birth weights."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.model import Bounce, LandmarkType
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.core.gm import GM
from mmslam.slam.models.measurement import measure
from mmslam.slam.phd.birth import birth_moments_by_kind
from mmslam.slam.phd.first_detection import (FIT_GATE, aod_fit, bounce_height, new_landmark_births,
                                             within_merge_gate)

MIR = int(Bounce.MIRROR)
SCAT = int(Bounce.SCATTER)
BS = np.array([0.0, 0.0, 40.0])
STATE = np.array([[20.0, 10.0, 1.5, 0.2, 8.0, 0.0, 0.0]])
R = np.diag([0.1, 0.01, 0.01, 0.01, 0.01]) ** 2
VA = np.array([100.0, 0.0, 40.0])  # the BS mirrored in the wall x = 50


def _moments(Z: np.ndarray, states: np.ndarray = STATE):
    return birth_moments_by_kind(states, Z, R, (MIR,), BS)[MIR]


def test_the_bounce_height_of_a_wall_path_by_hand():
    # the path car -> wall x = 50 -> BS: the bounce point is where the segment car -> image source crosses x = 50,
    # t = 30 / 80 of the way: z = 1.5 + 0.375 (40 - 1.5) = 15.9375, 14.4375 m above the antenna
    Z = measure(STATE[0], VA, MIR, BS)[None]
    assert bounce_height(STATE, Z, BS)[0, 0] == pytest.approx(14.4375, abs=1e-9)


def test_the_aod_fit_matches_a_linearised_covariance_and_gates_a_wrong_aod():
    """``q`` against an independent computation: the AOD Jacobian by central differences, ``S = J P J^T + R_aod``
    (the cubature rule is exact for the linear part); a noise-free path fits (q = 0 up to rounding), the same path
    with its AOD azimuth moved by 0.1 rad (10 sigma) does not."""
    z = measure(STATE[0], VA, MIR, BS)
    Z = np.stack([z, z + [0.0, 0.1, 0.0, 0.0, 0.0]])
    mean, cov, ok = _moments(Z)
    assert ok.all()
    q = aod_fit(STATE, Z, R, mean, cov, MIR, BS)
    assert q[0, 0] < 1e-3 and q[0, 1] > FIT_GATE  # (the birth's mean is the cubature images' mean: not exact)
    m, P = mean[0, 1], cov[0, 1]
    J = np.empty((2, 3))
    for a in range(3):
        d = np.zeros(3)
        d[a] = 1e-4
        J[:, a] = (measure(STATE[0], m + d, MIR, BS)[1:3] - measure(STATE[0], m - d, MIR, BS)[1:3]) / 2e-4
    S = J @ P @ J.T + R[1:3, 1:3]
    e = Z[1, 1:3] - measure(STATE[0], m, MIR, BS)[1:3]
    assert q[0, 1] == pytest.approx(float(e @ np.linalg.solve(S, e)), rel=2e-2)


def test_the_merge_gate_by_hand():
    mean = np.zeros((1, 1, 3))
    cov = np.eye(3)[None, None] * 4.0  # std 2 m: a point 2 sqrt(6) m away is at the gate 6
    r = 2.0 * np.sqrt(6.0)
    pts = np.array([[[r * 0.999, 0.0, 0.0], [0.0, r * 1.001, 0.0]]])
    assert within_merge_gate(mean, cov, pts[:, :1], np.ones((1, 1), bool), 6.0)[0, 0]
    assert not within_merge_gate(mean, cov, pts[:, 1:], np.ones((1, 1), bool), 6.0)[0, 0]
    assert not within_merge_gate(mean, cov, pts[:, :1], np.zeros((1, 1), bool), 6.0)[0, 0]  # a dead slot


def test_which_births_are_new_landmarks():
    """A wall path far from everything: new. The same with a Gaussian of the particle's map on it, or with a second
    image source 0.5 m beside it in the scan: not new (the reduction would merge them). A path off a car body (its
    bounce point at the antenna's height) and one with a wrong AOD: not new."""
    z = measure(STATE[0], VA, MIR, BS)
    car_image = np.array([60.0, 30.0, 1.5])  # a vertical car side: the bounce point at the antenna height
    Z = np.stack([z, measure(STATE[0], car_image, MIR, BS)])
    assert new_landmark_births(STATE, Z, R, _moments(Z), MIR, BS, 3.0, 6.0, None).tolist() == [[True, False]]
    bad = (z + [0.0, 0.2, 0.0, 0.0, 0.0])[None]  # the same TOA and AOA (the same birth), a wrong AOD
    assert not new_landmark_births(STATE, bad, R, _moments(bad), MIR, BS, 3.0, 6.0, None)[0, 0]
    assert abs(bounce_height(STATE, Z[1:2], BS)[0, 0]) < 3.0
    on_map = GM(np.array([[1.0]]), VA[None, None], np.eye(3)[None, None] * 0.25, np.ones((1, 1), bool))
    assert not new_landmark_births(STATE, Z[:1], R, _moments(Z[:1]), MIR, BS, 3.0, 6.0, on_map)[0, 0]
    far = GM(np.array([[1.0]]), (VA + [0.0, 40.0, 0.0])[None, None], np.eye(3)[None, None] * 0.25,
             np.ones((1, 1), bool))
    assert new_landmark_births(STATE, Z[:1], R, _moments(Z[:1]), MIR, BS, 3.0, 6.0, far)[0, 0]
    pair = np.stack([z, measure(STATE[0], VA + [0.0, 0.5, 0.0], MIR, BS)])
    assert not new_landmark_births(STATE, pair, R, _moments(pair), MIR, BS, 3.0, 6.0, None).any()


def test_the_births_weigh_birth_existence_where_new_and_the_plain_weight_elsewhere():
    from mmslam.slam.specs.landmarks import VA_SPEC, birth_point

    scn = with_overrides(load_preset("paper"), ["filter.types.VA.birth_existence=0.9"])
    states = np.repeat(STATE, 2, axis=0)
    z = measure(STATE[0], VA, MIR, BS)
    Z = np.stack([z, measure(STATE[0], VA + [0.0, -30.0, 0.0], MIR, BS)])
    mom = birth_moments_by_kind(states, Z, R, (MIR,), BS)[MIR]
    new = np.array([[True, False], [False, True]])
    unexplained = np.array([[1.0, 0.5], [0.25, 1.0]])
    pd = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.5)  # noqa: E731
    g = birth_point(states, mom, VA_SPEC, scn, pd, unexplained, new)
    bw = scn.filter.birth_weight
    np.testing.assert_allclose(g.w, [[0.9, bw * 0.5], [bw * 0.25, 0.9]], rtol=1e-15)
    plain = birth_point(states, mom, VA_SPEC, scn, pd, unexplained)
    np.testing.assert_allclose(plain.w, bw * unexplained, rtol=1e-15)
    np.testing.assert_array_equal(plain.m, g.m)
    assert load_preset("paper").filter.types["VA"].birth_existence == 0.0  # the paper's birth


def test_a_failed_birth_and_the_line_of_sight_are_never_new_and_nothing_raises():
    """A SCATTER birth of a measurement whose path length is below the BS distance (clutter, or the line of sight with
    a low clock bias) has every image at the antenna, a singular spread: it is not new and raises nothing. The line of
    sight births a VA at the BS, whose AOD fits any: the line of sight explains it, so it is not new either (found by
    a review: with the adaptive birth off it was born at birth_existence), whatever the particle's clock bias."""
    sc = int(Bounce.SCATTER)
    z_sp = measure(STATE[0], np.array([60.0, 20.0, 10.0]), sc, BS)
    clutter = np.array([5.0, 0.3, -0.1, 0.2, 0.0])
    Z = np.stack([z_sp, clutter])
    mom = birth_moments_by_kind(STATE, Z, R, (sc,), BS)[sc]
    assert mom[2].tolist() == [[True, False]]
    assert new_landmark_births(STATE, Z, R, mom, sc, BS, 3.0, 6.0, None).tolist() == [[True, False]]
    los = measure(STATE[0], BS, int(Bounce.DIRECT), BS)[None]
    lows = np.repeat(STATE, 5, axis=0)
    lows[:, 6] = np.linspace(-0.3, 0.3, 5)  # particles' clock biases about the true one
    assert not new_landmark_births(lows, los, R, birth_moments_by_kind(lows, los, R, (MIR,), BS)[MIR], MIR, BS, 3.0,
                                   6.0, None).any()


@pytest.mark.parametrize("row", ["VA", "SP", "VS"])
def test_a_local_filter_runs_with_birth_existence_on_any_type(row):
    from mmslam.slam.filter.local_filter import LocalFilter

    scn = with_overrides(load_preset("paper"), [f"filter.types.{row}.birth_existence=0.5", "filter.vs_birth_height=3",
                                                "filter.adaptive_birth=false"])
    bs = np.asarray(scn.bs, float)
    s0 = np.array([20.0, 10.0, 1.5, 0.2, 8.0, 0.0, 0.0])
    Z = np.stack([measure(s0, bs, int(Bounce.DIRECT), bs), measure(s0, bs + [60.0, -30.0, 0.0], MIR, bs),
                  measure(s0, np.array([40.0, 20.0, 12.0]), int(Bounce.SCATTER), bs), [5.0, 0.3, -0.1, 0.2, 0.0]])
    pd = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.9)  # noqa: E731
    f = LocalFilter(scn, "proposed", 8, s0, R, 1e-3, pd, np.random.default_rng(3), vehicle=0)
    f.step(Z)
    f.step(Z, 8.0, 0.0)
    va = f.maps[1]
    near_bs = np.linalg.norm(va.m[..., 0:3] - bs, axis=-1) < 5.0
    assert not (va.mask & near_bs & (va.w > 1e-3)).any()  # the line of sight births no VA of weight at the BS


def test_a_bounce_in_the_car_band_with_no_car_near_is_a_walls():
    """``filter.band_cars``: a path off a point q 22.4 m from the antenna and 0.5 m above it (a car body's height)
    fits a wall's AOD (the mirror hypothesis's specular point is q itself) and bounces in the 3 m band. Its SCATTER
    point spreads across the ray by r x 0.01 rad = 0.224 m and along it by the TOA's 0.1 m / (1 + d . (q - BS) /
    |q - BS|) = 0.057 m (the path length grows by 1 + d . (q - BS) / |q - BS| per metre along the ray d): in y,
    sqrt((0.894 x 0.224)^2 + (0.447 x 0.057)^2) = 0.202 m (the horizontal ray d = (0.894, 0.447); the across-ray
    direction (-0.447, 0.894) has y part d_x). With a car Gaussian 1 m from q (within half a car, 2.25
    m) it stays a possible car path; with the only car 30 m away (sigma 0.5 m) it is new; a car 30 m away whose sigma
    is 10 m (3 sigma + 2.25 > 30) could still be there; a dead slot is no car. A point 4 m from a car (sigma 0.1 m)
    is off it when the point is sharp (2.25 + 3 sqrt(0.01 + 0.01) = 2.67 m) and near it when the point spreads by
    1 m (2.25 + 3 sqrt(0.01 + 1) = 5.26 m): a far bounce's angle noise."""
    from mmslam.slam.phd.first_detection import off_every_car

    q = np.array([40.0, 20.0, 2.0])
    Z = measure(STATE[0], q, SCAT, BS)[None]
    scatter = birth_moments_by_kind(STATE, Z, R, (SCAT,), BS)[SCAT]
    np.testing.assert_allclose(scatter[0][0, 0], q, atol=0.01)
    d = (q - STATE[0, 0:3]) / np.linalg.norm(q - STATE[0, 0:3])
    along = 0.1 / (1.0 + d @ (q - BS) / np.linalg.norm(q - BS))
    across = np.linalg.norm(q - STATE[0, 0:3]) * 0.01
    np.testing.assert_allclose(np.sqrt(scatter[1][0, 0, 1, 1]), np.hypot(d[0] * across, d[1] * along), rtol=0.05)

    def cars(offset: float, var: float, live: bool = True) -> GM:
        m = np.zeros((1, 1, 7))
        m[0, 0, 0:3] = q + [offset, 0.0, 0.0]
        return GM(np.array([[1.0]]), m, np.eye(7)[None, None] * var, np.array([[live]]))

    assert off_every_car(scatter, cars(1.0, 0.01), 2.25).tolist() == [[False]]
    assert off_every_car(scatter, cars(30.0, 0.25), 2.25).tolist() == [[True]]
    assert off_every_car(scatter, cars(30.0, 100.0), 2.25).tolist() == [[False]]
    assert off_every_car(scatter, cars(1.0, 0.01, live=False), 2.25).tolist() == [[True]]
    sharp = (q[None, None], np.eye(3)[None, None] * 0.01, np.array([[True]]))
    spread = (q[None, None], np.eye(3)[None, None] * 1.0, np.array([[True]]))
    assert off_every_car(sharp, cars(4.0, 0.01), 2.25).tolist() == [[True]]
    assert off_every_car(spread, cars(4.0, 0.01), 2.25).tolist() == [[False]]
    no_point = (q[None, None], np.eye(3)[None, None], np.array([[False]]))
    assert off_every_car(no_point, cars(30.0, 0.01), 2.25).tolist() == [[False]]  # no single-scatter point: no test
    mom = _moments(Z)
    assert aod_fit(STATE, Z, R, mom[0], mom[1], MIR, BS)[0, 0] <= FIT_GATE  # a wall's AOD
    np.testing.assert_allclose(bounce_height(STATE, Z, BS), [[0.5]], atol=1e-9)
    assert not new_landmark_births(STATE, Z, R, mom, MIR, BS, 3.0, 6.0, None)[0, 0]  # the band alone
    assert not new_landmark_births(STATE, Z, R, mom, MIR, BS, 3.0, 6.0, None, cars(1.0, 0.01), 2.25, scatter)[0, 0]
    assert new_landmark_births(STATE, Z, R, mom, MIR, BS, 3.0, 6.0, None, cars(30.0, 0.25), 2.25, scatter)[0, 0]
    with pytest.raises(ValueError, match="SCATTER moments"):
        new_landmark_births(STATE, Z, R, mom, MIR, BS, 3.0, 6.0, None, cars(30.0, 0.25), 2.25)


def test_band_cars_asks_the_fleet_the_downlinks_brought():
    """``filter.band_cars`` asks the fleet as the downlinks told it (:meth:`LocalFilter._roster`): each other car's
    ego-labelled Gaussian of the fused VS map (not this car's own, not a birth's), kept when a later fused map has lost
    it (the BS's fusion can halve a car another upload missed) and predicted with the VS motion (5 m/s along x for
    0.5 s: 2.5 m); the test acts only once every other car of the scenario (canyon: three cars) is known."""
    from mmslam.slam.core.gm import LABEL_BITS, ego_label
    from mmslam.slam.filter.local_filter import LocalFilter
    from mmslam.slam.phd.first_detection import off_every_car

    scn = with_overrides(load_preset("canyon"), ["filter.band_cars=true"])
    vs = int(LandmarkType.VS)
    s0 = np.array([0.0, 0.0, 1.6, 0.0, 5.0, 0.0, 0.0])
    pd = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.9)  # noqa: E731
    f = LocalFilter(scn, "proposed", 4, s0, R, 1e-3, pd, np.random.default_rng(0), vehicle=0)

    def fused(*cars: tuple[int, float]) -> dict[int, GM]:
        n = len(cars)
        m = np.zeros((n, 7))
        m[:, 0] = [x for _, x in cars]
        m[:, 2], m[:, 3] = 1.6, 5.0  # on the road, 5 m/s along x
        return {vs: GM(np.ones(n), m, np.tile(np.eye(7) * 0.04, (n, 1, 1)), np.ones(n, bool),
                       label=np.array([lab for lab, _ in cars], np.int64))}

    assert f._cars() is None  # no downlink yet
    f.downlink(fused((ego_label(1), 10.0)))
    assert f._cars() is None  # car 2 unknown: it could be anywhere
    f.downlink(fused((ego_label(1), 10.0), (ego_label(2), 50.0), (ego_label(0), 0.0), ((1 << LABEL_BITS) + 4, 30.0)))
    assert sorted(f._fleet.label[f._fleet.mask].tolist()) == [ego_label(1), ego_label(2)]  # not its own, no birth
    cars = f._cars()
    assert cars is not None and cars.batch_shape == (4,)
    f.predict(5.0, 0.0)
    f.downlink(fused((ego_label(1), 20.0)))  # the fused map has lost car 2
    fleet = {int(lab): x for lab, x in zip(f._fleet.label[f._fleet.mask], f._fleet.m[f._fleet.mask, 0])}
    assert fleet[ego_label(1)] == 20.0
    assert fleet[ego_label(2)] == pytest.approx(52.5, abs=1e-9)
    cars = f._cars()
    assert np.isclose(cars.m[..., 0], 52.5).any(-1).all()  # every particle asks car 2 where the roster has it
    # a bounce 0.5 m above the antenna, 1 m from car 2's roster entry (the particles near x = 2.5, no VS map near):
    # a possible car path, not a wall's
    Z = measure(f.s[0], np.array([53.5, 0.0, 2.1]), SCAT, np.asarray(scn.bs, float))[None]
    scatter = birth_moments_by_kind(f.s, Z, R, (SCAT,), np.asarray(scn.bs, float))[SCAT]
    assert scatter[2].all() and not off_every_car(scatter, cars, 2.25).any()
    assert off_every_car(scatter, GM(cars.w[:, :-2], cars.m[:, :-2], cars.P[:, :-2], cars.mask[:, :-2]), 2.25).all()
    # without the option no roster is kept
    f = LocalFilter(with_overrides(scn, ["filter.band_cars=false"]), "proposed", 4, s0, R, 1e-3, pd,
                    np.random.default_rng(0), vehicle=0)
    f.downlink(fused((ego_label(1), 10.0), (ego_label(2), 50.0)))
    assert f._fleet is None and f._cars() is None
    # without labels no car is known as one: the test never acts
    scn = with_overrides(scn, ["fusion.average_by_label=false"])
    f = LocalFilter(scn, "proposed", 4, s0, R, 1e-3, pd, np.random.default_rng(0), vehicle=0)
    g = fused((ego_label(1), 10.0), (ego_label(2), 50.0))[vs]
    f.downlink({vs: GM(g.w, g.m, g.P, g.mask)})
    assert f._cars() is None


@pytest.mark.parametrize("on", [True, False])
def test_a_local_filter_with_band_cars_maps_a_wall_at_a_cars_height_where_no_car_is(on):
    """Through :meth:`LocalFilter.predict`: the fleet's two other cars 200-300 m away, a path off a point 0.5 m above
    the antenna (in the 3 m band) 34 m from the car. With ``filter.band_cars`` its VA birth is a new landmark (weight
    ``birth_existence`` 0.9, then one missed step); without it, the band holds it at ``filter.birth_weight`` order."""
    from mmslam.slam.core.gm import ego_label
    from mmslam.slam.filter.local_filter import LocalFilter

    scn = with_overrides(load_preset("canyon"), [f"filter.band_cars={str(on).lower()}"])
    vs, va = int(LandmarkType.VS), int(LandmarkType.VA)
    s0 = np.array([0.0, 0.0, 1.6, 0.0, 5.0, 0.0, 0.0])
    pd = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.9)  # noqa: E731
    f = LocalFilter(scn, "proposed", 8, s0, R, 1e-3, pd, np.random.default_rng(0), vehicle=0)
    m = np.zeros((2, 7))
    m[:, 0], m[:, 2] = [-200.0, 300.0], 1.6
    f.downlink({vs: GM(np.ones(2), m, np.tile(np.eye(7) * 0.04, (2, 1, 1)), np.ones(2, bool),
                       label=np.array([ego_label(1), ego_label(2)], np.int64))})
    f.step(measure(s0, np.array([30.0, 15.0, 2.1]), SCAT, np.asarray(scn.bs, float))[None])
    f.step(np.zeros((0, 5)), 5.0, 0.0)
    g = f.maps[va]
    assert (f._cars() is not None) == on
    assert (g.w[g.mask].max() > 0.5) if on else (g.w[g.mask].max() < 1e-3)


def test_off_every_car_on_empty_shapes():
    """``J = 0`` measurements: a ``(P, 0)`` answer; no car slot (``Q = 0``): every point with a single-scatter point
    is off every car, one without is not."""
    from mmslam.slam.phd.first_detection import off_every_car

    car = GM(np.ones((1, 1)), np.zeros((1, 1, 7)), np.eye(7)[None, None] * 0.01, np.ones((1, 1), bool))
    assert off_every_car((np.zeros((1, 0, 3)), np.zeros((1, 0, 3, 3)), np.zeros((1, 0), bool)), car, 2.25).shape \
        == (1, 0)
    none = GM(np.ones((1, 0)), np.zeros((1, 0, 7)), np.zeros((1, 0, 7, 7)), np.zeros((1, 0), bool))
    pts = (np.zeros((1, 2, 3)), np.tile(np.eye(3), (1, 2, 1, 1)), np.array([[True, False]]))
    assert off_every_car(pts, none, 2.25).tolist() == [[True, False]]
