"""Tests of mmslam.pipelines: ablation grid, executors, resume, aggregation, figures, report, CLI.

The end-to-end tests (``slow``) run the real filter through the CLI on the analytic source with
a small grid: 8 steps, P = 50, 2 seeds, 3 variants. The fast tests check the aggregation
arithmetic on hand-made results and the argument checks.
"""
from __future__ import annotations

import html.parser
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from mmslam.cli import main
from mmslam.pipelines import ablate as A
from mmslam.pipelines import figures as F
from mmslam.slam.filter.result import Result

STEPS, PARTICLES, MC = 8, 50, 2
SMALL = ["--source", "analytic", "--steps", str(STEPS), "--particles", str(PARTICLES), "--mc", str(MC),
         "--quiet"]


# ====================================================================== helpers
def _run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def _assert_one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ")
    for n in needles:
        assert n in lines[0]


def _jobs(d: Path) -> dict[A.Job, Result]:
    return {A.Job(v, s): Result.load(A.job_dir(d, A.Job(v, s))) for v in A.VARIANTS for s in range(MC)}


def _same_result(a: Result, b: Result) -> None:
    for name in ("vehicles", "metrics", "landmarks"):
        ta, tb = getattr(a, name), getattr(b, name)
        assert set(ta) == set(tb)
        for k in ta:
            va, vb = np.asarray(ta[k]), np.asarray(tb[k])
            assert va.shape == vb.shape, (name, k)
            if va.dtype.kind == "f":
                np.testing.assert_array_equal(va, vb, err_msg=f"{name}.{k}")
            else:
                assert va.tolist() == vb.tolist(), (name, k)
    # wall time is measured, the cache path differs between output directories; all else is equal
    strip = lambda m: {k: v for k, v in m.items() if k not in ("wall_time_s", "cache_path")}  # noqa: E731
    assert strip(a.meta) == strip(b.meta)


def _summary_tables_equal(a: A.Summary, b: A.Summary) -> None:
    assert set(a.table) == set(b.table)
    for k in a.table:
        va, vb = np.asarray(a.table[k]), np.asarray(b.table[k])
        if va.dtype.kind == "f":
            np.testing.assert_array_equal(va, vb, err_msg=k)
        else:
            assert va.tolist() == vb.tolist(), k


class _SummaryTableParser(html.parser.HTMLParser):
    """(variant, map, col) -> data-value of the report's <table id="summary">."""

    def __init__(self) -> None:
        super().__init__()
        self.inside = False
        self.row: tuple[str, str] | None = None
        self.cells: dict[tuple[str, str, str], str] = {}

    def handle_starttag(self, tag: str, attrs: list) -> None:
        a = dict(attrs)
        if tag == "table":
            self.inside = a.get("id") == "summary"
        elif self.inside and tag == "tr" and "data-variant" in a:
            self.row = (a["data-variant"], a["data-map"])
        elif self.inside and tag == "td" and "data-col" in a and self.row:
            self.cells[(*self.row, a["data-col"])] = a["data-value"]

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self.inside = False


def _expected_headline(jobs: dict[A.Job, Result], variant: str, map_: str, fusion_start: int) -> dict:
    """Headline numbers recomputed straight from the job results: each score is the mean over runs of
    the per-run score (mean GOSPA over steps >= fusion_start; the run's position RMSE), issue 23."""
    res = [r for j, r in jobs.items() if j.variant == variant]
    out = {}
    for ty in ("VA", "SP", "VS"):
        out[f"gospa_{ty}"] = float(np.mean([np.mean(np.asarray(r.metrics["gospa"], float)[
            (np.asarray(r.metrics["map"]).astype(str) == map_) & (np.asarray(r.metrics["type"]).astype(str) == ty)
            & (np.asarray(r.metrics["step"]) >= fusion_start)]) for r in res]))
    names = res[0].meta["vehicle_names"]
    rmse = []
    for r in res:
        sel = np.asarray(r.vehicles["step"]) >= fusion_start
        if map_ != "fused":
            sel &= np.asarray(r.vehicles["vehicle"]) == names.index(map_)
        e = np.asarray(r.vehicles["pos_err"], float)[sel]
        rmse.append(np.sqrt(np.mean(e ** 2)))
    out["pos_rmse"] = float(np.mean(rmse))
    nees = np.concatenate([np.asarray(r.vehicles["pos_nees"], float)[
        (np.asarray(r.vehicles["step"]) >= fusion_start)
        & ((np.asarray(r.vehicles["vehicle"]) == names.index(map_)) if map_ != "fused" else True)] for r in res])
    out["pos_nees"] = float(np.median(nees[np.isfinite(nees)]))  # pooled over runs and vehicle-steps
    out["runs"] = len(res)
    return out


# ====================================================================== fast unit tests
def test_parse_variants_keeps_order_and_rejects_unknown_and_duplicates() -> None:
    assert A.parse_variants("proposed, baseline") == ("proposed", "baseline")
    with pytest.raises(A.ConfigError, match="unknown variant 'cm2'"):
        A.parse_variants("baseline,cm2")
    with pytest.raises(A.ConfigError, match="given twice"):
        A.parse_variants("cm1,cm1")
    with pytest.raises(A.ConfigError, match="empty"):
        A.parse_variants(" , ")


def test_plan_jobs_is_the_variant_by_seed_grid() -> None:
    jobs = A.plan_jobs(["baseline", "proposed"], 3)
    assert [j.name for j in jobs] == ["baseline-seed0", "baseline-seed1", "baseline-seed2",
                                      "proposed-seed0", "proposed-seed1", "proposed-seed2"]


@pytest.mark.parametrize("kw, needle", [
    ({"mc": 0}, "--mc 0"), ({"particles": 0}, "--particles 0"), ({"steps": 0}, "--steps 0"),
    ({"executor": "ray"}, "--executor ray"), ({"scheduler": "tcp://x:1"}, "--scheduler"),
    ({"workers": 0}, "--workers 0"),
])
def test_check_run_args_rejects_bad_numbers(kw: dict, needle: str) -> None:
    args = {"mc": 2, "particles": 10, "steps": None, "executor": "local", "scheduler": None, "workers": None}
    args.update(kw)
    with pytest.raises(A.MmslamError) as e:
        A.check_run_args(**args)
    assert needle in str(e.value) and "\n" not in str(e.value)


def _hand_result(variant: str, seed: int, gospa: np.ndarray, pos_err: np.ndarray,
                 names: tuple[str, str] = ("veh1", "veh2"), extra_maps: tuple[str, ...] = (),
                 pos_nees: np.ndarray | None = None) -> Result:
    """A result with given fused-VS GOSPA per step and per-(step, vehicle) position errors."""
    steps = len(gospa)
    st, mp, ty, g = [], [], [], []
    for k in range(steps):
        for m in (*names, "fused", *extra_maps):
            for t in ("VA", "SP", "VS"):
                st.append(k), mp.append(m), ty.append(t), g.append(gospa[k] if (m, t) == ("fused", "VS") else 1.0)
    n = len(st)
    g = np.asarray(g, float)
    metrics = {"step": np.asarray(st, np.int32), "map": np.asarray(mp, object), "type": np.asarray(ty, object),
               "gospa": g, "loc": g ** 2, "missed": np.zeros(n), "false": np.zeros(n),
               "n_est": np.ones(n, np.int32), "n_true": np.ones(n, np.int32)}
    vst = np.repeat(np.arange(steps), 2).astype(np.int32)
    vid = np.tile([0, 1], steps).astype(np.int16)
    z = np.zeros(2 * steps)
    vehicles = {"step": vst, "vehicle": vid, "x": z, "y": z, "z": z, "heading": z, "bias": z, "true_x": z,
                "true_y": z, "true_z": z, "true_heading": z, "true_bias": z,
                "pos_err": np.asarray(pos_err, float).ravel(), "heading_err": z, "bias_err": z}
    if pos_nees is not None:
        vehicles["pos_nees"] = np.asarray(pos_nees, float).ravel()
    landmarks = {"step": np.zeros(0, np.int32), "map": np.zeros(0, object), "type": np.zeros(0, object),
                 "x": np.zeros(0), "y": np.zeros(0), "z": np.zeros(0), "weight": np.zeros(0)}
    meta = {"variant": variant, "seed": seed, "particles": 7, "steps": steps, "vehicle_names": list(names),
            "wall_time_s": 1.0 + seed}
    return Result(vehicles, metrics, landmarks, meta)


def test_aggregate_keeps_vehicle_errors_when_names_sort_before_fused_others(tmp_path: Path) -> None:
    """Vehicle names that sort before 'fused_others' (car_a, car_b: city presets) with a fused_others
    map: the per-vehicle and pooled position errors are still aggregated (the state loop once tested a
    map name left over from the metric loop and skipped every run)."""
    out = tmp_path / "abl"
    A.start_ablation_dir(out)
    g = np.array([4.0, 2.0, 0.0])
    for s in (0, 1):
        r = _hand_result("proposed", s, g, np.full((3, 2), 3.0 + s), names=("car_a", "car_b"),
                         extra_maps=("fused_others",))
        r.save(A.job_dir(out, A.Job("proposed", s)))
    A.store._write_json(out / A.ABLATION_FILE, {"variants": ["proposed"], "mc": 2, "seed0": 0, "seeds": [0, 1],
                                                "steps": 3, "scenario": {}, "config_hash": "x",
                                                "vehicle_names": ["car_a", "car_b"]})
    s = A.aggregate(out)
    pos = s.series("proposed", "all", "state", "pos_err")
    np.testing.assert_allclose(pos["rms"], math.sqrt((9 + 16) / 2))
    assert s.series("proposed", "car_a", "state", "pos_err")["n"].tolist() == [2, 2, 2]


def test_aggregate_means_rms_and_headline_on_known_numbers(tmp_path: Path) -> None:
    """Stored jobs are skipped (no filter runs) and the summary holds the right arithmetic."""
    out = tmp_path / "abl"
    cache = A.prepare_cache("paper", "analytic", out, steps=6, progress=False)
    g = {0: np.array([10.0, 8, 6, 4, 2, 0]), 1: np.array([20.0, 18, 16, 14, 12, 10])}
    pe = {0: np.full((6, 2), 3.0), 1: np.full((6, 2), 4.0)}
    for s in (0, 1):
        _hand_result("proposed", s, g[s], pe[s]).save(A.job_dir(out, A.Job("proposed", s)))
    run = A.run_ablation(cache, out, ["proposed"], mc=2, particles=7, progress=False)
    assert run.ran == [] and len(run.skipped) == 2
    s = A.load_summary(out)
    vs = s.series("proposed", "fused", "VS", "gospa")
    np.testing.assert_allclose(vs["mean"], (g[0] + g[1]) / 2)
    np.testing.assert_allclose(vs["std"], np.abs(g[0] - g[1]) / 2)  # population std of two values
    assert vs["n"].tolist() == [2] * 6
    pos = s.series("proposed", "all", "state", "pos_err")
    np.testing.assert_allclose(pos["rms"], math.sqrt((9 + 16) / 2))  # over 2 runs x 2 vehicles
    assert pos["n"].tolist() == [4] * 6
    fused = next(r for r in s.headline if r["map"] == "fused")
    assert s.config["fusion_start"] == 5
    assert fused["gospa_VS"] == pytest.approx((0 + 10) / 2)  # steps >= 5 only
    # the headline RMSE is the mean of the per-run RMSEs (3 and 4), the statistic its CI is of (issue 23);
    # the RMSE pooled over runs and steps, printed before with that CI, is kept as pos_rmse_pooled
    assert fused["pos_rmse"] == pytest.approx(3.5)
    assert fused["pos_rmse_pooled"] == pytest.approx(math.sqrt(12.5))
    assert fused["wall_time_s"] == pytest.approx(1.5)
    on_disk = json.loads((out / A.SUMMARY_JSON).read_text())
    assert on_disk["headline"][2]["gospa_VS"] == pytest.approx(5.0)


def test_headline_nees_is_the_median_over_vehicle_steps_by_hand(tmp_path: Path) -> None:
    """The headline's pos_nees: the median of the vehicles table's pos_nees over the steps >= fusion_start (5) of every
    run, per vehicle and pooled for fused; NaN and inf (a singular cloud) left out; NaN where no run stored it."""
    out = tmp_path / "abl"
    cache = A.prepare_cache("paper", "analytic", out, steps=7, progress=False)
    g = np.zeros(7)
    nees = {0: np.array([[9.0, 9.0]] * 5 + [[1.0, 2.0], [3.0, np.nan]]),
            1: np.array([[9.0, 9.0]] * 5 + [[5.0, np.inf], [7.0, 4.0]])}
    for s in (0, 1):
        _hand_result("proposed", s, g, np.ones((7, 2)), pos_nees=nees[s]).save(A.job_dir(out, A.Job("proposed", s)))
        _hand_result("baseline", s, g, np.ones((7, 2))).save(A.job_dir(out, A.Job("baseline", s)))
    run = A.run_ablation(cache, out, ["baseline", "proposed"], mc=2, particles=7, progress=False)
    assert run.ran == []
    s = A.load_summary(out)
    assert s.config["fusion_start"] == 5
    row = {(r["variant"], r["map"]): r for r in s.headline}
    assert row[("proposed", "veh1")]["pos_nees"] == 4.0  # median of 1, 3, 5, 7
    assert row[("proposed", "veh2")]["pos_nees"] == 3.0  # median of 2, 4
    assert row[("proposed", "fused")]["pos_nees"] == 3.5  # median of 1, 2, 3, 4, 5, 7
    assert math.isnan(row[("baseline", "fused")]["pos_nees"])  # results saved without the column
    mixed = [_hand_result("proposed", 0, g, np.ones((7, 2)), pos_nees=nees[0]), _hand_result("proposed", 1, g,
                                                                                              np.ones((7, 2)))]
    assert math.isnan(A.aggregation._median_nees(mixed, ["veh1", "veh2"], "fused", 5))  # not a partial median
    assert A.NEES_CONSISTENT == pytest.approx(1.3862944, rel=1e-7)


def test_ci95_matches_student_t_by_hand() -> None:
    mean, half = A.ci95(np.array([1.0, 2.0, 3.0]))
    assert mean == 2.0
    assert half == pytest.approx(4.302652729911275 / math.sqrt(3))  # t_{0.975, 2} * s / sqrt(n), s = 1
    assert math.isnan(A.ci95(np.array([5.0]))[1]) and A.ci95(np.array([5.0]))[0] == 5.0


def test_headline_intervals_and_paired_differences_on_known_numbers(tmp_path: Path) -> None:
    """Seeds 3..5 (--seed0 3): per-run fused-VS GOSPA baseline 20, 22, 24; proposed 3, 4, 8.
    Paired differences -17, -18, -16: mean -17, s = 1 -> significant; their means' CIs by hand."""
    out = tmp_path / "abl"
    cache = A.prepare_cache("paper", "analytic", out, steps=6, progress=False)
    fs = 5
    for v, vals in (("baseline", (20.0, 22.0, 24.0)), ("proposed", (3.0, 4.0, 8.0))):
        for s, val in zip((3, 4, 5), vals):
            g = np.r_[np.full(fs, 99.0), np.full(6 - fs, val)]  # steps before fusion start are ignored
            _hand_result(v, s, g, np.full((6, 2), 1.0)).save(A.job_dir(out, A.Job(v, s)))
    run = A.run_ablation(cache, out, ["baseline", "proposed"], mc=3, particles=7, progress=False, seed0=3)
    assert run.ran == [] and len(run.skipped) == 6
    t2 = 4.302652729911275
    rows = {(r["variant"], r["map"]): r for r in run.summary.headline}
    b, p = rows[("baseline", "fused")], rows[("proposed", "fused")]
    assert b["gospa_VS"] == pytest.approx(22.0) and b["gospa_VS_ci"] == pytest.approx(t2 * 2 / math.sqrt(3))
    assert p["gospa_VS"] == pytest.approx(5.0)
    assert p["gospa_VS_ci"] == pytest.approx(t2 * math.sqrt(7) / math.sqrt(3))  # s^2 = (4 + 1 + 9) / 2
    assert p["reference"] == "baseline" and b["reference"] is None
    assert p["gospa_VS_diff"] == pytest.approx(-17.0)
    assert p["gospa_VS_diff_ci"] == pytest.approx(t2 / math.sqrt(3)) and p["gospa_VS_sig"] is True
    assert p["gospa_VA_diff"] == pytest.approx(0.0) and p["gospa_VA_sig"] is False  # identical runs
    from mmslam.pipelines.report import paired_rows

    verdicts = {(r["variant"], r["map"], r["score"]): r["verdict"] for r in paired_rows(run.summary)}
    assert verdicts[("proposed", "fused", "gospa_VS")] == "lower than baseline (significant at 95%)"
    assert verdicts[("proposed", "fused", "pos_rmse")] == "no significant difference to baseline"


def test_set_grid_and_seed0_plan_labelled_jobs_and_validate_before_writing(tmp_path: Path) -> None:
    assert A.parse_sets(["fusion.vs_reduction = gate", "filter.merge=4"]) == ("fusion.vs_reduction=gate",
                                                                              "filter.merge=4")
    arms = A.parse_grid(["filter.vs_dither_scope=newborn,all", "fusion.beta_inside_fov=0.25,1"])
    assert arms == [("filter.vs_dither_scope=newborn", "fusion.beta_inside_fov=0.25"),
                    ("filter.vs_dither_scope=newborn", "fusion.beta_inside_fov=1"),
                    ("filter.vs_dither_scope=all", "fusion.beta_inside_fov=0.25"),
                    ("filter.vs_dither_scope=all", "fusion.beta_inside_fov=1")]
    jobs = A.plan_jobs(["proposed"], 2, seed0=7, arms=arms[:2])
    assert [j.name for j in jobs] == [
        "proposed[filter.vs_dither_scope=newborn,fusion.beta_inside_fov=0.25]-seed7",
        "proposed[filter.vs_dither_scope=newborn,fusion.beta_inside_fov=0.25]-seed8",
        "proposed[filter.vs_dither_scope=newborn,fusion.beta_inside_fov=1]-seed7",
        "proposed[filter.vs_dither_scope=newborn,fusion.beta_inside_fov=1]-seed8"]
    assert A.parse_label(jobs[0].label) == ("proposed", arms[0])
    with pytest.raises(A.ConfigError, match="given twice"):
        A.parse_sets(["filter.merge=4", "filter.merge=5"])
    out = tmp_path / "abl"
    cache = A.prepare_cache("paper", "analytic", out, steps=6, progress=False)
    for bad, needle in ((["filter.vs_dither_scope=sometimes"], "vs_dither_scope"),
                        (["sensor.fov_range=30"], "changes the traced scenario"),
                        (["filter.nope=1"], "unknown parameter")):
        with pytest.raises(A.ConfigError, match=needle):
            A.run_ablation(cache, out, ["proposed"], mc=1, particles=5, progress=False, sets=bad)
        assert not (out / A.ABLATION_FILE).exists() and not (out / A.JOBS_DIR).exists()  # nothing written


def test_resume_rejects_other_particles_and_keeps_jobs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "abl"
    cache = A.prepare_cache("paper", "analytic", out, steps=6, progress=False)
    for s in (0, 1):
        _hand_result("proposed", s, np.zeros(6), np.zeros((6, 2))).save(A.job_dir(out, A.Job("proposed", s)))
    A.run_ablation(cache, out, ["proposed"], mc=2, particles=7, progress=False)
    before = sorted(p.name for p in (out / "jobs").iterdir())
    code, _, err = _run_cli(["ablate", "paper", "--variants", "proposed", "--source", "analytic", "--steps", "6",
                             "--mc", "2", "--particles", "8", "--out", str(out), "--quiet"], capsys)
    _assert_one_line_error(code, err, "particles=7", "particles=8", "another --out")
    assert sorted(p.name for p in (out / "jobs").iterdir()) == before



def test_resume_rejects_a_scenario_file_whose_filter_table_changed(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """The same scenario file with another [filter] value (the trace unchanged) used to reuse every stored job,
    computed with the old value, and label them with the new one; now it is refused in one line before anything runs."""
    from mmslam.scenes.scenario import preset_path

    toml = preset_path("paper").read_text()
    assert "merge = 49.0" in toml
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text(toml)
    b.write_text(toml.replace("merge = 49.0", "merge = 4.0", 1))
    out = tmp_path / "abl"
    argv = ["ablate", "--variants", "proposed", "--source", "analytic", "--steps", "4", "--mc", "1",
            "--particles", "5", "--out", str(out), "--quiet"]
    code, _, err = _run_cli([argv[0], str(a), *argv[1:]], capsys)
    assert code == 0, err
    before = {p.name: p.stat().st_mtime_ns for p in (out / "jobs").rglob("*")}
    spec = (out / "ablation.json").read_text()
    code, _, err = _run_cli([argv[0], str(b), *argv[1:]], capsys)
    _assert_one_line_error(code, err, "filter.merge: 49.0 -> 4.0", "another --out")
    assert {p.name: p.stat().st_mtime_ns for p in (out / "jobs").rglob("*")} == before
    assert (out / "ablation.json").read_text() == spec
    code, _, err = _run_cli([argv[0], str(a), *argv[1:]], capsys)  # the same file again resumes (nothing to run)
    assert code == 0, err

def test_bad_cli_input_gives_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bad"
    code, _, err = _run_cli(["ablate", "paper", "--variants", "baseline,nope", "--out", str(out)] + SMALL, capsys)
    _assert_one_line_error(code, err, "nope", "--variants")
    code, _, err = _run_cli(["ablate", "paper", "--out", str(out), "--source", "analytic", "--mc", "0"], capsys)
    _assert_one_line_error(code, err, "--mc 0")
    code, _, err = _run_cli(["ablate", "paper", "--out", str(out), "--source", "analytic", "--particles", "0"],
                            capsys)
    _assert_one_line_error(code, err, "--particles 0")
    code, _, err = _run_cli(["demo", "--mc", "0", "--out", str(out)], capsys)
    _assert_one_line_error(code, err, "--mc 0")
    assert not out.exists()  # nothing started
    code, _, err = _run_cli(["report", str(tmp_path / "missing")], capsys)
    _assert_one_line_error(code, err, "missing", "mmslam ablate")


def test_unreachable_scheduler_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "dask-bad"
    code, _, err = _run_cli(["ablate", "paper", "--out", str(out), "--executor", "dask", "--scheduler",
                             "tcp://127.0.0.1:9"] + SMALL, capsys)
    _assert_one_line_error(code, err, "tcp://127.0.0.1:9", "dask scheduler")
    assert not any((out / "jobs").iterdir())


# ====================================================================== end to end (real filter)
@pytest.fixture(scope="module")
def e2e(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One small ablation with report through the CLI, local executor, 2 workers."""
    d = tmp_path_factory.mktemp("pipelines") / "abl"
    code = main(["ablate", "paper", "--out", str(d), "--workers", "2", "--report"] + SMALL)
    assert code == 0
    return {"dir": d, "jobs": _jobs(d)}


@pytest.mark.slow
def test_e2e_results_figures_and_report_exist(e2e: dict) -> None:
    d = e2e["dir"]
    assert sorted(p.name for p in (d / "jobs").iterdir()) == sorted(
        f"{v}-seed{s}" for v in A.VARIANTS for s in range(MC))
    for j, r in e2e["jobs"].items():
        assert r.meta["variant"] == j.variant and r.meta["seed"] == j.seed
        assert r.meta["particles"] == PARTICLES
        assert sorted(set(np.asarray(r.metrics["step"]).tolist())) == list(range(STEPS))
    for name in ("fig2a_gospa_vs", "fig2b_gospa_va", "fig3_position_rmse", "gospa_sp", "map_odometry", "map_baseline",
                 "map_cm1", "map_proposed"):
        png = d / "figures" / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = (d / "report.html").read_text()
    assert text.count("data:image/png;base64,") == 13  # 4 curves, 3 paired, 2 cardinality, 4 maps (odometry too)
    assert "numpy" in text and "sionna-rt" in text and "scipy" in text
    cmd = text.split('<pre id="command">')[1].split("</pre>")[0]
    assert cmd.startswith("mmslam ablate paper --variants odometry,baseline,cm1,proposed --mc 2 --particles 50 "
                          "--source analytic")


@pytest.mark.slow
def test_e2e_gospa_figures_plot_the_stored_means(e2e: dict) -> None:
    d, jobs = e2e["dir"], e2e["jobs"]
    s = A.load_summary(d)
    for ty in ("VS", "VA", "SP"):
        fig = F.fig_gospa(s, ty)
        ax = fig.axes[0]
        lines = {ln.get_label(): ln for ln in ax.get_lines() if ln.get_label() in A.VARIANTS}
        assert sorted(lines) == sorted(A.VARIANTS)
        marks = [ln for ln in ax.get_lines() if ln.get_gid() == "fusion_start"]
        assert len(marks) == 1 and marks[0].get_xdata()[0] == 5
        assert "GOSPA [m]" in ax.get_ylabel() and "time step" in ax.get_xlabel()
        for v, ln in lines.items():
            # equals the stored summary ...
            stored = s.series(v, "fused", ty, "gospa")
            np.testing.assert_array_equal(ln.get_xdata(), stored["step"])
            np.testing.assert_array_equal(ln.get_ydata(), stored["mean"])
            # ... which equals the mean over seeds of the job results
            per_seed = []
            for seed in range(MC):
                m = jobs[A.Job(v, seed)].metrics
                sel = (np.asarray(m["map"]).astype(str) == "fused") & (np.asarray(m["type"]).astype(str) == ty)
                order = np.argsort(np.asarray(m["step"])[sel])
                per_seed.append(np.asarray(m["gospa"], float)[sel][order])
            np.testing.assert_allclose(ln.get_ydata(), np.mean(per_seed, axis=0), rtol=1e-12)


@pytest.mark.slow
def test_e2e_cardinality_figure_plots_the_phd_mass_and_the_truth(e2e: dict) -> None:
    """Fused VS cardinality: each variant's line is the mean over seeds of the sum of the fused map's
    weights (recomputed from the stored landmark-free metrics' card column); the dotted truth is 2."""
    d, jobs = e2e["dir"], e2e["jobs"]
    s = A.load_summary(d)
    ax = F.fig_cardinality(s, "VS").axes[0]
    lines = {ln.get_label(): ln for ln in ax.get_lines() if ln.get_label() in A.VARIANTS}
    assert sorted(lines) == sorted(A.VARIANTS)
    truth = [ln for ln in ax.get_lines() if ln.get_gid() == "truth"]
    assert len(truth) == 1 and np.all(truth[0].get_ydata() == 2)
    np.testing.assert_array_equal(lines["baseline"].get_ydata(), 0.0)  # baseline has no VS map
    for v, ln in lines.items():
        per_seed = []
        for seed in range(MC):
            m = jobs[A.Job(v, seed)].metrics
            sel = (np.asarray(m["map"]).astype(str) == "fused") & (np.asarray(m["type"]).astype(str) == "VS")
            per_seed.append(np.asarray(m["card"], float)[sel][np.argsort(np.asarray(m["step"])[sel])])
        np.testing.assert_allclose(ln.get_ydata(), np.mean(per_seed, axis=0), rtol=1e-12)


@pytest.mark.slow
def test_e2e_rmse_figure_is_rmse_over_runs_and_vehicles(e2e: dict) -> None:
    d, jobs = e2e["dir"], e2e["jobs"]
    fig = F.fig_position_rmse(A.load_summary(d))
    ax = fig.axes[0]
    lines = {ln.get_label(): ln for ln in ax.get_lines() if ln.get_label() in A.VARIANTS}
    assert sorted(lines) == sorted(A.VARIANTS)
    assert ax.get_ylabel() == "position RMSE [m]"
    for v, ln in lines.items():
        sq = np.zeros(STEPS)
        cnt = np.zeros(STEPS)
        for seed in range(MC):
            vt = jobs[A.Job(v, seed)].vehicles
            np.add.at(sq, np.asarray(vt["step"]), np.asarray(vt["pos_err"], float) ** 2)
            np.add.at(cnt, np.asarray(vt["step"]), 1)
        assert cnt.tolist() == [MC * 2] * STEPS
        np.testing.assert_allclose(ln.get_ydata(), np.sqrt(sq / cnt), rtol=1e-12)


@pytest.mark.slow
def test_e2e_map_figure_shows_truth_and_estimates(e2e: dict) -> None:
    from mmslam.scenes.scenario import load_preset

    r = e2e["jobs"][A.Job("proposed", 0)]
    fig = F.fig_map(r, load_preset("paper"))
    gids = {ln.get_gid(): ln for ln in fig.axes[0].get_lines()}
    assert len(gids["true:VA"].get_xdata()) == 4 and len(gids["true:SP"].get_xdata()) == 4
    assert len(gids["true:VS"].get_xdata()) == 2
    tr = np.asarray(r.vehicles["true_x"])[np.asarray(r.vehicles["vehicle"]) == 0]
    np.testing.assert_array_equal(np.sort(gids["true_traj:veh1"].get_xdata()), np.sort(tr))
    lm = r.landmarks
    last = (np.asarray(lm["step"]) == STEPS - 1) & (np.asarray(lm["map"]).astype(str) == "fused")
    n_est = sum(len(gids[f"est:{t}"].get_xdata()) for t in ("VA", "SP", "VS"))
    if last.any():
        assert n_est == int(last.sum())


@pytest.mark.slow
def test_e2e_report_table_matches_stored_results(e2e: dict) -> None:
    d, jobs = e2e["dir"], e2e["jobs"]
    p = _SummaryTableParser()
    p.feed((d / "report.html").read_text())
    rows = {(v, m) for v, m, _ in p.cells}
    assert rows == {(v, m) for v in A.VARIANTS for m in ("veh1", "veh2", "fused")}
    for v, m in rows:
        exp = _expected_headline(jobs, v, m, fusion_start=5)
        for col, val in exp.items():
            got = float(p.cells[(v, m, col)])
            assert got == pytest.approx(val, rel=1e-12, abs=1e-12), (v, m, col)
        walls = [jobs[A.Job(v, s)].meta["wall_time_s"] for s in range(MC)]
        assert float(p.cells[(v, m, "wall_time_s")]) == pytest.approx(np.mean(walls))


@pytest.mark.slow
def test_e2e_report_command_regenerates_from_stored_results(e2e: dict, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "copy"
    shutil.copytree(e2e["dir"], d)
    shutil.rmtree(d / "figures")
    (d / "report.html").unlink()
    (d / "summary.parquet").unlink()
    code, out, _ = _run_cli(["report", str(d)], capsys)
    assert code == 0 and "report.html" in out
    assert (d / "report.html").is_file() and len(list((d / "figures").glob("*.png"))) == 13
    _summary_tables_equal(A.load_summary(d), A.load_summary(e2e["dir"]))


@pytest.mark.slow
def test_e2e_dask_local_cluster_gives_identical_results(e2e: dict, tmp_path: Path) -> None:
    d = tmp_path / "dask"
    code = main(["ablate", "paper", "--out", str(d), "--executor", "dask", "--workers", "2"] + SMALL)
    assert code == 0
    for j, r in _jobs(d).items():
        _same_result(r, e2e["jobs"][j])
    _summary_tables_equal(A.load_summary(d), A.load_summary(e2e["dir"]))


@pytest.mark.slow
def test_e2e_dask_scheduler_address_gives_identical_results(e2e: dict, tmp_path: Path) -> None:
    import logging

    from distributed import LocalCluster

    d = tmp_path / "dask-remote"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster:
        code = main(["ablate", "paper", "--out", str(d), "--executor", "dask", "--scheduler",
                     cluster.scheduler_address, "--variants", "proposed,baseline"] + SMALL)
    assert code == 0
    for v in ("proposed", "baseline"):
        for seed in range(MC):
            j = A.Job(v, seed)
            _same_result(Result.load(A.job_dir(d, j)), e2e["jobs"][j])


@pytest.mark.slow
def test_e2e_resume_runs_only_missing_jobs(e2e: dict, tmp_path: Path) -> None:
    d = tmp_path / "resume"
    shutil.copytree(e2e["dir"], d)
    lost = A.Job("cm1", 1)
    shutil.rmtree(A.job_dir(d, lost))
    stamps = {j: (A.job_dir(d, j) / "meta.json").stat().st_mtime_ns for j in e2e["jobs"] if j != lost}
    cache = next((d / "cache").iterdir())
    run = A.run_ablation(cache, d, A.VARIANTS, mc=MC, particles=PARTICLES, steps=STEPS, workers=1, progress=False)
    assert run.ran == [lost]
    assert sorted(run.skipped) == sorted(stamps)
    for j, t in stamps.items():
        assert (A.job_dir(d, j) / "meta.json").stat().st_mtime_ns == t
    _same_result(Result.load(A.job_dir(d, lost)), e2e["jobs"][lost])
    _summary_tables_equal(A.load_summary(d), A.load_summary(e2e["dir"]))
    # a second re-run has nothing to do
    assert A.run_ablation(cache, d, A.VARIANTS, mc=MC, particles=PARTICLES, steps=STEPS, progress=False).ran == []


@pytest.mark.slow
def test_e2e_partial_grid_then_full_grid_runs_only_the_rest(e2e: dict, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "grow"
    base = ["ablate", "paper", "--out", str(d), "--source", "analytic", "--steps", str(STEPS), "--particles",
            str(PARTICLES), "--quiet"]
    code, out, _ = _run_cli(base + ["--variants", "proposed", "--mc", "1"], capsys)
    assert code == 0 and "1 run, 0 reused" in out
    first = (A.job_dir(d, A.Job("proposed", 0)) / "meta.json").stat().st_mtime_ns
    code, out, _ = _run_cli(base + ["--mc", str(MC)], capsys)
    assert code == 0 and f"{len(A.VARIANTS) * MC - 1} run, 1 reused" in out
    assert (A.job_dir(d, A.Job("proposed", 0)) / "meta.json").stat().st_mtime_ns == first
    for j, r in _jobs(d).items():
        _same_result(r, e2e["jobs"][j])


@pytest.mark.slow
def test_e2e_demo_on_analytic_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "demo"
    code, out, _ = _run_cli(["demo", "--source", "analytic", "--mc", "1", "--particles", "20", "--out", str(d),
                             "--quiet"], capsys)
    assert code == 0
    assert f"report: {d / 'report.html'}" in out.replace("\n", "")
    spec = json.loads((d / "ablation.json").read_text())
    assert spec["scenario_name"] == "paper" and spec["steps"] == 40 and spec["variants"] == list(A.VARIANTS)
    assert spec["command"] == f"mmslam demo --source analytic --mc 1 --particles 20 --out {d}"
    s = A.load_summary(d)
    assert sorted(s.variants) == sorted(A.VARIANTS)
    for v in A.VARIANTS:
        assert s.series(v, "fused", "VS", "gospa")["step"].tolist() == list(range(40))


@pytest.mark.slow
def test_e2e_grid_and_set_through_the_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--grid makes one arm per value, --set applies to all, --seed0 picks the seeds; the report covers it."""
    out = tmp_path / "grid"
    code, stdout, err = _run_cli(["ablate", "paper", "--variants", "baseline,proposed", "--source", "analytic",
                                  "--steps", "8", "--particles", "20", "--mc", "2", "--seed0", "5", "--quiet",
                                  "--grid", "fusion.vs_reduction=matched,gate", "--set", "filter.extraction=vo_ma",
                                  "--out", str(out), "--report"], capsys)
    assert code == 0, err
    assert "proposed[fusion.vs_reduction=gate]" in stdout  # printed as text, not read as rich markup
    names = sorted(p.name for p in (out / A.JOBS_DIR).iterdir())
    assert names == sorted(f"{v}[fusion.vs_reduction={r}]-seed{s}" for v in ("baseline", "proposed")
                           for r in ("matched", "gate") for s in (5, 6))
    meta = json.loads((out / A.JOBS_DIR / "proposed[fusion.vs_reduction=gate]-seed6" / "meta.json").read_text())
    assert meta["seed"] == 6
    assert meta["overrides"] == ["filter.extraction=vo_ma", "fusion.vs_reduction=gate"]
    s = A.load_summary(out)
    assert s.variants == ["baseline[fusion.vs_reduction=matched]", "baseline[fusion.vs_reduction=gate]",
                          "proposed[fusion.vs_reduction=matched]", "proposed[fusion.vs_reduction=gate]"]
    rows = {(r["variant"], r["map"]): r for r in s.headline}
    assert rows[("proposed[fusion.vs_reduction=gate]", "fused")]["reference"] == "baseline[fusion.vs_reduction=gate]"
    report = (out / "report.html").read_text()
    assert 'id="paired"' in report and "fusion.vs_reduction=gate" in report
    # resuming with another --set is refused in one line and runs nothing
    code, _, err = _run_cli(["ablate", "paper", "--variants", "baseline,proposed", "--source", "analytic",
                             "--steps", "8", "--particles", "20", "--mc", "2", "--seed0", "5", "--quiet",
                             "--grid", "fusion.vs_reduction=matched,gate", "--out", str(out)], capsys)
    _assert_one_line_error(code, err, "--set")


def test_summary_table_keeps_variant_and_map_columns_at_80_columns() -> None:
    """The ablate / demo summary in an 80-column terminal: every row's variant (a grid-arm label too)
    and map are there in full, every number and interval is there unabridged, no line is wider."""
    from rich.console import Console

    from mmslam.pipelines.report import CONSOLE_COLUMNS, HEADLINE_COLUMNS, SCORED, summary_console_table

    rows = []
    for variant in ("odometry", "baseline", "proposed", "proposed[fusion.vs_reduction=gate]"):
        for mp in ("veh1", "veh2", "fused"):
            r = {"variant": variant, "map": mp, "runs": 10, "wall_time_s": 175.61, "card_VS": 1.972}
            for k in SCORED:
                r[k], r[k + "_ci"] = 28.284, 12.31
            rows.append(r)
    s = A.Summary(table={}, headline=rows, config={"fusion_start": 5})
    con = Console(width=80, record=True, color_system=None)
    con.print(summary_console_table(s, "mmslam ablate: paper", width=80))
    text = con.export_text()
    lines = text.splitlines()
    assert max(len(ln) for ln in lines) <= 80
    assert "…" not in text
    body = [ln for ln in lines if ln.startswith("│")]
    cells = [[c.strip() for c in ln.strip("│").split("│")] for ln in body]
    assert all(len(c) == 2 + len(CONSOLE_COLUMNS) for c in cells)
    assert "NEES" not in text and len(CONSOLE_COLUMNS) == len(HEADLINE_COLUMNS) - 1  # the report's, but the NEES
    starts = [i for i, c in enumerate(cells) if c[1]]  # the first line of each row names its map
    assert [cells[i][1] for i in starts] == [r["map"] for r in rows]
    labels = ["".join(c[0] for c in cells[i:j]) for i, j in zip(starts, starts[1:] + [len(cells)])]
    assert labels == [r["variant"] for r in rows]  # a long label folds onto more lines, never cut
    assert text.count("28.284") == len(rows) * len(SCORED) and text.count("±12.31") == len(rows) * len(SCORED)
    wide = Console(width=160, record=True, color_system=None)
    wide.print(summary_console_table(s, "mmslam ablate: paper", width=160))
    assert "proposed[fusion.vs_reduction=gate]" in wide.export_text()  # one line per row where it fits


def test_reproduce_command_keeps_the_dask_scheduler() -> None:
    cmd = A.default_command("paper", ["baseline"], 2, 50, "analytic", Path("out/a"), None, "dask",
                            scheduler="tcp://host:8786")
    assert cmd.endswith("--executor dask --scheduler tcp://host:8786")
    assert "--scheduler" not in A.default_command("paper", ["baseline"], 2, 50, "analytic", Path("out/a"), None)


def test_reproduce_command_keeps_the_trace_depth_samples_and_truth() -> None:
    # before: a --max-depth 2 ablation's report said to re-run it at depth 1 (another trace)
    cmd = A.default_command("canyon", ["proposed"], 10, 300, "sionna", Path("out/a"), None, max_depth=2,
                            samples=200000, truth="fixed").split()
    assert cmd[cmd.index("--max-depth") + 1] == "2" and cmd[cmd.index("--samples") + 1] == "200000"
    assert cmd[cmd.index("--truth") + 1] == "fixed"
    plain = A.default_command("canyon", ["proposed"], 10, 300, "sionna", Path("out/a"), None)
    assert not {"--max-depth", "--samples", "--truth"} & set(plain.split())


def test_variants_table_heads_its_descriptions_as_such() -> None:
    from mmslam.pipelines.report import _variants_html
    from mmslam.slam.specs.variants import get_variant

    text = _variants_html(["proposed"])
    head = [h.split("</th>")[0] for h in text.split("<th>")[1:]]
    assert head == ["variant", "label", "maps and countermeasures"]
    assert get_variant("proposed").describe().split(";")[0] in text


@pytest.mark.slow
def test_e2e_report_has_a_step_viewer_per_variant(e2e: dict) -> None:
    """One viewer per variant (its lowest seed), with the cache's paths, the renderer embedded once."""
    import json
    import re

    from mmslam.raytrace.cache import load_cache

    d, jobs = e2e["dir"], e2e["jobs"]
    text = (d / "report.html").read_text()
    assert text.count('<div class="mmslam-viewer"') == len(A.VARIANTS)
    assert text.count("function mmslamFrameSVG") == 1
    blobs = [json.loads(b) for b in re.findall(r'class="viewer-data">(.*?)</script>', text, re.S)]
    cache = load_cache(json.loads((d / "ablation.json").read_text())["cache_dir"])
    for v, data in zip(A.VARIANTS, blobs):
        res = jobs[next(j for j in jobs if j.variant == v and j.seed == 0)]
        assert data["steps"] == list(range(STEPS)) and data["title"].startswith(f"{v}, seed 0")
        for k in range(STEPS):  # every traced path of the step, to its receiver
            assert len(data["paths"][k]) == int(np.sum(np.asarray(cache.paths["step"]) == k))
        ex = np.asarray(res.vehicles["x"])[(np.asarray(res.vehicles["step"]) == STEPS - 1)
                                             & (np.asarray(res.vehicles["vehicle"]) == 0)][0]
        assert data["vehicles"][0]["est"][-1][0] == pytest.approx(ex, abs=0.005)


def test_settings_diff_lists_changed_run_parameters_and_skips_keys_one_version_lacks() -> None:
    """A parameter added since an ablation was written (absent from its stored scenario) is not a difference: the
    folder can still be resumed after an upgrade (found by a review); a changed value is, nested keys dotted."""
    from mmslam.scenes.scenario import load_preset, settings_diff

    new = load_preset("street").to_dict()
    old = json.loads(json.dumps(new))
    del old["filter"]["types"]["VA"]["birth_existence"]
    assert settings_diff(old, new) == []
    old["filter"]["types"]["VA"]["merge"] = 4.0
    old["seed"] = new["seed"] + 1
    assert settings_diff(old, new) == [f"filter.types.VA.merge: 4.0 -> {new['filter']['types']['VA']['merge']}",
                                       f"seed: {new['seed'] + 1} -> {new['seed']}"]
    assert settings_diff(new, json.loads(json.dumps(new))) == []
