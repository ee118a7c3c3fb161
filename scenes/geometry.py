"""Static scene geometry as plain triangles, and ray casting on it in NumPy (no Sionna, no Mitsuba).

:func:`static_geometry` gathers every static triangle of a scenario's scene: the shapes of its
external XML scene (``xml_scene``, PLY meshes; each XML shape is one object) plus the scenario's
own box buildings, scatterers and ground. Vehicles are not static and are left out.

Two ray casters work on it, both exact on the triangles (no tolerance other than float64):

- :meth:`StaticGeometry.vertical_hits`: every surface crossed by the vertical line through each
  query point ``(x, y)`` (height map, terrain, "what is above / below a car"); triangles are
  bucketed on a 2-D grid, so a query costs only the triangles over its cell. Vertical triangles
  (walls) have no area in plan and are never hit by a vertical line.
- :meth:`StaticGeometry.segments_blocked`: whether each segment ``a -> b`` crosses any triangle
  (Moeller-Trumbore, vectorised over segment x triangle pairs that pass a bounding-box test).

Global frame: x east, y north, z up, metres.
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mmslam.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover  (types only: the scenario loader sits above this module)
    from mmslam.scenes.scenario import Scenario


# ====================================================================== PLY reading
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply_triangles(path: str | Path) -> np.ndarray:
    """Triangles ``(T, 3, 3)`` (float64, the file's coordinates) of a PLY mesh.

    Binary little-endian PLY with triangle faces is read directly (fast: a city scene has
    thousands of small files); anything else is read with trimesh (polygons triangulated).
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            data = f.read()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the mesh ({e.strerror}); check the XML scene's filename") from None
    end = data.find(b"end_header\n")
    if data.startswith(b"ply") and end > 0:
        head = data[:end].decode("ascii", "replace").splitlines()
        if "format binary_little_endian 1.0" in head:
            tri = _read_binary_ply(head, data[end + len(b"end_header\n"):])
            if tri is not None:
                return tri
    import trimesh

    m = trimesh.load(p, process=False, force="mesh")
    return np.asarray(m.vertices, float)[np.asarray(m.faces, np.int64)].reshape(-1, 3, 3)


def _read_binary_ply(head: list[str], body: bytes) -> np.ndarray | None:
    elems: list[tuple[str, int, list[list[str]]]] = []
    for line in head:
        w = line.split()
        if w[:1] == ["element"]:
            elems.append((w[1], int(w[2]), []))
        elif w[:1] == ["property"] and elems:
            elems[-1][2].append(w[1:])
    if [e[0] for e in elems[:2]] != ["vertex", "face"] or len(elems) != 2:
        return None
    (_, nv, vprops), (_, nf, fprops) = elems
    if any(pr[0] == "list" for pr in vprops) or len(fprops) != 1 or fprops[0][0] != "list":
        return None
    vdt = np.dtype([(pr[1], "<" + _PLY_TYPES[pr[0]]) for pr in vprops])
    verts = np.frombuffer(body, vdt, count=nv)
    xyz = np.stack([verts["x"], verts["y"], verts["z"]], axis=1).astype(float)
    ct, it = _PLY_TYPES[fprops[0][1]], _PLY_TYPES[fprops[0][2]]
    fdt = np.dtype([("n", "<" + ct), ("v", "<" + it, (3,))])
    rest = body[vdt.itemsize * nv:]
    if len(rest) < fdt.itemsize * nf:
        return None
    faces = np.frombuffer(rest, fdt, count=nf)
    if nf and not np.all(faces["n"] == 3):
        return None
    return xyz[faces["v"].astype(np.int64)]


# ====================================================================== geometry
@dataclass
class StaticGeometry:
    """Static triangles of a scene.

    ``triangles (T, 3, 3)`` m, global frame; ``obj (T,)`` index into ``names``; ``kind[i]`` of
    object ``i``: ``"xml"`` (a shape of the external scene), ``"building"``, ``"scatterer"`` or
    ``"ground"`` (the scenario's own).
    """

    triangles: np.ndarray
    obj: np.ndarray
    names: tuple[str, ...]
    kind: tuple[str, ...]
    cell: float = 4.0
    _grid: dict = field(default_factory=dict, repr=False)

    @property
    def has_ground(self) -> bool:
        """True if anything can be under a vehicle (an external scene or a scenario ground)."""
        return any(k in ("xml", "ground") for k in self.kind)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo (3,), hi (3,))`` of all triangles, m."""
        t = self.triangles.reshape(-1, 3)
        return t.min(axis=0), t.max(axis=0)

    # ------------------------------------------------------------------ vertical rays
    def _plan_index(self) -> dict:
        if "tri" in self._grid:
            return self._grid
        tri = self.triangles
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
        keep = np.flatnonzero(np.abs(det) > 1e-12)  # triangles with an area in plan
        lo = tri[keep, :, :2].min(axis=1)
        hi = tri[keep, :, :2].max(axis=1)
        origin = lo.min(axis=0) if len(keep) else np.zeros(2)
        i0 = np.floor((lo - origin) / self.cell).astype(np.int64)
        i1 = np.floor((hi - origin) / self.cell).astype(np.int64)
        nx = int(i1[:, 0].max() + 1) if len(keep) else 1
        ny = int(i1[:, 1].max() + 1) if len(keep) else 1
        span = (i1 - i0 + 1)
        cnt = span[:, 0] * span[:, 1]
        rep = np.repeat(np.arange(len(keep)), cnt)
        local = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        cx = i0[rep, 0] + local % span[rep, 0]
        cy = i0[rep, 1] + local // span[rep, 0]
        cid = cx * ny + cy
        order = np.argsort(cid, kind="stable")
        starts = np.searchsorted(cid[order], np.arange(nx * ny + 1))
        self._grid.update({"tri": keep[rep[order]], "starts": starts, "origin": origin, "nx": nx, "ny": ny,
                           "det": det})
        return self._grid

    def vertical_hits(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All crossings of the vertical lines through ``xy (n, 2)`` with the triangles.

        Returns ``(point (h,), z (h,), tri (h,))``: the query index, the height (m) and the
        triangle of each crossing (a point on a shared edge may report both triangles).
        """
        xy = np.asarray(xy, float).reshape(-1, 2)
        g = self._plan_index()
        if not len(g["tri"]):
            e = np.zeros(0, np.int64)
            return e, np.zeros(0), e
        ij = np.floor((xy - g["origin"]) / self.cell).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < g["nx"]) & (ij[:, 1] < g["ny"])
        cid = np.where(inside, ij[:, 0] * g["ny"] + ij[:, 1], 0)
        s0 = np.where(inside, g["starts"][cid], 0)
        s1 = np.where(inside, g["starts"][cid + 1], 0)
        cnt = s1 - s0
        pt = np.repeat(np.arange(len(xy)), cnt)
        k = np.repeat(s0 - (np.cumsum(cnt) - cnt), cnt) + np.arange(cnt.sum())
        t = g["tri"][k]
        tri = self.triangles[t]
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        p = xy[pt]
        det = g["det"][t]
        l1 = ((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1])) / det
        l2 = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (p[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
        eps = 1e-12
        hit = (l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1 + eps)
        z = a[:, 2] + l1 * (b[:, 2] - a[:, 2]) + l2 * (c[:, 2] - a[:, 2])
        return pt[hit], z[hit], t[hit]

    def height_map(self, xy: np.ndarray, below: float | np.ndarray = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Highest surface at or below height ``below`` (scalar or ``(n,)``) over each point: ``(z (n,), obj (n,))``.

        ``z`` is NaN and ``obj`` -1 where no surface is below (off the map).
        """
        xy = np.asarray(xy, float).reshape(-1, 2)
        pt, z, t = self.vertical_hits(xy)
        sel = z <= np.broadcast_to(np.asarray(below, float), (len(xy),))[pt]
        pt, z, t = pt[sel], z[sel], t[sel]
        out = np.full(len(xy), -np.inf)
        np.maximum.at(out, pt, z)
        obj = np.full(len(xy), -1, np.int64)
        top = z == out[pt]
        obj[pt[top]] = self.obj[t[top]]
        return np.where(np.isfinite(out), out, np.nan), obj

    def lowest_above(self, xy: np.ndarray, z0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lowest surface strictly above ``z0 (n,)`` over each point: ``(z (n,), obj (n,))`` (NaN / -1: none)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        z0 = np.broadcast_to(np.asarray(z0, float), (len(xy),))
        pt, z, t = self.vertical_hits(xy)
        sel = z > z0[pt]
        pt, z, t = pt[sel], z[sel], t[sel]
        out = np.full(len(xy), np.inf)
        np.minimum.at(out, pt, z)
        obj = np.full(len(xy), -1, np.int64)
        low = z == out[pt]
        obj[pt[low]] = self.obj[t[low]]
        return np.where(np.isfinite(out), out, np.nan), obj

    # ------------------------------------------------------------------ segments
    def segments_blocked(self, a: np.ndarray, b: np.ndarray, exclude_obj: np.ndarray | None = None,
                         margin: float = 1e-3) -> np.ndarray:
        """Whether each segment ``a (n, 3) -> b (n, 3)`` crosses a triangle, ``(n,)`` bool.

        Vectorised over (segment, triangle) pairs from a plan grid (:meth:`_segment_index`).

        The first and last ``margin`` m of each segment are ignored (a path touching the
        surface it reflects on, or an antenna on a surface, is not blocked by it);
        ``exclude_obj (n,)`` (-1: none) is an object each segment may cross (a scatterer's own mesh).
        """
        a = np.asarray(a, float).reshape(-1, 3)
        b = np.asarray(b, float).reshape(-1, 3)
        n = len(a)
        out = np.zeros(n, bool)
        if n == 0 or not len(self.triangles):
            return out
        ex = np.full(n, -1, np.int64) if exclude_obj is None else np.asarray(exclude_obj, np.int64)
        g = self._segment_index()
        c = g["cell"]
        # sample each segment's plan projection every c / 2: a triangle registered in the cells of its
        # plan bounding box grown by one cell is then in the cell of some sample of every segment it crosses
        L = np.hypot(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1])
        ns = np.maximum(2, np.ceil(L / (c / 2)).astype(np.int64) + 1)
        seg = np.repeat(np.arange(n), ns)
        f = (np.arange(ns.sum()) - np.repeat(np.cumsum(ns) - ns, ns)) / np.repeat(ns - 1, ns)
        pxy = a[seg, :2] + f[:, None] * (b[seg, :2] - a[seg, :2])
        ij = np.floor((pxy - g["origin"]) / c).astype(np.int64)
        ok = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < g["nx"]) & (ij[:, 1] < g["ny"])
        seg, cid = seg[ok], ij[ok, 0] * g["ny"] + ij[ok, 1]
        sc = _unique_ints(seg * (g["nx"] * g["ny"]) + cid)
        seg, cid = sc // (g["nx"] * g["ny"]), sc % (g["nx"] * g["ny"])
        s0, s1 = g["starts"][cid], g["starts"][cid + 1]
        cnt = s1 - s0
        sp = np.repeat(seg, cnt)
        k = np.repeat(s0 - (np.cumsum(cnt) - cnt), cnt) + np.arange(cnt.sum())
        pair = _unique_ints(sp * len(self.triangles) + g["tri"][k])
        sp, t = pair // len(self.triangles), pair % len(self.triangles)
        keep = self.obj[t] != ex[sp]
        sp, t = sp[keep], t[keep]
        tri = self.triangles[t]
        d = b[sp] - a[sp]
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        pv = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        good = np.abs(det) > 1e-15
        inv = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)
        tv = a[sp] - tri[:, 0]
        u = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        v = np.einsum("ij,ij->i", d, qv) * inv
        s = np.einsum("ij,ij->i", e2, qv) * inv
        m = margin / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
        hit = good & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > m) & (s < 1 - m)
        out[sp[hit]] = True
        return out

    def _segment_index(self) -> dict:
        """Plan grid (cells of ``4 * self.cell`` m) -> triangles whose plan bbox, grown by a cell, meets it."""
        if "seg" in self._grid:
            return self._grid["seg"]
        c = 4.0 * self.cell
        tri = self.triangles
        lo = tri[:, :, :2].min(axis=1)
        hi = tri[:, :, :2].max(axis=1)
        origin = lo.min(axis=0) - 2 * c
        i0 = np.floor((lo - origin) / c).astype(np.int64) - 1
        i1 = np.floor((hi - origin) / c).astype(np.int64) + 1
        nx, ny = int(i1[:, 0].max() + 3), int(i1[:, 1].max() + 3)
        span = i1 - i0 + 1
        cnt = span[:, 0] * span[:, 1]
        rep = np.repeat(np.arange(len(tri)), cnt)
        local = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        cid = (i0[rep, 0] + local % span[rep, 0]) * ny + (i0[rep, 1] + local // span[rep, 0])
        order = np.argsort(cid, kind="stable")
        self._grid["seg"] = {"tri": rep[order], "starts": np.searchsorted(cid[order], np.arange(nx * ny + 1)),
                             "origin": origin, "nx": nx, "ny": ny, "cell": c}
        return self._grid["seg"]


def _unique_ints(x: np.ndarray) -> np.ndarray:
    """The sorted distinct values of a 1-D integer array, as ``np.unique(x)``, by one sort: NumPy 2.3+'s hash-based
    ``np.unique`` is 20-50x slower on the 10^5-10^6 (segment, cell) and (segment, triangle) keys here."""
    s = np.sort(np.asarray(x).reshape(-1))
    return s[np.concatenate(([True], s[1:] != s[:-1]))] if s.size else s


# ====================================================================== building it
def _xml_shapes(path: Path) -> list[tuple[str, Path]]:
    """(object name, mesh file) of every top-level shape of a Mitsuba XML scene."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise ConfigError(f"{path}: not valid XML ({e}); fix or replace the file") from None
    out = []
    for el in root:
        if el.tag != "shape":
            continue
        sid = el.get("id", "")
        name = sid[5:] if sid.startswith("mesh-") else sid
        if el.get("type") not in ("ply", "obj"):
            raise ConfigError(f"{path}: shape '{sid}' of type '{el.get('type')}': only ply / obj meshes are "
                              "supported for collision checks and street maps; convert it to a mesh")
        if el.find("transform") is not None:
            raise ConfigError(f"{path}: shape '{sid}' has a <transform>; bake it into the mesh (only meshes in "
                              "world coordinates are supported)")
        fn = next((s.get("value", "") for s in el.iter("string") if s.get("name") == "filename"), "")
        f = Path(fn) if os.path.isabs(fn) else path.parent / fn
        out.append((name, f))
    return out


_XML_CACHE: dict[tuple[str, float], StaticGeometry] = {}


def xml_geometry(spec: str, source_file: str = "<memory>") -> StaticGeometry:
    """Triangles of an external XML scene (``sionna:<name>`` or a path relative to ``source_file``'s folder).

    Kept in memory per file and modification time (read-only: do not modify the arrays).
    """
    from mmslam.scenes.meshes import resolve_xml_scene

    base = None if source_file.startswith(("<", "preset:")) else Path(source_file).parent
    path = resolve_xml_scene(spec, base)
    key = (str(path), path.stat().st_mtime)
    if key not in _XML_CACHE:
        tris, objs, names = [], [], []
        for name, f in _xml_shapes(path):
            t = read_ply_triangles(f) if f.suffix.lower() == ".ply" else _trimesh_triangles(f)
            objs.append(np.full(len(t), len(names), np.int64))
            tris.append(t)
            names.append(name)
        if not tris:
            g = StaticGeometry(np.zeros((0, 3, 3)), np.zeros(0, np.int64), (), ())
        else:
            g = StaticGeometry(np.concatenate(tris), np.concatenate(objs), tuple(names), ("xml",) * len(names))
        _XML_CACHE.clear()
        _XML_CACHE[key] = g
    return _XML_CACHE[key]


def static_geometry(scn: Scenario, include_scenario: bool = True) -> StaticGeometry:
    """Every static triangle of ``scn``'s scene (external XML shapes + buildings, scatterers, ground)."""
    from mmslam.scenes.meshes import box_mesh, ground_mesh, scatterer_mesh

    tris, objs, names, kinds = [], [], [], []

    def add(name: str, kind: str, t: np.ndarray) -> None:
        t = np.asarray(t, float).reshape(-1, 3, 3)
        objs.append(np.full(len(t), len(names), np.int64))
        tris.append(t)
        names.append(name)
        kinds.append(kind)

    if scn.xml_scene:
        x = xml_geometry(scn.xml_scene, scn.source_file)
        for o, name in enumerate(x.names):
            add(name, "xml", x.triangles[x.obj == o])
    if include_scenario:
        for b in scn.buildings:
            m = box_mesh(np.asarray(b.min), np.asarray(b.max))
            add(b.name, "building", np.asarray(m.vertices)[np.asarray(m.faces)])
        for s in scn.scatterers:
            m = scatterer_mesh(s)
            add(s.name, "scatterer", np.asarray(m.vertices)[np.asarray(m.faces)])
        if scn.ground is not None:
            m = ground_mesh(scn.ground.z, scn.ground.extent)
            add("ground", "ground", np.asarray(m.vertices)[np.asarray(m.faces)])
    if not tris:
        return StaticGeometry(np.zeros((0, 3, 3)), np.zeros(0, np.int64), (), ())
    if not include_scenario and scn.xml_scene:
        return xml_geometry(scn.xml_scene, scn.source_file)  # the cached object, its grids included
    return StaticGeometry(np.concatenate(tris), np.concatenate(objs), tuple(names), tuple(kinds))


def _trimesh_triangles(f: Path) -> np.ndarray:
    import trimesh

    if not f.is_file():
        raise ConfigError(f"{f}: mesh file not found; check the XML scene's filename")
    m = trimesh.load(f, process=False, force="mesh")
    return np.asarray(m.vertices, float)[np.asarray(m.faces, np.int64)]


# ====================================================================== vehicle poses
TERRAIN_TOL_M = 0.25
"""How far (m) the bottom of a car body may sink below the surface under its antenna."""


def footprint_points(v, state: np.ndarray) -> np.ndarray:
    """Nine plan points ``(9, 2)`` of a car's footprint (corners, edge midpoints, centre) at ``state``."""
    x, y, h = float(state[0]), float(state[1]), float(state[3])
    fx, fy = np.meshgrid([-0.5, 0.0, 0.5], [-0.5, 0.0, 0.5])
    lx, ly = fx.ravel() * v.length, fy.ravel() * v.width
    c, s = np.cos(h), np.sin(h)
    return np.stack([x + c * lx - s * ly, y + s * lx + c * ly], axis=1)


def check_vehicle_poses(scn: Scenario, states: np.ndarray, geom: StaticGeometry | None = None) -> None:
    """Raise a one-line :class:`ConfigError` at the first car pose that collides with the scene.

    ``states (steps, n_vehicles, 7)``. For every vehicle and step, over the nine footprint points
    (:func:`footprint_points`) of its body (``z`` from ``antenna z - roof_gap - height`` to
    ``antenna z - roof_gap``):

    - *below the terrain*: the surface under the antenna is more than ``TERRAIN_TOL_M`` above
      the body's bottom;
    - *inside an object*: the vertical line upwards from the body's mid-height crosses one
      object's triangles an odd number of times (the point is inside that closed mesh; a roof
      over an open-bottomed building counts too; a bridge deck over the car does not);
    - *off the map* (scenes with an external XML or a ground only): no surface under the antenna.
    """
    states = np.asarray(states, float)
    geom = static_geometry(scn) if geom is None else geom
    if not len(geom.triangles):
        return
    steps, nv = states.shape[:2]
    for i, v in enumerate(scn.vehicles):
        st = states[:, i]
        bottom = st[:, 2] - v.roof_gap - v.height
        zu, ou = geom.height_map(st[:, :2], below=st[:, 2] - v.roof_gap)  # the road under the antenna
        sunk = np.flatnonzero(np.nan_to_num(zu, nan=-np.inf) > bottom + TERRAIN_TOL_M)
        if sunk.size:
            k = int(sunk[0])
            raise ConfigError(f"{scn.source_file}: vehicle '{v.name}' at step {k} (x={st[k, 0]:.1f}, y={st[k, 1]:.1f}) "
                              f"is {zu[k] - bottom[k]:.2f} m below the surface of object '{geom.names[ou[k]]}' "
                              f"(z = {zu[k]:.2f} m); raise its antenna height z or let it follow the terrain")
        inside = vehicle_inside(geom, v, st)
        if inside is not None:
            k, obj = inside
            raise ConfigError(f"{scn.source_file}: vehicle '{v.name}' at step {k} (x={st[k, 0]:.1f}, y={st[k, 1]:.1f}) "
                              f"is inside object '{obj}' of the scene; move its route onto a street "
                              "(mmslam scene streets shows them)")
        if geom.has_ground:
            off = np.flatnonzero(np.isnan(zu))
            if off.size:
                k = int(off[0])
                raise ConfigError(f"{scn.source_file}: vehicle '{v.name}' at step {k} (x={st[k, 0]:.1f}, "
                                  f"y={st[k, 1]:.1f}) is off the map (no ground under it); keep its route inside "
                                  "the scene")


def points_inside(geom: StaticGeometry, points: np.ndarray) -> np.ndarray:
    """Object that encloses each point ``(n, 3)`` (m): ``(n,)`` index into ``geom.names``, -1 for none.

    A point is inside an object when the vertical line upwards from it crosses that object's
    triangles an odd number of times (a closed mesh around it; a roof over an open-bottomed
    building counts too; a slab such as a bridge deck above it, crossed twice, does not). A
    crossing reported twice on an edge shared by two triangles of the object counts once (same
    height to 1e-6 m). Of several enclosing objects the first in ``geom.names`` is returned.
    """
    p = np.asarray(points, float).reshape(-1, 3)
    out = np.full(len(p), -1, np.int64)
    if not len(p) or not len(geom.triangles):
        return out
    pt, z, t = geom.vertical_hits(p[:, :2])
    above = z > p[pt, 2]
    pt, z, o = pt[above], z[above], geom.obj[t[above]]
    if not pt.size:
        return out
    # one crossing per (point, object, height): an edge shared by two triangles reports both
    crossing = np.unique(np.stack([pt, o, np.round(z * 1e6).astype(np.int64)], axis=1), axis=0)
    key, cnt = np.unique(crossing[:, 0] * len(geom.names) + crossing[:, 1], return_counts=True)
    odd = key[cnt % 2 == 1]
    first = np.unique(odd // len(geom.names), return_index=True)
    out[first[0]] = odd[first[1]] % len(geom.names)
    return out


def vehicle_inside(geom: StaticGeometry, v, states: np.ndarray) -> tuple[int, str] | None:
    """First step ``k`` and object name at which a car's body is inside an object, or None.

    ``states (steps, 7)`` of vehicle ``v``; the nine footprint points (:func:`footprint_points`)
    at the body's mid-height are tested with :func:`points_inside`.
    """
    st = np.asarray(states, float)
    if not len(geom.triangles) or not len(st):
        return None
    pts = np.concatenate([footprint_points(v, st[k]) for k in range(len(st))])  # (steps * 9, 2)
    zmid = st[:, 2] - v.roof_gap - v.height / 2.0
    obj = points_inside(geom, np.concatenate([pts, np.repeat(zmid, 9)[:, None]], axis=1))
    hit = np.flatnonzero(obj >= 0)
    if not hit.size:
        return None
    return int(hit[0] // 9), geom.names[int(obj[hit[0]])]


def bs_inside(scn: Scenario, geom: StaticGeometry | None = None) -> str | None:
    """Name of the object (building, scatterer, shape of the XML scene, the ground) that encloses the BS, or None."""
    geom = static_geometry(scn) if geom is None else geom
    o = int(points_inside(geom, np.asarray(scn.bs, float)[None])[0])
    return None if o < 0 else geom.names[o]


def check_bs_position(scn: Scenario, geom: StaticGeometry | None = None) -> None:
    """One-line :class:`ConfigError` if the BS antenna is inside an object of the scene (:func:`bs_inside`).

    Sionna would still trace a line-of-sight path out of a closed mesh (its rays start inside
    and leave through the back faces), so the cache would look plausible and be wrong.
    """
    obj = bs_inside(scn, geom)
    if obj is not None:
        what = "below the ground" if obj == "ground" else f"inside object '{obj}' of the scene"
        raise ConfigError(f"{scn.source_file}: the BS {[float(c) for c in scn.bs]} is {what}; put it on a roof "
                          "(above the top surface: mmslam scene streets draws the heights) or in the open")


def vehicle_overlaps(scn: Scenario, states: np.ndarray) -> tuple[int, int, int] | None:
    """First ``(step, i, j)`` at which the bodies of vehicles ``i < j`` overlap, or None.

    ``states (steps, n_vehicles, >=4)``. A body is the box ``length x width`` centred on the
    antenna's plan position, turned by the heading, from ``z - roof_gap - height`` to
    ``z - roof_gap``; two boxes overlap when their height ranges overlap and no axis of the two
    rectangles separates them in plan (separating-axis test). Touching is not overlapping.
    """
    st = np.asarray(states, float)
    vs = scn.vehicles
    first = None
    for i in range(len(vs)):
        for j in range(i + 1, len(vs)):
            a, b = st[:, i], st[:, j]
            d = b[:, :2] - a[:, :2]
            ua = np.stack([np.cos(a[:, 3]), np.sin(a[:, 3])], axis=1)
            ub = np.stack([np.cos(b[:, 3]), np.sin(b[:, 3])], axis=1)
            va, vb = ua[:, ::-1] * [-1.0, 1.0], ub[:, ::-1] * [-1.0, 1.0]

            def r(u, w, veh, ax):  # half-width of a body's projection on axis ax
                return 0.5 * veh.length * np.abs(np.einsum("ij,ij->i", u, ax)) + \
                    0.5 * veh.width * np.abs(np.einsum("ij,ij->i", w, ax))

            sep = np.zeros(len(st), bool)
            for ax in (ua, va, ub, vb):
                sep |= np.abs(np.einsum("ij,ij->i", d, ax)) >= r(ua, va, vs[i], ax) + r(ub, vb, vs[j], ax)
            ta, tb = a[:, 2] - vs[i].roof_gap, b[:, 2] - vs[j].roof_gap
            sep |= (ta - vs[i].height >= tb) | (tb - vs[j].height >= ta)
            k = np.flatnonzero(~sep)
            if k.size and (first is None or int(k[0]) < first[0]):
                first = (int(k[0]), i, j)
    return first


def check_vehicle_overlaps(scn: Scenario, states: np.ndarray) -> None:
    """One-line :class:`ConfigError` naming the first two vehicles whose bodies overlap (:func:`vehicle_overlaps`)."""
    hit = vehicle_overlaps(scn, states)
    if hit is None:
        return
    k, i, j = hit
    a, b = np.asarray(states, float)[k, [i, j], :2]
    fix = ("draw other routes: change the scenario's seed or n_vehicles"
           if all(scn.vehicles[q].name.startswith("car_0") for q in (i, j)) else
           "move one route to another lane or street, or change a speed or start")
    raise ConfigError(f"{scn.source_file}: vehicles '{scn.vehicles[i].name}' and '{scn.vehicles[j].name}' overlap "
                      f"at step {k} (x={a[0]:.1f}, y={a[1]:.1f} and x={b[0]:.1f}, y={b[1]:.1f}); {fix}")


def inside_report(scn: Scenario, states: np.ndarray, geom: StaticGeometry | None = None) -> list[tuple[str, int, str, np.ndarray]]:
    """What sits inside an object of the scene: ``[(who, step, object, xyz (3,)), ...]``.

    ``who`` is ``"BS"`` (step -1) or a vehicle name (the first step its body is inside,
    :func:`vehicle_inside`); ``states (steps, n_vehicles, 7)``. Empty when all is in the open.
    """
    geom = static_geometry(scn) if geom is None else geom
    out = []
    obj = bs_inside(scn, geom)
    if obj is not None:
        out.append(("BS", -1, obj, np.asarray(scn.bs, float)))
    st = np.asarray(states, float)
    for i, v in enumerate(scn.vehicles):
        hit = vehicle_inside(geom, v, st[:, i])
        if hit is not None:
            out.append((v.name, hit[0], hit[1], st[hit[0], i, :3]))
    return out
