"""`--source analytic` on an external XML scene: paths from the scene's own triangles, cross-checked with Sionna."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mmslam.raytrace.trace import make_source
from mmslam.scenes.meshes import build_scene
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import true_trajectories
from mmslam.slam.models.measurement import BS, VA


def _floor_wall():
    base = load_preset("paper")
    veh = dataclasses.replace(base.vehicles[0], name="car", initial_state=(1.2, -0.5, 1.2, 0.0, 0.0, 0.0, 0.0),
                              length=0.5, width=0.5, height=0.5)
    return dataclasses.replace(base, xml_scene="sionna:floor_wall", buildings=(), scatterers=(), vehicles=(veh,),
                               bs=(1.5, 0.0, 2.0))


def _bs_va(out) -> dict[tuple[int, str], int]:
    return {(int(r), str(i)): j for j, (r, t, i) in enumerate(zip(out["rx"], out["type"], out["landmark_id"]))
            if t in (BS, VA)}


def test_floor_wall_paths_by_hand():
    """Wall x = 0, floor z = 0; BS (1.5, 0, 2), antenna (1.2, -0.5, 1.2): LOS and the wall VA at (-1.5, 0, 2);
    the floor VA's bounce point (1.3125, -0.3125, 0) lies under the receiving car's own 0.5 m body: no row."""
    scn = _floor_wall()
    src = make_source("analytic", scn)
    assert type(src).__name__ == "MeshAnalyticSource"
    u = np.array([1.2, -0.5, 1.2])
    out = src.trace_step(0, np.array([scn.vehicles[0].initial_state]))
    got = _bs_va(out)
    wall = "plane(+1.0000,+0.0000,+0.0000,+0.000)"
    assert set(got) == {(0, "bs"), (0, wall)}
    for key, img in (((0, "bs"), [1.5, 0.0, 2.0]), ((0, wall), [-1.5, 0.0, 2.0])):
        j = got[key]
        # the wall's plane comes from the scene's float32 vertices: 1e-6 m
        assert out["toa_m"][j] == pytest.approx(np.linalg.norm(np.array(img) - u), abs=1e-6)
        np.testing.assert_allclose([out["lm_x"][j], out["lm_y"][j], out["lm_z"][j]], img, atol=1e-6)
    j = got[(0, wall)]
    # incidence point: image (-1.5, 0, 2) + s (u - image) with x = 0: s = 1.5 / 2.7
    np.testing.assert_allclose([out["bounce_x"][j], out["bounce_y"][j], out["bounce_z"][j]],
                               [0.0, -0.5 * 1.5 / 2.7, 2.0 - 0.8 * 1.5 / 2.7], atol=1e-6)


def test_los_through_a_canyon_building_is_blocked():
    """Canyon, BS (-33, -10, 25) above building_1: (10, 0, 1.6) in the main street sees it (the line leaves
    building_1's roof at x = -31, z = 23.9 > 21.8); (0, 45, 1.6) north of building_4 does not (the line
    enters building_4's west face x = -15 at y = 20, z = 12.2)."""
    scn = load_preset("canyon")
    src = make_source("analytic", scn)
    st = true_trajectories(scn)[0].copy()
    st[0, :3] = [10.0, 0.0, 1.6]
    st[1, :3] = [0.0, 45.0, 1.6]
    got = _bs_va(src.trace_step(0, st))
    assert (0, "bs") in got and (1, "bs") not in got


def test_an_xml_written_by_mmslam_round_trips(tmp_path):
    """A scene mmslam wrote, used as xml_scene: no duplicate material ids, Sionna loads it, both sources trace."""
    from mmslam.raytrace.sionna_adapter import SionnaSource

    paper = load_preset("paper")
    xml = build_scene(paper, tmp_path / "first")
    veh = dataclasses.replace(paper.vehicles[0], name="newcar", initial_state=(0.0, -30.0, 1.6, 0.0, 5.0, 0.0, 0.0))
    scn = dataclasses.replace(paper, xml_scene=str(xml), buildings=(), scatterers=(), vehicles=(veh,))
    src = SionnaSource(scn, samples_per_src=10**5, scene_dir=tmp_path / "second")
    st = np.array([veh.initial_state])
    s_ids = {i for (_, i) in _bs_va(src.trace_step(0, st))}
    a_ids = {i for (_, i) in _bs_va(make_source("analytic", scn).trace_step(0, st))}
    walls = {"plane(+0.0000,+1.0000,+0.0000,-100.000)", "plane(+0.0000,-1.0000,+0.0000,-100.000)",
             "plane(+1.0000,+0.0000,+0.0000,-100.000)", "plane(-1.0000,+0.0000,+0.0000,-100.000)"}
    assert s_ids == a_ids == {"bs"} | walls  # the four walls at +-100 m are planes of the reused XML


@pytest.mark.slow
def test_munich_analytic_equals_sionna_on_bs_and_va_rows():
    """Independent cross-check in a city: the same BS / VA rows (receiver, id) and TOAs within 1 cm."""
    from mmslam.raytrace.sionna_adapter import SionnaSource

    scn = load_preset("munich")
    st = true_trajectories(scn)
    ana = make_source("analytic", scn)
    sio = SionnaSource(scn, samples_per_src=10**6)
    n = 0
    for k in (0, 27):
        a, s = ana.trace_step(k, st[k]), sio.trace_step(k, st[k])
        ka, ks = _bs_va(a), _bs_va(s)
        assert set(ka) == set(ks), (k, set(ka) ^ set(ks))
        for key in ka:
            assert a["toa_m"][ka[key]] == pytest.approx(s["toa_m"][ks[key]], abs=1e-2)
        n += len(ka)
    assert n >= 10


def test_trace_cli_analytic_on_an_xml_scene_writes_rays_and_paths(tmp_path, capsys):
    """`mmslam trace canyon --source analytic` uses the meshes: one ray per path row, LOS rows only where
    the line BS -> antenna is free (checked against the scene's triangles)."""
    from mmslam.cli import main
    from mmslam.raytrace.cache import load_cache
    from mmslam.scenes.geometry import static_geometry

    assert main(["trace", "canyon", "--source", "analytic", "--out", str(tmp_path), "--steps", "4", "--quiet"]) == 0
    import pyarrow.parquet as pq

    d = capsys.readouterr().out.strip().splitlines()[-1]
    c = load_cache(d)
    assert pq.read_table(f"{d}/rays").num_rows == len(c.paths["rx"]) > 0
    scn = load_preset("canyon")
    g = static_geometry(scn)
    st = true_trajectories(scn, 4)
    free = ~g.segments_blocked(np.repeat(scn.bs_array[None], 12, 0), st[:, :, :3].reshape(-1, 3)).reshape(4, 3)
    los = np.zeros((4, 3), bool)
    sel = c.paths["type"] == BS
    los[c.paths["step"][sel], c.paths["rx"][sel].astype(int)] = True
    np.testing.assert_array_equal(los, free)  # car bodies never stand between a roof antenna and the BS here


def test_mesh_rays_keep_the_closed_form_coefficients_of_unblocked_rows():
    """Rows the meshes do not block keep the closed-form source's complex coefficient; XML-plane VAs get
    the Friis coefficient lambda / (4 pi L) over their unfolded length L; |a| matches power_db."""
    from mmslam.raytrace.analytic import SPEED_OF_LIGHT, AnalyticSource

    scn = _floor_wall()
    st = np.array([scn.vehicles[0].initial_state])
    t = make_source("analytic", scn).trace_tables(0, st)
    ref = AnalyticSource(scn).trace_tables(0, st)
    r = t["rays"]
    a = r["a_re"] + 1j * r["a_im"]
    ids = [str(i) for i in r["landmark_id"]]
    j = ids.index("bs")
    k = [str(i) for i in ref["rays"]["landmark_id"]].index("bs")
    assert a[j] == ref["rays"]["a_re"][k] + 1j * ref["rays"]["a_im"][k]
    w = ids.index("plane(+1.0000,+0.0000,+0.0000,+0.000)")
    lam = SPEED_OF_LIGHT / scn.frequency_hz
    assert a[w] == pytest.approx(lam / (4 * np.pi * r["delay_s"][w] * SPEED_OF_LIGHT), rel=1e-12)
    np.testing.assert_allclose(20 * np.log10(np.abs(a)), r["power_db"], atol=1e-9)
