"""Closed-form path source: the paper's idealised geometry, no Sionna (docs/design.md sections 1, 4).

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

**Gains** (complex path coefficient ``a`` in Sionna's ``Paths.a`` convention: unit-gain isotropic
antennas, the carrier phase ``exp(-j 2 pi f_c delay)`` not included; ``power_db = 20 log10|a|``),
with ``lambda = c / f_c`` and the unfolded path length ``L``:

- BS (LOS): Friis, ``a = lambda / (4 pi L)``.
- VA: ``a = Gamma lambda / (4 pi L)`` with ``Gamma`` the Fresnel reflection coefficient of a
  smooth half-space of the face's material (ITU-R P.2040 relative permittivity
  ``eta = a f^b - j c f^d / (2 pi f eps0)``, f in GHz, :data:`ITU_MATERIALS`) at the incidence
  angle: TE (electric field parallel to the face, what a vertically polarised antenna sees on a
  vertical wall) on vertical faces, TM on horizontal faces (ground, roofs).
- SP / VS: a point scatterer with radar cross-section ``rcs_m2`` (setting, default 1 m^2),
  bistatic radar equation ``a = sqrt(rcs) lambda / ((4 pi)^(3/2) d_1 d_2)`` (``d_1`` BS to
  scatterer, ``d_2`` scatterer to receiver), real and positive.

**Doppler** ``f_D = -(1 / lambda) dL/dt`` with the receiver moving at its velocity
``speed (cos heading, sin heading, 0)`` and, for a VS, the scattering vehicle moving at its own;
BS, VAs and SPs are static. For LOS ``f_D = v_rx . (b - u) / (|b - u| lambda)``.

Each row is a single path: ``n_paths = 1``, ``delay_spread_m = 0``; ``bounces`` is 0 for LOS and
1 otherwise; ``diffuse`` is True for SP rows only (the ``rays`` table's interaction type: VA
specular, SP diffuse, VS specular). ``bounce_*`` is the incidence point (VA) or the scatter
point (SP, VS), NaN for LOS; ``lm_*`` is the ground-truth landmark (BS position, VA image
source, SP point, VS antenna). The ``rays`` table holds the same paths, one ray each.
"""
from __future__ import annotations

import numpy as np

from mmslam.raytrace.schema import (INTERACTION_LABELS, PATH_COLUMNS, ray_numbers, rays_columns, sort_paths,
                                    tx_position_columns)
from mmslam.scenes.landmarks import reflecting_faces
from mmslam.scenes.scenario import Scenario
from mmslam.model import BS, SP, VA, VS, direction_angles, mirror_point

_NONE, _SPECULAR, _DIFFUSE = (INTERACTION_LABELS.index(x) for x in ("none", "specular", "diffuse"))
INTERACTION_OF_TYPE: dict[int, int] = {BS: _NONE, VA: _SPECULAR, SP: _DIFFUSE, VS: _SPECULAR}
"""The analytic model's single interaction per landmark type (:data:`INTERACTION_LABELS` code): none for
the line of sight, a specular bounce on a wall (VA) or a car body (VS), a diffuse one on a small object (SP)."""


def interaction_of(types: np.ndarray) -> np.ndarray:
    """``(n,)`` int8 interaction code of each path of the analytic model from its type code ``(n,)``."""
    lut = np.zeros(max(INTERACTION_OF_TYPE) + 1, np.int8)
    for t, i in INTERACTION_OF_TYPE.items():
        lut[t] = i
    return lut[np.asarray(types, int)]


SPEED_OF_LIGHT = 299_792_458.0
"""Speed of light in vacuum, m/s."""

_FACE_TOL = 1e-9  # m, tolerance of the incidence-point-in-rectangle test
_EPS0 = 8.8541878128e-12  # F/m, vacuum permittivity

ITU_MATERIALS: dict[str, tuple[float, float, float, float]] = {
    "concrete": (5.24, 0.0, 0.0462, 0.7822), "brick": (3.91, 0.0, 0.0238, 0.16),
    "plasterboard": (2.73, 0.0, 0.0085, 0.9395), "wood": (1.99, 0.0, 0.0047, 1.0718),
    "glass": (6.31, 0.0, 0.0036, 1.3394), "ceiling_board": (1.48, 0.0, 0.0011, 1.0750),
    "chipboard": (2.58, 0.0, 0.0217, 0.7800), "floorboard": (3.66, 0.0, 0.0044, 1.3515),
    "metal": (1.0, 0.0, 1e7, 0.0), "marble": (7.074, 0.0, 0.0055, 0.9262),
    "very_dry_ground": (3.0, 0.0, 0.00015, 2.52),
}
"""ITU-R P.2040 (Table 3) material parameters ``(a, b, c, d)``: ``eps_r' = a f^b``, ``sigma = c f^d``
S/m with f in GHz."""


def relative_permittivity(material: str, frequency_hz: float) -> complex:
    """Complex relative permittivity ``eps_r' - j sigma / (2 pi f eps0)`` of an ITU material."""
    a, b, c, d = ITU_MATERIALS[material]
    fg = frequency_hz / 1e9
    return complex(a * fg**b, -c * fg**d / (2.0 * np.pi * frequency_hz * _EPS0))


def fresnel_reflection(cos_i: np.ndarray, eta: complex | np.ndarray, te: np.ndarray | bool) -> np.ndarray:
    """Fresnel reflection coefficient of a smooth half-space of relative permittivity ``eta``.

    ``cos_i``: cosine of the incidence angle (from the normal). TE (``te`` True, E parallel to the
    surface): ``(cos - s) / (cos + s)``; TM: ``(eta cos - s) / (eta cos + s)``,
    ``s = sqrt(eta - sin^2)`` (ITU-R P.2040 sign convention: at normal incidence
    ``Gamma_TE = -Gamma_TM = (1 - sqrt(eta)) / (1 + sqrt(eta))``; both tend to -1 at grazing).
    """
    cos_i = np.asarray(cos_i, float)
    eta = np.asarray(eta, complex)
    s = np.sqrt(eta - (1.0 - cos_i**2))
    r_te = (cos_i - s) / (cos_i + s)
    r_tm = (eta * cos_i - s) / (eta * cos_i + s)
    return np.where(te, r_te, r_tm)


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

    def __init__(self, scn: Scenario, rcs_m2: float = 1.0) -> None:
        if not (np.isfinite(rcs_m2) and rcs_m2 > 0):
            raise ValueError(f"rcs_m2={rcs_m2!r}: expected a positive radar cross-section in m^2")
        self.scn = scn
        self.rcs_m2 = float(rcs_m2)
        self.bs = scn.bs_array
        faces = reflecting_faces(scn)
        self.face_ids = [f.id for f in faces]
        if faces:
            self.face_point = np.stack([f.point for f in faces])  # (F, 3)
            self.face_normal = np.stack([f.normal for f in faces])
            self.face_lo = np.stack([f.lo for f in faces])
            self.face_hi = np.stack([f.hi for f in faces])
            self.images = mirror_point(self.bs[None, :], self.face_point, self.face_normal)
            mats = {b.name: b.material for b in scn.buildings}
            if scn.ground is not None:
                mats["ground"] = scn.ground.material
            self.face_object = [f.object for f in faces]
            self.face_eta = np.array([relative_permittivity(mats.get(f.object, "concrete"), scn.frequency_hz)
                                      for f in faces])
            self.face_te = np.abs(self.face_normal[:, 2]) < 0.5  # vertical face: TE
        else:
            self.face_object = []
            self.face_eta = np.zeros(0, complex)
            self.face_te = np.zeros(0, bool)
            self.face_point = self.face_normal = self.face_lo = self.face_hi = np.zeros((0, 3))
            self.images = np.zeros((0, 3))
        self.sp_ids = [s.name for s in scn.scatterers]
        self.sp_pos = np.array([s.position for s in scn.scatterers], dtype=float).reshape(-1, 3)
        self.vehicle_names = scn.vehicle_names

    # ------------------------------------------------------------------ protocol
    def settings(self) -> dict:
        """Settings that change the result (the geometry itself is in the scenario hash)."""
        return {"model": "first-order specular + point scatter, no blockage", "model_version": 2,
                "gain": "Friis LOS; VA Fresnel (ITU-R P.2040, TE vertical / TM horizontal faces); "
                        "SP/VS bistatic radar equation", "rcs_m2": self.rcs_m2}

    def versions(self) -> dict[str, str]:
        """Library versions that produced the rows."""
        return {"numpy": np.__version__}

    def trace_step(self, step: int, states: np.ndarray) -> dict[str, np.ndarray]:
        """The ``paths`` table of :meth:`trace_tables`."""
        return self.trace_tables(step, states)["paths"]

    def trace_tables(self, step: int, states: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        """``rays`` and ``paths`` of all receivers at one step (see module docstring).

        Args:
            step: time index written to the ``step`` column.
            states: ``(n_vehicles, 7)`` true states; columns 0:3 are antenna positions (m).

        Returns:
            ``{"rays": ..., "paths": ...}`` columns (schema dtypes); paths sorted by (rx, type,
            landmark_id), rays by (rx, ray); one ray per path row.
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

        # ---- complex gains and Doppler shifts, (R, L)
        lam = SPEED_OF_LIGHT / self.scn.frequency_hz
        gain = (lam / (4.0 * np.pi * toa)).astype(complex)
        if n_f:
            d_in = p - b  # BS -> incidence point
            with np.errstate(divide="ignore", invalid="ignore"):
                cos_i = np.abs(np.sum(d_in * self.face_normal[None], axis=-1)) / np.linalg.norm(d_in, axis=-1)
            gamma = fresnel_reflection(np.nan_to_num(cos_i, nan=1.0), self.face_eta[None], self.face_te[None])
            gain[:, 1:1 + n_f] *= gamma
        d1 = np.linalg.norm(pts - b, axis=-1)
        d2 = np.linalg.norm(pts - uu, axis=-1)
        with np.errstate(divide="ignore"):
            gain[:, 1 + n_f:] = np.sqrt(self.rcs_m2) * lam / ((4.0 * np.pi) ** 1.5 * d1 * d2)
        vel = np.stack([states[:, 4] * np.cos(states[:, 3]), states[:, 4] * np.sin(states[:, 3]),
                        np.zeros(n_rx)], axis=1)  # (R, 3)

        def unit(v):
            nv = np.linalg.norm(v, axis=-1, keepdims=True)
            return v / np.where(nv > 0, nv, 1.0)

        # -dL/dt: receiver term v_rx . (arrival direction), plus for VS the scatterer's own motion
        doppler = np.sum(vel[:, None, :] * unit(d_arr), axis=-1)
        v_s = vel[None, :, :]  # scattering vehicle j's velocity, (1, R, 3)
        doppler[:, 1 + n_f + n_s:] -= np.sum(v_s * (unit(pts[:, n_s:] - b) + unit(pts[:, n_s:] - uu)), axis=-1)
        doppler /= lam

        # ---- flatten the valid (rx, landmark) pairs into rows
        ri, li = np.nonzero(valid)
        n = ri.size
        tp = types[li]
        itype = interaction_of(tp)
        cols: dict[str, np.ndarray] = {
            "step": np.full(n, step, dtype=np.int32),
            "rx": ri.astype(np.int16),
            "type": tp,
            "landmark_id": ids[li],
            "bounces": (itype != _NONE).astype(np.int8),
            "diffuse": itype == _DIFFUSE,
            "toa_m": toa[ri, li],
            "aod_az": aod_az[ri, li], "aod_el": aod_el[ri, li],
            "aoa_az": aoa_az[ri, li], "aoa_el": aoa_el[ri, li],
            "power_db": free_space_power_db(toa[ri, li], self.scn.frequency_hz),
            **tx_position_columns(b, n),
            "bounce_x": bounce[ri, li, 0], "bounce_y": bounce[ri, li, 1], "bounce_z": bounce[ri, li, 2],
            "lm_x": lm[ri, li, 0], "lm_y": lm[ri, li, 1], "lm_z": lm[ri, li, 2],
            "n_paths": np.ones(n, dtype=np.int32),
            "delay_spread_m": np.zeros(n),
            "doppler_hz": doppler[ri, li],
        }
        a = gain[ri, li]
        with np.errstate(divide="ignore"):
            cols["power_db"] = 20.0 * np.log10(np.abs(a))
        angles = np.stack([cols["aod_az"], cols["aod_el"], cols["aoa_az"], cols["aoa_el"]], axis=1)
        ray = ray_numbers(ri, toa[ri, li] / SPEED_OF_LIGHT, tiebreak=li)
        cols["ray"] = ray
        objs = np.array(["", *self.face_object, *self.sp_ids, *self.vehicle_names[:n_rx]], dtype=object)[li]
        rays = rays_columns(step=step, rx=ri, typ=tp, landmark_id=ids[li], a=a, delay_s=toa[ri, li] / SPEED_OF_LIGHT,
                            angles=angles, doppler_hz=doppler[ri, li], itype=itype[:, None], objects=objs[:, None],
                            verts=bounce[ri, li][:, None, :], ray=ray, tx_pos=b)
        cols = {k: np.asarray(cols[k], dtype=object if t == "string" else np.dtype(t))
                for k, t in PATH_COLUMNS.items()}
        return {"rays": rays, "paths": sort_paths(cols)}
