"""Compiled update of the residual's 5-D DFT for the channel-parameter estimator
(:mod:`mmslam.slam.sim.channel_estimator`, step 1 of NOMP: the detection statistic).

The DFT is held as split real / imaginary ``(Na, K)`` float64 arrays (``Na = rx^2 tx^2`` antenna pairs
in the C order of the axes ``[rx column, rx row, tx column, tx row]``, ``K`` subcarriers), as the
residual in :mod:`.nomp_kernels`; ``dims (5,)`` the axis lengths, ``offsets (5,)`` the axis centres
``o_d`` of the atoms ``v_d(w)_i = exp(j w (i - o_d))``. Each detection changes the residual by a few
atoms; their DFTs are separable (one Dirichlet kernel per axis), and the update is applied lazily, block
by block, only where a block could hold the maximum.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

DFT_BLOCK = 32
"""Subcarriers per block of a row of the residual's DFT (:func:`update_dft`'s unit of update)."""
FIRST_ROWS = 16
"""Rows :func:`update_dft` visits in decreasing order of their bound before it scans the others in order."""


@nb.njit(cache=True, fastmath=True)
def update_dft(Xr: np.ndarray, Xi: np.ndarray, W: np.ndarray, g: np.ndarray, second: np.ndarray, a: np.ndarray,
               br: np.ndarray, bi: np.ndarray, offsets: np.ndarray, dims: np.ndarray, tw: np.ndarray,
               calls: np.ndarray, done: np.ndarray, top: np.ndarray, arg: np.ndarray,
               pend: np.ndarray) -> tuple[int, float]:
    """``X -= sum_m g_m a_m b_m^T`` for the atoms of the latest call, the DFTs of the atoms ``v(W_m)``,
    applied only where needed to find ``max |X|^2`` (``X = Xr + j Xi (Na, K)``, the residual's 5-D DFT);
    returns the flat index and value of that maximum of the updated ``X``. Rows are cut into blocks of
    :data:`DFT_BLOCK` subcarriers (``nb`` per row).

    The log: ``W (n, 5)``, ``g (n,)``: every atom subtracted so far, in order; call ``c`` subtracts atoms
    ``calls[c]:calls[c + 1]`` (``calls (C + 1,)``, the latest call last); this call fills the factors of
    its atoms' DFTs (:func:`_atom_dft`; ``tw (5, max(dims))``: ``exp(-2 pi j m / L_d)``): antenna ``a (n,
    Na)`` complex (the Kronecker product of the four antenna axes, C order), delay ``b = br + j bi (n,
    K)``; ``second[m]``: atoms ``m - 1`` and ``m`` are one path's move (new and old atom), bounded
    together. Per block ``(i, q)`` (arrays ``(Na, nb)``): ``done`` calls applied, ``top`` / ``arg`` the
    block's ``max |X|^2`` and its subcarrier as held, ``pend`` a bound of the change of any of its entries
    by the calls not applied. A block is brought up to date (its pending calls applied in order, two
    atoms per sweep: the same operations as updating every entry at every call) only where ``(sqrt(top)
    + pend)^2`` reaches the largest value found so far (first the :data:`FIRST_ROWS` rows of the largest
    such bound, in decreasing order, then the others in order); every other block is below the maximum.
    Bounds: per atom ``|g a_i b_k| <= |g a_i| max_q |b|`` (``max_q``: over the block); per move ``g1 a1
    b1 + g2 a2 b2 = (g1 a1 + g2 a2) b1 + g2 a2 (b2 - b1)``, small where the path moved little. The row of
    the maximum is brought up to date whole (the coordinate search reads it).
    """
    Na, K = Xr.shape
    nb = done.shape[1]
    C = calls.shape[0] - 1
    m0, m1 = calls[C - 1], calls[C]
    f = np.empty((5, tw.shape[1]), np.complex128)
    for m in range(m0, m1):
        for d in range(5):
            _atom_dft(W[m, d], offsets[d], dims[d], tw[d], f[d])
        for k in range(K):
            br[m, k] = f[4, k].real
            bi[m, k] = f[4, k].imag
        i = 0
        for i0 in range(dims[0]):
            for i1 in range(dims[1]):
                f01 = f[0, i0] * f[1, i1]
                for i2 in range(dims[2]):
                    f012 = f01 * f[2, i2]
                    for i3 in range(dims[3]):
                        a[m, i] = f012 * f[3, i3]
                        i += 1
    bm = np.zeros((m1 - m0, nb))  # per block max |b_m|; for the second atom of a move max |b_m - b_(m-1)|
    for m in range(m0, m1):
        for q in range(nb):
            t = 0.0
            for k in range(q * DFT_BLOCK, min(K, (q + 1) * DFT_BLOCK)):
                dr, di = br[m, k], bi[m, k]
                if second[m]:
                    dr, di = dr - br[m - 1, k], di - bi[m - 1, k]
                t = max(t, dr * dr + di * di)
            bm[m - m0, q] = math.sqrt(t) * (1.0 + 1e-9)  # and the rounding of these sums
    f1 = np.empty(Na)
    f2 = np.zeros(Na)
    m = m0
    while m < m1:  # pend += per row |coefficient| x per block max |b| (vectorised over the rows)
        pair = m + 1 < m1 and second[m + 1]
        for i in range(Na):
            c = g[m] * a[m, i]
            if pair:
                d = g[m + 1] * a[m + 1, i]
                c += d
                f2[i] = math.sqrt(d.real * d.real + d.imag * d.imag)
            f1[i] = math.sqrt(c.real * c.real + c.imag * c.imag)
        for i in range(Na):
            for q in range(nb):
                pend[i, q] += f1[i] * bm[m - m0, q] + (f2[i] * bm[m + 1 - m0, q] if pair else 0.0)
        m += 2 if pair else 1
    bound = np.empty((Na, nb))
    rowb = np.zeros(Na)
    for i in range(Na):
        for q in range(nb):
            pq = pend[i, q] * (1.0 + 1e-9)  # the rounding of the bound's sums
            if pq > 0.0:
                t = math.sqrt(top[i, q]) + pq
                bound[i, q] = t * t * (1.0 + 1e-9)
            else:
                bound[i, q] = top[i, q]
            rowb[i] = max(rowb[i], bound[i, q])
    best = -1.0
    jbest = 0
    for r in range(Na + FIRST_ROWS):  # the rows of the largest bounds first, then the others in order
        if r < FIRST_ROWS:
            i = np.argmax(rowb)
        elif r - FIRST_ROWS < Na:
            i = r - FIRST_ROWS
        if rowb[i] < best:
            if r < FIRST_ROWS:
                break
            continue
        rowb[i] = -1.0  # done
        for q in range(nb):
            if bound[i, q] < best:
                continue
            if done[i, q] < C:
                _update_block(Xr, Xi, a, br, bi, g, calls, done, top, arg, pend, i, q)
            j = i * K + arg[i, q]
            if top[i, q] > best or (top[i, q] == best and j < jbest):
                best = top[i, q]
                jbest = j
    i = jbest // K
    for q in range(nb):  # the maximum's whole row (the coordinate search reads it)
        if done[i, q] < C:
            _update_block(Xr, Xi, a, br, bi, g, calls, done, top, arg, pend, i, q)
    return jbest, best


@nb.njit(cache=True)
def _atom_dft(w: float, offset: float, L: int, tw: np.ndarray, out: np.ndarray) -> None:
    """The DFT of a 1-D atom: ``out[m] = sum_i exp(j w (i - offset)) exp(-2 pi j m i / L)`` for ``m < L``; closed
    form ``exp(-j w offset) (1 - exp(j w L)) / (1 - exp(j w) tw[m])`` (``tw[m] = exp(-2 pi j m / L)``), the
    sum itself (phasor by recurrence) where the denominator is below 0.03 (within ~0.03 rad of a bin)."""
    z = complex(math.cos(w), math.sin(w))
    e0 = complex(math.cos(w * offset), -math.sin(w * offset))
    num = e0 * (1.0 - complex(math.cos(w * L), math.sin(w * L)))
    for m in range(L):
        zm = z * tw[m]
        den = 1.0 - zm
        if den.real * den.real + den.imag * den.imag > 1e-3:
            out[m] = num / den
        else:
            t = 0j
            e = e0
            for i in range(L):
                t += e
                e *= zm
            out[m] = t


@nb.njit(cache=True, fastmath=True)
def _update_block(Xr: np.ndarray, Xi: np.ndarray, a: np.ndarray, br: np.ndarray, bi: np.ndarray, g: np.ndarray,
                  calls: np.ndarray, done: np.ndarray, top: np.ndarray, arg: np.ndarray, pend: np.ndarray, i: int,
                  q: int) -> None:
    """Block ``(i, q)`` of :func:`update_dft` brought up to date: its pending calls applied in order, its
    maximum and where."""
    K = Xr.shape[1]
    C = calls.shape[0] - 1
    k0, k1 = q * DFT_BLOCK, min(K, (q + 1) * DFT_BLOCK)
    xr = Xr[i]
    xi = Xi[i]
    for c in range(done[i, q], C):
        m = calls[c]
        while m < calls[c + 1]:  # two atoms per sweep of the block
            c1 = g[m] * a[m, i]
            cr, ci = c1.real, c1.imag
            if m + 1 < calls[c + 1]:
                c2 = g[m + 1] * a[m + 1, i]
                c2r, c2i = c2.real, c2.imag
                for k in range(k0, k1):
                    xr[k] -= (cr * br[m, k] - ci * bi[m, k]) + (c2r * br[m + 1, k] - c2i * bi[m + 1, k])
                for k in range(k0, k1):
                    xi[k] -= (cr * bi[m, k] + ci * br[m, k]) + (c2r * bi[m + 1, k] + c2i * br[m + 1, k])
            else:
                for k in range(k0, k1):
                    xr[k] -= cr * br[m, k] - ci * bi[m, k]
                for k in range(k0, k1):
                    xi[k] -= cr * bi[m, k] + ci * br[m, k]
            m += 2
    done[i, q] = C
    pend[i, q] = 0.0
    t = -1.0  # the block's maximum and its first index
    for k in range(k0, k1):
        pk = xr[k] * xr[k] + xi[k] * xi[k]
        if pk > t:
            t = pk
            arg[i, q] = k
    top[i, q] = t
