"""Static scene triangles and NumPy ray casting (scenes/geometry.py); vehicle poses against the meshes."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.cli import main
from mmslam.errors import ConfigError
from mmslam.scenes.geometry import StaticGeometry, check_vehicle_poses, read_ply_triangles, static_geometry
from mmslam.scenes.meshes import box_mesh, build_scene
from mmslam.scenes.scenario import load_preset, scenario_from_dict
from mmslam.scenes.trajectory import true_trajectories


def _box_geom(lo, hi, name="house") -> StaticGeometry:
    m = box_mesh(np.asarray(lo, float), np.asarray(hi, float))
    tri = np.asarray(m.vertices)[np.asarray(m.faces)]
    return StaticGeometry(tri, np.zeros(len(tri), np.int64), (name,), ("building",))


def test_ply_reader_equals_trimesh_on_a_written_scene(tmp_path):
    import trimesh

    build_scene(load_preset("street"), tmp_path)
    for f in sorted((tmp_path / "meshes").glob("*.ply")):
        m = trimesh.load(f, process=False, force="mesh")
        np.testing.assert_array_equal(read_ply_triangles(f), np.asarray(m.vertices)[np.asarray(m.faces)])


def test_vertical_hits_of_a_box_are_its_floor_and_roof():
    g = _box_geom([20.0, -10.0, 0.0], [22.0, 10.0, 15.0])
    pt, z, _ = g.vertical_hits(np.array([[21.0, 0.3], [25.0, 0.0], [20.5, -9.9]]))
    got = sorted(zip(pt.tolist(), np.round(z, 12).tolist()))
    assert got == [(0, 0.0), (0, 15.0), (2, 0.0), (2, 15.0)]  # walls are never hit by a vertical line
    z, obj = g.height_map(np.array([[21.0, 0.0], [21.0, 0.0], [30.0, 0.0]]), below=np.array([20.0, 10.0, 20.0]))
    np.testing.assert_array_equal(z[:2], [15.0, 0.0])
    assert np.isnan(z[2]) and obj.tolist() == [0, 0, -1]


def test_segments_blocked_by_a_box():
    g = _box_geom([20.0, -10.0, 0.0], [22.0, 10.0, 15.0])
    a = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [0.0, 0.0, 20.0]])
    b = np.array([[40.0, 0.0, 5.0], [40.0, 30.0, 5.0], [20.0, 0.0, 5.0], [40.0, 0.0, 20.0]])
    # through the box; beside it (crosses y = 10 at x = 13.3); ends on its wall (margin); above it
    assert g.segments_blocked(a, b).tolist() == [True, False, False, False]


def test_shipped_presets_pass_the_pose_check():
    for name in ("paper", "street", "canyon", "munich"):
        scn = load_preset(name)
        check_vehicle_poses(scn, true_trajectories(scn))


def test_munich_car_inside_a_building_off_the_map_or_sunk_is_a_one_line_error():
    scn = load_preset("munich")
    st = true_trajectories(scn)
    g = static_geometry(scn)
    bad = st.copy()
    bad[17, 2, :2] = [8.5, 21.0]  # under the BS, on the Neues Rathaus
    with pytest.raises(ConfigError, match=r"vehicle 'car_c' at step 17 \(x=8\.5, y=21\.0\) is inside object "
                                          r"'Neues_Rathaus-itu_\w+'") as e:
        check_vehicle_poses(scn, bad, g)
    assert "\n" not in str(e.value)
    bad = st.copy()
    bad[5, 1, :2] = [2000.0, 0.0]
    with pytest.raises(ConfigError, match=r"vehicle 'car_b' at step 5 .* off the map"):
        check_vehicle_poses(scn, bad, g)
    bad = st.copy()
    bad[3, 0, 2] = 0.5  # body bottom at -1.05 m
    with pytest.raises(ConfigError, match=r"vehicle 'car_a' at step 3 .* 1\.05 m below the surface of object 'ground'"):
        check_vehicle_poses(scn, bad, g)


def _drive_through(tmp_path):
    toml = tmp_path / "wall.toml"
    toml.write_text("""
name = "drive_through"
bs = [0.0, 0.0, 20.0]
steps = 12
[[buildings]]
name = "block"
min = [20.0, -10.0, 0.0]
max = [30.0, 10.0, 15.0]
[[vehicles]]
name = "car1"
motion = "waypoints"
waypoints = [[0.0, 0.0], [50.0, 0.0]]
initial_state = [0.0, 0.0, 1.6, 0.0, 4.0, 0.0, 0.0]
""")
    return toml


def test_a_car_driving_into_a_scenario_building_is_refused_at_its_step(tmp_path):
    from mmslam.scenes.scenario import load_scenario

    scn = load_scenario(_drive_through(tmp_path))
    with pytest.raises(ConfigError, match=r"vehicle 'car1' at step 9 \(x=18\.0, y=0\.0\) is inside object 'block'"):
        check_vehicle_poses(scn, true_trajectories(scn))  # front corners cross x = 20 at step 9 (x = 18 + 2.25)


def test_trace_cli_refuses_a_colliding_route_with_exit_2(tmp_path, capsys):
    rc = main(["trace", str(_drive_through(tmp_path)), "--source", "analytic", "--out", str(tmp_path / "c"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0
    assert "vehicle 'car1' at step 9" in err and "'block'" in err


def test_scene_show_draws_munich_heights(tmp_path, capsys):
    """The height raster under `scene show`: the Neues Rathaus roof (26 m) under the BS, the street (0 m)
    under car_a's start; the CLI writes the PNG."""
    from mmslam.scenes.plan import height_raster

    scn = load_preset("munich")
    z, (x0, x1, y0, y1) = height_raster(scn, true_trajectories(scn))
    ny, nx = z.shape
    at = lambda x, y: z[int((y - y0) / (y1 - y0) * ny), int((x - x0) / (x1 - x0) * nx)]  # noqa: E731
    assert at(8.5, 21.0) == pytest.approx(26.0, abs=1.0)
    assert at(0.0, 100.0) == pytest.approx(0.0, abs=1e-6)
    assert x0 <= -62.0 - 59 and x1 >= 190.0 + 59  # trajectories + 60 m margin
    png = tmp_path / "plan.png"
    assert main(["scene", "show", "munich", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000


def test_unique_ints_equals_numpys_unique():
    """The sort-based distinct values used by ``segments_blocked`` (NumPy's hash-based np.unique is far slower there)."""
    from mmslam.scenes.geometry import _unique_ints

    rng = np.random.default_rng(7)
    for x in (rng.integers(0, 10**9, 50_000), rng.integers(-5, 5, 1_000), np.array([3, 3, 3]), np.zeros(0, np.int64)):
        x = np.concatenate([x, x[: len(x) // 3]])
        got, want = _unique_ints(x), np.unique(x)
        np.testing.assert_array_equal(got, want)
        assert got.dtype == want.dtype
