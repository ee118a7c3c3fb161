"""Motion models (DESIGN.md section 3). Pure NumPy, broadcasting over leading axes.

Global frame: x east, y north, z up, metres; angles in radians; time in seconds.

Vehicle state ``s = [x, y, z, alpha, zeta, xi, B]`` (position m, heading rad, speed m/s,
turn rate rad/s, clock bias m): polar coordinated turn, :func:`vehicle_ct`.

VS (vehicle scatterer) state ``t = [x, y, z, vx, vy, vz, xi]``: Cartesian coordinated turn with
unknown turn rate (Li & Jilkov 2003, sec. V-B), :func:`vs_ct` and its Jacobian :func:`vs_ct_jacobian`.
"""
from __future__ import annotations

import numpy as np

from mmslam.model import wrap_angle  # noqa: F401  (re-exported: the filter's angle convention)

# Below this |xi * dt| the turn-rate formulas switch to their series expansion (no 0/0).
_SMALL = 1e-9

VEHICLE_DIM = 7
VS_DIM = 7


def _sinc_terms(w: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(sin(w dt)/w, (1 - cos(w dt))/w)`` with their limits ``(dt, 0)`` as ``w -> 0``.

    Uses second-order series for ``|w dt| < 1e-4`` so the result is smooth and exact to
    double precision around zero.
    """
    w = np.asarray(w, dtype=float)
    wt = w * dt
    small = np.abs(wt) < 1e-4
    w_safe = np.where(small, 1.0, w)
    a = np.where(small, dt * (1.0 - wt**2 / 6.0), np.sin(wt) / w_safe)
    b = np.where(small, dt * (wt / 2.0 - wt**3 / 24.0), (1.0 - np.cos(wt)) / w_safe)
    return a, b


def vehicle_ct(s: np.ndarray, dt: float) -> np.ndarray:
    """Noise-free polar coordinated-turn transition of vehicle states.

    Args:
        s: ``(..., 7)`` states ``[x, y, z, alpha, zeta, xi, B]`` (global frame).
        dt: time step in seconds.

    Returns:
        ``(..., 7)`` next states: ``x' = x + (zeta/xi)(sin(alpha + xi dt) - sin alpha)``,
        ``y' = y + (zeta/xi)(cos alpha - cos(alpha + xi dt))``, ``alpha' = alpha + xi dt``;
        ``z, zeta, xi, B`` unchanged (noise is added by the caller).
    """
    s = np.asarray(s, dtype=float)
    x, y, z, a, v, w, b = np.moveaxis(s, -1, 0)
    sa, ca = np.sin(a), np.cos(a)
    # (sin(a + w dt) - sin a)/w = ca * sin(w dt)/w - sa * (1 - cos(w dt))/w, likewise for cos.
    s1, c1 = _sinc_terms(w, dt)
    out = np.empty_like(s)
    out[..., 0] = x + v * (ca * s1 - sa * c1)
    out[..., 1] = y + v * (sa * s1 + ca * c1)
    out[..., 2] = z
    out[..., 3] = a + w * dt
    out[..., 4] = v
    out[..., 5] = w
    out[..., 6] = b
    return out


def vs_ct(t: np.ndarray, dt: float) -> np.ndarray:
    """Cartesian coordinated-turn transition of VS states ``[x, y, z, vx, vy, vz, xi]``.

    ``x' = x + (sin(xi T)/xi) vx - ((1 - cos(xi T))/xi) vy`` etc. (DESIGN.md section 3);
    equals constant velocity as ``xi -> 0``. Shape ``(..., 7)`` in and out.
    """
    t = np.asarray(t, dtype=float)
    x, y, z, vx, vy, vz, w = np.moveaxis(t, -1, 0)
    s1, c1 = _sinc_terms(w, dt)
    cw, sw = np.cos(w * dt), np.sin(w * dt)
    out = np.empty_like(t)
    out[..., 0] = x + s1 * vx - c1 * vy
    out[..., 1] = y + c1 * vx + s1 * vy
    out[..., 2] = z + dt * vz
    out[..., 3] = cw * vx - sw * vy
    out[..., 4] = sw * vx + cw * vy
    out[..., 5] = vz
    out[..., 6] = w
    return out


def vs_ct_jacobian(t: np.ndarray, dt: float) -> np.ndarray:
    """Jacobian ``d vs_ct(t) / d t``, shape ``(..., 7, 7)``; exact, including ``xi -> 0``."""
    t = np.asarray(t, dtype=float)
    vx, vy, w = t[..., 3], t[..., 4], t[..., 6]
    s1, c1 = _sinc_terms(w, dt)
    wt = w * dt
    cw, sw = np.cos(wt), np.sin(wt)
    small = np.abs(wt) < 1e-4
    w_safe = np.where(small, 1.0, w)
    # d/dw of sin(w dt)/w and (1 - cos(w dt))/w
    ds1 = np.where(small, -dt**3 * w / 3.0, (dt * cw * w - sw) / w_safe**2)
    dc1 = np.where(small, dt**2 / 2.0 - dt**4 * w**2 / 8.0, (dt * sw * w - (1.0 - cw)) / w_safe**2)
    J = np.zeros(t.shape[:-1] + (7, 7))
    J[..., 0, 0] = 1.0
    J[..., 0, 3] = s1
    J[..., 0, 4] = -c1
    J[..., 0, 6] = ds1 * vx - dc1 * vy
    J[..., 1, 1] = 1.0
    J[..., 1, 3] = c1
    J[..., 1, 4] = s1
    J[..., 1, 6] = dc1 * vx + ds1 * vy
    J[..., 2, 2] = 1.0
    J[..., 2, 5] = dt
    J[..., 3, 3] = cw
    J[..., 3, 4] = -sw
    J[..., 3, 6] = -dt * (sw * vx + cw * vy)
    J[..., 4, 3] = sw
    J[..., 4, 4] = cw
    J[..., 4, 6] = dt * (cw * vx - sw * vy)
    J[..., 5, 5] = 1.0
    J[..., 6, 6] = 1.0
    return J
