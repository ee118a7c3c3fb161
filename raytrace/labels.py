"""Label traced paths as BS / VA / SP / VS / OTHER and reduce diffuse clusters (pure NumPy).

Input: per-path arrays from a ray tracer (one row per traced path and receiver), with the
objects hit per bounce given as indices into a list of object names. Output: the ``paths``
table columns of :mod:`mmslam.raytrace.schema` (global frame, metres, radians).

Rules (``D`` = number of non-empty bounce slots of a path):

- any bounce on the receiving vehicle's own car body: path dropped;
- ``D == 0``: BS (line of sight), landmark the BS position, id ``bs``;
- ``D == 1`` specular on a scenario building: VA, face chosen as the box face whose plane is
  nearest the bounce point, id ``<building>:<face>`` (e.g. ``wall_east:-x``), landmark the BS
  mirrored in that face plane;
- ``D == 1`` specular on the ground: VA ``ground:+z``;
- ``D == 1`` specular on a static object of an external XML scene (no box known): VA by the
  plane through the bounce point with the hit triangle's normal; id
  ``<object>:plane(<nx>,<ny>,<nz>,<d>)`` with the normal (oriented towards the BS) rounded to
  1e-3 and the plane offset ``d = n . p`` rounded to 1 cm; landmark the BS mirrored in the plane;
- ``D == 1`` (specular or diffuse) on a scatterer: SP, id its name, landmark its reference point;
- ``D == 1`` (specular or diffuse) on another vehicle: VS, id that vehicle's name, landmark
  that vehicle's antenna position at this step;
- ``D == 2``, both bounces specular on static planar surfaces (box faces, the ground, XML planes,
  identified as above) and not the same plane twice: VA of order 2 (``bounces`` = 2), landmark the
  image of an image (the BS mirrored in the first plane, then in the second), id
  ``<first>|<second>`` (each as for a single bounce, e.g. ``wall_east:-x|wall_west:+x``);
- anything else (``D >= 3``, a diffuse bounce on a static object or a car / scatterer in a
  double bounce, refraction, an unknown object): OTHER, id the ``+``-joined object names,
  landmark NaN.

Paths sharing (receiver, type, landmark id) are one resolvable landmark: the row keeps the
strongest path (highest power; ties: shortest TOA) with ``n_paths`` and ``delay_spread_m``
(max - min TOA) of the cluster, its ``doppler_hz`` and its ``ray`` number (the link to the
``rays`` table). With ``return_rays=True`` the per-ray labels come back too: every input ray keeps
a (type, landmark id); rays dropped from ``paths`` (own car body) are OTHER with the ``+``-joined
object names.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmslam.raytrace.schema import PATH_COLUMNS, empty_paths, ray_numbers, sort_paths, tx_position_columns
from mmslam.scenes.landmarks import FACES
from mmslam.scenes.scenario import Scenario
from mmslam.model import BS, OTHER, SP, VA, VS, mirror_point

# interaction codes (Sionna's InteractionType bit values)
NONE, SPECULAR, DIFFUSE = 0, 1, 2

# object kinds
K_BUILDING, K_GROUND, K_SCATTERER, K_VEHICLE, K_STATIC = 0, 1, 2, 3, 4

_FACE_TAGS = list(FACES)  # "+x", "-x", "+y", "-y", "+z", "-z"
_NORMAL_Q = 1e4  # normal quantization (1e-4)
_OFFSET_Q = 1e3  # plane offset quantization (1 mm)


@dataclass(frozen=True)
class SceneIndex:
    """What the labeller needs to know about every object name the tracer can report.

    ``names[i]`` is object ``i``; ``kind[i]`` its kind (building, ground, scatterer, vehicle,
    other static); ``box_lo/box_hi`` the building boxes (NaN otherwise); ``ref[i]`` the
    scatterer reference point (NaN otherwise); ``vehicle[i]`` the vehicle index (-1 otherwise).
    ``ground_z`` the ground height (NaN if none). ``bs`` the BS position (m).
    """

    names: tuple[str, ...]
    kind: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    ref: np.ndarray
    vehicle: np.ndarray
    ground_z: float
    bs: np.ndarray
    planes: "PlaneTable | None" = None

    @classmethod
    def from_scenario(cls, scn: Scenario, extra_static: list[str] | tuple[str, ...] = (),
                      planes: "PlaneTable | None" = None) -> "SceneIndex":
        """Index of a scenario's objects plus ``extra_static`` names (objects of an external XML).

        ``planes``: the plane table of the static triangles (:func:`plane_table`), if known.
        """
        names: list[str] = []
        kind, lo, hi, ref, veh = [], [], [], [], []
        nan3 = np.full(3, np.nan)
        for b in scn.buildings:
            names.append(b.name); kind.append(K_BUILDING)
            lo.append(np.asarray(b.min, float)); hi.append(np.asarray(b.max, float)); ref.append(nan3); veh.append(-1)
        for s in scn.scatterers:
            names.append(s.name); kind.append(K_SCATTERER)
            lo.append(nan3); hi.append(nan3); ref.append(np.asarray(s.position, float)); veh.append(-1)
        if scn.ground is not None:
            names.append("ground"); kind.append(K_GROUND)
            lo.append(nan3); hi.append(nan3); ref.append(nan3); veh.append(-1)
        for i, v in enumerate(scn.vehicles):
            names.append(v.name); kind.append(K_VEHICLE)
            lo.append(nan3); hi.append(nan3); ref.append(nan3); veh.append(i)
        for n in extra_static:
            if n in names:
                continue
            names.append(n); kind.append(K_STATIC)
            lo.append(nan3); hi.append(nan3); ref.append(nan3); veh.append(-1)
        return cls(tuple(names), np.asarray(kind, np.int64), np.asarray(lo).reshape(-1, 3),
                   np.asarray(hi).reshape(-1, 3), np.asarray(ref).reshape(-1, 3), np.asarray(veh, np.int64),
                   float(scn.ground.z) if scn.ground is not None else float("nan"), scn.bs_array, planes)

    def index_of(self, names: list[str] | np.ndarray) -> np.ndarray:
        """Object names -> indices (-1 for names not in the index)."""
        lut = {n: i for i, n in enumerate(self.names)}
        return np.asarray([lut.get(str(n), -1) for n in names], np.int64)


@dataclass(frozen=True)
class PlaneTable:
    """Distinct planes of a set of static triangles (see :func:`plane_table`).

    ``normal (P, 3)`` unit normals oriented towards the BS, ``offset (P,)`` plane offsets
    ``d = n . x`` (m), ``ids`` the landmark ids ``plane(nx,ny,nz,d)``; ``tri_plane (T,)`` the
    plane of each input triangle (-1: degenerate triangle), ``tri_normal (T, 3)`` the plane
    normal per triangle (NaN for degenerate ones): what a tracer passes to :func:`label_paths`
    as a hit triangle's normal, so that the labeller finds the plane by exact lookup.
    """

    normal: np.ndarray
    offset: np.ndarray
    ids: tuple[str, ...]
    tri_plane: np.ndarray
    tri_normal: np.ndarray

    def lookup(self, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
        """Plane index of hits with table normals ``normal (n, 3)`` at points ``point (n, 3)``.

        Among the planes with exactly that normal, the one whose offset is nearest ``n . point``;
        -1 where no plane has that normal.
        """
        out = np.full(len(normal), -1, np.int64)
        if not len(normal) or not len(self.normal):
            return out
        un, inv = np.unique(normal, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        for j, nv in enumerate(un):
            cand = np.flatnonzero(np.all(self.normal == nv, axis=1))
            if not cand.size:
                continue
            rows = np.flatnonzero(inv == j)
            d = point[rows] @ nv
            out[rows] = cand[np.argmin(np.abs(d[:, None] - self.offset[cand][None, :]), axis=1)]
        return out


def _plane_id(cell: np.ndarray) -> str:
    return (f"plane({cell[0] / _NORMAL_Q:+.4f},{cell[1] / _NORMAL_Q:+.4f},{cell[2] / _NORMAL_Q:+.4f},"
            f"{cell[3] / _OFFSET_Q:+.3f})")


def plane_table(triangles: np.ndarray, bs: np.ndarray) -> PlaneTable:
    """Group triangles ``(T, 3, 3)`` (m, global frame) by the plane they lie in.

    Each triangle's normal is oriented towards the BS ``bs (3,)`` and quantized with its offset
    into a cell (normal to 1e-4, offset to 1 mm: float32 vertices of a city scene are coplanar to
    about 1e-5). Cells are taken in order of decreasing triangle
    area (ties: cell order); each cell not yet taken starts a plane and takes every untaken cell
    within one quantum in all four coordinates, so a plane whose offset sits on a rounding
    boundary is still one plane. A plane's normal and offset are the area-weighted means of its
    triangles'; its id is formatted from its first cell (ids are unique). Deterministic.
    """
    tri = np.asarray(triangles, float).reshape(-1, 3, 3)
    bs = np.asarray(bs, float)
    nv = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(nv, axis=1)
    ok = area2 > 1e-12 * np.maximum(1.0, np.max(np.abs(tri), axis=(1, 2))) ** 2
    T = len(tri)
    tri_plane = np.full(T, -1, np.int64)
    tri_normal = np.full((T, 3), np.nan)
    if not np.any(ok):
        return PlaneTable(np.zeros((0, 3)), np.zeros(0), (), tri_plane, tri_normal)
    idx = np.flatnonzero(ok)
    n = nv[idx] / area2[idx, None]
    c = tri[idx].mean(axis=1)
    n = np.where((np.sum((bs - c) * n, axis=1) < 0)[:, None], -n, n)
    d = np.sum(n * c, axis=1)
    cells = np.concatenate([np.round(n * _NORMAL_Q), np.round(d * _OFFSET_Q)[:, None]], axis=1).astype(np.int64)
    ucell, inv = np.unique(cells, axis=0, return_inverse=True)  # rows sorted lexicographically
    inv = inv.reshape(-1)
    w = np.bincount(inv, weights=area2[idx], minlength=len(ucell))
    order = np.lexsort(tuple(ucell[:, k] for k in range(3, -1, -1)) + (-w,))

    def code(c: np.ndarray) -> np.ndarray:  # one opaque, sortable value per cell
        return np.ascontiguousarray(c, dtype=">i8").view(np.dtype((np.void, 32))).reshape(-1)

    srt = np.argsort(code(ucell))
    codes = code(ucell)[srt]
    offs = np.array(np.meshgrid(*([[-1, 0, 1]] * 4), indexing="ij")).reshape(4, -1).T
    nb = np.empty((len(ucell), len(offs)), np.int64)  # neighbouring cells (-1: none)
    for j, o in enumerate(offs):
        c2 = code(ucell + o)
        pos = np.minimum(np.searchsorted(codes, c2), len(codes) - 1)
        nb[:, j] = np.where(codes[pos] == c2, srt[pos], -1)
    owner = np.full(len(ucell), -1, np.int64)
    seeds = []
    for u in order:
        if owner[u] >= 0:
            continue
        cand = nb[u][nb[u] >= 0]
        owner[cand[owner[cand] < 0]] = len(seeds)
        seeds.append(u)
    plane_of = owner[inv]
    P = len(seeds)
    wa = area2[idx]
    sn = np.zeros((P, 3))
    np.add.at(sn, plane_of, n * wa[:, None])
    normal = sn / np.linalg.norm(sn, axis=1, keepdims=True)
    offset = np.bincount(plane_of, weights=d * wa, minlength=P) / np.bincount(plane_of, weights=wa, minlength=P)
    tri_plane[idx] = plane_of
    tri_normal[idx] = normal[plane_of]
    ids = tuple(_plane_id(ucell[u]) for u in seeds)
    return PlaneTable(normal, offset, ids, tri_plane, tri_normal)


def _box_face(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Index into ``FACES`` of the box face whose plane is nearest each point ``p (n, 3)``."""
    d = np.stack([np.abs(p[:, 0] - hi[:, 0]), np.abs(p[:, 0] - lo[:, 0]),
                  np.abs(p[:, 1] - hi[:, 1]), np.abs(p[:, 1] - lo[:, 1]),
                  np.abs(p[:, 2] - hi[:, 2]), np.abs(p[:, 2] - lo[:, 2])], axis=1)
    return np.argmin(d, axis=1)


def _surfaces(index: SceneIndex, o: np.ndarray, kind: np.ndarray, p: np.ndarray,
              nrm: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The plane of specular bounces on static planar surfaces (one bounce slot of ``m`` paths).

    Args:
        index: the scene's objects.
        o, kind: ``(m,)`` object index and kind (building, ground or other static) of each bounce.
        p: ``(m, 3)`` bounce points, m, global frame.
        nrm: ``(m, 3)`` hit-triangle normals (used for kind "other static"; may be None otherwise).

    Returns:
        ``normal (m, 3)`` unit normal (a box face's outward normal; the ground's +z; an XML plane's
        normal oriented towards the BS), ``point (m, 3)`` a point of the plane (m), ``sub (m, 4)``
        the sub-key (box / ground: the ``FACES`` index in column 0; plane: the quantized normal and
        offset, or ``[-1, -1, -1, row]`` for a plane of ``index.planes``) and ``plane_ix (m,)`` the
        row of ``index.planes`` (-1: none).
    """
    m = o.shape[0]
    normal = np.full((m, 3), np.nan)
    point = np.full((m, 3), np.nan)
    sub = np.zeros((m, 4), np.int64)
    plane_ix = np.full(m, -1, np.int64)
    box = kind == K_BUILDING
    if np.any(box):
        s0 = np.clip(o[box], 0, None)
        lo, hi = index.box_lo[s0], index.box_hi[s0]
        f = _box_face(p[box], lo, hi)
        ax = np.array([FACES[t][0] for t in _FACE_TAGS])[f]
        sg = np.array([FACES[t][1] for t in _FACE_TAGS])[f]
        nv = np.zeros((f.size, 3))
        nv[np.arange(f.size), ax] = sg
        normal[box] = nv
        point[box] = np.where(sg[:, None] > 0, hi, lo)
        sub[box, 0] = f
    gr = kind == K_GROUND
    if np.any(gr):
        normal[gr] = [0.0, 0.0, 1.0]
        point[gr] = [0.0, 0.0, index.ground_z]
        sub[gr, 0] = _FACE_TAGS.index("+z")
    pl = kind == K_STATIC
    if np.any(pl):
        bs = index.bs
        pp = p[pl]
        ix = np.full(pp.shape[0], -1, np.int64)
        if index.planes is not None:
            ix = index.planes.lookup(nrm[pl], pp)
        known = ix >= 0
        nn = nrm[pl]
        nn = nn / np.linalg.norm(nn, axis=1, keepdims=True)
        sgn = np.where(np.sum((bs - pp) * nn, axis=1) < 0, -1.0, 1.0)
        nn = nn * sgn[:, None]
        dd = np.sum(nn * pp, axis=1)
        qsub = np.concatenate([np.round(nn * _NORMAL_Q), np.round(dd * _OFFSET_Q)[:, None]], axis=1).astype(np.int64)
        if np.any(known):
            pk = ix[known]
            nn[known] = index.planes.normal[pk]
            dd[known] = index.planes.offset[pk]
            qsub[known] = [-1, -1, -1, 0]  # table planes are keyed by their row, not by rounding
            qsub[known, 3] = pk
        normal[pl] = nn
        point[pl] = nn * dd[:, None]
        sub[pl] = qsub
        plane_ix[pl] = ix
    return normal, point, sub, plane_ix


def _surface_id(index: SceneIndex, o: int, kind: int, sub: np.ndarray, plane_ix: int) -> str:
    """Landmark id of one planar surface: ``<object>:<face>`` (box, ground) or ``plane(...)``."""
    if kind == K_STATIC:
        return index.planes.ids[plane_ix] if plane_ix >= 0 else _plane_id(sub)
    return f"{index.names[o]}:{_FACE_TAGS[sub[0]]}"


def label_paths(index: SceneIndex, *, rx: np.ndarray, obj: np.ndarray, itype: np.ndarray,
                verts: np.ndarray, toa_m: np.ndarray, angles: np.ndarray, power_db: np.ndarray,
                antennas: np.ndarray, normals: np.ndarray | None = None, step: int = 0,
                doppler_hz: np.ndarray | None = None, ray: np.ndarray | None = None,
                return_rays: bool = False):
    """Label traced paths and keep the strongest path per (receiver, landmark).

    Args:
        index: the scene's objects (:class:`SceneIndex`).
        rx: ``(n,)`` receiving vehicle index per path.
        obj: ``(n, D)`` object index per bounce slot (-1: no interaction in that slot).
        itype: ``(n, D)`` interaction type per slot (0 none, 1 specular, 2 diffuse, other: OTHER).
        verts: ``(n, D, 3)`` interaction points, m, global frame.
        toa_m: ``(n,)`` path length (delay x c), m.
        angles: ``(n, 4)`` ``[aod_az, aod_el, aoa_az, aoa_el]``, rad, global frame.
        power_db: ``(n,)`` path power, dB (NaN if unknown).
        antennas: ``(n_vehicles, 3)`` antenna positions at this step, m.
        normals: ``(n, D, 3)`` unit normals of the hit triangles (needed only for static
            objects of kind "other static"; NaN elsewhere is fine).
        step: time index written to the ``step`` column.
        doppler_hz: ``(n,)`` Doppler shift per path, Hz (NaN if not given).
        ray: ``(n,)`` ray numbers (:func:`~mmslam.raytrace.schema.ray_numbers`; default: by TOA).
        return_rays: also return the per-ray labels.

    Returns:
        The ``paths`` columns (all of :data:`~mmslam.raytrace.schema.PATH_COLUMNS`), sorted; with
        ``return_rays`` a tuple ``(paths, {"type": (n,) int8, "landmark_id": (n,) object})``
        with one label per input ray, in input order.
    """
    rx = np.asarray(rx, np.int64)
    n = rx.shape[0]
    n_in = n
    if n == 0:
        out = empty_paths()
        return (out, {"type": np.zeros(0, np.int8), "landmark_id": np.zeros(0, object)}) if return_rays else out
    obj = np.asarray(obj, np.int64).reshape(n, -1)
    itype = np.asarray(itype, np.int64).reshape(n, -1)
    verts = np.asarray(verts, float).reshape(n, -1, 3)
    toa = np.asarray(toa_m, float).reshape(n)
    angles = np.asarray(angles, float).reshape(n, 4)
    power = np.asarray(power_db, float).reshape(n)
    antennas = np.asarray(antennas, float).reshape(-1, 3)
    dop = np.full(n, np.nan) if doppler_hz is None else np.asarray(doppler_hz, float).reshape(n)
    rayn = ray_numbers(rx, toa) if ray is None else np.asarray(ray, np.int64).reshape(n)
    if not (np.all(np.isfinite(toa)) and np.all(np.isfinite(angles))):
        bad = int(np.sum(~np.isfinite(toa)) + np.sum(~np.all(np.isfinite(angles), axis=1)))
        raise ValueError(f"label_paths: {bad} traced paths have non-finite TOA or angles")
    D = obj.shape[1]
    used = itype != NONE
    obj = np.where(used, obj, -1)
    depth = used.sum(axis=1)
    nobj = len(index.names)
    safe = np.clip(obj, 0, max(nobj - 1, 0))
    okind = np.where(obj >= 0, index.kind[safe] if nobj else -1, -1)
    oveh = np.where(obj >= 0, index.vehicle[safe] if nobj else -1, -1)

    # drop paths touching the receiving vehicle's own body
    own = np.any((okind == K_VEHICLE) & (oveh == rx[:, None]), axis=1)
    keep = ~own
    ray_typ = np.full(n_in, OTHER, np.int8)
    ray_id = np.array(["+".join(index.names[o] for o in row if o >= 0) or "?" for row in obj], dtype=object) \
        if np.any(own) else np.full(n_in, "", dtype=object)
    rx, obj, itype, verts, toa, angles, power = rx[keep], obj[keep], itype[keep], verts[keep], toa[keep], angles[keep], power[keep]
    depth, okind, oveh, dop, rayn = depth[keep], okind[keep], oveh[keep], dop[keep], rayn[keep]
    nrm = None if normals is None else np.asarray(normals, float).reshape(n, D, 3)[keep]
    n = rx.shape[0]
    if n == 0:
        out = empty_paths()
        return (out, {"type": ray_typ, "landmark_id": ray_id}) if return_rays else out

    o0, k0, t0, p0 = obj[:, 0], okind[:, 0], itype[:, 0], verts[:, 0]
    single = depth == 1
    first_known = o0 >= 0
    typ = np.full(n, OTHER, np.int64)
    typ[depth == 0] = BS
    # a specular bounce on a static planar surface, per slot: box face, ground, XML plane
    planar = (obj >= 0) & (itype == SPECULAR) & ((okind == K_BUILDING) | (okind == K_GROUND) | (okind == K_STATIC))
    if nrm is not None:
        planar &= (okind != K_STATIC) | np.all(np.isfinite(nrm), axis=2)
    else:
        planar &= okind != K_STATIC
    is_va1 = single & planar[:, 0]
    is_va2 = (depth == 2) & planar[:, 0] & (planar[:, 1] if D > 1 else False)
    is_sp = single & first_known & ((t0 == SPECULAR) | (t0 == DIFFUSE)) & (k0 == K_SCATTERER)
    is_vs = single & first_known & ((t0 == SPECULAR) | (t0 == DIFFUSE)) & (k0 == K_VEHICLE)

    # ---------------------------------------------------------------- landmarks and sub-keys
    bs = index.bs
    lm = np.full((n, 3), np.nan)
    va_order = np.where(is_va1, 1, np.where(is_va2, 2, 0))  # image order of a VA (0: not a VA)
    sub = np.zeros((n, 2, 4), np.int64)  # per bounce: face index / quantized plane
    plane_ix = np.full((n, 2), -1, np.int64)  # per bounce: row of index.planes (-1: none)
    surf_n = np.full((n, 2, 3), np.nan)  # per bounce: unit normal and a point of its plane
    surf_p = np.full((n, 2, 3), np.nan)
    for j in range(min(D, 2)):
        sel = np.flatnonzero(va_order > j)
        if sel.size:
            surf_n[sel, j], surf_p[sel, j], sub[sel, j], plane_ix[sel, j] = _surfaces(
                index, obj[sel, j], okind[sel, j], verts[sel, j], None if nrm is None else nrm[sel, j])
    if np.any(is_va2):  # two bounces on one plane: no specular double bounce, OTHER
        k1, o1 = okind[:, 1], obj[:, 1]
        same = is_va2 & np.all(sub[:, 0] == sub[:, 1], axis=1) & (
            ((k0 == K_STATIC) & (k1 == K_STATIC)) | ((k0 != K_STATIC) & (o0 == o1)))
        is_va2 &= ~same
        va_order[same] = 0
    typ[is_va1 | is_va2] = VA
    typ[is_sp] = SP
    typ[is_vs] = VS
    lm[typ == BS] = bs
    if np.any(is_va1):
        lm[is_va1] = mirror_point(bs, surf_p[is_va1, 0], surf_n[is_va1, 0])
    if np.any(is_va2):  # image of an image: the BS mirrored in the first plane, then in the second
        lm[is_va2] = mirror_point(mirror_point(bs, surf_p[is_va2, 0], surf_n[is_va2, 0]),
                                  surf_p[is_va2, 1], surf_n[is_va2, 1])
    if np.any(is_sp):
        lm[is_sp] = index.ref[o0[is_sp]]
    if np.any(is_vs):
        lm[is_vs] = antennas[oveh[is_vs, 0]]

    # ---------------------------------------------------------------- cluster key
    objkey = np.where((typ == OTHER)[:, None], obj, np.where(np.arange(D)[None, :] == 0, obj, -1))
    # a VA is its ordered surfaces: a box face / the ground by its object and face, a plane by itself
    va_obj = np.where((np.arange(D)[None, :] < va_order[:, None]) & (okind != K_STATIC), obj, -1)
    objkey = np.where((typ == VA)[:, None], va_obj, objkey)
    objkey = np.where((typ == BS)[:, None], -1, objkey)
    # OTHER paths from an unknown object keep the interaction types apart too
    key = np.concatenate([rx[:, None], typ[:, None], va_order[:, None], objkey, sub.reshape(n, 8),
                          np.where((typ == OTHER)[:, None], itype, 0)], axis=1)
    uk, first_idx, g = np.unique(key, axis=0, return_index=True, return_inverse=True)
    g = g.reshape(-1)
    ng = uk.shape[0]
    pw = np.where(np.isfinite(power), power, -np.inf)
    order = np.lexsort((toa, -pw, g))
    gs = g[order]
    starts = np.flatnonzero(np.r_[True, gs[1:] != gs[:-1]])
    rep = order[starts]  # strongest path per group (groups in ascending g)
    n_paths = np.bincount(g, minlength=ng)
    ts = toa[order]
    spread = np.maximum.reduceat(ts, starts) - np.minimum.reduceat(ts, starts)

    # ---------------------------------------------------------------- landmark ids
    ids = np.empty(ng, dtype=object)
    for j, r in enumerate(rep):
        t = typ[r]
        if t == BS:
            ids[j] = "bs"
        elif t == VA:  # order 2: '<first surface>|<second surface>'
            ids[j] = "|".join(_surface_id(index, obj[r, b], okind[r, b], sub[r, b], plane_ix[r, b])
                              for b in range(va_order[r]))
        elif t in (SP, VS):
            ids[j] = index.names[o0[r]]
        else:
            ids[j] = "+".join(index.names[o] if o >= 0 else "?" for o in obj[r] if o >= 0) or "?"

    bounce = np.where((depth[rep] > 0)[:, None], verts[rep, 0], np.nan)
    cols = {
        "step": np.full(ng, step, np.int32),
        "rx": rx[rep].astype(np.int16),
        "type": typ[rep].astype(np.int8),
        "landmark_id": ids,
        "bounces": depth[rep].astype(np.int8),
        "diffuse": np.any(itype[rep] == DIFFUSE, axis=1),
        "toa_m": toa[rep],
        "aod_az": angles[rep, 0], "aod_el": angles[rep, 1],
        "aoa_az": angles[rep, 2], "aoa_el": angles[rep, 3],
        "power_db": power[rep],
        **tx_position_columns(bs, ng),
        "bounce_x": bounce[:, 0], "bounce_y": bounce[:, 1], "bounce_z": bounce[:, 2],
        "lm_x": lm[rep, 0], "lm_y": lm[rep, 1], "lm_z": lm[rep, 2],
        "n_paths": n_paths.astype(np.int32),
        "delay_spread_m": spread.astype(float),
        "doppler_hz": dop[rep],
        "ray": rayn[rep].astype(np.int32),
    }
    assert set(cols) == set(PATH_COLUMNS)
    out = sort_paths({k: cols[k] for k in PATH_COLUMNS})
    if not return_rays:
        return out
    ray_typ[keep] = typ
    ray_id[keep] = ids[g]
    return out, {"type": ray_typ, "landmark_id": ray_id}
