"""Sensor model ``estimated`` (issue 24): pilots from traced rays, estimates against the rays, evaluation
labels, the estimates' cache (same seed, same estimates; read back), and a filter run on them."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.analytic import AnalyticSource
from mmslam.raytrace.cache import load_cache
from mmslam.raytrace.trace import trace_scenario
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.sim import channel_estimator as ce
from mmslam.slam.sim import estimated_sensor as es
from mmslam.slam.models.measurement import BS

C = 299_792_458.0


@pytest.fixture(scope="module")
def paper2(tmp_path_factory):
    scn = with_overrides(load_preset("paper"), ["sensor.model=estimated"])
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path_factory.mktemp("est") / "c", steps=2, progress=False)
    return scn, load_cache(d)


def test_pilots_of_one_ray_give_its_parameters(paper2):
    """One traced ray (the LOS at step 0), noise free: one estimate equal to the ray's TOA + bias, AODs and
    body-frame AOA (the channel module's array conventions and the estimator's atoms agree)."""
    scn, c = paper2
    r = c.read_rays()
    pm = es.PilotModel.from_sensor(scn.sensor, scn.frequency_hz)
    i = np.flatnonzero((r["step"] == 0) & (r["rx"] == 1) & (r["type"] == BS))
    assert i.size == 1
    st = c.states[0, 1]
    Y, t0 = es.received_pilots(r, i, st[3], 12.0, pm, None)
    assert t0 < r["delay_s"][i[0]] * C + 12.0 - es.GUARD * C / 400e6 + 1e-9
    z, cov, snr, _ = es.estimate_link(Y, t0, pm, 0.01, 5)
    assert z.shape == (1, 5)
    want = [r["delay_s"][i[0]] * C + 12.0, r["aod_az"][i[0]], r["aod_el"][i[0]], r["aoa_az"][i[0]] - st[3],
            r["aoa_el"][i[0]]]
    np.testing.assert_allclose(z[0, 0], want[0], atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (z[0, 1:] - want[1:]))), 0.0, atol=1e-6)
    # its SNR: |a|^2 x (P / N0 B) x N, the full array and subcarrier gain
    a2 = r["a_re"][i[0]] ** 2 + r["a_im"][i[0]] ** 2
    assert snr[0] == pytest.approx(10 * np.log10(a2 * pm.grid.size) + pm.snr_scale_db, abs=1e-6)
    assert np.all(np.linalg.eigvalsh(cov[0]) > 0)


def test_a_link_without_rays_is_a_noise_only_channel(paper2):
    """A vehicle-step with no traced ray (a car blocked from the BS, e.g. on canyon): the pilots are the
    full (rx^2, tx^2, K) block, all zero without noise, unit-variance noise with it (crashed before:
    'cannot reshape array of size 0')."""
    scn, c = paper2
    r = c.read_rays()
    pm = es.PilotModel.from_sensor(scn.sensor, scn.frequency_hz)
    g = pm.grid
    none = np.zeros(0, np.int64)
    Y, t0 = es.received_pilots(r, none, 0.3, 12.0, pm, None)
    assert Y.shape == (g.rx_array ** 2, g.tx_array ** 2, g.n_subcarriers) and not np.any(Y) and t0 == 0.0
    Y, _ = es.received_pilots(r, none, 0.3, 12.0, pm, np.random.default_rng(1))
    assert np.mean(np.abs(Y) ** 2) == pytest.approx(1.0, rel=0.02)


def test_estimates_labelled_against_the_rays_and_cached(paper2, tmp_path):
    """The estimates of 2 steps: the LOS of every link found and labelled 'bs' within 5 cm and 0.02 rad of
    the truth; counts consistent (estimates = detected + false); the same seed gives the same estimates,
    a cache file is written atomically and read back equal; another seed other noise."""
    scn, c = paper2
    rays = c.read_rays()
    a = es.estimated_run(scn, c.states, rays, c.paths, np.random.default_rng(4), tmp_path, seed=4)
    files = list((tmp_path / "estimates").rglob("*.npz"))
    assert len(files) == 1 and not list((tmp_path / "estimates").rglob("*.tmp*"))
    b = es.estimated_run(scn, c.states, rays, c.paths, np.random.default_rng(99), tmp_path, seed=4)  # cached
    np.testing.assert_array_equal(a["z"], b["z"])
    np.testing.assert_array_equal(a["origin_id"], b["origin_id"])
    fresh = es.estimate_run(scn, c.states, rays, c.paths, np.random.default_rng(4))
    np.testing.assert_array_equal(a["z"], fresh["z"])
    other = es.estimate_run(scn, c.states, rays, c.paths, np.random.default_rng(5))
    assert not np.array_equal(other["z"][:1], a["z"][:1])
    counts = a["counts"]
    assert counts.shape == (2, 2, len(es.COUNT_COLUMNS))
    np.testing.assert_array_equal(counts[..., 0], counts[..., 1] + counts[..., 3])
    true = a["true_states"]
    for k in range(2):
        for v in range(2):
            s = a["set"] == k * 2 + v
            los = s & (a["origin_type"] == BS)
            assert los.sum() >= 1
            j = np.flatnonzero(los)[np.argmax(a["snr_db"][los])]
            p = np.flatnonzero((c.paths["step"] == k) & (c.paths["rx"] == v) & (c.paths["type"] == BS))[0]
            assert a["z"][j, 0] == pytest.approx(c.paths["toa_m"][p] + true[k, v, 6], abs=0.05)
            assert abs(np.angle(np.exp(1j * (a["z"][j, 3] - (c.paths["aoa_az"][p] - true[k, v, 3]))))) < 0.02
    # the key changes with the settings that change the estimates, not with filter options
    assert es.settings_key(scn) != es.settings_key(with_overrides(scn, ["sensor.est_pfa=0.001"]))
    assert es.settings_key(scn) == es.settings_key(with_overrides(scn, ["filter.r_scale=2"]))


def test_association_merges_and_false_alarms_by_hand():
    grid = ce.Grid(4, 4, 16, 100e6)  # cells: pi / 2 in the spatial, 2 pi / 16 in the delay frequencies
    cell = 2 * np.pi / np.array(grid.shape)
    w_true = np.array([[0, 0, 0, 0, 0.0], [0, 0, 0, 0, 0.5 * cell[4]], [2.0, 0, 0, 0, 0]])
    key = np.array([0, 1, 2])
    power = np.array([1.0, 2.0, 1.0])
    w_hat = np.array([[0, 0, 0, 0, 0.2 * cell[4]], [2.0, 0.1, 0, 0, 0], [-2.0, 0, 0, 0, 0]])
    label, n_lm = es.associate(w_hat, w_true, power, key, grid)
    np.testing.assert_array_equal(label, [1, 2, -1])  # the stronger of two merged rays; a false alarm
    np.testing.assert_array_equal(n_lm, [2, 1, 0])


def test_non_maximum_suppression_by_hand():
    """Greedy NMS in cells of every axis at once: a weaker estimate inside a kept one's box goes, one outside
    it in a single axis stays, one near only a dropped estimate stays, axes wrap; radius 0 keeps all."""
    grid = ce.Grid(4, 4, 16, 100e6)
    cell = 2 * np.pi / np.array(grid.shape)  # pi / 2 in the spatial axes (4 elements), 2 pi / 16 in delay
    a = np.array([0.3, -0.2, 0.1, 0.0, 1.0])
    off = np.array([[0, 0, 0, 0, 0],            # 0: the strongest
                    [0.9, 0.9, 0.9, 0.9, 0.9],  # 1: 0.9 cells from 0 in every axis
                    [0, 0, 0, 0, 1.5],          # 2: 1.5 cells from 0 in delay only
                    [0, 0, 0, 0, 2.4],          # 3: 2.4 cells from 0, 0.9 from 2
                    [0, 0, 0, 2.9, 0],          # 4: 2.9 cells in an axis of 4 cells: 1.1 the other way round
                    [0, 0, 0, 0, 15.5]])        # 5: 15.5 cells in delay (16): 0.5 the other way round
    w = a + off * cell
    snr = np.array([30.0, 20.0, 25.0, 10.0, 15.0, 12.0])
    # radius 1: 0 drops 1 and 5; 2 stays (1.5 cells) and drops 3; 4 stays (1.1 cells)
    np.testing.assert_array_equal(es.suppress_non_maxima(w, snr, grid, 1.0), [1, 0, 1, 0, 1, 0])
    # radius 2: 0 drops 1, 2, 4 and 5; 3 is 2.4 cells from 0 and only near the dropped 2: it stays
    np.testing.assert_array_equal(es.suppress_non_maxima(w, snr, grid, 2.0), [1, 0, 0, 1, 0, 0])
    assert es.suppress_non_maxima(w, snr, grid, 0.0).all()
    # only the strengths order them, not the position in the list
    p = np.array([3, 5, 0, 2, 4, 1])
    np.testing.assert_array_equal(es.suppress_non_maxima(w[p], snr[p], grid, 2.0), [1, 0, 1, 0, 0, 0])


def test_resolve_estimates_recounts_what_the_filter_gets(paper2):
    """Two links: a VA estimate inside the LOS estimate's main lobe is dropped and its VA becomes missed;
    two distant estimates of the other link both stay; the input dict is not modified."""
    scn, _ = paper2
    grid = es.PilotModel.from_sensor(scn.sensor, scn.frequency_hz).grid
    t0 = 10.0
    cell = 2 * np.pi / np.array(grid.shape)
    w0 = np.array([0.2, -0.3, 0.4, -0.1, -1.0])
    w = np.array([w0, w0 + 0.5 * cell, w0, w0 + 2.5 * cell * np.array([0, 0, 1, 0, 0])])  # 2.5 BS cells
    z = ce.measurement_of_w(w, t0, grid)
    est = {"set": np.array([0, 0, 1, 1]), "z": z, "cov": np.tile(np.eye(5), (4, 1, 1)),
           "snr_db": np.array([30.0, 20.0, 25.0, 18.0]), "origin_type": np.array([0, 1, 1, -1]),
           "origin_id": np.array(["bs", "wall", "wall", ""], object),
           "origin_pos": np.array([[0, 0, 40.0], [1, 2, 3], [1, 2, 3], [np.nan] * 3]),
           "merged": np.array([True, False, False, False]), "true_states": np.zeros((1, 2, 7)),
           "counts": np.array([[[2, 2, 1, 0, 0], [2, 1, 0, 1, 3]]])}
    before = {k: np.array(v, copy=True) for k, v in est.items()}
    r = es.resolve_estimates(with_overrides(scn, ["sensor.est_resolve=2"]), est, 1, 2)
    np.testing.assert_array_equal(r["set"], [0, 1, 1])
    np.testing.assert_array_equal(r["origin_type"], [0, 1, -1])
    # estimates, detected, merged, false, missed (+1 at link 0: the VA), suppressed
    np.testing.assert_array_equal(r["counts"], [[[1, 1, 1, 0, 1, 1], [2, 1, 0, 1, 3, 0]]])
    for k, v in before.items():
        np.testing.assert_array_equal(np.asarray(est[k]), v)
    off = es.resolve_estimates(with_overrides(scn, ["sensor.est_resolve=0"]), est, 1, 2)
    np.testing.assert_array_equal(off["set"], est["set"])
    np.testing.assert_array_equal(off["counts"][..., :5], est["counts"])
    # an OTHER landmark (no stored position) of link 0's paths whose one estimate is dropped: missed only
    # when the paths table is given (exact); the VA is missed either way
    est2 = {k: np.asarray(v).copy() for k, v in est.items()}
    est2["origin_type"] = np.array([0, 4, 1, -1])
    est2["origin_id"] = np.array(["bs", "rough", "wall", ""], object)
    est2["origin_pos"][1] = np.nan
    paths = {"step": np.array([0, 0, 0, 0]), "rx": np.array([0, 0, 1, 1]), "type": np.array([0, 4, 1, 2]),
             "landmark_id": np.array(["bs", "rough", "wall", "sp"])}
    sc2 = with_overrides(scn, ["sensor.est_resolve=2"])
    assert es.resolve_estimates(sc2, est2, 1, 2)["counts"][0, 0, 4] == 0
    assert es.resolve_estimates(sc2, est2, 1, 2, paths)["counts"][0, 0, 4] == 1
    assert es.resolve_estimates(sc2, est, 1, 2, paths)["counts"][0, 0, 4] == 0  # 'wall' is not in link 0's paths


def test_an_unresolved_roof_reflection_biases_the_toa_far_beyond_its_fisher_std(paper2):
    """The case behind ``sensor.est_toa_floor``: a path plus a 1 dB weaker copy 5 cm later (a roof
    reflection; 0.07 delay cells) at 50 dB, on the default grid, no noise. In phase: one estimate, its TOA at
    the amplitude-weighted centre of the two (first order of the one-atom fit: ``d rho / (1 + rho)``, 2.36 cm;
    the power-weighted centre would be 2.21 cm), dozens of Fisher standard deviations off the direct path,
    within the floor; measurement_variances adds the floor to the TOA alone. In anti-phase the pair nearly
    cancels and the strongest estimate lies before the direct path by more than the gap (first order
    ``-d rho / (1 - rho)``): the bias is not bounded by half the gap."""
    scn, _ = paper2
    pm = es.PilotModel.from_sensor(scn.sensor, scn.frequency_hz)
    grid = pm.grid
    z_direct = np.array([[80.0, 0.3, -0.4, -0.2, 0.5]])
    t0 = 76.0
    w_a = ce.w_of_measurement(z_direct, t0, grid)[0]
    w_b = ce.w_of_measurement(z_direct + np.array([[0.05, 0, 0, 0, 0]]), t0, grid)[0]
    amp_a = 10 ** (50 / 20) / np.sqrt(grid.size)
    rho = 10 ** (-1 / 20)
    Y = amp_a * ce.atom_tensor(w_a, grid) + rho * amp_a * ce.atom_tensor(w_b, grid)
    z, cov, snr, _ = es.estimate_link(Y, t0, pm, scn.sensor.est_pfa, 5)
    assert len(z) == 1
    centre = 0.05 * rho / (1 + rho)  # 2.36 cm after the direct path
    bias = z[0, 0] - z_direct[0, 0]
    assert bias == pytest.approx(centre, rel=0.02) and bias > 20 * np.sqrt(cov[0, 0, 0])
    thr = es.threshold_covariance(scn)  # the shared R carries the floor too
    assert thr[0, 0] > scn.sensor.est_toa_floor**2 and thr[0, 0] - scn.sensor.est_toa_floor**2 < 1e-4
    var = es.measurement_variances(scn, cov)
    np.testing.assert_allclose(var[0, 0], cov[0, 0, 0] + scn.sensor.est_toa_floor**2, rtol=1e-12)
    np.testing.assert_array_equal(var[0, 1:], np.diagonal(cov[0])[1:])
    assert abs(bias) < np.sqrt(var[0, 0])
    Y = amp_a * ce.atom_tensor(w_a, grid) - rho * amp_a * ce.atom_tensor(w_b, grid)
    z, _, snr, _ = es.estimate_link(Y, t0, pm, scn.sensor.est_pfa, 5)
    assert z[np.argmax(snr), 0] - z_direct[0, 0] < -0.05


def test_a_path_beyond_the_delay_window_is_estimated_at_its_own_delay(paper2):
    """A first arrival 3.5 m into the window (its sample 4 = GUARD) and a path 190 m after it, past the
    191.9 m window's end: the DFT puts it 191.9 m early, before the first arrival; estimate_link gives both
    at their true TOAs. A path 195 m after the first arrival aliases to after it (6.6 m into the window):
    not told apart, stays (the documented limit: only the guard interval unwraps). unwrap_delay by hand:
    only estimates more than one sample before the first arrival move."""
    scn, _ = paper2
    pm = es.PilotModel.from_sensor(scn.sensor, scn.frequency_hz)
    grid, t0 = pm.grid, 40.0
    dr = C / grid.bandwidth_hz
    window = grid.n_subcarriers * dr
    assert window == pytest.approx(191.9, abs=0.1)
    for excess, want in ((190.0, t0 + 3.5 + 190.0), (195.0, t0 + 3.5 + 195.0 - window)):
        z_true = np.array([[t0 + 3.5, 0.3, -0.4, -0.2, 0.5], [t0 + 3.5 + excess, -0.8, -0.2, 1.1, 0.1]])
        w = ce.w_of_measurement(z_true, t0, grid)
        amp = 10 ** (np.array([40.0, 30.0]) / 20) / np.sqrt(grid.size)
        Y = amp[0] * ce.atom_tensor(w[0], grid) + amp[1] * ce.atom_tensor(w[1], grid)
        z, _, _, _ = es.estimate_link(Y, t0, pm, scn.sensor.est_pfa, 5)
        assert len(z) == 2
        np.testing.assert_allclose(np.sort(z[:, 0]), np.sort([t0 + 3.5, want]), atol=1e-3)
    by_hand = es.unwrap_delay(np.array([[t0 + 0.5, 0, 0, 0, 0], [t0 + 2.0, 0, 0, 0, 0], [t0 + 2.4, 0, 0, 0, 0],
                                        [t0 + 150.0, 0, 0, 0, 0]]), t0, grid)
    np.testing.assert_allclose(by_hand[:, 0], [t0 + 0.5 + window, t0 + 2.0 + window, t0 + 2.4, t0 + 150.0])


def test_filter_runs_on_the_estimates(paper2):
    """run_slam with sensor.model=estimated: a result with the per-step estimator counts in its meta;
    measurements reach the filter (the vehicles' maps are not all empty)."""
    from mmslam.slam.filter.run import run_slam

    _, c = paper2
    r = run_slam(c.path, "proposed", particles=20, seed=1, overrides=["sensor.model=estimated"])
    cnt = np.asarray(r.meta["estimator_counts"]["per_step_vehicle"])
    assert cnt.shape == (2, 2, len(es.RESOLVED_COLUMNS)) and cnt[..., 0].min() >= 1
    assert r.meta["estimator_counts"]["columns"][-1] == "suppressed"
    assert list((c.path / "estimates").rglob("seed-1-steps-2.npz"))


_READY_BEFORE_THE_CLOCK = """
import json, sys
import numba.core.registry as reg
import mmslam.slam.filter.run as R
from mmslam.slam.sim import dft_kernels as dk, nomp_kernels as nk

def overloads():
    return {k: len(o.overloads) for m in (nk, dk) for k, o in vars(m).items()
            if isinstance(o, reg.CPUDispatcher) and o.py_func.__module__ == m.__name__}

seen = {}
orig = R.run_filter
def spy(*a, **k):
    seen["start"] = overloads()
    res = orig(*a, **k)
    seen["end"] = overloads()
    return res
R.run_filter = spy
R.run_slam(sys.argv[1], "baseline", particles=10, seed=2, overrides=["sensor.model=estimated"])
print(json.dumps(seen))
"""


def test_the_estimators_kernels_are_ready_before_the_run_clock_starts(paper2):
    """In a fresh process, run_slam compiles (first time) or loads the estimator's numba kernels before
    run_filter, where the run's wall_time_s is measured: no kernel of slam/sim/nomp_kernels.py or
    dft_kernels.py is compiled or loaded during the run (before: inside the first estimation, ~20 s of
    CPU counted as the run's time when not cached, silently)."""
    import json
    import subprocess
    import sys

    _, c = paper2
    out = subprocess.run([sys.executable, "-c", _READY_BEFORE_THE_CLOCK, str(c.path)], capture_output=True,
                         text=True, timeout=600, check=True).stdout.splitlines()[-1]
    seen = json.loads(out)
    called = ("contract", "update_dft", "add_cross_terms", "coordinate_search", "next_mover", "refine")
    assert all(seen["start"][k] >= 1 for k in called), seen["start"]  # the estimator's entry kernels, ready
    assert seen["end"] == seen["start"]
    assert es.estimator_kernels_cached()


def test_a_cache_with_estimates_is_reused_by_trace(paper2, tmp_path):
    """The estimates folder inside a cache is the cache's own: tracing the same scenario into the same root
    reuses the cache (it raised 'exists and is not a cache mmslam wrote' before, so a second ablation on
    a cache with estimates was refused); a foreign file next to them still is refused."""
    from mmslam.errors import CacheError

    scn, _ = paper2
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path, steps=2, progress=False)
    c = load_cache(d)
    es.estimated_run(scn, c.states, c.read_rays(), c.paths, np.random.default_rng(0), d, seed=0)
    assert list((d / "estimates").rglob("*.npz"))
    assert trace_scenario(scn, AnalyticSource(scn), tmp_path, steps=2, progress=False) == d
    (d / "estimates" / "mine.txt").write_text("x")
    with pytest.raises(CacheError, match="not a cache mmslam wrote"):
        trace_scenario(scn, AnalyticSource(scn), tmp_path, steps=2, progress=False)
