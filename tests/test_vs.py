"""Tests of slam/models/vs.py: CT prediction of VS Gaussians, birth mean / covariance."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mmslam.slam.models.dynamics import vs_ct
from mmslam.slam.core.gm import GM, empty
from mmslam.slam.models.vs import predict_vs, vs_birth_covariance, vs_birth_mean

Q_STD = np.array([1, 1, 0.1, 3, 3, 0.1, 0.05])
DITHER = np.array([9, 9, 0.09, 5, 5, 0.09, 0.18])


def _single(m, P, w=0.5):
    return GM(np.array([w]), np.asarray(m, float)[None], np.asarray(P, float)[None], np.array([True]))


def test_zero_turn_is_constant_velocity():
    dt = 0.5
    m = np.array([1.0, 2.0, 3.0, 4.0, -2.0, 0.5, 0.0])
    P0 = np.diag([1.0, 2.0, 0.5, 3.0, 4.0, 0.2, 1e-6])
    out = predict_vs(_single(m, P0), dt, 0.99, np.zeros(7), None)
    np.testing.assert_allclose(out.m[0], [1 + 2.0, 2 - 1.0, 3 + 0.25, 4, -2, 0.5, 0], atol=1e-12)
    F = np.eye(7)
    F[0, 3] = F[1, 4] = F[2, 5] = dt
    # with xi = 0 the Jacobian adds the turn-rate column: d x'/d xi = -dt^2/2 vy, d y'/d xi = dt^2/2 vx,
    # d vx'/d xi = -dt vy, d vy'/d xi = dt vx
    F[0, 6], F[1, 6], F[3, 6], F[4, 6] = -dt**2 / 2 * -2.0, dt**2 / 2 * 4.0, -dt * -2.0, dt * 4.0
    np.testing.assert_allclose(out.P[0], F @ P0 @ F.T, atol=1e-12)
    np.testing.assert_allclose(out.w, [0.5 * 0.99])


def test_covariance_matches_finite_difference_jacobian():
    dt = 0.5
    m = np.array([10.0, -5.0, 1.0, 6.0, 3.0, 0.2, 0.4])
    rng = np.random.default_rng(2)
    A = rng.standard_normal((7, 7))
    P0 = A @ A.T + np.eye(7)
    Jfd = np.empty((7, 7))
    h = 1e-6
    for k in range(7):
        e = np.zeros(7)
        e[k] = h
        Jfd[:, k] = (vs_ct(m + e, dt) - vs_ct(m - e, dt)) / (2 * h)
    out = predict_vs(_single(m, P0), dt, 1.0, Q_STD, DITHER)
    expected = Jfd @ P0 @ Jfd.T + np.diag(Q_STD**2) + np.diag(DITHER)
    np.testing.assert_allclose(out.P[0], expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(out.m[0], vs_ct(m, dt))


def test_quarter_turn_mean():
    # turn rate pi/2 rad/s for 1 s: velocity (1, 0) rotates to (0, 1); position x + 2/pi, y + 2/pi
    m = np.array([0, 0, 0, 1.0, 0, 0, math.pi / 2])
    out = predict_vs(_single(m, np.eye(7)), 1.0, 1.0, np.zeros(7), None)
    np.testing.assert_allclose(out.m[0], [2 / math.pi, 2 / math.pi, 0, 0, 1, 0, math.pi / 2], atol=1e-12)


def test_batched_masked_and_spd():
    rng = np.random.default_rng(0)
    B, Q = (3, 2), 4
    g = empty(B, Q, 7)
    g.mask[..., :3] = True
    g.w[..., :3] = rng.uniform(0.1, 1, B + (3,))
    g.m[..., :3, :] = rng.standard_normal(B + (3, 7))
    A = rng.standard_normal(B + (3, 7, 7))
    g.P[..., :3, :, :] = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(7)
    out = predict_vs(g, 0.5, 0.99, Q_STD, DITHER)
    assert out.w.shape == B + (Q,)
    np.testing.assert_array_equal(out.mask, g.mask)
    assert np.all(out.w[..., 3] == 0) and np.all(out.m[..., 3, :] == 0)
    np.testing.assert_array_equal(out.P[..., 3, :, :], np.broadcast_to(np.eye(7), B + (7, 7)))
    np.testing.assert_allclose(out.P, np.swapaxes(out.P, -1, -2))
    assert np.all(np.linalg.eigvalsh(out.P[out.mask]) > 0)
    # each batch member equals a single-mixture prediction
    one = predict_vs(GM(g.w[1, 0], g.m[1, 0], g.P[1, 0], g.mask[1, 0]), 0.5, 0.99, Q_STD, DITHER)
    np.testing.assert_allclose(out.P[1, 0], one.P)
    np.testing.assert_allclose(out.m[1, 0], one.m)


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        predict_vs(empty((), 2, 3), 0.5, 0.99, Q_STD, None)
    with pytest.raises(ValueError):
        predict_vs(empty((), 2, 7), 0.5, 0.99, Q_STD[:3], None)


def test_birth_mean_and_covariance():
    pos = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    mu = vs_birth_mean(pos)
    np.testing.assert_array_equal(mu[:, :3], pos)
    np.testing.assert_array_equal(mu[:, 3:], 0.0)
    assert vs_birth_mean(pos, turn_mean=0.3)[0, 6] == 0.3
    Pp = np.stack([np.diag([1.0, 2.0, 3.0]), np.eye(3) * 0.5])
    Pp[0, 0, 1] = Pp[0, 1, 0] = 0.2
    C = vs_birth_covariance(Pp, np.array([100, 100, 0.09]), math.pi / 2)
    assert C.shape == (2, 7, 7)
    np.testing.assert_array_equal(C[:, :3, :3], Pp)
    np.testing.assert_array_equal(C[0, 3:6, 3:6], np.diag([100, 100, 0.09]))
    assert C[0, 6, 6] == pytest.approx((math.pi / 2) ** 2)
    assert np.all(C[:, :3, 3:] == 0) and np.all(C[:, 3:6, 6] == 0)
    assert np.all(np.linalg.eigvalsh(C) > 0)


@pytest.mark.parametrize("scope", ["all", "newborn"])
@pytest.mark.parametrize("n_old", [0, 3])
def test_vs_map_prediction_equals_the_concatenated_predictions(scope, n_old):
    """predict_vs_map writes the predicted map and its predicted births side by side: bit for bit the
    concatenation of the two predictions (old Gaussians dithered only with scope 'all')."""
    from types import SimpleNamespace

    from mmslam.slam.core.gm import concat
    from mmslam.slam.specs.landmarks import predict_vs_map

    rng = np.random.default_rng(9)

    def rand_gm(q):
        m = rng.normal(size=(4, q, 7)) * [10, 10, 1, 5, 5, 0.1, 0.3]
        X = rng.normal(size=(4, q, 7, 7))
        mask = rng.random((4, q)) < 0.7
        P = np.where(mask[..., None, None], X @ np.swapaxes(X, -1, -2) + np.eye(7), np.eye(7))
        return GM(np.where(mask, rng.random((4, q)), 0.0), np.where(mask[..., None], m, 0.0), P, mask)

    old, born = rand_gm(n_old), rand_gm(5)
    fp = SimpleNamespace(vs_process_std=tuple(Q_STD), vs_dither=tuple(DITHER), vs_dither_scope=scope, p_survival=0.99)
    scn = SimpleNamespace(filter=fp, dt=0.5)
    out = predict_vs_map(old, born, scn)
    ref = concat(predict_vs(old, 0.5, 0.99, Q_STD, DITHER if scope == "all" else None),
                 predict_vs(born, 0.5, 0.99, Q_STD, DITHER))
    for a, b in ((out.w, ref.w), (out.m, ref.m), (out.P, ref.P), (out.mask, ref.mask)):
        assert np.array_equal(a, b)
    assert out.pd_beta is None
    alone = predict_vs_map(old, None, scn)  # no births: the map alone
    assert alone.capacity == n_old and np.array_equal(alone.P, ref.P[:, :n_old])


def test_predict_vs_into_rejects_an_out_it_would_overrun_or_copy():
    """The compiled loop does not check bounds: an ``out`` too small for ``off + Q`` slots, of another
    batch shape or not contiguous (its reshape a copy: the prediction lost) is a ValueError, and
    nothing is written past it."""
    from mmslam.slam.models.vs import predict_vs_into, process_noise

    g = empty((2,), 3, 7)
    g.mask[:] = True
    g.w[:] = 0.5
    add = process_noise(Q_STD, None)
    ok = empty((2,), 5, 7)
    predict_vs_into(g, 0.1, 0.9, add, ok, 2)  # slots 2..4 of 5: fits
    np.testing.assert_array_equal(ok.w, [[0, 0, 0.45, 0.45, 0.45]] * 2)
    for bad_out, off in [(empty((2,), 4, 7), 2), (empty((2,), 5, 7), -1), (empty((3,), 5, 7), 0),
                         (empty((2,), 5, 3), 0)]:
        with pytest.raises(ValueError, match="predict_vs_into"):
            predict_vs_into(g, 0.1, 0.9, add, bad_out, off)
    strided = empty((2,), 10, 7)
    view = GM(strided.w[:, ::2], strided.m[:, ::2], strided.P[:, ::2], strided.mask[:, ::2])
    with pytest.raises(ValueError, match="predict_vs_into"):
        predict_vs_into(g, 0.1, 0.9, add, view, 0)
    with pytest.raises(ValueError, match="predict_vs_into"):
        predict_vs_into(g, 0.1, 0.9, np.eye(3), empty((2,), 3, 7), 0)
