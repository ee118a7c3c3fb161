"""Antenna arrays of the BS and the vehicles: element positions and array responses (pure NumPy).

Both arrays are square uniform planar arrays (URAs) of ``n x n`` isotropic, vertically polarised
elements at half-wavelength spacing, laid out and numbered exactly as Sionna RT's
``PlanarArray(num_rows=n, num_cols=n, vertical_spacing=0.5, horizontal_spacing=0.5)``: in the
array's local y-z plane, element ``e`` at row ``r = e % n`` (top first) and column ``c = e // n``
("column-first from the top-left"), normalised position (wavelengths)
``p_e = (0, (c - (n - 1) / 2) / 2, ((n - 1) / 2 - r) / 2)``.

Mounting (a fixed rotation ``R = R_z(yaw) R_y(pitch)``, Sionna's ``rotation_matrix((yaw, pitch,
0))``, local -> global):

- **vehicle**: horizontal on the roof, its normal up (``pitch = -pi/2``) and its rows along the
  heading (``yaw = heading``): local z -> backwards, local y -> left. It sees every azimuth without
  a front/back ambiguity (a vertical array would mirror every azimuth about its plane) and assumes
  arrivals from the upper half-space (elevation >= 0), where the BS and its images are;
- **BS**: horizontal, its normal down (``pitch = +pi/2``, ``yaw = 0``): every departure to a car
  below the BS is in its lower half-space (elevation <= 0).

Array response (narrowband, Sionna's synthetic-array model: the same delay on every element and a
phase ``2 pi / lambda`` times the element's position along the path's direction):
``a_e(k) = exp(j 2 pi (R p_e) . k)`` with ``k`` the unit vector from the array towards the path
(departure direction at the BS, the direction the wave arrives from at the vehicle) and positions
in wavelengths. In the array's local frame ``u = R^T k``: ``a_e = exp(j 2 pi (p_e,y u_y + p_e,z u_z))``,
a 2-D DFT atom in the spatial frequencies ``(u_y, u_z)`` (``|u| <= 1``; ``u_x = +sqrt(1 - u_y^2 -
u_z^2)`` in the hemisphere the array faces, see :func:`local_to_direction`).
"""
from __future__ import annotations

import math

import numpy as np

VEHICLE_PITCH = -math.pi / 2.0
"""Vehicle array pitch (rad): horizontal, normal up."""
BS_PITCH = math.pi / 2.0
"""BS array pitch (rad): horizontal, normal down."""


def element_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Local ``(y, z)`` positions (wavelengths) of the ``n * n`` elements, ``((n*n,), (n*n,))``, Sionna's order."""
    e = np.arange(int(n) * int(n))
    r, c = e % n, e // n
    return 0.5 * (c - (n - 1) / 2.0), 0.5 * ((n - 1) / 2.0 - r)


def rotation(yaw: np.ndarray | float, pitch: float) -> np.ndarray:
    """``R = R_z(yaw) R_y(pitch)``, ``(..., 3, 3)`` (Sionna's ``rotation_matrix((yaw, pitch, 0))``)."""
    yaw = np.asarray(yaw, float)
    ca, sa = np.cos(yaw), np.sin(yaw)
    cb, sb = math.cos(pitch), math.sin(pitch)
    R = np.empty(yaw.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = ca * cb, -sa, ca * sb
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sa * cb, ca, sa * sb
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sb, 0.0, cb
    return R


def element_positions(n: int, yaw: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    """Rotated element positions ``R p_e`` (wavelengths), ``(n*n, 3)``."""
    y, z = element_grid(n)
    p = np.stack([np.zeros_like(y), y, z], axis=-1)
    return p @ rotation(yaw, pitch).T


def unit_vector(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """``(cos el cos az, cos el sin az, sin el)``, ``(..., 3)``."""
    az, el = np.asarray(az, float), np.asarray(el, float)
    ce = np.cos(el)
    return np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=-1)


def direction_to_local(az: np.ndarray, el: np.ndarray, yaw: np.ndarray | float, pitch: float) -> np.ndarray:
    """Local spatial frequencies ``(u_y, u_z)`` of directions (global az, el), ``(..., 2)``; ``yaw`` broadcasts."""
    u = np.einsum("...ji,...j->...i", rotation(yaw, pitch), unit_vector(az, el))
    return u[..., 1:3]


def local_to_direction(u: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation (rad) in the mount's yaw-free frame of local frequencies ``u (..., 2)``.

    The local normal component is ``u_x = +sqrt(max(0, 1 - u_y^2 - u_z^2))`` (the hemisphere the
    array faces, its local +x normal); the direction is ``R_y(pitch) u``. Add the yaw to the azimuth to
    get the global azimuth.
    """
    u = np.asarray(u, float)
    uy, uz = u[..., 0], u[..., 1]
    ux = np.sqrt(np.maximum(0.0, 1.0 - uy * uy - uz * uz))
    cb, sb = math.cos(pitch), math.sin(pitch)
    gx, gy, gz = cb * ux + sb * uz, uy, -sb * ux + cb * uz
    return np.arctan2(gy, gx), np.arcsin(np.clip(gz, -1.0, 1.0))


def response(n: int, u: np.ndarray) -> np.ndarray:
    """Array response ``exp(j 2 pi (y_e u_y + z_e u_z))`` of local frequencies ``u (..., 2)``, ``(..., n*n)``."""
    y, z = element_grid(n)
    u = np.asarray(u, float)
    return np.exp(2j * np.pi * (u[..., 0:1] * y + u[..., 1:2] * z))
