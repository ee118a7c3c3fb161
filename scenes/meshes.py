"""Scene geometry for Sionna RT: trimesh meshes -> one PLY per object + a Mitsuba XML.

Global frame: x east, y north, z up, metres; headings in radians (counter-clockwise from +x).

Objects (the XML shape id is ``mesh-<name>``, which Sionna turns into the object name
``<name>``, so scene object names equal scenario names):

- each building: its axis-aligned box;
- each scatterer: a box of edge ``size`` or a cylinder of diameter and height ``size``, centred
  at its reference point;
- the ground (if any): a square of side ``extent`` at height ``z``, normal +z, named ``ground``;
- each vehicle: a ``length x width x height`` box whose roof is ``roof_gap`` m below the antenna
  position ``(x, y, z)`` of its initial state, long axis along the initial heading.

Radio materials are Sionna ``itu-radio-material`` BSDFs, one per distinct
``(ITU type, scattering coefficient)``; their ids (``rm:<type>:s<coef>``) contain ``:`` so they
can never collide with object names and do not start with ``itu_``/``mat-`` (Sionna's XML
preprocessor rewrites those and drops ``scattering_coefficient``). Buildings and the ground get
scattering coefficient 0 (specular only); scatterers and cars get theirs (> 0: diffuse paths).

With ``scenario.xml_scene`` set (a file path, or ``sionna:<name>`` for a scene shipped with
sionna-rt such as ``sionna:munich``), the external scene's XML is copied with absolute mesh
paths, and the scenario's own objects (vehicles, buildings, scatterers, ground) are appended.

This module does not import Sionna or Mitsuba.
"""
from __future__ import annotations

import importlib.util
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import trimesh

from mmslam.errors import ConfigError
from mmslam.scenes.scenario import Scenario, Scatterer, Vehicle

MATERIAL_THICKNESS_M = 0.1
"""Thickness given to every radio material (m); irrelevant with refraction off."""


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    from mmslam.outputs import atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data, fsync=False)


# ====================================================================== meshes
def box_mesh(lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh:
    """Axis-aligned box with corners ``lo``/``hi`` (m, global frame), outward face normals."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2.0)
    return m


def scatterer_mesh(s: Scatterer) -> trimesh.Trimesh:
    """Box (edge ``size``) or vertical cylinder (diameter = height = ``size``) centred at ``s.position``."""
    c = np.asarray(s.position, float)
    if s.shape == "cylinder":
        m = trimesh.creation.cylinder(radius=s.size / 2.0, height=s.size, sections=24)
    else:
        m = trimesh.creation.box(extents=(s.size, s.size, s.size))
    m.apply_translation(c)
    return m


def ground_mesh(z: float, extent: float) -> trimesh.Trimesh:
    """Square ``extent`` x ``extent`` m at height ``z`` centred on the origin, normal +z."""
    e = extent / 2.0
    v = np.array([[-e, -e, z], [e, -e, z], [e, e, z], [-e, e, z]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def car_local_vertices(v: Vehicle) -> tuple[np.ndarray, np.ndarray]:
    """Car body box in the vehicle frame: vertices ``(8, 3)`` (m) and faces ``(12, 3)``.

    Vehicle frame: origin at the antenna, x forward (heading), y left, z up. The box spans
    ``x in [-L/2, L/2]``, ``y in [-W/2, W/2]``, ``z in [-roof_gap - H, -roof_gap]``.
    """
    m = trimesh.creation.box(extents=(v.length, v.width, v.height))
    m.apply_translation((0.0, 0.0, -v.roof_gap - v.height / 2.0))
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def car_pose_vertices(local: np.ndarray, x: float, y: float, z: float, heading: float) -> np.ndarray:
    """Vehicle-frame vertices ``(n, 3)`` -> global frame for antenna ``(x, y, z)`` and ``heading`` (rad)."""
    c, s = np.cos(heading), np.sin(heading)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return local @ rot.T + np.array([x, y, z], float)


def car_mesh(v: Vehicle, state: np.ndarray | None = None) -> trimesh.Trimesh:
    """Car body of vehicle ``v`` posed at ``state`` (default: its initial state), global frame."""
    st = np.asarray(v.initial_state if state is None else state, float)
    loc, faces = car_local_vertices(v)
    return trimesh.Trimesh(vertices=car_pose_vertices(loc, st[0], st[1], st[2], st[3]), faces=faces,
                           process=False)


# ====================================================================== materials
def material_id(itu_type: str, scattering: float) -> str:
    """Radio-material id for an ITU type and a scattering coefficient (never a valid object name)."""
    return f"rm:{itu_type}:s{scattering:.3f}"


def _material_xml(mid: str, itu_type: str, scattering: float) -> ET.Element:
    e = ET.Element("bsdf", {"type": "itu-radio-material", "id": mid})
    ET.SubElement(e, "string", {"name": "type", "value": itu_type})
    ET.SubElement(e, "float", {"name": "thickness", "value": repr(MATERIAL_THICKNESS_M)})
    ET.SubElement(e, "float", {"name": "scattering_coefficient", "value": repr(float(scattering))})
    return e


def _xml_signature(el: ET.Element) -> tuple:
    """An element's tag, attributes and children, whitespace ignored (to compare two definitions)."""
    return (el.tag, sorted(el.attrib.items()), [_xml_signature(c) for c in el])


def _shape_xml(name: str, filename: str, mid: str) -> ET.Element:
    e = ET.Element("shape", {"type": "ply", "id": f"mesh-{name}"})
    ET.SubElement(e, "string", {"name": "filename", "value": filename})
    ET.SubElement(e, "boolean", {"name": "face_normals", "value": "true"})
    ET.SubElement(e, "ref", {"id": mid, "name": "bsdf"})
    return e


# ====================================================================== external scenes
def resolve_xml_scene(spec: str, base: str | Path | None = None) -> Path:
    """``sionna:<name>`` (a scene shipped with sionna-rt) or a file path -> absolute XML path.

    Relative file paths are taken relative to ``base`` (the scenario file's folder) if it
    exists, else to the working directory. Does not import Sionna.
    """
    if spec.startswith("sionna:"):
        name = spec[len("sionna:"):]
        sp = importlib.util.find_spec("sionna")
        if sp is None or not sp.submodule_search_locations:
            raise ConfigError(f"xml_scene '{spec}': sionna-rt is not installed; install it or give an XML file path")
        root = Path(list(sp.submodule_search_locations)[0]) / "rt" / "scenes"
        p = root / name / f"{name}.xml"
        if not re.fullmatch(r"[A-Za-z0-9_]+", name) or not p.is_file():
            avail = sorted(d.name for d in root.iterdir() if (d / f"{d.name}.xml").is_file()) if root.is_dir() else []
            raise ConfigError(f"xml_scene '{spec}': no such Sionna scene; expected one of "
                              f"{', '.join('sionna:' + a for a in avail)} or an XML file path")
        return p
    p = Path(spec)
    if not p.is_absolute() and base is not None and (Path(base) / p).is_file():
        p = Path(base) / p
    if not p.is_file():
        raise ConfigError(f"xml_scene '{spec}': file not found; give an existing Mitsuba XML file or "
                          "'sionna:<name>' (e.g. sionna:munich)")
    return p.resolve()


def _external_scene(scn: Scenario) -> tuple[list[ET.Element], list[ET.Element], set[str]]:
    """Top-level <bsdf> and <shape> elements of the external XML (mesh paths made absolute),
    and the object names it defines."""
    base = None if scn.source_file.startswith(("<", "preset:")) else Path(scn.source_file).parent
    path = resolve_xml_scene(scn.xml_scene or "", base)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise ConfigError(f"xml_scene '{scn.xml_scene}': not valid XML ({e}); fix or replace the file") from None
    bsdfs, shapes, names = [], [], set()
    for el in root:
        if el.tag == "bsdf":
            bsdfs.append(el)
        elif el.tag == "shape":
            for s in el.iter("string"):
                if s.get("name") == "filename" and not os.path.isabs(s.get("value", "")):
                    s.set("value", str((path.parent / s.get("value", "")).resolve()))
            sid = el.get("id", "")
            names.add(sid[5:] if sid.startswith("mesh-") else sid)
            shapes.append(el)
        # emitters, sensors, integrators etc. are irrelevant to the ray tracer: dropped
    return bsdfs, shapes, names


# ====================================================================== scene build
def scene_objects(scn: Scenario) -> dict[str, tuple[trimesh.Trimesh, str, float]]:
    """Scenario object name -> (mesh in the global frame, ITU material, scattering coefficient).

    Order: buildings, scatterers, ground, vehicles (vehicles at their initial state).
    """
    out: dict[str, tuple[trimesh.Trimesh, str, float]] = {}
    for b in scn.buildings:
        out[b.name] = (box_mesh(np.asarray(b.min), np.asarray(b.max)), b.material, 0.0)
    for s in scn.scatterers:
        out[s.name] = (scatterer_mesh(s), s.material, s.scattering_coefficient)
    if scn.ground is not None:
        if "ground" in out:
            raise ConfigError(f"{scn.source_file}: object name 'ground' is reserved for the ground plane; "
                              "rename that building or scatterer")
        out["ground"] = (ground_mesh(scn.ground.z, scn.ground.extent), scn.ground.material, 0.0)
    for v in scn.vehicles:
        if v.name == "ground" and scn.ground is not None:
            raise ConfigError(f"{scn.source_file}: vehicle name 'ground' is reserved for the ground plane; rename it")
        out[v.name] = (car_mesh(v), v.material, v.scattering_coefficient)
    return out


SCENE_KIND = "scene"
"""Output-marker kind of a ``mmslam scene build`` folder (:mod:`mmslam.outputs`)."""


def build_scene(scn: Scenario, out_dir: str | Path) -> Path:
    """Write ``<out_dir>/meshes/<name>.ply`` per object and ``<out_dir>/<scenario>.xml``.

    Returns the XML path. Every file is written to a temporary name and renamed, the XML last,
    so a reader never sees a partial scene. The XML loads with
    ``sionna.rt.load_scene(xml, merge_shapes=False)`` into one object per scenario object
    (plus the external scene's objects when ``xml_scene`` is set).
    """
    out = Path(out_dir)
    (out / "meshes").mkdir(parents=True, exist_ok=True)
    root = ET.Element("scene", {"version": "2.1.0"})
    ext_bsdfs: list[ET.Element] = []
    ext_shapes: list[ET.Element] = []
    ext_names: set[str] = set()
    if scn.xml_scene:
        ext_bsdfs, ext_shapes, ext_names = _external_scene(scn)
    objs = scene_objects(scn)
    clash = sorted(set(objs) & ext_names)
    if clash:
        raise ConfigError(f"{scn.source_file}: object names {clash} already exist in xml_scene "
                          f"'{scn.xml_scene}'; rename them in the scenario")
    mats: dict[str, tuple[str, float]] = {}
    for _, (_, itu, sc) in objs.items():
        mats.setdefault(material_id(itu, sc), (itu, sc))
    ext_ids = {}
    for el in ext_bsdfs:
        root.append(el)
        ext_ids[el.get("id")] = el
    for mid, (itu, sc) in mats.items():
        if mid in ext_ids:  # an XML that mmslam wrote already defines this material: reuse it if identical
            if _xml_signature(ext_ids[mid]) != _xml_signature(_material_xml(mid, itu, sc)):
                raise ConfigError(f"xml_scene '{scn.xml_scene}': material id '{mid}' is defined differently "
                                  "there; rename that material in the XML")
            continue
        root.append(_material_xml(mid, itu, sc))
    for el in ext_shapes:
        root.append(el)
    for name, (mesh, itu, sc) in objs.items():
        fn = f"meshes/{name}.ply"
        _atomic_write_bytes(out / fn, mesh.export(file_type="ply", encoding="binary"))
        root.append(_shape_xml(name, fn, material_id(itu, sc)))
    ET.indent(root)
    xml = out / f"{scn.name}.xml"
    _atomic_write_bytes(xml, ET.tostring(root, encoding="utf-8", xml_declaration=False) + b"\n")
    return xml


# ====================================================================== plan plot
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


def plot_plan(scn: Scenario, out_png: str | Path, fov_points: int = 4,
              inside: list[tuple[str, int, str, np.ndarray]] | None = None) -> Path:
    """Top-down plan (x east, y north, m): BS, buildings, SPs, VAs, trajectories, FOV circles.

    An external XML scene is drawn as its top-surface height map (buildings as shaded footprints).

    Trajectories start at the open circle; the arrow head marks the last step's direction.

    FOV circles (radius ``sensor.fov_range``) are drawn around ``fov_points`` evenly spaced
    trajectory points of each vehicle. ``inside`` (:func:`mmslam.scenes.geometry.inside_report`):
    a BS or car inside an object is marked with a red cross and named. Written atomically in the format of the file's suffix (png, pdf, svg); returns the path.
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
    for j, (who, k, obj, p) in enumerate(inside if inside is not None else []):
        ax.plot(p[0], p[1], "X", color="red", ms=14, mec="k", zorder=10,
                label="inside an object (not traceable)" if j == 0 else None)
        ax.annotate(f"{who}{'' if k < 0 else f' (step {k})'} inside {obj}", p[:2], textcoords="offset points",
                    xytext=(6, -12), fontsize=8, color="red", zorder=10)
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
