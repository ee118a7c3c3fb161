"""Per-type VA merge gate (filter.types.VA.merge, alias filter.merge_va) and the city defaults on canyon
(issues 10 and 22)."""
from __future__ import annotations


import numpy as np
import pytest
from scipy import stats

from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.filter import FusionCenter, LocalFilter
from mmslam.slam.core.gm import GM, empty
from mmslam.slam.specs.landmarks import landmark_type
from mmslam.slam.models.measurement import SP, VA, VS

# Two VAs 1.53 m apart in y (canyon's image sources of the facades y = 9.57 and y = 10.34), each with
# position covariance 0.25 I m^2: squared Mahalanobis distance 1.53^2 / 0.25 = 9.36 (between 4 and 49).
M2 = np.array([[-33.0, 29.14, 25.0], [-33.0, 30.67, 25.0]])
W2 = np.array([0.9, 0.6])


def _scn(**filt):
    """paper with these [filter] keys (old flat aliases such as merge_va allowed) set as by --set."""
    return with_overrides(load_preset("paper"), [f"filter.{k}={v}" for k, v in filt.items()])


def _pair(batch: tuple[int, ...]) -> GM:
    w = np.broadcast_to(W2, batch + (2,)).copy()
    m = np.broadcast_to(M2, batch + (2, 3)).copy()
    P = np.broadcast_to(0.25 * np.eye(3), batch + (2, 3, 3)).copy()
    return GM(w, m, P, np.ones(batch + (2,), bool))


def test_merge_gate_is_merge_va_for_vas_and_merge_for_the_others():
    scn = _scn(merge=49.0, merge_va=4.0)
    assert landmark_type(VA).merge_gate(scn) == 4.0
    assert landmark_type(SP).merge_gate(scn) == landmark_type(VS).merge_gate(scn) == 49.0
    paper = load_preset("paper")
    assert paper.filter.merge == 49.0 and landmark_type(VA).merge_gate(paper) == 49.0  # paper unchanged


def test_unset_merge_va_follows_filter_merge():
    """A VA merge gate that is not set (``merge_va`` < 0) means filter.merge: an override of filter.merge (TOML,
    --set, a grid) then reaches the VA maps, locally and in the fused-map reduction, as before merge_va existed.
    The built-in VA row sets 6 (docs/city-slam.md); ``paper`` pins the paper's single gate, 49."""
    assert load_preset("canyon").filter.types["VA"].merge == 6.0
    assert load_preset("paper").filter.types["VA"].merge == 49.0
    scn = with_overrides(load_preset("paper"), ["filter.merge_va=-1", "filter.merge=4"])
    assert scn.filter.merge_va < 0
    assert landmark_type(VA).merge_gate(scn) == landmark_type(SP).merge_gate(scn) == 4.0
    assert scn.filter.types["VA"].merge == -1.0
    assert landmark_type(VA).merge_gate(with_overrides(scn, ["filter.merge_va=9"])) == 9.0
    assert landmark_type(VA).merge_gate(with_overrides(scn, ["filter.types.VA.merge=9"])) == 9.0
    assert landmark_type(VA).merge_gate(with_overrides(scn, ["filter.merge_va=9", "filter.merge_va=-1"])) == 4.0


@pytest.mark.parametrize("merge_va, n_va", [(4.0, 2), (49.0, 1)])
def test_local_reduction_merges_close_vas_only_within_merge_va(merge_va, n_va):
    """Squared distance 9.36: kept apart with merge_va = 4, merged with 49; the SP map (filter.merge = 49)
    merges the same pair whatever merge_va is. The merged Gaussian: weight 1.5, mean at
    y = (0.9 * 29.14 + 0.6 * 30.67) / 1.5 = 29.752."""
    scn = _scn(merge=49.0, merge_va=merge_va)
    f = LocalFilter(scn, "baseline", 2, scn.vehicles[0].initial_state, np.eye(5), 1e-3,
                    lambda u, x, t: np.zeros(np.broadcast_shapes(u.shape[:-1], x.shape[:-1])),
                    np.random.default_rng(0))
    f.maps[VA], f.maps[SP] = _pair((2,)), _pair((2,))
    f.reduce()
    va, sp = f.maps[VA], f.maps[SP]
    assert va.mask[0].sum() == n_va and sp.mask[0].sum() == 1
    assert sp.w[0][sp.mask[0]][0] == pytest.approx(1.5)
    assert sp.m[0][sp.mask[0]][0, 1] == pytest.approx(29.752)
    if n_va == 2:
        np.testing.assert_allclose(np.sort(va.m[0][va.mask[0]][:, 1]), M2[:, 1])


@pytest.mark.parametrize("merge_va, n_va", [(4.0, 2), (49.0, 1)])
def test_fused_va_map_reduction_uses_merge_va(merge_va, n_va):
    """The BS map's reduction after an upload uses the VA gate too (p_detect_va = 0.2 < gamma_D: the
    unreported VAs keep beta = 1, so only the gate decides)."""
    scn = _scn(merge=49.0, merge_va=merge_va, p_detect_va=0.2)
    fc = FusionCenter(scn, "baseline")
    fc.maps[VA] = _pair(())
    fused = fc.fuse({VA: empty((), 0, 3)}, np.array([[0.0, 0.0, 1.6]]), np.zeros(7), np.eye(7))
    g = fused[VA]
    assert g.mask.sum() == n_va
    assert g.w[g.mask].sum() == pytest.approx(1.5)


@pytest.mark.slow
def test_canyon_defaults_lower_the_fused_va_gospa_paired_over_seeds(tmp_path):
    """Sionna-traced canyon (no [filter] / [fusion] tables: the defaults), proposed, P = 300, seeds 0-9,
    steps k >= 10: the defaults (docs/city-slam.md) give a lower fused VA GOSPA than the paper's filter
    settings, the defaults before issue 22 (r_scale 9, fixed p_D 0.95, VA threshold 0.7, no labels,
    equal AA weights), on every seed's pairing (95% CI of the paired difference below 0), and the
    position RMSE stays >= 30% below dead reckoning. Ten seeds, not five: since the fused map keeps both
    shares of a matched pair (session 24) the difference is bimodal, -1.4 to -4.8 m where canyon's VA seen
    by one car is lost late and -15 to -17 m where it stays (seeds 0-9: -7.1 +- 4.4 m; seeds 0-4 alone
    -8.2 +- 9.4 m, every seed lower but the t interval too wide)."""
    from mmslam.pipelines.ablate import prepare_cache
    from mmslam.slam.filter import run_slam

    cache = prepare_cache("canyon", "sionna", tmp_path, progress=False)
    old = ("filter.r_scale=9", "filter.pd_model=fixed", "filter.p_detect_va=0.95", "filter.threshold_va=0.7",
           "fusion.average_by_label=false", "fusion.aa_weights=equal")

    def score(r):
        m, v = r.metrics, r.vehicles
        sel = ((np.asarray(m["map"]).astype(str) == "fused") & (np.asarray(m["type"]).astype(str) == "VA")
               & (np.asarray(m["step"]) >= 10))
        e = np.asarray(v["pos_err"], float)[np.asarray(v["step"]) >= 10]
        return float(np.asarray(m["gospa"], float)[sel].mean()), float(np.sqrt(np.mean(e * e)))

    new_va, old_va, rmse, odo = [], [], [], []
    for s in range(10):
        g, e = score(run_slam(cache, "proposed", 300, s))
        new_va.append(g)
        rmse.append(e)
        old_va.append(score(run_slam(cache, "proposed", 300, s, overrides=old))[0])
        odo.append(score(run_slam(cache, "odometry", 300, s))[1])
    d = np.array(new_va) - np.array(old_va)
    half = stats.t.ppf(0.975, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size)
    assert d.mean() + half < 0, (new_va, old_va)
    e2 = np.array(rmse) ** 2
    assert np.sqrt(e2.mean()) <= 0.7 * np.sqrt(np.mean(np.array(odo) ** 2)), (rmse, odo)
