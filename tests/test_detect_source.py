"""``filter.types.<T>.p_detect_source = "link"``: a type's p_D from the sensor's link budget (issue 24, VS).

Under a power-aware sensor model the filter's VS detection probability is the link budget's mean detection
probability of the VS paths inside the FOV (their traced power), not the paper's 0.95 (docs/estimator.md 6b).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.special import i0e
from scipy.integrate import quad

from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.filter.run import CooperativeRun, link_detect_rate, resolve_detect_probs
from mmslam.slam.sim.sensor import LinkBudget
from mmslam.slam.specs.landmarks import VA_SPEC, VS_SPEC


def _marcum_q1(a: float, b: float) -> float:
    """``Q_1(a, b)`` by numerical integration of its definition (independent of scipy's ncx2)."""
    f = lambda x: x * np.exp(-(x - a) ** 2 / 2) * i0e(a * x)  # noqa: E731  (x exp(-(x^2+a^2)/2) I0(ax))
    return float(quad(f, b, np.inf, limit=200)[0])


def _paths(powers: list[float], dists: list[float], code: int) -> dict[str, np.ndarray]:
    n = len(powers)
    return {"step": np.zeros(n, int), "rx": np.zeros(n, int), "type": np.full(n, code),
            "lm_x": np.asarray(dists, float), "lm_y": np.zeros(n), "lm_z": np.full(n, 1.5),
            "power_db": np.asarray(powers, float), "landmark_id": np.array([f"l{i}" for i in range(n)])}


def test_link_detect_rate_is_the_mean_marcum_q_of_the_paths_in_the_fov():
    scn = with_overrides(load_preset("paper"), ["sensor.model=link"])
    states = np.zeros((1, 1, 7))
    states[0, 0, 2] = 1.5
    link = LinkBudget.from_sensor(scn.sensor)
    # a path at the detection threshold's SNR region, a strong one, and one beyond fov_range (50 m): not counted
    snr_target = 12.0  # dB
    p_mid = snr_target - float(link.snr_db(0.0))
    paths = _paths([p_mid, -60.0, p_mid], [20.0, 30.0, 80.0], VS_SPEC.code)
    rate, n = link_detect_rate(scn, states, paths, VS_SPEC.code)
    assert n == 2
    snr = 10 ** (snr_target / 10)
    q = _marcum_q1(np.sqrt(2 * snr), np.sqrt(-2 * np.log(scn.sensor.pfa)))
    assert 0.05 < q < 0.95  # a value the test can tell apart from 0 and 1
    assert rate == pytest.approx((q + 1.0) / 2, abs=1e-6)
    # a type that is not range-gated (VA) counts at any range
    va = _paths([p_mid, p_mid], [20.0, 500.0], VA_SPEC.code)
    assert link_detect_rate(scn, states, va, VA_SPEC.code) == (pytest.approx(q, abs=1e-6), 2)
    assert np.isnan(link_detect_rate(scn, states, _paths([], [], VS_SPEC.code), VS_SPEC.code)[0])


def test_resolve_detect_probs_sets_vs_only_under_power_aware_models():
    base = load_preset("paper")
    states = np.zeros((1, 1, 7))
    strong = _paths([-60.0, -60.0], [10.0, 20.0], VS_SPEC.code)
    scn, notes = resolve_detect_probs(base, states, strong)  # constant model: unchanged
    assert notes == {} and scn is base
    for model in ("link", "estimated"):
        sc = with_overrides(base, [f"sensor.model={model}"])
        out, notes = resolve_detect_probs(sc, states, strong)
        assert notes == {"VS": {"p_detect": 0.99, "paths": 2}}  # p_D ~ 1, clipped to 0.99
        assert out.filter.type_params("VS").p_detect == 0.99
        assert out.filter.type_params("VA").p_detect == sc.filter.type_params("VA").p_detect  # source "value"
        assert out.filter.type_params("VS").threshold == sc.filter.type_params("VS").threshold
    # p_detect_source = value keeps the preset's number; no VS path in the FOV keeps it too
    sc = with_overrides(base, ["sensor.model=link", "filter.types.VS.p_detect_source=value"])
    assert resolve_detect_probs(sc, states, strong) == (sc, {})
    sc = with_overrides(base, ["sensor.model=link"])
    assert resolve_detect_probs(sc, states, _paths([-60.0], [90.0], VS_SPEC.code)) == (sc, {})


def test_a_run_filters_with_the_link_budgets_vs_detection_probability(tmp_path):
    """The run's scenario, its p_D function and its meta all carry the computed value."""
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.cache import load_cache
    from mmslam.raytrace.trace import trace_scenario

    scn = with_overrides(load_preset("paper"), ["sensor.model=link"])
    c = load_cache(trace_scenario(scn, AnalyticSource(scn), tmp_path / "c", steps=3, progress=False))
    run = CooperativeRun(scn, c.states, c.paths, "proposed", 5, 0)
    want, n = link_detect_rate(scn, c.states, c.paths, VS_SPEC.code)
    assert n > 0
    pd = float(np.clip(want, 0.01, 0.99))
    assert run.scn.filter.type_params("VS").p_detect == pytest.approx(pd)
    assert run.result().meta["p_detect_from_link"] == {"VS": {"p_detect": pytest.approx(pd), "paths": n}}
    u, x = c.states[0, 0, 0:3][None], c.states[0, 1, 0:3][None]  # the other car, 10 m away: inside the FOV
    assert float(np.asarray(run.pd_fn(u, x, VS_SPEC.code))[0]) == pytest.approx(pd)
