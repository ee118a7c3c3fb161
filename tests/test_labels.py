"""Path labelling on hand-made arrays (no Sionna): one wall, one scatterer, two cars."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.labels import DIFFUSE, SPECULAR, SceneIndex, label_paths
from mmslam.raytrace.schema import PATH_COLUMNS
from mmslam.scenes.scenario import scenario_from_dict
from mmslam.slam.models.measurement import BS, OTHER, SP, VA, VS

BS_POS = np.array([0.0, 0.0, 10.0])


def _scn(ground: bool = False):
    d = {
        "name": "tiny", "bs": BS_POS.tolist(),
        "buildings": [{"name": "wall", "min": [20.0, -10.0, 0.0], "max": [22.0, 10.0, 15.0]}],
        "scatterers": [{"name": "pole", "position": [5.0, 5.0, 2.0], "size": 1.0}],
        "vehicles": [{"name": "car1", "initial_state": [10.0, 0.0, 1.5, 0.0, 5.0, 0.0, 0.0]},
                     {"name": "car2", "initial_state": [10.0, -6.0, 1.5, 0.0, 5.0, 0.0, 0.0]}],
    }
    if ground:
        d["ground"] = {"z": 0.0, "extent": 100.0}
    return scenario_from_dict(d, "<test>")


ANT = np.array([[10.0, 0.0, 1.5], [10.0, -6.0, 1.5]])


def _paths(index: SceneIndex, rows: list[tuple]) -> dict:
    """rows: (rx, [(object name, itype, vertex)], toa, power)."""
    n, D = len(rows), 3
    rx = np.array([r[0] for r in rows])
    obj = np.full((n, D), -1)
    it = np.zeros((n, D), int)
    vt = np.full((n, D, 3), np.nan)
    for i, r in enumerate(rows):
        for j, (name, t, v) in enumerate(r[1]):
            obj[i, j] = index.names.index(name)
            it[i, j] = t
            vt[i, j] = v
    toa = np.array([r[2] for r in rows], float)
    pw = np.array([r[3] for r in rows], float)
    ang = np.tile(np.arange(4, dtype=float) * 0.1, (n, 1)) + np.arange(n)[:, None] * 1e-3
    return dict(rx=rx, obj=obj, itype=it, verts=vt, toa_m=toa, angles=ang, power_db=pw)


ROWS = [
    (0, [], 12.3, -80.0),                                                     # LOS
    (0, [("wall", SPECULAR, [20.0, 1.0, 5.0])], 40.0, -90.0),                 # VA on -x face
    (0, [("pole", DIFFUSE, [4.6, 5.0, 2.0])], 21.0, -120.0),                  # SP cluster ...
    (0, [("pole", DIFFUSE, [5.0, 4.6, 2.2])], 20.5, -110.0),                  # ... strongest
    (0, [("pole", SPECULAR, [5.5, 5.0, 2.0])], 20.9, -115.0),                 # ... (specular, same SP)
    (0, [("car2", DIFFUSE, [10.2, -5.5, 1.45])], 19.0, -130.0),               # VS car2
    (0, [("car1", DIFFUSE, [10.5, 0.2, 1.45])], 15.0, -100.0),                # own car: dropped
    (0, [("wall", SPECULAR, [20.0, 2.0, 4.0]), ("pole", DIFFUSE, [5.0, 5.4, 2.0])], 60.0, -140.0),  # OTHER
    (1, [("car1", SPECULAR, [10.0, -0.9, 1.0])], 18.0, -105.0),               # VS car1 seen by car2
    (1, [("wall", SPECULAR, [20.0, -3.0, 6.0]), ("car2", DIFFUSE, [9.0, -6.0, 1.0])], 50.0, -150.0),  # own: dropped
    (1, [("wall", SPECULAR, [21.0, 3.0, 15.0])], 45.0, -95.0),                # roof (+z face) of the wall
]


def test_tiny_scene_labels_equal_expected_set():
    scn = _scn()
    idx = SceneIndex.from_scenario(scn)
    out = label_paths(idx, antennas=ANT, step=7, **_paths(idx, ROWS))
    got = {(int(r), int(t), str(i)) for r, t, i in zip(out["rx"], out["type"], out["landmark_id"])}
    assert got == {
        (0, BS, "bs"), (0, VA, "wall:-x"), (0, SP, "pole"), (0, VS, "car2"), (0, OTHER, "wall+pole"),
        (1, VS, "car1"), (1, VA, "wall:+z"),
    }
    assert set(out) == set(PATH_COLUMNS)
    assert np.all(out["step"] == 7)
    by = {(int(r), str(i)): k for k, (r, i) in enumerate(zip(out["rx"], out["landmark_id"]))}
    # VA landmark: BS mirrored in x = 20 -> (40, 0, 10); the roof z = 15 -> (0, 0, 20)
    np.testing.assert_allclose([out[c][by[(0, "wall:-x")]] for c in ("lm_x", "lm_y", "lm_z")], [40, 0, 10])
    np.testing.assert_allclose([out[c][by[(1, "wall:+z")]] for c in ("lm_x", "lm_y", "lm_z")], [0, 0, 20])
    # SP cluster: 3 paths, strongest (-110 dB, toa 20.5) kept, spread 21.0 - 20.5
    k = by[(0, "pole")]
    assert out["n_paths"][k] == 3 and out["power_db"][k] == -110.0 and out["toa_m"][k] == 20.5
    assert out["delay_spread_m"][k] == pytest.approx(0.5)
    assert out["diffuse"][k]
    np.testing.assert_allclose([out["bounce_x"][k], out["bounce_y"][k], out["bounce_z"][k]], [5.0, 4.6, 2.2])
    np.testing.assert_allclose([out[c][k] for c in ("lm_x", "lm_y", "lm_z")], [5, 5, 2])
    # the strongest path's angles travel with it (row 3 of the input)
    assert out["aod_az"][k] == pytest.approx(0.0 + 3e-3)
    # VS: the other car's antenna position
    np.testing.assert_allclose([out[c][by[(0, "car2")]] for c in ("lm_x", "lm_y", "lm_z")], ANT[1])
    np.testing.assert_allclose([out[c][by[(1, "car1")]] for c in ("lm_x", "lm_y", "lm_z")], ANT[0])
    assert not out["diffuse"][by[(1, "car1")]]
    # BS row: landmark = BS, no bounce point; OTHER: NaN landmark, 2 bounces
    kb = by[(0, "bs")]
    np.testing.assert_allclose([out[c][kb] for c in ("lm_x", "lm_y", "lm_z")], BS_POS)
    assert np.isnan(out["bounce_x"][kb]) and out["bounces"][kb] == 0
    ko = by[(0, "wall+pole")]
    assert np.isnan(out["lm_x"][ko]) and out["bounces"][ko] == 2
    # sorted by (rx, type, id)
    keys = list(zip(out["rx"], out["type"], out["landmark_id"]))
    assert keys == sorted(keys)


def test_labels_do_not_depend_on_path_order():
    scn = _scn()
    idx = SceneIndex.from_scenario(scn)
    a = label_paths(idx, antennas=ANT, **_paths(idx, ROWS))
    perm = np.random.default_rng(3).permutation(len(ROWS))
    b = label_paths(idx, antennas=ANT, **_paths(idx, [ROWS[i] for i in perm]))
    for c in PATH_COLUMNS:
        if c == "landmark_id":
            assert list(a[c]) == list(b[c])
        elif c == "aod_az" or c.startswith(("aod", "aoa")):
            continue  # the synthetic angles encode the input row number
        else:
            np.testing.assert_array_equal(a[c], b[c])


def test_ground_and_xml_plane_va():
    scn = _scn(ground=True)
    idx = SceneIndex.from_scenario(scn, extra_static=["facade"])
    rows = [(0, [("ground", SPECULAR, [3.0, 0.0, 0.0])], 14.0, -90.0),
            (0, [("facade", SPECULAR, [-5.0, 1.0, 4.0])], 30.0, -95.0),
            (0, [("facade", SPECULAR, [-5.0, 3.0, 6.0])], 31.0, -99.0),   # same plane, other triangle
            (1, [("facade", DIFFUSE, [-5.0, 2.0, 5.0])], 33.0, -120.0)]   # diffuse on a facade: OTHER
    p = _paths(idx, rows)
    nrm = np.full((4, 3, 3), np.nan)
    nrm[1, 0] = [-1.0, 0.0, 0.0]  # triangle normals may point either way: labels orient them to the BS
    nrm[2, 0] = [1.0, 0.0, 0.0]
    nrm[3, 0] = [1.0, 0.0, 0.0]
    out = label_paths(idx, antennas=ANT, normals=nrm, **p)
    got = {(int(r), int(t), str(i)): k for k, (r, t, i) in enumerate(zip(out["rx"], out["type"], out["landmark_id"]))}
    assert set(got) == {(0, VA, "ground:+z"), (0, VA, "plane(+1.0000,+0.0000,+0.0000,-5.000)"), (1, OTHER, "facade")}
    k = got[(0, VA, "ground:+z")]
    np.testing.assert_allclose([out[c][k] for c in ("lm_x", "lm_y", "lm_z")], [0, 0, -10])
    k = got[(0, VA, "plane(+1.0000,+0.0000,+0.0000,-5.000)")]
    np.testing.assert_allclose([out[c][k] for c in ("lm_x", "lm_y", "lm_z")], [-10, 0, 10], atol=1e-12)
    assert out["n_paths"][k] == 2 and out["delay_spread_m"][k] == pytest.approx(1.0)


def test_empty_and_all_dropped_give_empty_tables():
    scn = _scn()
    idx = SceneIndex.from_scenario(scn)
    out = label_paths(idx, antennas=ANT, **_paths(idx, [(0, [("car1", DIFFUSE, [10, 0, 1])], 5.0, -90.0)]))
    assert set(out) == set(PATH_COLUMNS) and all(len(v) == 0 for v in out.values())
    e = _paths(idx, [])
    e["obj"] = np.zeros((0, 3), int); e["itype"] = np.zeros((0, 3), int); e["verts"] = np.zeros((0, 3, 3))
    e["angles"] = np.zeros((0, 4))
    out = label_paths(idx, antennas=ANT, **e)
    assert all(len(v) == 0 for v in out.values())


def test_non_finite_input_is_rejected():
    scn = _scn()
    idx = SceneIndex.from_scenario(scn)
    p = _paths(idx, ROWS[:2])
    p["toa_m"][1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        label_paths(idx, antennas=ANT, **p)


def _box_triangles(lo, hi) -> np.ndarray:
    from mmslam.scenes.meshes import box_mesh

    m = box_mesh(np.asarray(lo, float), np.asarray(hi, float))
    return np.asarray(m.vertices)[np.asarray(m.faces)]


def test_plane_table_of_a_box_has_its_six_face_planes_oriented_to_the_bs():
    from mmslam.raytrace.labels import plane_table

    tri = _box_triangles([20.0, -10.0, 0.0], [22.0, 10.0, 15.0])  # 12 triangles
    pt = plane_table(tri, BS_POS)
    assert len(pt.ids) == 6 and len(set(pt.ids)) == 6
    # each face's two triangles share a plane; the BS (x = 0, z = 10) sees x = 20 from its -x side
    assert all(np.sum(pt.tri_plane == p) == 2 for p in range(6))
    # the BS is at x < 20, -10 < y < 10, 0 < z < 15: every normal points back towards it
    want = {"plane(-1.0000,+0.0000,+0.0000,-20.000)", "plane(-1.0000,+0.0000,+0.0000,-22.000)",
            "plane(+0.0000,-1.0000,+0.0000,-10.000)", "plane(+0.0000,+1.0000,+0.0000,-10.000)",
            "plane(+0.0000,+0.0000,+1.0000,+0.000)", "plane(+0.0000,+0.0000,-1.0000,-15.000)"}
    assert set(pt.ids) == want
    for p in range(6):  # the normal points to the BS's side of each plane
        assert np.dot(pt.normal[p], BS_POS) - pt.offset[p] > 0


def test_plane_table_keeps_one_plane_across_a_rounding_boundary_and_separates_near_planes():
    from mmslam.raytrace.labels import plane_table

    # two triangles of the plane x = 5.0005 (a 1 mm rounding boundary), one nudged by 1e-7 m
    a = np.array([[5.0005, 0.0, 0.0], [5.0005, 1.0, 0.0], [5.0005, 0.0, 1.0]])
    b = a + [[-2e-7, 3.0, 0.0]]
    c = a + [[0.01, 6.0, 0.0]]  # a parallel facade 1 cm behind: another plane
    pt = plane_table(np.stack([a, b, c]), np.array([0.0, 0.0, 0.0]))
    assert pt.tri_plane[0] == pt.tri_plane[1] != pt.tri_plane[2]
    assert len(pt.ids) == 2


def test_coplanar_facades_of_two_objects_are_one_va_with_the_exact_image():
    """A specular hit is a VA of its plane, not of its object: two buildings' facades on x = -5 give one
    VA row (both paths in its cluster), the BS mirrored in x = -5, the same id at any hit point."""
    from mmslam.raytrace.labels import plane_table

    scn = _scn()
    tri_a = np.array([[[-5.0, 0.0, 0.0], [-5.0, 4.0, 0.0], [-5.0, 0.0, 8.0]]])
    tri_b = np.array([[[-5.0, 10.0, 0.0], [-5.0, 14.0, 0.0], [-5.0, 10.0, 8.0]]])
    pt = plane_table(np.concatenate([tri_a, tri_b]), BS_POS)
    assert len(pt.ids) == 1
    idx = SceneIndex.from_scenario(scn, extra_static=["house_a", "house_b"], planes=pt)
    ids = []
    for pa, pb in (([-5.0, 1.0, 4.0], [-5.0, 11.0, 2.0]), ([-5.0, 2.5, 1.0], [-5.0, 12.0, 6.0])):
        rows = [(0, [("house_a", SPECULAR, pa)], 30.0, -95.0), (0, [("house_b", SPECULAR, pb)], 31.0, -99.0)]
        nrm = np.full((2, 3, 3), np.nan)
        nrm[:, 0] = pt.tri_normal[[0, 1]]
        out = label_paths(idx, antennas=ANT, normals=nrm, **_paths(idx, rows))
        assert list(out["type"]) == [VA] and out["n_paths"][0] == 2
        np.testing.assert_allclose([out["lm_x"][0], out["lm_y"][0], out["lm_z"][0]], [-10.0, 0.0, 10.0], atol=1e-12)
        ids.append(str(out["landmark_id"][0]))
    assert ids == ["plane(+1.0000,+0.0000,+0.0000,-5.000)"] * 2


# ------------------------------------------------------------------ second-order reflections (issue 24)
def _canyon_scn():
    """Two parallel walls x = 20 (face -x of 'east') and x = -20 (face +x of 'west'), ground z = 0, a pole."""
    return scenario_from_dict({
        "name": "canyon2", "bs": BS_POS.tolist(), "ground": {"z": 0.0, "extent": 100.0},
        "buildings": [{"name": "east", "min": [20.0, -50.0, 0.0], "max": [22.0, 50.0, 15.0]},
                      {"name": "west", "min": [-22.0, -50.0, 0.0], "max": [-20.0, 50.0, 15.0]}],
        "scatterers": [{"name": "pole", "position": [5.0, 5.0, 2.0], "size": 1.0}],
        "vehicles": [{"name": "car1", "initial_state": [10.0, 5.0, 1.5, 0.0, 5.0, 0.0, 0.0]},
                     {"name": "car2", "initial_state": [-10.0, -6.0, 1.5, 0.0, 5.0, 0.0, 0.0]}]}, "<test>")


def _direction(a, b) -> tuple[float, float]:
    d = np.asarray(b, float) - np.asarray(a, float)
    return float(np.arctan2(d[1], d[0])), float(np.arcsin(d[2] / np.linalg.norm(d)))


# BS (0, 0, 10), car1 antenna u = (10, 5, 1.5). East then west: image v1 = (40, 0, 10) (BS in x = 20),
# v2 = (-80, 0, 10) (v1 in x = -20). The segment u -> v2 crosses x = -20 at t = 1/3: q2 = (-20, 10/3, 13/3);
# q2 -> v1 crosses x = 20 at s = 2/3: q1 = (20, 10/9, 73/9).
U1 = np.array([10.0, 5.0, 1.5])
Q_EW = (np.array([20.0, 10 / 9, 73 / 9]), np.array([-20.0, 10 / 3, 13 / 3]))
V_EW = np.array([-80.0, 0.0, 10.0])


def _two_bounce_row(rx, names, types, q1, q2, u, extra_len=0.0):
    toa = np.linalg.norm(q1 - BS_POS) + np.linalg.norm(q2 - q1) + np.linalg.norm(u - q2) + extra_len
    return (rx, [(names[0], types[0], q1), (names[1], types[1], q2)], toa, -100.0), (
        *_direction(BS_POS, q1), *_direction(u, q2))


def test_double_specular_bounce_on_two_walls_is_an_order_two_va_at_the_image_of_the_image():
    """Hand-computed canyon: BS -> east wall -> west wall -> car. The label is VA, id 'east:-x|west:+x'
    (first bounce first), 2 bounces, landmark the image of the image (-80, 0, 10); |u - v2| equals the
    path length and the arrival direction points at v2. The reverse order is another VA (80, 0, 10).
    A diffuse bounce, a scatterer or a car in the chain stays OTHER (old code: all OTHER)."""
    idx = SceneIndex.from_scenario(_canyon_scn())
    # west then east: v1 = (-40, 0, 10), v2 = (80, 0, 10); u -> v2: x = 10 + 70 t = 20 at t = 1/7
    q2_we = U1 + (np.array([80.0, 0.0, 10.0]) - U1) / 7
    np.testing.assert_allclose(q2_we, [20.0, 30 / 7, 1.5 + 8.5 / 7])
    # q2 -> v1 (-40, 0, 10): x = 20 - 60 s = -20 at s = 2/3
    q1_we = q2_we + (np.array([-40.0, 0.0, 10.0]) - q2_we) * 2 / 3
    np.testing.assert_allclose(q1_we, [-20.0, 10 / 7, 10 - (8.5 - 8.5 / 7) / 3])
    ant = np.array([U1, [-10.0, -6.0, 1.5]])
    specs = [
        (0, ("east", "west"), (SPECULAR, SPECULAR), *Q_EW),        # VA order 2
        (0, ("west", "east"), (SPECULAR, SPECULAR), q1_we, q2_we),  # VA order 2, the other image
        (0, ("east", "west"), (SPECULAR, DIFFUSE), *Q_EW),         # diffuse in the chain: OTHER
        (0, ("east", "pole"), (SPECULAR, SPECULAR), Q_EW[0], np.array([5.0, 4.6, 2.0])),  # scatterer: OTHER
        (0, ("east", "car2"), (SPECULAR, SPECULAR), Q_EW[0], np.array([-10.0, -5.5, 1.0])),  # a car: OTHER
    ]
    rows, ang = [], []
    for rx, names, types, q1, q2 in specs:
        r, a = _two_bounce_row(rx, names, types, q1, q2, ant[rx])
        rows.append(r)
        ang.append(a)
    p = _paths(idx, rows)
    p["angles"] = np.array(ang)
    out = label_paths(idx, antennas=ant, **p)
    by = {str(i): k for k, i in enumerate(out["landmark_id"])}
    assert set(by) == {"east:-x|west:+x", "west:+x|east:-x", "east+west", "east+pole", "east+car2"}
    for lid, v2, q in (("east:-x|west:+x", V_EW, Q_EW), ("west:+x|east:-x", np.array([80.0, 0.0, 10.0]), (q1_we, q2_we))):
        k = by[lid]
        assert out["type"][k] == VA and out["bounces"][k] == 2 and out["n_paths"][k] == 1
        lm = np.array([out[c][k] for c in ("lm_x", "lm_y", "lm_z")])
        np.testing.assert_allclose(lm, v2, atol=1e-12)
        assert abs(np.linalg.norm(U1 - lm) - out["toa_m"][k]) < 1e-9  # TOA: the image's distance
        az, el = _direction(U1, lm)  # the arrival direction points at the image of the image
        assert abs(az - out["aoa_az"][k]) < 1e-12 and abs(el - out["aoa_el"][k]) < 1e-12
        np.testing.assert_allclose([out["bounce_x"][k], out["bounce_y"][k], out["bounce_z"][k]], q[0])
    for lid in ("east+west", "east+pole", "east+car2"):
        assert out["type"][by[lid]] == OTHER and np.isnan(out["lm_x"][by[lid]])


def test_double_bounces_with_ground_and_xml_planes_and_one_plane_twice():
    """Ground then wall and wall then ground are two VAs at the same point (perpendicular mirrors
    commute), told apart by their ids; two XML planes give 'plane(...)|plane(...)' with the mirrored
    image; the same plane twice is no specular double bounce (OTHER)."""
    idx = SceneIndex.from_scenario(_canyon_scn(), extra_static=["facade_a", "facade_b"])
    rows = [
        (0, [("ground", SPECULAR, [12.0, 2.0, 0.0]), ("east", SPECULAR, [20.0, 3.0, 1.0])], 40.0, -100.0),
        (0, [("east", SPECULAR, [20.0, 3.0, 5.0]), ("ground", SPECULAR, [15.0, 4.0, 0.0])], 40.0, -101.0),
        (1, [("facade_a", SPECULAR, [-5.0, 1.0, 4.0]), ("facade_b", SPECULAR, [0.0, 30.0, 3.0])], 80.0, -110.0),
        (1, [("facade_a", SPECULAR, [-5.0, 1.0, 4.0]), ("facade_a", SPECULAR, [-5.0, 8.0, 3.0])], 90.0, -120.0),
    ]
    p = _paths(idx, rows)
    nrm = np.full((4, 3, 3), np.nan)
    nrm[2, 0] = nrm[3, 0] = nrm[3, 1] = [1.0, 0.0, 0.0]   # plane x = -5 (either orientation)
    nrm[2, 1] = [0.0, 1.0, 0.0]                           # plane y = 30
    out = label_paths(idx, antennas=np.array([U1, [-10.0, -6.0, 1.5]]), normals=nrm, **p)
    by = {(int(r), str(i)): k for k, (r, i) in enumerate(zip(out["rx"], out["landmark_id"]))}
    assert set(by) == {(0, "ground:+z|east:-x"), (0, "east:-x|ground:+z"),
                       (1, "plane(+1.0000,+0.0000,+0.0000,-5.000)|plane(+0.0000,-1.0000,+0.0000,-30.000)"),
                       (1, "facade_a+facade_a")}
    for key in ((0, "ground:+z|east:-x"), (0, "east:-x|ground:+z")):
        assert out["type"][by[key]] == VA and out["bounces"][by[key]] == 2
        np.testing.assert_allclose([out[c][by[key]] for c in ("lm_x", "lm_y", "lm_z")], [40.0, 0.0, -10.0])
    k = by[(1, "plane(+1.0000,+0.0000,+0.0000,-5.000)|plane(+0.0000,-1.0000,+0.0000,-30.000)")]
    # BS in x = -5: (-10, 0, 10); then in y = 30: (-10, 60, 10)
    np.testing.assert_allclose([out[c][k] for c in ("lm_x", "lm_y", "lm_z")], [-10.0, 60.0, 10.0], atol=1e-12)
    assert out["type"][by[(1, "facade_a+facade_a")]] == OTHER
