"""The ``twc2020`` preset against Kim's TWC2020 MATLAB release (issue 23; docs/twc2020.md).

His code (HyowonKim-P1/5GmmWavePHDFilterMapFusion, run under Octave, one run each) gives a fused VA
GOSPA of 1.05 m with 100 particles and 1.36 m with 20 (his scoring: every VA in the truth from step 1,
the BS map at his upload steps k = 10:2:40). mmslam's baseline on the preset must put each value inside
the range of its own 10 seeds.
"""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.pipelines.ablate import (_fusion_start, _run_scores, load_jobs, prepare_cache, read_ablation,
                                     run_ablation, start_ablation_dir, upload_steps)
from mmslam.scenes.scenario import load_preset, preset_path


def _fused_va(out) -> np.ndarray:
    spec = read_ablation(out)
    up = upload_steps(spec["scenario"], int(spec["steps"]))
    assert up == list(range(9, 40, 2))  # his k = 10:2:40, from 1
    fs = _fusion_start(spec["scenario"])
    return np.array([_run_scores(r, list(spec["vehicle_names"]), fs, up)["fused"]["gospa_VA"]
                     for _, r in sorted(load_jobs(out).items())])


def test_twc2020_preset_is_kims_setup() -> None:
    scn = load_preset("twc2020")
    s = np.array([v.initial_state for v in scn.vehicles])
    np.testing.assert_allclose(np.hypot(s[:, 0], s[:, 1]), 70.73)  # one circle, opposite sides
    assert s[0, 0] == -s[1, 0] and s[0, 4] / s[0, 5] == pytest.approx(70.73, abs=0.01)
    assert sorted((abs(p.position[0]), abs(p.position[1])) for p in scn.scatterers) == [(65.0, 65.0)] * 4
    assert scn.sensor.p_detect == 1.0 and scn.filter.p_detect_va == 0.9
    # his filter, not mmslam's city defaults: one fixed P_D, the plain average of the maps, no labels
    assert scn.filter.pd_model == "fixed"
    assert (scn.fusion.aa_weights, scn.fusion.average_by_label) == ("equal", False)
    assert scn.filter.prior_std[3] == pytest.approx(np.deg2rad(0.3))
    assert (scn.fusion.start, scn.fusion.period) == ((9, 11), 4)
    assert (scn.evaluation.truth_set, scn.evaluation.fused_steps) == ("all", "uploads")


@pytest.mark.slow
@pytest.mark.parametrize("particles,kim", [(100, 1.05), (20, 1.36)])
def test_twc2020_fused_va_gospa_brackets_kims(tmp_path, particles: int, kim: float) -> None:
    out = start_ablation_dir(tmp_path / "abl")  # as the CLI does, before the trace
    cache = prepare_cache("twc2020", "analytic", out, progress=False)
    run_ablation(cache, out, "baseline", mc=10, particles=particles, workers=2, progress=False,
                 truth_scenario=preset_path("twc2020"))
    g = _fused_va(out)
    assert g.size == 10 and g.min() <= kim <= g.max(), (particles, g.round(2).tolist())
