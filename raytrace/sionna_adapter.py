"""Sionna RT path source: the only module that imports Sionna / Mitsuba / Dr.Jit.

:class:`SionnaSource` builds the scenario's scene once (:func:`mmslam.scenes.meshes.build_scene`),
loads it with one Sionna object per scenario object (box buildings, scatterers, ground, cars) and
the shapes of an external XML scene merged per radio material (Sionna's ``merge_shapes``: the
per-object cost dominates a city trace; Munich's 2367 objects become about 10), and per step:

1. moves every car body to its vehicle's state (position and heading; the vertex buffer is
   rewritten from the exact vehicle-frame box, so no drift accumulates) and sets its velocity;
2. moves one receiver per vehicle to the antenna position ``(x, y, z)`` (just above the roof);
3. runs one :class:`sionna.rt.PathSolver` call for all receivers (transmitter at the BS,
   isotropic single antennas, LOS + specular + diffuse reflection, no refraction/diffraction);
4. converts the valid paths to NumPy once (complex coefficients ``a``, delays, angles, Doppler
   shifts, interactions, vertices) and labels them (:mod:`mmslam.raytrace.labels`): every valid
   path becomes a row of the ``rays`` table, the strongest per landmark a row of ``paths``. A
   specular bounce on the external scene is a VA of the hit triangle's plane (a plane table built
   once from the loaded triangles), whichever building or merged shape the triangle belongs to.

Every receiver moves with its vehicle's velocity (set on the receiver and on the car body), so
Sionna's Doppler shifts include the receiver's motion and that of the car a VS path bounces off.

Receivers and the transmitter are created once and only moved; geometry changes only by
rewriting vertex buffers of constant size, so the solver's kernels are traced once and reused.
Two things would otherwise become literal constants in Dr.Jit kernels and force a re-trace
(an LLVM/CUDA compile) at almost every step: receiver positions and car velocities (set as
opaque Dr.Jit variables here) and the number of paths of the busiest receiver, which Sionna's
``Paths`` uses as the last tensor dimension and in its scatter indices. That dimension is rounded
up to a per-source capacity (:class:`_PathCapacity`, grown by doubling, so it changes only a few
times per run); the extra slots are invalid paths and never read.
Object ids reported by Sionna are mapped to names inside each step (never cached).

Global frame, metres, radians throughout. Angles returned are global (AOA azimuth not
heading-corrected); elevation = pi/2 - Sionna's zenith angle.
"""
from __future__ import annotations

import importlib.metadata
import re
import tempfile
from pathlib import Path

import numpy as np

from mmslam.backend import import_mitsuba
from mmslam.errors import ConfigError, MmslamError
from mmslam.raytrace.labels import SceneIndex, label_paths, plane_table
from mmslam.raytrace.schema import SIONNA_INTERACTION_CODE, ray_numbers, rays_columns
from mmslam.scenes.meshes import build_scene, car_local_vertices, car_pose_vertices
from mmslam.scenes.scenario import Scenario

SPEED_OF_LIGHT = 299_792_458.0  # m/s
MAX_DEPTH_LIMIT = 3
TX_NAME = "tx:bs"


def _rx_name(vehicle: str) -> str:
    return f"rx:{vehicle}"


def _step_seed(seed: int, step: int) -> int:
    """Solver seed for one step: a deterministic function of (seed, step), in [0, 2**31)."""
    return int(np.random.SeedSequence([int(seed), int(step)]).generate_state(1)[0] & 0x7FFFFFFF)


class _PathCapacity:
    """Round Sionna's per-link path count up to a capacity that rarely changes (see module doc).

    ``Paths._build_from_buffer`` sizes its tensors ``[..., max_num_paths]`` with ``max_num_paths``
    baked into the generated kernels; while this context is active the count is replaced by
    ``capacity``: at the first step the smallest power of two >= ``minimum`` and >= twice the count,
    later doubled only when a step needs more. The padded paths have ``valid == False``.
    """

    def __init__(self, minimum: int = 1024) -> None:
        self.minimum = int(minimum)
        self.capacity = 0
        self.grown = 0  # times the capacity grew after the first step (each costs one re-trace)

    def round_up(self, count: int) -> int:
        if self.capacity == 0:
            self.capacity = self.minimum
            while self.capacity < 2 * count:
                self.capacity *= 2
        while self.capacity < count:
            self.capacity *= 2
            self.grown += 1
        return self.capacity

    def __enter__(self) -> "_PathCapacity":
        from sionna.rt.path_solvers.paths import Paths

        self._cls = Paths
        self._orig = Paths.__dict__["_build_from_buffer"]
        capacity = self

        def build_padded(paths, *args, **kwargs):
            paths._max_num_paths = capacity.round_up(int(paths._max_num_paths))
            return capacity._orig(paths, *args, **kwargs)

        Paths._build_from_buffer = build_padded
        return self

    def __exit__(self, *exc) -> None:
        self._cls._build_from_buffer = self._orig


class SionnaSource:
    """Path source backed by Sionna RT's PathSolver (LLVM on the CPU, CUDA if available).

    Args:
        scn: the scenario.
        max_depth: maximum number of bounces (0..3).
        samples_per_src: rays shot from the BS per step. The default 10**6 gives every
            1-m scatterer of ``paper`` several diffuse hits per step.
        seed: base seed; step ``k`` uses a seed derived from ``(seed, k)``. The solver runs in
            deterministic mode, so the same seed gives the same paths.
        scene_dir: where to write the scene (PLY + XML); a temporary folder if ``None``.
    """

    name = "sionna"

    def __init__(self, scn: Scenario, max_depth: int = 1, samples_per_src: int = 10**6, seed: int = 0,
                 scene_dir: str | Path | None = None) -> None:
        if isinstance(max_depth, bool) or not isinstance(max_depth, (int, np.integer)) or not 0 <= max_depth <= MAX_DEPTH_LIMIT:
            raise ConfigError(f"max_depth={max_depth!r}: expected an integer in 0..{MAX_DEPTH_LIMIT}")
        if isinstance(samples_per_src, bool) or not isinstance(samples_per_src, (int, np.integer)) or samples_per_src < 1:
            raise ConfigError(f"samples_per_src={samples_per_src!r}: expected a positive integer (e.g. 1000000)")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed={seed!r}: expected a non-negative integer")
        self.scn = scn
        self.max_depth = int(max_depth)
        self.samples_per_src = int(samples_per_src)
        self.seed = int(seed)
        if scene_dir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="mmslam-scene-")
            scene_dir = self._tmp.name
        self.scene_dir = Path(scene_dir)
        self.xml_path = build_scene(scn, self.scene_dir)

        self._mi = mi = import_mitsuba()
        import sionna.rt as rt

        self._rt = rt
        # scenario objects (box buildings, scatterers, ground, cars) stay separate objects: the labeller
        # needs their names and the cars move; an external scene's shapes are merged per material
        keep = [b.name for b in scn.buildings] + [s.name for s in scn.scatterers] + scn.vehicle_names
        if scn.ground is not None:
            keep.append("ground")
        self.merged = bool(scn.xml_scene)
        exclude = "^mesh-(" + "|".join(re.escape(k) for k in keep) + ")$"
        try:
            self.scene = rt.load_scene(str(self.xml_path), merge_shapes=self.merged,
                                       merge_shapes_exclude_regex=exclude if self.merged else None)
        except Exception as e:  # Mitsuba/Sionna parse errors: name the file and the cause
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ConfigError(f"{self.xml_path}: Sionna could not load the scene ({msg}); check xml_scene "
                              "and the materials (ITU materials valid at the scenario frequency)") from None
        try:
            self.scene.frequency = float(scn.frequency_hz)
        except Exception as e:
            raise ConfigError(f"{scn.source_file}: frequency_hz={scn.frequency_hz:g}: a radio material is not "
                              f"defined at this frequency ({str(e).splitlines()[0]}); choose other materials") from None
        self.scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
        self.scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
        self.scene.add(rt.Transmitter(TX_NAME, position=mi.Point3f(*map(float, scn.bs))))
        for v in scn.vehicles:
            self.scene.add(rt.Receiver(_rx_name(v.name), position=mi.Point3f(*map(float, v.initial_state[:3]))))
        if list(self.scene.receivers) != [_rx_name(v.name) for v in scn.vehicles]:
            raise MmslamError("Sionna scene: receivers are not in vehicle order; this is a bug in sionna_adapter")
        self.solver = rt.PathSolver(deterministic=True)

        veh_names = set(scn.vehicle_names)
        scen_names = {b.name for b in scn.buildings} | {s.name for s in scn.scatterers} | veh_names
        if scn.ground is not None:
            scen_names.add("ground")
        extra = sorted(n for n in self.scene.objects if n not in scen_names)
        # triangles of the external scene's (merged) shapes, stacked in ``extra`` order:
        # triangle (object index o, primitive i) = row self._nrm_off[o] + i
        tris = []
        for n in extra:
            mesh = self.scene.objects[n].mi_mesh
            vp = np.asarray(mesh.vertex_positions_buffer().numpy(), float).reshape(-1, 3)
            fc = np.asarray(mesh.faces_buffer().numpy(), np.int64).reshape(-1, 3)
            tris.append(vp[fc])
        planes = plane_table(np.concatenate(tris) if tris else np.zeros((0, 3, 3)), scn.bs_array)
        self.index = SceneIndex.from_scenario(scn, extra_static=extra, planes=planes)
        missing = sorted(scen_names - set(self.scene.objects))
        if missing:
            raise MmslamError(f"{self.xml_path}: objects {missing} missing from the loaded Sionna scene; "
                              "rebuild the scene (mmslam scene build)")

        # exact vehicle-frame vertices, in the vertex order Mitsuba loaded
        self._car_local: dict[str, np.ndarray] = {}
        self._vp_key: dict[str, str] = {}
        params = self.scene.mi_scene_params
        for v in scn.vehicles:
            mesh = self.scene.objects[v.name].mi_mesh
            key = f"{mesh.id()}.vertex_positions"
            loaded = np.asarray(params[key].numpy(), float).reshape(-1, 3)
            st = v.initial_state
            c, s = np.cos(st[3]), np.sin(st[3])
            rel = loaded - np.array(st[:3], float)
            back = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)
            exact, _ = car_local_vertices(v)
            d = np.linalg.norm(back[:, None, :] - exact[None, :, :], axis=2)
            j = np.argmin(d, axis=1)
            if np.max(d[np.arange(len(j)), j]) > 1e-3:
                raise MmslamError(f"Sionna scene: car mesh of '{v.name}' does not match its box; rebuild the scene")
            self._car_local[v.name] = exact[j]
            self._vp_key[v.name] = key

        # hit-triangle normal = the normal of its plane in the plane table (exact lookup when labelling):
        # normal of (object index o, primitive i) = self._normals[self._nrm_off[o] + i]
        self._nrm_off = np.full(len(self.index.names), -1, np.int64)
        self._nrm_count = np.zeros(len(self.index.names), np.int64)
        off = 0
        for n, t in zip(extra, tris):
            k = self.index.names.index(n)
            self._nrm_off[k], self._nrm_count[k] = off, len(t)
            off += len(t)
        self._normals = planes.tri_normal
        self._steps_traced = 0
        self._capacity = _PathCapacity()
        # Sionna creates a car's velocity attribute with literal values on the first assignment and
        # updates it with the given (opaque) array afterwards: assign twice so that step 0 already
        # compiles the kernels every later step reuses.
        import drjit as dr

        for v in scn.vehicles:
            for _ in range(2):
                self.scene.objects[v.name].velocity = dr.opaque(mi.Vector3f, [0.0, 0.0, 0.0])
            self.scene.receivers[_rx_name(v.name)].velocity = dr.opaque(mi.Vector3f, [0.0, 0.0, 0.0])
        self.last_paths = None  # the Sionna Paths object of the latest step (for cross-checks)

    # ------------------------------------------------------------------ protocol
    def settings(self) -> dict:
        """Solver settings that change the traced paths (part of the cache config hash)."""
        return {"max_depth": self.max_depth, "samples_per_src": self.samples_per_src, "seed": self.seed,
                "los": True, "specular_reflection": True, "diffuse_reflection": True, "refraction": False,
                "diffraction": False, "synthetic_array": True, "deterministic": True, "antenna": "iso/V",
                "seed_per_step": "SeedSequence([seed, step])",
                "merge_external_shapes": self.merged,
                # depth >= 2: double specular bounces on planes are labelled VA (image of an image);
                # a new value so that depth-2 caches labelled OTHER before are re-traced
                "va_labels": "plane table" if self.max_depth < 2 else "plane table, order-2 images"}

    def versions(self) -> dict[str, str]:
        """Installed versions of sionna-rt, mitsuba and drjit, and the Mitsuba variant in use."""
        out = {}
        for pkg in ("sionna-rt", "mitsuba", "drjit"):
            try:
                out[pkg] = importlib.metadata.version(pkg)
            except importlib.metadata.PackageNotFoundError:
                out[pkg] = "unknown"
        out["variant"] = str(self._mi.variant())
        return out

    # ------------------------------------------------------------------ per step
    def _move(self, states: np.ndarray) -> None:
        """Car meshes, velocities and receivers to ``states (n_vehicles, 7)``; opaque values (no re-trace)."""
        import drjit as dr

        mi = self._mi
        params = self.scene.mi_scene_params
        for i, v in enumerate(self.scn.vehicles):
            x, y, z, h, sp = (float(a) for a in states[i, :5])
            verts = car_pose_vertices(self._car_local[v.name], x, y, z, h)
            params[self._vp_key[v.name]] = mi.Float(verts.astype(np.float32).reshape(-1))
        params.update()
        self.scene.scene_geometry_updated()
        for i, v in enumerate(self.scn.vehicles):
            x, y, z, h, sp = (float(a) for a in states[i, :5])
            vel = [sp * np.cos(h), sp * np.sin(h), 0.0]
            self.scene.objects[v.name].velocity = dr.opaque(mi.Vector3f, vel)
            rx = self.scene.receivers[_rx_name(v.name)]
            rx.position = dr.opaque(mi.Point3f, [x, y, z])
            rx.velocity = dr.opaque(mi.Vector3f, vel)

    def raw_paths(self, step: int, states: np.ndarray) -> dict[str, np.ndarray]:
        """Move vehicles/receivers to ``states`` and trace; unlabelled valid paths as NumPy.

        Returns ``rx (n,)``, ``obj (n, D)`` (index into ``self.index.names``, -1 empty slot),
        ``itype (n, D)``, ``verts (n, D, 3)``, ``normals (n, D, 3)`` (static XML objects only),
        ``toa_m (n,)``, ``angles (n, 4)`` (global ``aod_az, aod_el, aoa_az, aoa_el``), ``power_db (n,)``,
        ``a (n,)`` complex path coefficients (Sionna's ``Paths.a``), ``delay_s (n,)`` (s),
        ``doppler_hz (n,)`` (Hz). The Sionna ``Paths`` object stays in :attr:`last_paths`.
        """
        states = np.asarray(states, float)
        nv = len(self.scn.vehicles)
        if states.shape != (nv, 7):
            raise MmslamError(f"trace_step: states has shape {states.shape}, expected ({nv}, 7) "
                              "(one [x, y, z, heading, speed, turn_rate, bias] row per vehicle)")
        if not np.all(np.isfinite(states[:, :5])):
            raise MmslamError(f"trace_step: step {step}: non-finite vehicle state; check the trajectory")
        self._move(states)
        with self._capacity:
            p = self.solver(self.scene, max_depth=self.max_depth, samples_per_src=self.samples_per_src,
                            max_num_paths_per_src=max(self.samples_per_src, 1000), synthetic_array=True,
                            los=True, specular_reflection=True, diffuse_reflection=True, refraction=False,
                            diffraction=False, seed=_step_seed(self.seed, step))
        self._steps_traced += 1
        self.last_paths = p
        valid = np.asarray(p.valid.numpy(), bool).reshape(nv, -1)  # one tx
        r_idx, p_idx = np.nonzero(valid)
        n = r_idx.size
        tau = np.asarray(p.tau.numpy(), float).reshape(nv, -1)[r_idx, p_idx]
        ang = [np.asarray(a.numpy(), float).reshape(nv, -1)[r_idx, p_idx]
               for a in (p.phi_t, p.theta_t, p.phi_r, p.theta_r)]
        are, aim = (np.asarray(a.numpy(), float).reshape(nv, -1)[r_idx, p_idx] for a in p.a)
        doppler = np.asarray(p.doppler.numpy(), float).reshape(nv, -1)[r_idx, p_idx]
        with np.errstate(divide="ignore"):
            power = 10.0 * np.log10(are**2 + aim**2)
        inter = np.asarray(p.interactions.numpy()).astype(np.int64)
        D = inter.shape[0]
        if D == 0:
            itype = np.zeros((n, 1), np.int64)
            obj = np.full((n, 1), -1, np.int64)
            verts = np.full((n, 1, 3), np.nan)
            prims = np.zeros((n, 1), np.int64)
        else:
            itype = inter.reshape(D, nv, -1)[:, r_idx, p_idx].T
            ids = np.asarray(p.objects.numpy()).astype(np.int64).reshape(D, nv, -1)[:, r_idx, p_idx].T
            prims = np.asarray(p.primitives.numpy()).astype(np.int64).reshape(D, nv, -1)[:, r_idx, p_idx].T
            verts = np.asarray(p.vertices.numpy(), float).reshape(D, nv, -1, 3)[:, r_idx, p_idx].transpose(1, 0, 2)
            # object id -> name index, built now (ids are per-load pointers)
            id2name = {int(o.object_id): nm for nm, o in self.scene.objects.items()}
            uid = np.unique(ids)
            lut_idx = self.index.index_of([id2name.get(int(u), "") for u in uid])
            obj = lut_idx[np.searchsorted(uid, ids)]
            obj = np.where(itype != 0, obj, -1)
        normals = np.full(verts.shape, np.nan)
        if len(self._normals) and n:
            so = np.clip(obj, 0, None)
            has = (obj >= 0) & (self._nrm_off[so] >= 0) & (prims >= 0) & (prims < self._nrm_count[so])
            normals[has] = self._normals[self._nrm_off[so][has] + prims[has]]
        el_t = np.pi / 2 - ang[1]
        el_r = np.pi / 2 - ang[3]
        angles = np.stack([ang[0], el_t, ang[2], el_r], axis=1) if n else np.zeros((0, 4))
        return {"rx": r_idx.astype(np.int64), "obj": obj, "itype": itype, "verts": verts, "normals": normals,
                "toa_m": tau * SPEED_OF_LIGHT, "angles": angles, "power_db": power, "a": are + 1j * aim,
                "delay_s": tau, "doppler_hz": doppler}

    def trace_step(self, step: int, states: np.ndarray) -> dict[str, np.ndarray]:
        """The ``paths`` table of :meth:`trace_tables`."""
        return self.trace_tables(step, states)["paths"]

    def trace_tables(self, step: int, states: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        """``rays`` (every valid path) and labelled ``paths`` at one step (schema columns, sorted).

        Args:
            step: time index (selects the solver seed).
            states: ``(n_vehicles, 7)`` true states ``[x, y, z, heading, speed, turn_rate, bias]``.
        """
        raw = self.raw_paths(step, states)
        ray = ray_numbers(raw["rx"], raw["delay_s"])
        paths, lab = label_paths(self.index, rx=raw["rx"], obj=raw["obj"], itype=raw["itype"], verts=raw["verts"],
                                 toa_m=raw["toa_m"], angles=raw["angles"], power_db=raw["power_db"],
                                 antennas=np.asarray(states, float)[:, 0:3], normals=raw["normals"], step=step,
                                 doppler_hz=raw["doppler_hz"], ray=ray, return_rays=True)
        itype = raw["itype"]
        code = np.zeros(itype.shape, np.int64)
        for sc, c in SIONNA_INTERACTION_CODE.items():
            code[itype == sc] = c
        names = np.array([*self.index.names, "?"], dtype=object)
        objects = np.where(itype != 0, names[np.where(raw["obj"] >= 0, raw["obj"], len(self.index.names))], "")
        rays = rays_columns(step=step, rx=raw["rx"], typ=lab["type"], landmark_id=lab["landmark_id"], a=raw["a"],
                            delay_s=raw["delay_s"], angles=raw["angles"], doppler_hz=raw["doppler_hz"], itype=code,
                            objects=objects, verts=raw["verts"], ray=ray, tx_pos=self.scn.bs_array)
        return {"rays": rays, "paths": paths}


def sionna_radio_map(scn: Scenario, center: tuple[float, float, float], size: tuple[float, float], cell: float,
                     samples: int = 10**6, max_depth: int = 1, seed: int = 0) -> np.ndarray:
    """Sionna's own radio map (:class:`sionna.rt.RadioMapSolver`) of the BS over a horizontal plane.

    The scene is the scenario's static scene (external XML shapes, box buildings, scatterers,
    ground) without the cars; the transmitter is an isotropic vertically polarised antenna at the
    BS, as in :class:`SionnaSource`, with the same interactions (LOS, specular and diffuse
    reflection, no refraction or diffraction) up to ``max_depth`` bounces.

    Args:
        center: ``(x, y, z)`` m, centre of the measurement plane (parallel to x-y).
        size: ``(sx, sy)`` m, extent of the plane; cells of ``cell`` m (``sx / cell`` cells along x).
        samples: rays shot from the BS; seed: Sionna's sampling seed.

    Returns:
        ``(ny, nx)`` path gain per cell (linear, the cell average of ``sum |a|^2``, eq. 54 of Sionna's
        radio map solver docs); row ``i`` is at ``y = center_y - size_y / 2 + (i + 0.5) cell``,
        column ``j`` at ``x = center_x - size_x / 2 + (j + 0.5) cell``.
    """
    import dataclasses

    mi = import_mitsuba()
    import sionna.rt as rt

    static = dataclasses.replace(scn, vehicles=())
    with tempfile.TemporaryDirectory(prefix="mmslam-radiomap-") as d:
        xml = build_scene(static, d)
        try:
            scene = rt.load_scene(str(xml), merge_shapes=True)
        except Exception as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ConfigError(f"{xml}: Sionna could not load the scene ({msg}); check xml_scene") from None
    try:
        scene.frequency = float(scn.frequency_hz)
    except Exception as e:
        raise ConfigError(f"{scn.source_file}: frequency_hz={scn.frequency_hz:g}: a radio material is not "
                          f"defined at this frequency ({str(e).splitlines()[0]}); choose other materials") from None
    scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.add(rt.Transmitter(TX_NAME, position=mi.Point3f(*map(float, scn.bs))))
    rm = rt.RadioMapSolver()(scene, center=mi.Point3f(*map(float, center)), orientation=mi.Point3f(0.0, 0.0, 0.0),
                             size=mi.Point2f(*map(float, size)), cell_size=mi.Point2f(float(cell), float(cell)),
                             samples_per_tx=int(samples), max_depth=int(max_depth), los=True,
                             specular_reflection=True, diffuse_reflection=True, refraction=False,
                             diffraction=False, seed=int(seed))
    pg = np.asarray(rm.path_gain.numpy(), float)  # (num_tx, ny, nx)
    return pg[0]
