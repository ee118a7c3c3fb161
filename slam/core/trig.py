"""A branch-free ``atan2`` for the compiled kernels (the angles of paper eq. (3)).

The CKF update (:func:`mmslam.slam.phd.ckf.ckf_update`) evaluates the measurement model at 6
cubature points per Gaussian, 4 angles each, thousands of Gaussians per filter step. libm's
``atan2`` costs ~25 ns a call there and cannot be vectorised by LLVM (numba has no SVML on this
build); :func:`atan2` here is plain arithmetic and selects, so the loop over a Gaussian's 24
angles compiles to AVX2 vector code.

Algorithm, for finite ``(y, x)``: with ``a = min(|x|, |y|)``, ``b = max(|x|, |y|)`` the angle
of ``(b, a)`` is ``atan(a / b)`` in ``[0, pi/4]``; above ``tan(pi/8)`` it is ``pi/4 +
atan(u)`` with ``u = (a - b) / (a + b)``, so one division gives ``u`` in ``[-tan(pi/8),
tan(pi/8)]``. ``atan(u) = u + u s p(s)``, ``s = u^2``, with ``p`` the degree-10 minimax
polynomial of ``(atan(sqrt(s)) - sqrt(s)) / s^(3/2)`` on ``[0, tan^2(pi/8)]``
(:func:`fit_atan_polynomial`: Remez exchange in extended precision, rounded to double; its
error times ``s`` is below 1e-17). The octant folds back as ``k pi/4 +- atan(u)``, with
``pi/4`` split into a 50-bit head (``k * head`` exact) and a tail. Measured accuracy against
``math.atan2`` (``tests/test_trig.py``, 2e6 random and special inputs): at most 2 ulp, signed
zeros as ``math.atan2`` (``atan2(+-0, -0) = +-pi``), NaN for a NaN input. Infinite inputs are not
supported (NaN), nor inputs with ``|x| + |y|`` above the largest double (~1.8e308: the fold's
``a + b`` overflows and the angle is wrong, e.g. ``pi/4`` for ``(0.9e308, 1e308)``); the measurement
model's path vectors (m) are far below both, and :func:`mmslam.slam.models.measurement.angle_arguments`
overflows already for ``|d_xy|`` above ~1e154.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

TAN_PI_8 = math.tan(math.pi / 8.0)
"""``tan(pi/8)``: above it, the reduced ratio is folded about ``pi/4``."""
_PI_4_HEAD = math.ldexp(math.floor(math.ldexp(math.pi / 4.0, 50)), -50)  # pi/4 to 50 bits: k * head exact, k <= 4
_PI_4_TAIL = math.pi / 4.0 - _PI_4_HEAD  # the double nearest pi/4, minus the head (exact)

# p(s) = sum_i ATAN_POLY[i] s^i ~ (atan(sqrt(s)) - sqrt(s)) / s^(3/2) on [0, tan(pi/8)^2]:
# fit_atan_polynomial() rounded to double (checked by tests/test_trig.py).
ATAN_POLY = (
    -0.3333333333333333,
    0.19999999999995774,
    -0.14285714284715087,
    0.11111111018874333,
    -0.0909090471508624,
    0.07692186169071387,
    -0.066645508740477,
    0.058584719517529464,
    -0.05087049233216432,
    0.03927550593171647,
    -0.019227974260330294,
)
_C0, _C1, _C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10 = ATAN_POLY


@nb.njit(cache=True, error_model="numpy")
def atan2(y: float, x: float) -> float:
    """``atan2(y, x)`` in ``[-pi, pi]`` (rad) of finite ``y, x`` (``|x| + |y|`` finite), within 2 ulp of ``math.atan2``.

    Branch-free (selects only), so a loop over many angles vectorises; see the module docstring.
    """
    ax, ay = abs(x), abs(y)
    a, b = min(ax, ay), max(ax, ay)
    fold = a > TAN_PI_8 * b  # the angle of (b, a) is above pi/8: fold about pi/4
    num = a - b if fold else a
    den = a + b if fold else b
    u = num / (den if den > 0.0 else 1.0)  # (0, 0): u = 0
    s = u * u
    p = _C10
    p = p * s + _C9
    p = p * s + _C8
    p = p * s + _C7
    p = p * s + _C6
    p = p * s + _C5
    p = p * s + _C4
    p = p * s + _C3
    p = p * s + _C2
    p = p * s + _C1
    p = p * s + _C0
    # the angle of (|x|, |y|) is swap * pi/2 + sign * (fold * pi/4 + atan(u)); x < 0 mirrors it to pi - angle
    swap = ay > ax
    west = math.copysign(1.0, x) < 0.0  # also x = -0
    sign = -1.0 if swap != west else 1.0
    k = (2.0 if swap else (4.0 if west else 0.0)) + (sign if fold else 0.0)  # multiples of pi/4: 0..4
    v = sign * u
    r = k * _PI_4_HEAD + (v + (v * s * p + k * _PI_4_TAIL))
    return math.copysign(r + (x * 0.0 + y * 0.0), y)  # + 0, or NaN for a NaN input


def fit_atan_polynomial(degree: int = 10, grid: int = 20001, iterations: int = 12) -> np.ndarray:
    """Minimax polynomial ``p (degree + 1,)`` (coefficients of ``s^0, s^1, ...``) of
    ``f(s) = (atan(sqrt(s)) - sqrt(s)) / s^(3/2)`` on ``[0, tan(pi/8)^2]``, the derivation of
    :data:`ATAN_POLY`.

    Remez exchange in NumPy's extended precision (``longdouble``, 64-bit mantissa on x86) in the
    Chebyshev basis of the interval; ``f`` from its alternating series
    ``sum_n (-1)^n s^(n-1) / (2n + 1)`` (no cancellation). Returns the coefficients in extended
    precision (round them to double for use).
    """
    from numpy.polynomial import chebyshev, polynomial

    ld = np.longdouble
    hi = np.tan(ld(np.pi) / 8) ** 2

    def f(s: np.ndarray) -> np.ndarray:
        out, term = np.zeros_like(s), np.ones_like(s)
        for n in range(1, 40):  # 0.172^39 < 1e-29
            out += (-1) ** n * term / ld(2 * n + 1)
            term = term * s
        return out

    n = degree + 2
    t = -np.cos(np.pi * np.arange(n, dtype=ld) / (n - 1))  # reference points in [-1, 1] (s = hi (t + 1) / 2)
    tg = np.linspace(ld(-1), ld(1), grid, dtype=ld)
    fg = f(hi * (tg + 1) / 2)
    basis = np.eye(degree + 1, dtype=ld)
    for _ in range(iterations):
        A = np.empty((n, n), ld)
        for j in range(degree + 1):
            A[:, j] = chebyshev.chebval(t, basis[j])
        A[:, -1] = (-1.0) ** np.arange(n)
        sol = _solve(A, f(hi * (t + 1) / 2))
        c, E = sol[:-1], sol[-1]
        err = chebyshev.chebval(tg, c) - fg
        ext: list[int] = []  # one extremum per sign run of the error, alternating, large ones only
        for seg in np.split(np.arange(grid), np.flatnonzero(np.diff(np.sign(err)) != 0) + 1):
            i = int(seg[np.argmax(np.abs(err[seg]))])
            if abs(err[i]) < 0.5 * abs(E):
                continue
            if ext and np.sign(err[i]) == np.sign(err[ext[-1]]):
                ext[-1] = i if abs(err[i]) > abs(err[ext[-1]]) else ext[-1]
            else:
                ext.append(i)
        while len(ext) > n:
            ext = ext[1:] if abs(err[ext[0]]) < abs(err[ext[-1]]) else ext[:-1]
        if len(ext) < n:
            break
        t = tg[ext]
    mono = chebyshev.cheb2poly(c)  # in t = 2 s / hi - 1
    out, power = np.zeros(1, ld), np.ones(1, ld)
    for cj in mono:
        out = polynomial.polyadd(out, cj * power)
        power = polynomial.polymul(power, np.array([-1, 2 / hi], dtype=ld))
    return out


def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A^-1 b`` by Gaussian elimination with partial pivoting, in ``A``'s dtype (``longdouble``)."""
    A, b = A.copy(), b.copy()
    n = b.size
    for i in range(n):
        p = i + int(np.argmax(np.abs(A[i:, i])))
        A[[i, p]], b[[i, p]] = A[[p, i]], b[[p, i]]
        for r in range(i + 1, n):
            f = A[r, i] / A[i, i]
            A[r, i:] -= f * A[i, i:]
            b[r] -= f * b[i]
    x = np.zeros_like(b)
    for i in range(n - 1, -1, -1):
        x[i] = (b[i] - A[i, i + 1:] @ x[i + 1:]) / A[i, i]
    return x
