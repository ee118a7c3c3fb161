"""Scenario model: the paper preset's geometry and every validation error's message."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mmslam.errors import ConfigError
from mmslam.scenes.landmarks import reflecting_faces, sp_truth, va_truth
from mmslam.scenes.scenario import (list_presets, load_preset, load_scenario, preset_path,
                                    scenario_from_resolved)
from mmslam.scenes.trajectory import vehicle_trajectories


def test_presets_listed():
    assert {"paper", "street"} <= set(list_presets())


def test_paper_vehicle1_circle_radius_and_return():
    scn = load_preset("paper")
    s = vehicle_trajectories(scn, steps=41)
    v1 = scn.vehicles[0].initial_state
    # turn radius zeta / xi and the circle centred on the BS footprint
    assert v1[4] / v1[5] == pytest.approx(70.73, abs=2e-3)
    r = np.hypot(s[:, 0, 0], s[:, 0, 1])
    assert np.allclose(r, 70.73, atol=4e-3)  # CT centre is 1.5 mm off the BS (22.22 m/s is rounded)
    # 40 steps of 0.5 s at pi/10 rad/s is exactly one lap
    assert np.linalg.norm(s[40, 0, :3] - s[0, 0, :3]) < 1e-6
    assert s[40, 0, 3] == pytest.approx(s[0, 0, 3] + 2 * math.pi)


def test_paper_vehicles_parallel_same_bearing():
    scn = load_preset("paper")
    s = vehicle_trajectories(scn)
    bearing = np.arctan2(s[:, :, 1], s[:, :, 0])
    diff = np.angle(np.exp(1j * (bearing[:, 0] - bearing[:, 1])))
    assert np.max(np.abs(diff)) < 1e-4
    assert np.allclose(s[:, 0, 3], s[:, 1, 3])  # same heading at every step
    # and 10 m apart radially
    assert np.allclose(np.hypot(s[:, 0, 0], s[:, 0, 1]) - np.hypot(s[:, 1, 0], s[:, 1, 1]), 10.0, atol=1.5e-2)


def test_paper_vas_and_sps():
    scn = load_preset("paper")
    vas = va_truth(scn)
    got = sorted(tuple(np.round(v, 9)) for v in vas.values())
    assert got == sorted([(200.0, 0.0, 40.0), (-200.0, 0.0, 40.0), (0.0, 200.0, 40.0), (0.0, -200.0, 40.0)])
    sps = sp_truth(scn)
    assert len(sps) == 4
    for p in sps.values():
        assert abs(abs(p[0]) - 55) < 1e-12 and abs(abs(p[1]) - 55) < 1e-12 and 0 <= p[2] <= 40
    # drawn once from the scenario seed: the same every load, different z per SP
    assert [p.position for p in load_preset("paper").scatterers] == [p.position for p in scn.scatterers]
    assert len({p[2] for p in sps.values()}) == 4


def test_paper_reflecting_faces_are_inner_walls():
    faces = {f.id for f in reflecting_faces(load_preset("paper"))}
    assert faces == {"wall_east:-x", "wall_west:+x", "wall_north:-y", "wall_south:+y"}


def test_street_preset_shape():
    scn = load_preset("street")
    assert scn.ground is not None and len(scn.buildings) >= 6 and len(scn.scatterers) == 4
    assert len({b.max[2] for b in scn.buildings}) == len(scn.buildings)  # all heights differ
    assert len(scn.vehicles) == 3 and scn.steps == 60
    s = vehicle_trajectories(scn)
    # car_a drives east, car_b north at first: not parallel
    assert abs(math.cos(s[0, 0, 3] - s[0, 1, 3])) < 1e-9
    # waypoint motion: the CT model with the stored inputs reproduces the next position exactly
    from mmslam.slam.models.dynamics import vehicle_ct

    pred = vehicle_ct(s[:-1], scn.dt)
    assert np.allclose(pred[..., :2], s[1:, :, :2], atol=1e-9)
    # ... and the next heading: no jump at car_b's corner that the filter's motion model cannot follow
    assert np.abs(np.angle(np.exp(1j * (pred[..., 3] - s[1:, :, 3])))).max() < 1e-12
    assert abs(math.cos(s[-1, 1, 3]) + 1) < 5e-5 and abs(s[0, 1, 3] - math.pi / 2) < 1e-12  # north, then west (within 0.01 rad)


def test_a_jagged_route_is_driven_as_a_smooth_curve_with_consistent_inputs():
    """A street-centreline route zig-zagging +-0.5 m every 2 m (what `mmslam scene streets` routes look like at
    the scale of one step): the car drives it under the CT model with its stored inputs (positions and heading
    reproduced to 1e-9 / 1e-12), stays within 0.6 m of its centre line (the zig-zag is +-0.5 m), turns by less than the polyline's
    chords would (each about 0.46 rad), keeps its plan speed and stops at the last waypoint; a straight route
    is driven on the line exactly, as before this rule."""
    from mmslam.scenes.scenario import Vehicle
    from mmslam.scenes.driving import _project, _route
    from mmslam.scenes.trajectory import _waypoint_trajectory
    from mmslam.slam.models.dynamics import vehicle_ct

    xs = np.arange(0.0, 101.0, 2.0)
    wps = np.stack([xs, np.where(np.arange(xs.size) % 2 == 1, 0.5, -0.5), np.full(xs.size, 1.5)], -1)
    car = Vehicle(name="z", initial_state=(0.0, -0.5, 1.5, 0.0, 7.0, 0.0, 0.0), motion="waypoints",
                  waypoints=tuple(tuple(map(float, p)) for p in wps))
    s = _waypoint_trajectory(car, 30, 0.5)
    pred = vehicle_ct(s[:-1], 0.5)
    assert np.abs(pred[:, :2] - s[1:, :2]).max() < 1e-9
    assert np.abs(np.angle(np.exp(1j * (pred[:, 3] - s[1:, 3])))).max() < 1e-12
    assert np.abs(s[:, 1]).max() < 0.6 and np.abs(np.angle(np.exp(1j * s[1:, 3]))).max() < 0.2
    assert np.allclose(s[:14, 4], 7.0) and s[-1, 4] == 0.0 and s[-1, 5] == 0.0
    seg, sl, cum = _route(wps)
    assert abs(_project(s[-1, :2], s[-1, 3], wps, seg, sl, cum, 0.0, cum[-1]) - cum[-1]) < 1e-6  # at the end
    straight = Vehicle(name="s", initial_state=(0.0, 2.0, 1.5, 0.0, 7.0, 0.0, 0.0), motion="waypoints",
                       waypoints=((0.0, 2.0), (60.0, 2.0)))
    t = _waypoint_trajectory(straight, 12, 0.5)
    np.testing.assert_allclose(t[:, 0], np.minimum(np.arange(12) * 3.5, 60.0), atol=1e-9)
    assert np.abs(t[:, 1] - 2.0).max() < 1e-12 and np.abs(t[:, 3]).max() < 1e-12


def test_u_turns_and_hairpins_are_driven_round_the_turning_circle():
    """Out and back on one line, and a hairpin whose return leg is 2 m from the outward one: the car turns round on
    its tightest circle (5 m radius: it swings out at most 2 x 5 m), its progress never jumps to the return leg
    (at most 1.5 steps + 0.5 m per step), it ends at the route's end, and its turn rate never exceeds speed / 5 m;
    the stored inputs reproduce every next state (CT model)."""
    from mmslam.scenes.driving import MIN_TURN_RADIUS, _route, drive_route
    from mmslam.slam.models.dynamics import vehicle_ct

    def off_route(wps: np.ndarray, xy: np.ndarray) -> np.ndarray:
        seg, sl, _ = _route(wps)
        t = np.clip(np.einsum("nsk,sk->ns", xy[:, None] - wps[None, :-1, :2], seg) / sl ** 2, 0.0, 1.0)
        return np.min(np.linalg.norm(wps[None, :-1, :2] + t[..., None] * seg - xy[:, None], axis=-1), axis=1)

    for route in ([[0.0, 0.0], [50.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [50.0, 0.0], [50.0, 2.0], [0.0, 2.0]]):
        wps = np.array(route)
        s = drive_route(wps, 7.0, 40, 0.5)
        assert off_route(wps, s[:, :2]).max() <= 2 * MIN_TURN_RADIUS + 0.1
        assert np.linalg.norm(s[-1, :2] - wps[-1]) < 1.0 and s[-1, 4] == 0.0
        assert np.abs(s[:, 5]).max() <= 7.0 / MIN_TURN_RADIUS + 1e-12
        pred = vehicle_ct(s[:-1], 0.5)
        assert np.abs(pred[:, :2] - s[1:, :2]).max() < 1e-9
        back = (np.cos(s[:, 3]) < 0) & (s[:, 0] < 30.0)  # heading back, 20 m past the turn: on the return leg
        assert back.sum() >= 5 and (np.abs(s[back, 1] - wps[-1, 1]) < 1.0).all()


def test_resolved_roundtrip():
    scn = load_preset("paper")
    back = scenario_from_resolved(scn.to_dict())
    assert back.to_dict() == scn.to_dict()
    assert back.geometry_hash() == scn.geometry_hash()


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


BASE = """
name = "t"
bs = [0, 0, 10]
[[buildings]]
name = "b1"
min = [10, -5, 0]
max = [20, 5, 10]
[[vehicles]]
name = "v1"
initial_state = [0, 0, 1.6, 0, 5, 0, 0]
"""


@pytest.mark.parametrize("mutate, key, expect", [
    (lambda t: "colour = 3\n" + t, "colour", "unknown key"),
    (lambda t: t.replace('bs = [0, 0, 10]', 'bs = [0, 10]'), "bs", "list of 3 numbers"),
    (lambda t: t.replace('bs = [0, 0, 10]', 'bs = "origin"'), "bs", "list of 3 numbers"),
    (lambda t: "dt = -1\n" + t, "dt", "> 0.0"),
    (lambda t: "steps = 2.5\n" + t, "steps", "integer"),
    (lambda t: t.replace("initial_state = [0, 0, 1.6, 0, 5, 0, 0]", "initial_state = [15, 0, 1.6, 0, 5, 0, 0]"),
     "vehicles[0].initial_state", "starts inside building 'b1'"),
    (lambda t: t + '\n[sensor]\np_detect = 1.5\n', "sensor.p_detect", "probability in [0, 1]"),
    (lambda t: t + '\n[sensor]\nnoise = 1\n', "sensor.noise", "unknown key"),
    (lambda t: t + '\n[sensor]\ntoa_stdd = 1\n', "sensor.toa_stdd", "did you mean 'toa_std'?"),
    (lambda t: "stepps = 3\n" + t, "stepps", "did you mean 'steps'?"),
    (lambda t: t.replace('max = [20, 5, 10]', 'max = [20, 5, 10]\nmaterial = "medium_dry_ground"'),
     "buildings[0].material", "expected one of"),
    (lambda t: t.replace('max = [20, 5, 10]', 'max = [5, 5, 10]'), "buildings[0].max", "max > min"),
    (lambda t: t.replace('name = "v1"', 'name = "b1"'), "name", "unique"),
    (lambda t: t.replace('name = "v1"', 'name = "v1"\nmotion = "teleport"'), "vehicles[0].motion", "expected one of"),
    (lambda t: t.replace('name = "v1"', 'name = "v1"\nmotion = "waypoints"\nwaypoints = [[0, 0]]'),
     "vehicles[0].waypoints", "at least two"),
])
def test_validation_errors(tmp_path, mutate, key, expect):
    p = _write(tmp_path, mutate(BASE))
    with pytest.raises(ConfigError) as e:
        load_scenario(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: key '{key}'") and expect in msg and "\n" not in msg


def test_no_vehicles_rejected(tmp_path):
    text = "vehicles = []\n" + BASE.split("[[vehicles]]")[0]
    with pytest.raises(ConfigError, match=r"key 'vehicles': expected at least one"):
        load_scenario(_write(tmp_path, text))


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="scenario file not found"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(_write(tmp_path, "name = [\n"))


def test_unknown_preset():
    with pytest.raises(ConfigError, match=r"unknown scenario 'nope'; expected a preset \(canyon, munich, paper, street, twc2020\) or a path to a \.toml file"):
        load_preset("nope")


def test_valid_base_loads(tmp_path):
    scn = load_scenario(_write(tmp_path, BASE))
    assert scn.vehicles[0].name == "v1" and scn.steps == 40 and preset_path("paper").is_file()


def test_true_process_noise_changes_truth_and_hash():
    import dataclasses

    from mmslam.scenes.trajectory import true_trajectories

    noisy = load_preset("paper")
    assert noisy.sensor.true_process_noise  # the paper preset's truth has process noise (TWC2020)
    scn = dataclasses.replace(noisy, sensor=dataclasses.replace(noisy.sensor, true_process_noise=False))
    a, b = true_trajectories(noisy, 10), true_trajectories(noisy, 20)
    assert np.array_equal(a, b[:10])  # extension keeps the first steps
    clean = true_trajectories(scn, 10)
    assert np.array_equal(clean[0], a[0]) and not np.allclose(clean[5, :, :2], a[5, :, :2])
    assert np.all(a[:, :, 6] == 300.0)  # the clock bias walk is the sensor model's, not here
    assert noisy.geometry_hash() != scn.geometry_hash()


def test_every_filter_section_parameter_is_declared_with_doc_and_bounds():
    import dataclasses

    from mmslam.scenes.params import spec_of
    from mmslam.scenes.scenario import PARAM_SECTIONS, TypeParams

    sections = {**PARAM_SECTIONS, "filter.types.<TYPE>": TypeParams}
    for section, cls in sections.items():
        for f in dataclasses.fields(cls):
            if (cls, f.name) == (PARAM_SECTIONS["filter"], "types"):  # the per-type table: TypeParams rows
                continue
            spec = spec_of(f)
            assert spec is not None and spec.doc, f"{section}.{f.name} has no declaration"
            if not isinstance(f.default, (bool, str)):
                assert spec.lo is not None and spec.hi is not None, f"{section}.{f.name} is unbounded"


@pytest.mark.parametrize("sets,needle", [
    (["evaluation.gospa_c=0"], "evaluation.gospa_c"),
    (["evaluation.gospa_p=0.5"], "evaluation.gospa_p"),
    (["evaluation.gospa_alpha=3"], "evaluation.gospa_alpha"),
    (["sensor.clutter_mean=1e9"], "sensor.clutter_mean"),
    (["filter.particles=1000000000"], "filter.particles"),
    (["filter.p_survival=1.5"], "probability"),
    (["filter.vs_dither=[1, 2]"], "filter.vs_dither"),
    (["filter.nonsense=1"], "unknown parameter"),
    (["filter.merge"], "section.key=value"),
    (["filter.merg=4"], "did you mean filter.merge?"),
    (["fusion.gama_detect=0.5"], "did you mean fusion.gamma_detect?"),
    (["filter.types.VA.birth_existance=0.9"], "did you mean filter.types.VA.birth_existence?"),
])
def test_overrides_are_validated_like_the_file(sets, needle):
    from mmslam.scenes.scenario import load_preset, with_overrides

    with pytest.raises(ConfigError) as e:
        with_overrides(load_preset("paper"), sets)
    msg = str(e.value)
    assert needle in msg and "\n" not in msg


def test_overrides_change_only_the_named_keys():
    from mmslam.scenes.scenario import load_preset, with_overrides

    base = load_preset("paper")
    s = with_overrides(base, ["filter.merge=4", "fusion.beta_inside_fov=0.5", "filter.vs_dither=[1,1,1,1,1,1,1]"])
    assert s.filter.merge == 4.0 and s.fusion.beta_inside_fov == 0.5 and s.filter.vs_dither == (1.0,) * 7
    assert s.geometry_hash() == base.geometry_hash()
    assert s.scatterers == base.scatterers and s.fusion.start == base.fusion.start
    assert s.filter.p_survival == base.filter.p_survival


def test_parameter_reference_lists_every_key():
    import dataclasses

    from mmslam.scenes.scenario import PARAM_SECTIONS, TypeParams, parameter_reference

    text = parameter_reference()
    sections = {**PARAM_SECTIONS, "filter.types.<TYPE>": TypeParams}
    for section, cls in sections.items():
        for f in dataclasses.fields(cls):
            if (cls, f.name) != (PARAM_SECTIONS["filter"], "types"):  # the table: its rows' keys below
                assert f"`{section}.{f.name}`" in text


def test_city_presets_ship_with_the_package():
    canyon, munich = load_preset("canyon"), load_preset("munich")
    assert canyon.xml_scene == "sionna:simple_street_canyon" and len(canyon.vehicles) == 3
    assert munich.xml_scene == "sionna:munich" and len(munich.vehicles) == 5 and munich.steps == 40
    assert np.allclose(munich.bs, [8.5, 21.0, 30.0])
    assert all(4.0 <= v.initial_state[4] <= 7.0 for v in munich.vehicles)
    assert all(v.motion == "waypoints" for v in (*canyon.vehicles, *munich.vehicles))


def test_every_declared_parameter_is_read_by_the_code():
    """No dead knobs: each [sensor]/[filter]/[fusion]/[evaluation] parameter is read outside its
    declaration (an attribute access ``obj.<name>`` in the code, docstrings and strings not counted,
    including the per-type table's keys (:class:`TypeParams`, read through the landmark specs)."""
    import ast
    from pathlib import Path

    from mmslam.scenes.params import iter_params
    from mmslam.scenes.scenario import PARAM_SECTIONS, TypeParams

    root = Path(__file__).resolve().parents[1]
    skip = {root / "scenes" / "scenario.py", root / "scenes" / "params.py"}
    read = {n.attr for d in ("slam", "pipelines", "raytrace", "scenes", "mmslam")
            for p in sorted((root / d).rglob("*.py")) if p not in skip
            for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.Attribute)}
    dead = [f"{sec}.{f.name}" for sec, cls in PARAM_SECTIONS.items() for f, _ in iter_params(cls)
            if f.name not in read]
    dead += [f"filter.types.<TYPE>.{f.name}" for f, _ in iter_params(TypeParams) if f.name not in read]
    assert dead == []


HELD_OUT = sorted((Path(__file__).resolve().parents[1] / "benchmarks" / "scenes").glob("*.toml"))


@pytest.mark.parametrize("path", HELD_OUT, ids=lambda p: p.stem)
def test_held_out_scenes_are_written_as_a_user_would(path):
    """The held-out city scenarios (docs/city-slam.md) carry the scene only: no [filter] / [fusion] / [sensor]
    table (the defaults under test), a Sionna city scene, a header saying how they were built, a line in the
    folder's README; and they load (routes snapped to the streets)."""
    import tomllib

    text = path.read_text()
    raw = tomllib.loads(text)
    assert not {"filter", "fusion", "sensor"} & set(raw), f"{path.name} tunes the filter"
    assert raw["xml_scene"].startswith("sionna:") and "How it was built" in text
    assert f"`{path.name}`" in (path.parent / "README.md").read_text()
    scn = load_scenario(path)
    assert scn.name == path.stem and len(scn.vehicles) == 3 and scn.filter.r_scale == 1.0
    from mmslam.scenes.scenario import scenario_route_points
    from mmslam.scenes.trajectory import route_warnings, true_trajectories

    # every car drives its route as written, to the last step (no detour, no stop)
    assert route_warnings(scn, true_trajectories(scn), scenario_route_points(scn)) == []


def test_the_held_out_scenes_are_all_there():
    assert [p.stem for p in HELD_OUT] == ["etoile", "etoile2", "etoile3", "etoile4", "etoile5", "etoile6",
                                          "florence", "florence2", "florence3", "florence4", "florence5", "munich2",
                                          "munich3", "munich4", "munich5", "munich6", "munich7",
                                          "sanfrancisco", "sf3", "sf4",
                                          "sf5", "sf6", "sfhills", "sfhills2"]


def test_a_typo_gets_one_suggestion_not_the_whole_list():
    """A close key names only itself (the full list, ~80 keys, only when nothing is close); a file's unknown key too."""
    from mmslam.scenes.params import did_you_mean
    from mmslam.scenes.scenario import load_preset, with_overrides

    assert did_you_mean("merg", ["merge", "prune"]) == "merge" and did_you_mean("xyz", ["merge", "prune"]) is None
    with pytest.raises(ConfigError) as e:
        with_overrides(load_preset("paper"), ["filter.p_detect_vaa=0.2"])
    assert str(e.value).count(",") == 0 and "filter.p_detect_va?" in str(e.value)
    with pytest.raises(ConfigError) as e:
        with_overrides(load_preset("paper"), ["filter.xyz=1"])
    assert "sensor.toa_std" in str(e.value)  # nothing close: the list

