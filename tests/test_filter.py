"""The cooperative MM-PHD-SLAM filter (slam/filter.py, slam/filter/rbpf.py, slam/cli.py)."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.errors import CacheError, MmslamError
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.scenes.trajectory import true_trajectories, vehicle_trajectories
from mmslam.slam.filter import ego_gaussian, run_filter, run_slam
from mmslam.slam.eval.gospa import gospa
from mmslam.slam.filter.rbpf import systematic_resample


@pytest.fixture(scope="module")
def paper():
    scn = load_preset("paper")
    states = true_trajectories(scn)  # the preset's truth, with process noise, as a trace caches it
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(scn.steps)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    return scn, states, paths


def _rmse(res, lo=10, hi=40):
    v = res.vehicles
    s = (v["step"] >= lo) & (v["step"] < hi)
    return float(np.sqrt(np.mean(v["pos_err"][s] ** 2)))


def _metric(res, step, mp, typ, col="gospa"):
    m = res.metrics
    s = (m["step"] == step) & (m["map"] == mp) & (m["type"] == typ)
    assert s.sum() == 1
    return float(m[col][s][0])


# ---------------------------------------------------------------- small units
def test_systematic_resampling_reproduces_weights_exactly_when_they_are_multiples_of_1_over_p():
    rng = np.random.default_rng(0)
    w = np.array([0.5, 0.0, 0.25, 0.25])
    for _ in range(20):
        idx = systematic_resample(w, rng)
        assert np.bincount(idx, minlength=4).tolist() == [2, 0, 1, 1]


def test_ego_gaussian_jacobian_matches_finite_differences():
    """The linearisation mapping the particle covariance to [pos, vel, xi] (proposed upload)."""
    mean = np.array([10.0, -3.0, 0.5, 0.7, 20.0, 0.3, 300.0])

    def f(s):
        return ego_gaussian(s, np.zeros((7, 7)), np.zeros(7))[0]

    eps = 1e-6
    Jfd = np.stack([(f(mean + eps * e) - f(mean - eps * e)) / (2 * eps) for e in np.eye(7)], 1)
    cov = np.diag([0.1, 0.2, 0.0, 1e-4, 0.0, 0.0, 0.09]) + 0.01
    m, C = ego_gaussian(mean, cov, np.zeros(7))
    assert np.allclose(m, f(mean))
    assert np.allclose(C, Jfd @ cov @ Jfd.T, atol=1e-8)
    _, C2 = ego_gaussian(mean, cov, np.ones(7))
    assert np.allclose(C2 - C, np.eye(7))


# ---------------------------------------------------------------- errors
def test_bad_inputs_give_one_line_errors(paper, tmp_path):
    scn, states, paths = paper
    for kw, word in [({"variant": "fancy"}, "variant"), ({"particles": 0}, "particles"),
                     ({"steps": 999}, "steps"), ({"steps": 0}, "steps"), ({"include_types": (9,)}, "include_types")]:
        with pytest.raises(MmslamError) as e:
            run_filter(scn, states, paths, **kw)
        assert "\n" not in str(e.value) and word in str(e.value)
    with pytest.raises(CacheError):
        run_slam(tmp_path / "nope")
    with pytest.raises(MmslamError, match="particles"):
        run_slam(tmp_path / "nope", particles=0)


def test_cli_bad_cache_exits_2_with_one_line(tmp_path, capsys):
    from mmslam.cli import main

    code = main(["slam", str(tmp_path / "missing"), "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("error:") and "\n" not in err


# ---------------------------------------------------------------- end to end
def test_same_seed_same_result_and_seed_matters(paper):
    scn, states, paths = paper
    a = run_filter(scn, states, paths, variant="proposed", particles=30, seed=4, steps=9)
    b = run_filter(scn, states, paths, variant="proposed", particles=30, seed=4, steps=9)
    c = run_filter(scn, states, paths, variant="proposed", particles=30, seed=5, steps=9)
    for k in a.vehicles:
        assert np.array_equal(a.vehicles[k], b.vehicles[k])
    for k in a.metrics:
        assert np.array_equal(a.metrics[k], b.metrics[k])
    assert not np.array_equal(a.vehicles["x"], c.vehicles["x"])
    # table layout: per step, (veh1, veh2, fused) x (VA, SP, VS); GOSPA^2 = loc + missed + false
    m = a.metrics
    assert len(m["step"]) == 9 * 3 * 3
    assert np.allclose(m["gospa"] ** 2, m["loc"] + m["missed"] + m["false"])
    assert set(m["map"]) == {"veh1", "veh2", "fused"}
    assert len(a.vehicles["step"]) == 9 * 2


@pytest.mark.slow
def test_filter_beats_dead_reckoning_and_maps_the_vas(paper):
    """Analytic `paper` data without VS rows, baseline filter, P = 300, one seed."""
    scn, states, paths = paper
    res = run_filter(scn, states, paths, variant="baseline", particles=300, seed=0, include_types=(0, 1, 2))
    dr = run_filter(scn, states, paths, variant="baseline", particles=300, seed=0, include_types=(0, 1, 2),
                    measurement_update=False)
    r_f, r_dr = _rmse(res), _rmse(dr)
    assert r_f <= 0.5 * r_dr, (r_f, r_dr)
    last = scn.steps - 1
    n_true = int(_metric(res, last, "fused", "VA", "n_true"))
    assert n_true == 4
    empty = gospa(np.zeros((n_true, 3)), np.zeros((0, 3)), 20.0, 2.0, 2.0).d
    g = _metric(res, last, "fused", "VA")
    assert g <= 0.5 * empty, (g, empty)


def test_cli_writes_result_and_prints_summary(paper, tmp_path, capsys):
    from mmslam.cli import main
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.slam.filter.result import Result

    scn = paper[0]
    cache = trace_scenario(scn, AnalyticSource(scn), tmp_path / "cache", steps=7, progress=False)
    out = tmp_path / "res"
    code = main(["slam", str(cache), "--variant", "cm1", "--particles", "20", "--seed", "1",
                 "--out", str(out), "--steps", "7"])
    text = capsys.readouterr().out
    assert code == 0
    r = Result.load(out)
    assert r.meta["variant"] == "cm1" and r.meta["particles"] == 20 and r.meta["steps"] == 7
    assert r.meta["source"] == "analytic" and r.meta["cache"]
    assert "position RMSE veh1" in text and "fused" in text
    assert main(["slam", str(cache), "--variant", "nope", "--out", str(out)]) == 2


# ---------------------------------------------------------------- ablation (paper Sec. V claims)
ABLATION_SEEDS = tuple(range(5))
FUSION_START = 5  # paper preset: vehicle 1 uploads first at k = 5


def _ablation_scores(args) -> dict:
    """One (variant, seed) run of the acceptance ablation, reduced to its scores (a worker function)."""
    variant, seed = args
    scn = load_preset("paper")
    states = true_trajectories(scn)
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(scn.steps)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    r = run_filter(scn, states, paths, variant=variant, particles=300, seed=seed)
    m = r.metrics
    after = m["step"] >= FUSION_START
    sel = lambda mp, ty: after & (m["map"] == mp) & (m["type"] == ty)  # noqa: E731
    fused_vs = m["gospa"][(m["map"] == "fused") & (m["type"] == "VS")]
    return {
        "vs": float(m["gospa"][sel("fused", "VS")].mean()),
        "va": float(m["gospa"][sel("fused", "VA")].mean()),
        "local_vs": float(np.max([m["gospa"][sel(n, "VS")].mean() for n in scn.vehicle_names])),
        "rmse": _rmse(r, 10, scn.steps),
        "vs_odd": float(fused_vs[11::2].mean()), "vs_even": float(fused_vs[10::2].mean()),
    }


@pytest.fixture(scope="module")
def ablation():
    """baseline, cm1 and proposed, 5 fixed seeds, P = 300, analytic `paper` data (all path types;
    the preset's truth with process noise), on 2 worker processes.

    Per seed: fused-map VS / VA GOSPA averaged over k >= fusion start, the worse of the vehicles'
    local VS GOSPA (same steps), the position RMSE over k >= 10 and the fused VS GOSPA at vehicle
    1's / vehicle 2's upload steps (odd / even k >= 10: the period-2 pattern of Fig. 2a)."""
    import concurrent.futures as cf

    variants = ("baseline", "cm1", "proposed")
    grid = [(v, s) for v in variants for s in ABLATION_SEEDS]
    with cf.ProcessPoolExecutor(max_workers=2) as ex:
        rows = dict(zip(grid, ex.map(_ablation_scores, grid)))
    return {v: {k: np.array([rows[(v, s)][k] for s in ABLATION_SEEDS]) for k in rows[grid[0]]} for v in variants}


def _paired_ci(d: np.ndarray) -> tuple[float, float]:
    from scipy.stats import t

    return float(d.mean()), float(t.ppf(0.975, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size))


@pytest.mark.slow
def test_ablation_acceptance_thresholds_and_ordering(ablation):
    """Issue 9 acceptance on 5 seeds: proposed VS <= 3.0 m and VA <= 5.0 m; baseline VS = 20 (no VS
    map, every vehicle missed at c = 20 with 2 vehicles: sqrt(2 * 20^2 / 2)); cm1 strictly between,
    by paired differences whose 95% CI excludes 0."""
    p, c, b = ablation["proposed"], ablation["cm1"], ablation["baseline"]
    assert p["vs"].mean() <= 3.0, p["vs"]
    assert p["va"].mean() <= 5.0, p["va"]
    np.testing.assert_allclose(b["vs"], 20.0)
    for hi, lo in ((b, c), (c, p)):
        mean, half = _paired_ci(hi["vs"] - lo["vs"])
        assert mean - half > 0, (mean, half)


@pytest.mark.slow
def test_ablation_proposed_fused_vs_map_no_worse_than_local_and_no_sawtooth(ablation):
    """The fused VS map (both vehicles) is no worse than the worse vehicle's local VS map (its one
    neighbour; was 12.0 fused vs 5.4 / 2.9 local before the fixes of issue 9)."""
    p = ablation["proposed"]
    assert p["vs"].mean() <= p["local_vs"].mean(), (p["vs"], p["local_vs"])
    # Fig. 2a: after vehicle 1's uploads (odd k) the fused VS GOSPA is not systematically worse
    # than after vehicle 2's (even k) by more than 2 m (it was ~10 m with every VS Gaussian dithered
    # and the fused map merged with the gate U = 49)
    mean, half = _paired_ci(p["vs_odd"] - p["vs_even"])
    assert mean < 2.0, (mean, half)


@pytest.mark.slow
def test_ablation_proposed_lowers_fused_va_gospa(ablation):
    mean, half = _paired_ci(ablation["baseline"]["va"] - ablation["proposed"]["va"])
    assert mean - half > 0, (mean, half)


@pytest.mark.slow
def test_ablation_proposed_position_rmse_not_worse(ablation):
    """Non-inferiority, paired over seeds: the 95% CI of RMSE(proposed) - RMSE(baseline) lies below
    +0.1 m (a quarter of the RMSE). The paper's claim that proposed is *lower* is not reproduced:
    the paired difference is +0.02 +- 0.04 m on held-out seeds 100-109 (docs/vs-fusion.md), so a
    one-sided "p <= b" on the means would be a coin flip, not a test."""
    mean, half = _paired_ci(ablation["proposed"]["rmse"] - ablation["baseline"]["rmse"])
    assert mean + half < 0.1, (mean, half)


def test_sp_truth_only_counts_scatterers_inside_the_fov():
    """A ray tracer reports SPs at any range; the evaluation truth must only hold those the
    vehicle could measure (inside fov_range), else far SPs count as missed for every variant."""
    import dataclasses

    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.scenes.scenario import load_preset
    from mmslam.scenes.trajectory import vehicle_trajectories
    from mmslam.slam.eval.evaluation import first_seen as _first_seen

    scn = load_preset("paper")
    states = vehicle_trajectories(scn, 12)
    src = AnalyticSource(dataclasses.replace(scn, sensor=dataclasses.replace(scn.sensor, fov_range=1e9)))
    parts = [src.trace_step(k, states[k]) for k in range(12)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    seen = _first_seen(paths, 2, 12, states[:, :, :3], scn.sensor)
    # every SP is in the (FOV-free) paths from step 0 ...
    assert len({i for i, t in zip(paths["landmark_id"], paths["type"]) if t == 2}) == 4
    for n in range(2):
        for lid, (k0, pos) in seen[2][n].items():
            # ... but counts only from the first step it is within 50 m of the antenna
            d = np.linalg.norm(states[:, n, :3] - pos, axis=1)
            assert d[k0] <= 50.0 and np.all(d[:k0] > 50.0)
        far = [lid for lid, p in zip(paths["landmark_id"], paths["type"]) if p == 2
               and np.all(np.linalg.norm(states[:, n, :3] - paths_pos(paths, lid), axis=1) > 50.0)]
        assert not set(far) & set(seen[2][n])
    # VAs have no range limit: all four counted from step 0
    assert all(k0 == 0 for k0, _ in seen[1][0].values()) and len(seen[1][0]) == 4


def paths_pos(paths, lid):
    i = int(np.nonzero(np.asarray(paths["landmark_id"]) == lid)[0][0])
    return np.array([paths["lm_x"][i], paths["lm_y"][i], paths["lm_z"][i]])


def test_estimate_extraction_threshold_and_vo_ma():
    from mmslam.slam.filter import cardinality, estimates_of
    from mmslam.slam.core.gm import GM

    w = np.array([2.2, 0.6, 0.4, 1.4, 0.0])
    m = np.arange(15, dtype=float).reshape(5, 3)
    g = GM(w, m, np.broadcast_to(np.eye(3), (5, 3, 3)).copy(), np.array([1, 1, 1, 1, 0], bool))
    X, _ = estimates_of(g, 0.55)
    np.testing.assert_array_equal(X, m[[0, 1, 3]])  # one per Gaussian above the threshold
    X, wx = estimates_of(g, 0.55, "vo_ma")  # round(w) copies of each Gaussian with w > 0.5
    np.testing.assert_array_equal(X, m[[0, 0, 1, 3]])
    np.testing.assert_array_equal(wx, w[[0, 0, 1, 3]])
    assert cardinality(g) == pytest.approx(4.6)
    with pytest.raises(MmslamError, match="extraction"):
        estimates_of(g, 0.5, "nope")


@pytest.mark.parametrize("scope", ["newborn", "all"])
def test_vs_dithering_scope(paper, scope):
    """newborn: a tracked VS Gaussian is predicted with J P J^T + Q only; all: + T_d as well."""
    import dataclasses

    from mmslam.slam.models.dynamics import vs_ct, vs_ct_jacobian
    from mmslam.slam.filter import LocalFilter
    from mmslam.slam.core.gm import GM
    from mmslam.slam.models.measurement import VS

    scn = paper[0]
    scn = dataclasses.replace(scn, filter=dataclasses.replace(scn.filter, vs_dither_scope=scope))
    f = LocalFilter(scn, "proposed", 4, scn.vehicles[0].initial_state, np.eye(5), 1e-3,
                    lambda u, x, t: np.full(np.broadcast_shapes(u.shape[:-1], x.shape[:-1]), 0.95),
                    np.random.default_rng(0))
    m0 = np.array([10.0, 5.0, 0.0, 3.0, -1.0, 0.0, 0.1])
    P0 = np.diag([2.0, 2.0, 0.1, 1.0, 1.0, 0.1, 0.01])
    f.maps[VS] = GM(np.full((4, 1), 0.9), np.broadcast_to(m0, (4, 1, 7)).copy(),
                    np.broadcast_to(P0, (4, 1, 7, 7)).copy(), np.ones((4, 1), bool))
    f.predict(1.0, 0.0)  # no previous measurements: no births
    J = vs_ct_jacobian(m0[None], scn.dt)[0]
    want = J @ P0 @ J.T + np.diag(np.asarray(scn.filter.vs_process_std) ** 2)
    if scope == "all":
        want = want + np.diag(scn.filter.vs_dither)
    np.testing.assert_allclose(f.maps[VS].P[0, 0], want, rtol=1e-12)
    np.testing.assert_allclose(f.maps[VS].m[0, 0], vs_ct(m0[None], scn.dt)[0])


@pytest.mark.parametrize("p_va, kept", [(0.95, 0.5), (0.5, 1.0)])
def test_accumulated_fov_uses_the_filters_detection_probability_and_gamma(p_va, kept):
    """A BS-map VA the uploading vehicle did not report is a possible false alarm (beta = 1/2) only if
    the filter expected to detect it: p_detect_va >= fusion.gamma_detect (0.9); a VA with p_D = 0.5
    (occluded walls in a city) is never judged so and keeps beta = 1."""
    import dataclasses

    from mmslam.slam.filter import FusionCenter
    from mmslam.slam.core.gm import GM, empty
    from mmslam.slam.models.measurement import VA

    scn = load_preset("paper")
    scn = with_overrides(scn, [f"filter.types.VA.p_detect={p_va}"])
    fc = FusionCenter(scn, "baseline")
    fc.maps[VA] = GM(np.array([1.0]), np.array([[200.0, 0.0, 40.0]]), np.eye(3)[None], np.ones(1, bool))
    fused = fc.fuse({VA: empty((), 0, 3)}, np.array([[70.0, 0.0, 0.0]]), np.zeros(7), np.eye(7))
    assert fused[VA].w[fused[VA].mask].tolist() == [kept]


def test_odometry_reference_is_dead_reckoning_with_empty_maps(paper):
    scn, states, paths = paper
    odo = run_filter(scn, states, paths, variant="odometry", particles=20, seed=3, steps=12)
    dr = run_filter(scn, states, paths, variant="proposed", particles=20, seed=3, steps=12, measurement_update=False)
    np.testing.assert_allclose(odo.vehicles["pos_err"], dr.vehicles["pos_err"], rtol=1e-12)
    assert odo.meta["variant"] == "odometry" and odo.meta["measurement_update"] is False
    m = odo.metrics
    assert np.all(m["n_est"] == 0) and np.all(m["card"] == 0)
    c = scn.evaluation.gospa_c  # an empty estimate: every true landmark missed at c^2 / 2 (alpha = 2, p = 2)
    np.testing.assert_allclose(m["gospa"], np.sqrt(m["n_true"] * c**2 / 2), rtol=1e-12)
    with pytest.raises(MmslamError, match="unknown variant"):
        run_filter(scn, states, paths, variant="odometer", particles=5, steps=2)


def test_visible_counts_separate_forgetting_from_never_seeing(paper):
    """paper: the four walls are visible from both vehicles at every step (4 VAs per map), each
    vehicle sees the other as a VS (1 per vehicle map, 2 in the fused map); SPs are visible only
    inside the 50 m FOV, never more than the truth that counts them from their first sighting."""
    scn, states, paths = paper
    m = run_filter(scn, states, paths, variant="odometry", particles=5, seed=0, steps=20).metrics
    mp, ty = np.asarray(m["map"]).astype(str), np.asarray(m["type"]).astype(str)
    assert np.all(m["n_visible"][ty == "VA"] == 4)
    assert np.all(m["n_visible"][(ty == "VS") & (mp != "fused")] == 1)
    assert np.all(m["n_visible"][(ty == "VS") & (mp == "fused")] == 2)
    sp = ty == "SP"
    assert np.all(m["n_visible"][sp] <= m["n_true"][sp])
    assert m["n_visible"][sp].min() < m["n_true"][sp].max()  # an SP left the FOV: still in the truth


def test_facades_of_two_objects_on_one_plane_are_one_va_in_the_truth():
    """Two wall segments of different buildings on the plane y = 10 mirror the BS to the same
    image source: one VA for the evaluation (the filter cannot tell them apart, nor should it)."""
    from mmslam.slam.eval.evaluation import first_seen as _first_seen, truth_keys
    from mmslam.slam.models.measurement import VA

    scn = load_preset("paper")
    img = (0.0, 20.0, 40.0)  # BS (0, 0, 40) mirrored in y = 10
    paths = {"step": np.array([0, 1, 2]), "rx": np.array([0, 0, 1]), "type": np.array([VA, VA, VA]),
             "landmark_id": np.array(["bldg_a:plane(0,1,0,10)", "bldg_b:plane(0,1,0,10)", "bldg_c:plane(1,0,0,5)"]),
             "lm_x": np.array([img[0], img[0] + 2e-4, 10.0]), "lm_y": np.array([img[1], img[1], 0.0]),
             "lm_z": np.array([img[2], img[2], 40.0])}
    keys = truth_keys(paths)
    assert keys[0] == keys[1] != keys[2]
    pos = np.zeros((3, 2, 3))
    seen = _first_seen(paths, 2, 3, pos, scn.sensor)[VA]
    assert len(seen[0]) == 1 and len(seen[1]) == 1  # vehicle 0: the two facades are one VA


def test_order_two_vas_count_in_the_truth_and_the_visible_counts_like_order_one():
    """Second-order reflections (issue 24): an order-2 VA row (bounces = 2, landmark the image of an image)
    is a VA of the truth from the step it is observed, in first_seen and visible_counts alike; the two
    orders of a wall-ground pair (perpendicular mirrors commute: one image) are one VA."""
    from mmslam.slam.eval.evaluation import first_seen as _first_seen, truth_keys, visible_counts
    from mmslam.slam.models.measurement import VA

    scn = load_preset("paper")
    # BS (0, 0, 40): in x = 100 -> (200, 0, 40); then in z = 0 -> (200, 0, -40), either order
    paths = {"step": np.array([0, 1, 1, 2]), "rx": np.array([0, 0, 1, 1]), "type": np.full(4, VA),
             "bounces": np.array([1, 2, 2, 2]),
             "landmark_id": np.array(["wall:-x", "wall:-x|ground:+z", "ground:+z|wall:-x", "wall:-x|west:+x"]),
             "lm_x": np.array([200.0, 200.0, 200.0, -400.0]), "lm_y": np.zeros(4),
             "lm_z": np.array([40.0, -40.0, -40.0, 40.0])}
    keys = truth_keys(paths)
    assert keys[1] == keys[2] and len(set(keys)) == 3
    pos = np.zeros((3, 2, 3))
    seen = _first_seen(paths, 2, 3, pos, scn.sensor)[VA]
    assert {k: s for k, (s, _) in seen[0].items()} == {keys[0]: 0, keys[1]: 1}
    assert {k: s for k, (s, _) in seen[1].items()} == {keys[2]: 1, keys[3]: 2}
    vis = visible_counts(paths, 2, 3, pos, scn.sensor)[VA]
    np.testing.assert_array_equal(vis, [[1, 0, 1], [1, 1, 1], [0, 1, 1]])


def test_unconfirmed_counts_are_the_truths_seen_at_one_step_so_far():
    """Hand-counted: VA a seen at steps 0 and 3 (confirmed from 3 on), b at step 1 only, c by both vehicles at
    step 2 only (one step: still unconfirmed), d at steps 2 and 4 by different vehicles; min_steps = 3 keeps a
    until the end too. The fused truth count of each step minus these is what a two-detection filter can find."""
    from mmslam.slam.eval.evaluation import sightings, unconfirmed_counts
    from mmslam.slam.models.measurement import VA

    scn = load_preset("paper")
    rows = [(0, 0, "a", 20.0), (3, 0, "a", 20.0), (1, 1, "b", 60.0), (2, 0, "c", 100.0), (2, 1, "c", 100.0),
            (2, 1, "d", 140.0), (4, 0, "d", 140.0)]
    paths = {"step": np.array([r[0] for r in rows]), "rx": np.array([r[1] for r in rows]),
             "type": np.full(len(rows), VA), "landmark_id": np.array([r[2] for r in rows]),
             "lm_x": np.zeros(len(rows)), "lm_y": np.array([r[3] for r in rows]), "lm_z": np.full(len(rows), 40.0)}
    pos = np.zeros((5, 2, 3))
    np.testing.assert_array_equal(unconfirmed_counts(paths, 2, 5, pos, scn.sensor)[VA], [1, 2, 4, 3, 2])
    np.testing.assert_array_equal(unconfirmed_counts(paths, 2, 5, pos, scn.sensor, min_steps=3)[VA], [1, 2, 4, 4, 4])
    np.testing.assert_array_equal(unconfirmed_counts(paths, 2, 3, pos, scn.sensor)[VA], [1, 2, 4])  # steps < 3 only
    # the distinct steps behind those counts, by hand (keyed by position: a, b, c, d at y = 20, 60, 100, 140 m)
    by_y = lambda seen: {round(float(k.split(",")[1]) / 1000): sorted(v) for k, v in seen.items()}  # noqa: E731
    assert by_y(sightings(paths, 5, pos, scn.sensor)[VA]) == {20: [0, 3], 60: [1], 100: [2], 140: [2, 4]}
    assert by_y(sightings(paths, 3, pos, scn.sensor)[VA]) == {20: [0], 60: [1], 100: [2], 140: [2]}


def test_va_truths_closer_than_the_resolution_are_one():
    """evaluation.va_resolution (1 m): the images of two parallel facades 0.4 m apart (0.8 m apart) are one
    VA for the truth, those of facades 0.765 m apart (canyon's, images 1.53 m apart) stay two; a chain
    of images each within the resolution of the next is one only as far as the resolution from its first (40 and
    40.9 one, 41.8 another: single linkage made facets 3.4 m end to end one truth); the keys of one cluster are the
    first's."""
    from mmslam.slam.eval.evaluation import first_seen as _first_seen, resolve_points, truth_keys
    from mmslam.slam.models.measurement import VA

    y = [20.0, 20.8, 22.33, 40.0, 40.9, 41.8]  # 20 / 20.8 one; 22.33 apart; 40 - 40.9 one, 41.8 1.8 m from 40
    n = len(y)
    paths = {"step": np.arange(n), "rx": np.zeros(n, int), "type": np.full(n, VA),
             "landmark_id": np.array([f"f{i}" for i in range(n)]), "lm_x": np.zeros(n), "lm_y": np.array(y),
             "lm_z": np.full(n, 40.0)}
    k = truth_keys(paths, 1.0)
    assert k[0] == k[1] != k[2] and k[3] == k[4] != k[5] and len({k[0], k[2], k[3], k[5]}) == 4
    assert len(set(truth_keys(paths))) == n  # the default key resolution (1 mm): all distinct
    seen = _first_seen(paths, 1, n, np.zeros((n, 1, 3)), load_preset("paper").sensor, 1.0)[VA][0]
    assert len(seen) == 4 and sorted(s for s, _ in seen.values()) == [0, 2, 3, 5]
    np.testing.assert_array_equal(resolve_points(np.array([[0, 0, 0], [0, 0, 0.99], [0, 0, 3.0]]), 1.0),
                                  [0, 0, 2])
    # rows out of sorted order: clusters follow the order of appearance (41.8 first, so 40.9 joins it, not 40.0)
    yo = [41.8, 40.0, 40.9, 41.8]
    po = dict(paths, step=np.arange(4), rx=np.zeros(4, int), type=np.full(4, VA),
              landmark_id=np.array([f"g{i}" for i in range(4)]), lm_x=np.zeros(4), lm_y=np.array(yo),
              lm_z=np.full(4, 40.0))
    ko = truth_keys(po, 1.0)
    assert ko[0] == ko[2] == ko[3] != ko[1] and ko[0].endswith(",41800,40000")
    # a chain of ten facets 0.6 m apart (5.4 m end to end): clusters of two, each member within 1 m of its first
    chain = np.stack([np.zeros(10), 0.6 * np.arange(10), np.zeros(10)], -1)
    c = resolve_points(chain, 1.0)
    np.testing.assert_array_equal(c, [0, 0, 2, 2, 4, 4, 6, 6, 8, 8])
    assert (np.linalg.norm(chain - chain[c], axis=-1) < 1.0).all()
    # the first cluster within the resolution wins (0.9 from 0, 0.5 from 1.4's own): order of appearance decides
    np.testing.assert_array_equal(resolve_points(np.array([[0, 0, 0], [0, 1.4, 0], [0, 0.9, 0]]), 1.0), [0, 1, 0])


def test_power_aware_sensor_gives_the_filter_each_measurements_covariance(paper, monkeypatch):
    """sensor.model = link: every correction gets R_z = r_scale diag(R_meas) of exactly its measurements."""
    from mmslam.scenes.scenario import with_overrides
    from mmslam.slam import filter as F

    scn, states, paths = paper
    scn = with_overrides(scn, ["sensor.model=link"])
    seen = []
    orig = F.LocalFilter.step

    def spy(self, Z, speed=None, turn_rate=None, R_z=None):
        seen.append((Z.shape[0], None if R_z is None else R_z.copy()))
        return orig(self, Z, speed, turn_rate, R_z)

    monkeypatch.setattr(F.LocalFilter, "step", spy)
    run_filter(scn, states, paths, variant="proposed", particles=10, seed=0, steps=6)
    assert len(seen) == 12 and all(R is not None and R.shape == (J, 5, 5) for J, R in seen)
    J, R = seen[-1]
    assert np.all(R[:, ~np.eye(5, dtype=bool)] == 0) and np.all(np.diagonal(R, axis1=1, axis2=2) > 0)
    assert len({tuple(np.round(np.diag(r), 12)) for r in R}) > 1  # measurements differ in accuracy


def test_weighted_state_cov_rejects_weights_of_another_length():
    """The compiled sum reads ``w[p]`` for every state without bounds checks: a shorter ``w`` read
    past it (the einsum raised); now a ValueError naming the shapes."""
    from mmslam.slam.filter.rbpf import weighted_state_cov

    s = np.arange(70.0).reshape(10, 7)
    with pytest.raises(ValueError, match="weighted_state_cov"):
        weighted_state_cov(s, np.full(3, 1 / 3), s.mean(0))
    with pytest.raises(ValueError, match="weighted_state_cov"):
        weighted_state_cov(s, np.full(10, 0.1), s.mean(0)[:3])


def test_weighted_state_cov_equals_the_einsum_bit_for_bit():
    """The compiled weighted outer-product sum gives the same bits as the NumPy form it replaced."""
    from mmslam.slam.models.dynamics import wrap_angle
    from mmslam.slam.filter.rbpf import weighted_state_cov, weighted_state_mean

    rng = np.random.default_rng(12)
    for P_ in (1, 7, 300, 3000):
        s = rng.normal(size=(P_, 7)) * [50, 50, 1, 3, 20, 0.3, 200]
        w = rng.random(P_)
        w /= w.sum()
        mean = weighted_state_mean(s, w)
        d = s - mean
        d[:, 3] = wrap_angle(d[:, 3])
        assert np.array_equal(weighted_state_cov(s, w, mean), np.einsum("p,pa,pb->ab", w, d, d))


def test_propagate_equals_the_numpy_form_bit_for_bit():
    """The compiled noise step of ``propagate`` gives the same bits (same draws, same order) as the
    NumPy form it replaced: CT transition, ``+ N(0, 1) * std``, known speed / turn rate, heading wrapped."""
    from mmslam.slam.models.dynamics import vehicle_ct, wrap_angle
    from mmslam.slam.filter.rbpf import propagate

    rng = np.random.default_rng(3)
    std = np.array([0.2, 0.2, 0.0, 0.001, 0.5, 0.1, 0.2])
    for P_, turn in ((1, 0.0), (7, 1e-7), (300, np.pi / 10), (300, -2.0)):
        s = rng.normal(size=(P_, 7)) * [50, 50, 1, 4, 20, 0.3, 200]
        out = propagate(s, 22.22, turn, 0.5, std, np.random.default_rng(5))
        ref = s.copy()
        ref[:, 4], ref[:, 5] = 22.22, turn
        ref = vehicle_ct(ref, 0.5)
        ref += np.random.default_rng(5).standard_normal(ref.shape) * std[None, :]
        ref[:, 4], ref[:, 5] = 22.22, turn
        ref[:, 3] = wrap_angle(ref[:, 3])
        assert np.array_equal(out, ref)
        assert np.all(np.abs(out[:, 3]) <= np.pi)


def test_propagate_rejects_a_noise_std_of_another_length():
    """The compiled noise step reads ``std[i]`` for the 7 state components unchecked: a shorter
    ``noise_std`` raises a one-line ValueError naming the shapes first."""
    from mmslam.slam.filter.rbpf import propagate

    s = np.zeros((4, 7))
    with pytest.raises(ValueError, match="noise_std"):
        propagate(s, 1.0, 0.1, 0.5, np.ones(3), np.random.default_rng(0))
    with pytest.raises(ValueError, match="particles"):
        propagate(np.zeros((4, 6)), 1.0, 0.1, 0.5, np.ones(7), np.random.default_rng(0))


@pytest.mark.parametrize("p_detect", [0.95, 0.0])
def test_run_pd_fn_is_the_filters_type_probability_inside_the_sensors_fov(paper, p_detect):
    """``CooperativeRun.pd_fn`` == ``filter.p_detect_<type>`` where ``fov_detect_prob > 0`` else 0
    (its definition), bit for bit, for every type and a sensor that never detects."""
    import dataclasses

    from mmslam.slam.filter.fusion_center import filter_detect_probs
    from mmslam.slam.models.measurement import BS, SP, VA, VS
    from mmslam.slam.filter.run import CooperativeRun
    from mmslam.slam.sim.sensor import fov_detect_prob

    scn, states, paths = paper
    scn = dataclasses.replace(with_overrides(scn, ["filter.p_detect_va=0.5"]),  # the old flat key: an alias
                              sensor=dataclasses.replace(scn.sensor, p_detect=p_detect))
    run = CooperativeRun(scn, states, paths, "proposed", 3, 0, 2, evaluate=False)
    rng = np.random.default_rng(2)
    u = np.broadcast_to(rng.normal(size=(4, 1, 3)), (4, 5, 3))
    x = rng.normal(size=(4, 5, 3)) * scn.sensor.fov_range
    pd_type = filter_detect_probs(scn)
    for t in (BS, VA, SP, VS):
        want = np.where(fov_detect_prob(u, x, t, scn.sensor) > 0, pd_type[t], 0.0)
        got = run.pd_fn(u, x, t)
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, want)
        if p_detect == 0.0:
            assert not got.any()


@pytest.mark.parametrize("variant", ["baseline", "proposed"])
def test_no_pruning_runs(paper, variant):
    """``filter.prune = 0`` is inside its bounds: the filter keeps zero-weight and subnormal-weight
    components and still runs (it raised "singular or indefinite covariance in Gaussian-mixture
    merging" at step 2: a zero-weight cluster got a zero covariance; at step 5: subnormal weights)."""
    from mmslam.scenes.scenario import with_overrides

    scn, states, paths = paper
    res = run_filter(with_overrides(scn, ["filter.prune=0"]), states, paths, variant=variant, particles=20, seed=1,
                     steps=8)
    assert np.isfinite(_rmse(res, lo=0, hi=8))


def test_position_nees_by_hand_and_its_degenerate_cases():
    """``e^T P^-1 e`` on hand values: diag(1, 4) with e = (1, 2) gives 1 + 1 = 2; a correlated covariance against
    ``solve``; a singular covariance (one particle) is NaN; other shapes are refused."""
    from mmslam.slam.filter.rbpf import position_nees

    assert position_nees(np.array([1.0, 2.0]), np.diag([1.0, 4.0])) == pytest.approx(2.0, rel=1e-15)
    C = np.array([[2.0, 0.6], [0.6, 0.5]])
    e = np.array([0.3, -0.7])
    assert position_nees(e, C) == pytest.approx(float(e @ np.linalg.solve(C, e)), rel=1e-12)
    assert np.isnan(position_nees(e, np.zeros((2, 2))))
    with pytest.raises(ValueError, match="expected"):
        position_nees(np.zeros(3), np.eye(3))


def test_the_vehicle_rows_carry_the_nees_of_the_estimate_they_record(paper):
    """Each vehicle row's ``pos_nees`` is the horizontal error of that step's posterior mean against its particle
    covariance: recomputed from the run's own estimates and the truth (a second computation of the same quantity)."""
    from mmslam.slam.filter.run import CooperativeRun

    scn, states, paths = paper
    run = CooperativeRun(scn, states, paths, "proposed", 20, 3, 4)
    want = []
    for k in range(run.steps):
        for n, est in enumerate(run.step(k)):
            e = est.mean[0:2] - states[k, n, 0:2]
            want.append(float(e @ np.linalg.solve(est.cov[0:2, 0:2], e)))
    got = np.asarray(run.result().vehicles["pos_nees"], float)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert (got > 0).all()
