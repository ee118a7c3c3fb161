"""Closed-form path source: the paper's idealised geometry, no Sionna (DESIGN.md sections 1, 4).

For every receiving vehicle ``u`` at one step the source emits one noise-free row per visible
landmark (global frame, metres, radians):

- **BS** (line of sight), always: ``toa = |b - u|``.
- **VA**, one per reflecting face (:func:`mmslam.scenes.landmarks.reflecting_faces`, ground
  included): image source ``v`` = BS mirrored in the face plane; the incidence point ``p`` is the
  intersection of the segment ``v -> u`` with the face plane. The path exists only if the
  receiver is strictly on the BS side of the plane and ``p`` lies inside the face rectangle
  ``[Face.lo, Face.hi]`` (1e-9 m tolerance). ``toa = |v - u|``, AOD = direction ``b -> p``,
  AOA = direction ``u -> v``.
- **SP**: each scatterer's reference point ``s``, only if ``|s - u| <= scn.sensor.fov_range``.
- **VS**: every *other* vehicle's antenna position ``s`` at this step, same range gate.
  SP / VS: ``toa = |b - s| + |s - u|``, AOD = direction ``b -> s``, AOA = direction ``u -> s``.

**Blockage is ignored**: walls, scatterers and car bodies never occlude a path (the paper's
setting, where the FOV is a range gate only). Higher-order reflections and diffraction are not
modelled; no ``OTHER`` rows are produced.

``power_db`` is the free-space (Friis) received power relative to the transmit power with
isotropic unit-gain antennas over the *total* unfolded path length ``L = toa``:
``power_db = -20 log10(4 pi L f_c / c)`` at the scenario's carrier frequency ``f_c``; reflection
and scattering losses are not included. Each row is a single path: ``n_paths = 1``,
``delay_spread_m = 0``; ``bounces`` is 0 for LOS and 1 otherwise; ``diffuse`` is True for SP
rows only. ``bounce_*`` is the incidence point (VA) or the scatter point (SP, VS), NaN for LOS;
``lm_*`` is the ground-truth landmark (BS position, VA image source, SP point, VS antenna).
"""
from __future__ import annotations

import numpy as np

from mmslam.raytrace.schema import PATH_COLUMNS, sort_paths
from mmslam.scenes.landmarks import reflecting_faces
from mmslam.scenes.scenario import Scenario
from mmslam.slam.measurement import BS, SP, VA, VS, direction_angles, mirror_point

SPEED_OF_LIGHT = 299_792_458.0
"""Speed of light in vacuum, m/s."""

_FACE_TOL = 1e-9  # m, tolerance of the incidence-point-in-rectangle test


def free_space_power_db(length_m: np.ndarray, frequency_hz: float) -> np.ndarray:
    """Friis received power (dB re transmit power, isotropic antennas) over ``length_m`` metres."""
    length_m = np.asarray(length_m, dtype=float)
    return -20.0 * np.log10(4.0 * np.pi * length_m * frequency_hz / SPEED_OF_LIGHT)


class AnalyticSource:
    """Closed-form :class:`~mmslam.raytrace.schema.PathSource` (name ``"analytic"``).

    See the module docstring for the model. The landmark geometry (faces, images, scatterers)
    is precomputed once; :meth:`trace_step` is vectorised over receivers and landmarks.
    """

    name = "analytic"

    def __init__(self, scn: Scenario) -> None:
        self.scn = scn
        self.bs = scn.bs_array
        faces = reflecting_faces(scn)
        self.face_ids = [f.id for f in faces]
        if faces:
            self.face_point = np.stack([f.point for f in faces])  # (F, 3)
            self.face_normal = np.stack([f.normal for f in faces])
            self.face_lo = np.stack([f.lo for f in faces])
            self.face_hi = np.stack([f.hi for f in faces])
            self.images = mirror_point(self.bs[None, :], self.face_point, self.face_normal)
        else:
            self.face_point = self.face_normal = self.face_lo = self.face_hi = np.zeros((0, 3))
            self.images = np.zeros((0, 3))
        self.sp_ids = [s.name for s in scn.scatterers]
        self.sp_pos = np.array([s.position for s in scn.scatterers], dtype=float).reshape(-1, 3)
        self.vehicle_names = scn.vehicle_names

    # ------------------------------------------------------------------ protocol
    def settings(self) -> dict:
        """Settings that change the result (the geometry itself is in the scenario hash)."""
        return {"model": "first-order specular + point scatter, no blockage", "model_version": 1}

    def versions(self) -> dict[str, str]:
        """Library versions that produced the rows."""
        return {"numpy": np.__version__}

    def trace_step(self, step: int, states: np.ndarray) -> dict[str, np.ndarray]:
        """Paths of all receivers at one step (see module docstring).

        Args:
            step: time index written to the ``step`` column.
            states: ``(n_vehicles, 7)`` true states; columns 0:3 are antenna positions (m).

        Returns:
            ``paths`` columns (schema dtypes), sorted by (rx, type, landmark_id).
        """
        states = np.asarray(states, dtype=float)
        u = states[:, 0:3]  # (R, 3)
        n_rx = u.shape[0]
        b = self.bs
        n_f, n_s = len(self.face_ids), len(self.sp_ids)

        # ---- candidate landmarks: BS | VA faces | SPs | VSs (other vehicles), per receiver
        types = np.concatenate([[BS], np.full(n_f, VA), np.full(n_s, SP), np.full(n_rx, VS)]).astype(np.int8)
        ids = np.array(["bs", *self.face_ids, *self.sp_ids, *self.vehicle_names[:n_rx]], dtype=object)
        n_l = types.size
        lm = np.empty((n_rx, n_l, 3))
        lm[:, 0] = b
        lm[:, 1:1 + n_f] = self.images
        lm[:, 1 + n_f:1 + n_f + n_s] = self.sp_pos
        lm[:, 1 + n_f + n_s:] = u[None, :, :]
        uu = u[:, None, :]  # (R, 1, 3)

        # ---- VA incidence point and visibility, (R, F)
        if n_f:
            v = self.images[None]  # (1, F, 3)
            nrm = self.face_normal[None]
            d = uu - v  # segment v -> u
            den = np.sum(d * nrm, axis=-1)
            rx_side = np.sum((uu - self.face_point[None]) * nrm, axis=-1)  # > 0: BS side
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.sum((self.face_point[None] - v) * nrm, axis=-1) / np.where(den != 0, den, 1.0)
            p = v + t[..., None] * d
            inside = np.all((p >= self.face_lo[None] - _FACE_TOL) & (p <= self.face_hi[None] + _FACE_TOL),
                            axis=-1)
            va_ok = (rx_side > _FACE_TOL) & (den > 0) & inside
        else:
            p = np.zeros((n_rx, 0, 3))
            va_ok = np.zeros((n_rx, 0), dtype=bool)

        # ---- point scatterers (SP, VS): range gate; a vehicle is no VS of itself
        pts = lm[:, 1 + n_f:]  # (R, S + R, 3)
        rng_ok = np.linalg.norm(pts - uu, axis=-1) <= self.scn.sensor.fov_range
        rng_ok[:, n_s:] &= ~np.eye(n_rx, dtype=bool)

        valid = np.concatenate([np.ones((n_rx, 1), bool), va_ok, rng_ok], axis=1)  # (R, L)

        # ---- bounce points and departure / arrival direction vectors, (R, L, 3)
        bounce = np.full((n_rx, n_l, 3), np.nan)
        bounce[:, 1:1 + n_f] = p
        bounce[:, 1 + n_f:] = pts
        d_dep = np.empty((n_rx, n_l, 3))
        d_arr = np.empty((n_rx, n_l, 3))
        d_dep[:, 0] = u - b
        d_arr[:, 0] = b - u
        d_dep[:, 1:] = bounce[:, 1:] - b
        d_arr[:, 1:1 + n_f] = lm[:, 1:1 + n_f] - uu
        d_arr[:, 1 + n_f:] = pts - uu
        toa = np.empty((n_rx, n_l))
        toa[:, 0] = np.linalg.norm(u - b, axis=-1)
        toa[:, 1:1 + n_f] = np.linalg.norm(lm[:, 1:1 + n_f] - uu, axis=-1)
        toa[:, 1 + n_f:] = np.linalg.norm(pts - b, axis=-1) + np.linalg.norm(pts - uu, axis=-1)
        aod_az, aod_el = direction_angles(d_dep)
        aoa_az, aoa_el = direction_angles(d_arr)

        # ---- flatten the valid (rx, landmark) pairs into rows
        ri, li = np.nonzero(valid)
        n = ri.size
        tp = types[li]
        cols: dict[str, np.ndarray] = {
            "step": np.full(n, step, dtype=np.int32),
            "rx": ri.astype(np.int16),
            "type": tp,
            "landmark_id": ids[li],
            "bounces": np.where(tp == BS, 0, 1).astype(np.int8),
            "diffuse": tp == SP,
            "toa_m": toa[ri, li],
            "aod_az": aod_az[ri, li], "aod_el": aod_el[ri, li],
            "aoa_az": aoa_az[ri, li], "aoa_el": aoa_el[ri, li],
            "power_db": free_space_power_db(toa[ri, li], self.scn.frequency_hz),
            "bounce_x": bounce[ri, li, 0], "bounce_y": bounce[ri, li, 1], "bounce_z": bounce[ri, li, 2],
            "lm_x": lm[ri, li, 0], "lm_y": lm[ri, li, 1], "lm_z": lm[ri, li, 2],
            "n_paths": np.ones(n, dtype=np.int32),
            "delay_spread_m": np.zeros(n),
        }
        cols = {k: np.asarray(cols[k], dtype=object if t == "string" else np.dtype(t))
                for k, t in PATH_COLUMNS.items()}
        return sort_paths(cols)
