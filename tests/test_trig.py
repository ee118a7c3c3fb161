"""The branch-free ``atan2`` of :mod:`mmslam.slam.core.trig` against libm, and its polynomial's derivation."""
from __future__ import annotations

import math

import numba as nb
import numpy as np
import pytest

from mmslam.slam.core import trig
from mmslam.slam.models.measurement import measure_point, wrap


@nb.njit(error_model="numpy")
def _atan2_loop(y: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    for i in range(y.size):
        out[i] = trig.atan2(y[i], x[i])


def _atan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = np.empty(np.size(y))
    _atan2_loop(np.ascontiguousarray(y, float).ravel(), np.ascontiguousarray(x, float).ravel(), out)
    return out


def _inputs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random ``(y, x)`` of both signs over 32 decades of ratio, plus axes, diagonals and signed zeros."""
    rng = np.random.default_rng(seed)
    y = rng.standard_normal(n) * 10.0 ** rng.uniform(-16, 16, n)
    x = rng.standard_normal(n) * 10.0 ** rng.uniform(-16, 16, n)
    k = n // 20
    y[:k] = 0.0
    x[k:2 * k] = 0.0
    y[2 * k:3 * k] = -0.0
    x[3 * k:4 * k] = -0.0
    x[4 * k:5 * k] = y[4 * k:5 * k]  # diagonals
    x[5 * k:6 * k] = -y[5 * k:6 * k]
    x[6 * k:7 * k] = y[6 * k:7 * k] / trig.TAN_PI_8  # at the fold
    y[7 * k:8 * k] = rng.uniform(-1e-9, 1e-9, k)  # next to the +-pi cut (x < 0) and to 0
    x[7 * k:8 * k] = rng.choice([-1.0, 1.0], k) * rng.uniform(0.1, 10.0, k)
    return y, x


def _libm_atan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """libm's ``atan2`` element by element through :func:`math.atan2` (scalar, so no SIMD path).

    Not ``np.arctan2``: NumPy dispatches it to SIMD code chosen at run time (on an AVX-512 CPU it
    differs from libm by 1 ulp on ~7% of these inputs), so it is no fixed reference."""
    return np.frompyfunc(math.atan2, 2, 1)(y, x).astype(float)


def test_atan2_is_within_2_ulp_of_libm_with_libm_signs_on_2e6_inputs():
    """Against glibc's ``atan2`` (correctly rounded in practice) the error is at most 2 ulp
    (measured: 2 ulp on 0.03% of the inputs, 1 ulp on 12%, exact on the rest)."""
    y, x = _inputs(2_000_000, 1)
    got = _atan2(y, x)
    ref = _libm_atan2(y, x)
    ulp = np.abs(got - ref) / np.spacing(np.abs(ref))
    assert ulp.max() <= 2.0, f"max error {ulp.max()} ulp"
    assert np.array_equal(np.signbit(got), np.signbit(ref))  # signed zeros and +-pi
    assert np.all(np.abs(got) <= math.pi)


@pytest.mark.parametrize(("y", "x"), [(0.0, 0.0), (-0.0, 0.0), (0.0, -0.0), (-0.0, -0.0), (1.0, 0.0), (-1.0, 0.0),
                                      (0.0, -1.0), (-0.0, -1.0), (0.0, 3.0), (2.0, 2.0), (-2.0, -2.0),
                                      (1e-310, 1.0), (1e300, 1e-300), (1e-300, -1e300)])
def test_atan2_special_values_equal_math_atan2(y, x):
    got = _atan2(np.array([y]), np.array([x]))[0]
    want = math.atan2(y, x)
    assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want)


def test_atan2_propagates_nan():
    assert np.isnan(_atan2(np.array([np.nan, 1.0, np.nan]), np.array([1.0, np.nan, np.nan]))).all()


def test_atan2_polynomial_is_the_minimax_fit_and_below_1e_17_after_scaling():
    """:data:`trig.ATAN_POLY` is :func:`trig.fit_atan_polynomial` rounded (the same function to
    3e-17 on the interval; the high coefficients themselves are ill-conditioned), and its error
    in ``atan`` (``u^3 (p - f)``, relative ``s (p - f)``) is below 1e-17."""
    ld = np.longdouble
    hi = np.tan(ld(np.pi) / 8) ** 2
    s = np.linspace(ld(0), hi, 50001, dtype=ld)
    f = np.zeros_like(s)
    term = np.ones_like(s)
    for n in range(1, 40):
        f += (-1) ** n * term / ld(2 * n + 1)
        term *= s
    stored = np.polynomial.polynomial.polyval(s, np.array(trig.ATAN_POLY, dtype=ld))
    fitted = np.polynomial.polynomial.polyval(s, trig.fit_atan_polynomial())
    assert float(np.max(np.abs(stored - fitted))) < 3e-17
    assert float(np.max(np.abs(s * (stored - f)))) < 1e-17
    assert trig.ATAN_POLY[0] == -1.0 / 3.0


def test_measured_azimuths_wrap_at_pi():
    """A landmark straight behind the BS / vehicle (azimuth +-pi) gives azimuths in (-pi, pi] on
    both sides of the cut, and their wrapped difference is the small true one."""
    b = np.array([0.0, 0.0, 0.0])
    s = np.array([10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    az = []
    for dy in (1e-7, 0.0, -1e-7):
        z = measure_point(2, s, np.array([-5.0, dy, 0.0]), b)  # scatter point west of both
        assert -math.pi < z[1] <= math.pi and -math.pi < z[3] <= math.pi
        az.append(z[3])
    assert az[0] > 3.14 and az[2] < -3.14 and az[1] == math.pi
    assert wrap(az[0] - az[2]) == pytest.approx(-2e-7 / 15.0, rel=1e-6)
