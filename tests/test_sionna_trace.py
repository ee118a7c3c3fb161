"""Sionna RT tracing of the `paper` preset checked against closed-form geometry.

One SionnaSource per module (LLVM backend on the CPU); a few steps traced once.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mmslam.errors import ConfigError, MmslamError
from mmslam.raytrace.schema import PATH_COLUMNS
from mmslam.scenes.landmarks import reflecting_faces, va_truth
from mmslam.scenes.meshes import car_mesh, scatterer_mesh
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import vehicle_trajectories
from mmslam.slam.models.measurement import BS, OTHER, SP, VA, VS, channel_params
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import geometry_of

STEPS = (0, 9, 17, 26, 33)


@pytest.fixture(scope="module")
def traced(tmp_path_factory):
    from mmslam.raytrace.sionna_adapter import SionnaSource

    scn = load_preset("paper")
    states = vehicle_trajectories(scn)
    src = SionnaSource(scn, max_depth=1, samples_per_src=10**6, seed=0,
                       scene_dir=tmp_path_factory.mktemp("paper_scene"))
    out = {}
    for k in STEPS:
        raw = src.raw_paths(k, states[k])
        lab = src.trace_step(k, states[k])
        out[k] = (raw, lab)
    return scn, states, src, out


def _rows(lab, typ):
    return [i for i in range(len(lab["rx"])) if lab["type"][i] == typ]


def _unit(az, el):
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def test_output_columns_and_sorting(traced):
    _, _, _, out = traced
    for k, (_, lab) in out.items():
        assert set(lab) == set(PATH_COLUMNS)
        n = len(lab["rx"])
        assert n > 0 and all(len(v) == n for v in lab.values())
        assert np.all(lab["step"] == k)
        keys = list(zip(lab["rx"], lab["type"], lab["landmark_id"]))
        assert keys == sorted(keys) and len(set(keys)) == n


def test_tx_columns_are_the_bs_on_every_row(traced):
    """Schema version 3: ``tx_x, tx_y, tx_z`` of both tables hold the scenario's BS (Sionna's transmitter)."""
    scn, states, src, out = traced
    for k, (_, lab) in out.items():
        np.testing.assert_array_equal(np.c_[lab["tx_x"], lab["tx_y"], lab["tx_z"]], np.tile(scn.bs, (len(lab["rx"]), 1)))
    rays = src.trace_tables(STEPS[0], states[STEPS[0]])["rays"]
    assert len(rays["rx"]) > len(out[STEPS[0]][1]["rx"])  # every ray, more than the labelled paths
    np.testing.assert_array_equal(np.c_[rays["tx_x"], rays["tx_y"], rays["tx_z"]], np.tile(scn.bs, (len(rays["rx"]), 1)))


def test_los_delay_equals_distance(traced):
    scn, states, _, out = traced
    b = scn.bs_array
    for k, (_, lab) in out.items():
        for i in _rows(lab, BS):
            u = states[k, lab["rx"][i], :3]
            assert lab["toa_m"][i] == pytest.approx(np.linalg.norm(b - u), abs=1e-3)


def test_bs_and_va_paths_match_channel_params(traced):
    scn, states, _, out = traced
    b = scn.bs_array
    vas = va_truth(scn)
    n_va = 0
    for k, (_, lab) in out.items():
        for typ in (BS, VA):
            for i in _rows(lab, typ):
                u = states[k, lab["rx"][i], :3]
                lm = np.array([lab["lm_x"][i], lab["lm_y"][i], lab["lm_z"][i]])
                if typ == VA:
                    np.testing.assert_allclose(lm, vas[lab["landmark_id"][i]], atol=1e-9)
                    n_va += 1
                    assert lab["n_paths"][i] == 1 and not lab["diffuse"][i]
                g = channel_params(u, lm, geometry_of(typ), b)
                got = np.array([lab[c][i] for c in ("toa_m", "aod_az", "aod_el", "aoa_az", "aoa_el")])
                assert abs(got[0] - g[0]) < 1e-2, (k, lab["landmark_id"][i], got[0], g[0])
                d = np.angle(np.exp(1j * (got[1:] - g[1:])))
                assert np.all(np.abs(d) < 1e-3), (k, lab["landmark_id"][i], d)
    assert n_va >= 3 * len(out)


def _segment_hits_box(p0, p1, lo, hi):
    """Slab test: does the open segment p0 -> p1 cross the axis-aligned box [lo, hi]?"""
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - p0) / d, (hi - p0) / d
    tmin = np.nanmax(np.where(d != 0, np.minimum(t1, t2), np.where((p0 >= lo) & (p0 <= hi), -np.inf, np.inf)))
    tmax = np.nanmin(np.where(d != 0, np.maximum(t1, t2), np.where((p0 >= lo) & (p0 <= hi), np.inf, -np.inf)))
    return tmax > max(tmin, 1e-6) and tmin < 1 - 1e-6


def _blocked(p0, p1, boxes):
    """Segment blocked by any (rotation, centre, lo, hi) box given in its own frame."""
    for rot, c, lo, hi in boxes:
        if _segment_hits_box(rot.T @ (p0 - c), rot.T @ (p1 - c), lo, hi):
            return True
    return False


def _closed_form_visible(scn, states_k, rx):
    """BS/VA ids visible at a receiver: VA incidence point inside the face rectangle; both legs
    unobstructed by the cars and scatterers (the paper scene has no other obstacles)."""
    b = scn.bs_array
    u = states_k[rx, :3]
    boxes = []
    for j, v in enumerate(scn.vehicles):
        m = car_mesh(v, states_k[j])
        h = states_k[j, 3]
        rot = np.array([[np.cos(h), -np.sin(h), 0], [np.sin(h), np.cos(h), 0], [0, 0, 1]])
        loc = (m.vertices - states_k[j, :3]) @ rot
        boxes.append((rot, states_k[j, :3], loc.min(0) - 1e-9, loc.max(0) + 1e-9))
    for s in scn.scatterers:
        m = scatterer_mesh(s)
        boxes.append((np.eye(3), np.zeros(3), m.bounds[0], m.bounds[1]))
    vis = set()
    if not _blocked(b, u, boxes):
        vis.add("bs")
    for f in reflecting_faces(scn):
        v = va_truth(scn)[f.id]
        ax = int(np.argmax(np.abs(f.normal)))
        if abs(u[ax] - v[ax]) < 1e-12:
            continue  # antenna in the image's plane: grazing, no reflection
        t = (f.point[ax] - v[ax]) / (u[ax] - v[ax])
        if not 0 < t < 1:
            continue
        p = v + t * (u - v)
        inside = all(f.lo[a] - 1e-9 <= p[a] <= f.hi[a] + 1e-9 for a in range(3) if a != ax)
        if inside and not _blocked(b, p, boxes) and not _blocked(p, u, boxes):
            vis.add(f.id)
    return vis


def test_visible_bs_va_set_equals_closed_form(traced):
    scn, states, _, out = traced
    for k, (_, lab) in out.items():
        for rx in range(len(scn.vehicles)):
            got = {lab["landmark_id"][i] for i in range(len(lab["rx"]))
                   if lab["rx"][i] == rx and lab["type"][i] in (BS, VA)}
            assert got == _closed_form_visible(scn, states[k], rx), (k, rx)


def test_sp_and_vs_paths_within_object_size(traced):
    scn, states, _, out = traced
    b = scn.bs_array
    radius = {s.name: np.max(np.linalg.norm(scatterer_mesh(s).vertices - np.array(s.position), axis=1))
              for s in scn.scatterers}
    n_sp = n_vs = 0
    for k, (_, lab) in out.items():
        rad_k = dict(radius)
        for j, v in enumerate(scn.vehicles):
            rad_k[v.name] = np.max(np.linalg.norm(car_mesh(v, states[k, j]).vertices - states[k, j, :3], axis=1))
        for typ in (SP, VS):
            for i in _rows(lab, typ):
                name = lab["landmark_id"][i]
                u = states[k, lab["rx"][i], :3]
                lm = np.array([lab["lm_x"][i], lab["lm_y"][i], lab["lm_z"][i]])
                r = rad_k[name]
                g = channel_params(u, lm, geometry_of(typ), b)
                assert abs(lab["toa_m"][i] - g[0]) <= 2 * r, (k, name)
                # angular error bounded by the angle the object subtends around its reference point
                dep = np.arccos(np.clip(_unit(lab["aod_az"][i], lab["aod_el"][i]) @ _unit(g[1], g[2]), -1, 1))
                arr = np.arccos(np.clip(_unit(lab["aoa_az"][i], lab["aoa_el"][i]) @ _unit(g[3], g[4]), -1, 1))
                assert dep <= np.arcsin(min(1.0, r / np.linalg.norm(lm - b))) + 1e-3, (k, name, dep)
                assert arr <= np.arcsin(min(1.0, r / np.linalg.norm(lm - u))) + 1e-3, (k, name, arr)
                bp = np.array([lab["bounce_x"][i], lab["bounce_y"][i], lab["bounce_z"][i]])
                assert np.linalg.norm(bp - lm) <= r + 1e-3
                n_sp += typ == SP
                n_vs += typ == VS
    # every scatterer is found by each receiver at most steps (10**6 samples: several hits each)
    assert n_sp >= 0.8 * len(out) * len(scn.vehicles) * len(scn.scatterers)
    assert n_vs >= len(out)


def test_paths_touching_own_vehicle_are_absent(traced):
    scn, _, src, out = traced
    names = src.index.names
    own_raw = 0
    for k, (raw, lab) in out.items():
        veh_idx = np.array([names.index(v.name) for v in scn.vehicles])
        own_raw += int(np.sum(np.any(raw["obj"] == veh_idx[raw["rx"]][:, None], axis=1)))
        for i in range(len(lab["rx"])):
            own = scn.vehicles[lab["rx"][i]].name
            parts = lab["landmark_id"][i].split("+") if lab["type"][i] == OTHER else [lab["landmark_id"][i]]
            assert own not in parts
    assert own_raw > 0  # the tracer does produce own-roof paths: the filter is exercised


def test_same_seed_same_paths(traced):
    scn, states, src, out = traced
    again = src.trace_step(STEPS[0], states[STEPS[0]])
    first = out[STEPS[0]][1]
    for c in PATH_COLUMNS:
        if c == "landmark_id":
            assert list(again[c]) == list(first[c])
        else:
            np.testing.assert_array_equal(again[c], first[c])


def test_bad_inputs_are_one_line_errors(traced):
    scn, states, src, _ = traced
    from mmslam.raytrace.sionna_adapter import SionnaSource

    with pytest.raises(MmslamError, match="expected"):
        src.trace_step(0, states[0, :1])
    with pytest.raises(ConfigError, match="max_depth"):
        SionnaSource(scn, max_depth=5)
    v = src.versions()
    assert set(v) >= {"sionna-rt", "mitsuba", "drjit"} and v["sionna-rt"].startswith("2.")
    assert src.settings()["max_depth"] == 1 and src.settings()["refraction"] is False


def test_external_xml_scene_va_by_plane(tmp_path):
    """sionna:floor_wall (wall in the plane x = 0) with one car: the wall VA is labelled by its plane."""
    from mmslam.raytrace.sionna_adapter import SionnaSource

    base = load_preset("paper")
    veh = dataclasses.replace(base.vehicles[0], name="car", initial_state=(1.2, -0.5, 1.2, 0.0, 0.0, 0.0, 0.0),
                              length=0.5, width=0.5, height=0.5)
    scn = dataclasses.replace(base, xml_scene="sionna:floor_wall", buildings=(), scatterers=(), vehicles=(veh,),
                              bs=(1.5, 0.0, 2.0))
    src = SionnaSource(scn, max_depth=1, samples_per_src=10**4, scene_dir=tmp_path)
    st = np.array([veh.initial_state])
    lab = src.trace_step(0, st)
    ids = {str(i): j for j, i in enumerate(lab["landmark_id"])}
    assert "bs" in ids
    va = [i for i in ids if i.startswith("plane(")]
    assert va == ["plane(+1.0000,+0.0000,+0.0000,+0.000)"]  # the wall x = 0, normal towards the BS
    j = ids[va[0]]
    lm = np.array([lab["lm_x"][j], lab["lm_y"][j], lab["lm_z"][j]])
    np.testing.assert_allclose(lm, [-1.5, 0.0, 2.0], atol=1e-3)
    g = channel_params(st[0, :3], lm, Bounce.MIRROR, np.array(scn.bs))
    assert abs(lab["toa_m"][j] - g[0]) < 1e-2
    assert np.all(np.abs(np.angle(np.exp(1j * (np.array([lab[c][j] for c in ("aod_az", "aod_el", "aoa_az", "aoa_el")]) - g[1:])))) < 1e-3)


def test_visibility_with_partial_walls(tmp_path):
    """Shortened walls: VAs appear and disappear along the lap exactly as the closed form says."""
    from mmslam.raytrace.sionna_adapter import SionnaSource
    from mmslam.scenes.scenario import Building

    base = load_preset("paper")
    walls = (Building("wall_east", (100.0, -100.0, -5.0), (105.0, -20.0, 60.0)),
             Building("wall_north", (0.0, 100.0, -5.0), (100.0, 105.0, 60.0)),
             Building("wall_west", (-105.0, -100.0, -5.0), (-100.0, 100.0, 20.0)))
    scn = dataclasses.replace(base, buildings=walls)
    states = vehicle_trajectories(scn)
    src = SionnaSource(scn, max_depth=1, samples_per_src=2 * 10**5, scene_dir=tmp_path)
    seen_sets = set()
    for k in range(0, 40, 4):
        lab = src.trace_step(k, states[k])
        for rx in range(2):
            got = {lab["landmark_id"][i] for i in range(len(lab["rx"]))
                   if lab["rx"][i] == rx and lab["type"][i] in (BS, VA)}
            want = _closed_form_visible(scn, states[k], rx)
            assert got == want, (k, rx, got, want)
            seen_sets.add(frozenset(want))
    assert len(seen_sets) >= 3  # the visible set really changes along the lap


def test_moving_vehicles_does_not_recompile(traced):
    """After the first steps, new vehicle poses reuse the cached kernels (no JIT cache miss)."""
    import drjit as dr

    scn, states, src, _ = traced
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history_clear()
        for k in (3, 21):
            src.trace_step(k, states[k])
        hist = dr.kernel_history([dr.KernelType.JIT])
    assert len(hist) > 0
    assert sum(not h["cache_hit"] for h in hist) == 0


_FRESH_CACHE_SCRIPT = """
import json, sys
import drjit as dr
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import vehicle_trajectories
from mmslam.raytrace.sionna_adapter import SionnaSource
out = {}
for name, steps in (("paper", (0, 1, 13, 29)), ("canyon", (0, 1, 21))):
    scn = load_preset(name)
    states = vehicle_trajectories(scn)
    src = SionnaSource(scn, max_depth=1, samples_per_src=10**5, seed=0)
    misses = []
    for k in steps:
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history_clear()
            src.trace_step(k, states[k])
            misses.append(sum(not h["cache_hit"] for h in dr.kernel_history([dr.KernelType.JIT])))
    out[name] = misses
print(json.dumps(out))
"""


def test_no_kernel_is_retraced_after_the_first_step_with_an_empty_kernel_cache(tmp_path):
    """Fresh Dr.Jit kernel cache (HOME is an empty folder): step 0 compiles, later steps of the
    same scene compile nothing (receiver positions, car velocities and path counts would otherwise
    be literal constants in the kernels, one compile per step)."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, HOME=str(tmp_path))
    run = subprocess.run([sys.executable, "-c", _FRESH_CACHE_SCRIPT], env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    misses = json.loads(run.stdout.strip().splitlines()[-1])
    assert (tmp_path / ".drjit").is_dir()  # the cache really was the empty folder
    for name, per_step in misses.items():
        assert per_step[0] > 0, (name, per_step)  # the first step did compile (the cache was empty)
        assert per_step[1:] == [0] * (len(per_step) - 1), (name, per_step)


def test_bs_va_rows_agree_with_analytic_source(traced):
    """Cross-check against the closed-form source: same BS/VA ids, TOA, angles; LOS power = Friis."""
    from mmslam.raytrace.analytic import AnalyticSource

    scn, states, _, out = traced
    ana = AnalyticSource(scn)
    for k, (_, lab) in out.items():
        ref = ana.trace_step(k, states[k])

        def rows(t):
            return {(int(r), str(i)): j for j, (r, ty, i) in enumerate(zip(t["rx"], t["type"], t["landmark_id"]))
                    if ty in (BS, VA)}

        a, s = rows(ref), rows(lab)
        assert set(a) == set(s), k
        for key, j in s.items():
            i = a[key]
            assert abs(lab["toa_m"][j] - ref["toa_m"][i]) < 1e-2
            for c in ("aod_az", "aod_el", "aoa_az", "aoa_el"):
                assert abs(np.angle(np.exp(1j * (lab[c][j] - ref[c][i])))) < 1e-3, (k, key, c)
            if key[1] == "bs":  # free-space LOS: isotropic antennas, no material involved
                assert lab["power_db"][j] == pytest.approx(ref["power_db"][i], abs=0.05)


@pytest.mark.slow
def test_munich_merged_va_labels_are_exact_planes_of_the_scene(tmp_path):
    """Munich loads as a few merged shapes; every VA row's bounce point lies on the plane whose mirror
    image is its landmark (the perpendicular bisector of BS and landmark), its TOA is the distance
    image -> antenna, and an id names the same landmark at every step."""
    from mmslam.raytrace.sionna_adapter import SionnaSource

    scn = load_preset("munich")
    states = vehicle_trajectories(scn)
    src = SionnaSource(scn, max_depth=1, samples_per_src=2 * 10**5, scene_dir=tmp_path)
    assert src.merged and len(src.scene.objects) < 30  # 2367 objects unmerged
    b = scn.bs_array
    seen: dict[str, np.ndarray] = {}
    n_va = 0
    for k in (0, 13, 27):
        lab = src.trace_step(k, states[k])
        for i in _rows(lab, VA):
            lm = np.array([lab["lm_x"][i], lab["lm_y"][i], lab["lm_z"][i]])
            p = np.array([lab["bounce_x"][i], lab["bounce_y"][i], lab["bounce_z"][i]])
            n = (b - lm) / np.linalg.norm(b - lm)
            assert abs(np.dot(n, p - (b + lm) / 2)) < 1e-2, lab["landmark_id"][i]
            u = states[k, lab["rx"][i], :3]
            assert lab["toa_m"][i] == pytest.approx(np.linalg.norm(lm - u), abs=1e-2)
            lid = str(lab["landmark_id"][i])
            assert lid.startswith("plane(")
            if lid in seen:
                np.testing.assert_array_equal(seen[lid], lm)
            seen[lid] = lm
            n_va += 1
    assert n_va >= 5


def test_double_wall_bounces_are_order_two_vas_at_the_image_of_the_image(tmp_path):
    """`paper`'s east and west walls only (x = +-100, parallel), one car between them, max_depth 2
    (issue 24, second-order reflections): Sionna's two double wall bounces are VAs of order 2 with ids
    'east|west' and 'west|east'; each landmark is the BS mirrored in the first face, then in the second;
    |u - v2| equals the traced path length (1e-4 m) and the arrival direction points at v2 (1e-4 rad); the
    reflection points the label implies (where u -> v2 crosses the second face, then where that point ->
    v1 crosses the first) lie inside the two faces and are Sionna's bounce vertices (1 mm). The filter's
    single-mirror model gets the TOA and AOA of v2 right but not the AOD (a model limit, docs/estimator.md)."""
    from mmslam.raytrace.sionna_adapter import SionnaSource
    from mmslam.model import mirror_point

    base = load_preset("paper")
    walls = tuple(b for b in base.buildings if b.name in ("wall_east", "wall_west"))
    veh = dataclasses.replace(base.vehicles[0], name="car", initial_state=(30.0, 20.0, 0.0, 0.3, 0.0, 0.0, 0.0))
    scn = dataclasses.replace(base, buildings=walls, scatterers=(), vehicles=(veh,))
    st = vehicle_trajectories(scn)[0]
    u = st[0, :3]
    b = scn.bs_array
    src = SionnaSource(scn, max_depth=2, samples_per_src=10**6, scene_dir=tmp_path)
    tabs = src.trace_tables(0, st)
    lab, rays = tabs["paths"], tabs["rays"]
    rows = {str(i): k for k, (t, i) in enumerate(zip(lab["type"], lab["landmark_id"])) if t in (BS, VA)}
    assert set(rows) == {"bs", "wall_east:-x", "wall_west:+x", "wall_east:-x|wall_west:+x", "wall_west:+x|wall_east:-x"}
    face = {"wall_east:-x": (np.array([100.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])),
            "wall_west:+x": (np.array([-100.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))}
    for lid in ("wall_east:-x|wall_west:+x", "wall_west:+x|wall_east:-x"):
        k = rows[lid]
        f1, f2 = (face[s] for s in lid.split("|"))
        v1 = mirror_point(b, *f1)
        v2 = mirror_point(v1, *f2)
        assert lab["bounces"][k] == 2 and lab["n_paths"][k] == 1
        lm = np.array([lab[c][k] for c in ("lm_x", "lm_y", "lm_z")])
        np.testing.assert_allclose(lm, v2, atol=1e-9)
        assert abs(np.linalg.norm(u - lm) - lab["toa_m"][k]) < 1e-4
        d = _unit(lab["aoa_az"][k], lab["aoa_el"][k])
        assert np.linalg.norm(d - (lm - u) / np.linalg.norm(lm - u)) < 1e-4
        # reflection points implied by the label
        t2 = (f2[0][0] - u[0]) / (v2[0] - u[0])
        q2 = u + t2 * (v2 - u)
        t1 = (f1[0][0] - q2[0]) / (v1[0] - q2[0])
        q1 = q2 + t1 * (v1 - q2)
        assert 0 < t2 < 1 and 0 < t1 < 1
        for q in (q1, q2):
            assert -100.0 <= q[1] <= 100.0 and -5.0 <= q[2] <= 60.0  # inside the face rectangle
        r = int(np.flatnonzero((rays["rx"] == 0) & (rays["ray"] == lab["ray"][k]))[0])
        np.testing.assert_allclose([rays[f"bounce1_{c}"][r] for c in "xyz"], q1, atol=1e-3)
        np.testing.assert_allclose([rays[f"bounce2_{c}"][r] for c in "xyz"], q2, atol=1e-3)
        g = channel_params(u, lm, Bounce.MIRROR, b)
        assert abs(g[0] - lab["toa_m"][k]) < 1e-4
        assert np.all(np.abs(np.angle(np.exp(1j * (g[3:] - [lab["aoa_az"][k], lab["aoa_el"][k]])))) < 1e-4)
        # the true departure is towards q1; the single-mirror model departs towards the bisector of b, v2
        aod = _unit(lab["aod_az"][k], lab["aod_el"][k])
        np.testing.assert_allclose(aod, (q1 - b) / np.linalg.norm(q1 - b), atol=1e-4)
        assert np.linalg.norm(_unit(g[1], g[2]) - aod) > 1.0
