"""What the filter was given per sensor model (issue 24 report view): measurement origin counts per
vehicle-step, the estimator's counts, and paired comparisons between sensor-model arms."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import t as student_t

from mmslam.cli import main
from mmslam.pipelines import ablate as A
from mmslam.pipelines.ablate.sensor_models import link_pd_notice, measurement_rows, sensor_model, sensor_pairs
from mmslam.slam.sim.sensor import Measurements


def _meas(mask: np.ndarray, otype: np.ndarray) -> Measurements:
    s, v, j = mask.shape
    return Measurements(z=np.zeros((s, v, j, 5)), mask=mask, origin_type=otype.astype(np.int8),
                        origin_id=np.full((s, v, j), "", object), origin_pos=np.full((s, v, j, 3), np.nan),
                        true_states=np.zeros((s, v, 7)), clutter_intensity=0.0, R=np.eye(5))


def test_origin_counts_count_live_slots_by_type_other_and_clutter() -> None:
    # step 0, vehicle 0: BS, VA, VA, clutter; vehicle 1: VS, OTHER, and a padded slot that says VA (not live)
    mask = np.array([[[1, 1, 1, 1], [1, 1, 0, 0]]], bool)
    ot = np.array([[[0, 1, 1, -1], [3, 4, 1, -1]]])
    cols, c = _meas(mask, ot).origin_counts()
    assert cols == ["BS", "VA", "SP", "VS", "OTHER", "clutter"]
    assert c.shape == (1, 2, 6)
    assert c[0, 0].tolist() == [1, 2, 0, 0, 0, 1]
    assert c[0, 1].tolist() == [0, 0, 0, 1, 1, 0]


def test_run_meta_counts_every_measurement_the_filter_was_given() -> None:
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.scenes.scenario import load_preset
    from mmslam.scenes.trajectory import vehicle_trajectories
    from mmslam.slam.filter.run import CooperativeRun

    scn = load_preset("paper")
    states = vehicle_trajectories(scn, 4)
    parts = [AnalyticSource(scn).trace_step(k, states[k]) for k in range(4)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    run = CooperativeRun(scn, states, paths, "baseline", 10, 3, 4, evaluate=False)
    used = np.array([[run.local_inputs(k, n)[0].shape[0] for n in range(run.n_veh)] for k in range(4)])
    md = run.result().meta["measurement_counts"]
    c = np.asarray(md["per_step_vehicle"])
    assert md["model"] == "constant" and md["columns"][-1] == "clutter"
    assert c.sum(axis=-1).tolist() == used.tolist()


def test_sensor_pairs_compare_each_arm_with_the_link_twin_of_the_same_variant_and_settings() -> None:
    def runs(vals: list[float]) -> dict:
        return {s: {"fused": {"gospa_VA": v, "gospa_VS": 2 * v, "pos_rmse": 0.1}} for s, v in enumerate(vals)}

    est = "proposed[sensor.model=estimated]"
    link = "proposed[sensor.model=link]"
    const = "proposed[sensor.model=constant]"
    other = "proposed[filter.merge=4,sensor.model=estimated]"
    per_run = {est: runs([5.0, 6.1, 7.2]), link: runs([4.0, 5.0, 6.0]), const: runs([1.0, 1.0, 1.0]),
               other: runs([0.0, 0.0, 0.0])}
    models = {lab: sensor_model(lab, {}) for lab in per_run}
    assert models == {est: "estimated", link: "link", const: "constant", other: "estimated"}
    rows = {r["variant"]: r for r in sensor_pairs(per_run, models)}
    assert set(rows) == {est, const}  # link is the reference; `other` has no link twin with filter.merge=4
    r = rows[est]
    assert r["reference"] == link and r["n"] == 3
    d = np.array([1.0, 1.1, 1.2])  # paired differences: sd 0.1, 95% half-width 4.303 * 0.1 / sqrt(3) = 0.248
    half = student_t.ppf(0.975, 2) * d.std(ddof=1) / math.sqrt(3)
    assert half == pytest.approx(0.2484, abs=1e-4)
    assert r["gospa_VA_diff"] == pytest.approx(1.1) and r["gospa_VA_diff_ci"] == pytest.approx(half)
    assert r["gospa_VA"] == pytest.approx(6.1) and r["gospa_VA_ref"] == pytest.approx(5.0)
    assert r["gospa_VS_diff"] == pytest.approx(2.2) and r["gospa_VA_sig"] is True
    assert r["pos_rmse_diff"] == pytest.approx(0.0) and r["pos_rmse_sig"] is False
    assert rows[const]["reference"] == link and rows[const]["gospa_VA_diff"] == pytest.approx(-4.0)


def test_measurement_rows_average_per_vehicle_step_over_runs() -> None:
    class R:
        def __init__(self, counts: list, est: list | None = None) -> None:
            self.meta = {"measurement_counts": {"model": "estimated", "columns": ["BS", "clutter"],
                                                "per_step_vehicle": counts}}
            if est is not None:
                self.meta["estimator_counts"] = {"columns": ["estimates", "merged"], "per_step_vehicle": est}

    jobs = {A.Job("proposed", 0): R([[[1, 0], [1, 2]]], [[[3, 1], [5, 1]]]),
            A.Job("proposed", 1): R([[[1, 4], [1, 2]]], [[[3, 0], [5, 0]]])}
    (row,) = measurement_rows(jobs, ["proposed"], {})
    assert row["model"] == "estimated" and row["runs"] == 2
    assert row["measurements"] == {"BS": 1.0, "clutter": 2.0}
    assert row["estimator"] == {"estimates": 4.0, "merged": 0.5}
    assert row["p_detect_from_link"] is None and link_pd_notice([row]) is None


def test_the_link_budget_p_d_is_averaged_per_label_and_named_in_one_line() -> None:
    class R:
        def __init__(self, pd: float | None) -> None:
            self.meta = {} if pd is None else {"p_detect_from_link": {"VS": {"p_detect": pd, "paths": 80}}}

    jobs = {A.Job("proposed", 0): R(0.5), A.Job("proposed", 1): R(0.3), A.Job("baseline", 0): R(None)}
    rows = measurement_rows(jobs, ["proposed", "baseline"], {})
    assert rows[0]["p_detect_from_link"] == {"VS": pytest.approx(0.4)} and rows[1]["p_detect_from_link"] is None
    assert link_pd_notice(rows) == "p_D from the link budget (filter.types.<T>.p_detect_source = link): proposed: VS 0.40"


def test_measurement_rows_average_runs_that_store_different_columns() -> None:
    """A resumed ablation: a run stored before the estimator's ``suppressed`` column and one after; each
    column is averaged over the runs that have it (no crash on the ragged blocks)."""
    class R:
        def __init__(self, cols: list, est: list) -> None:
            self.meta = {"estimator_counts": {"columns": cols, "per_step_vehicle": est}}

    old = ["estimates", "detected", "merged", "false", "missed"]
    jobs = {A.Job("proposed", 0): R(old, [[[3, 2, 1, 1, 0], [5, 5, 0, 0, 2]]]),
            A.Job("proposed", 1): R(old + ["suppressed"], [[[1, 1, 0, 0, 1, 2], [2, 2, 0, 0, 1, 6]]])}
    (row,) = measurement_rows(jobs, ["proposed"], {})
    assert row["estimator"] == {"estimates": 2.75, "detected": 2.5, "merged": 0.25, "false": 0.25, "missed": 1.0,
                                "suppressed": 4.0}
    assert list(row["estimator"]) == old + ["suppressed"]


@pytest.mark.slow
def test_report_shows_measurements_and_the_paired_sensor_models(tmp_path: Path) -> None:
    d = tmp_path / "abl"
    code = main(["ablate", "paper", "--source", "analytic", "--variants", "proposed", "--grid",
                 "sensor.model=constant,link", "--mc", "2", "--steps", "6", "--particles", "20", "--workers", "1",
                 "--out", str(d), "--report"])
    assert code == 0
    text = (d / "report.html").read_text()
    table = text.split('<table id="measurements">')[1].split("</table>")[0]
    rows = re.findall(r'<tr data-variant="([^"]+)" data-model="([^"]+)">', table)
    assert rows == [("proposed[sensor.model=constant]", "constant"), ("proposed[sensor.model=link]", "link")]
    jobs = A.load_jobs(d)
    for lab, _ in rows:  # each cell: the mean per vehicle-step of the stored counts
        c = np.concatenate([np.asarray(r.meta["measurement_counts"]["per_step_vehicle"], float).reshape(-1, 6)
                            for j, r in jobs.items() if j.label == lab])
        row = table.split(f'data-variant="{lab}"')[1].split("</tr>")[0]
        got = [float(x) for x in re.findall(r'data-col="(?:BS|VA|SP|VS|OTHER|clutter)">([0-9.]+)<', row)]
        assert got == pytest.approx(np.round(c.mean(axis=0), 2).tolist(), abs=5e-3)
    pairs = text.split('<table id="sensor-pairs">')[1].split("</table>")[0]
    assert pairs.count('data-variant="proposed[sensor.model=constant]"') == 3  # VA, VS, RMSE vs the link arm
