"""benchmarks/va_map_error.py: the nearest-Gaussian error and NEES, by hand."""
from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest


def _bench():
    spec = importlib.util.spec_from_file_location("va_map_error",
                                                  Path(__file__).parents[1] / "benchmarks" / "va_map_error.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["va_map_error"] = mod  # a dataclass's annotations are resolved through its module
    spec.loader.exec_module(mod)
    return mod


def test_nearest_errors_by_hand():
    """Gaussians at (1, 0, 0) (covariance diag(0.25, 1, 1), weight 1), (0, 2, 0) (identity, weight 0.9) and at the
    origin with weight 0.1 (too light). Truth (0, 0, 0): nearest live one (1, 0, 0) at 1 m, error (1, 0, 0), NEES
    1 / 0.25 = 4. Truth (0, 2.5, 0): (0, 2, 0) at 0.5 m, error (0, -0.5, 0), NEES 0.25. Truth (10, 0, 0): nearest
    at 9 m > within 3: not found (NaN)."""
    b = _bench()
    m = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 0]])
    P = np.stack([np.diag([0.25, 1.0, 1.0]), np.eye(3), np.eye(3)])
    w = np.array([1.0, 0.9, 0.1])
    err, nees = b.nearest_errors(m, w, P, np.array([[0.0, 0, 0], [0, 2.5, 0], [10.0, 0, 0]]), 3.0, 0.5)
    np.testing.assert_allclose(err[:2], [[1.0, 0, 0], [0, -0.5, 0]], rtol=0, atol=1e-15)
    assert nees[0] == pytest.approx(4.0, rel=1e-14) and nees[1] == pytest.approx(0.25, rel=1e-14)
    assert np.isnan(err[2]).all() and np.isnan(nees[2])
    none_err, none_nees = b.nearest_errors(m, np.zeros(3), P, np.zeros((1, 3)), 3.0, 0.5)
    assert np.isnan(none_err).all() and np.isnan(none_nees).all()


@pytest.mark.parametrize("script", ["va_map_error.py", "city_va.py"])
def test_missing_cache_is_one_line_exit_2(tmp_path, script):
    """A cache that is not there: the benchmark's one-line error naming it and the fix (exit 2), no traceback."""
    import subprocess

    missing = tmp_path / "no_cache"
    r = subprocess.run([sys.executable, str(Path(__file__).parents[1] / "benchmarks" / script), str(missing)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{script}: error: ") and str(missing) in lines[0]
    assert "mmslam trace" in lines[0]


@pytest.fixture(scope="module")
def paper6(tmp_path_factory):
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.cache import load_cache
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.scenes.scenario import load_preset

    scn = load_preset("paper")
    return load_cache(trace_scenario(scn, AnalyticSource(scn), tmp_path_factory.mktemp("trace") / "c", steps=6,
                                     progress=False))


def test_va_trace_reproduces_run_slam(paper6, capsys):
    """benchmarks/va_trace.py runs the filter stage by stage; its RMSEs (with VAs and with them ignored) are those
    of run_slam's vehicle table on the same seed, computed independently from the per-step pos_err column."""
    from mmslam.slam.filter.run import run_slam
    from mmslam.slam.specs.landmarks import VA_SPEC, landmark_types

    spec = importlib.util.spec_from_file_location("va_trace", Path(__file__).parents[1] / "benchmarks" / "va_trace.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main([str(paper6.path), "--seed", "3", "--car", "1", "--particles", "20", "--kmin", "2"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    got = [float(x) for x in re.findall(r"([0-9.]+) m", last)[:2]]
    no_va = tuple(s.code for s in landmark_types() if s.code != VA_SPEC.code)
    want = []
    for inc in (None, no_va):
        v = run_slam(paper6.path, "proposed", 20, 3, include_types=inc).vehicles
        sel = (np.asarray(v["vehicle"]) == 1) & (np.asarray(v["step"]) >= 2)
        want.append(float(np.sqrt(np.mean(np.asarray(v["pos_err"], float)[sel] ** 2))))
    np.testing.assert_allclose(got, want, atol=5e-4)  # printed to 3 decimals
    assert want[0] != want[1]  # the VA paths reach the filter in one run and not in the other


def test_va_trace_negative_seed_is_argparse_one_line_error(capsys):
    spec = importlib.util.spec_from_file_location("va_trace", Path(__file__).parents[1] / "benchmarks" / "va_trace.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    with pytest.raises(SystemExit) as e:
        mod.main(["some_cache", "--seed", "-1", "--car", "0"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("argument --seed: '-1': expected a seed, an integer >= 0")
