"""The model vocabulary shared by the ray tracer, the scenes and the filter (neutral: imports NumPy only).

Landmark types are the integer codes stored in path caches (``paths.type``) and used by the
filter: ``BS=0, VA=1, SP=2, VS=3, OTHER=4``. A path's geometry (:class:`Bounce`) says how its
channel parameters follow from a landmark point: the line of sight (``DIRECT``), a specular
reflection whose landmark is the image source of the BS in the wall (``MIRROR``), or a single
bounce at the landmark point itself (``SCATTER``).

A measurement is ``z = [TOA (m, incl. clock bias), AOD az, AOD el, AOA az (body frame), AOA el]``
(rad): :data:`MEAS_DIM` components, the azimuths (:data:`AZIMUTH_COMPONENTS`) live on the circle.

Global frame: x east, y north, z up, metres; angles in radians.

The vehicle motion model (paper eq. (1), :func:`vehicle_ct`) lives here too: the scenes' true
trajectories and the filter's particles use the same one.
"""
from __future__ import annotations

from enum import IntEnum

import numpy as np


class LandmarkType(IntEnum):
    """Path / landmark type codes (as stored in caches)."""

    BS = 0
    """the line-of-sight path from the base station (a known landmark)"""
    VA = 1
    """virtual anchor: a specular wall bounce, landmark = image source of the BS in the wall"""
    SP = 2
    """static scatter point (a single diffuse bounce on a small object)"""
    VS = 3
    """vehicle scatterer: a single bounce on another (moving) vehicle"""
    OTHER = 4
    """anything else (multi-bounce, diffraction, ...): clutter for the filter"""


BS, VA, SP, VS, OTHER = (int(t) for t in LandmarkType)
TYPE_NAMES: dict[int, str] = {int(t): t.name for t in LandmarkType}
TYPE_CODES: dict[str, int] = {v: k for k, v in TYPE_NAMES.items()}

_LANDMARK_NAMES: list[str] = [t.name for t in LandmarkType if t != LandmarkType.OTHER]
"""The names a ``[filter.types.<TYPE>]`` row may carry: the built-in types, then those registered since
(:func:`mmslam.slam.specs.landmarks.register_landmark_type` adds and removes them here, so the scenario loader,
a lower layer, can refuse a misspelt row)."""


def landmark_type_names() -> tuple[str, ...]:
    """The registered landmark type names (BS, VA, SP, VS, then any added ones)."""
    return tuple(_LANDMARK_NAMES)


def set_landmark_type_name(name: str, present: bool) -> None:
    """Add (``present``) or remove a registered type's name (the registry's bookkeeping; idempotent)."""
    if present and name not in _LANDMARK_NAMES:
        _LANDMARK_NAMES.append(name)
    elif not present and name in _LANDMARK_NAMES:
        _LANDMARK_NAMES.remove(name)


def unknown_type_row(name: str) -> str:
    """The message for a ``[filter.types.<name>]`` row of an unregistered type (one line)."""
    return (f"no landmark type {name!r} is registered; use one of {', '.join(_LANDMARK_NAMES)} (names are "
            "case-sensitive; register a new type before loading a scenario that sets it)")


class Bounce(IntEnum):
    """Geometry of a single-interaction path (how ``h(s, x)`` maps a landmark point to ``z``)."""

    DIRECT = 0
    """line of sight BS -> vehicle (the landmark point is the BS)"""
    MIRROR = 1
    """specular reflection: the landmark point is the image source ``v`` of the BS"""
    SCATTER = 2
    """single bounce at the landmark point ``x`` (BS -> x -> vehicle)"""


MEAS_DIM = 5
"""components of a measurement ``[TOA, AOD az, AOD el, AOA az, AOA el]``"""
ANGLE_COMPONENTS = (1, 2, 3, 4)
AZIMUTH_COMPONENTS = (1, 3)
"""measurement components that are azimuths (wrapped to ``(-pi, pi]``)"""


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles (rad) to ``(-pi, pi]``."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def direction_angles(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth ``atan2(dy, dx)`` and elevation ``asin(dz / |d|)`` (rad) of vectors ``d (..., 3)``."""
    d = np.asarray(d, dtype=float)
    r = np.linalg.norm(d, axis=-1)
    az = np.arctan2(d[..., 1], d[..., 0])
    el = np.arcsin(np.clip(d[..., 2] / np.where(r > 0, r, 1.0), -1.0, 1.0))
    return az, el


def mirror_point(p: np.ndarray, plane_point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror points ``p (..., 3)`` (m) in the plane through ``plane_point (3,)`` with normal ``normal (3,)``."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    d = np.sum((np.asarray(p, float) - plane_point) * n, axis=-1, keepdims=True)
    return p - 2.0 * d * n


def _sinc_terms(w: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(sin(w dt)/w, (1 - cos(w dt))/w)`` with their limits ``(dt, 0)`` as ``w -> 0``.

    Uses second-order series for ``|w dt| < 1e-4`` so the result is smooth and exact to
    double precision around zero.
    """
    w = np.asarray(w, dtype=float)
    wt = w * dt
    small = np.abs(wt) < 1e-4
    if not small.any():  # the usual case (turning): the closed forms only, the same values as below
        return np.sin(wt) / w, (1.0 - np.cos(wt)) / w
    w_safe = np.where(small, 1.0, w)
    a = np.where(small, dt * (1.0 - wt**2 / 6.0), np.sin(wt) / w_safe)
    b = np.where(small, dt * (wt / 2.0 - wt**3 / 24.0), (1.0 - np.cos(wt)) / w_safe)
    return a, b


def vehicle_ct(s: np.ndarray, dt: float, speed: float | None = None, turn_rate: float | None = None) -> np.ndarray:
    """Noise-free polar coordinated-turn transition of vehicle states.

    Args:
        s: ``(..., 7)`` states ``[x, y, z, alpha, zeta, xi, B]`` (global frame).
        dt: time step in seconds.
        speed, turn_rate: known inputs (m/s, rad/s), both or neither: they replace ``zeta`` and ``xi``
            of every state (the turn terms then evaluated once, for the one turn rate).

    Returns:
        ``(..., 7)`` next states: ``x' = x + (zeta/xi)(sin(alpha + xi dt) - sin alpha)``,
        ``y' = y + (zeta/xi)(cos alpha - cos(alpha + xi dt))``, ``alpha' = alpha + xi dt``;
        ``z, zeta, xi, B`` unchanged (noise is added by the caller).
    """
    out = np.array(s, dtype=float)  # a copy: z, zeta, xi, B carried over
    if out.shape[-1:] != (7,):
        raise ValueError(f"vehicle_ct: states of shape {out.shape}; expected (..., 7) [x, y, z, alpha, zeta, xi, B]")
    a = out[..., 3]
    if speed is None and turn_rate is None:
        v, w = out[..., 4], out[..., 5]
    elif speed is None or turn_rate is None:
        raise ValueError("vehicle_ct: pass both speed and turn_rate (the known inputs) or neither")
    else:
        v, w = np.float64(speed), np.float64(turn_rate)
        out[..., 4], out[..., 5] = v, w
    sa, ca = np.sin(a), np.cos(a)
    # (sin(a + w dt) - sin a)/w = ca * sin(w dt)/w - sa * (1 - cos(w dt))/w, likewise for cos.
    s1, c1 = _sinc_terms(w, dt)
    out[..., 0] += v * (ca * s1 - sa * c1)
    out[..., 1] += v * (sa * s1 + ca * c1)
    out[..., 3] = a + w * dt
    return out
