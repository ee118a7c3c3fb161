"""`mmslam trace` / `mmslam paths` through the CLI entry point (exit codes, output)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mmslam.cli import main
from mmslam.raytrace.cache import load_cache
from mmslam.raytrace.cli import path_counts


def _trace(tmp_path, capsys, *extra):
    capsys.readouterr()
    rc = main(["trace", "paper", "--source", "analytic", "--out", str(tmp_path), "--steps", "8", "--quiet",
               *extra])
    out = capsys.readouterr().out.strip().splitlines()
    return rc, out


def test_trace_then_paths(tmp_path, capsys):
    rc, out = _trace(tmp_path, capsys)
    assert rc == 0
    d = Path(out[-1])
    assert d.parent == tmp_path and d.name.startswith("paper-analytic-")
    c = load_cache(d)
    assert c.steps == 8
    assert main(["paths", str(d)]) == 0
    text = capsys.readouterr().out
    # the paper preset without blockage: 1 LOS + 4 VAs per receiver and step, the other car as VS
    lines = [ln for ln in text.splitlines() if "veh1" in ln or "veh2" in ln]
    assert len(lines) == 16
    for ln in lines:
        cells = [x.strip() for x in ln.strip("│| ").split("│")]
        assert cells[2:4] == ["1", "4"] and cells[5] == "1"
    total = [ln for ln in text.splitlines() if "all" in ln][-1]
    assert str(len(c.paths["rx"])) in total


def test_path_counts_hand_example():
    paths = {"step": np.array([0, 0, 1, 1, 1]), "rx": np.array([0, 1, 1, 1, 0], np.int16),
             "type": np.array([0, 1, 1, 1, 3], np.int8)}
    n = path_counts(paths, steps=2, n_rx=2)
    assert n.shape == (2, 2, 5) and n.sum() == 5
    assert n[0, 0, 0] == 1 and n[0, 1, 1] == 1 and n[1, 1, 1] == 2 and n[1, 0, 3] == 1


def test_paths_plot_writes_png(tmp_path, capsys):
    rc, out = _trace(tmp_path, capsys)
    png = tmp_path / "toa.png"
    assert main(["paths", out[-1], "--plot", str(png)]) == 0
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_trace_resume_via_cli_is_idempotent(tmp_path, capsys):
    _, out1 = _trace(tmp_path, capsys)
    before = load_cache(out1[-1]).manifest["chunks"]
    _, out2 = _trace(tmp_path, capsys)
    assert out1[-1] == out2[-1]
    assert load_cache(out2[-1]).manifest["chunks"] == before
    rc, out3 = _trace(tmp_path, capsys, "--force")
    assert rc == 0 and load_cache(out3[-1]).manifest["chunks"] == before  # deterministic re-trace



def test_retrace_with_other_filter_settings_says_so_in_one_line(tmp_path, capsys):
    """The same geometry with another [filter] value re-uses the cache (no path changes) but its stored settings
    follow the new file, which changes what mmslam slam runs: trace says so (it used to rewrite them silently)."""
    from mmslam.scenes.scenario import preset_path

    toml = preset_path("paper").read_text()
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text(toml)
    b.write_text(toml.replace("merge = 49.0", "merge = 4.0", 1))
    root = tmp_path / "c"
    argv = ["--source", "analytic", "--out", str(root), "--steps", "4", "--quiet"]
    assert main(["trace", str(a), *argv]) == 0
    capsys.readouterr()
    assert main(["trace", str(a), *argv]) == 0  # unchanged: no note
    assert "note:" not in capsys.readouterr().err
    assert main(["trace", str(b), *argv]) == 0
    cap = capsys.readouterr()
    notes = [ln for ln in cap.err.splitlines() if ln.startswith("note:")]
    assert len(notes) == 1 and "filter.merge: 49.0 -> 4.0" in notes[0] and "traced paths are unchanged" in notes[0]
    assert load_cache(cap.out.strip().splitlines()[-1]).scenario.filter.merge == 4.0

@pytest.mark.parametrize("args, needle", [
    (["trace", "nosuchscenario", "--source", "analytic"], "unknown scenario 'nosuchscenario'"),
    (["trace", "paper", "--source", "raytracer"], "--source 'raytracer'"),
    (["trace", "paper", "--source", "analytic", "--max-depth", "0"], "--max-depth 0"),
    (["trace", "paper", "--source", "analytic", "--max-depth", "4"], "--max-depth 4"),
    (["trace", "paper", "--source", "analytic", "--steps", "0"], "--steps 0"),
    (["trace", "missing.toml", "--source", "analytic"], "scenario file not found"),
])
def test_bad_trace_arguments_exit_2_with_one_line(tmp_path, capsys, args, needle):
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and needle in err and len(err.splitlines()) == 1
    assert not any(tmp_path.iterdir())  # nothing written


def test_paths_on_missing_dir_exit_2(tmp_path, capsys):
    capsys.readouterr()
    assert main(["paths", str(tmp_path / "none")]) == 2
    assert "no such cache directory" in capsys.readouterr().err


def test_trace_a_toml_file(tmp_path, capsys):
    toml = tmp_path / "mini.toml"
    toml.write_text('name = "mini"\nbs = [0.0, 0.0, 10.0]\nsteps = 3\n'
                    '[[vehicles]]\nname = "a"\ninitial_state = [20.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]\n')
    capsys.readouterr()
    assert main(["trace", str(toml), "--source", "analytic", "--out", str(tmp_path / "c"), "--quiet"]) == 0
    c = load_cache(capsys.readouterr().out.strip().splitlines()[-1])
    assert c.steps == 3 and c.paths["type"].tolist() == [0, 0, 0]  # LOS only: no walls, no others
    np.testing.assert_allclose(c.paths["toa_m"], np.hypot(10.0, 20.0 + np.arange(3) * 0.5))


@pytest.mark.parametrize("extra, needle", [
    (["--executor", "spark"], "--executor spark: expected one of local, dask"),
    (["--workers", "2"], "only used with --executor dask"),
    (["--executor", "dask", "--workers", "0"], "--workers 0: expected 1..4096 workers"),
])
def test_trace_executor_options_are_checked(tmp_path, capsys, extra, needle):
    assert main(["trace", "paper", "--source", "analytic", "--out", str(tmp_path), "--quiet", *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.strip().count("\n") == 0
