"""Motion and measurement models against hand-computed geometry and finite differences."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mmslam.slam.models.dynamics import vehicle_ct, vs_ct, vs_ct_jacobian, wrap_angle
from mmslam.slam.models.measurement import BS, SP, VA, channel_params, measure, mirror_point, residual
from mmslam.model import Bounce


def test_vehicle_ct_straight_and_turn():
    s = np.array([1.0, 2.0, 0.5, 0.3, 10.0, 0.0, 5.0])
    n = vehicle_ct(s, 0.5)
    assert np.allclose(n[:2], [1 + 5 * math.cos(0.3), 2 + 5 * math.sin(0.3)])
    # quarter circle of radius 10 about the origin, counter-clockwise
    s = np.array([10.0, 0.0, 0.0, math.pi / 2, 10.0, 1.0, 0.0])
    n = vehicle_ct(s, math.pi / 2)
    assert np.allclose(n[:2], [0.0, 10.0], atol=1e-12) and n[3] == pytest.approx(math.pi)
    # continuity at xi -> 0
    a = vehicle_ct(np.array([0, 0, 0, 0.2, 10, 1e-12, 0.0]), 0.5)
    b = vehicle_ct(np.array([0, 0, 0, 0.2, 10, 0.0, 0.0]), 0.5)
    assert np.allclose(a, b, atol=1e-10)


def test_vs_ct_zero_turn_is_constant_velocity():
    t = np.array([1.0, -2.0, 0.5, 3.0, 4.0, 0.1, 0.0])
    n = vs_ct(t, 0.5)
    assert np.allclose(n, [2.5, 0.0, 0.55, 3.0, 4.0, 0.1, 0.0])


def test_vs_ct_full_circle_returns():
    w = 0.3
    t = np.array([5.0, 1.0, 0.0, 2.0, -1.0, 0.0, w])
    dt = 2 * math.pi / w / 40
    x = t.copy()
    for _ in range(40):
        x = vs_ct(x, dt)
    assert np.allclose(x, t, atol=1e-9)


@pytest.mark.parametrize("w", [0.0, 1e-7, 0.4, -1.3])
def test_vs_ct_jacobian_finite_difference(w):
    t = np.array([5.0, 1.0, 2.0, 2.0, -1.0, 0.3, w])
    J = vs_ct_jacobian(t, 0.5)
    h = 1e-6
    Jn = np.stack([(vs_ct(t + h * e, 0.5) - vs_ct(t - h * e, 0.5)) / (2 * h) for e in np.eye(7)], axis=1)
    assert np.allclose(J, Jn, atol=1e-6)


def test_wrap_angle_range():
    a = wrap_angle(np.array([math.pi, -math.pi, 3 * math.pi, 0.1 - 2 * math.pi]))
    assert np.allclose(a, [math.pi, math.pi, math.pi, 0.1])


def test_channel_params_los_hand_computed():
    b = np.array([0.0, 0.0, 40.0])
    u = np.array([30.0, 40.0, 0.0])
    g = channel_params(u, None, Bounce.DIRECT, b)
    d = math.sqrt(30**2 + 40**2 + 40**2)
    assert g[0] == pytest.approx(d)
    assert g[1] == pytest.approx(math.atan2(40, 30)) and g[2] == pytest.approx(-math.asin(40 / d))
    assert g[3] == pytest.approx(math.atan2(-40, -30)) and g[4] == pytest.approx(math.asin(40 / d))


def test_channel_params_va_incidence_point_on_wall():
    b = np.array([0.0, 0.0, 40.0])
    v = mirror_point(b, np.array([100.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]))
    assert np.allclose(v, [200, 0, 40])
    u = np.array([60.0, 20.0, 0.0])
    g = channel_params(u, v, Bounce.MIRROR, b)
    assert g[0] == pytest.approx(np.linalg.norm(v - u))
    # the incidence point p is where segment v->u crosses x = 100; AOD points b -> p
    lam = (100 - v[0]) / (u[0] - v[0])
    p = v + lam * (u - v)
    d = p - b
    assert g[1] == pytest.approx(math.atan2(d[1], d[0]))
    assert g[2] == pytest.approx(math.asin(d[2] / np.linalg.norm(d)))
    # path length via the incidence point equals the image distance
    assert np.linalg.norm(p - b) + np.linalg.norm(u - p) == pytest.approx(g[0])


def test_measure_scatter_body_frame():
    b = np.array([0.0, 0.0, 40.0])
    s = np.array([55.0, 55.0, 10.0])
    st = np.array([40.0, 50.0, 0.0, 1.0, 0, 0, 300.0])
    z = measure(st, s, Bounce.SCATTER, b)
    assert z[0] == pytest.approx(np.linalg.norm(s - b) + np.linalg.norm(s - st[:3]) + 300.0)
    assert z[3] == pytest.approx(wrap_angle(math.atan2(5, 15) - 1.0))


def test_residual_wraps_azimuth():
    r = residual(np.array([0, math.pi - 0.01, 0, -math.pi + 0.01, 0]), np.array([0, -math.pi + 0.01, 0, math.pi - 0.01, 0]))
    assert np.allclose(r, [0, -0.02, 0, 0.02, 0])


def test_vehicle_ct_with_known_inputs_equals_the_states_carrying_them():
    """``vehicle_ct(s, dt, speed, turn_rate)`` (the turn terms once, for the one turn rate) gives the bits
    of ``vehicle_ct`` of the states with ``zeta, xi`` set to the inputs; one input alone is refused."""
    rng = np.random.default_rng(2)
    s = rng.normal(size=(50, 7)) * [50, 50, 1, 3, 20, 0.3, 200]
    for v, w in ((22.22, math.pi / 10), (5.0, 0.0), (5.0, -3e-6)):
        ref = s.copy()
        ref[:, 4], ref[:, 5] = v, w
        assert np.array_equal(vehicle_ct(s, 0.5, v, w), vehicle_ct(ref, 0.5))
    with pytest.raises(ValueError, match="both"):
        vehicle_ct(s, 0.5, 1.0)


@pytest.mark.parametrize("shape", [(2, 6), (2, 8), (7, 3)])
def test_vehicle_ct_rejects_states_without_seven_components(shape):
    """The CT model reads columns 3-5 of a ``(..., 7)`` state: any other length is a one-line error
    (the in-place version returned a (2, 6) or (2, 8) array silently)."""
    from mmslam.model import vehicle_ct

    with pytest.raises(ValueError, match="expected \\(..., 7\\)"):
        vehicle_ct(np.ones(shape), 0.1)


def test_vehicle_ct_equals_the_textbook_coordinated_turn():
    """An independent reference (paper eq. (1) written directly, the straight-line limit for xi = 0):
    ``x' = x + zeta/xi (sin(a + xi dt) - sin a)``, ``y' = y + zeta/xi (cos a - cos(a + xi dt))``,
    ``a' = a + xi dt``, other components carried; for both the per-state and the known-input forms."""
    rng = np.random.default_rng(7)
    s = rng.normal(size=(40, 7)) * [50, 50, 1, 3, 20, 0.3, 200]
    s[:5, 5] = 0.0
    dt = 0.5

    def ref(st):
        out = st.copy()
        for r in out:
            a, v, w = r[3], r[4], r[5]
            if w == 0.0:
                r[0] += v * dt * math.cos(a)
                r[1] += v * dt * math.sin(a)
            else:
                r[0] += v / w * (math.sin(a + w * dt) - math.sin(a))
                r[1] += v / w * (math.cos(a) - math.cos(a + w * dt))
            r[3] = a + w * dt
        return out

    np.testing.assert_allclose(vehicle_ct(s, dt), ref(s), rtol=1e-9, atol=1e-9)
    known = s.copy()
    known[:, 4], known[:, 5] = 12.0, 0.2
    np.testing.assert_allclose(vehicle_ct(s, dt, 12.0, 0.2), ref(known), rtol=1e-9, atol=1e-9)
