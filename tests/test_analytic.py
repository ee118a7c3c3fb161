"""AnalyticSource: closed-form rows checked against hand-computed geometry (docs/design.md section 4)."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.analytic import AnalyticSource, free_space_power_db, fresnel_reflection, relative_permittivity
from mmslam.raytrace.schema import PATH_COLUMNS
from mmslam.scenes.scenario import load_preset, scenario_from_dict
from mmslam.scenes.trajectory import vehicle_trajectories
from mmslam.slam.models.measurement import BS, SP, VA, VS, channel_params
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import geometry_of


@pytest.fixture(scope="module")
def paper():
    scn = load_preset("paper")
    states = vehicle_trajectories(scn)
    src = AnalyticSource(scn)
    return scn, states, src, [src.trace_step(k, states[k]) for k in range(scn.steps)]


def test_columns_and_dtypes_match_schema(paper):
    _, _, _, rows = paper
    for cols in rows[:3]:
        assert list(cols) == list(PATH_COLUMNS)
        n = len(cols["rx"])
        for k, t in PATH_COLUMNS.items():
            assert len(cols[k]) == n
            if t == "string":
                assert cols[k].dtype == object and all(isinstance(x, str) for x in cols[k])
            else:
                assert cols[k].dtype == np.dtype(t), k
    assert rows[7]["step"].tolist() == [7] * len(rows[7]["rx"])


def test_los_toa_is_distance(paper):
    scn, states, _, rows = paper
    b = scn.bs_array
    for k in (0, 13, 39):
        c = rows[k]
        los = c["type"] == BS
        assert los.sum() == 2  # LOS always present for both receivers
        u = states[k, c["rx"][los], 0:3]
        np.testing.assert_allclose(c["toa_m"][los], np.linalg.norm(b - u, axis=1), rtol=0, atol=1e-9)
        assert np.isnan(c["bounce_x"][los]).all()
        np.testing.assert_allclose(np.c_[c["lm_x"][los], c["lm_y"][los], c["lm_z"][los]], [b, b])
        assert (c["bounces"][los] == 0).all() and (c["landmark_id"][los] == "bs").all()


def test_va_ids_positions_and_incidence_on_wall(paper):
    scn, states, _, rows = paper
    expect = {"wall_east:-x": (200, 0, 40), "wall_west:+x": (-200, 0, 40),
              "wall_north:-y": (0, 200, 40), "wall_south:+y": (0, -200, 40)}
    wall_plane = {"wall_east:-x": (0, 100.0), "wall_west:+x": (0, -100.0),
                  "wall_north:-y": (1, 100.0), "wall_south:+y": (1, -100.0)}
    b = scn.bs_array
    for k in (0, 5, 22):
        c = rows[k]
        va = np.flatnonzero(c["type"] == VA)
        # no blockage and walls of 200 m x 65 m: all four VAs seen by both receivers
        assert len(va) == 8
        for i in va:
            lid = c["landmark_id"][i]
            lm = np.array([c["lm_x"][i], c["lm_y"][i], c["lm_z"][i]])
            np.testing.assert_allclose(lm, expect[lid], atol=1e-9)
            p = np.array([c["bounce_x"][i], c["bounce_y"][i], c["bounce_z"][i]])
            ax, val = wall_plane[lid]
            assert p[ax] == pytest.approx(val, abs=1e-9)
            assert -100 <= p[1 - ax] <= 100 and -5 <= p[2] <= 60
            u = states[k, c["rx"][i], 0:3]
            # specular: the incidence point splits the unfolded path exactly
            assert np.linalg.norm(p - b) + np.linalg.norm(u - p) == pytest.approx(c["toa_m"][i], abs=1e-9)
            # cross-check with the measurement model's closed form
            g = channel_params(u, lm, Bounce.MIRROR, b)
            got = [c["toa_m"][i], c["aod_az"][i], c["aod_el"][i], c["aoa_az"][i], c["aoa_el"][i]]
            np.testing.assert_allclose(got, g, atol=1e-9)


def test_sp_vs_only_within_fov_range(paper):
    scn, states, _, rows = paper
    r = scn.sensor.fov_range
    sps = {s.name: np.asarray(s.position) for s in scn.scatterers}
    names = scn.vehicle_names
    n_sp = n_vs = 0
    for k, c in enumerate(rows):
        for rx in range(len(names)):
            u = states[k, rx, 0:3]
            sel = c["rx"] == rx
            got_sp = set(c["landmark_id"][sel & (c["type"] == SP)])
            want_sp = {n for n, p in sps.items() if np.linalg.norm(p - u) <= r}
            assert got_sp == want_sp, (k, rx)
            got_vs = set(c["landmark_id"][sel & (c["type"] == VS)])
            want_vs = {names[j] for j in range(len(names))
                       if j != rx and np.linalg.norm(states[k, j, 0:3] - u) <= r}
            assert got_vs == want_vs, (k, rx)
            n_sp += len(got_sp)
            n_vs += len(got_vs)
        for i in np.flatnonzero(np.isin(c["type"], (SP, VS))):
            u = states[k, c["rx"][i], 0:3]
            s = np.array([c["lm_x"][i], c["lm_y"][i], c["lm_z"][i]])
            assert np.linalg.norm(s - u) <= r
            np.testing.assert_allclose([c["bounce_x"][i], c["bounce_y"][i], c["bounce_z"][i]], s)
            g = channel_params(u, s, geometry_of(int(c["type"][i])), scn.bs_array)
            np.testing.assert_allclose([c["toa_m"][i], c["aod_az"][i], c["aod_el"][i], c["aoa_az"][i],
                                        c["aoa_el"][i]], g, atol=1e-9)
            assert c["diffuse"][i] == (c["type"][i] == SP)
    # the gate is not vacuous on this trajectory: some SPs are seen, some steps see none
    assert 0 < n_sp < len(rows) * 2 * len(sps)
    assert n_vs == 2 * len(rows)  # the two cars are 10 m apart: always in each other's range


def _one_wall_scenario(receivers):
    """BS at [0, 0, 10]; one box building whose -x face x = 20 spans y in [-5, 5], z in [0, 20]."""
    return scenario_from_dict({
        "name": "onewall", "bs": [0.0, 0.0, 10.0], "dt": 0.5, "steps": 1,
        "buildings": [{"name": "w", "min": [20.0, -5.0, 0.0], "max": [25.0, 5.0, 20.0]}],
        "vehicles": [{"name": f"car{i}", "initial_state": [x, y, z, 0.0, 0.0, 0.0, 0.0]}
                     for i, (x, y, z) in enumerate(receivers)],
        "sensor": {"fov_range": 1.0},
    })


def test_va_visibility_hand_computed():
    # image source v = [40, 0, 10]; incidence point p = v + t (u - v) with t = 20 / (40 - u_x)
    rx = [(0.0, 0.0, 1.5),    # p = [20, 0, 5.75]: inside the face -> visible
          (0.0, 8.0, 1.5),    # p = [20, 4, 5.75]: inside -> visible
          (0.0, 30.0, 1.5),   # p = [20, 15, 5.75]: y > 5 -> invisible
          (0.0, 0.0, -50.0),  # p = [20, 0, -20]: below the face -> invisible
          (30.0, 0.0, 1.5)]   # behind the wall plane -> invisible
    scn = _one_wall_scenario(rx)
    src = AnalyticSource(scn)
    assert src.face_ids == ["w:-x"]
    c = src.trace_step(0, vehicle_trajectories(scn, 1)[0])
    va = c["type"] == VA
    assert sorted(c["rx"][va].tolist()) == [0, 1]
    i0 = np.flatnonzero(va & (c["rx"] == 0))[0]
    i1 = np.flatnonzero(va & (c["rx"] == 1))[0]
    np.testing.assert_allclose([c["bounce_x"][i0], c["bounce_y"][i0], c["bounce_z"][i0]], [20, 0, 5.75])
    np.testing.assert_allclose([c["bounce_x"][i1], c["bounce_y"][i1], c["bounce_z"][i1]], [20, 4, 5.75])
    np.testing.assert_allclose([c["lm_x"][i0], c["lm_y"][i0], c["lm_z"][i0]], [40, 0, 10])
    assert c["toa_m"][i0] == pytest.approx(np.hypot(40, 8.5))
    # AOD points at the incidence point: b -> [20, 0, 5.75]
    assert c["aod_az"][i0] == pytest.approx(0.0)
    assert c["aod_el"][i0] == pytest.approx(np.arcsin(-4.25 / np.hypot(20, 4.25)))
    # fov_range 1 m: no VS rows (cars are further apart), LOS for every receiver
    assert (c["type"] == VS).sum() == 0 and (c["type"] == BS).sum() == 5


def test_ground_face_gives_va_below_ground():
    scn = scenario_from_dict({
        "name": "g", "bs": [0.0, 0.0, 10.0], "ground": {"z": 0.0, "extent": 100.0},
        "vehicles": [{"name": "a", "initial_state": [30.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0]},
                     {"name": "b", "initial_state": [70.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0]}]})
    c = AnalyticSource(scn).trace_step(0, vehicle_trajectories(scn, 1)[0])
    va = np.flatnonzero(c["type"] == VA)
    # receiver a: p = [25, 0, 0] on the 100 m ground square; receiver b: p = [58.3, 0, 0] is off it
    assert c["rx"][va].tolist() == [0] and c["landmark_id"][va[0]] == "ground:+z"
    np.testing.assert_allclose([c["bounce_x"][va[0]], c["bounce_z"][va[0]]], [25.0, 0.0], atol=1e-9)
    np.testing.assert_allclose([c["lm_x"][va[0]], c["lm_z"][va[0]]], [0.0, -10.0])


def test_power_is_free_space_loss_for_los_and_reflection_and_radar_otherwise(paper):
    # FSPL at 100 m, 28 GHz: 20 log10(4 pi 100 28e9 / c) = 101.391 dB
    assert free_space_power_db(100.0, 28e9) == pytest.approx(-101.391, abs=1e-3)
    _, _, _, rows = paper
    c = rows[3]
    los = c["type"] == BS
    np.testing.assert_allclose(c["power_db"][los], free_space_power_db(c["toa_m"][los], 28e9))
    # a reflection loses power (|Gamma| < 1), a 1 m^2 point scatterer much more than free space
    va = c["type"] == VA
    assert np.all(c["power_db"][va] < free_space_power_db(c["toa_m"][va], 28e9) - 1.0)
    assert (c["n_paths"] == 1).all() and (c["delay_spread_m"] == 0).all()
    assert (c["bounces"][c["type"] != BS] == 1).all()


def _c():
    return 299_792_458.0


def test_gains_and_doppler_hand_computed():
    """Normal incidence on a concrete wall, a point scatterer, a receiver driving at the BS."""
    # BS [0, 0, 10], wall face x = 20 (concrete). Receiver 0 at [5, 0, 10] driving towards -x at 10 m/s.
    scn = scenario_from_dict({
        "name": "onewall", "bs": [0.0, 0.0, 10.0], "dt": 0.5, "steps": 1,
        "buildings": [{"name": "w", "min": [20.0, -5.0, 0.0], "max": [25.0, 5.0, 20.0]}],
        "scatterers": [{"name": "s", "position": [5.0, 30.0, 10.0]}],
        "vehicles": [{"name": "car0", "initial_state": [5.0, 0.0, 10.0, np.pi, 10.0, 0.0, 0.0]},
                     {"name": "car1", "initial_state": [5.0, 20.0, 10.0, np.pi / 2, 4.0, 0.0, 0.0]}],
        "sensor": {"fov_range": 40.0},
    })
    f = scn.frequency_hz
    lam = _c() / f
    t = AnalyticSource(scn, rcs_m2=2.0).trace_tables(0, vehicle_trajectories(scn, 1)[0])
    c, r = t["paths"], t["rays"]
    row = {(int(rx), str(i)): j for j, (rx, i) in enumerate(zip(c["rx"], c["landmark_id"]))}
    a = c["a_re"] if "a_re" in c else None
    ra = r["a_re"] + 1j * r["a_im"]
    rrow = {(int(rx), str(i)): j for j, (rx, i) in enumerate(zip(r["rx"], r["landmark_id"]))}
    # LOS: |a| = lambda / (4 pi 5); moving straight at the BS: Doppler +10 / lambda
    j = rrow[(0, "bs")]
    assert ra[j] == pytest.approx(lam / (4 * np.pi * 5.0), rel=1e-12)
    assert r["doppler_hz"][j] == pytest.approx(10.0 / lam, abs=1e-9)
    assert c["doppler_hz"][row[(0, "bs")]] == pytest.approx(10.0 / lam, abs=1e-9)
    # VA at normal incidence: Gamma = (1 - sqrt(eta)) / (1 + sqrt(eta)), ITU concrete at 28 GHz
    fg = f / 1e9
    eta = 5.24 - 1j * 0.0462 * fg**0.7822 / (2 * np.pi * f * 8.8541878128e-12)
    gamma = (1 - np.sqrt(eta)) / (1 + np.sqrt(eta))
    j = rrow[(0, "w:-x")]
    assert ra[j] == pytest.approx(gamma * lam / (4 * np.pi * 35.0), rel=1e-9)
    # the image [40, 0, 10] is ahead of... behind the receiver driving away from it: -10 / lambda
    assert r["doppler_hz"][j] == pytest.approx(-10.0 / lam, abs=1e-9)
    assert r["bounce1_type"][j] == 1 and r["bounce1_object"][j] == "w"
    np.testing.assert_allclose([r["bounce1_x"][j], r["bounce1_y"][j], r["bounce1_z"][j]], [20, 0, 10])
    # SP at [5, 30, 10]: d1 = |[5, 30, 0]|, d2 = 30 (receiver 0); a = sqrt(2) lambda / ((4 pi)^1.5 d1 d2)
    d1 = np.hypot(5.0, 30.0)
    j = rrow[(0, "s")]
    assert ra[j] == pytest.approx(np.sqrt(2.0) * lam / ((4 * np.pi) ** 1.5 * d1 * 30.0), rel=1e-12)
    assert r["doppler_hz"][j] == pytest.approx(0.0, abs=1e-9)  # moving perpendicular to the SP direction
    # VS: car1 at [5, 20, 10] moving +y at 4 m/s seen by car0 (moving -x at 10 m/s):
    # f = (v0 . u(s - u0) - v1 . (u(s - b) + u(s - u0))) / lambda
    s_, b_, u0 = np.array([5.0, 20, 10]), np.array([0.0, 0, 10]), np.array([5.0, 0, 10])
    v0, v1 = np.array([-10.0, 0, 0]), np.array([0.0, 4, 0])
    unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
    want = (v0 @ unit(s_ - u0) - v1 @ (unit(s_ - b_) + unit(s_ - u0))) / lam
    assert r["doppler_hz"][rrow[(0, "car1")]] == pytest.approx(want, abs=1e-9)
    assert want == pytest.approx(-4.0 * (20 / np.hypot(5, 20) + 1.0) / lam)
    assert a is None  # paths carries power and Doppler; the complex gain lives in rays
    # paths link to their ray: same delay and power
    for i in range(len(c["rx"])):
        k = np.flatnonzero((r["rx"] == c["rx"][i]) & (r["ray"] == c["ray"][i]))
        assert k.size == 1 and r["landmark_id"][k[0]] == c["landmark_id"][i]
        assert r["delay_s"][k[0]] * _c() == pytest.approx(c["toa_m"][i], rel=1e-12)
        assert r["power_db"][k[0]] == pytest.approx(c["power_db"][i], abs=1e-12)


def test_fresnel_normal_incidence_and_grazing():
    """ITU-R P.2040 convention: at normal incidence Gamma_TE = -Gamma_TM = (1 - sqrt(eta)) / (1 + sqrt(eta));
    both tend to -1 at grazing incidence."""
    eta = relative_permittivity("concrete", 28e9)
    g = fresnel_reflection(np.array([1.0, 1.0, 1e-6, 1e-6]), eta, np.array([True, False, True, False]))
    assert g[0] == pytest.approx(-g[1]) and g[0] == pytest.approx((1 - np.sqrt(eta)) / (1 + np.sqrt(eta)))
    assert g[2] == pytest.approx(-1.0, abs=1e-4) and g[3] == pytest.approx(-1.0, abs=1e-4)
    assert relative_permittivity("metal", 28e9).imag < -1e6  # a conductor


def test_rows_sorted_and_deterministic(paper):
    scn, states, src, rows = paper
    again = AnalyticSource(scn).trace_step(9, states[9])
    for k in PATH_COLUMNS:
        np.testing.assert_array_equal(again[k], rows[9][k])
    c = rows[9]
    key = list(zip(c["rx"].tolist(), c["type"].tolist(), c["landmark_id"].tolist()))
    assert key == sorted(key)
