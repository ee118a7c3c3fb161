"""benchmarks/va_map_error.py: the nearest-Gaussian error and NEES, by hand."""
from __future__ import annotations

import importlib.util
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
