"""Vehicles as extended scatterers (issue 22): a VS path bounces at the specular point of the car body
(:func:`mmslam.slam.models.vs.body_specular_point`), in the VS likelihood and at a VS birth; the paper's
point VS where the paths come from point scatterers."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize

from mmslam.model import Bounce
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.filter.run import resolve_vs_body
from mmslam.slam.models.measurement import measure
from mmslam.slam.models.vs import body_antennas, body_points
from mmslam.slam.phd.ckf import kalman_update
from mmslam.slam.specs.vehicle_body import vs_body

BODY = np.array([4.5, 1.8, 1.5, 0.8])  # length, width, height, centre depth below the antenna (m)
GOLDEN = Path(__file__).parent / "golden"


def _point(x, heading, b, u, body=BODY):
    return body_points(np.asarray(x, float)[None], np.array([heading]), np.asarray(b, float),
                       np.asarray(u, float)[None], body)[0]


def test_specular_point_on_known_faces():
    """BS and receiver far ahead: the front of the body, a semi-length ahead of the centre; from the
    side: a semi-width; from above: the roof; a car turned by 90 degrees shows its side to the front."""
    x = np.array([10.0, -5.0, 1.6])  # antenna; the body centre is 0.8 m below
    c = x - [0, 0, 0.8]
    far = 1e7
    np.testing.assert_allclose(_point(x, 0.0, c + [far, 0, 0], c + [far, 0, 0]), c + [2.25, 0, 0], atol=1e-6)
    np.testing.assert_allclose(_point(x, 0.0, c + [0, -far, 0], c + [0, -far, 0]), c + [0, -0.9, 0], atol=1e-6)
    np.testing.assert_allclose(_point(x, 0.0, c + [0, 0, far], c + [0, 0, far]), c + [0, 0, 0.75], atol=1e-6)
    np.testing.assert_allclose(_point(x, math.pi / 2, c + [far, 0, 0], c + [far, 0, 0]), c + [0.9, 0, 0], atol=1e-6)
    # a BS ahead and a receiver to the left: the bisector (1, 1, 0) / sqrt 2, on the ellipse x^2/a^2 + y^2/b^2 = 1
    p = _point(x, 0.0, c + [far, 0, 0], c + [0, far, 0]) - c
    assert p[0] ** 2 / 2.25 ** 2 + p[1] ** 2 / 0.9 ** 2 == pytest.approx(1.0, abs=1e-9)
    assert p[0] / 2.25 ** 2 == pytest.approx(p[1] / 0.9 ** 2, rel=1e-6)  # the normal there is (1, 1, 0) / sqrt 2
    np.testing.assert_array_equal(_point(x, 0.3, c + [far, 0, 0], c + [0, far, 0], np.zeros(4)), x)  # point VS


def test_specular_point_is_fermats_shortest_path_on_the_ellipsoid():
    """Cross-check by an independent computation: for ends far from the car, the bounce point minimises
    |b - p| + |p - u| over the ellipsoid's surface (numerical minimisation over its two angles)."""
    rng = np.random.default_rng(5)
    a, w, h = BODY[:3] / 2
    for _ in range(6):
        x = rng.uniform(-20, 20, 3)
        c = x - [0, 0, BODY[3]]
        heading = rng.uniform(-math.pi, math.pi)
        d_b, d_u = rng.normal(size=3), rng.normal(size=3)
        d_b[2], d_u[2] = abs(d_b[2]), abs(d_u[2])  # both ends above the car's centre
        b = c + 5e4 * d_b / np.linalg.norm(d_b)
        u = c + 5e4 * d_u / np.linalg.norm(d_u)
        R = np.array([[math.cos(heading), -math.sin(heading), 0], [math.sin(heading), math.cos(heading), 0], [0, 0, 1]])

        def surface(t):
            return c + R @ np.array([a * math.cos(t[0]) * math.cos(t[1]), w * math.sin(t[0]) * math.cos(t[1]),
                                     h * math.sin(t[1])])

        p = _point(x, heading, b, u)
        best = min((minimize(lambda t: np.linalg.norm(b - surface(t)) + np.linalg.norm(surface(t) - u), t0,
                             method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 4000})
                    for t0 in ([0.0, 0.0], [math.pi / 2, 0.3], [math.pi, -0.3], [-math.pi / 2, 0.8])),
                   key=lambda r: r.fun)
        np.testing.assert_allclose(p, surface(best.x), atol=2e-3)


def test_birth_inversion_returns_the_antenna_of_a_round_body():
    """:func:`body_antennas` inverts :func:`body_points` where the heading does not matter (length = width):
    the antenna is found back to 2 cm, the far-field approximation's error (ends about 1 km away)."""
    rng = np.random.default_rng(1)
    body = np.array([2.0, 2.0, 1.5, 0.8])
    x = rng.uniform(-30, 30, (20, 3))
    b = np.array([300.0, 900.0, 25.0])
    u = x + rng.normal(size=(20, 3)) * [800, 800, 1]
    p = body_points(x, rng.uniform(-3, 3, 20), b, u, body)
    assert np.all(np.linalg.norm(p - x, axis=1) > 0.3)  # the bounce is not at the antenna
    np.testing.assert_allclose(body_antennas(p, u, b, body), x, atol=2e-2)


def test_ellipsoid_body_explains_the_traced_vs_path_lengths():
    """On the stored Sionna trace of `paper` (car meshes, diffuse bounces on the body), the path length of a VS
    path predicted at the antenna point is up to 1.6 m too long (the inner car seen from the outer one bounces
    at its roof, next to the antenna; the outer one seen from inside at its side: 15 sigma of the TOA noise);
    at the body's specular point (true heading) every error is within 0.35 m."""
    import sys

    sys.path.insert(0, str(GOLDEN))
    import make_golden as mg

    states, paths = mg.load_paths(GOLDEN / "sionna_paths.npz")
    scn = mg.paper()
    names = list(scn.vehicle_names)
    sel = np.nonzero(np.asarray(paths["type"]) == 3)[0]
    assert sel.size >= 10
    b = np.array([paths["tx_x"][0], paths["tx_y"][0], paths["tx_z"][0]], float)
    k, rx = np.asarray(paths["step"])[sel], np.asarray(paths["rx"])[sel]
    tgt = np.array([names.index(str(i)) for i in np.asarray(paths["landmark_id"])[sel]])
    x, u, heading = states[k, tgt, 0:3], states[k, rx, 0:3], states[k, tgt, 3]
    car = scn.vehicles[0]
    body = np.array([car.length, car.width, car.height, car.roof_gap + car.height / 2])
    length = np.asarray(paths["toa_m"], float)[sel]

    def err(p):
        return np.linalg.norm(b - p, axis=1) + np.linalg.norm(p - u, axis=1) - length

    e_point, e_body = err(x), err(body_points(x, heading, b, u, body))
    assert e_point.max() > 1.4
    assert np.abs(e_body).max() < 0.35 and np.sqrt(np.mean(e_body ** 2)) < 0.25 * np.sqrt(np.mean(e_point ** 2))


def test_vs_likelihood_predicts_the_bounce_on_the_body():
    """The CKF of a VS Gaussian with a body predicts the measurement of the path via the body's specular point:
    a measurement of exactly that path leaves a tight Gaussian where it is (and scores higher) and moves the point
    model's Gaussian by the offset."""
    s = np.array([0.0, 0.0, 1.6, 0.0, 10.0, 0.0, 30.0])  # receiving vehicle
    bs = np.array([-60.0, 80.0, 20.0])
    m = np.array([25.0, 5.0, 1.6, 8.0, 2.0, 0.0, 0.0])  # the VS: antenna, velocity (heading atan2(2, 8))
    P = np.diag([0.01, 0.01, 0.01, 1.0, 1.0, 0.01, 0.01])
    p = _point(m[:3], math.atan2(2.0, 8.0), bs, s[:3])
    z = measure(s, p, int(Bounce.SCATTER), bs)
    R = np.diag([0.1, 0.01, 0.01, 0.01, 0.01]) ** 2
    m_body, _, ll_body = kalman_update(m, P, z, R, s, int(Bounce.SCATTER), bs, body=BODY)
    m_point, _, ll_point = kalman_update(m, P, z, R, s, int(Bounce.SCATTER), bs)
    assert np.linalg.norm(m_body[:3] - m[:3]) < 0.02
    assert np.linalg.norm(m_point[:3] - m[:3]) > 0.1
    assert ll_body > ll_point + 10


def test_auto_body_model_follows_the_path_source():
    """``vs_body_model = "auto"`` (the default): the body on a traced source, the point on the analytic one
    (its VS paths are point scatterers) and on paths of unknown source; the paper presets pin the point."""
    scn = load_preset("street")
    assert scn.filter.vs_body_model == "auto"
    for source, model in (("sionna", "ellipsoid"), ("analytic", "point"), (None, "point")):
        got, note = resolve_vs_body(scn, source)
        assert got.filter.vs_body_model == model and note.startswith(f"{model} (auto")
        assert (vs_body(got) is not None) == (model == "ellipsoid")
    fixed = with_overrides(scn, ["filter.vs_body_model=point"])
    assert resolve_vs_body(fixed, "sionna") == (fixed, "point")
    for preset in ("paper", "twc2020"):
        assert resolve_vs_body(load_preset(preset), "sionna")[0].filter.vs_body_model == "point"


def _births(scn, points, u=(0.0, 0.0, 1.6)):
    from mmslam.slam.specs.landmarks import VS_SPEC, birth_vs

    states = np.array([[*u, 0.0, 10.0, 0.0, 30.0]])
    mean = np.asarray(points, float)[None]
    cov = np.broadcast_to(np.eye(3) * 0.01, mean.shape + (3,)).copy()
    born = birth_vs(states, (mean, cov, np.ones(mean.shape[:2], bool)), VS_SPEC, scn,
                    lambda up, x, t: np.ones(np.shape(x)[:-1]))
    return born.m[0, :, 0:3][born.mask[0]], born.P[0][born.mask[0]]


def test_vs_births_only_where_a_car_can_be():
    """A VS birth needs its bounce point within ``filter.vs_birth_height`` (3 m) of the receiving antenna's height:
    a bounce on a car 20 m away at 1.0 m is born, the 9 m high specular point of a wall reflection is not;
    without the gate (the paper's 1e4 m) both are."""
    scn = with_overrides(load_preset("street"), ["filter.vs_body_model=point"])
    pts = [[20.0, 0.0, 1.0], [0.0, 25.0, 9.0], [-30.0, 5.0, -1.2]]
    m, _ = _births(scn, pts)
    np.testing.assert_allclose(m, np.array(pts)[[0, 2]])
    m, _ = _births(with_overrides(scn, ["filter.vs_birth_height=10000"]), pts)
    np.testing.assert_allclose(m, pts)


def test_vs_birth_is_placed_at_the_antenna_behind_the_bounce():
    """With the body, a birth from a bounce on the car is moved from the bounce point towards the car's antenna:
    over three headings (front, oblique, side) it lands at less than half the bounce's offset on average (the
    heading is unknown at birth: the body is averaged over headings), and (length - width) / 4 = 0.675 m is added
    to its horizontal standard deviation."""
    scn = with_overrides(load_preset("street"), ["filter.vs_body_model=ellipsoid"])
    bs = np.asarray(scn.bs_array, float)
    u = np.array([0.0, 0.0, 1.6])
    x = np.array([18.0, 9.0, 1.6])
    err, off = [], []
    for heading in (0.0, 0.7, 1.6):
        p = _point(x, heading, bs, u)
        m, P = _births(scn, [p], tuple(u))
        err.append(np.linalg.norm(m[0] - x))
        off.append(np.linalg.norm(p - x))
        assert P[0][0, 0] == pytest.approx(0.01 + 0.675 ** 2) and P[0][2, 2] == pytest.approx(0.01)
    assert min(off) > 1.5 and np.mean(err) < 0.5 * np.mean(off)


def test_vs_on_road_removes_only_nearby_gaussians_off_the_road_band():
    """The prediction's road gate (:func:`vs_on_road`), by hand: per particle, a VS Gaussian within
    ``sensor.fov_range`` (50 m, horizontally) whose antenna height differs from the particle's by more than
    ``filter.vs_birth_height`` (3 m) is removed (weight 0, mean 0, covariance I); one farther away, one on the
    band and the dead slots stay as they are; the input map is not written."""
    from mmslam.slam.core.gm import GM
    from mmslam.slam.specs.vehicle_body import vs_on_road

    scn = load_preset("street")
    assert scn.sensor.fov_range == 50.0 and scn.filter.vs_birth_height == 3.0
    states = np.zeros((2, 7))
    states[:, 2] = [1.6, 10.0]  # particle 1 is (as if) on a bridge 8.4 m higher
    m = np.zeros((2, 4, 7))
    m[:, :, 0:3] = [[20.0, 0.0, 1.2], [10.0, 5.0, 8.0], [80.0, 0.0, 9.0], [5.0, 5.0, 1.6]]
    w = np.full((2, 4), 0.7)
    mask = np.array([[True, True, True, False], [True, True, True, True]])
    g = GM(w, m, np.broadcast_to(np.eye(7) * 2.0, (2, 4, 7, 7)).copy(), mask)
    before = g.copy()
    out = vs_on_road(g, states, scn)
    for a in ("w", "m", "P", "mask"):
        np.testing.assert_array_equal(getattr(g, a), getattr(before, a))
    # particle 0 (z 1.6): slot 1 (8 m up, 11 m away) goes; slot 2 (9 m up but 80 m away) stays
    # particle 1 (z 10): slot 0 (8.8 m below) and slot 3 (8.4 m below) go; slot 1 (2 m below) stays
    np.testing.assert_array_equal(out.mask, [[True, False, True, False], [False, True, True, False]])
    gone = mask & ~out.mask
    assert np.all(out.w[gone] == 0) and np.all(out.m[gone] == 0) and np.all(out.P[gone] == np.eye(7))
    np.testing.assert_array_equal(out.w[out.mask], w[out.mask])
    high = with_overrides(scn, ["filter.vs_birth_height=10000"])
    assert vs_on_road(g, states, high) is g  # no gate: the same map


def test_vs_on_road_keeps_another_cars_own_estimate_off_the_band():
    """Another car's own estimate (its :func:`ego_label`, downlinked from the fused VS map) is a car wherever it
    stands: 8 m above the particle on a hill, 20 m away, it stays, while a Gaussian the car bore there (a birth label)
    and one without a label go; labels of vehicles 0 and 5 both count, a birth label of vehicle 5 does not."""
    from mmslam.slam.core.gm import GM, LABEL_BITS, NO_LABEL, ego_label, is_ego_label
    from mmslam.slam.specs.vehicle_body import vs_on_road

    assert is_ego_label(np.array([ego_label(0), ego_label(5), 5 << LABEL_BITS, (5 << LABEL_BITS) + 7, NO_LABEL, 0])
                        ).tolist() == [True, True, False, False, False, False]
    scn = load_preset("street")
    states = np.zeros((1, 7))
    states[0, 2] = 1.6
    m = np.zeros((1, 4, 7))
    m[0, :, 0:3] = [[20.0, 0.0, 9.6], [0.0, 20.0, 9.6], [-20.0, 0.0, 9.6], [14.0, 14.0, 9.6]]
    label = np.array([[ego_label(5), (5 << LABEL_BITS) + 3, NO_LABEL, ego_label(0)]], np.int64)
    g = GM(np.full((1, 4), 0.9), m, np.broadcast_to(np.eye(7), (1, 4, 7, 7)).copy(), np.ones((1, 4), bool),
           label=label)
    out = vs_on_road(g, states, scn)
    np.testing.assert_array_equal(out.mask, [[True, False, False, True]])
    np.testing.assert_array_equal(out.m[0, [0, 3]], m[0, [0, 3]])
    np.testing.assert_array_equal(out.label, [[ego_label(5), NO_LABEL, NO_LABEL, ego_label(0)]])  # removed: no identity
    np.testing.assert_array_equal(g.label, label)  # the input is not written
    # without labels (fusion.average_by_label off) no Gaussian is known as a car's own, and with
    # filter.vs_keep_cars off none is kept as one: all four go
    assert not vs_on_road(GM(g.w, g.m, g.P, g.mask), states, scn).mask.any()
    assert not vs_on_road(g, states, with_overrides(scn, ["filter.vs_keep_cars=false"])).mask.any()
