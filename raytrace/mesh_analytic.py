"""Closed-form paths on the triangles of an external XML scene: an independent cross-check of Sionna.

:class:`MeshAnalyticSource` is the ``analytic`` source of a scenario with ``xml_scene`` set. It
reads the scene's triangles itself (:func:`mmslam.scenes.geometry.static_geometry`: PLY files
parsed in NumPy, no Sionna / Mitsuba) and per receiver ``u`` and step (global frame, metres,
radians):

- **BS** (line of sight): if the segment BS -> ``u`` crosses no triangle;
- **VA** of an XML plane (the planes of :func:`mmslam.raytrace.labels.plane_table`, the table the
  Sionna source labels with, so ids match): for each triangle, the segment image -> ``u`` (image =
  BS mirrored in the triangle's plane) must cross that triangle with ``u`` on the BS side; the
  crossing is the incidence point ``p``; both legs BS -> ``p`` and ``p`` -> ``u`` unblocked;
- **VA** of a scenario box face, **SP** and **VS** as in :class:`~mmslam.raytrace.analytic.AnalyticSource`
  (range gate for SP / VS), kept only if their legs are unblocked (an SP's own mesh excepted).

Blockers are the static triangles (XML shapes and scenario boxes, scatterers, ground) and the car
bodies at this step (the receiving car's own too: it hides ground reflections close to it).
Each landmark is one row (``n_paths = 1``) and one ray; box / SP / VS rows keep the gains and
Doppler of :class:`~mmslam.raytrace.analytic.AnalyticSource`; XML-plane VAs get the Friis gain
over the unfolded length (the XML materials' reflection loss is not modelled) and the
receiver's Doppler.
Higher orders, diffuse paths on the XML geometry and diffraction are not modelled.
"""
from __future__ import annotations

import numpy as np

from mmslam.raytrace.analytic import SPEED_OF_LIGHT, AnalyticSource, interaction_of
from mmslam.raytrace.labels import plane_table
from mmslam.raytrace.schema import PATH_COLUMNS, ray_numbers, rays_columns, sort_paths, tx_position_columns
from mmslam.scenes.geometry import StaticGeometry, static_geometry
from mmslam.scenes.meshes import car_mesh
from mmslam.scenes.scenario import Scenario
from mmslam.model import BS, SP, VA, direction_angles, mirror_point

_EPS = 1e-9


class MeshAnalyticSource(AnalyticSource):
    """``analytic`` source on an external XML scene (see module docstring)."""

    def __init__(self, scn: Scenario) -> None:
        super().__init__(scn)
        self.geom = static_geometry(scn)
        xml = np.flatnonzero(np.asarray(self.geom.kind) == "xml")
        self._xml_tri_idx = np.flatnonzero(np.isin(self.geom.obj, xml))
        tri = self.geom.triangles[self._xml_tri_idx]
        self.planes = plane_table(tri, self.bs)
        ok = self.planes.tri_plane >= 0
        self._tri = tri[ok]
        self._tri_global = self._xml_tri_idx[ok]
        self._tri_plane = self.planes.tri_plane[ok]
        n, d = self.planes.normal, self.planes.offset
        self._plane_image = mirror_point(self.bs[None, :], n * d[:, None], n) if len(n) else np.zeros((0, 3))
        self._sp_obj = np.array([self.geom.names.index(s) for s in self.sp_ids], np.int64)

    def settings(self) -> dict:
        return {"model": "mesh: LOS + first-order specular on the XML planes and box faces + point scatter, "
                         "static triangles block, cars do not", "model_version": 1}

    # ------------------------------------------------------------------
    def _xml_vas(self, u: np.ndarray) -> list[tuple[int, np.ndarray, int]]:
        """(plane, incidence point, triangle) of every XML-plane VA path to receiver ``u`` before blockage."""
        tri = self._tri
        if not len(tri):
            return []
        v = self._plane_image[self._tri_plane]  # (T, 3) segment start
        n = self.planes.normal[self._tri_plane]
        side = np.sum(n * u, axis=1) - self.planes.offset[self._tri_plane]  # > 0: u on the BS side
        d = u[None, :] - v
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        pv = np.cross(d, e2)
        det = np.sum(e1 * pv, axis=1)
        good = (np.abs(det) > 1e-15) & (side > _EPS)
        inv = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)
        tv = v - tri[:, 0]
        a = np.sum(tv * pv, axis=1) * inv
        qv = np.cross(tv, e1)
        b = np.sum(d * qv, axis=1) * inv
        s = np.sum(e2 * qv, axis=1) * inv
        hit = good & (a >= -_EPS) & (b >= -_EPS) & (a + b <= 1 + _EPS) & (s > 0) & (s < 1)
        out, seen = [], set()
        for t in np.flatnonzero(hit):
            pl = int(self._tri_plane[t])
            if pl in seen:  # a point on an edge shared by two triangles of one plane
                continue
            seen.add(pl)
            out.append((pl, v[t] + s[t] * d[t], int(t)))
        return out

    def _cars(self, states: np.ndarray) -> StaticGeometry:
        """The car bodies posed at ``states (n_vehicles, 7)`` as triangles (one object per car)."""
        tris = [np.asarray(m.vertices)[np.asarray(m.faces)]
                for m in (car_mesh(v, states[i]) for i, v in enumerate(self.scn.vehicles))]
        obj = np.repeat(np.arange(len(tris)), [len(t) for t in tris])
        return StaticGeometry(np.concatenate(tris), obj, tuple(self.scn.vehicle_names), ("car",) * len(tris))

    def trace_step(self, step: int, states: np.ndarray) -> dict[str, np.ndarray]:
        """The ``paths`` table of :meth:`trace_tables`."""
        return self.trace_tables(step, states)["paths"]

    def trace_tables(self, step: int, states: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        """``rays`` and ``paths`` of all receivers at one step (one ray per path row); see the module doc."""
        states = np.asarray(states, float)
        tables = super().trace_tables(step, states)
        base, br = tables["paths"], tables["rays"]
        # the parent's complex coefficient of each of its path rows (one ray per row, linked by (rx, ray))
        a_of = {(int(r), int(k)): complex(x, y) for r, k, x, y in zip(br["rx"], br["ray"], br["a_re"], br["a_im"])}
        base_a = np.array([a_of[(int(r), int(k))] for r, k in zip(base["rx"], base["ray"])], complex)
        u_all = states[:, :3]
        b = self.bs
        # ---- rows of the box / SP / VS model, filtered by blockage
        n0 = len(base["rx"])
        rx0 = base["rx"].astype(np.int64)
        typ0 = base["type"]
        bounce = np.stack([base["bounce_x"], base["bounce_y"], base["bounce_z"]], axis=1)
        u0 = u_all[rx0]
        is_bs = typ0 == BS
        mid = np.where(is_bs[:, None], u0, bounce)
        ex = np.full(n0, -1, np.int64)
        sp_rows = np.flatnonzero(typ0 == SP)
        if sp_rows.size:
            lut = dict(zip(self.sp_ids, self._sp_obj))
            ex[sp_rows] = [lut[str(i)] for i in base["landmark_id"][sp_rows]]
        cars = self._cars(states)
        b0 = np.repeat(b[None], n0, 0)
        leg1 = self.geom.segments_blocked(b0, mid, exclude_obj=ex) | cars.segments_blocked(b0, mid)
        leg2 = np.where(is_bs, False, self.geom.segments_blocked(mid, u0, exclude_obj=ex) | cars.segments_blocked(mid, u0))
        keep = ~(leg1 | leg2)
        cols = {k: np.asarray(v)[keep] for k, v in base.items()}
        a_rows = [base_a[keep]]
        objects = [("" if t == BS else str(i).split(":")[0]) for t, i in zip(cols["type"], cols["landmark_id"])]
        # ---- XML-plane VAs (Friis gain: the reflection loss of the XML's materials is not modelled)
        ri, pl, pp, tr = [], [], [], []
        for r, u in enumerate(u_all):
            for plane, p, t in self._xml_vas(u):
                ri.append(r), pl.append(plane), pp.append(p), tr.append(t)
        if ri:
            ri_a, pl_a, p_a, tr_a = np.asarray(ri), np.asarray(pl), np.asarray(pp), np.asarray(tr)
            u = u_all[ri_a]
            bb = np.repeat(b[None], len(ri_a), 0)
            ok = ~(self.geom.segments_blocked(bb, p_a) | self.geom.segments_blocked(p_a, u)
                   | cars.segments_blocked(bb, p_a) | cars.segments_blocked(p_a, u))
            ri_a, pl_a, p_a, tr_a, u = ri_a[ok], pl_a[ok], p_a[ok], tr_a[ok], u[ok]
            img = self._plane_image[pl_a]
            toa = np.linalg.norm(img - u, axis=1)
            aod_az, aod_el = direction_angles(p_a - b)
            aoa_az, aoa_el = direction_angles(img - u)
            lam = SPEED_OF_LIGHT / self.scn.frequency_hz
            h = states[ri_a, 3]
            vel = np.stack([states[ri_a, 4] * np.cos(h), states[ri_a, 4] * np.sin(h), np.zeros(len(h))], axis=1)
            d_arr = (img - u) / np.maximum(toa, 1e-12)[:, None]
            n = len(ri_a)
            a = (lam / (4.0 * np.pi * toa)).astype(complex)
            new = {
                "step": np.full(n, step, np.int32), "rx": ri_a.astype(np.int16), "type": np.full(n, VA, np.int8),
                "landmark_id": np.array([self.planes.ids[i] for i in pl_a], dtype=object),
                "bounces": np.ones(n, np.int8), "diffuse": np.zeros(n, bool), "toa_m": toa,
                "aod_az": aod_az, "aod_el": aod_el, "aoa_az": aoa_az, "aoa_el": aoa_el,
                "power_db": 20.0 * np.log10(np.abs(a)), **tx_position_columns(b, n),
                "bounce_x": p_a[:, 0], "bounce_y": p_a[:, 1], "bounce_z": p_a[:, 2],
                "lm_x": img[:, 0], "lm_y": img[:, 1], "lm_z": img[:, 2],
                "n_paths": np.ones(n, np.int32), "delay_spread_m": np.zeros(n),
                "doppler_hz": np.sum(vel * d_arr, axis=1) / lam, "ray": np.zeros(n, np.int32),
            }
            cols = {k: np.concatenate([cols[k], np.asarray(new[k], dtype=cols[k].dtype)]) for k in PATH_COLUMNS}
            objects += [self.geom.names[self.geom.obj[self._tri_global[t]]] for t in tr_a]
            a_rows.append(a)
        # ---- one ray per path row, numbered by delay within each receiver
        n = len(cols["rx"])
        a_all = np.concatenate(a_rows)
        order_key = np.arange(n)
        cols["ray"] = ray_numbers(cols["rx"], cols["toa_m"] / SPEED_OF_LIGHT, tiebreak=order_key)
        typ = cols["type"]
        verts = np.stack([cols["bounce_x"], cols["bounce_y"], cols["bounce_z"]], axis=1)
        angles = np.stack([cols[c] for c in ("aod_az", "aod_el", "aoa_az", "aoa_el")], axis=1)
        rays = rays_columns(step=step, rx=cols["rx"], typ=typ, landmark_id=cols["landmark_id"], a=a_all,
                            delay_s=cols["toa_m"] / SPEED_OF_LIGHT, angles=angles, doppler_hz=cols["doppler_hz"],
                            itype=interaction_of(typ)[:, None],
                            objects=np.asarray(objects, dtype=object)[:, None], verts=verts[:, None, :],
                            ray=cols["ray"], tx_pos=b)
        cols = {k: np.asarray(cols[k], dtype=object if t == "string" else np.dtype(t)) for k, t in PATH_COLUMNS.items()}
        return {"rays": rays, "paths": sort_paths(cols)}
