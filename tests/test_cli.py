"""The CLI turns usage and file-system errors into one line and exit code 2 (no traceback)."""
from __future__ import annotations

from mmslam.cli import main


def test_bad_option_value_is_a_usage_error(capsys):
    assert main(["slam", "nowhere", "--particles", "abc", "--out", "x"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--particles" in err


def test_output_path_that_is_a_file(tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("")
    assert main(["trace", "paper", "--source", "analytic", "--out", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and str(f) in err and "writable path" in err and "\n" not in err


def test_plot_into_missing_directory(tmp_path, capsys):
    assert main(["trace", "paper", "--source", "analytic", "--out", str(tmp_path / "c"), "--steps", "2",
                 "--quiet"]) == 0
    capsys.readouterr()
    bad = tmp_path / "missing" / "dir" / "toa.png"
    assert main(["paths", str(tmp_path / "c"), "--plot", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "missing" in err and "\n" not in err


def _tree(p):
    return {str(f.relative_to(p)): f.read_bytes() for f in sorted(p.rglob("*")) if f.is_file()}


def test_slam_out_never_deletes_a_user_folder_or_the_cache(tmp_path, capsys):
    cache = tmp_path / "c"
    assert main(["trace", "paper", "--source", "analytic", "--out", str(cache), "--steps", "3", "--quiet"]) == 0
    (cdir,) = [p for p in cache.iterdir() if p.is_dir()]
    user = tmp_path / "thesis"
    user.mkdir()
    (user / "thesis.tex").write_text("\\documentclass{article}")
    before = _tree(user)
    capsys.readouterr()
    args = ["slam", str(cdir), "--particles", "5", "--steps", "2"]
    assert main(args + ["--out", str(user)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "--force" in err and "\n" not in err
    assert _tree(user) == before
    cache_before = _tree(cache)
    for target in (cdir, cache):  # the cache just read, or a folder holding it: refused even with --force
        assert main(args + ["--out", str(target), "--force"]) == 2
    assert _tree(cache) == cache_before
    afile = tmp_path / "notes.txt"
    afile.write_text("keep me")
    assert main(args + ["--out", str(afile)]) == 2
    assert afile.read_text() == "keep me" and not list(tmp_path.glob(".notes.txt*"))
    run = tmp_path / "run"
    assert main(args + ["--out", str(run)]) == 0
    assert main(args + ["--seed", "1", "--out", str(run)]) == 0  # a previous result is replaced
    from mmslam.slam.filter.result import Result
    assert Result.load(run).meta["seed"] == 1


def test_a_bug_is_one_line_with_a_log_and_ctrl_c_is_130(monkeypatch, capsys):
    import mmslam.slam.filter as F

    def boom(*a, **k):
        raise RuntimeError("kaboom")

    monkeypatch.setattr(F, "run_slam", boom)
    assert main(["slam", "nowhere", "--out", "/nonexistent-dir-xyz/r"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "kaboom" in err and "Traceback" not in err
    log = err.rsplit(" ", 1)[-1]
    text = open(log).read()
    assert "Traceback" in text and "RuntimeError: kaboom" in text

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(F, "run_slam", interrupt)
    assert main(["slam", "nowhere", "--out", "/nonexistent-dir-xyz/r"]) == 130
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "interrupted" in err


def test_usage_error_is_one_line(capsys):
    assert main(["slam"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "--help" in err


def test_usage_errors_of_a_typer_on_click_are_one_line(monkeypatch, capsys):
    """typer before its own copy of click raises click's ``UsageError`` (no ``typer.TyperException``
    there): still one line and exit 2, not an 'internal error'."""
    import click
    import pytest

    import mmslam.cli as cli

    def app(*a, **k):  # noqa: ANN002, ANN003, ANN202
        raise click.UsageError("Missing argument 'CACHE'.")

    monkeypatch.setattr(cli, "app", app)
    assert main(["slam"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Missing argument 'CACHE'" in err and "internal error" not in err
    with pytest.raises(AttributeError):
        getattr(click, "TyperException")


def test_slam_set_overrides_a_filter_parameter_and_refuses_an_unknown_one(tmp_path, capsys):
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.scenes.scenario import load_preset
    from mmslam.slam.filter.result import Result

    scn = load_preset("paper")
    cache = trace_scenario(scn, AnalyticSource(scn), tmp_path / "c", steps=3, progress=False)
    out = tmp_path / "r"
    assert main(["slam", str(cache), "--particles", "5", "--steps", "3", "--set", "filter.extraction=vo_ma",
                 "--out", str(out)]) == 0
    assert Result.load(out).meta["overrides"] == ["filter.extraction=vo_ma"]
    capsys.readouterr()
    assert main(["slam", str(cache), "--set", "filter.nope=1", "--out", str(tmp_path / "r2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "filter.nope" in err
    assert not (tmp_path / "r2").exists()


def test_slam_says_when_the_run_ends_before_the_first_fusion(tmp_path, capsys):
    """Before: a run shorter than the first upload (paper's fusion.start [5, 6], --steps 4) printed an empty GOSPA
    table and nothing else. Now a note says why, and a run that reaches the fusion prints none."""
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.scenes.scenario import load_preset

    scn = load_preset("paper")
    cache = trace_scenario(scn, AnalyticSource(scn), tmp_path / "c", steps=7, progress=False)
    assert main(["slam", str(cache), "--particles", "5", "--steps", "4", "--out", str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert "note: the run has 4 steps and the first map fusion is at step 5: no map was fused or scored" in out
    assert main(["slam", str(cache), "--particles", "5", "--steps", "7", "--out", str(tmp_path / "r2")]) == 0
    out = capsys.readouterr().out
    assert "note:" not in out and "fused" in out


def test_slam_ignore_types_leaves_those_paths_out_of_the_measurements(tmp_path, capsys):
    """--ignore-types VA: the run's include_types lack VA (1) and keep BS, SP, VS; an unknown name is one line,
    exit 2, naming the option."""
    import json

    cache = tmp_path / "c"
    assert main(["trace", "paper", "--source", "analytic", "--out", str(cache), "--steps", "3", "--quiet"]) == 0
    (cdir,) = [p for p in cache.iterdir() if p.is_dir()]
    args = ["slam", str(cdir), "--particles", "5", "--steps", "2"]
    assert main(args + ["--ignore-types", "VA", "--out", str(tmp_path / "r")]) == 0
    assert json.loads((tmp_path / "r" / "meta.json").read_text())["include_types"] == [0, 2, 3]
    assert main(args + ["--out", str(tmp_path / "r2")]) == 0
    assert json.loads((tmp_path / "r2" / "meta.json").read_text())["include_types"] == [0, 1, 2, 3]
    capsys.readouterr()
    assert main(args + ["--ignore-types", "WALL", "--out", str(tmp_path / "r3")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--ignore-types" in err and "WALL" in err and "\n" not in err


def test_a_run_that_names_no_variant_runs_the_proposed_filter(tmp_path, capsys):
    """`mmslam slam` without --variant, run_slam and run_filter without one run DEFAULT_VARIANT, the paper's filter
    (proposed): it maps the other cars as VSs (VS estimates in the result's landmarks), which baseline does not; an
    explicit --variant baseline still runs baseline."""
    import inspect
    import json

    import pandas as pd

    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.scenes.scenario import load_preset
    from mmslam.slam.filter.run import CooperativeRun, run_filter, run_slam
    from mmslam.slam.specs.variants import DEFAULT_VARIANT

    assert DEFAULT_VARIANT == "proposed"
    for f in (run_slam, run_filter, CooperativeRun.__init__):
        assert inspect.signature(f).parameters["variant"].default == DEFAULT_VARIANT
    scn = load_preset("paper")
    cache = trace_scenario(scn, AnalyticSource(scn), tmp_path / "c", steps=7, progress=False)
    types = {}
    for name, extra in (("r", []), ("b", ["--variant", "baseline"])):
        assert main(["slam", str(cache), "--particles", "5", "--steps", "7", "--out", str(tmp_path / name)] + extra) == 0
        assert json.loads((tmp_path / name / "meta.json").read_text())["variant"] == ("proposed" if name == "r" else "baseline")
        lm = pd.read_parquet(tmp_path / name / "landmarks.parquet")
        types[name] = set(lm["type"].astype(str))
    capsys.readouterr()
    assert "VS" in types["r"] and "VS" not in types["b"]


def test_summarize_sets_each_mean_gospa_against_the_empty_map():
    """The empty map's GOSPA at a step is (c^p / alpha n_true)^(1/p), every truth missed (by hand: c = 20, p = 2,
    alpha = 2: 1 truth 14.142, 2 truths 20, 4 truths 28.284 m); its mean over the scored steps (from the first fusion)
    sits beside the mean GOSPA, with the mean truths and estimates. A result without meta['gospa'] gets NaN."""
    import math
    from types import SimpleNamespace

    from mmslam.slam.cli import summarize

    metrics = {"step": [4, 5, 6, 5, 6], "map": ["fused"] * 3 + ["car_a"] * 2, "type": ["VA"] * 5,
               "gospa": [99.0, 10.0, 12.0, 5.0, 7.0], "n_true": [9, 2, 4, 1, 1], "n_est": [0, 1, 3, 1, 2]}
    res = SimpleNamespace(metrics=metrics, meta={"fusion_start": 5, "gospa": {"c": 20.0, "p": 2.0, "alpha": 2.0}})
    rows = summarize(res)
    assert [r[:2] for r in rows] == [("fused", "VA"), ("car_a", "VA")]
    mp, t, g, e, nt, ne = rows[0]
    assert g == 11.0 and math.isclose(e, (20.0 + math.sqrt(800.0)) / 2, rel_tol=1e-12) and nt == 3.0 and ne == 2.0
    assert math.isclose(rows[1][3], math.sqrt(200.0), rel_tol=1e-12) and rows[1][2] == 6.0
    res.meta.pop("gospa")
    assert math.isnan(summarize(res)[0][3])
