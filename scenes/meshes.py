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
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from mmslam.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover  (types only: the scenario loader sits above this module)
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


def scene_files(scn: Scenario) -> list[str]:
    """The files :func:`build_scene` writes, relative to its folder: ``meshes/<object>.ply`` per scenario
    object (:func:`scene_objects`' names) and ``<scenario>.xml``."""
    names = [b.name for b in scn.buildings] + [s.name for s in scn.scatterers]
    names += ["ground"] * (scn.ground is not None) + [v.name for v in scn.vehicles]
    return [f"meshes/{n}.ply" for n in names] + [f"{scn.name}.xml"]


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
