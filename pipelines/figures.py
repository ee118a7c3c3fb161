"""Figures of an ablation (matplotlib, Agg, no pyplot state): one function per figure.

Each function returns a :class:`matplotlib.figure.Figure` so callers (tests, notebooks) can
inspect the plotted lines; :func:`save_figure` writes it atomically (PNG, PDF or SVG by suffix). Data lines carry the
variant name as their label; the fusion-start marker is a vertical line labelled
``"fusion start"`` with ``gid == "fusion_start"``.

- :func:`fig_gospa` (the paper's Fig. 2a with ``type="VS"``, Fig. 2b with ``type="VA"``, and
  the SP plot with ``type="SP"``): mean GOSPA of one map (default the fused BS map) vs step.
- :func:`fig_position_rmse` (the paper's Fig. 3): position RMSE over runs and vehicles vs step.
- :func:`fig_map`: top-down view of one run at its last step: true and estimated VA / SP / VS,
  true and estimated trajectories, the BS.

Colours are the Okabe-Ito colour-blind-safe palette; variants also differ in line style and
marker, so the plots read in greyscale too.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mmslam.pipelines.ablate import ALL_VEHICLES, Summary
from mmslam.slam.specs.landmarks import mapped_types
from mmslam.slam.specs.variants import get_variant, variant_names

OKABE_ITO: dict[str, str] = {
    "black": "#000000", "orange": "#E69F00", "sky_blue": "#56B4E9", "bluish_green": "#009E73",
    "yellow": "#F0E442", "blue": "#0072B2", "vermillion": "#D55E00", "reddish_purple": "#CC79A7",
}
"""Okabe & Ito (2008) colour-blind-safe palette."""

VARIANT_STYLE: dict[str, dict[str, Any]] = {
    "odometry": {"color": OKABE_ITO["black"], "linestyle": ":", "marker": "x"},
    "baseline": {"color": OKABE_ITO["vermillion"], "linestyle": "--", "marker": "s"},
    "cm1": {"color": OKABE_ITO["orange"], "linestyle": "-.", "marker": "^"},
    "proposed": {"color": OKABE_ITO["blue"], "linestyle": "-", "marker": "o"},
}
VARIANT_LABEL: dict[str, str] = {v: get_variant(v).label for v in variant_names()}
"""Legend label of each variant (:attr:`mmslam.slam.specs.variants.VariantSpec.label`)."""
TYPE_COLOR: dict[str, str] = {"VA": OKABE_ITO["orange"], "SP": OKABE_ITO["bluish_green"],
                              "VS": OKABE_ITO["reddish_purple"]}
VEHICLE_COLORS: tuple[str, ...] = (OKABE_ITO["blue"], OKABE_ITO["vermillion"], OKABE_ITO["sky_blue"],
                                   OKABE_ITO["bluish_green"], OKABE_ITO["orange"])
TYPE_NAMES = {t.name: t.description for t in mapped_types()}
"""Title of each map type (:attr:`mmslam.slam.specs.landmarks.LandmarkSpec.description`)."""


def _figure(size: tuple[float, float] = (6.4, 4.0)) -> tuple[Any, Any]:
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    return fig, fig.subplots()


def _step_label(summary: Summary) -> str:
    dt = summary.config.get("dt")
    return f"time step k (Δ = {dt:g} s)" if dt else "time step k"


def _mark_fusion(ax: Any, fusion_start: int | None) -> None:
    if fusion_start is not None and fusion_start > 0:
        ax.axvline(fusion_start, color=OKABE_ITO["black"], linestyle=":", linewidth=1.2,
                   label="fusion start", gid="fusion_start")


def _plot_variants(ax: Any, summary: Summary, map: str, type: str, quantity: str, column: str,
                   band: bool) -> None:
    for v in summary.variants:
        s = summary.series(v, map, type, quantity)
        if s["step"].size == 0:
            continue
        st = VARIANT_STYLE.get(v, {})
        y = s[column]
        ax.plot(s["step"], y, label=v, gid=f"variant:{v}", markersize=4, linewidth=1.6, **st)
        if band:
            ax.fill_between(s["step"], np.maximum(y - s["std"], 0.0), y + s["std"], color=st.get("color"), alpha=0.12,
                            linewidth=0)
    ax.grid(True, alpha=0.3)


def fig_gospa(summary: Summary, type: str = "VS", map: str = "fused", band: bool = True) -> Any:
    """Mean GOSPA (over Monte Carlo runs) of one map's ``type`` landmarks vs time step.

    One line per variant (label = variant, y = the summary's ``mean`` of ``gospa``), a shaded
    +-1 std band (clipped at 0), and the fusion start marked by a vertical line.
    """
    fig, ax = _figure()
    _plot_variants(ax, summary, map, type, "gospa", "mean", band)
    return _finish_map_figure(fig, ax, summary, "Mean GOSPA", type, map, "mean GOSPA [m]")


def _finish_map_figure(fig: Any, ax: Any, summary: Summary, what: str, type: str, map: str, ylabel: str) -> Any:
    """Fusion-start line, legend, title ``what, type, map``, axis labels, y from 0."""
    _mark_fusion(ax, summary.config.get("fusion_start"))
    _relabel_legend(ax)
    where = "fused BS map" if map == "fused" else f"local map of {map}"
    ax.set_title(f"{what}, {TYPE_NAMES.get(type, type)}, {where}")
    ax.set_xlabel(_step_label(summary))
    ax.set_ylabel(ylabel)
    ax.set_ylim(bottom=0)
    return fig


def fig_position_rmse(summary: Summary, map: str = ALL_VEHICLES) -> Any:
    """Position RMSE vs time step, one line per variant (RMSE over runs and vehicles by default)."""
    fig, ax = _figure()
    _plot_variants(ax, summary, map, "state", "pos_err", "rms", band=False)
    _mark_fusion(ax, summary.config.get("fusion_start"))
    _relabel_legend(ax)
    who = "all vehicles" if map == ALL_VEHICLES else map
    ax.set_title(f"Vehicle position RMSE ({who}, {_runs_text(summary)})")
    ax.set_xlabel(_step_label(summary))
    ax.set_ylabel("position RMSE [m]")
    ax.set_ylim(bottom=0)
    return fig


def fig_cardinality(summary: Summary, type: str = "VS", map: str = "fused") -> Any:
    """Estimated number of landmarks (PHD mass of the map) vs time step, mean over runs per variant.

    The true count (mean of ``n_true`` over runs, the same for every variant) is drawn dotted.
    A variant whose VS mass drops below the number of vehicles has merged vehicles into one
    Gaussian (or lost one).
    """
    fig, ax = _figure()
    _plot_variants(ax, summary, map, type, "card", "mean", band=False)
    for v in summary.variants:
        s = summary.series(v, map, type, "n_true")
        if s["step"].size:
            ax.plot(s["step"], s["mean"], color=OKABE_ITO["black"], linestyle=":", linewidth=1.2,
                    label="truth", gid="truth")
            break
    return _finish_map_figure(fig, ax, summary, "Estimated cardinality", type, map, "PHD mass (expected count)")


def _runs_text(summary: Summary) -> str:
    seeds = summary.config.get("seeds_found") or {}
    ns = sorted({len(v) for v in seeds.values()})
    return f"{'/'.join(map(str, ns))} runs" if ns else "runs"


def _relabel_legend(ax: Any) -> None:
    handles, labels = ax.get_legend_handles_labels()
    ax.legend(handles, [VARIANT_LABEL.get(lb, lb) for lb in labels], loc="best", fontsize=8)


def fig_map(result: Any, scenario: Any, title: str | None = None) -> Any:
    """Top-down view (x-y plane) of one run at its last step.

    True VAs / SPs (hollow markers), true VSs (the vehicles' true positions at the last step),
    the estimated landmarks of the fused map at the last step (filled markers; the vehicles'
    local maps when the run has no fused map), true (solid) and estimated (dashed) trajectories
    and the BS.
    """
    from mmslam.scenes.landmarks import sp_truth, va_truth

    fig, ax = _figure((6.4, 7.6))
    veh = result.vehicles
    names = list(result.meta.get("vehicle_names") or scenario.vehicle_names)
    vidx = np.asarray(veh["vehicle"]).astype(int)
    steps = np.asarray(veh["step"]).astype(int)
    last = int(steps.max()) if steps.size else 0
    for i, name in enumerate(names):
        sel = vidx == i
        order = np.argsort(steps[sel], kind="stable")
        c = VEHICLE_COLORS[i % len(VEHICLE_COLORS)]
        ax.plot(np.asarray(veh["true_x"])[sel][order], np.asarray(veh["true_y"])[sel][order], color=c,
                linestyle="-", linewidth=1.2, label=f"{name} true trajectory", gid=f"true_traj:{name}")
        ax.plot(np.asarray(veh["x"])[sel][order], np.asarray(veh["y"])[sel][order], color=c,
                linestyle="--", linewidth=1.2, label=f"{name} estimate", gid=f"est_traj:{name}")
    bs = scenario.bs_array
    ax.plot([bs[0]], [bs[1]], linestyle="none", marker="^", markersize=10, color=OKABE_ITO["black"],
            label="BS", gid="bs")
    va = np.array(list(va_truth(scenario).values())).reshape(-1, 3)
    sp = np.array(list(sp_truth(scenario).values())).reshape(-1, 3)
    at_last = steps == last
    vs = np.column_stack([np.asarray(veh["true_x"])[at_last], np.asarray(veh["true_y"])[at_last]])
    for ty, pts, mk in (("VA", va, "s"), ("SP", sp, "D"), ("VS", vs, "o")):
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], linestyle="none", marker=mk, markersize=11, markerfacecolor="none",
                    markeredgewidth=1.6, color=TYPE_COLOR[ty], label=f"true {ty}", gid=f"true:{ty}")
    lm = result.landmarks
    lstep = np.asarray(lm["step"]).astype(int)
    lmap = np.asarray(lm["map"]).astype(str)
    sel = lstep == last
    shown = "fused" if np.any(sel & (lmap == "fused")) else "local"
    if shown == "fused":
        sel &= lmap == "fused"
    ltype = np.asarray(lm["type"]).astype(str)
    for ty, mk in (("VA", "s"), ("SP", "D"), ("VS", "o")):
        s = sel & (ltype == ty)
        ax.plot(np.asarray(lm["x"])[s], np.asarray(lm["y"])[s], linestyle="none", marker="x", markersize=8,
                markeredgewidth=2.0, color=TYPE_COLOR[ty], label=f"estimated {ty} ({shown} map)",
                gid=f"est:{ty}")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (east) [m]")
    ax.set_ylabel("y (north) [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), fontsize=7, ncol=3, frameon=False)
    variant = result.meta.get("variant", "")
    seed = result.meta.get("seed", "")
    ax.set_title(title or f"{variant}, seed {seed}: map at step {last}")
    return fig


def save_figure(fig: Any, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` atomically in the format of ``path``'s suffix (png, pdf, svg)."""
    from mmslam.outputs import save_figure as _save

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return _save(fig, p, dpi=dpi)
