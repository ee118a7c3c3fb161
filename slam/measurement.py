"""Geometric measurement model (DESIGN.md section 4). Pure NumPy, broadcasting over leading axes.

A measurement is ``z = [TOA, AOD az, AOD el, AOA az, AOA el]``: TOA in metres (delay x c) plus
the clock bias ``B`` (m); AOD at the BS and AOA at the vehicle in radians. The *global* channel
parameters (:func:`channel_params`) have AOA azimuth in the global frame; the *body-frame*
measurement (:func:`to_body`) subtracts the vehicle heading from it and wraps to ``(-pi, pi]``.

Landmark types (integer codes used in caches and the filter): ``BS=0, VA=1, SP=2, VS=3, OTHER=4``.
"""
from __future__ import annotations

import numpy as np

from mmslam.model import (ANGLE_COMPONENTS, AZIMUTH_COMPONENTS, BS, MEAS_DIM, OTHER, SP, TYPE_CODES,  # noqa: F401
                          TYPE_NAMES, VA, VS, direction_angles, mirror_point, wrap_angle)


def channel_params(u: np.ndarray, lm: np.ndarray, lm_type: int, bs: np.ndarray) -> np.ndarray:
    """Noise-free global channel parameters ``[toa, aod_az, aod_el, aoa_az, aoa_el]`` (m, rad).

    Args:
        u: vehicle antenna positions ``(..., 3)``, global frame, m.
        lm: landmark positions ``(..., 3)`` (BS: ignored; VA: image source; SP/VS: scatter point).
        lm_type: one of ``BS, VA, SP, VS``.
        bs: BS position ``(3,)`` or ``(..., 3)``.

    Returns:
        ``(..., 5)`` with TOA without clock bias and AOA azimuth in the global frame.
        VA: the AOD points at the incidence point on the wall, i.e. the direction ``u - v``
        reflected in the wall plane (the perpendicular bisector of ``b`` and ``v``).
    """
    u = np.asarray(u, dtype=float)
    b = np.asarray(bs, dtype=float)
    if lm_type == BS:
        d_dep = u - b
        toa = np.linalg.norm(d_dep, axis=-1)
        d_arr = b - u
    elif lm_type == VA:
        v = np.asarray(lm, dtype=float)
        d_vu = u - v
        toa = np.linalg.norm(d_vu, axis=-1)
        n = v - b
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        d_dep = d_vu - 2.0 * np.sum(d_vu * n, axis=-1, keepdims=True) * n
        d_arr = v - u
    elif lm_type in (SP, VS):
        s = np.asarray(lm, dtype=float)
        d_dep = s - b
        d_arr = s - u
        toa = np.linalg.norm(d_dep, axis=-1) + np.linalg.norm(d_arr, axis=-1)
    else:
        raise ValueError(f"unknown landmark type {lm_type!r}")
    aod_az, aod_el = direction_angles(d_dep)
    aoa_az, aoa_el = direction_angles(d_arr)
    toa, aod_az = np.broadcast_arrays(toa, aod_az)
    return np.stack([toa, aod_az, aod_el, aoa_az, aoa_el], axis=-1)


def to_body(g: np.ndarray, heading: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """Global channel parameters ``(..., 5)`` -> measurement: TOA + B, AOA az - heading (wrapped)."""
    z = np.array(g, dtype=float, copy=True)
    z[..., 0] = z[..., 0] + bias
    z[..., 3] = wrap_angle(z[..., 3] - heading)
    return z


def measure(state: np.ndarray, lm: np.ndarray, lm_type: int, bs: np.ndarray) -> np.ndarray:
    """Noise-free measurement ``h(s, x, m)`` for vehicle states ``(..., 7)`` (DESIGN.md sec. 3)."""
    state = np.asarray(state, dtype=float)
    g = channel_params(state[..., 0:3], lm, lm_type, bs)
    return to_body(g, state[..., 3], state[..., 6])


def residual(z: np.ndarray, zhat: np.ndarray) -> np.ndarray:
    """``z - zhat`` with azimuth components (1 and 3) wrapped to ``(-pi, pi]``."""
    r = np.asarray(z, dtype=float) - np.asarray(zhat, dtype=float)
    r[..., 1] = wrap_angle(r[..., 1])
    r[..., 3] = wrap_angle(r[..., 3])
    return r
