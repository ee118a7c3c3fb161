"""Geometric measurement model (docs/architecture.md, paper eq. (3)): per-point kernels and a NumPy API.

A measurement is ``z = [TOA, AOD az, AOD el, AOA az, AOA el]``: TOA in metres (delay x c) plus
the clock bias ``B`` (m); AOD at the BS and AOA at the vehicle in radians. The *global* channel
parameters (:func:`channel_params`) have AOA azimuth in the global frame; the *body-frame*
measurement (:func:`to_body`) subtracts the vehicle heading from it and wraps to ``(-pi, pi]``.

Every function here takes a path *geometry* (:class:`mmslam.model.Bounce`: DIRECT, MIRROR,
SCATTER), never a landmark type: the caller knows its type's geometry (a VA is a MIRROR, an SP or a
VS a SCATTER point; :attr:`mmslam.slam.specs.landmarks.LandmarkSpec.geometry`). The model is written
once, for one landmark point and one vehicle (:func:`channel_point`, :func:`measure_point`, numba
``njit``), and the NumPy API (:func:`channel_params`, :func:`measure`) loops over it.
:class:`LandmarkKind` is what the building blocks of the layers above are handed about a type.
"""
from __future__ import annotations

import math
from typing import Protocol

import numba as nb
import numpy as np

from mmslam.model import (ANGLE_COMPONENTS, AZIMUTH_COMPONENTS, BS, MEAS_DIM, OTHER, SP, TYPE_CODES,  # noqa: F401
                          TYPE_NAMES, VA, VS, direction_angles, mirror_point, wrap_angle)
from mmslam.model import Bounce

from ..core.trig import atan2

_DIRECT, _MIRROR = int(Bounce.DIRECT), int(Bounce.MIRROR)
_TWO_PI = 2.0 * math.pi


class LandmarkKind(Protocol):
    """What a building block needs to know of a landmark type, handed over by its caller (a
    :class:`~mmslam.slam.specs.landmarks.LandmarkSpec` is one): its ``name`` (messages), ``code``
    (the value passed to a ``pd_fn``), path ``geometry`` (:class:`mmslam.model.Bounce`), map
    ``state_dim`` (3, or 7 for a VS) and whether it is ``range_gated`` (``sensor.fov_range``)."""

    name: str
    code: int
    geometry: int
    state_dim: int
    range_gated: bool


def check_geometry(geometry: int) -> int:
    """``geometry`` as an int :class:`~mmslam.model.Bounce` code; ValueError if it is none."""
    try:
        return int(Bounce(int(geometry)))
    except (TypeError, ValueError):
        raise ValueError(f"geometry {geometry!r} is not a path geometry; use one of "
                         f"{', '.join(f'{b.name}={int(b)}' for b in Bounce)} (mmslam.model.Bounce)") from None


@nb.njit(cache=True, error_model="numpy")
def wrap(a: float) -> float:
    """Angle ``a`` (rad) wrapped to ``(-pi, pi]`` (the scalar twin of :func:`mmslam.model.wrap_angle`)."""
    if -math.pi < a <= math.pi:  # the usual case: no floating-point modulo
        return a
    w = (a + math.pi) % _TWO_PI - math.pi
    return math.pi if w == -math.pi else w


@nb.njit(cache=True, error_model="numpy")
def path_vectors(geometry: int, u: np.ndarray, x: np.ndarray, b: np.ndarray
                 ) -> tuple[float, float, float, float, float, float, float]:
    """Path length and end directions of one path, the geometry of paper eq. (3).

    Args:
        geometry: :class:`~mmslam.model.Bounce` code: DIRECT (line of sight, ``x`` ignored),
            MIRROR (``x`` = image source ``v`` of the BS in the wall) or SCATTER (``x`` = bounce point).
        u: ``(>= 3,)`` vehicle antenna position (first three entries read); x: ``(3,)`` landmark
            point; b: ``(3,)`` BS position (global frame, m). Arrays or tuples of floats.

    Returns:
        ``(toa, dep_x, dep_y, dep_z, arr_x, arr_y, arr_z)``: the TOA (path length, m), the
        departure direction at the BS and the arrival direction at the vehicle (vectors pointing
        along the path's first and against its last leg, global frame, not normalised).
        DIRECT: ``|u - b|``, ``u - b``, ``b - u``. MIRROR: ``|u - v|``; the arrival direction is
        ``v - u``, the departure direction points at the incidence point on the wall, i.e. ``u - v``
        reflected in the wall plane (the perpendicular bisector of ``b`` and ``v``). SCATTER:
        ``|x - b| + |x - u|``, ``x - b``, ``x - u``.
    """
    if geometry == _DIRECT:
        dep0, dep1, dep2 = u[0] - b[0], u[1] - b[1], u[2] - b[2]
        arr0, arr1, arr2 = -dep0, -dep1, -dep2
        toa = math.sqrt(dep0 * dep0 + dep1 * dep1 + dep2 * dep2)
    elif geometry == _MIRROR:
        arr0, arr1, arr2 = x[0] - u[0], x[1] - u[1], x[2] - u[2]  # v - u
        n0, n1, n2 = x[0] - b[0], x[1] - b[1], x[2] - b[2]  # wall normal ~ v - b
        nn = n0 * n0 + n1 * n1 + n2 * n2
        proj = -(arr0 * n0 + arr1 * n1 + arr2 * n2) / (nn if nn > 0.0 else 1.0)  # (u - v) . n / |n|^2
        dep0, dep1, dep2 = -arr0 - 2.0 * proj * n0, -arr1 - 2.0 * proj * n1, -arr2 - 2.0 * proj * n2
        toa = math.sqrt(arr0 * arr0 + arr1 * arr1 + arr2 * arr2)  # a mirror keeps the length
    else:
        dep0, dep1, dep2 = x[0] - b[0], x[1] - b[1], x[2] - b[2]
        arr0, arr1, arr2 = x[0] - u[0], x[1] - u[1], x[2] - u[2]
        toa = math.sqrt(dep0 * dep0 + dep1 * dep1 + dep2 * dep2) + math.sqrt(arr0 * arr0 + arr1 * arr1 + arr2 * arr2)
    return toa, dep0, dep1, dep2, arr0, arr1, arr2


@nb.njit(cache=True, error_model="numpy")
def angle_arguments(dx: float, dy: float, dz: float) -> tuple[float, float, float, float]:
    """``(y, x)`` arguments of :func:`~mmslam.slam.core.trig.atan2` for the azimuth and the elevation of a
    direction ``d``: azimuth ``atan2(dy, dx)``, elevation ``asin(dz / |d|) = atan2(dz, |(dx, dy)|)``
    (0 for ``d = 0``). Returns ``(dy, dx, dz, |(dx, dy)|)``."""
    return dy, dx, dz, math.sqrt(dx * dx + dy * dy)


@nb.njit(cache=True, error_model="numpy")
def channel_point(geometry: int, u: np.ndarray, x: np.ndarray, b: np.ndarray
                  ) -> tuple[float, float, float, float, float]:
    """Noise-free global channel parameters of one path, paper eq. (3) without noise and clock bias.

    ``geometry``, ``u``, ``x``, ``b``: as :func:`path_vectors`. Returns ``(toa (m), aod az,
    aod el, aoa az (global frame), aoa el)`` (rad): the angles of :func:`path_vectors`' directions
    (:func:`angle_arguments`).
    """
    toa, dep0, dep1, dep2, arr0, arr1, arr2 = path_vectors(geometry, u, x, b)
    ya, xa, ye, xe = angle_arguments(dep0, dep1, dep2)
    yb, xb, yf, xf = angle_arguments(arr0, arr1, arr2)
    return toa, atan2(ya, xa), atan2(ye, xe), atan2(yb, xb), atan2(yf, xf)


@nb.njit(cache=True, error_model="numpy")
def body_frame(s: np.ndarray, toa: float, aod_az: float, aod_el: float, aoa_az: float, aoa_el: float
               ) -> tuple[float, float, float, float, float]:
    """The measurement of global channel parameters seen from vehicle state ``s (>= 7,)`` (paper
    eq. (3)): ``(toa + B (m), aod az, aod el, aoa az - heading (wrapped to (-pi, pi]), aoa el)``."""
    return toa + s[6], aod_az, aod_el, wrap(aoa_az - s[3]), aoa_el


@nb.njit(cache=True, error_model="numpy")
def measure_point(geometry: int, s: np.ndarray, x: np.ndarray, b: np.ndarray
                  ) -> tuple[float, float, float, float, float]:
    """Noise-free measurement ``h(s, x)`` of one landmark point seen from one vehicle, paper eq. (3).

    ``s (>= 7,)``: vehicle state ``[x, y, z (m), heading (rad), v (m/s), turn rate (rad/s), clock
    bias B (m)]``; ``x``, ``b``, ``geometry``: as :func:`path_vectors`. Returns
    ``(TOA + B (m), AOD az, AOD el, AOA az - heading (body frame, wrapped to (-pi, pi]), AOA el)``.
    """
    toa, aod_az, aod_el, aoa_az, aoa_el = channel_point(geometry, s, x, b)
    return body_frame(s, toa, aod_az, aod_el, aoa_az, aoa_el)


@nb.njit(cache=True, error_model="numpy")
def _channel_loop(geometry: int, u: np.ndarray, x: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    for n in range(u.shape[0]):
        out[n, 0], out[n, 1], out[n, 2], out[n, 3], out[n, 4] = channel_point(geometry, u[n], x[n], b[n])


@nb.njit(cache=True, error_model="numpy")
def _measure_loop(geometry: int, s: np.ndarray, x: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    for n in range(s.shape[0]):
        out[n, 0], out[n, 1], out[n, 2], out[n, 3], out[n, 4] = measure_point(geometry, s[n], x[n], b[n])


def _broadcast(loop, v: np.ndarray, lm: np.ndarray | None, geometry: int, bs: np.ndarray) -> np.ndarray:
    """Run ``loop`` (:func:`_channel_loop` / :func:`_measure_loop`) over broadcast vehicle rows
    ``v (..., k)``, landmark points ``lm (..., 3)`` (the BS for DIRECT) and BS positions: ``(..., 5)``."""
    geo = check_geometry(geometry)
    v = np.asarray(v, dtype=float)
    b = np.asarray(bs, dtype=float)
    need = 7 if loop is _measure_loop else 3
    if v.ndim == 0 or v.shape[-1] < need:
        raise ValueError(f"vehicle array of shape {v.shape}: expected (..., {need}) "
                         f"({'states [x, y, z, heading, speed, turn rate, bias]' if need == 7 else 'positions'})")
    if lm is None and geo != _DIRECT:
        raise ValueError(f"geometry {Bounce(geo).name}: landmark positions (..., 3) are required (only the BS, "
                         "DIRECT, has none)")
    if b.shape[-1:] != (3,) or (lm is not None and np.shape(lm)[-1:] != (3,)):
        raise ValueError(f"BS {b.shape} / landmark {np.shape(lm)} arrays: expected (..., 3) positions")
    x = b if geo == _DIRECT or lm is None else np.asarray(lm, dtype=float)
    shape = np.broadcast_shapes(v.shape[:-1], x.shape[:-1], b.shape[:-1])
    out = np.empty(shape + (5,))

    def flat(a: np.ndarray, k: int) -> np.ndarray:
        return np.ascontiguousarray(np.broadcast_to(a, shape + (k,))).reshape(-1, k)

    loop(geo, flat(v, v.shape[-1]), flat(x, 3), flat(b, 3), out.reshape(-1, 5))
    return out


def channel_params(u: np.ndarray, lm: np.ndarray, geometry: int, bs: np.ndarray) -> np.ndarray:
    """Noise-free global channel parameters ``[toa, aod_az, aod_el, aoa_az, aoa_el]`` (m, rad).

    Broadcasts :func:`channel_point` (paper eq. (3)) over the leading axes.

    Args:
        u: vehicle antenna positions ``(..., 3)``, global frame, m.
        lm: landmark positions ``(..., 3)`` (BS: ignored, may be None; VA: image source; SP/VS:
            scatter point).
        geometry: the path geometry (:class:`mmslam.model.Bounce`: DIRECT for the BS, MIRROR for a VA,
            SCATTER for an SP or a VS).
        bs: BS position ``(3,)`` or ``(..., 3)``.

    Returns:
        ``(..., 5)`` with TOA without clock bias and AOA azimuth in the global frame.
    """
    return _broadcast(_channel_loop, u, lm, geometry, bs)


def to_body(g: np.ndarray, heading: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """Global channel parameters ``(..., 5)`` -> measurement: TOA + B, AOA az - heading (wrapped)."""
    z = np.array(g, dtype=float, copy=True)
    z[..., 0] = z[..., 0] + bias
    z[..., 3] = wrap_angle(z[..., 3] - heading)
    return z


def measure(state: np.ndarray, lm: np.ndarray, geometry: int, bs: np.ndarray) -> np.ndarray:
    """Noise-free measurement ``h(s, x, m)`` for vehicle states ``(..., 7)`` and a path ``geometry``
    (:class:`mmslam.model.Bounce`): :func:`measure_point` broadcast."""
    return _broadcast(_measure_loop, state, lm, geometry, bs)


def residual(z: np.ndarray, zhat: np.ndarray) -> np.ndarray:
    """``z - zhat`` with azimuth components (1 and 3) wrapped to ``(-pi, pi]``."""
    r = np.asarray(z, dtype=float) - np.asarray(zhat, dtype=float)
    r[..., 1] = wrap_angle(r[..., 1])
    r[..., 3] = wrap_angle(r[..., 3])
    return r
