"""Vehicle particles of the Rao-Blackwellised particle filter (paper Sec. III-A).

Vehicle states ``s = [x, y, z, alpha, zeta, xi, B]`` (m, m, m, rad, m/s, rad/s, m; global frame),
particles ``(P, 7)`` with log-weights ``(P,)``. Speed ``zeta`` and turn rate ``xi`` are known
inputs (on-board inertial sensor): the caller passes them per step and they overwrite the
particles' values before the coordinated-turn transition.

Every random draw uses the ``numpy.random.Generator`` passed in.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..models.dynamics import VEHICLE_DIM, vehicle_ct, wrap_angle


def init_particles(mean: np.ndarray, std: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` particles from ``N(mean, diag(std^2))``: ``(n, 7)`` (zero-std entries stay fixed)."""
    mean = np.asarray(mean, float)
    std = np.asarray(std, float)
    return mean[None, :] + rng.standard_normal((n, mean.size)) * std[None, :]


def propagate(s: np.ndarray, speed: float, turn_rate: float, dt: float, noise_std: np.ndarray,
              rng: np.random.Generator) -> np.ndarray:
    """Sample ``s' ~ f_V(. | s)``: CT transition with known speed / turn rate plus Gaussian noise.

    Args:
        s: ``(P, 7)`` particles at step k-1.
        speed, turn_rate: the known inputs (m/s, rad/s) over the interval (from step k-1).
        dt: time step (s).
        noise_std: ``(7,)`` process noise std (zero entries draw nothing).

    Returns:
        ``(P, 7)`` particles at step k (heading wrapped to ``(-pi, pi]``; speed and turn rate
        equal to the known inputs).
    """
    std = np.asarray(noise_std, dtype=float)
    if np.ndim(s) != 2 or np.shape(s)[1] != VEHICLE_DIM or std.shape != (VEHICLE_DIM,):
        raise ValueError(f"propagate: particles {np.shape(s)} and noise_std {std.shape}; expected "
                         f"(P, {VEHICLE_DIM}) and ({VEHICLE_DIM},)")
    out = vehicle_ct(s, dt, speed, turn_rate)  # a new array
    _add_noise(out, rng.standard_normal(out.shape), std, float(speed), float(turn_rate))
    out[:, 3] = wrap_angle(out[:, 3])
    return out


@nb.njit(cache=True, error_model="numpy")
def _add_noise(s: np.ndarray, noise: np.ndarray, std: np.ndarray, speed: float, turn_rate: float) -> None:
    """In place on particles ``s (P, 7)``: ``s[p] += noise[p] * std`` (``noise (P, 7)`` standard normal
    draws, ``std (7,)``), then speed and turn rate set to the known inputs."""
    for p in range(s.shape[0]):
        for i in range(s.shape[1]):
            s[p, i] += noise[p, i] * std[i]
        s[p, 4] = speed
        s[p, 5] = turn_rate


def normalise_log_weights(logw: np.ndarray, stage: str = "particle weights") -> tuple[np.ndarray, np.ndarray]:
    """Return ``(log w - logsumexp(log w), w)``; FloatingPointError if all weights vanish / NaN."""
    if np.isnan(logw).any():
        raise FloatingPointError(f"NaN {stage}")
    mx = logw.max()
    if not np.isfinite(mx):
        raise FloatingPointError(f"all {stage} are zero or infinite")
    lw = logw - mx
    lse = np.log(np.exp(lw).sum())
    lw = lw - lse
    return lw, np.exp(lw)


def ess(w: np.ndarray) -> float:
    """Effective sample size ``1 / sum w^2`` of normalised weights ``(P,)``."""
    return float(1.0 / np.sum(w * w))


def systematic_resample(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling: ``(P,)`` ancestor indices for normalised weights ``w (P,)``."""
    n = w.size
    u = (rng.random() + np.arange(n)) / n
    c = np.cumsum(w)
    c[-1] = 1.0
    return np.minimum(np.searchsorted(c, u, side="right"), n - 1)


def weighted_state_mean(s: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Posterior-mean vehicle state ``(7,)``; the heading is a circular (weighted) mean."""
    m = w @ s
    m[3] = np.arctan2(w @ np.sin(s[:, 3]), w @ np.cos(s[:, 3]))
    return m


@nb.njit(cache=True, error_model="numpy")
def _weighted_outer_sum(w: np.ndarray, d: np.ndarray, out: np.ndarray) -> None:
    """``out[a, b] = sum_p w[p] d[p, a] d[p, b]`` (``w (P,)``, ``d (P, n)``), each sum over ``p`` in order."""
    for a in range(d.shape[1]):
        for b in range(d.shape[1]):
            t = 0.0
            for p in range(d.shape[0]):
                t += w[p] * d[p, a] * d[p, b]
            out[a, b] = t


def weighted_state_cov(s: np.ndarray, w: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Weighted particle covariance ``(7, 7)`` around ``mean`` (heading differences wrapped):
    ``sum_p w_p (s_p - mean)(s_p - mean)^T``."""
    if np.shape(w) != (s.shape[0],) or np.shape(mean) != (s.shape[1],):
        raise ValueError(f"weighted_state_cov: weights {np.shape(w)} and mean {np.shape(mean)} do not match "
                         f"the states {s.shape}; pass w (P,) and mean (7,)")
    d = s - mean[None, :]
    d[:, 3] = wrap_angle(d[:, 3])
    out = np.empty((d.shape[1], d.shape[1]))
    _weighted_outer_sum(np.ascontiguousarray(w, dtype=float), d, out)
    return out


def position_nees(err_xy: np.ndarray, cov_xy: np.ndarray) -> float:
    """Normalised estimation error squared of the horizontal position: ``e^T P^-1 e`` (dimensionless, 2 degrees of
    freedom: its mean is 2 for a filter whose covariance matches its error) for the error ``err_xy (2,)`` (m; estimate
    minus truth, global x-y) and the posterior covariance ``cov_xy (2, 2)`` (m^2; the weighted particle covariance,
    :func:`weighted_state_cov`). The height is left out: on flat streets its process noise is 0 and its covariance
    singular. NaN where ``cov_xy`` is not positive definite (a single particle, or every particle at one point)."""
    e = np.asarray(err_xy, float)
    C = np.asarray(cov_xy, float)
    if e.shape != (2,) or C.shape != (2, 2):
        raise ValueError(f"position_nees: error {e.shape} and covariance {C.shape}; expected (2,) and (2, 2)")
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return float("nan")
    y = np.linalg.solve(L, e)
    return float(y @ y)
