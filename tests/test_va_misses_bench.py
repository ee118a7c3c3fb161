"""benchmarks/va_misses.py: the class of each truth VA by the fused map's Gaussians near it, on hand geometry."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def vm():
    spec = importlib.util.spec_from_file_location("va_misses", Path(__file__).parents[1] / "benchmarks" / "va_misses.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_classify_by_hand(vm):
    """Truths on the x axis at 0, 3, 10, 20, 21.4 and 40 m; Gaussians at 0.5 m (w 0.9), 3.2 m (w 0.3), 12.5 m (w 0.9)
    and 21.6 m (w 0.8), threshold 0.5: found (0.5 m off), low (0.2 m off, weight below), off (2.5 m, no truth within
    1.5 m of it), shared (1.6 m to the Gaussian that is 0.2 m from the truth at 21.4), found, none (19.4 m)."""
    truth = np.array([[0.0, 0, 0], [3, 0, 0], [10, 0, 0], [20, 0, 0], [21.4, 0, 0], [40, 0, 0]])
    est = np.array([[0.5, 0, 0], [3.2, 0, 0], [12.5, 0, 0], [21.6, 0, 0]])
    w = np.array([0.9, 0.3, 0.9, 0.8])
    assert vm.classify(truth, est, w, 0.5) == ["found", "low", "off", "shared", "found", "none"]
    assert vm.classify(truth, est, w, 0.2)[1] == "found"  # the threshold decides found against low
    assert vm.classify(truth, est, w, 0.5, far=2.0)[2] == "none"  # 2.5 m is beyond a 2 m neighbour radius
    assert vm.classify(truth, np.zeros((0, 3)), np.zeros(0), 0.5) == ["none"] * 6
    assert vm.classify(truth[:1], est[:1], w[:1], 0.5) == ["found"]  # one truth, one Gaussian
    assert vm.classify(np.zeros((0, 3)), est, w, 0.5) == []


def test_estimate_classes_by_hand(vm):
    """Estimates at 0.5 m (within 1.5 m of the truth at 0), 4 m (1.5-5 m of it), 30.2 m (0.2 m from a VA first seen
    later) and 60 m (nothing near): true, near, later, far; with no truth of the step, the first two are far."""
    truth = np.array([[0.0, 0, 0], [10, 0, 0]])
    later = np.array([[30.0, 0, 0]])
    est = np.array([[0.5, 0, 0], [4, 0, 0], [30.2, 0, 0], [60, 0, 0]])
    assert vm.estimate_classes(est, truth, later) == ["true", "near", "later", "far"]
    assert vm.estimate_classes(est, np.zeros((0, 3)), np.zeros((0, 3))) == ["far"] * 4
    assert vm.estimate_classes(np.zeros((0, 3)), truth, later) == []
    # the first class that applies: 3 m from a truth of the step and 0.2 m from a VA seen later is "near"
    assert vm.estimate_classes(np.array([[13, 0, 0]]), truth, np.array([[13.2, 0, 0]])) == ["near"]


def test_seed_ranges_and_bad_input(vm, tmp_path, capsys):
    """Seed ranges parse; a bad --seeds and a missing cache end in one line and exit 2."""
    assert vm.parse_seeds("5000-5002,7") == [5000, 5001, 5002, 7]
    with pytest.raises(SystemExit) as e:
        vm.main([str(tmp_path), "--seeds", "five"])
    assert e.value.code == 2 and "expected seeds" in capsys.readouterr().err
    assert vm.main([str(tmp_path / "no-cache"), "--seeds", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("va_misses: ") and "\n" not in err
