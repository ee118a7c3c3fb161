"""Step through one filter run: per-step vehicles, maps and traced paths (HTML viewer, animation).

One run (one variant, one seed, a :class:`mmslam.slam.filter.result.Result`) is turned into frames, one
per time step k, each holding (top-down, x east / y north, metres, global frame):

- every vehicle's true and estimated position at k and both trajectories up to k, with its 3-D
  position error [m];
- the estimated landmarks (extracted Gaussians of the PHD) of one map at k: the BS's fused map or
  one vehicle's local map, by type (VA / SP / VS), with their weights, and that map's GOSPA per
  type at k;
- the truth: VA image sources and SP reference points (those seen in the traced paths when the
  cache is at hand, else the scenario's), and the vehicles' true positions as the true VS;
- the traced paths of step k when the cache is at hand: a polyline BS -> first interaction point
  -> receiving vehicle per path (``paths`` table of the cache; line of sight BS -> vehicle).

:func:`viewer_data` gathers that into one JSON-ready dict (positions rounded to 1 cm);
:func:`viewer_html` renders it as a self-contained HTML fragment (inline SVG, a step slider, play
button, map selector, path toggle; no network, no external script), and :data:`VIEWER_JS` is the
renderer it embeds (a pure function ``mmslamFrameSVG(data, k, map, showPaths)`` returning the SVG of
one frame, plus the DOM glue). :func:`animate` draws the same frames with matplotlib into a GIF
(Pillow) or MP4 (ffmpeg) file for ``mmslam slam --animate``.
"""
from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.model import LandmarkType

TYPES: tuple[str, ...] = ("VA", "SP", "VS")
"""Landmark types drawn (the mapped types of the built-in filter)."""
TYPE_COLOR: dict[str, str] = {"VA": "#E69F00", "SP": "#009E73", "VS": "#CC79A7", "BS": "#000000",
                              "OTHER": "#999999"}
"""Okabe-Ito colours per type (the same as the report's figures)."""
VEHICLE_COLORS: tuple[str, ...] = ("#0072B2", "#D55E00", "#56B4E9", "#009E73", "#E69F00", "#CC79A7")
"""One colour per vehicle (cycled)."""
ANIMATION_FORMATS: tuple[str, ...] = ("gif", "mp4")
"""File suffixes :func:`animate` writes."""


def _r(x: Any) -> float | None:
    """Round to 1 cm for display; NaN / inf -> None (JSON null)."""
    v = float(x)
    return round(v, 2) if math.isfinite(v) else None


def _path_truth(paths: dict[str, np.ndarray], type_code: int) -> list[list[float | None]]:
    """Unique ground-truth landmark positions ``[x, y, z]`` of one type seen in ``paths``."""
    sel = np.asarray(paths["type"]).astype(int) == type_code
    ids = np.asarray(paths["landmark_id"]).astype(str)[sel]
    xyz = np.column_stack([np.asarray(paths[c], float)[sel] for c in ("lm_x", "lm_y", "lm_z")])
    out: dict[str, list[float | None]] = {}
    for i, lid in enumerate(ids):
        if lid not in out and np.all(np.isfinite(xyz[i])):
            out[lid] = [_r(v) for v in xyz[i]]
    return [out[k] for k in sorted(out)]


def viewer_data(result: Any, scenario: Any, paths: dict[str, np.ndarray] | None = None,
                title: str | None = None) -> dict[str, Any]:
    """Frames of one run as a JSON-ready dict (the input of :func:`viewer_html` and :func:`animate`).

    Args:
        result: a :class:`mmslam.slam.filter.result.Result` (its ``vehicles``, ``metrics``, ``landmarks``).
        scenario: the run's :class:`mmslam.scenes.scenario.Scenario` (BS position, vehicle names,
            and the VA / SP truth when ``paths`` is None).
        paths: the cache's ``paths`` table (columns of :data:`mmslam.raytrace.schema.PATH_SPEC`), or
            None to draw no paths.
        title: a title (default: variant and seed from ``result.meta``).

    Returns:
        ``{"title", "steps": [k...] (K,), "bounds": [xmin, xmax, ymin, ymax] m, "bs": [x, y],
        "colors": {type: css}, "vehicles": [{"name", "color", "true": (K, 2), "est": (K, 2),
        "err": (K,) m}], "truth": {"VA": (n, 3), "SP": (n, 3)}, "maps": ["fused"?, vehicle...],
        "estimates": {map: [[[type, x, y, weight], ...] per step]}, "gospa": {map: {type: (K,)}},
        "paths": [[[rx, type, [[x, y], ...]], ...] per step] | None}``; positions in metres,
        rounded to 1 cm, missing values as None.
    """
    veh = result.vehicles
    names = [str(n) for n in (result.meta.get("vehicle_names") or scenario.vehicle_names)]
    vstep = np.asarray(veh["step"]).astype(int)
    vidx = np.asarray(veh["vehicle"]).astype(int)
    steps = sorted(set(vstep.tolist()))
    kpos = {k: i for i, k in enumerate(steps)}
    K = len(steps)
    vehicles = []
    for i, name in enumerate(names):
        true = [[None, None] for _ in range(K)]
        est = [[None, None] for _ in range(K)]
        err: list[float | None] = [None] * K
        for row in np.flatnonzero(vidx == i):
            j = kpos[int(vstep[row])]
            true[j] = [_r(veh["true_x"][row]), _r(veh["true_y"][row])]
            est[j] = [_r(veh["x"][row]), _r(veh["y"][row])]
            err[j] = _r(veh["pos_err"][row])
        vehicles.append({"name": name, "color": VEHICLE_COLORS[i % len(VEHICLE_COLORS)], "true": true,
                         "est": est, "err": err})

    lm = result.landmarks
    lmap = np.asarray(lm["map"]).astype(str)
    maps = (["fused"] if "fused" in set(lmap.tolist()) or _has_fused_metrics(result) else []) + names
    estimates: dict[str, list[list[list[Any]]]] = {m: [[] for _ in range(K)] for m in maps}
    lstep = np.asarray(lm["step"]).astype(int)
    ltype = np.asarray(lm["type"]).astype(str)
    for row in range(len(lstep)):
        m, k = lmap[row], int(lstep[row])
        if m in estimates and k in kpos and ltype[row] in TYPES:
            estimates[m][kpos[k]].append([ltype[row], _r(lm["x"][row]), _r(lm["y"][row]),
                                          round(float(lm["weight"][row]), 3)])

    met = result.metrics
    gospa: dict[str, dict[str, list[float | None]]] = {m: {t: [None] * K for t in TYPES} for m in maps}
    mstep = np.asarray(met["step"]).astype(int)
    mmap = np.asarray(met["map"]).astype(str)
    mtype = np.asarray(met["type"]).astype(str)
    for row in range(len(mstep)):
        m, t, k = mmap[row], mtype[row], int(mstep[row])
        if m in gospa and t in gospa[m] and k in kpos:
            gospa[m][t][kpos[k]] = _r(met["gospa"][row])

    if paths is not None:
        truth = {"VA": _path_truth(paths, int(LandmarkType.VA)), "SP": _path_truth(paths, int(LandmarkType.SP))}
    else:
        from mmslam.scenes.landmarks import sp_truth, va_truth

        truth = {"VA": [[_r(v) for v in p] for p in va_truth(scenario).values()],
                 "SP": [[_r(v) for v in p] for p in sp_truth(scenario).values()]}
    bs = [float(v) for v in scenario.bs_array[:2]]
    frames_paths = _frame_paths(paths, kpos, vehicles, bs) if paths is not None else None

    pts = [bs] + [p for v in vehicles for p in v["true"] + v["est"] if p[0] is not None]
    pts += [p[:2] for ty in truth.values() for p in ty]
    arr = np.asarray(pts, float)
    lo, hi = arr.min(axis=0), arr.max(axis=0)
    pad = 0.06 * float(max(hi - lo)) + 5.0
    bounds = [_r(lo[0] - pad), _r(hi[0] + pad), _r(lo[1] - pad), _r(hi[1] + pad)]
    meta = result.meta
    return {"title": title or f"{meta.get('variant', '')}, seed {meta.get('seed', '')}, "
                              f"P = {meta.get('particles', '')}",
            "steps": steps, "bounds": bounds, "bs": [_r(bs[0]), _r(bs[1])], "colors": TYPE_COLOR,
            "vehicles": vehicles, "truth": truth, "maps": maps, "estimates": estimates, "gospa": gospa,
            "paths": frames_paths}


def _has_fused_metrics(result: Any) -> bool:
    return "fused" in set(np.asarray(result.metrics["map"]).astype(str).tolist())


def _frame_paths(paths: dict[str, np.ndarray], kpos: dict[int, int], vehicles: list[dict[str, Any]],
                 bs: list[float]) -> list[list[list[Any]]]:
    """Per step: ``[rx, type name, [[x, y] BS, [x, y] first bounce (if any), [x, y] receiver]]``."""
    out: list[list[list[Any]]] = [[] for _ in kpos]
    step = np.asarray(paths["step"]).astype(int)
    rx = np.asarray(paths["rx"]).astype(int)
    typ = np.asarray(paths["type"]).astype(int)
    bx, by = np.asarray(paths["bounce_x"], float), np.asarray(paths["bounce_y"], float)
    for row in range(len(step)):
        j = kpos.get(int(step[row]))
        r = int(rx[row])
        if j is None or r >= len(vehicles) or vehicles[r]["true"][j][0] is None:
            continue
        pts = [[_r(bs[0]), _r(bs[1])]]
        if math.isfinite(bx[row]) and math.isfinite(by[row]):
            pts.append([_r(bx[row]), _r(by[row])])
        pts.append(vehicles[r]["true"][j])
        out[j].append([r, LandmarkType(int(typ[row])).name, pts])
    return out


VIEWER_JS = r"""
function mmslamFrameSVG(D, j, map, showPaths) {
  // One frame (step index j into D.steps) of the viewer as an SVG string: y axis up (north).
  const [x0, x1, y0, y1] = D.bounds, W = 640, H = Math.round(W * (y1 - y0) / (x1 - x0));
  const sx = x => ((x - x0) / (x1 - x0) * W).toFixed(1), sy = y => ((y1 - y) / (y1 - y0) * H).toFixed(1);
  const out = [`<svg xmlns="http://www.w3.org/2000/svg" width="${W}" height="${H}" viewBox="0 0 ${W} ${H}" class="frame">`,
               `<rect width="${W}" height="${H}" fill="#fff" stroke="#ccc"/>`];
  const esc = s => String(s).replace(/[&<>"]/g, c => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;"}[c]));
  if (showPaths && D.paths) {
    for (const [rx, type, pts] of D.paths[j]) {
      const p = pts.map(q => `${sx(q[0])},${sy(q[1])}`).join(" ");
      out.push(`<polyline class="path" data-type="${type}" data-rx="${rx}" points="${p}" fill="none" stroke="${D.colors[type] || "#999"}" stroke-width="0.8" opacity="0.55"/>`);
    }
  }
  for (const type of ["VA", "SP"]) {
    for (const p of D.truth[type]) {
      const s = type === "VA" ? `<rect x="${(sx(p[0]) - 5).toFixed(1)}" y="${(sy(p[1]) - 5).toFixed(1)}" width="10" height="10"`
                              : `<circle cx="${sx(p[0])}" cy="${sy(p[1])}" r="5"`;
      out.push(`${s} class="truth" data-type="${type}" fill="none" stroke="${D.colors[type]}" stroke-width="1.5"/>`);
    }
  }
  out.push(`<path class="bs" d="M${sx(D.bs[0])},${(sy(D.bs[1]) - 8).toFixed(1)} l7,13 h-14 z" fill="#000"/>`);
  D.vehicles.forEach((v, i) => {
    for (const [key, dash] of [["true", ""], ["est", ' stroke-dasharray="4 3"']]) {
      const pts = v[key].slice(0, j + 1).filter(q => q[0] !== null).map(q => `${sx(q[0])},${sy(q[1])}`).join(" ");
      out.push(`<polyline class="traj-${key}" data-vehicle="${i}" points="${pts}" fill="none" stroke="${v.color}" stroke-width="1.4"${dash}/>`);
    }
    const t = v.true[j], e = v.est[j];
    if (t[0] !== null) out.push(`<circle class="truth" data-type="VS" data-vehicle="${i}" cx="${sx(t[0])}" cy="${sy(t[1])}" r="7" fill="none" stroke="${D.colors.VS}" stroke-width="1.5"/><circle class="vehicle-true" data-vehicle="${i}" cx="${sx(t[0])}" cy="${sy(t[1])}" r="3.5" fill="${v.color}"/>`);
    if (e[0] !== null) out.push(`<path class="vehicle-est" data-vehicle="${i}" d="M${sx(e[0]) - 5},${sy(e[1])} h10 M${sx(e[0])},${sy(e[1]) - 5} v10" stroke="${v.color}" stroke-width="2"/>`);
  });
  for (const [type, x, y, w] of (D.estimates[map] || [])[j] || []) {
    if (x === null || y === null) continue;
    out.push(`<path class="estimate" data-type="${type}" data-weight="${w}" d="M${(sx(x) - 5).toFixed(1)},${(sy(y) - 5).toFixed(1)} l10,10 M${(sx(x) - 5).toFixed(1)},${(+sy(y) + 5).toFixed(1)} l10,-10" stroke="${D.colors[type]}" stroke-width="2.2"/>`);
  }
  out.push(`<text x="8" y="18" font-size="13" font-family="sans-serif">${esc(D.title)}: step ${D.steps[j]}, ${esc(map)} map</text>`);
  out.push("</svg>");
  return out.join("\n");
}

function mmslamFrameText(D, j, map) {
  // The frame's numbers: GOSPA of the shown map per type and each vehicle's position error.
  const g = D.gospa[map] || {};
  const parts = ["VA", "SP", "VS"].filter(t => g[t] && g[t][j] !== null).map(t => `GOSPA ${t} ${g[t][j].toFixed(2)} m`);
  const errs = D.vehicles.filter(v => v.err[j] !== null).map(v => `${v.name} error ${v.err[j].toFixed(2)} m`);
  const n = D.paths ? D.paths[j].length : null;
  return parts.concat(errs).join(" | ") + (n === null ? "" : ` | ${n} traced paths`);
}

function mmslamViewer(root) {
  const D = JSON.parse(root.querySelector("script.viewer-data").textContent);
  const slider = root.querySelector("input.step"), sel = root.querySelector("select.map");
  const box = root.querySelector("div.frame-box"), info = root.querySelector("p.frame-text");
  const paths = root.querySelector("input.paths"), play = root.querySelector("button.play");
  let timer = null;
  const draw = () => {
    const j = +slider.value;
    box.innerHTML = mmslamFrameSVG(D, j, sel.value, paths.checked);
    info.textContent = mmslamFrameText(D, j, sel.value);
  };
  for (const el of [slider, sel, paths]) el.addEventListener("input", draw);
  sel.addEventListener("change", draw);
  play.addEventListener("click", () => {
    if (timer) { clearInterval(timer); timer = null; play.textContent = "play"; return; }
    play.textContent = "pause";
    timer = setInterval(() => { slider.value = (+slider.value + 1) % D.steps.length; draw(); }, 400);
  });
  draw();
}

if (typeof document !== "undefined") {
  document.addEventListener("DOMContentLoaded", () => document.querySelectorAll("div.mmslam-viewer").forEach(mmslamViewer));
}
if (typeof module !== "undefined") module.exports = { mmslamFrameSVG, mmslamFrameText };
"""
"""The viewer's renderer (plain JavaScript, no library): embedded once per HTML page."""


def _json_script(data: dict[str, Any]) -> str:
    """``data`` as JSON safe inside a ``<script>`` element (no ``</`` sequence)."""
    return json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")


def viewer_html(data: dict[str, Any], element_id: str = "viewer", script: bool = True) -> str:
    """A self-contained HTML fragment that steps through ``data`` (from :func:`viewer_data`).

    A ``div.mmslam-viewer`` holding the data (``script.viewer-data``, JSON), a step slider
    (``input.step``, 0 .. K-1), a map selector, a path toggle, a play button, the frame's SVG and
    its numbers. ``script=False`` leaves out :data:`VIEWER_JS` (a page with several viewers embeds
    it once).
    """
    n = len(data["steps"])
    opts = "".join(f'<option value="{html.escape(m)}">{html.escape(m)}{" (BS)" if m == "fused" else ""}</option>'
                   for m in data["maps"])
    has_paths = data.get("paths") is not None
    return (f'<div class="mmslam-viewer" id="{html.escape(element_id)}">'
            f'<script type="application/json" class="viewer-data">{_json_script(data)}</script>'
            f'<p class="viewer-controls"><button type="button" class="play">play</button> '
            f'<label>step <input class="step" type="range" min="0" max="{max(n - 1, 0)}" value="{max(n - 1, 0)}" '
            f'step="1"></label> <label>map <select class="map">{opts}</select></label> '
            f'<label><input class="paths" type="checkbox"{" checked" if has_paths else " disabled"}> traced paths'
            f'{"" if has_paths else " (cache not found)"}</label></p>'
            f'<div class="frame-box"></div><p class="frame-text"></p>'
            f'<p class="legend">Hollow squares / circles: true VA image sources / SPs (seen in the traced paths); '
            f'hollow ring: a vehicle\'s true position (true VS); filled dot and solid line: true position and '
            f'trajectory; plus and dashed line: estimated; x: estimated landmarks of the selected map; lines: '
            f'traced paths BS - first bounce - vehicle, coloured by type.</p></div>'
            + (f"<script>{VIEWER_JS}</script>" if script else ""))


def check_animation_target(path: str | Path, force: bool = False, option: str = "--animate") -> str:
    """Check an animation file target before any work; returns its format (``gif`` or ``mp4``).

    The same rule as figures (:func:`mmslam.outputs.check_figure_target`): a missing file or one
    mmslam wrote, with or without ``force``. An MP4 needs ffmpeg on the PATH.
    """
    from mmslam.outputs import check_figure_target

    fmt = check_figure_target(path, force, option, formats=ANIMATION_FORMATS)
    if fmt == "mp4":
        from matplotlib import animation

        if not animation.writers.is_available("ffmpeg"):
            from mmslam.errors import MmslamError

            raise MmslamError(f"{option} {path}: writing .mp4 needs ffmpeg, which is not installed; install "
                              "it (apt-get install ffmpeg) or give a .gif file name")
    return fmt


def animate(data: dict[str, Any], path: str | Path, map: str | None = None, fps: float = 4.0,
            dpi: int = 100) -> Path:
    """Draw every frame of ``data`` (from :func:`viewer_data`) into a GIF or MP4, atomically.

    The same frames as the HTML viewer: paths, truth, vehicles, the estimates of ``map`` (default:
    the fused map if any, else the first vehicle's), and the frame's numbers as the title.
    """
    import os
    import tempfile

    from matplotlib import animation
    from matplotlib.figure import Figure

    from mmslam import __version__
    from mmslam.outputs import FIGURE_TOKEN, apply_umask, figure_format

    p = Path(path)
    fmt = figure_format(p, "--animate", formats=ANIMATION_FORMATS)
    shown = map or data["maps"][0]
    x0, x1, y0, y1 = data["bounds"]
    fig = Figure(figsize=(6.4, max(3.0, 6.4 * (y1 - y0) / (x1 - x0)) + 0.6))
    ax = fig.add_subplot(1, 1, 1)

    def frame(j: int) -> None:
        ax.clear()
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.set_xlabel("x (east) [m]")
        ax.set_ylabel("y (north) [m]")
        if data.get("paths"):
            for _rx, ty, pts in data["paths"][j]:
                q = np.asarray(pts, float)
                ax.plot(q[:, 0], q[:, 1], color=data["colors"].get(ty, "#999999"), linewidth=0.6, alpha=0.55)
        for ty, mk in (("VA", "s"), ("SP", "o")):
            q = np.asarray(data["truth"][ty], float).reshape(-1, 3)
            ax.plot(q[:, 0], q[:, 1], linestyle="none", marker=mk, markerfacecolor="none",
                    color=data["colors"][ty], markersize=7)
        ax.plot([data["bs"][0]], [data["bs"][1]], marker="^", color="black", markersize=9, linestyle="none")
        for v in data["vehicles"]:
            for key, ls in (("true", "-"), ("est", "--")):
                q = np.asarray([p if p[0] is not None else [np.nan, np.nan] for p in v[key][: j + 1]], float)
                ax.plot(q[:, 0], q[:, 1], linestyle=ls, color=v["color"], linewidth=1.2)
            t, e = v["true"][j], v["est"][j]
            if t[0] is not None:
                ax.plot([t[0]], [t[1]], marker="o", color=v["color"], markersize=5)
                ax.plot([t[0]], [t[1]], marker="o", markerfacecolor="none", color=data["colors"]["VS"],
                        markersize=11)
            if e[0] is not None:
                ax.plot([e[0]], [e[1]], marker="+", color=v["color"], markersize=10, markeredgewidth=2)
        for ty, x, y, _w in data["estimates"].get(shown, [[]] * len(data["steps"]))[j]:
            if x is not None and y is not None:
                ax.plot([x], [y], marker="x", color=data["colors"][ty], markersize=8, markeredgewidth=2)
        g = data["gospa"].get(shown, {})
        nums = ", ".join(f"{t} {g[t][j]:.1f}" for t in TYPES if t in g and g[t][j] is not None)
        ax.set_title(f"{data['title']}: step {data['steps'][j]}, {shown} map"
                     + (f"\nGOSPA [m] {nums}" if nums else ""), fontsize=9)

    anim = animation.FuncAnimation(fig, frame, frames=len(data["steps"]), interval=1000.0 / fps)
    comment = f"{FIGURE_TOKEN} {__version__}"
    if fmt == "gif":
        writer: Any = animation.PillowWriter(fps=fps, metadata={"comment": comment})
    else:
        writer = animation.FFMpegWriter(fps=fps, metadata={"comment": comment})
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=f".{fmt}", dir=p.parent)
    os.close(fd)
    try:
        anim.save(tmp, writer=writer, dpi=dpi)
        if fmt == "gif":
            _tag_gif(Path(tmp), comment)
        apply_umask(tmp, is_dir=False)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


def _tag_gif(path: Path, comment: str) -> None:
    """Make sure the GIF holds ``comment`` (Pillow's writer may drop metadata): a comment extension."""
    data = path.read_bytes()
    if comment.encode() in data:
        return
    # GIF comment extension (0x21 0xFE), one sub-block, inserted before the trailer byte 0x3B.
    block = b"\x21\xfe" + bytes([len(comment)]) + comment.encode() + b"\x00"
    path.write_bytes(data[:-1] + block + data[-1:])
