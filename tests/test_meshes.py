"""Scene meshes and XML: geometry of the exported PLYs, and that Sionna loads the XML by name."""
from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

from mmslam.errors import ConfigError
from mmslam.scenes.meshes import build_scene, car_mesh, resolve_xml_scene
from mmslam.scenes.plan import plot_plan
from mmslam.scenes.scenario import load_preset


@pytest.fixture(scope="module")
def street_dir(tmp_path_factory):
    scn = load_preset("street")
    d = tmp_path_factory.mktemp("street")
    return scn, build_scene(scn, d)


def test_ply_geometry_matches_scenario(street_dir):
    scn, xml = street_dir
    meshes = xml.parent / "meshes"
    for b in scn.buildings:
        m = trimesh.load(meshes / f"{b.name}.ply")
        np.testing.assert_allclose(m.bounds, [b.min, b.max], atol=1e-6)
        assert m.is_watertight and m.volume > 0  # outward normals
    for s in scn.scatterers:
        m = trimesh.load(meshes / f"{s.name}.ply")
        np.testing.assert_allclose(m.bounds.mean(axis=0), s.position, atol=1e-6)
        np.testing.assert_allclose(m.bounds[1] - m.bounds[0], [s.size] * 3, atol=1e-6)
    g = trimesh.load(meshes / "ground.ply")
    e = scn.ground.extent / 2
    np.testing.assert_allclose(g.bounds, [[-e, -e, scn.ground.z], [e, e, scn.ground.z]])
    np.testing.assert_allclose(g.face_normals, [[0, 0, 1], [0, 0, 1]])


def test_car_body_roof_below_antenna_along_heading():
    scn = load_preset("paper")
    v = scn.vehicles[0]  # heading pi/2: long axis along y
    m = car_mesh(v)
    x, y, z = v.initial_state[:3]
    lo, hi = m.bounds
    np.testing.assert_allclose(hi[2], z - v.roof_gap, atol=1e-9)
    np.testing.assert_allclose(lo[2], z - v.roof_gap - v.height, atol=1e-9)
    np.testing.assert_allclose(hi[:2] - lo[:2], [v.width, v.length], atol=1e-9)
    np.testing.assert_allclose((hi[:2] + lo[:2]) / 2, [x, y], atol=1e-9)
    # heading 30 deg: the long edge direction of the top face is along the heading
    st = np.array(v.initial_state)
    st[3] = np.pi / 6
    m2 = car_mesh(v, st)
    vt = m2.vertices[np.isclose(m2.vertices[:, 2], z - v.roof_gap)]
    d = vt[:, None, :2] - vt[None, :, :2]
    L = np.linalg.norm(d, axis=2)
    i, j = np.unravel_index(np.argmin(np.abs(L - v.length)), L.shape)
    ang = np.arctan2(d[i, j, 1], d[i, j, 0]) % np.pi
    assert ang == pytest.approx(np.pi / 6, abs=1e-9)


def test_xml_materials_ids_keep_scattering(street_dir):
    scn, xml = street_dir
    root = ET.parse(xml).getroot()
    mats = {b.get("id"): b for b in root.findall("bsdf")}
    assert all(not (i.startswith("itu") or i.startswith("mat-")) for i in mats)
    shapes = {s.get("id"): s.find("ref").get("id") for s in root.findall("shape")}
    expected = {f"mesh-{n}" for n in [*(b.name for b in scn.buildings), *(s.name for s in scn.scatterers),
                                      "ground", *scn.vehicle_names]}
    assert set(shapes) == expected

    def coef(sid: str) -> float:
        b = mats[shapes[sid]]
        return float(b.find("float[@name='scattering_coefficient']").get("value"))

    assert coef("mesh-ne_tower") == 0.0 and coef("mesh-ground") == 0.0
    assert coef("mesh-lamp_ne") == pytest.approx(0.7) and coef("mesh-car_a") == pytest.approx(0.5)
    assert mats[shapes["mesh-nw_shop"]].find("string[@name='type']").get("value") == "brick"


def test_sionna_loads_xml_with_scenario_names(street_dir):
    scn, xml = street_dir
    from mmslam.backend import import_mitsuba

    import_mitsuba()
    import sionna.rt as rt

    scene = rt.load_scene(str(xml), merge_shapes=False)
    names = {*(b.name for b in scn.buildings), *(s.name for s in scn.scatterers), "ground", *scn.vehicle_names}
    assert set(scene.objects) == names
    assert float(scene.objects["lamp_nw"].radio_material.scattering_coefficient.numpy()[0]) == pytest.approx(0.7)
    assert float(scene.objects["car_b"].radio_material.scattering_coefficient.numpy()[0]) == pytest.approx(0.5)
    assert float(scene.objects["se_hall"].radio_material.scattering_coefficient.numpy()[0]) == 0.0
    assert scene.objects["nw_shop"].radio_material.itu_type == "brick"
    scene.frequency = 28e9  # all materials valid at 28 GHz (raises otherwise)
    bb = scene.objects["ne_tower"].mi_mesh.bbox()
    np.testing.assert_allclose([bb.min.x, bb.min.y, bb.min.z, bb.max.x, bb.max.y, bb.max.z],
                               [15, 15, 0, 45, 45, 30], atol=1e-4)


def test_xml_scene_external_is_merged(tmp_path):
    scn = dataclasses.replace(load_preset("paper"), xml_scene="sionna:floor_wall", buildings=(), scatterers=())
    xml = build_scene(scn, tmp_path)
    root = ET.parse(xml).getroot()
    ids = {s.get("id") for s in root.findall("shape")}
    assert ids == {"mesh-floor", "mesh-wall", "mesh-veh1", "mesh-veh2"}
    for s in root.findall("shape"):
        fn = s.find("string[@name='filename']").get("value")
        assert (xml.parent / fn).is_file()
    clash = dataclasses.replace(scn, vehicles=(dataclasses.replace(scn.vehicles[0], name="wall"),))
    with pytest.raises(ConfigError, match=r"\['wall'\] already exist in xml_scene"):
        build_scene(clash, tmp_path / "clash")
    with pytest.raises(ConfigError, match="no such Sionna scene"):
        resolve_xml_scene("sionna:nope")
    with pytest.raises(ConfigError, match="file not found"):
        resolve_xml_scene(str(tmp_path / "missing.xml"))


def test_plot_plan_writes_png(tmp_path):
    out = plot_plan(load_preset("paper"), tmp_path / "plan.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in tmp_path.iterdir() if p.name != "plan.png"]  # no temp files left


def test_scene_cli_list_build_show(tmp_path, capsys):
    from mmslam.cli import main

    assert main(["scene", "list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert any(l.startswith("paper: 2 vehicles, 4 buildings, 4 scatterers") and "40 steps" in l for l in lines)
    assert any(l.startswith("street: 3 vehicles, 7 buildings") and "60 steps" in l for l in lines)
    assert main(["scene", "build", "paper", "--out", str(tmp_path / "s")]) == 0
    assert (tmp_path / "s" / "paper.xml").is_file()
    assert sorted(p.name for p in (tmp_path / "s" / "meshes").iterdir()) == sorted(
        f"{n}.ply" for n in ["wall_east", "wall_west", "wall_north", "wall_south", "sp_ne", "sp_nw", "sp_sw",
                             "sp_se", "veh1", "veh2"])
    assert main(["scene", "show", "paper", "--out", str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").is_file()
    capsys.readouterr()
    assert main(["scene", "build", "no_such_preset", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: unknown scenario 'no_such_preset'")
