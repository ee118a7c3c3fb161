"""Drivable free space and street routes of an external scene (ray-cast height map, NumPy + SciPy).

:func:`street_map` casts vertical rays on a plan grid over the scene
(:meth:`mmslam.scenes.geometry.StaticGeometry.vertical_hits`) and calls a cell *road* where its
topmost surface is also its lowest one (nothing above the ground: no roof, no overhang), keeping
the largest connected road area. *Free space* is road at least ``clearance`` m from any non-road
cell (a car fits); *centrelines* are the ridge of that distance (cells at least as far from the
kerb as their 8 neighbours). The terrain height is the road surface's z.

:func:`plan_route` joins points along the free space by the shortest path whose cost grows near
the kerb (so it keeps to the middle of the street) and returns 3-D waypoints ``[x, y, z]`` at
antenna height above the terrain. :func:`random_routes` draws seeded start / end points near the
BS and keeps routes that see the BS in most steps.

Global frame: x east, y north, z up, metres.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmslam.errors import ConfigError
from mmslam.scenes.driving import drive_route
from mmslam.scenes.geometry import StaticGeometry

ROAD_TOL_M = 0.3
"""A cell is road if its top surface is within this (m) of its lowest surface."""


@dataclass
class StreetMap:
    """Plan grid of an external scene. Cell ``(i, j)`` is centred at ``(x0 + (j + 0.5) res, y0 + (i + 0.5) res)``.

    ``top (ny, nx)`` top-surface z (NaN off the map), ``ground (ny, nx)`` lowest surface z,
    ``road`` / ``free`` / ``centre`` bool masks, ``kerb (ny, nx)`` distance to the nearest
    non-road cell (m).
    """

    x0: float
    y0: float
    res: float
    top: np.ndarray
    ground: np.ndarray
    road: np.ndarray
    free: np.ndarray
    centre: np.ndarray
    kerb: np.ndarray
    clearance: float

    @property
    def extent(self) -> tuple[float, float, float, float]:
        ny, nx = self.top.shape
        return (self.x0, self.x0 + nx * self.res, self.y0, self.y0 + ny * self.res)

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """``(n, 2)`` points -> ``(n, 2)`` integer (row, column), clipped to the grid."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        ny, nx = self.top.shape
        j = np.clip(np.floor((xy[:, 0] - self.x0) / self.res).astype(int), 0, nx - 1)
        i = np.clip(np.floor((xy[:, 1] - self.y0) / self.res).astype(int), 0, ny - 1)
        return np.stack([i, j], axis=1)

    def centre_xy(self, ij: np.ndarray) -> np.ndarray:
        ij = np.asarray(ij).reshape(-1, 2)
        return np.stack([self.x0 + (ij[:, 1] + 0.5) * self.res, self.y0 + (ij[:, 0] + 0.5) * self.res], axis=1)

    def snap(self, xy: np.ndarray) -> np.ndarray:
        """Nearest free-space cell centre ``(n, 2)`` of each point (to a centreline cell when within 10 m)."""
        from scipy.spatial import cKDTree

        xy = np.asarray(xy, float).reshape(-1, 2)
        free = np.argwhere(self.free)
        if not len(free):
            raise ConfigError("the scene has no drivable free space (no road wide enough for a car)")
        pts = self.centre_xy(free)
        d, k = cKDTree(pts).query(xy)
        cen = np.argwhere(self.centre)
        out = pts[k]
        if len(cen):
            cp = self.centre_xy(cen)
            dc, kc = cKDTree(cp).query(xy)
            out = np.where((dc <= d + 10.0)[:, None], cp[kc], out)
        return out


def street_map(geom: StaticGeometry, res: float = 2.0, clearance: float = 3.0,
               window: tuple[float, float, float, float] | None = None) -> StreetMap:
    """Road, free space, centrelines and terrain of ``geom`` on a ``res`` m grid (see module doc).

    ``window = (x0, x1, y0, y1)`` limits the grid (default: the scene's plan bounds).
    """
    from scipy import ndimage

    if not len(geom.triangles):
        raise ConfigError("the scene has no triangles; streets need an xml_scene with a ground")
    lo, hi = geom.bounds()
    x0, x1, y0, y1 = window if window is not None else (lo[0], hi[0], lo[1], hi[1])
    x0, y0 = max(x0, lo[0]), max(y0, lo[1])
    x1, y1 = min(x1, hi[0]), min(y1, hi[1])
    nx, ny = max(1, int(np.ceil((x1 - x0) / res))), max(1, int(np.ceil((y1 - y0) / res)))
    X, Y = np.meshgrid(x0 + (np.arange(nx) + 0.5) * res, y0 + (np.arange(ny) + 0.5) * res)
    pt, z, _ = geom.vertical_hits(np.stack([X.ravel(), Y.ravel()], axis=1))
    top = np.full(X.size, -np.inf)
    bot = np.full(X.size, np.inf)
    np.maximum.at(top, pt, z)
    np.minimum.at(bot, pt, z)
    top = np.where(np.isfinite(top), top, np.nan).reshape(X.shape)
    bot = np.where(np.isfinite(bot), bot, np.nan).reshape(X.shape)
    road = np.isfinite(top) & (top - bot <= ROAD_TOL_M)
    lab, n = ndimage.label(road, structure=np.ones((3, 3)))
    if n > 1:
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        road = lab == int(np.argmax(sizes))
    kerb = ndimage.distance_transform_edt(road) * res
    free = road & (kerb >= clearance)
    ridge = kerb >= ndimage.maximum_filter(kerb, size=3) - 1e-9
    centre = free & ridge
    return StreetMap(float(x0), float(y0), float(res), top, bot, road, free, centre, kerb, float(clearance))


def _graph(sm: StreetMap):
    """Sparse 8-neighbour graph over the free cells; edge cost = length x (1 + 4 m / kerb distance)."""
    from scipy.sparse import coo_matrix

    ny, nx = sm.free.shape
    idx = -np.ones(sm.free.shape, np.int64)
    cells = np.argwhere(sm.free)
    idx[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    rows, cols, w = [], [], []
    pen = 1.0 + 4.0 / np.maximum(sm.kerb, 1e-6)
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        i2, j2 = cells[:, 0] + di, cells[:, 1] + dj
        ok = (i2 >= 0) & (i2 < ny) & (j2 >= 0) & (j2 < nx)
        a = np.flatnonzero(ok)
        b = idx[i2[ok], j2[ok]]
        good = b >= 0
        a, b = a[good], b[good]
        length = sm.res * np.hypot(di, dj)
        c = length * 0.5 * (pen[cells[a, 0], cells[a, 1]] + pen[cells[b, 0], cells[b, 1]])
        rows += [a, b]
        cols += [b, a]
        w += [c, c]
    n = len(cells)
    g = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    return g, cells, idx


def _simplify(p: np.ndarray, tol: float) -> np.ndarray:
    """Ramer-Douglas-Peucker simplification of a polyline ``(n, 2)`` to within ``tol`` m."""
    keep = np.zeros(len(p), bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(p) - 1)]
    while stack:
        a, b = stack.pop()
        if b <= a + 1:
            continue
        seg = p[b] - p[a]
        L = np.hypot(*seg)
        rel = p[a + 1:b] - p[a]
        d = np.abs(seg[0] * rel[:, 1] - seg[1] * rel[:, 0]) / L if L > 0 else np.hypot(rel[:, 0], rel[:, 1])
        k = int(np.argmax(d))
        if d[k] > tol:
            keep[a + 1 + k] = True
            stack += [(a, a + 1 + k), (a + 1 + k, b)]
    return p[keep]


def _path_cells(pred: np.ndarray, src: int, dst: int) -> list[int]:
    out = [dst]
    while out[-1] != src:
        nxt = int(pred[out[-1]])
        if nxt < 0:
            return []
        out.append(nxt)
    return out[::-1]


def terrain_z(sm: StreetMap, xy: np.ndarray) -> np.ndarray:
    """Road surface height (m) under each point ``(n, 2)`` (the nearest cell's ground)."""
    ij = sm.cell_of(xy)
    return sm.ground[ij[:, 0], ij[:, 1]]


def plan_route(sm: StreetMap, points: np.ndarray, antenna_height: float = 1.6, tol: float = 0.5,
               graph=None) -> np.ndarray:
    """3-D waypoints ``(m, 3)`` along the streets through ``points (k >= 2, 2)`` (each snapped first).

    z is ``antenna_height`` above the terrain at each waypoint; straight legs between waypoints
    stay within ``tol`` m of the street path (inside the free space).
    """
    from scipy.sparse.csgraph import dijkstra

    pts = sm.snap(points)
    g, cells, idx = graph if graph is not None else _graph(sm)
    ij = sm.cell_of(pts)
    nodes = idx[ij[:, 0], ij[:, 1]]
    poly = []
    for a, b in zip(nodes[:-1], nodes[1:]):
        _, pred = dijkstra(g, indices=int(a), return_predecessors=True)
        seq = _path_cells(pred, int(a), int(b))
        if not seq:
            raise ConfigError(f"no street connects ({sm.centre_xy(cells[a])[0].round(1).tolist()}) and "
                              f"({sm.centre_xy(cells[b])[0].round(1).tolist()}); pick points on connected streets")
        poly.append(sm.centre_xy(cells[seq]))
    xy = np.concatenate([p if i == 0 else p[1:] for i, p in enumerate(poly)])
    return _waypoints(sm, xy, antenna_height, tol)


def _waypoints(sm: StreetMap, xy: np.ndarray, antenna_height: float, tol: float) -> np.ndarray:
    """Cell-centre path ``(n, 2)`` -> simplified 3-D waypoints at most 10 m apart, z on the terrain."""
    xy = _simplify(xy, tol)
    dense = [xy[0]]
    for p, q in zip(xy[:-1], xy[1:]):
        k = max(1, int(np.ceil(np.hypot(*(q - p)) / 10.0)))
        dense += [p + (q - p) * t for t in np.arange(1, k + 1) / k]
    xy = np.asarray(dense)
    return np.concatenate([xy, (terrain_z(sm, xy) + antenna_height)[:, None]], axis=1)


def _truncate(wp: np.ndarray, length: float) -> np.ndarray:
    """Waypoints ``(k, 3)`` cut at plan length ``length`` m (the last point interpolated)."""
    L = np.hypot(*np.diff(wp[:, :2], axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    if cum[-1] <= length:
        return wp
    k = int(np.searchsorted(cum, length, side="right"))  # cum[k - 1] <= length < cum[k]
    f = (length - cum[k - 1]) / L[k - 1]
    return np.concatenate([wp[:k], (wp[k - 1] + f * (wp[k] - wp[k - 1]))[None]])


def _driven(wp: np.ndarray, length: float, steps: int) -> np.ndarray:
    """``(steps, 2)`` plan positions of a car driving waypoints ``wp`` ``length`` m in ``steps`` steps, as the
    trajectory drives it (:func:`mmslam.scenes.driving.drive_route`: pure pursuit, corners rounded)."""
    return drive_route(wp, length / steps, steps, 1.0)[:, :2]


def random_routes(sm: StreetMap, geom: StaticGeometry, bs: np.ndarray, n: int, length_m: np.ndarray,
                  rng: np.random.Generator, radius: float = 150.0, min_los: float = 0.6,
                  antenna_height: float = 1.6, tries: int = 40, steps: int | None = None,
                  min_gap: float = 6.0) -> list[np.ndarray]:
    """``n`` seeded routes (3-D waypoints) of at least ``length_m[i]`` m on the centrelines near the BS.

    Start points are drawn from the centreline cells within ``radius`` m (plan) of the BS; the end
    is a random reachable cell at street distance ``>= length_m[i]``. A route is kept if the BS is
    in line of sight (static triangles) from at least ``min_los`` of its points sampled every 5 m;
    else the best of ``tries`` draws is kept. With ``steps``, car ``i`` drives ``length_m[i] / steps`` per step
    from the start as its trajectory will (:func:`_driven`: corners rounded), and a draw that brings
    it within ``min_gap`` m (plan, antenna to antenna; 6 m clears two 4.5 x 1.8 m bodies in any
    orientation) of an earlier car at the same step is not kept and not counted as one of the
    ``tries`` (at most ``10 tries`` draws in all): cars on one centreline would drive through each other.
    """
    from scipy.sparse.csgraph import dijkstra

    g, cells, idx = _graph(sm)
    cen = np.argwhere(sm.centre)
    cxy = sm.centre_xy(cen)
    near = cen[np.hypot(*(cxy - np.asarray(bs, float)[:2]).T) <= radius]
    if not len(near):
        raise ConfigError(f"no street centreline within {radius:g} m of the BS; move the BS or widen the radius")
    xy_all = sm.centre_xy(cells)
    on_centre = sm.centre[cells[:, 0], cells[:, 1]]
    out: list[np.ndarray] = []
    placed: list[np.ndarray] = []  # (steps, 2) plan positions of the routes kept so far
    for i in range(n):
        best, best_score, used = None, -1.0, 0
        for _ in range(10 * tries):  # a draw too close to an earlier car is not one of the `tries`
            if used >= tries:
                break
            used += 1
            s = near[rng.integers(len(near))]
            a = int(idx[s[0], s[1]])
            if a < 0:
                continue
            dist, pred = dijkstra(g, indices=a, return_predecessors=True, limit=6.0 * length_m[i] + 100.0)
            geo = np.hypot(*(xy_all - xy_all[a]).T)
            ok = np.flatnonzero(np.isfinite(dist) & (geo >= length_m[i]) & on_centre)
            if not ok.size:
                continue
            b = int(ok[rng.integers(ok.size)])
            wp = _waypoints(sm, xy_all[_path_cells(pred, a, b)], antenna_height, 0.5)
            wp = _truncate(wp, length_m[i] + 1.0)  # the car stops at the end: score only what it drives
            seg = np.diff(wp[:, :2], axis=0)
            L = np.hypot(seg[:, 0], seg[:, 1])
            if L.sum() < length_m[i]:
                continue
            t = np.linspace(0.0, L.sum(), 16)
            cum = np.concatenate([[0.0], np.cumsum(L)])
            k = np.clip(np.searchsorted(cum, t, side="right") - 1, 0, len(L) - 1)
            f = (t - cum[k]) / np.where(L[k] > 0, L[k], 1.0)
            samp = wp[k] + f[:, None] * (wp[k + 1] - wp[k])
            if steps is not None:
                pos = _driven(wp, length_m[i], steps)
                if any(np.min(np.hypot(*(pos - q).T)) < min_gap for q in placed):
                    used -= 1
                    continue
            los = ~geom.segments_blocked(np.repeat(np.asarray(bs, float)[None], len(samp), 0), samp)
            score = float(los.mean())
            if score > best_score:
                best, best_score = wp, score
            if score >= min_los:
                break
        if best is None:
            raise ConfigError(f"could not draw route {i + 1} of {n} near the BS clear of the other cars; lower "
                              "n_vehicles or change the seed")
        out.append(best)
        if steps is not None:
            placed.append(_driven(best, length_m[i], steps))
    return out


class _StreetContext:
    """A scene's street map, built once, for planning the routes of one scenario."""

    def __init__(self, geom: StaticGeometry, bs: np.ndarray) -> None:
        self.geom = geom
        self.bs = np.asarray(bs, float)
        self.sm = street_map(geom)

    def route(self, xy: np.ndarray, antenna_height: float) -> np.ndarray:
        return plan_route(self.sm, xy, antenna_height)

    def random(self, n: int, lengths: np.ndarray, rng: np.random.Generator, steps: int | None = None
               ) -> list[np.ndarray]:
        return random_routes(self.sm, self.geom, self.bs, n, lengths, rng, steps=steps)


_CTX: dict[tuple, _StreetContext] = {}


def scenario_street_context(src: str, data: dict, bs) -> _StreetContext:
    """The street context of a scenario dict's ``xml_scene`` (kept in memory per scene and BS)."""
    from mmslam.scenes.geometry import xml_geometry

    geom = xml_geometry(str(data["xml_scene"]), src)
    key = (id(geom), tuple(map(float, bs)))
    if key not in _CTX:
        _CTX.clear()
        _CTX[key] = _StreetContext(geom, np.asarray(bs, float))
    return _CTX[key]


NPZ_KIND = "streets"
"""Tag of a street-map ``.npz`` (:data:`mmslam.outputs.NPZ_TAG`)."""


def save_street_map(sm: StreetMap, path: str | Path) -> Path:
    """Write the street map as ``.npz`` (``top, ground, road, free, centre, kerb`` grids and
    ``x0, y0, res, clearance``; cell (i, j) centred at ``(x0 + (j + 0.5) res, y0 + (i + 0.5) res)``), atomically,
    tagged ``mmslam_output`` = :data:`NPZ_KIND` so that a later run may replace it (:mod:`mmslam.outputs`)."""
    from mmslam.outputs import atomic_write_bytes, npz_bytes

    p = Path(path)
    atomic_write_bytes(p, npz_bytes(NPZ_KIND, compressed=True, top=sm.top, ground=sm.ground, road=sm.road,
                                    free=sm.free, centre=sm.centre, kerb=sm.kerb, x0=sm.x0, y0=sm.y0, res=sm.res,
                                    clearance=sm.clearance))
    return p


def plot_streets(sm: StreetMap, out_png: str | Path, title: str, routes: dict[str, np.ndarray] | None = None,
                 bs: np.ndarray | None = None) -> Path:
    """Figure (format by suffix: png, pdf, svg; tagged as mmslam's): top-surface height (grey), drivable free
    space (green), centrelines (blue), routes, BS. Written atomically (:func:`mmslam.outputs.save_figure`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mmslam.outputs import save_figure

    fig, ax = plt.subplots(figsize=(9, 8))
    z = np.ma.masked_invalid(sm.top)
    im = ax.imshow(z, origin="lower", extent=sm.extent, cmap="Greys", vmin=float(np.nanmin(sm.top)),
                   vmax=float(np.nanpercentile(sm.top, 99)), interpolation="nearest", zorder=0)
    fig.colorbar(im, ax=ax, shrink=0.6, label="top surface z [m]")
    ax.imshow(np.ma.masked_where(~sm.free, np.ones_like(sm.top)), origin="lower", extent=sm.extent, cmap="Greens",
              vmin=0, vmax=2, alpha=0.45, interpolation="nearest", zorder=1)
    c = sm.centre_xy(np.argwhere(sm.centre))
    ax.plot(c[:, 0], c[:, 1], ".", ms=1.0, color="tab:blue", label="street centrelines", zorder=2)
    ax.plot([], [], "s", color="tab:green", alpha=0.45, label=f"free space (>= {sm.clearance:g} m from kerbs)")
    for name, wp in (routes or {}).items():
        ax.plot(wp[:, 0], wp[:, 1], "-", lw=1.5, label=name, zorder=3)
        ax.plot(wp[0, 0], wp[0, 1], "o", mfc="white", color="k", ms=4, zorder=4)
    if bs is not None:
        ax.plot(bs[0], bs[1], "^", color="k", ms=10, label="BS", zorder=5)
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    try:
        return save_figure(fig, out_png, dpi=130, bbox_inches="tight")
    finally:
        plt.close(fig)
