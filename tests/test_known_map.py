"""The known (oracle) landmark map of slam/filter/known_map.py: built from the path table, handed to the filter."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.errors import MmslamError
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import true_trajectories
from mmslam.slam.filter.known_map import KNOWN_MIN_STD, known_map
from mmslam.slam.filter.run import CooperativeRun
from mmslam.slam.specs.landmarks import VA_SPEC, VS_SPEC


def _paths(rows):
    """A path table from (step, rx, type, landmark_id, x, y, z) rows."""
    st, rx, ty, lid, x, y, z = zip(*rows)
    return {"step": np.array(st), "rx": np.array(rx), "type": np.array(ty), "landmark_id": np.array(lid),
            "lm_x": np.array(x, float), "lm_y": np.array(y, float), "lm_z": np.array(z, float)}


def test_rows_of_the_type_per_step_and_vehicle_exact_without_error():
    va, bs = VA_SPEC.code, 0
    p = _paths([(0, 0, va, "w:+x", 10, 0, 2), (0, 1, va, "w:+x", 10, 0, 2), (0, 0, bs, "bs", 0, 0, 9),
                (1, 0, va, "w:+x", 10, 0, 2), (1, 0, va, "v:-y", 0, -7, 2)])
    km = known_map(p, va, 0.0, 0.95, np.random.default_rng(0))
    np.testing.assert_array_equal(km.at(0, 0), [[10, 0, 2]])  # the BS row is not the VA map
    np.testing.assert_array_equal(km.at(1, 0), [[0, -7, 2], [10, 0, 2]])
    assert km.at(1, 1).shape == (0, 3) and km.std == KNOWN_MIN_STD
    g = km.mixture(1, 0, 4, with_pd_beta=True, with_label=True)
    assert g.w.shape == (4, 2) and np.all(g.w == 1.0) and g.mask.all()
    np.testing.assert_allclose(g.pd_beta[..., 0] / g.pd_beta.sum(-1), 0.95)
    np.testing.assert_allclose(g.P[2, 1], np.eye(3) * KNOWN_MIN_STD ** 2)


def test_one_fixed_error_per_landmark_of_the_stated_std():
    va = VA_SPEC.code
    truth = np.stack([10.0 * np.arange(3000), np.zeros(3000), np.zeros(3000)], 1)  # 10 m apart: order kept
    rows = [(k, r, va, f"wall{i:04d}", *truth[i]) for i in range(3000) for k, r in ((0, 0), (5, 2))]
    km = known_map(_paths(rows), va, 0.3, 0.9, np.random.default_rng(1))
    a, b = km.at(0, 0), km.at(5, 2)
    np.testing.assert_array_equal(a, b)  # the same landmark moved by the same error at every step and vehicle
    err = a - truth  # at() sorts by x, the truth's order (errors << 5 m)
    assert abs(err.std() / 0.3 - 1.0) < 0.05 and abs(err.mean()) < 0.02  # 9000 draws: 3% / 0.006 m sd
    assert km.std == 0.3


def test_a_vehicle_given_no_known_landmark_has_an_empty_map():
    """Degenerate shapes: Q = 0 for every particle (vehicle 1 is given nothing), P = 1."""
    scn = load_preset("paper")
    states = true_trajectories(scn)[:3]
    parts = [AnalyticSource(scn).trace_step(k, states[k]) for k in range(3)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    only0 = {c: v[np.asarray(paths["rx"]) == 0] for c, v in paths.items()}
    km = known_map(only0, VA_SPEC.code, 0.0, 0.95, np.random.default_rng(0))
    g = km.mixture(0, 1, 1, with_pd_beta=True, with_label=True)
    assert g.w.shape == (1, 0) and g.m.shape == (1, 0, 3) and g.P.shape == (1, 0, 3, 3) and g.pd_beta.shape == (1, 0, 2)
    run = CooperativeRun(scn, states, paths, "proposed", 1, seed=0, known_map=km)
    for k in range(3):
        est = run.step(k)
        g1, g0 = est[1].avg_maps[VA_SPEC.code], est[0].avg_maps[VA_SPEC.code]
        assert not g1.mask.any()  # nothing given, its own births replaced
        assert g0.mask.sum() >= 1


@pytest.mark.parametrize("err, pd", [(-0.1, 0.9), (0.0, 1.0), (0.0, 0.0)])
def test_bad_parameters_are_one_line_errors(err, pd):
    with pytest.raises(MmslamError, match="known map"):
        known_map(_paths([(0, 0, 1, "a", 0, 0, 0)]), VA_SPEC.code, err, pd, np.random.default_rng(0))


def test_the_filter_maps_on_the_known_landmarks_only():
    """With the exact known VA map every vehicle's averaged VA map after its correction is the known
    landmarks of that step (weight about 1 each: missed and detected copies of one Gaussian; 1 - p_D = 0.05
    where the sensor missed the path, pruned), and nothing else: its own births from the VA measurements, which
    would lie anywhere the noise puts them, are replaced."""
    scn = load_preset("paper")
    states = true_trajectories(scn)[:5]
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(5)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    km = known_map(paths, VA_SPEC.code, 0.0, 0.95, np.random.default_rng(0))
    run = CooperativeRun(scn, states, paths, "proposed", 30, seed=2, known_map=km)
    checked, seen = 0, 0
    for k in range(5):
        for n, est in enumerate(run.step(k)):
            g, pts = est.avg_maps[VA_SPEC.code], km.at(k, n)
            m, w = g.m[g.mask][:, :3], g.w[g.mask]
            d = np.linalg.norm(m[:, None] - pts[None], axis=-1) if len(pts) else np.full((len(m), 1), np.inf)
            assert np.all(d.min(1) < 0.3), (k, n)  # every component on a known landmark
            for j in range(len(pts)):
                wj = w[d[:, j] < 0.3].sum()
                assert wj < 0.1 or 0.5 < wj < 1.5, (k, n, j, wj)
                seen += wj > 0.5
            checked += len(pts)
    assert checked >= 20 and seen >= 0.8 * checked  # paper: four walls per vehicle, each detected with 0.95


def test_a_variant_without_the_map_refuses_it():
    scn = load_preset("paper")
    states = true_trajectories(scn)[:2]
    parts = [AnalyticSource(scn).trace_step(k, states[k]) for k in range(2)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    km = known_map(paths, VS_SPEC.code, 0.0, 0.95, np.random.default_rng(0))
    with pytest.raises(MmslamError, match="keeps no such map"):  # the baseline keeps VA and SP maps only
        CooperativeRun(scn, states, paths, "baseline", 10, known_map=km)
