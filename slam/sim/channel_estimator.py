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
   Newton steps each): without it a strong path biased by a later-found neighbour leaves a residual
   above the threshold (spurious estimates around the line of sight).

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
from dataclasses import dataclass

import numba as nb
import numpy as np

from mmslam import arrays

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


def _ant_tensor(r2: np.ndarray, vk: np.ndarray, grid: Grid) -> np.ndarray:
    """``r (Na, K)`` contracted on the delay axis with ``conj(vk (p, K))``: ``(rx, rx, tx, tx, p)``."""
    return (r2 @ vk.conj().T).reshape(grid.shape[:4] + (vk.shape[0],))


def _contract_ant(t: np.ndarray, vs: list[np.ndarray]) -> np.ndarray:
    """A ``(rx, rx, tx, tx, ...)`` tensor contracted with ``conj(vs[d] (p_d, L_d))`` on its four antenna axes:
    ``(..., p3, p2, p1, p0)`` (tensordot appends each new axis)."""
    for d in range(3, -1, -1):
        t = np.tensordot(t, vs[d].conj(), axes=([d], [1]))
    return t


def _self_terms(grid: Grid, w: np.ndarray, w_self: np.ndarray) -> np.ndarray:
    """``(v^(p0)(w) (x) .. (x) v^(p4)(w))^H v(w_self)`` for ``p_d = 0..2``, ``(3, 3, 3, 3, 3)``: per axis
    ``sum_i (-j i)^p exp(j (w_self - w) i)`` (``i`` centred), their outer product (separable)."""
    out = np.ones((1,) * 0)
    for d, (n, o) in enumerate(zip(grid.shape, grid.offsets)):
        i = np.arange(n) - o
        e = np.exp(1j * (w_self[d] - w[d]) * i)
        out = np.multiply.outer(out, np.array([e.sum(), (-1j * i * e).sum(), (-(i * i) * e).sum()]))
    return out


def value_grad_hess(r2: np.ndarray, w: np.ndarray, grid: Grid, g_self: complex = 0j,
                    w_self: np.ndarray | None = None) -> tuple[complex, np.ndarray, np.ndarray]:
    """``c = v(w)^H (r + g_self v(w_self))``, its gradient ``(5,)`` and Hessian ``(5, 5)`` (complex) in ``w``
    (``w_self`` default ``w``: the atom's own term held where it is); ``r2 (Na, K)``. The added atom's
    term is separable, so ``r`` is not touched."""
    vs = atoms(w, grid, 2)
    T = _contract_ant(_ant_tensor(r2, vs[4], grid), vs[:4])  # (p4, p3, p2, p1, p0)
    T = T.transpose(4, 3, 2, 1, 0)
    if g_self != 0:
        T = T + g_self * _self_terms(grid, w, w if w_self is None else w_self)
    c = T[0, 0, 0, 0, 0]
    g = np.empty(5, complex)
    H = np.empty((5, 5), complex)
    for d in range(5):
        idx = [0] * 5
        idx[d] = 1
        g[d] = T[tuple(idx)]
        idx[d] = 2
        H[d, d] = T[tuple(idx)]
        for e in range(d + 1, 5):
            idx = [0] * 5
            idx[d] = idx[e] = 1
            H[d, e] = H[e, d] = T[tuple(idx)]
    return c, g, H


def _ant_atom(vs: list[np.ndarray]) -> np.ndarray:
    """Kronecker product of the four antenna-axis atoms ``(Na,)`` (the 5-D tensor's C order)."""
    out = vs[0]
    for v in vs[1:4]:
        out = np.multiply.outer(out, v)
    return out.reshape(-1)


def coordinate_search(r2: np.ndarray, w: np.ndarray, grid: Grid, sweeps: int = 2, points: int = 17) -> np.ndarray:
    """Per axis in turn, the maximum of ``|v(w)^H r|^2`` over ``points`` values of ``w_d`` within one DFT
    cell either side (the others fixed): brings a grid cell's ``w`` into Newton's basin. ``r2 (Na, K)``."""
    w = np.array(w, float)
    for _ in range(sweeps):
        vs = [a[0] for a in atoms(w, grid, 0)]
        for d in (4, 2, 3, 0, 1):
            if d == 4:
                x = _ant_atom(vs).conj() @ r2
                A = None
            else:
                if A is None:
                    A = (r2 @ vs[4].conj()).reshape(grid.shape[:4])
                t = A
                for e in range(3, -1, -1):
                    if e != d:
                        t = np.tensordot(t, vs[e].conj(), axes=([e], [0]))
                x = t
            L = grid.shape[d]
            cand = w[d] + np.linspace(-2 * np.pi / L, 2 * np.pi / L, points)
            i = np.arange(L) - grid.offsets[d]
            val = np.abs(np.exp(-1j * np.outer(cand, i)) @ x)
            w[d] = cand[int(np.argmax(val))]
            vs[d] = np.exp(1j * w[d] * i)
            if d == 4:
                A = None
    return w


def refine(r2: np.ndarray, w: np.ndarray, grid: Grid, iters: int = 8, tol: float = 0.02, g_self: complex = 0j,
           w_self: np.ndarray | None = None) -> np.ndarray:
    """Newton steps on ``S(w) = |v(w)^H r|^2`` from ``w``, ``r2 (Na, K)``: stops where the Hessian is not
    negative definite, a step lowers ``S`` (that step undone) or every step is below ``tol`` times the
    axis' CRB standard deviation at the current gain ``c / N`` (converged far inside the noise);
    steps limited to half a DFT cell per axis. ``g_self, w_self``: refine on ``r + g_self v(w_self)``."""
    w = np.array(w, float)
    w_self = None if w_self is None else np.asarray(w_self, float)
    half = np.pi / np.asarray(grid.shape, float)
    prev_w, prev_S = None, -1.0
    for _ in range(iters):
        c, g, H = value_grad_hess(r2, w, grid, g_self, w_self)
        S = abs(c) ** 2
        if S < prev_S:
            return prev_w
        step = newton_step(c, g, H)
        if step is None:
            break
        step = np.clip(step, -half, half)
        prev_w, prev_S = w, S
        w = w + step
        if np.all(np.abs(step) * np.sqrt(np.diag(fisher_w(c / grid.size, grid))) < tol):
            break
    return w


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


def newton_step(c: complex, g: np.ndarray, H: np.ndarray) -> np.ndarray | None:
    """Newton step on ``S = |c|^2`` from ``c``, its gradient and Hessian; None where ``S``'s Hessian is not
    negative definite."""
    grad = 2.0 * np.real(np.conj(c) * g)
    hess = 2.0 * np.real(np.conj(g)[:, None] * g[None, :] + np.conj(c) * H)
    try:
        np.linalg.cholesky(-hess)
    except np.linalg.LinAlgError:
        return None
    return -np.linalg.solve(hess, grad)


def _would_move(r2: np.ndarray, w: np.ndarray, g: complex, grid: Grid, frac: float = 0.5) -> bool:
    """Whether path ``(w, g)`` re-fitted on ``r + g v(w)`` moves by more than ``frac`` of its CRB standard
    deviation in some axis (one contraction of the residual; no update of it). Left where it is, its
    residual holds about ``sum (step / std)^2 / 2 <= 5 frac^2`` noise variances, far below the CFAR
    threshold (~17 at the default grid): no spurious detection from it."""
    step = newton_step(*value_grad_hess(r2, w, grid, g))
    if step is None:
        return True
    return bool(np.any(np.abs(step) * np.sqrt(np.diag(fisher_w(g, grid))) > frac))


@nb.njit(cache=True)
def _rank2_update(X: np.ndarray, a1: np.ndarray, b1: np.ndarray, g1: complex, a2: np.ndarray, b2: np.ndarray,
                  g2: complex) -> None:
    """``X -= g1 a1 b1^T + g2 a2 b2^T`` in place (one pass)."""
    for i in range(X.shape[0]):
        c1, c2 = g1 * a1[i], g2 * a2[i]
        for k in range(X.shape[1]):
            X[i, k] -= c1 * b1[k] + c2 * b2[k]


@nb.njit(cache=True)
def _rank1_update_argmax(X: np.ndarray, a: np.ndarray, b: np.ndarray, g: complex) -> tuple[int, float]:
    """``X -= g a b^T`` in place (``X (Na, K)``, ``a (Na,)``, ``b (K,)``); returns the flat index and value of
    ``max |X|^2`` after the update (one pass)."""
    best, jbest = -1.0, 0
    for i in range(X.shape[0]):
        ga = g * a[i]
        for k in range(X.shape[1]):
            x = X[i, k] - ga * b[k]
            X[i, k] = x
            p = x.real * x.real + x.imag * x.imag
            if p > best:
                best, jbest = p, i * X.shape[1] + k
    return jbest, best


def nomp(Y: np.ndarray, grid: Grid, pfa: float, max_paths: int = 20,
         cyclic_passes: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """NOMP (module docstring) on one received tensor.

    Args:
        Y: ``(rx_ant, tx_ant, K)`` or the 5-D tensor; unit noise variance.
        grid: sizes. pfa: false-alarm probability per call on noise only (CFAR design value).
        max_paths: at most this many estimates. cyclic_passes: refinement passes over the earlier
            paths after each detection.

    Returns:
        ``(w (L, 5), g (L,))``: spatial / delay frequencies and complex amplitudes, in detection order.
    """
    import scipy.fft

    Na, K = grid.size // grid.n_subcarriers, grid.n_subcarriers
    r2 = np.array(np.asarray(Y).reshape(Na, K), complex)  # residual
    R2 = scipy.fft.fftn(r2.reshape(grid.shape), workers=1).reshape(Na, K)  # its 5-D DFT
    N = float(grid.size)
    t = cfar_threshold(grid, pfa) * N
    ws, gs = [], []

    def fit(w):  # gain of atom w on the residual, and its antenna / delay factors
        vs = [a[0] for a in atoms(w, grid, 0)]
        va, vk = _ant_atom(vs), vs[4]
        return complex(va.conj() @ (r2 @ vk.conj())) / N, va, vk, vs

    j, pmax = _rank1_update_argmax(R2, np.zeros(Na, complex), np.zeros(K, complex), 0j)
    for _ in range(int(max_paths)):
        if pmax <= t:
            break
        w = coordinate_search(r2, grid_frequency(np.unravel_index(j, grid.shape), grid), grid)
        w = refine(r2, w, grid)
        g, va, vk, vs = fit(w)
        _rank1_update_argmax(r2, va, vk, g)
        j, pmax = _rank1_update_argmax(R2, _ant_atom([np.fft.fft(v) for v in vs]), np.fft.fft(vk), g)
        ws.append(w)
        gs.append(g)
        # cyclic refinement (NOMP): every earlier path re-fitted on the residual plus itself (its own
        # term added in closed form; the residual updated once per moved path, its DFT once per pass)
        for _ in range(int(cyclic_passes)):
            moved = False
            for l in range(len(ws) - 1):
                if not _would_move(r2, ws[l], gs[l], grid):
                    continue
                w_new = refine(r2, ws[l], grid, iters=3, g_self=gs[l], w_self=ws[l])
                vs_old = [a[0] for a in atoms(ws[l], grid, 0)]
                g_new, va, vk, _ = fit(w_new)
                g_new += gs[l] * complex(np.prod([np.vdot(a, b) for a, b in zip(
                    [a[0] for a in atoms(w_new, grid, 0)], vs_old)])) / N
                _rank2_update(r2, va, vk, g_new, _ant_atom(vs_old), vs_old[4], -gs[l])
                ws[l], gs[l] = w_new, g_new
                moved = True
            if moved:
                R2 = scipy.fft.fftn(r2.reshape(grid.shape), workers=1).reshape(Na, K)
                j, pmax = _rank1_update_argmax(R2, np.zeros(Na, complex), np.zeros(K, complex), 0j)
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
