"""Motion models (docs/design.md section 3), broadcasting over leading axes.

Global frame: x east, y north, z up, metres; angles in radians; time in seconds.

Vehicle state ``s = [x, y, z, alpha, zeta, xi, B]`` (position m, heading rad, speed m/s,
turn rate rad/s, clock bias m): polar coordinated turn, :func:`mmslam.model.vehicle_ct` (in the
neutral model module: the scenes' true trajectories use it too).

VS (vehicle scatterer) state ``t = [x, y, z, vx, vy, vz, xi]``: Cartesian coordinated turn with
unknown turn rate (Li & Jilkov 2003, sec. V-B), :func:`vs_ct` and its Jacobian :func:`vs_ct_jacobian`.

Static landmarks (VA, SP) keep their place: :func:`predict_static`, paper eq. (4) without its births.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from mmslam.model import vehicle_ct, wrap_angle  # noqa: F401  (re-exported: the vehicle model, the angle convention)

from ..core.gm import GM

VEHICLE_DIM = 7
VS_DIM = 7


@nb.njit(cache=True, error_model="numpy", inline="always")
def vs_ct_point(t: np.ndarray, dt: float, out: np.ndarray, F: np.ndarray) -> None:
    """Cartesian coordinated turn of one VS state and its Jacobian, paper eq. (2) without noise.

    ``t = [x, y, z, vx, vy, vz, xi]`` (m, m/s, rad/s): ``x' = x + (sin(xi T)/xi) vx - ((1 - cos(xi
    T))/xi) vy``, ``y' = y + ((1 - cos(xi T))/xi) vx + (sin(xi T)/xi) vy``, ``z' = z + T vz``,
    ``[vx', vy'] = R(xi T) [vx, vy]``, ``vz, xi`` unchanged; constant velocity as ``xi -> 0``
    (series below ``|xi T| < 1e-4``). Writes ``out (7,)`` and ``F = d t' / d t (7, 7)``.
    """
    vx, vy, w = t[3], t[4], t[6]
    wt = w * dt
    cw, sw = math.cos(wt), math.sin(wt)
    if abs(wt) < 1e-4:
        s1 = dt * (1.0 - wt * wt / 6.0)
        c1 = dt * (wt / 2.0 - wt * wt * wt / 24.0)
        ds1 = -dt * dt * dt * w / 3.0  # d/dw of sin(w T)/w and (1 - cos(w T))/w
        dc1 = dt * dt / 2.0 - dt * dt * dt * dt * w * w / 8.0
    else:
        s1, c1 = sw / w, (1.0 - cw) / w
        ds1 = (dt * cw * w - sw) / (w * w)
        dc1 = (dt * sw * w - (1.0 - cw)) / (w * w)
    out[0] = t[0] + s1 * vx - c1 * vy
    out[1] = t[1] + c1 * vx + s1 * vy
    out[2] = t[2] + dt * t[5]
    out[3] = cw * vx - sw * vy
    out[4] = sw * vx + cw * vy
    out[5] = t[5]
    out[6] = w
    for i in range(7):
        for k in range(7):
            F[i, k] = (1.0 if i == k else 0.0)
    F[0, 3], F[0, 4], F[0, 6] = s1, -c1, ds1 * vx - dc1 * vy
    F[1, 3], F[1, 4], F[1, 6] = c1, s1, dc1 * vx + ds1 * vy
    F[2, 5] = dt
    F[3, 3], F[3, 4], F[3, 6] = cw, -sw, -dt * (sw * vx + cw * vy)
    F[4, 3], F[4, 4], F[4, 6] = sw, cw, dt * (cw * vx - sw * vy)


@nb.njit(cache=True, error_model="numpy")
def _vs_ct_loop(t: np.ndarray, dt: float, out: np.ndarray, F: np.ndarray) -> None:
    for n in range(t.shape[0]):
        vs_ct_point(t[n], dt, out[n], F[n])


def _vs_ct_both(t: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=float)
    flat = np.ascontiguousarray(t.reshape(-1, VS_DIM))
    out, F = np.empty_like(flat), np.empty((flat.shape[0], VS_DIM, VS_DIM))
    _vs_ct_loop(flat, float(dt), out, F)
    return out.reshape(t.shape), F.reshape(t.shape[:-1] + (VS_DIM, VS_DIM))


def vs_ct(t: np.ndarray, dt: float) -> np.ndarray:
    """Cartesian coordinated-turn transition of VS states ``[x, y, z, vx, vy, vz, xi]`` (:func:`vs_ct_point`).

    Shape ``(..., 7)`` in and out; equals constant velocity as ``xi -> 0``.
    """
    return _vs_ct_both(t, dt)[0]


def vs_ct_jacobian(t: np.ndarray, dt: float) -> np.ndarray:
    """Jacobian ``d vs_ct(t) / d t``, shape ``(..., 7, 7)``; exact, including ``xi -> 0`` (:func:`vs_ct_point`)."""
    return _vs_ct_both(t, dt)[1]


def predict_static(g: GM, p_survival: float) -> GM:
    """Static landmark prediction, paper eq. (4) without its births (identity dynamics): the map ``g`` (any batch
    shape) with its weights times ``p_survival``; a Beta detection history ``pd_beta`` and the labels are kept as
    they are."""
    return GM(g.w * p_survival, g.m, g.P, g.mask, g.pd_beta, g.label)
