"""Model defects of issue 23: each test fails on the code before its fix."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.core.gm import empty
from mmslam.slam.filter import ego_gaussian
from mmslam.slam.models.measurement import measure
from mmslam.slam.phd.ckf import kalman_update
from mmslam.slam.specs.landmarks import VS_SPEC, FusionInput, vs_extent
from mmslam.slam.specs.variants import get_variant


def test_vs_extent_enters_once() -> None:
    """The body extent is added once: in the VS likelihood, not also to the uploaded ego Gaussian.

    Vehicle 2 sees vehicle 1's uploaded ego Gaussian as a VS; the innovation covariance of that
    scatter path must be ``H (P_ego + E) H^T + R`` with the extent ``E`` once (``ckf_update``
    adds it), so the upload must carry ``P_ego`` (the antenna position, the VS state) unchanged.
    """
    scn = with_overrides(load_preset("paper"), ["filter.vs_extent_std=[1.0,0.3]"])
    E = vs_extent(scn)
    assert E is not None and np.allclose(np.diag(E), [1.0, 1.0, 0.09])
    mean = np.array([70.0, 5.0, 0.0, 1.5, 22.0, 0.3, 300.0])
    cov = np.diag([0.04, 0.04, 0.0, 1e-4, 0.0, 0.0, 0.04])
    em, ec = ego_gaussian(mean, cov, scn.filter.vs_process_std)
    ctx = FusionInput(scn, get_variant("proposed"), mean, cov, vehicle=0)
    fuse = VS_SPEC.fusion_operator(get_variant("proposed"))  # fuse_vs of the ego-averaged upload (eq. 11)
    fused, _ = fuse(empty((), 0, 7), empty((), 0, 7), np.zeros(0, bool), ctx)
    live = np.flatnonzero(fused.w > 0)
    assert live.size == 1
    P_up = fused.P[live[0]]
    np.testing.assert_allclose(P_up, ec, rtol=1e-12, atol=1e-15)
    # vehicle 2's likelihood of a path bouncing off vehicle 1: the scatter point's covariance is
    # P_ego + E (E once: the CKF's cubature points of P + E), not P_ego + 2 E
    s = np.array([60.0, 0.0, 0.0, 1.6, 19.0, 0.3, 300.0])
    bs = scn.bs_array
    R = np.diag([0.01, 1e-4, 1e-4, 1e-4, 1e-4])
    z = measure(s, fused.m[live[0], :3] + np.array([0.5, -0.3, 0.2]), VS_SPEC.geometry, bs)
    E7 = np.zeros((7, 7))
    E7[:3, :3] = E
    _, _, ll = kalman_update(fused.m[live[0]], P_up, z, R, s, VS_SPEC.geometry, bs, E)
    _, _, ll_once = kalman_update(em, ec + E7, z, R, s, VS_SPEC.geometry, bs, None)
    _, _, ll_twice = kalman_update(em, ec + 2 * E7, z, R, s, VS_SPEC.geometry, bs, None)
    assert abs(ll - ll_once) < 1e-9 and abs(ll - ll_twice) > 1e-3


def _mimo_ofdm_mean(theta: np.ndarray, nt: int, nr: int, freqs: np.ndarray) -> np.ndarray:
    """Noise-free samples ``(K, nt^2, nr^2)`` of one path: gain ``theta[0] + j theta[1]``, delay
    ``theta[2]`` (s), AOD az / el ``theta[3:5]``, AOA az / el ``theta[5:7]`` (rad); UPAs of
    half-wavelength spacing in the plane normal to broadside, element indices centred."""
    def upa(n: int, az: float, el: float) -> np.ndarray:
        p = np.arange(n) - (n - 1) / 2
        P, Q = np.meshgrid(p, p, indexing="ij")
        return np.exp(1j * np.pi * (P * np.sin(az) * np.cos(el) + Q * np.sin(el))).ravel()

    a = theta[0] + 1j * theta[1]
    f = np.exp(-2j * np.pi * freqs * theta[2])
    return a * f[:, None, None] * np.conj(upa(nt, *theta[3:5]))[None, :, None] * upa(nr, *theta[5:7])[None, None, :]


def test_link_angle_bound_matches_numerical_fisher_information() -> None:
    """``LinkBudget.stds`` against the CRB of a numerical Fisher information (finite differences of
    the MIMO-OFDM path response, complex white noise, unknown complex gain).

    SNR := received energy over all samples / noise variance per sample (what a link budget with
    both array gains computes). The old bound (array gain counted twice) was ``sqrt(2 N)`` too small.
    """
    from mmslam.slam.sim.sensor import SPEED_OF_LIGHT, LinkBudget

    nt, nr, K, B = 3, 4, 64, 400e6
    freqs = (np.arange(K) - (K - 1) / 2) * B / K
    theta = np.array([1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0])
    mu = _mimo_ofdm_mean(theta, nt, nr, freqs)
    snr = 100.0
    sigma2 = float(np.sum(np.abs(mu) ** 2)) / snr
    steps = np.array([1e-6, 1e-6, 1e-13, 1e-6, 1e-6, 1e-6, 1e-6])
    D = np.empty((mu.size, theta.size), complex)
    for i, h in enumerate(steps):
        e = np.zeros_like(theta)
        e[i] = h
        D[:, i] = ((_mimo_ofdm_mean(theta + e, nt, nr, freqs) - _mimo_ofdm_mean(theta - e, nt, nr, freqs)) / (2 * h)).ravel()
    fim = 2.0 / sigma2 * np.real(D.conj().T @ D)
    crb = np.sqrt(np.diag(np.linalg.inv(fim)))
    lb = LinkBudget(tx_array=nt, rx_array=nr, bandwidth_hz=B)
    got = lb.stds(10 * np.log10(snr))
    # K discrete tones: mean f^2 = B^2 (K^2 - 1) / (12 K^2), the bound's B^2 / 12 in the limit
    np.testing.assert_allclose(crb[2] * SPEED_OF_LIGHT * np.sqrt((K * K - 1) / K**2), got[0], rtol=1e-5)
    np.testing.assert_allclose(crb[3:7], got[1:5], rtol=1e-5)


def test_link_snr_is_the_energy_of_the_pilot_symbol_the_estimator_receives() -> None:
    """The link model's SNR of a path equals the received energy of the estimator's noise-free pilots
    (unit noise variance per sample) for the same path: one OFDM symbol of K subcarriers through both
    arrays. Before the fix the link SNR was that of one sample, 10 log10 K (24.1 dB at K = 256) lower."""
    import dataclasses

    from mmslam.scenes.scenario import SensorParams
    from mmslam.slam.sim.estimated_sensor import PilotModel, received_pilots
    from mmslam.slam.sim.sensor import LinkBudget

    sp = dataclasses.replace(SensorParams(), tx_gain_dbi=10 * np.log10(64), rx_gain_dbi=10 * np.log10(16))
    pm = PilotModel.from_sensor(sp, 28e9)
    g_db = -101.3
    a = 10 ** (g_db / 20) * np.exp(0.7j)
    rays = {"delay_s": np.array([3.1e-7]), "a_re": np.array([a.real]), "a_im": np.array([a.imag]),
            "aod_az": np.array([0.4]), "aod_el": np.array([-0.2]), "aoa_az": np.array([2.0]), "aoa_el": np.array([0.15])}
    Y, _ = received_pilots(rays, np.array([0]), 0.3, 0.0, pm, None)
    assert Y.shape == (16, 64, 256)
    energy_db = 10 * np.log10(np.sum(np.abs(Y) ** 2))
    assert float(LinkBudget.from_sensor(sp).snr_db(g_db)) == pytest.approx(energy_db, abs=1e-9)
    assert LinkBudget.from_sensor(sp).subcarriers == sp.est_subcarriers == 256


def _paper_paths(scn, steps: int):
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.scenes.trajectory import true_trajectories

    states = true_trajectories(scn)[:steps]
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(steps)]
    return states, {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


def test_va_mapped_with_twice_the_noise() -> None:
    """With 2x the `paper` measurement noise every VA birth's position trace exceeds
    ``filter.max_trace = 50 m^2`` (angle std 3 x 0.02 rad at 100-270 m); the cap dropped them all and
    no VA was ever mapped. The cap now applies to the moving VS only (``max_trace_scope = "moving"``);
    ``"all"`` (the old behaviour) still maps none: that is the defect, reproduced."""
    from mmslam.slam.filter import run_filter

    scn = with_overrides(load_preset("paper"), ["sensor.toa_std=0.2", "sensor.angle_std=0.02"])
    steps = 8
    states, paths = _paper_paths(scn, steps)

    c = scn.evaluation.gospa_c

    def true_vas_found(s) -> int:
        """True VAs matched in the two local maps at the last step: GOSPA (p = 2, alpha = 2) counts
        each missed one as c^2 / 2 in ``missed`` (gospa^2 = loc + missed + false)."""
        r = run_filter(s, states, paths, "baseline", particles=20, seed=3, steps=steps)
        m = r.metrics
        sel = (m["type"] == "VA") & (m["map"] != "fused") & (m["step"] == steps - 1)
        n_true = np.asarray(m["n_true"])[sel]
        missed = np.rint(np.asarray(m["missed"])[sel] / (c * c / 2)).astype(int)
        return int((n_true - missed).sum())

    assert true_vas_found(scn) >= 4  # of 2 x 4
    assert true_vas_found(with_overrides(scn, ["filter.max_trace_scope=all"])) == 0


def test_per_run_truth(tmp_path) -> None:
    """Run s's truth is the scenario file resolved with seed s (trajectory noise, SP heights): the
    scenario's own seed gives the cache's truth, other seeds another one, the same seed the same."""
    from mmslam.pipelines.ablate import _truth_mode
    from mmslam.pipelines.truth import truth_of_run, truth_scenario
    from mmslam.scenes.scenario import preset_path
    from mmslam.scenes.trajectory import true_trajectories

    base = load_preset("paper")
    f = preset_path("paper")
    s7 = truth_scenario(f, base.seed, base)
    st7, _ = truth_of_run(s7, 6)
    np.testing.assert_array_equal(st7, true_trajectories(base, 6))
    assert [s.position for s in s7.scatterers] == [s.position for s in base.scatterers]
    a, b, a2 = (truth_scenario(f, s, base) for s in (100, 101, 100))
    (sa, pa), (sb, _), (sa2, pa2) = (truth_of_run(x, 6) for x in (a, b, a2))
    assert np.abs(sa - sb)[1:].max() > 0.05 and np.abs(sa - st7)[1:].max() > 0.05
    assert a.scatterers[0].position[2] != b.scatterers[0].position[2]
    assert a.scatterers[0].position[:2] == base.scatterers[0].position[:2]
    np.testing.assert_array_equal(sa, sa2)
    for c in pa:
        np.testing.assert_array_equal(pa[c], pa2[c])
    assert a.filter == base.filter  # only the drawn world changes, not the filter
    info = {"source": "sionna", "scenario": base.to_dict()}
    assert _truth_mode(tmp_path, info, "per-run", f)[0] == "fixed"
    assert _truth_mode(tmp_path, {**info, "source": "analytic"}, "per-run", f)[0] == "per_run"
    assert _truth_mode(tmp_path, {**info, "source": "analytic"}, "fixed", f)[0] == "fixed"


def test_paired_steps_by_hand() -> None:
    """Per step, the paired difference to baseline over the common seeds, with the Student-t half-width."""
    from scipy.stats import t as student_t

    from mmslam.pipelines.ablate import paired_steps

    base = {s: {"pos_err": {0: 1.0, 1: 2.0}} for s in (0, 1, 2)}
    prop = {0: {"pos_err": {0: 1.5, 1: 1.0}}, 1: {"pos_err": {0: 1.0, 1: 1.5}}, 2: {"pos_err": {0: 1.0, 1: 1.2}},
            3: {"pos_err": {0: 9.0, 1: 9.0}}}  # seed 3: no baseline run, not paired
    p = paired_steps({"baseline": base, "proposed": prop})
    rows = [i for i, q in enumerate(p["quantity"]) if q == "pos_err"]
    assert [p["step"][i] for i in rows] == [0, 1] and all(p["reference"][i] == "baseline" for i in rows)
    d1 = np.array([-1.0, -0.5, -0.8])
    i1 = rows[1]
    assert p["diff"][i1] == pytest.approx(d1.mean()) and p["n"][i1] == 3
    assert p["ci"][i1] == pytest.approx(student_t.ppf(0.975, 2) * d1.std(ddof=1) / np.sqrt(3))
    assert p["sig"][i1] is True and p["sig"][rows[0]] is False  # step 0: +0.5, 0, 0


def test_headline_rmse_is_the_statistic_of_its_ci() -> None:
    """The headline position RMSE is the mean over runs of the per-run RMSE, the quantity its CI is of
    (before: the RMSE pooled over all runs and steps, printed with that CI); the pooled one is kept."""
    from mmslam.pipelines.ablate import _add_intervals, ci95

    runs = {s: {"fused": {"pos_rmse": r, **{f"gospa_{t}": 1.0 for t in ("VA", "SP", "VS")},
                          **{f"card_{t}": 1.0 for t in ("VA", "SP", "VS")}}} for s, r in ((0, 0.3), (1, 0.5), (2, 1.6))}
    head = [{"variant": "baseline", "map": "fused", "pos_rmse": 1.0, "gospa_VA": 1.0, "gospa_SP": 1.0, "gospa_VS": 1.0}]
    _add_intervals(head, {"baseline": runs})
    mean, half = ci95(np.array([0.3, 0.5, 1.6]))
    assert head[0]["pos_rmse"] == pytest.approx(0.8) == pytest.approx(mean)
    assert head[0]["pos_rmse_ci"] == pytest.approx(half) and head[0]["pos_rmse_pooled"] == 1.0
