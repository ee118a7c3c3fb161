"""BS placement aid: Sionna's radio map of the BS at street level over the plan, with the routes.

:func:`coverage_map` asks Sionna's :class:`~sionna.rt.RadioMapSolver`
(:func:`mmslam.raytrace.sionna_adapter.sionna_radio_map`, the only Sionna import) for the path gain
of the BS on a horizontal plane ``height`` m above the street (the median ground height under the
routes), over the bounding box of the BS and the routes plus a margin. Cells whose top surface
lies above the plane (inside a building, or terrain above the plane on a hilly scene) are marked
as such from the scene's own triangles (:class:`mmslam.scenes.geometry.StaticGeometry`), not from
the radio map. :func:`plot_coverage` draws it; :func:`route_gain_db` reads it along the routes.

Global frame: x east, y north, z up, metres. Path gain in dB: ``10 log10`` of Sionna's cell
average of ``sum |a|^2`` over the paths (isotropic antennas, no transmit power).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmslam.errors import BackendError, ConfigError
from mmslam.scenes.scenario import Scenario

MAX_CELLS = 2_000_000
"""Largest radio map (cells): a typo in --res must not exhaust memory."""


@dataclass
class CoverageMap:
    """Path gain of the BS on a plan grid. Cell ``(i, j)`` is centred at ``(x0 + (j + 0.5) res, y0 + (i + 0.5) res)``.

    ``gain_db (ny, nx)``: path gain, dB (``-inf``: no path reached the cell); ``covered (ny, nx)``
    bool: the scene's top surface is above the plane there (a building); ``z`` the plane height (m).
    """

    x0: float
    y0: float
    res: float
    z: float
    gain_db: np.ndarray
    covered: np.ndarray

    @property
    def extent(self) -> tuple[float, float, float, float]:
        ny, nx = self.gain_db.shape
        return (self.x0, self.x0 + nx * self.res, self.y0, self.y0 + ny * self.res)

    def at(self, xy: np.ndarray) -> np.ndarray:
        """Path gain (dB) of the cell under each point ``(n, 2)``; NaN outside the map or in a building."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        ny, nx = self.gain_db.shape
        j = np.floor((xy[:, 0] - self.x0) / self.res).astype(np.int64)
        i = np.floor((xy[:, 1] - self.y0) / self.res).astype(np.int64)
        ok = (i >= 0) & (j >= 0) & (i < ny) & (j < nx)
        out = np.full(len(xy), np.nan)
        ic, jc = i[ok], j[ok]
        out[ok] = np.where(self.covered[ic, jc], np.nan, self.gain_db[ic, jc])
        return out


def coverage_map(scn: Scenario, states: np.ndarray, height: float = 1.5, res: float = 2.0, margin: float = 40.0,
                 samples: int = 10**6, max_depth: int = 1, seed: int = 0) -> CoverageMap:
    """Sionna radio map of ``scn``'s BS, ``height`` m above the street, around the routes ``states (steps, n, >=3)``.

    The plane is at the median ground height under the vehicles' positions (the highest surface
    below each antenna; 0 where there is none) plus ``height``; it spans the BS and every
    position, ``margin`` m beyond, in cells of ``res`` m.

    Raises:
        ConfigError: a bad argument or too many cells; BackendError: Sionna is not installed.
    """
    from mmslam.scenes.geometry import static_geometry

    if not 0.1 <= res <= 100.0:
        raise ConfigError(f"--res {res}: expected 0.1 .. 100 m")
    if not 0.0 < height <= 100.0:
        raise ConfigError(f"--height {height}: expected 0 .. 100 m above the street")
    st = np.asarray(states, float).reshape(-1, np.asarray(states).shape[-1])
    geom = static_geometry(scn)
    zg, _ = geom.height_map(st[:, :2], below=st[:, 2]) if len(geom.triangles) else (np.zeros(len(st)), None)
    ground = float(np.median(np.nan_to_num(zg, nan=0.0))) if len(st) else 0.0
    pts = np.concatenate([st[:, :2], np.asarray(scn.bs, float)[None, :2]])
    lo, hi = pts.min(axis=0) - margin, pts.max(axis=0) + margin
    n = np.ceil((hi - lo) / res).astype(np.int64)
    if int(n[0]) * int(n[1]) > MAX_CELLS:
        raise ConfigError(f"--res {res}: the map would have {int(n[0]) * int(n[1])} cells (at most {MAX_CELLS}); "
                          "use a coarser --res")
    size = n * res
    z = ground + height
    try:
        from mmslam.raytrace.sionna_adapter import sionna_radio_map
    except ImportError as e:
        raise BackendError(f"the radio map needs Sionna RT ({e}); install sionna-rt") from None
    pg = sionna_radio_map(scn, (float(lo[0] + size[0] / 2), float(lo[1] + size[1] / 2), z), (float(size[0]),
                          float(size[1])), res, samples=samples, max_depth=max_depth, seed=seed)
    if pg.shape != (int(n[1]), int(n[0])):
        raise BackendError(f"Sionna returned a radio map of shape {pg.shape}, expected {(int(n[1]), int(n[0]))}")
    with np.errstate(divide="ignore"):
        gain = 10.0 * np.log10(pg)
    X, Y = np.meshgrid(lo[0] + (np.arange(n[0]) + 0.5) * res, lo[1] + (np.arange(n[1]) + 0.5) * res)
    top, _ = geom.height_map(np.stack([X.ravel(), Y.ravel()], axis=1)) if len(geom.triangles) else \
        (np.full(X.size, np.nan), None)
    covered = (np.nan_to_num(top, nan=-np.inf) > z).reshape(X.shape)
    return CoverageMap(float(lo[0]), float(lo[1]), float(res), float(z), gain, covered)


def route_gain_db(cm: CoverageMap, states: np.ndarray) -> np.ndarray:
    """Path gain (dB) of the map's cell under each vehicle at each step, ``(steps, n_vehicles)``."""
    st = np.asarray(states, float)
    return cm.at(st[:, :, :2].reshape(-1, 2)).reshape(st.shape[:2])


def plot_coverage(cm: CoverageMap, scn: Scenario, states: np.ndarray, out: str | Path, floor_db: float = 60.0) -> Path:
    """Figure: path gain (dB, ``floor_db`` below the strongest cell and lower in the darkest colour), cells
    with no path (black), buildings (grey), the routes (start: open circle) and the BS. Format from the suffix."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mmslam.outputs import save_figure

    st = np.asarray(states, float)
    g = np.where(cm.covered, np.nan, cm.gain_db)
    finite = g[np.isfinite(g)]
    vmax = float(finite.max()) if finite.size else 0.0
    fig, ax = plt.subplots(figsize=(9, 8))
    ax.imshow(np.where(np.isneginf(g), 1.0, np.nan), origin="lower", extent=cm.extent, cmap="Greys", vmin=0, vmax=1,
              interpolation="nearest")  # no path: black
    im = ax.imshow(np.where(np.isfinite(g), g, np.nan), origin="lower", extent=cm.extent, cmap="viridis",
                   vmin=vmax - floor_db, vmax=vmax, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.6, label=f"path gain at z = {cm.z:.1f} m [dB]")
    ax.imshow(np.where(cm.covered, 0.45, np.nan), origin="lower", extent=cm.extent, cmap="Greys", vmin=0, vmax=1,
              interpolation="nearest")
    ax.plot([], [], "s", color="0.55", label="building (top above the plane)")
    ax.plot([], [], "s", color="k", label="no path")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, v in enumerate(scn.vehicles):
        c = colors[(i + 1) % len(colors)]
        ax.plot(st[:, i, 0], st[:, i, 1], "-", color=c, lw=2.0, label=v.name)
        ax.plot(st[0, i, 0], st[0, i, 1], "o", color=c, mfc="white", ms=6)
    ax.plot(scn.bs[0], scn.bs[1], "^", color="red", mec="k", ms=12, label="BS")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(f"'{scn.name}': Sionna radio map of the BS")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    p = Path(out)
    try:
        save_figure(fig, p, dpi=120, bbox_inches="tight")
    finally:
        plt.close(fig)
    return p
