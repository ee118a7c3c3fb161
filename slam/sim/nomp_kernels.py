"""Compiled inner loops of the channel-parameter estimator (:mod:`mmslam.slam.sim.channel_estimator`).

The residual ``r`` and its 5-D DFT are held as split real / imaginary ``(Na, K)`` float64 arrays
(``Na = rx^2 tx^2`` antenna pairs in the C order of the axes ``[rx column, rx row, tx column, tx row]``,
``K`` subcarriers): the passes over them (contraction with a delay atom, updates of the DFT by atoms)
then run as SIMD loops. ``dims (5,)`` are the axis lengths ``(rx, rx, tx, tx, K)``, ``offsets (5,)`` the axis
centres ``o_d``; the 1-D atoms are ``v_d(w)_i = exp(j w (i - o_d))`` and their derivatives
``d^p v_d / dw^p = (j (i - o_d))^p v_d``.

Each pass touches every cell once (~0.12 ms at the default 262144 cells on this machine); everything
else is per axis. Sums are reordered against a numpy evaluation (``fastmath``) and phasors come from
short products and recurrences: results agree to rounding (~1e-13 relative in the estimates).
Derivative tensors ``(3,)*5`` hold the entries of total order ``<= 2`` (value, gradient, Hessian: all
that Newton reads); the others are zero.
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
def _contract_middle(X: np.ndarray, c: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``out[m, q, p] = sum_l X[m, l, p] c[q, l]``: ``X (M, L, P)``, ``c (Q, L)`` -> ``(M, Q, P)``, where ``q +
    order[p] <= 2`` (``order (P,)``: the total derivative order of ``p``); zero elsewhere."""
    M, L, P = X.shape
    out = np.zeros((M, c.shape[0], P), np.complex128)
    for m in range(M):
        for q in range(c.shape[0]):
            for p in range(P):
                if q + order[p] <= 2:
                    t = 0j
                    for l in range(L):
                        t += X[m, l, p] * c[q, l]
                    out[m, q, p] = t
    return out


@nb.njit(cache=True, fastmath=True)
def contract(rr: np.ndarray, ri: np.ndarray, w: np.ndarray, offsets: np.ndarray, dims: np.ndarray,
             W: np.ndarray, G: np.ndarray) -> np.ndarray:
    """``T[p0, .., p4] = (d^p0 v_0 (x) .. (x) d^p4 v_4)(w)^H r`` for ``p_d = 0..2``: ``(3, 3, 3, 3, 3)`` complex,
    on the residual ``r = y - sum_m G_m v(W_m)`` (``W (L, 5)``, ``G (L,)``); the entries of total order ``p0
    + .. + p4 <= 2`` (the value, gradient and Hessian of ``v(w)^H r``: all that is read of it), the others
    zero.

    One pass over ``y = rr + j ri (Na, K)`` (the delay axis, three derivative orders at once:
    :func:`_delay_pass`), then the four antenna axes and the atoms' terms (:func:`_antenna_part`).
    """
    A = np.empty((rr.shape[0], 3), np.complex128)
    _delay_pass(rr, ri, w[4], offsets[4], A)
    return _antenna_part(A, w, offsets, dims, W, G)


@nb.njit(cache=True, fastmath=True)
def _delay_pass(rr: np.ndarray, ri: np.ndarray, w4: float, o4: float, A: np.ndarray) -> None:
    """``A[a, p] = sum_k y[a, k] conj(d^p v_4 / dw^p)(w4)_k`` for ``p = 0, 1, 2`` into ``A (Na, 3)`` complex: one
    pass over ``y = rr + j ri (Na, K)``."""
    Na, K = rr.shape
    cr = np.empty(K)
    ci = np.empty(K)
    _phasors(w4, o4, cr, ci)
    xs = np.empty(K)
    for k in range(K):
        xs[k] = k - o4
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


@nb.njit(cache=True)
def _phasors(w: float, offset: float, c: np.ndarray, s: np.ndarray) -> None:
    """``c[i] + j s[i] = exp(j w (i - offset))`` for ``i < len(c)``: ``exp(j w (16 u - offset)) exp(j w t)`` with
    ``i = 16 u + t`` (a sixteenth of the cosines and sines; ~2 eps)."""
    B = 16
    lr = np.empty(B)
    li = np.empty(B)
    for t in range(B):
        lr[t] = math.cos(w * t)
        li[t] = math.sin(w * t)
    n = c.shape[0]
    for u in range((n + B - 1) // B):
        x = B * u - offset
        hr = math.cos(w * x)
        hi = math.sin(w * x)
        for t in range(min(B, n - B * u)):
            c[B * u + t] = hr * lr[t] - hi * li[t]
            s[B * u + t] = hr * li[t] + hi * lr[t]


@nb.njit(cache=True)
def _antenna_part(A: np.ndarray, w: np.ndarray, offsets: np.ndarray, dims: np.ndarray, W: np.ndarray,
                  G: np.ndarray) -> np.ndarray:
    """:func:`contract` from the delay pass ``A (Na, 3)`` of ``y``: the four antenna axes one after the other,
    less the atoms' terms in closed form (separable, :func:`add_cross_terms`)."""
    Na = A.shape[0]
    X = A.reshape(Na * 3)
    P = 3
    M = Na
    order = np.arange(3)  # total derivative order of the flat index over the axes contracted so far
    for d in range(3, -1, -1):  # axis d is the innermost antenna axis left: X (M, L_d, P) -> (M, 3, P)
        M //= dims[d]
        X = _contract_middle(X.reshape((M, dims[d], P)), _axis_factors(w[d], offsets[d], dims[d]),
                             order).reshape(-1)
        order3 = np.empty(3 * P, np.int64)
        for q in range(3):
            for p in range(P):
                order3[q * P + p] = q + order[p]
        order = order3
        P *= 3
    T = X.reshape((3, 3, 3, 3, 3))
    s = np.empty((5, 3), np.complex128)
    for m in range(G.shape[0]):
        for d in range(5):
            _axis_sums(W[m, d] - w[d], offsets[d], dims[d], s, d)
        _add_outer(T, s, -G[m])
    return T


@nb.njit(cache=True, fastmath=True)
def _axis_sums(theta: float, offset: float, n: int, s: np.ndarray, d: int) -> None:
    """``s[d, p] = sum_i (-j x)^p exp(j theta x)`` for ``p = 0, 1, 2``, ``x = i - offset`` (the phasor by
    recurrence, four interleaved chains of step ``exp(4 j theta)``: ~n eps / 4 relative)."""
    q = complex(math.cos(theta), math.sin(theta))
    q4 = (q * q) * (q * q)
    e0 = complex(math.cos(theta * offset), -math.sin(theta * offset))
    e1 = e0 * q
    e2 = e1 * q
    e3 = e2 * q
    a0 = 0j
    a1 = 0j  # sum x exp(j theta x), times -j at the end
    a2 = 0j  # sum x^2 exp(j theta x), times -1
    i = 0
    while i + 4 <= n:
        x0 = i - offset
        x1 = x0 + 1.0
        x2 = x0 + 2.0
        x3 = x0 + 3.0
        a0 += (e0 + e1) + (e2 + e3)
        a1 += (x0 * e0 + x1 * e1) + (x2 * e2 + x3 * e3)
        a2 += (x0 * x0 * e0 + x1 * x1 * e1) + (x2 * x2 * e2 + x3 * x3 * e3)
        e0 *= q4
        e1 *= q4
        e2 *= q4
        e3 *= q4
        i += 4
    while i < n:
        x0 = i - offset
        a0 += e0
        a1 += x0 * e0
        a2 += x0 * x0 * e0
        e0 *= q
        i += 1
    s[d, 0] = a0
    s[d, 1] = complex(a1.imag, -a1.real)
    s[d, 2] = -a2


@nb.njit(cache=True)
def _add_outer(T: np.ndarray, s: np.ndarray, g: complex) -> None:
    """``T += g s[0] (x) s[1] (x) .. (x) s[4]`` (``T (3,)*5``, ``s (5, 3)``) on the entries of total order
    ``p0 + .. + p4 <= 2``: the value, gradient and Hessian, all that is read of a derivative tensor
    (:func:`_value_grad_hess`); the others are left as they are."""
    for p0 in range(3):
        f0 = g * s[0, p0]
        for p1 in range(3 - p0):
            f01 = f0 * s[1, p1]
            for p2 in range(3 - p0 - p1):
                f012 = f01 * s[2, p2]
                for p3 in range(3 - p0 - p1 - p2):
                    f0123 = f012 * s[3, p3]
                    for p4 in range(3 - p0 - p1 - p2 - p3):
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


AXIS_ORDER = np.array([4, 2, 3, 0, 1])
"""The coordinate search's axis order: delay, tx column, tx row, rx column, rx row."""


@nb.njit(cache=True, fastmath=True)
def coordinate_search(rr: np.ndarray, ri: np.ndarray, w0: np.ndarray, offsets: np.ndarray, dims: np.ndarray,
                      cand: np.ndarray, sweeps: int, W: np.ndarray, G: np.ndarray,
                      x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis in turn (delay, tx column, tx row, rx column, rx row), ``w_d <- w_d + cand[d, j]`` with ``j``
    the maximum of ``|v(w)^H r|`` over ``j`` (the other axes fixed); ``sweeps`` times. ``cand (5, P)``:
    offsets within one DFT cell either side; ``r = y - sum_m G_m v(W_m)`` as in :func:`contract`. Two
    passes over ``y = rr + j ri`` per sweep (the antenna-contracted delay profile, then the
    delay-contracted antenna tensor), the atoms' terms added to each; ``x0 (K,)``, where not empty, is
    the first delay profile ``v_ant(w0)^H r`` (read off the residual's DFT when ``w0`` is a cell).

    Returns the final ``w`` and its :func:`contract` (``sweeps >= 1``): the last sweep's delay-contracted
    pass is :func:`contract`'s at the final delay (the delay axis is searched first), so only the antenna
    axes are left."""
    Na, K = rr.shape
    L1, L2, L3 = dims[1], dims[2], dims[3]
    nmax = np.max(dims)
    w = w0.copy()
    vs = np.empty((5, nmax), np.complex128)  # conj(v_d(w_d)), padded
    pc = np.empty(nmax)
    ps = np.empty(nmax)
    for d in range(5):
        _phasors(w[d], offsets[d], pc[:dims[d]], ps[:dims[d]])
        for i in range(dims[d]):
            vs[d, i] = complex(pc[i], -ps[i])
    ix = np.empty((Na, 4), np.int64)  # antenna pair a -> its index on each antenna axis (C order)
    a = 0
    for i0 in range(dims[0]):
        for i1 in range(L1):
            for i2 in range(L2):
                for i3 in range(L3):
                    ix[a, 0], ix[a, 1], ix[a, 2], ix[a, 3] = i0, i1, i2, i3
                    a += 1
    L = G.shape[0]
    vm = np.empty((L, 5, nmax), np.complex128)  # the atoms' v_d(W_md)
    vam = np.empty((L, Na), np.complex128)  # their antenna factors
    for m in range(L):
        for d in range(5):  # the phasor by recurrence (~n eps; they only steer the search)
            e = complex(math.cos(W[m, d] * offsets[d]), -math.sin(W[m, d] * offsets[d]))
            q = complex(math.cos(W[m, d]), math.sin(W[m, d]))
            for i in range(dims[d]):
                vm[m, d, i] = e
                e *= q
        for a in range(Na):
            vam[m, a] = vm[m, 0, ix[a, 0]] * vm[m, 1, ix[a, 1]] * vm[m, 2, ix[a, 2]] * vm[m, 3, ix[a, 3]]
    x = np.empty(nmax, np.complex128)
    A = np.empty(Na, np.complex128)
    A3 = np.empty((Na, 3), np.complex128)
    for sweep in range(sweeps):
        for d in AXIS_ORDER:
            n = dims[d]
            if d == 4 and sweep == 0 and x0.size:
                x[:K] = x0
            elif d == 4:  # x[k] = sum_a conj(va[a]) r[a, k]
                xr = np.zeros(K)
                xi = np.zeros(K)
                for a in range(Na):
                    c = vs[0, ix[a, 0]] * vs[1, ix[a, 1]] * vs[2, ix[a, 2]] * vs[3, ix[a, 3]]
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
                if d == 2 and sweep == sweeps - 1:  # the delay is final: its three orders, for the result's T
                    _delay_pass(rr, ri, w[4], offsets[4], A3)
                    for a in range(Na):
                        A[a] = A3[a, 0]
                elif d == 2:  # first antenna axis after the delay: A[a] = sum_k r[a, k] conj(vk[k])
                    for a in range(Na):
                        sr = 0.0
                        si = 0.0
                        for k in range(K):
                            sr += rr[a, k] * vs[4, k].real - ri[a, k] * vs[4, k].imag
                            si += ri[a, k] * vs[4, k].real + rr[a, k] * vs[4, k].imag
                        A[a] = complex(sr, si)
                if d == 2:
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
                    c = A[a]
                    for e in range(4):
                        if e != d:
                            c *= vs[e, ix[a, e]]
                    x[ix[a, d]] += c
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
            _phasors(w[d], offsets[d], pc[:n], ps[:n])
            for i in range(n):
                vs[d, i] = complex(pc[i], -ps[i])
    return w, _antenna_part(A3, w, offsets, dims, W, G)


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
