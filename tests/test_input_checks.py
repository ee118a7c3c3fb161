"""Bad input to the public kernel-level API gives an error naming the problem (numba does not
bounds-check: without these checks a wrong shape read past an array and returned a number)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mmslam.errors import MmslamError
from mmslam.model import SP, VA, Bounce
from mmslam.scenes.scenario import load_preset
from mmslam.slam.specs import landmarks as L
from mmslam.slam.phd.ckf import innovate
from mmslam.slam.filter.local_filter import LocalFilter
from mmslam.slam.models.measurement import channel_params, measure
from mmslam.slam.specs.landmarks import landmark_type

BS_POS = np.array([0.0, 0.0, 10.0])
STATE = np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5])


@pytest.mark.parametrize("change, match", [
    (dict(geometry=7), "not a path geometry"),
    (dict(geometry=Bounce.DIRECT), "MIRROR or SCATTER"),
    (dict(state_dim=2), "at least 3"),
    (dict(code=9.5), "must be an integer"),
])
def test_register_rejects_a_spec_the_kernels_cannot_run(change, match):
    spec = dataclasses.replace(L.landmark_type(SP), **{"name": "BAD", "code": 11, **change})
    with pytest.raises(MmslamError, match=match):
        L.register_landmark_type(spec)
    assert "BAD" not in [t.name for t in L.landmark_types()]


def test_measurement_model_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="landmark positions"):
        channel_params(STATE[:3], None, Bounce.SCATTER, BS_POS)  # was: the BS silently used as the scatter point
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 7\)"):
        measure(STATE[:3], np.array([30.0, 0.0, 2.0]), Bounce.SCATTER, BS_POS)  # was: read s[3], s[6] past the end
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 3\)"):
        channel_params(STATE[:3], np.array([30.0, 0.0]), Bounce.MIRROR, BS_POS)
    # the valid call still works and agrees with the hand-computed TOA of a single bounce
    lm = np.array([30.0, 0.0, 2.0])
    toa = channel_params(STATE[:3], lm, Bounce.SCATTER, BS_POS)[0]
    assert toa == pytest.approx(np.linalg.norm(lm - BS_POS) + np.linalg.norm(lm - STATE[:3]), rel=1e-12)


def test_innovate_rejects_wrong_shapes():
    m, P = np.zeros((2, 3)) + 30.0, np.broadcast_to(np.eye(3), (2, 3, 3)).copy()
    Z, R = np.zeros((1, 5)), np.eye(5)
    with pytest.raises(ValueError, match="expected"):
        innovate(m, P, np.zeros((2, 3)), int(Bounce.SCATTER), BS_POS, Z, R, "test")  # states (N, 3)
    with pytest.raises(ValueError, match="expected"):
        innovate(m[:, :2], P[:, :2, :2], np.zeros((2, 7)), int(Bounce.SCATTER), BS_POS, Z, R, "test")  # d = 2



def _pd09(u, x, t):
    """A constant p_D of 0.9 for every Gaussian (the shape of the vehicle positions without the last axis)."""
    return np.full(np.shape(u)[:-1], 0.9)


def _sp_case(pd_beta: bool = False):
    """Two particles with three SP Gaussians at (30, 30, 30) m, two measurements, R = I, states 0:
    ``(g, Z, R, states)`` for the correction's shape checks."""
    from mmslam.slam.core.gm import GM

    P_, Q = 2, 3
    g = GM(np.ones((P_, Q)), np.zeros((P_, Q, 3)) + 30.0, np.broadcast_to(np.eye(3), (P_, Q, 3, 3)).copy(),
           np.ones((P_, Q), bool), np.full((P_, Q, 2), 2.0) if pd_beta else None)
    return g, np.zeros((2, 5)), np.eye(5), np.zeros((P_, 7))

def test_type_terms_rejects_wrong_shapes_before_its_kernel():
    """The compiled correction reads states[p] and P[p, q] unchecked: a mismatched shape is a
    ValueError naming the stage, never an out-of-bounds read (particle count, state length, d = 2,
    covariance shape, one R per measurement)."""
    from mmslam.slam.core.gm import GM
    from mmslam.slam.phd.gmphd import type_terms

    pd_fn = _pd09
    P_, Q = 2, 3
    g, Z, R, s = _sp_case()
    assert type_terms(g, landmark_type(SP), s, Z, R, BS_POS, pd_fn).logq.shape == (P_, Q, 2)
    for states in (np.zeros((P_ + 1, 7)), np.zeros((1, 7)), np.zeros((P_, 3))):
        with pytest.raises(ValueError, match="SP correction: shapes .* expected"):
            type_terms(g, landmark_type(SP), states, Z, R, BS_POS, pd_fn)
    bad = [GM(g.w, g.m[..., :2], g.P[..., :2, :2], g.mask), GM(g.w, g.m, g.P[:, :2], g.mask)]
    for b in bad:
        with pytest.raises(ValueError, match="SP correction: shapes .* expected"):
            type_terms(b, landmark_type(SP), s, Z, R, BS_POS, pd_fn)
    with pytest.raises(ValueError, match=r"R has shape \(3, 5, 5\); expected \(5, 5\) or \(2, 5, 5\)"):
        type_terms(g, landmark_type(SP), s, Z, np.stack([R] * 3), BS_POS, pd_fn)


def test_type_terms_rejects_a_pd_beta_of_another_shape():
    """Review finding: the correction kernel reads pd_beta[p, q] unchecked; a Beta array that
    NumPy broadcasts in expected_pd ((P, 1, 2), (1, Q, 2)) gave the corrected components Beta
    parameters read past the array (denormal garbage). Now a ValueError naming the stage."""
    from mmslam.slam.phd.gmphd import type_terms

    pd_fn = _pd09
    P_, Q = 2, 3
    g, Z, R, s = _sp_case(pd_beta=True)
    assert type_terms(g, landmark_type(SP), s, Z, R, BS_POS, pd_fn).logq.shape == (P_, Q, 2)
    for beta in (np.full((P_, 1, 2), 2.0), np.full((1, Q, 2), 2.0), np.full((P_, Q, 3), 2.0), np.full(2, 2.0)):
        with pytest.raises(ValueError, match=r"SP correction: shapes .* pd_beta .* expected .*\(P, Q, 2\)"):
            type_terms(dataclasses.replace(g, pd_beta=beta), landmark_type(SP), s, Z, R, BS_POS, pd_fn)


def test_bs_logterm_rejects_wrong_shapes_before_its_kernel():
    """Review finding: gmphd.correct computes the BS term first, and its compiled loop read R[j],
    states[p] and bs unchecked: one R per measurement for too few measurements returned numbers
    read past the array (later hidden by type_terms' ValueError). Now a ValueError up front."""
    from mmslam.slam.phd.gmphd import bs_logterm

    R = np.diag([0.3, 0.03, 0.03, 0.03, 0.03]) ** 2
    s = np.array([[20.0, 20.0, 0.0, 0.5, 10.0, 0.0, 1.0]] * 2)
    Z = np.stack([measure(s[0], np.array([40.0, 50.0, 2.0]), Bounce.MIRROR, BS_POS)] * 3)
    p = np.full(2, 0.9)
    ok = bs_logterm(s, Z, R, BS_POS, p)
    np.testing.assert_array_equal(bs_logterm(s, Z, np.stack([R] * 3), BS_POS, p), ok)
    with pytest.raises(ValueError, match=r"R has shape \(2, 5, 5\); expected \(5, 5\) or \(3, 5, 5\)"):
        bs_logterm(s, Z, np.stack([R] * 2), BS_POS, p)
    for bad in ((s[:, :6], Z, BS_POS), (s, Z[:, :4], BS_POS), (s, Z, BS_POS[:2])):
        with pytest.raises(ValueError, match="BS likelihood: shapes"):
            bs_logterm(*bad[:2], R, bad[2], p)


def test_corrected_gm_rejects_a_log_psi_of_another_shape():
    """Review finding: the corrected-components kernel reads logpsi[p, j] unchecked; a (P, J')
    log psi with J' < J gave weights from past the array. Now a ValueError."""
    from mmslam.slam.phd.gmphd import corrected_gm, log_psi, type_terms

    pd_fn = _pd09
    P_, Q = 2, 3
    g, Z, R, s = _sp_case()
    tc = type_terms(g, landmark_type(SP), s, Z, R, BS_POS, pd_fn)
    lp = log_psi([tc], None, np.log(1e-5), (P_, 2))
    assert corrected_gm(tc, Z, lp).capacity == Q * 3
    for bad in (lp[:, :1], lp[:1], lp[..., None]):
        with pytest.raises(ValueError, match=r"logpsi has shape .*; expected \(2, 2\)"):
            corrected_gm(tc, Z, bad)


def test_step_keeps_its_own_copy_of_the_measurements():
    """The measurements are kept for the next step's births: a caller reusing its buffer must not
    change them."""
    scn = load_preset("paper")
    f = LocalFilter(scn, "baseline", 5, STATE, np.diag([0.1, 1e-4, 1e-4, 1e-4, 1e-4]), 1e-3,
                    lambda u, x, t: np.full(np.shape(u)[:-1], 0.9), np.random.default_rng(0))
    Z = measure(STATE, np.array([[30.0, 0.0, 2.0], [10.0, 30.0, 3.0]]), Bounce.SCATTER, scn.bs_array)
    f.step(Z)
    kept = Z.copy()
    Z[:] = 0.0
    np.testing.assert_array_equal(f._prev_Z, kept)
