"""The PHD-mass invariant the filter checks at every correction (issue 10).

Per particle, type and step: ``sum_q w_q(corrected) <= sum_q w_q(predicted) + J``. The check
(:func:`mmslam.slam.phd.gmphd.check_phd_mass`, called by :func:`mmslam.slam.phd.gmphd.correct`) must stay silent on
normal runs and fail loudly on the weight corruption of the old ``_logsumexp_slots``.
"""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.analytic import AnalyticSource
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import true_trajectories
from mmslam.slam.phd import gmphd
from mmslam.slam.filter import run_filter
from mmslam.slam.core.gm import GM
from mmslam.slam.models.measurement import VA, VS

STEPS = 8
_LOGSUMEXP_SLOTS = gmphd._logsumexp_slots  # the fixed kernel (before any monkeypatch)


@pytest.fixture(scope="module")
def paper8():
    """The analytic `paper` preset, truth and paths of its first ``STEPS`` steps."""
    scn = load_preset("paper")
    states = true_trajectories(scn)[:STEPS]
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(STEPS)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    return scn, states, paths


def _old_logsumexp_slots(logq: np.ndarray) -> np.ndarray:
    """``_logsumexp_slots`` as it was before commit 48e7f9d: the same return value, but for
    ``J >= 2`` its slot-first buffer ``np.ascontiguousarray(logq.transpose(1, 0, 2))`` was a *view*
    of ``logq`` when ``P == 1`` or ``Q == 1``, and the in-place ``t -= max`` / ``np.exp(t, out=t)``
    rewrote the log-weights that ``corrected_gm`` reads afterwards. Reproduced here as that side
    effect on ``logq``."""
    out = _LOGSUMEXP_SLOTS(logq)
    P_, Q, J = logq.shape
    if J > 1 and (P_ == 1 or Q == 1):
        mx = logq.max(axis=1, keepdims=True)
        logq -= np.where(np.isfinite(mx), mx, 0.0)
        np.exp(logq, out=logq)
    return out


def _gm(w, mask=None) -> GM:
    w = np.asarray(w, float)
    mask = np.ones(w.shape, bool) if mask is None else np.asarray(mask, bool)
    return GM(w, np.zeros(w.shape + (3,)), np.broadcast_to(np.eye(3), w.shape + (3, 3)).copy(), mask)


def test_check_phd_mass_bound_by_hand():
    pred = _gm([[0.5, 1.0, 7.0], [0.2, 0.0, 0.0]], mask=[[True, True, False], [True, False, False]])  # 1.5, 0.2
    ok = _gm([[1.5, 2.0, 0.0, 9.0], [2.2, 0.0, 0.0, 0.0]], mask=[[True, True, True, False], [True, True, True, True]])
    gmphd.check_phd_mass(pred, ok, 2, "VA", 4)  # 3.5 <= 1.5 + 2 and 2.2 <= 0.2 + 2: equality is allowed
    bad = _gm([[1.5, 2.1, 0.0], [0.1, 0.0, 0.0]])  # 3.6 > 1.5 + 2
    with pytest.raises(FloatingPointError, match=r"VS correction at step 4, particle 0: corrected mass 3\.6 > "
                                                 r"predicted mass 1\.5 \+ 2 measurements"):
        gmphd.check_phd_mass(pred, bad, 2, "VS", 4)
    nan = _gm([[np.nan], [0.0]])
    with pytest.raises(FloatingPointError, match="particle 0: corrected mass nan"):
        gmphd.check_phd_mass(pred, nan, 2, "VA", 0)
    # no measurement: the correction cannot add mass
    with pytest.raises(FloatingPointError, match="particle 1"):
        gmphd.check_phd_mass(pred, _gm([[1.0], [0.3]]), 0, "VA", 0)
    # masses summed by the correction's kernels are used instead of the maps' weights
    gmphd.check_phd_mass(pred, bad, 2, "VS", 4, masses=(np.array([1.5, 0.2]), np.array([3.5, 2.2])))
    with pytest.raises(FloatingPointError, match=r"VA correction at step 3, particle 1: corrected mass 2\.3 > "
                                                 r"predicted mass 0\.2 \+ 2 measurements \(1 of 2 particles\)"):
        gmphd.check_phd_mass(pred, ok, 2, "VA", 3, masses=(np.array([1.5, 0.2]), np.array([3.5, 2.3])))
    with pytest.raises(FloatingPointError, match="particle 1: corrected mass nan"):
        gmphd.check_phd_mass(pred, ok, 2, "VA", 3, masses=(np.array([1.5, 0.2]), np.array([3.5, np.nan])))
    with pytest.raises(FloatingPointError, match="particle 0: corrected mass 3.5 > predicted mass nan"):
        gmphd.check_phd_mass(pred, ok, 2, "VA", 3, masses=(np.array([np.nan, 0.2]), np.array([3.5, 2.2])))


@pytest.mark.parametrize("particles", [20, 1])
def test_invariant_is_checked_and_silent_on_a_normal_run(paper8, particles, monkeypatch):
    scn, states, paths = paper8
    calls = []
    real = gmphd.check_phd_mass

    def spy(pred, corr, J, t, k, masses=None):
        calls.append((t, k, J))
        # the masses the correction's kernels summed == NumPy's sums of the maps, bit for bit
        assert masses is not None
        np.testing.assert_array_equal(masses[0], np.where(pred.mask, pred.w, 0.0).sum(-1))
        np.testing.assert_array_equal(masses[1], np.where(corr.mask, corr.w, 0.0).sum(-1))
        real(pred, corr, J, t, k, masses=masses)

    monkeypatch.setattr(gmphd, "check_phd_mass", spy)  # called by gmphd.correct
    res = run_filter(scn, states, paths, variant="proposed", particles=particles, seed=3, steps=STEPS)
    n_veh = len(scn.vehicles)
    assert len(calls) == n_veh * STEPS * 3  # every vehicle, step and type (VA, SP, VS) was checked
    assert {k for _, k, _ in calls} == set(range(STEPS)) and all(J > 0 for _, _, J in calls)
    assert np.isfinite(res.vehicles["pos_err"]).all()


def test_invariant_fires_on_the_old_logsumexp_slots(paper8, monkeypatch):
    """The old kernel wrote into ``logq`` (P == 1 makes its slot-first copy a view): the check
    stops the run at the first corrupted correction, naming type, step and both masses."""
    scn, states, paths = paper8
    monkeypatch.setattr(gmphd, "_logsumexp_slots", _old_logsumexp_slots)
    with pytest.raises(FloatingPointError, match=r"PHD mass invariant violated in the (VA|SP|VS) correction at "
                                                 r"step \d+, particle 0: corrected mass .* > predicted mass .* \+ \d+ "
                                                 r"measurements"):
        run_filter(scn, states, paths, variant="proposed", particles=1, seed=3, steps=STEPS)


def test_without_the_check_the_old_kernel_corrupts_the_map_silently(paper8, monkeypatch):
    """Why the check exists: with it disabled, the old kernel runs to the end without an error
    while the corrected mass exceeds the bound (weights of ~1/clutter intensity).

    The correction of the old kernel's time computed every posterior mean; the skipped means of
    today's (``gmphd._skip_floors``, NaN-marked) would turn this corruption into a non-finite error
    (next test), so they are switched off here to show what the mass check alone catches."""
    scn, states, paths = paper8
    monkeypatch.setattr(gmphd, "_logsumexp_slots", _old_logsumexp_slots)
    monkeypatch.setattr(gmphd, "_skip_floors", lambda log_clutter, prune: (-np.inf, -np.inf))
    excess = []

    def record(pred, corr, J, t, k, masses=None):
        p = np.where(pred.mask, pred.w, 0.0).sum(-1)
        c = np.where(corr.mask, corr.w, 0.0).sum(-1)
        excess.append(float((c - p - J).max()))

    monkeypatch.setattr(gmphd, "check_phd_mass", record)
    run_filter(scn, states, paths, variant="proposed", particles=1, seed=3, steps=STEPS)
    assert max(excess) > 1.0


def test_a_corrupted_log_weight_never_reads_a_skipped_mean(paper8, monkeypatch):
    """The correction skips the posterior means of the pairs it will prune (``gmphd._skip_floors``);
    such a mean is NaN-marked, not stale memory. If the log-weights are corrupted after the CKF (the
    old kernel, mass check off) so that a skipped pair is kept, the run stops with a non-finite
    error at once instead of carrying whatever the buffer held."""
    scn, states, paths = paper8
    monkeypatch.setattr(gmphd, "_logsumexp_slots", _old_logsumexp_slots)
    monkeypatch.setattr(gmphd, "check_phd_mass", lambda *a, **kw: None)
    with pytest.raises(FloatingPointError, match="non-finite"):
        run_filter(scn, states, paths, variant="proposed", particles=1, seed=3, steps=STEPS)


def test_check_phd_mass_rejects_masses_of_another_shape():
    """``masses`` from the kernels must match the maps' batch: a short corrected-mass array was read past
    its end by the compiled test (and passed); now a one-line ValueError."""
    g = _gm([[0.5, 1.0], [0.2, 0.0], [0.1, 0.1]])  # P = 3
    gmphd.check_phd_mass(g, g, 0, "VA", 0, masses=(np.ones(3), np.ones(3)))  # equal masses: the bound holds
    for bad in ((np.ones(3), np.ones(2)), (np.ones(2), np.ones(2)), (np.ones(3), np.ones((3, 1)))):
        with pytest.raises(ValueError, match="check_phd_mass: masses of shapes"):
            gmphd.check_phd_mass(g, g, 0, "VA", 0, masses=bad)
    with pytest.raises(FloatingPointError, match="particle 2"):
        gmphd.check_phd_mass(g, g, 1, "VA", 0, masses=(np.ones(3), np.array([1.0, 2.0, 2.5])))  # 2.5 > 1 + 1
