"""Compiled inner loops of the channel-parameter estimator (:mod:`mmslam.slam.sim.channel_estimator`).

The residual ``r`` and its 5-D DFT are held as split real / imaginary ``(Na, K)`` float64 arrays
(``Na = rx^2 tx^2`` antenna pairs in the C order of the axes ``[rx column, rx row, tx column, tx row]``,
``K`` subcarriers): the passes over them (contraction with a delay atom, rank-n updates) then run as
SIMD loops. ``dims (5,)`` are the axis lengths ``(rx, rx, tx, tx, K)``, ``offsets (5,)`` the axis
centres ``o_d``; the 1-D atoms are ``v_d(w)_i = exp(j w (i - o_d))`` and their derivatives
``d^p v_d / dw^p = (j (i - o_d))^p v_d``.

Each pass touches every cell once (~0.13 ms at the default 262144 cells on this machine); everything
else is per axis. Sums are reordered against a numpy evaluation (``fastmath``): results agree to
rounding (~1e-15 relative).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _axis_factors(w: float, offset: float, n: int) -> np.ndarray:
    """``conj(d^p v / dw^p)`` of one axis for ``p = 0, 1, 2``: ``(3, n)`` complex, ``(-j x)^p exp(-j w x)``
    with ``x = i - offset``."""
    c = np.empty((3, n), np.complex128)
    for i in range(n):
        x = i - offset
        e = complex(math.cos(w * x), -math.sin(w * x))
        c[0, i] = e
        c[1, i] = complex(0.0, -x) * e
        c[2, i] = -(x * x) * e
    return c


@nb.njit(cache=True)
def _contract_middle(X: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``out[m, q, p] = sum_l X[m, l, p] c[q, l]``: ``X (M, L, P)``, ``c (Q, L)`` -> ``(M, Q, P)``."""
    M, L, P = X.shape
    out = np.zeros((M, c.shape[0], P), np.complex128)
    for m in range(M):
        for q in range(c.shape[0]):
            for l in range(L):
                f = c[q, l]
                for p in range(P):
                    out[m, q, p] += X[m, l, p] * f
    return out


@nb.njit(cache=True, fastmath=True)
def contract(rr: np.ndarray, ri: np.ndarray, w: np.ndarray, offsets: np.ndarray, dims: np.ndarray,
             W: np.ndarray, G: np.ndarray) -> np.ndarray:
    """``T[p0, .., p4] = (d^p0 v_0 (x) .. (x) d^p4 v_4)(w)^H r`` for ``p_d = 0..2``: ``(3, 3, 3, 3, 3)`` complex,
    on the residual ``r = y - sum_m G_m v(W_m)`` (``W (L, 5)``, ``G (L,)``).

    One pass over ``y = rr + j ri (Na, K)`` (the delay axis, three derivative orders at once), then the
    four antenna axes one after the other on the ``(Na, 3)`` result; the atoms' terms in closed form
    (separable, :func:`add_cross_terms`).
    """
    Na, K = rr.shape
    cr = np.empty(K)
    ci = np.empty(K)
    xs = np.empty(K)
    for k in range(K):
        x = k - offsets[4]
        xs[k] = x
        cr[k] = math.cos(w[4] * x)
        ci[k] = math.sin(w[4] * x)
    A = np.empty((Na, 3), np.complex128)
    for a in range(Na):
        s0r = 0.0
        s0i = 0.0
        s1r = 0.0
        s1i = 0.0
        s2r = 0.0
        s2i = 0.0
        for k in range(K):
            yr = rr[a, k] * cr[k] + ri[a, k] * ci[k]  # r conj(v)
            yi = ri[a, k] * cr[k] - rr[a, k] * ci[k]
            x = xs[k]
            s0r += yr
            s0i += yi
            s1r += yr * x
            s1i += yi * x
            s2r += yr * (x * x)
            s2i += yi * (x * x)
        A[a, 0] = complex(s0r, s0i)
        A[a, 1] = complex(s1i, -s1r)  # (-j) s1
        A[a, 2] = complex(-s2r, -s2i)  # (-j)^2 s2
    X = A.reshape(Na * 3)
    P = 3
    M = Na
    for d in range(3, -1, -1):  # axis d is the innermost antenna axis left: X (M, L_d, P) -> (M, 3, P)
        M //= dims[d]
        X = _contract_middle(X.reshape((M, dims[d], P)), _axis_factors(w[d], offsets[d], dims[d])).reshape(-1)
        P *= 3
    T = X.reshape((3, 3, 3, 3, 3))
    s = np.empty((5, 3), np.complex128)
    for m in range(G.shape[0]):
        for d in range(5):
            _axis_sums(W[m, d] - w[d], offsets[d], dims[d], s, d)
        _add_outer(T, s, -G[m])
    return T


@nb.njit(cache=True)
def _axis_sums(theta: float, offset: float, n: int, s: np.ndarray, d: int) -> None:
    """``s[d, p] = sum_i (-j x)^p exp(j theta x)`` for ``p = 0, 1, 2``, ``x = i - offset`` (the phasor by
    recurrence: ~n eps relative)."""
    e = complex(math.cos(theta * offset), -math.sin(theta * offset))
    q = complex(math.cos(theta), math.sin(theta))
    a0 = 0j
    a1 = 0j
    a2 = 0j
    for i in range(n):
        x = i - offset
        a0 += e
        a1 += complex(0.0, -x) * e
        a2 += -(x * x) * e
        e *= q
    s[d, 0] = a0
    s[d, 1] = a1
    s[d, 2] = a2


@nb.njit(cache=True)
def _add_outer(T: np.ndarray, s: np.ndarray, g: complex) -> None:
    """``T += g s[0] (x) s[1] (x) .. (x) s[4]`` (``T (3,)*5``, ``s (5, 3)``)."""
    for p0 in range(3):
        for p1 in range(3):
            f01 = g * s[0, p0] * s[1, p1]
            for p2 in range(3):
                f012 = f01 * s[2, p2]
                for p3 in range(3):
                    f0123 = f012 * s[3, p3]
                    for p4 in range(3):
                        T[p0, p1, p2, p3, p4] += f0123 * s[4, p4]


@nb.njit(cache=True)
def add_cross_terms(T: np.ndarray, W: np.ndarray, w: np.ndarray, g: complex, offsets: np.ndarray,
                    dims: np.ndarray) -> None:
    """``T[k] += g S_k`` in place for ``k < len(W)``, ``S_k = (d^p0 v_0 (x) .. (x) d^p4 v_4)(W_k)^H v(w)``
    (``p_d = 0..2``; ``T (n, 3, 3, 3, 3, 3)`` complex, ``W (n, 5)``). Separable: per axis
    ``sum_i (-j x)^p exp(j (w_d - W_kd) x)``, their outer product."""
    s = np.empty((5, 3), np.complex128)
    for k in range(W.shape[0]):
        for d in range(5):
            _axis_sums(w[d] - W[k, d], offsets[d], dims[d], s, d)
        _add_outer(T[k], s, g)


@nb.njit(cache=True, fastmath=True)
def subtract_atoms(Xr: np.ndarray, Xi: np.ndarray, a: np.ndarray, b: np.ndarray, g: np.ndarray,
                   argmax: bool) -> tuple[int, float]:
    """``X -= sum_m g_m a_m b_m^T`` in place (``X = Xr + j Xi (Na, K)``, ``a (n, Na)``, ``b (n, K)``, ``g (n,)``
    complex; ``n`` may be 0); with ``argmax``, the flat index and value of ``max |X|^2`` after the
    update (else ``(0, -1)``). One pass."""
    Na, K = Xr.shape
    n = g.shape[0]
    br = np.ascontiguousarray(b.real)
    bi = np.ascontiguousarray(b.imag)
    best = -1.0
    jbest = 0
    for i in range(Na):
        xr = Xr[i]
        xi = Xi[i]
        m = 0
        while m < n:  # the row stays in L1 over the n terms; two terms per sweep of it
            c = g[m] * a[m, i]
            cr, ci = c.real, c.imag
            bmr, bmi = br[m], bi[m]
            if m + 1 < n:
                c2 = g[m + 1] * a[m + 1, i]
                c2r, c2i = c2.real, c2.imag
                b2r, b2i = br[m + 1], bi[m + 1]
                for k in range(K):
                    xr[k] -= (cr * bmr[k] - ci * bmi[k]) + (c2r * b2r[k] - c2i * b2i[k])
                for k in range(K):
                    xi[k] -= (cr * bmi[k] + ci * bmr[k]) + (c2r * b2i[k] + c2i * b2r[k])
            else:
                for k in range(K):
                    xr[k] -= cr * bmr[k] - ci * bmi[k]
                for k in range(K):
                    xi[k] -= cr * bmi[k] + ci * bmr[k]
            m += 2
        if argmax:
            top = -1.0  # the row's maximum first (a vectorised reduction), its index only where it wins
            for k in range(K):
                top = max(top, xr[k] * xr[k] + xi[k] * xi[k])
            if top > best:
                for k in range(K):
                    p = xr[k] * xr[k] + xi[k] * xi[k]
                    if p > best:
                        best = p
                        jbest = i * K + k
    return jbest, best


AXIS_ORDER = np.array([4, 2, 3, 0, 1])
"""The coordinate search's axis order: delay, tx column, tx row, rx column, rx row."""


@nb.njit(cache=True, fastmath=True)
def coordinate_search(rr: np.ndarray, ri: np.ndarray, w0: np.ndarray, offsets: np.ndarray, dims: np.ndarray,
                      cand: np.ndarray, sweeps: int, W: np.ndarray, G: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """Per axis in turn (delay, tx column, tx row, rx column, rx row), ``w_d <- w_d + cand[d, j]`` with ``j``
    the maximum of ``|v(w)^H r|`` over ``j`` (the other axes fixed); ``sweeps`` times. ``cand (5, P)``:
    offsets within one DFT cell either side; ``r = y - sum_m G_m v(W_m)`` as in :func:`contract`. Two
    passes over ``y = rr + j ri`` per sweep (the antenna-contracted delay profile, then the
    delay-contracted antenna tensor), the atoms' terms added to each; ``x0 (K,)``, where not empty, is
    the first delay profile ``v_ant(w0)^H r`` (read off the residual's DFT when ``w0`` is a cell)."""
    Na, K = rr.shape
    L1, L2, L3 = dims[1], dims[2], dims[3]
    nmax = np.max(dims)
    w = w0.copy()
    vs = np.empty((5, nmax), np.complex128)  # conj(v_d(w_d)), padded
    for d in range(5):
        for i in range(dims[d]):
            vs[d, i] = complex(math.cos(w[d] * (i - offsets[d])), -math.sin(w[d] * (i - offsets[d])))
    L = G.shape[0]
    vm = np.empty((L, 5, nmax), np.complex128)  # the atoms' v_d(W_md)
    vam = np.empty((L, Na), np.complex128)  # their antenna factors
    for m in range(L):
        for d in range(5):
            for i in range(dims[d]):
                ph = W[m, d] * (i - offsets[d])
                vm[m, d, i] = complex(math.cos(ph), math.sin(ph))
        for a in range(Na):
            vam[m, a] = (vm[m, 0, a // (L3 * L2 * L1)] * vm[m, 1, (a // (L3 * L2)) % L1]
                         * vm[m, 2, (a // L3) % L2] * vm[m, 3, a % L3])
    x = np.empty(nmax, np.complex128)
    A = np.empty(Na, np.complex128)
    idx = np.empty(4, np.int64)
    for sweep in range(sweeps):
        for d in AXIS_ORDER:
            n = dims[d]
            if d == 4 and sweep == 0 and x0.size:
                x[:K] = x0
            elif d == 4:  # x[k] = sum_a conj(va[a]) r[a, k]
                xr = np.zeros(K)
                xi = np.zeros(K)
                for a in range(Na):
                    c = (vs[0, a // (L3 * L2 * L1)] * vs[1, (a // (L3 * L2)) % L1] * vs[2, (a // L3) % L2]
                         * vs[3, a % L3])
                    for k in range(K):
                        xr[k] += c.real * rr[a, k] - c.imag * ri[a, k]
                        xi[k] += c.real * ri[a, k] + c.imag * rr[a, k]
                for k in range(K):
                    x[k] = complex(xr[k], xi[k])
                for m in range(L):
                    c = G[m]
                    for e in range(4):
                        t = 0j
                        for i in range(dims[e]):
                            t += vs[e, i] * vm[m, e, i]
                        c *= t
                    for k in range(K):
                        x[k] -= c * vm[m, 4, k]
            else:
                if d == 2:  # first antenna axis after the delay: A[a] = sum_k r[a, k] conj(vk[k])
                    for a in range(Na):
                        sr = 0.0
                        si = 0.0
                        for k in range(K):
                            sr += rr[a, k] * vs[4, k].real - ri[a, k] * vs[4, k].imag
                            si += ri[a, k] * vs[4, k].real + rr[a, k] * vs[4, k].imag
                        A[a] = complex(sr, si)
                    for m in range(L):
                        t = 0j
                        for k in range(K):
                            t += vs[4, k] * vm[m, 4, k]
                        c = G[m] * t
                        for a in range(Na):
                            A[a] -= c * vam[m, a]
                for i in range(n):
                    x[i] = 0j
                for a in range(Na):
                    idx[0] = a // (L3 * L2 * L1)
                    idx[1] = (a // (L3 * L2)) % L1
                    idx[2] = (a // L3) % L2
                    idx[3] = a % L3
                    c = A[a]
                    for e in range(4):
                        if e != d:
                            c *= vs[e, idx[e]]
                    x[idx[d]] += c
            best = -1.0
            jbest = 0
            for j in range(cand.shape[1]):  # |v_d(w_d + cand)^H x|, the phasor by recurrence
                wc = w[d] + cand[d, j]
                e = complex(math.cos(wc * offsets[d]), math.sin(wc * offsets[d]))
                q = complex(math.cos(wc), -math.sin(wc))
                s = 0j
                for i in range(n):
                    s += e * x[i]
                    e *= q
                v = abs(s)
                if v > best:
                    best = v
                    jbest = j
            w[d] = w[d] + cand[d, jbest]
            for i in range(n):
                vs[d, i] = complex(math.cos(w[d] * (i - offsets[d])), -math.sin(w[d] * (i - offsets[d])))
    return w


@nb.njit(cache=True)
def newton_step(c: complex, g: np.ndarray, H: np.ndarray, step: np.ndarray) -> bool:
    """Newton step on ``S = |c|^2`` (``g (n,)``, ``H (n, n)`` complex: gradient and Hessian of ``c``) into
    ``step (n,)``: ``-hess(S)^-1 grad(S)`` by a Cholesky factorisation of ``-hess(S)``; False (``step``
    undefined) where that is not positive definite."""
    n = g.shape[0]
    A = np.empty((n, n))  # -hess(S) = -2 Re(conj(g) g^T + conj(c) H)
    b = np.empty(n)  # grad(S) = 2 Re(conj(c) g)
    for d in range(n):
        b[d] = 2.0 * (c.conjugate() * g[d]).real
        for e in range(n):
            A[d, e] = -2.0 * (g[d].conjugate() * g[e] + c.conjugate() * H[d, e]).real
    for d in range(n):  # A = L L^T in place (lower triangle)
        s = A[d, d]
        for k in range(d):
            s -= A[d, k] * A[d, k]
        if not s > 0.0:
            return False
        A[d, d] = math.sqrt(s)
        for e in range(d + 1, n):
            t = A[e, d]
            for k in range(d):
                t -= A[e, k] * A[d, k]
            A[e, d] = t / A[d, d]
    for d in range(n):  # L y = b
        t = b[d]
        for k in range(d):
            t -= A[d, k] * step[k]
        step[d] = t / A[d, d]
    for d in range(n - 1, -1, -1):  # L^T x = y
        t = step[d]
        for k in range(d + 1, n):
            t -= A[k, d] * step[k]
        step[d] = t / A[d, d]
    return True


@nb.njit(cache=True)
def _value_grad_hess(T: np.ndarray, g: np.ndarray, H: np.ndarray) -> complex:
    """``v(w)^H r`` from its ``(3,)*5`` derivative tensor; its gradient into ``g (5,)``, Hessian into ``H (5, 5)``."""
    t = T.reshape(-1)
    for d in range(5):
        g[d] = t[3 ** (4 - d)]
        for e in range(5):
            H[d, e] = t[3 ** (4 - d) + 3 ** (4 - e)]
    return t[0]


@nb.njit(cache=True)
def next_mover(Ts: np.ndarray, G: np.ndarray, self_term: np.ndarray, var: np.ndarray, N: float, start: int,
               stop: int, frac: float) -> int:
    """The first path ``l`` in ``[start, stop)`` whose Newton step on ``r + G_l v(w_l)`` (tensor ``Ts[l] + G_l
    self_term``) is undefined or exceeds ``frac`` times its CRB standard deviation ``1 / sqrt(2 N |G_l|^2
    var_d)`` in some axis; ``stop`` if none."""
    g = np.empty(5, np.complex128)
    H = np.empty((5, 5), np.complex128)
    step = np.empty(5)
    for l in range(start, stop):
        c = _value_grad_hess(Ts[l] + G[l] * self_term, g, H)
        if not newton_step(c, g, H, step):
            return l
        a2 = abs(G[l]) ** 2
        for d in range(5):
            if abs(step[d]) * math.sqrt(2.0 * N * a2 * var[d]) > frac:
                return l
    return stop


@nb.njit(cache=True)
def refine(rr: np.ndarray, ri: np.ndarray, w0: np.ndarray, offsets: np.ndarray, dims: np.ndarray, W: np.ndarray,
           G: np.ndarray, iters: int, tol: float, g_self: complex, w_self: np.ndarray, first: np.ndarray,
           var: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Newton steps on ``S(w) = |v(w)^H (r + g_self v(w_self))|^2`` from ``w0`` (``r`` as in :func:`contract`):
    stops where the Hessian of ``S`` is not negative definite, a step lowers ``S`` (that step undone) or
    every step is below ``tol`` times the axis' CRB standard deviation ``1 / sqrt(2 N |c / N|^2 var_d)``
    at the current gain (``var``: the axes' index variances); steps limited to half a DFT cell per axis.

    ``first``: :func:`contract` at ``w0`` when known (else an empty array). Returns the final ``w``, its
    :func:`contract` and True where that was computed on the way (else an unspecified array and False).
    """
    N = 1.0
    for d in range(5):
        N *= dims[d]
    w = w0.copy()
    prev_w = w0.copy()
    prev_T = np.zeros((3, 3, 3, 3, 3), np.complex128)
    prev_S = -1.0
    step = np.empty(5)
    g = np.empty(5, np.complex128)
    H = np.empty((5, 5), np.complex128)
    s = np.empty((5, 3), np.complex128)
    for it in range(iters):
        T = first.copy() if it == 0 and first.size else contract(rr, ri, w, offsets, dims, W, G)
        Tc = T.copy()
        if g_self != 0:
            for d in range(5):
                _axis_sums(w_self[d] - w[d], offsets[d], dims[d], s, d)
            _add_outer(Tc, s, g_self)
        c = _value_grad_hess(Tc, g, H)
        S = abs(c) ** 2
        if S < prev_S:
            return prev_w, prev_T, True
        if not newton_step(c, g, H, step):
            return w, T, True
        prev_w, prev_S, prev_T = w, S, T
        w = w.copy()
        small = True
        a2 = abs(c / N) ** 2
        for d in range(5):
            half = math.pi / dims[d]
            step[d] = min(max(step[d], -half), half)
            w[d] += step[d]
            small = small and abs(step[d]) * math.sqrt(2.0 * N * a2 * var[d]) < tol
        if small:
            break
    return w, prev_T, False
