"""Top-down plan figures of a scenario: BS, buildings, SPs, VAs, trajectories, FOV circles, and the
top-surface height raster of an external XML scene (moved out of :mod:`mmslam.scenes.meshes` so the
mesh builder does not import the geometry, landmark and trajectory modules above it).

This module does not import Sionna or Mitsuba.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mmslam.scenes.scenario import Scenario


def height_raster(scn: Scenario, traj: np.ndarray, margin: float = 60.0,
                  max_px: int = 700) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Top-surface height (m) of an external scene on a plan raster, by vertical ray casting.

    The window is the trajectories ``traj (steps, n, >=2)`` and the BS plus ``margin`` m, inside
    the scene's bounds; at most ``max_px`` pixels a side (at least 0.5 m each). Returns
    ``z (ny, nx)`` (row 0 the southmost, NaN where no surface: off the map) and its extent
    ``(x0, x1, y0, y1)`` (m).
    """
    from mmslam.scenes.geometry import static_geometry

    g = static_geometry(scn, include_scenario=False)
    if not len(g.triangles):
        return np.full((1, 1), np.nan), (0.0, 1.0, 0.0, 1.0)
    lo, hi = g.bounds()
    pts = np.concatenate([np.asarray(traj, float)[:, :, :2].reshape(-1, 2), np.asarray(scn.bs, float)[None, :2]])
    x0, y0 = np.maximum(pts.min(axis=0) - margin, lo[:2])
    x1, y1 = np.minimum(pts.max(axis=0) + margin, hi[:2])
    res = max(0.5, max(x1 - x0, y1 - y0) / max_px)
    nx, ny = max(1, int(np.ceil((x1 - x0) / res))), max(1, int(np.ceil((y1 - y0) / res)))
    X, Y = np.meshgrid(x0 + (np.arange(nx) + 0.5) * res, y0 + (np.arange(ny) + 0.5) * res)
    z, _ = g.height_map(np.stack([X.ravel(), Y.ravel()], axis=1))
    return z.reshape(X.shape), (float(x0), float(x0 + nx * res), float(y0), float(y0 + ny * res))


def _draw_xml_heights(ax, scn: Scenario, traj: np.ndarray) -> None:
    """Shade an external scene's top-surface height under the plan (buildings as dark footprints)."""
    z, extent = height_raster(scn, traj)
    if not np.isfinite(z).any():
        return
    im = ax.imshow(np.ma.masked_invalid(z), origin="lower", extent=extent, cmap="Greys", vmin=float(np.nanmin(z)),
                   vmax=float(np.nanpercentile(z, 99)), alpha=0.85, zorder=0, interpolation="nearest")
    ax.figure.colorbar(im, ax=ax, shrink=0.6, label=f"top surface z of {scn.xml_scene} [m]")


def plot_plan(scn: Scenario, out_png: str | Path, fov_points: int = 4) -> Path:
    """Top-down plan (x east, y north, m): BS, buildings, SPs, VAs, trajectories, FOV circles.

    An external XML scene is drawn as its top-surface height map (buildings as shaded footprints).

    Trajectories start at the open circle; the arrow head marks the last step's direction.

    FOV circles (radius ``sensor.fov_range``) are drawn around ``fov_points`` evenly spaced
    trajectory points of each vehicle. Written atomically in the format of the file's suffix (png, pdf, svg); returns the path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    from mmslam.scenes.landmarks import va_truth
    from mmslam.scenes.trajectory import vehicle_trajectories

    fig, ax = plt.subplots(figsize=(8, 8))
    traj = vehicle_trajectories(scn)
    if scn.xml_scene:
        _draw_xml_heights(ax, scn, traj)
    for i, b in enumerate(scn.buildings):
        ax.add_patch(Rectangle((b.min[0], b.min[1]), b.max[0] - b.min[0], b.max[1] - b.min[1],
                               facecolor="0.75", edgecolor="0.3", label="building" if i == 0 else None))
    if scn.ground is not None:
        e = scn.ground.extent / 2
        ax.add_patch(Rectangle((-e, -e), 2 * e, 2 * e, fill=False, ls=":", ec="0.6", label="ground extent"))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, v in enumerate(scn.vehicles):
        c = colors[i % len(colors)]
        ax.plot(traj[:, i, 0], traj[:, i, 1], "-", color=c, lw=1.5, label=f"{v.name} trajectory")
        ax.plot(traj[0, i, 0], traj[0, i, 1], "o", color=c, ms=7, mfc="white")  # start
        ax.annotate("", xy=traj[-1, i, :2], xytext=traj[-2, i, :2],
                    arrowprops=dict(arrowstyle="-|>", color=c, lw=1.5))  # direction at the end
        idx = np.floor(np.linspace(0, len(traj), max(fov_points, 1), endpoint=False)).astype(int)
        for j, k in enumerate(np.unique(idx)):
            ax.add_patch(Circle((traj[k, i, 0], traj[k, i, 1]), scn.sensor.fov_range, fill=False, color=c,
                                ls="--", lw=0.8, label=f"{v.name} FOV ({scn.sensor.fov_range:g} m)" if j == 0 else None))
    if scn.scatterers:
        sp = np.array([s.position for s in scn.scatterers])
        ax.plot(sp[:, 0], sp[:, 1], "s", color="tab:green", label="SP (scatterer)")
        for s in scn.scatterers:
            ax.annotate(s.name, s.position[:2], textcoords="offset points", xytext=(4, 4), fontsize=7)
    vas = va_truth(scn)
    if vas:
        va = np.array(list(vas.values()))
        ax.plot(va[:, 0], va[:, 1], "x", color="tab:purple", ms=8, label="VA (image of BS)")
    ax.plot(scn.bs[0], scn.bs[1], "^", color="k", ms=11, label="BS")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(f"scenario '{scn.name}' (plan view)")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.grid(True, lw=0.3)
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    from mmslam.outputs import save_figure

    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        save_figure(fig, out, dpi=120, bbox_inches="tight")
    finally:
        plt.close(fig)
    return out
