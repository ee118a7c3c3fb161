"""Channel-parameter estimator: beamspace-delay Newtonized OMP on the received MIMO-OFDM pilots (issue 24).

Signal model (one vehicle and step, unit noise variance; :mod:`mmslam.arrays` for the arrays)::

    Y[m, n, k] = sum_l g_l a_rx,m(u_rx,l) a_tx,n(u_tx,l) exp(-j 2 pi f_k tau_l) + W[m, n, k],   W ~ CN(0, 1)

``m`` over the ``rx_array^2`` vehicle elements, ``n`` over the ``tx_array^2`` BS elements, ``k`` over
``K`` subcarriers ``f_k = (k - K/2) B / K``; ``tau_l`` the delay after the receiver's window start
(:class:`PilotModel`), ``g_l`` the complex amplitude (``|g|^2`` the per-entry SNR). On the URAs'
element grids every factor is a 1-D complex exponential, so one path is a Kronecker product of five
1-D atoms ``v_d(w_d)_i = exp(j w_d (i - o_d))`` over the axes ``[rx column, rx row, tx column, tx row,
delay]`` with the *spatial / delay frequencies* ``w = (pi u_rx,y, -pi u_rx,z, pi u_tx,y, -pi u_tx,z,
-2 pi (B/K) tau)`` (``o_d``: the axis centre, ``K/2`` for the delay).

Estimator: Newtonized orthogonal matching pursuit (NOMP, Mamandipoor, Ramasamy & Madhow, IEEE TSP
64(19), 2016, extending OMP of Pati et al. 1993 / Mallat & Zhang 1993 to the continuum) in the
5-D beamspace-delay domain, the approach of Shahmansoori et al. (IEEE TWC 17(3), 2018) for mmWave
positioning, with a CFAR stop:

1. detect: the residual's orthogonal 5-D DFT (cells of the resolution grid, one FFT of ``Y``
   updated in place); the statistic ``T = max_j |R_j|^2 / N`` (``N = rx^2 tx^2 K``). On noise only
   the ``T_j`` are i.i.d. Exp(1), so ``T > t = -ln(1 - (1 - P_fa)^(1/N))`` has false-alarm
   probability ``P_fa`` per vehicle-step (the design value, :func:`cfar_threshold`);
2. refine: two sweeps of a per-axis search (17 values within a cell either side) bring the grid
   cell into the basin of ``S(w) = |v(w)^H r|^2``, then Newton steps (value, gradient and Hessian of
   ``v^H r`` from one contraction of the residual with ``[v, v', v'']`` per axis);
3. gain ``g = v^H r / N``; residual ``r -= g v`` (and its DFT by the DFT of the atom);
4. after each detection, one cyclic pass re-refines every earlier path on ``r + g_l v_l`` (up to three
   Newton steps each) whose Newton step there exceeds half its CRB std: without it a strong path
   biased by a later-found neighbour leaves a residual above the threshold (spurious estimates
   around the line of sight).

Cost (:func:`nomp`, :mod:`.nomp_kernels`, :mod:`.dft_kernels`): ``r = Y - sum_l g_l v(w_l)`` is never formed; a
contraction of ``r`` is one compiled pass over ``Y`` less the atoms' separable closed-form terms, and
each path keeps its derivative tensor on ``r``, updated in closed form when an atom is added or
moved, so step 4's test costs no pass; the DFT of ``r`` (for step 1) is updated lazily, per block of
a row only where the block could hold the maximum (exact bounds, :func:`.dft_kernels.update_dft`).

Paths closer than the resolution (about one DFT cell in every axis: ``c / B`` in range, ``2 / n``
in each spatial frequency) are one atom to this estimator: they merge into one estimate near their
power-weighted centre (tested). Grid cells scallop: an off-grid path loses up to ~3.9 dB per axis in
the detection statistic (about 1 dB per axis on average); refinement recovers its full gain.

Accuracy: the Fisher information of one path at the estimate (:func:`fisher_w`, closed form from
the axis moments, the complex gain a nuisance) mapped to the measurement ``[toa (m), aod az, aod
el, aoa az (body), aoa el]`` through the Jacobian of ``z -> w`` (:func:`measurement_covariance`).
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from mmslam import arrays

from . import dft_kernels as dk
from . import nomp_kernels as nk

SPEED_OF_LIGHT = 299_792_458.0  # m/s
ANGLE_PRIOR_STD = (math.pi, math.pi / 2.0)
"""Weak prior (rad) on azimuths / elevations added to the Fisher information before inversion: keeps
the covariance finite where the mapping ``angles -> w`` is singular (elevation at the horizon of a
horizontal array); negligible elsewhere."""


@dataclass(frozen=True)
class Grid:
    """The estimator's geometry: URA sizes and OFDM subcarriers.

    Attributes: tx_array, rx_array: elements per axis (BS, vehicle). n_subcarriers: K.
    bandwidth_hz: B (subcarrier spacing ``B / K``).
    """

    tx_array: int
    rx_array: int
    n_subcarriers: int
    bandwidth_hz: float

    @property
    def shape(self) -> tuple[int, int, int, int, int]:
        """5-D axes ``(rx column, rx row, tx column, tx row, subcarrier)``."""
        return (self.rx_array, self.rx_array, self.tx_array, self.tx_array, self.n_subcarriers)

    @property
    def offsets(self) -> np.ndarray:
        """Axis centres ``o_d`` (phase references)."""
        r, t, k = self.rx_array, self.tx_array, self.n_subcarriers
        return np.array([(r - 1) / 2, (r - 1) / 2, (t - 1) / 2, (t - 1) / 2, k // 2], float)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def spacing_hz(self) -> float:
        return self.bandwidth_hz / self.n_subcarriers

    @property
    def window_m(self) -> float:
        """Unambiguous delay window ``c K / B`` (m)."""
        return SPEED_OF_LIGHT / self.spacing_hz


def cfar_threshold(grid: Grid, pfa: float) -> float:
    """Threshold ``t`` on ``max_j |R_j|^2 / N`` with ``P(max > t) = pfa`` on white unit noise."""
    return float(-math.log(-math.expm1(math.log1p(-pfa) / grid.size)))


def atoms(w: np.ndarray, grid: Grid, order: int = 0) -> list[np.ndarray]:
    """Per axis ``[d^p/dw^p v_d(w_d) for p = 0..order]``, each ``(order + 1, L_d)`` complex."""
    out = []
    for d, L in enumerate(grid.shape):
        i = np.arange(L) - grid.offsets[d]
        v = np.exp(1j * w[d] * i)
        out.append(np.stack([v * (1j * i) ** p for p in range(order + 1)]))
    return out


def _outer(vs: list[np.ndarray]) -> np.ndarray:
    """``v0 (x) v1 (x) .. (x) v4`` as the 5-D tensor."""
    out = vs[0]
    for v in vs[1:]:
        out = np.multiply.outer(out, v)
    return out


def atom_tensor(w: np.ndarray, grid: Grid) -> np.ndarray:
    """The 5-D atom ``v(w)``."""
    return _outer([a[0] for a in atoms(w, grid, 0)])


def grid_frequency(index: tuple[int, ...], grid: Grid) -> np.ndarray:
    """``w`` of DFT cell ``index``: ``2 pi j / L`` wrapped to ``(-pi, pi]``."""
    L = np.asarray(grid.shape, float)
    w = 2.0 * np.pi * np.asarray(index, float) / L
    return np.where(w > np.pi, w - 2.0 * np.pi, w)


_SCRATCH = threading.local()
"""Per thread, the four ``(Na, K)`` arrays of :class:`_Residual`, the FFT's buffer and the DFT's update log,
reused by the next :func:`nomp` call of the same size: fresh arrays of this size are fresh pages from the
system, and their page faults made the set-up of one call 19 ms instead of 8 ms (measured, default grid)."""


class _Residual:
    """The residual ``r = y - sum_m g_m v(w_m) (Na, K)`` of one :func:`nomp` call: the pilots ``y`` split
    real / imaginary (:mod:`.nomp_kernels`), never modified, and the atoms ``(w_m, g_m)`` so far (every
    contraction of ``r`` is one of ``y`` less the atoms' closed-form terms); the residual's 5-D DFT,
    updated by the atoms' DFTs; the grid's constants."""

    def __init__(self, Y: np.ndarray, grid: Grid):
        import scipy.fft

        self.grid = grid
        self.N = float(grid.size)
        Na, K = grid.size // grid.n_subcarriers, grid.n_subcarriers
        Y2 = np.asarray(Y).reshape(Na, K)
        ws = getattr(_SCRATCH, "arrays", None)
        if ws is None or ws[0].shape != (Na, K):
            ws = _SCRATCH.arrays = (np.empty((Na, K)), np.empty((Na, K)), np.empty((Na, K)), np.empty((Na, K)),
                                    np.empty(grid.shape, complex))
        self.rr, self.ri, self.Rr, self.Ri, work = ws
        np.copyto(self.rr, Y2.real)
        np.copyto(self.ri, Y2.imag if np.iscomplexobj(Y2) else 0.0)
        np.copyto(work, Y2.reshape(grid.shape))
        R2 = scipy.fft.fftn(work, workers=1, overwrite_x=True).reshape(Na, K)
        np.copyto(self.Rr, R2.real)
        np.copyto(self.Ri, R2.imag)
        self.dims = np.asarray(grid.shape, np.int64)
        self.offsets = np.asarray(grid.offsets, float)
        L = np.asarray(grid.shape, float)  # coordinate-search offsets within one cell either side
        self.cand = np.stack([np.linspace(-2 * np.pi / n, 2 * np.pi / n, 17) for n in L])
        i = [np.arange(n) - o for n, o in zip(grid.shape, grid.offsets)]
        m1 = np.array([x.sum() for x in i]) / L
        m2 = np.array([(x * x).sum() for x in i]) / L
        self.var = m2 - m1 * m1  # per-axis index variance (:func:`fisher_w`)
        self.twiddle = np.ones((5, max(grid.shape)), complex)  # exp(-2 pi j m / L_d), the DFTs of the atoms
        for d, n in enumerate(grid.shape):
            self.twiddle[d, :n] = np.exp(-2j * np.pi * np.arange(n) / n)
        self.self_term = self.cross(np.zeros(5), np.zeros(5))[0]  # v^(p)(w)^H v(w): the same for every w
        self.W, self.G = np.zeros((0, 5)), np.zeros(0, complex)  # the atoms subtracted from y
        self.no_tensor = np.zeros((0, 3, 3, 3, 3), complex)
        # the DFT's update log (:func:`.dft_kernels.update_dft`): atoms' factors and gains, call boundaries,
        # per row the calls applied, its maximum and a bound of its pending change
        self.log = getattr(_SCRATCH, "log", None)  # its arrays reused (as the four above), grown as needed
        if self.log is None or self.log[3].shape[1] != Na or self.log[4].shape[1] != K:
            self.log = self._new_log(64, Na, K)
        self.n_log = 0
        self.calls = [0]
        nb = -(-K // dk.DFT_BLOCK)
        self.done = np.zeros((Na, nb), np.int64)
        self.top = np.full((Na, nb), np.inf)
        self.arg = np.zeros((Na, nb), np.int64)
        self.pend = np.zeros((Na, nb))

    def contract(self, w: np.ndarray) -> np.ndarray:
        """``(3,)*5`` derivatives of ``v(w)^H r`` (one pass over ``y``, the atoms' terms in closed form)."""
        return nk.contract(self.rr, self.ri, np.asarray(w, float), self.offsets, self.dims, self.W, self.G)

    def cross(self, W: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``(n, 3,)*5``: the same derivatives of ``v(W_k)^H v(w)`` (closed form, separable)."""
        W = np.atleast_2d(np.asarray(W, float))
        S = np.zeros((len(W), 3, 3, 3, 3, 3), complex)
        nk.add_cross_terms(S, W, np.asarray(w, float), 1.0 + 0j, self.offsets, self.dims)
        return S

    def coordinate_search(self, j: int, sweeps: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """From DFT cell ``j`` (flat index), per axis in turn the maximum of ``|v(w)^H r|^2`` over 17 values of
        ``w_d`` within one DFT cell either side (the others fixed): brings the cell into Newton's basin.

        The first delay profile ``v_ant(w)^H r`` is the inverse delay DFT of the cell's row of the
        residual's DFT (times the phase of the axes' centres): no pass over ``y``. Returns the final ``w``
        and its :meth:`contract` (from the last sweep's pass: no pass of its own)."""
        w = grid_frequency(np.unravel_index(j, self.grid.shape), self.grid)
        ja = j // self.grid.n_subcarriers
        x0 = np.fft.ifft(self.Rr[ja] + 1j * self.Ri[ja]) * np.exp(1j * np.dot(w[:4], self.offsets[:4]))
        return nk.coordinate_search(self.rr, self.ri, w, self.offsets, self.dims, self.cand, sweeps, self.W,
                                    self.G, x0)

    def subtract_dft(self, ws: list[np.ndarray], gs: list[complex], second: list[bool]) -> tuple[int, float]:
        """The DFT's ``R -= sum_m g_m DFT(v(w_m))``; returns the flat index and value of ``max |R|^2``.
        ``second[m]``: atoms ``m - 1`` and ``m`` are one path's new and old atom. Rows of ``R`` are brought
        up to date only where they may hold the maximum (:func:`.dft_kernels.update_dft`); the row of the
        maximum always is."""
        n = len(ws)
        if self.n_log + n > len(self.log[0]):  # grow the log (doubling)
            log = self._new_log(max(2 * len(self.log[0]), self.n_log + n), self.log[3].shape[1], self.log[4].shape[1])
            for x, y in zip(log, self.log):
                x[:self.n_log] = y[:self.n_log]
            self.log = log
        W, g, sec, a, br, bi = self.log
        if n:
            sl = slice(self.n_log, self.n_log + n)
            W[sl], g[sl], sec[sl] = ws, gs, second
        self.n_log += n
        self.calls.append(self.n_log)
        return dk.update_dft(self.Rr, self.Ri, W, g, sec, a, br, bi, self.offsets, self.dims, self.twiddle,
                             np.asarray(self.calls, np.int64), self.done, self.top, self.arg, self.pend)

    @staticmethod
    def _new_log(cap: int, Na: int, K: int) -> tuple[np.ndarray, ...]:
        """Empty log arrays for ``cap`` atoms (:func:`.dft_kernels.update_dft`), kept for the thread's next call."""
        _SCRATCH.log = (np.empty((cap, 5)), np.empty(cap, complex), np.empty(cap, bool), np.empty((cap, Na), complex),
                        np.empty((cap, K)), np.empty((cap, K)))
        return _SCRATCH.log


def refine(res: _Residual, w: np.ndarray, iters: int = 8, tol: float = 0.02, g_self: complex = 0j,
           w_self: np.ndarray | None = None, first: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Newton steps on ``S(w) = |v(w)^H (r + g_self v(w_self))|^2`` from ``w`` (:func:`.nomp_kernels.refine`):
    stops where the Hessian is not negative definite, a step lowers ``S`` (that step undone) or every
    step is below ``tol`` times the axis' CRB standard deviation at the current gain ``c / N``
    (converged far inside the noise); steps limited to half a DFT cell per axis.

    ``first``: :meth:`_Residual.contract` at ``w`` when already known. Returns the final ``w`` and its
    contraction where it was computed on the way (else None)."""
    w = np.asarray(w, float)
    w, T, known = nk.refine(res.rr, res.ri, w, res.offsets, res.dims, res.W, res.G, int(iters), float(tol),
                            complex(g_self), w if w_self is None else np.asarray(w_self, float),
                            res.no_tensor if first is None else first, res.var)
    return w, (T if known else None)


def nomp(Y: np.ndarray, grid: Grid, pfa: float, max_paths: int = 20,
         cyclic_passes: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """NOMP (module docstring) on one received tensor.

    Each path keeps ``T_l``, the ``(3,)*5`` derivatives of ``v(w_l)^H r`` on the current residual: a
    change of the residual by ``g v(w)`` changes it by the closed-form separable ``g v^(p)(w_l)^H v(w)``
    (:func:`.nomp_kernels.add_cross_terms`), so the cyclic refinement decides which earlier paths move, and
    takes their first Newton step, without touching the residual; only the paths that move cost
    passes over it. The residual's DFT is updated once per detection, by the DFTs of the atoms added
    and removed.

    Args:
        Y: ``(rx_ant, tx_ant, K)`` or the 5-D tensor; unit noise variance.
        grid: sizes. pfa: false-alarm probability per call on noise only (CFAR design value).
        max_paths: at most this many estimates. cyclic_passes: refinement passes over the earlier
            paths after each detection.

    Returns:
        ``(w (L, 5), g (L,))``: spatial / delay frequencies and complex amplitudes, in detection order.
    """
    res = _Residual(Y, grid)
    N = res.N
    t = cfar_threshold(grid, pfa) * N
    ws: list[np.ndarray] = []
    gs: list[complex] = []
    W_all, G_all = np.zeros((int(max_paths), 5)), np.zeros(int(max_paths), complex)  # res.W, res.G: their heads
    T_all = np.zeros((int(max_paths), 3, 3, 3, 3, 3), complex)  # per path: derivatives of v(w_l)^H r
    Ts = T_all[:0]

    def replace(l: int, w: np.ndarray, g: complex, T_fit: np.ndarray) -> None:
        """Path ``l`` (``l = len(ws)``: a new one) becomes ``(w, g)``; ``T_fit`` its tensor on the residual
        before the change. Updates the residual and every path's tensor."""
        nonlocal Ts
        add, sub = [w], [g]
        if l == len(ws):
            ws.append(w)
            gs.append(g)
            Ts = T_all[:len(ws)]
        else:
            add, sub = [w, ws[l]], [g, -gs[l]]
            ws[l], gs[l] = w, g
        Ts[l] = T_fit
        W_all[l], G_all[l] = w, g
        res.W, res.G = W_all[:len(ws)], G_all[:len(ws)]
        for wa, ga in zip(add, sub):
            nk.add_cross_terms(Ts, res.W, wa, -ga, res.offsets, res.dims)
        pending.extend(zip(add, sub, [False, True]))

    pending: list[tuple[np.ndarray, complex, bool]] = []
    j, pmax = res.subtract_dft([], [], [])
    for _ in range(int(max_paths)):
        if pmax <= t:
            break
        w, T_fit = res.coordinate_search(j)
        w, T_fit = refine(res, w, first=T_fit)
        T_fit = res.contract(w) if T_fit is None else T_fit
        replace(len(ws), w, complex(T_fit.flat[0]) / N, T_fit)
        # cyclic refinement (NOMP): every earlier path re-fitted on the residual plus itself (its own
        # term added in closed form) where its Newton step exceeds half its CRB std. Left where it is,
        # its residual holds about sum (step / std)^2 / 2 <= 1.25 noise variances, far below the CFAR
        # threshold (~17 at the default grid): no spurious detection from it.
        for _ in range(int(cyclic_passes)):
            l = -1
            while True:
                l = nk.next_mover(Ts, res.G, res.self_term, res.var, N, l + 1, len(ws) - 1, 0.5)
                if l == len(ws) - 1:
                    break
                w_new, T_fit = refine(res, ws[l], iters=3, g_self=gs[l], w_self=ws[l], first=Ts[l])
                T_fit = res.contract(w_new) if T_fit is None else T_fit
                g_new = complex(T_fit.flat[0]) / N + gs[l] * complex(res.cross(w_new, ws[l])[0].flat[0]) / N
                replace(l, w_new, g_new, T_fit)
        j, pmax = res.subtract_dft(*map(list, zip(*pending)))
        pending.clear()
    w_out = np.angle(np.exp(1j * np.array(ws, float).reshape(-1, 5)))  # wrapped to (-pi, pi]
    return w_out, np.array(gs, complex)


def fisher_w(g: complex | np.ndarray, grid: Grid) -> np.ndarray:
    """Efficient Fisher information of ``w`` (5 x 5, the complex gain a nuisance) for one path of
    amplitude ``g`` in unit white noise; ``(..., 5, 5)`` for an array of gains.

    ``F = 2 Re(D^H D)`` with ``D = [g dv/dw_0 .. g dv/dw_4, v, j v]``; with the per-axis index means
    ``m_p = mean_i (i - o_d)^p``: ``<v, v> = N``, ``<v, dv/dw_d> = j N m1_d``, ``<dv/dw_d, dv/dw_d> =
    N m2_d``, ``<dv/dw_d, dv/dw_e> = N m1_d m1_e``; the Schur
    complement over the gain ``(Re g, Im g)`` (block ``2 N I``) removes ``2 N |g|^2 m1 m1^T``, leaving the
    diagonal ``F = 2 N |g|^2 diag(m2 - m1^2)``: each axis' index variance (for the delay axis
    ``(K^2 - 1) / 12``).
    """
    L = np.asarray(grid.shape, float)
    i = [np.arange(n) - o for n, o in zip(grid.shape, grid.offsets)]
    m1 = np.array([x.sum() for x in i]) / L
    m2 = np.array([(x * x).sum() for x in i]) / L
    a2 = np.abs(np.asarray(g, complex)) ** 2
    return 2.0 * grid.size * a2[..., None, None] * np.diag(m2 - m1 * m1)


def w_of_measurement(z: np.ndarray, t0_m: float, grid: Grid) -> np.ndarray:
    """``w`` of measurements ``z (..., 5) = [toa (m), aod az, aod el, aoa az (body), aoa el]`` with window
    start ``t0_m`` (m, receiver clock)."""
    z = np.asarray(z, float)
    ut = arrays.direction_to_local(z[..., 1], z[..., 2], 0.0, arrays.BS_PITCH)
    ur = arrays.direction_to_local(z[..., 3], z[..., 4], 0.0, arrays.VEHICLE_PITCH)
    tau = (z[..., 0] - t0_m) / SPEED_OF_LIGHT
    return np.stack([np.pi * ur[..., 0], -np.pi * ur[..., 1], np.pi * ut[..., 0], -np.pi * ut[..., 1],
                     -2.0 * np.pi * grid.spacing_hz * tau], axis=-1)


def measurement_of_w(w: np.ndarray, t0_m: float, grid: Grid) -> np.ndarray:
    """Inverse of :func:`w_of_measurement` (delay in ``[0, window)``; spatial frequencies outside the unit
    circle are scaled onto it, i.e. the horizon)."""
    w = np.angle(np.exp(1j * np.asarray(w, float)))  # (-pi, pi]: the atoms are 2 pi periodic

    def direction(wy, wz, pitch):
        u = np.stack([wy / np.pi, -wz / np.pi], axis=-1)
        n = np.linalg.norm(u, axis=-1, keepdims=True)
        u = np.where(n > 1.0, u / np.maximum(n, 1e-300), u)
        return arrays.local_to_direction(u, pitch)

    raz, rel = direction(w[..., 0], w[..., 1], arrays.VEHICLE_PITCH)
    taz, tel = direction(w[..., 2], w[..., 3], arrays.BS_PITCH)
    tau = np.mod(-w[..., 4], 2.0 * np.pi) / (2.0 * np.pi * grid.spacing_hz)
    return np.stack([t0_m + SPEED_OF_LIGHT * tau, taz, tel, raz, rel], axis=-1)


def measurement_covariance(z: np.ndarray, g: np.ndarray, t0_m: float, grid: Grid) -> np.ndarray:
    """Covariances ``(L, 5, 5)`` of measurements ``z (L, 5)`` with amplitudes ``g (L,)``:
    ``(J^T F_w J + P0)^-1`` with ``J = dw/dz`` (central differences) and the weak angle prior ``P0``
    (:data:`ANGLE_PRIOR_STD`)."""
    z = np.atleast_2d(np.asarray(z, float))
    Fw = fisher_w(np.asarray(g, complex).reshape(-1), grid)
    h = np.array([1e-4, 1e-7, 1e-7, 1e-7, 1e-7])
    J = np.empty((z.shape[0], 5, 5))
    for e in range(5):
        dz = np.zeros(5)
        dz[e] = h[e]
        J[:, :, e] = (w_of_measurement(z + dz, t0_m, grid) - w_of_measurement(z - dz, t0_m, grid)) / (2 * h[e])
    P0 = np.diag([0.0, ANGLE_PRIOR_STD[0] ** -2, ANGLE_PRIOR_STD[1] ** -2, ANGLE_PRIOR_STD[0] ** -2,
                  ANGLE_PRIOR_STD[1] ** -2])
    Fz = np.einsum("lae,lab,lbf->lef", J, Fw, J) + P0
    return np.linalg.inv(Fz)
