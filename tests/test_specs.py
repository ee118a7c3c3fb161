"""Landmark-type specs, variant specs, the source registry and the run loop's step API."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mmslam.errors import ConfigError, MmslamError
from mmslam.model import Bounce, LandmarkType
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.scenes.trajectory import vehicle_trajectories
from mmslam.slam.specs import landmarks as L
from mmslam.slam.specs import variants as V
from mmslam.slam.models.measurement import measure
from mmslam.slam.filter.run import CooperativeRun, run_filter
from mmslam.slam.sim.sensor import fov_detect_prob
from mmslam.slam.specs.landmarks import geometry_of

BS_POS = np.array([0.0, 0.0, 40.0])


@pytest.fixture(scope="module")
def paper12():
    scn = load_preset("paper")
    states = vehicle_trajectories(scn, 12)
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(12)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    return scn, states, paths


# ---------------------------------------------------------------- landmark types
def test_builtin_types_codes_geometry_and_dimensions():
    by = {s.name: s for s in L.landmark_types()}
    assert list(by) == ["BS", "VA", "SP", "VS"]
    assert {n: s.code for n, s in by.items()} == {t.name: int(t) for t in LandmarkType if t.name != "OTHER"}
    assert [by[n].geometry for n in ("BS", "VA", "SP", "VS")] == [Bounce.DIRECT, Bounce.MIRROR, Bounce.SCATTER,
                                                                   Bounce.SCATTER]
    assert [by[n].state_dim for n in ("VA", "SP", "VS")] == [3, 3, 7]
    assert [s.name for s in L.mapped_types()] == ["VA", "SP", "VS"]
    assert [s.name for s in L.landmark_types() if s.moving] == ["VS"]


@pytest.mark.parametrize("name", ["VA", "SP", "VS"])
def test_each_types_geometry_is_its_measurement_model(name):
    """The geometry code of a spec drives h(s, x): MIRROR = distance from the image source,
    SCATTER = BS -> point -> vehicle (hand-computed TOA), AOA towards the point in both."""
    spec = L.landmark_type(name)
    s = np.array([30.0, -20.0, 1.5, 0.3, 10.0, 0.1, 5.0])
    x = np.array([120.0, 15.0, 12.0])
    z = measure(s, x, spec.geometry, BS_POS)
    u = s[:3]
    if spec.geometry is Bounce.MIRROR:
        toa = np.linalg.norm(x - u)
    else:
        toa = np.linalg.norm(x - BS_POS) + np.linalg.norm(x - u)
    assert z[0] == pytest.approx(toa + s[6], rel=1e-12)
    d = x - u
    assert z[3] == pytest.approx(np.arctan2(d[1], d[0]) - s[3], abs=1e-12)
    assert z[4] == pytest.approx(np.arcsin(d[2] / np.linalg.norm(d)), abs=1e-12)
    # the type's code leads to the same geometry through the registry (the one owner of code -> geometry)
    np.testing.assert_allclose(measure(s, x, geometry_of(spec.code), BS_POS), z, rtol=1e-12)
    assert geometry_of(spec.code) == geometry_of(spec.name) == int(spec.geometry)


def test_fov_rule_follows_the_specs():
    scn = load_preset("paper")
    r = scn.sensor.fov_range
    u = np.zeros(3)
    for spec in L.landmark_types():
        near, far = np.array([r - 1.0, 0.0, 0.0]), np.array([r + 1.0, 0.0, 0.0])
        assert float(fov_detect_prob(u, near, spec.code, scn.sensor)) == scn.sensor.p_detect
        want_far = 0.0 if spec.range_gated else scn.sensor.p_detect
        assert float(fov_detect_prob(u, far, spec.code, scn.sensor)) == want_far
        assert spec.fov_radius(scn.sensor) == (r if spec.range_gated else np.inf)
    # vectorised over codes: the same rule row by row
    codes = np.array([s.code for s in L.landmark_types()])
    pts = np.broadcast_to([r + 1.0, 0.0, 0.0], (codes.size, 3))
    got = fov_detect_prob(np.zeros((codes.size, 3)), pts, codes, scn.sensor)
    np.testing.assert_array_equal(got > 0, [not s.range_gated for s in L.landmark_types()])


def test_spec_parameters_are_the_rows_of_the_per_type_table():
    """Each built-in type reads its own [filter.types.<NAME>] row; the old flat keys are aliases of the
    rows' entries (in --set and as attributes), a type without a row gets TypeParams' defaults."""
    from mmslam.scenes.scenario import DEFAULT_TYPE_PARAMS, TYPE_PARAM_ALIASES, TypeParams

    scn = load_preset("paper")
    assert set(DEFAULT_TYPE_PARAMS) == set(L.BUILTIN_TYPES)
    for spec in L.landmark_types():
        assert spec.params == spec.name and spec.type_params(scn) == scn.filter.types[spec.name]
        assert spec.p_detect(scn) == 0.95
        if spec.mapped:
            assert spec.threshold(scn) == (0.7 if spec.name == "VA" else 0.55)
            assert spec.merge_gate(scn) == scn.filter.merge == 49.0
        else:
            with pytest.raises(MmslamError, match="no estimate threshold"):
                spec.threshold(scn)
    scn2 = with_overrides(scn, ["filter.threshold_vs=0.8", "filter.p_detect_sp=0.5", "filter.types.VA.merge=4"])
    assert L.landmark_type("VS").threshold(scn2) == 0.8 and L.landmark_type("SP").p_detect(scn2) == 0.5
    assert L.landmark_type("VA").merge_gate(scn2) == 4.0 and L.landmark_type("SP").merge_gate(scn2) == 49.0
    assert scn2.filter.threshold_vs == 0.8 and scn2.filter.merge_va == 4.0  # alias attributes
    assert len(TYPE_PARAM_ALIASES) == 8 and all(getattr(scn.filter, a) is not None for a in TYPE_PARAM_ALIASES)
    assert scn.filter.type_params("LP") == TypeParams()
    lp = dataclasses.replace(L.SP_SPEC, name="LPX", code=9, params="SP")
    assert lp.type_params(scn2) is scn2.filter.types["SP"] and lp.p_detect(scn2) == 0.5


def test_the_per_type_table_in_a_file_and_its_aliases():
    """[filter.types.<TYPE>] rows set only the keys they give; an old flat key fills the same entry; both for
    one entry is refused naming the key; merge_va < 0 is 'not set'; the resolved scenario round-trips."""
    import tomllib
    from importlib import resources

    from mmslam.scenes.scenario import scenario_from_dict, scenario_from_resolved

    text = resources.files("mmslam.scenes").joinpath("presets", "paper.toml").read_text()

    def load(**filt):
        data = tomllib.loads(text)
        data["filter"].update(filt)
        return scenario_from_dict(data, "test.toml")

    from mmslam.model import set_landmark_type_name

    with pytest.raises(ConfigError, match="filter.types.LP': no landmark type 'LP' is registered"):
        load(types={"LP": {"p_detect": 0.3}})  # a row of a type nobody registered (a misspelt row) is refused
    set_landmark_type_name("LP", True)  # what registering a type "LP" does for the loader (docs/extending.md)
    try:
        scn = load(merge_va=-1, p_detect_sp=0.4, types={"VA": {"merge": 4.0}, "LP": {"p_detect": 0.3}})
        resolved = scenario_from_resolved(scn.to_dict()).filter
    finally:
        set_landmark_type_name("LP", False)
    from mmslam.scenes.scenario import DEFAULT_TYPE_PARAMS

    builtin_va = DEFAULT_TYPE_PARAMS["VA"].threshold  # 0.5 since issue 22 (the paper's 0.7 is in paper.toml's row)
    assert scn.filter.types["VA"].merge == 4.0 and scn.filter.types["VA"].threshold == builtin_va == 0.5
    assert scn.filter.types["SP"].p_detect == 0.4 and scn.filter.types["LP"].p_detect == 0.3
    assert resolved == scn.filter
    assert load(merge_va=-1).filter.types["VA"].merge == 49.0  # paper.toml's row pins its gate
    data = tomllib.loads(text)
    del data["filter"]["types"]["VA"]["merge"]
    data["filter"]["merge_va"] = -1
    scn = scenario_from_dict(data, "test.toml")  # no row value: merge_va < 0 is filter.merge (not the VA default 9)
    assert scn.filter.types["VA"].merge == -1.0 and scn.filter.type_params("VA").merge_gate(scn.filter.merge) == 49.0
    with pytest.raises(ConfigError, match=r"filter.p_detect_va.*given twice \(also as filter.types.VA.p_detect\)"):
        load(p_detect_va=0.4, types={"VA": {"p_detect": 0.5}})
    with pytest.raises(ConfigError, match="filter.types.VA.bogus"):
        load(types={"VA": {"bogus": 1}})
    with pytest.raises(ConfigError, match="filter.types.VA.p_detect"):
        load(types={"VA": {"p_detect": 1.5}})


def test_type_registry_round_trip_and_errors():
    toy = dataclasses.replace(L.SP_SPEC, name="SPX", code=9)
    try:
        assert L.register_landmark_type(toy) is toy
        assert L.landmark_type("SPX") is toy and L.landmark_type(9) is toy
        assert 9 in L.known_codes() and 9 in L.range_gated_codes()
        with pytest.raises(MmslamError, match="already registered"):
            L.register_landmark_type(toy)
        with pytest.raises(MmslamError, match="code 9 is taken"):
            L.register_landmark_type(dataclasses.replace(toy, name="SPY"))
    finally:
        L.unregister_landmark_type("SPX")
    with pytest.raises(MmslamError, match="unknown landmark type"):
        L.landmark_type(9)
    with pytest.raises(MmslamError, match="code 4 is taken"):  # OTHER is clutter, never a type
        L.register_landmark_type(dataclasses.replace(toy, code=4))
    with pytest.raises(MmslamError, match="needs predict"):
        L.register_landmark_type(dataclasses.replace(toy, predict=None))
    with pytest.raises(MmslamError, match="built in"):
        L.unregister_landmark_type("VA")


# ---------------------------------------------------------------- variants
def test_variant_specs():
    assert V.variant_names() == ("odometry", "baseline", "cm1", "proposed")
    assert V.VARIANTS == ("baseline", "cm1", "proposed") and V.REFERENCES == ("odometry",)
    for name in V.variant_names():
        v = V.get_variant(name)
        assert all(t.mapped for t in v.types()) and v.label
    assert "VS" not in V.get_variant("baseline").map_types
    assert V.get_variant("cm1").map_types == ("VA", "SP", "VS")
    p = V.get_variant("proposed")
    assert p.ego_vs_average and p.predict_at_bs and p.vs_fusion and p.downlink_ego_removal
    c = V.get_variant("cm1")
    assert not (c.ego_vs_average or c.predict_at_bs or c.vs_fusion or c.downlink_ego_removal)
    assert not V.get_variant("odometry").measurement_update and V.get_variant("odometry").reference
    with pytest.raises(MmslamError, match="unknown variant 'x'.*odometry, baseline, cm1, proposed"):
        V.get_variant("x")
    with pytest.raises(MmslamError, match="unknown landmark type"):
        V.register_variant(V.VariantSpec("bad", "bad", ("VA", "XX")))
    with pytest.raises(MmslamError, match="not a map type"):
        V.register_variant(V.VariantSpec("bad", "bad", ("BS",)))
    assert "bad" not in V.variant_names()


def test_pipelines_read_the_variant_specs():
    from mmslam.pipelines import ablate, figures

    assert ablate.VARIANTS == V.variant_names() and ablate.FILTER_VARIANTS == V.VARIANTS
    assert ablate.TYPES == ("VA", "SP", "VS") and ablate.SCORED[:3] == ("gospa_VA", "gospa_SP", "gospa_VS")
    assert figures.VARIANT_LABEL["proposed"] == V.get_variant("proposed").label
    assert figures.TYPE_NAMES["VS"] == L.VS_SPEC.description


# ---------------------------------------------------------------- sources
def test_source_registry_round_trip():
    from mmslam.raytrace import trace as T

    scn = load_preset("paper")
    assert tuple(T.SOURCES) == ("sionna", "analytic")
    made = []

    def factory(s, **kw):
        made.append(kw)
        return AnalyticSource(s)

    T.register_source("toy_src", factory)
    try:
        assert "toy_src" in T.SOURCES
        src = T.make_source("toy_src", scn, max_depth=2, samples=5, seed=3)
        assert isinstance(src, AnalyticSource) and made == [{"max_depth": 2, "samples": 5, "seed": 3}]
        with pytest.raises(ConfigError, match="already registered"):
            T.register_source("toy_src", factory)
    finally:
        T.unregister_source("toy_src")
    with pytest.raises(ConfigError, match="unknown source 'toy_src'; expected one of sionna, analytic"):
        T.make_source("toy_src", scn)


# ---------------------------------------------------------------- run loop
def test_particles_default_is_the_scenarios_filter_particles(paper12):
    scn, states, paths = paper12
    scn7 = with_overrides(scn, ["filter.particles=7"])
    a = run_filter(scn7, states, paths, variant="cm1", seed=2, steps=5)
    b = run_filter(scn, states, paths, variant="cm1", particles=7, seed=2, steps=5)
    assert a.meta["particles"] == 7
    np.testing.assert_array_equal(a.vehicles["pos_err"], b.vehicles["pos_err"])
    with pytest.raises(MmslamError, match="particles=0"):
        run_filter(scn, states, paths, particles=0, steps=2)


def test_step_api_stages_reproduce_run_filter(paper12):
    """Driving CooperativeRun stage by stage (as the benchmark does) is run_filter."""
    scn, states, paths = paper12
    ref = run_filter(scn, states, paths, variant="proposed", particles=15, seed=4, steps=10)
    run = CooperativeRun(scn, states, paths, "proposed", 15, 4, 10)
    uploads = 0
    for k in range(run.steps):
        run.predict_at_bs(k)
        for n in range(run.n_veh):
            est = run.local_step(k, n)
            run.record_vehicle(k, n, est)
            uploads += run.upload(k, n, est)
        run.record_fused(k)
    res = run.result()
    assert uploads == sum(len(s) for s in run.schedule) > 0
    for tab in ("vehicles", "metrics", "landmarks"):
        a, b = getattr(ref, tab), getattr(res, tab)
        for c in a:
            np.testing.assert_array_equal(np.asarray(a[c]), np.asarray(b[c]), err_msg=f"{tab}.{c}")


def test_unevaluated_run_has_the_same_filter_results(paper12):
    scn, states, paths = paper12
    a = CooperativeRun(scn, states, paths, "cm1", 10, 1, 6).run()
    b = CooperativeRun(scn, states, paths, "cm1", 10, 1, 6, evaluate=False).run()
    np.testing.assert_array_equal(a.vehicles["pos_err"], b.vehicles["pos_err"])
    assert len(b.metrics["step"]) == 0 and len(a.metrics["step"]) == 6 * 3 * 3


def test_constant_sensor_model_corrects_with_the_shared_r(paper12):
    """With sensor.model = constant every measurement's covariance is R: the run hands the filter no
    per-measurement R_z (the batched shared-R correction); forcing the J copies of R gives the same
    run to 1e-9 (it only costs more)."""
    scn, states, paths = paper12
    run = CooperativeRun(scn, states, paths, "proposed", 12, 5, 8, evaluate=False)
    forced = CooperativeRun(scn, states, paths, "proposed", 12, 5, 8, evaluate=False)
    for k in range(8):
        run.predict_at_bs(k)
        forced.predict_at_bs(k)
        for n in range(run.n_veh):
            Z, spd, tr, R_z = run.local_inputs(k, n)
            assert R_z is None
            sel = np.asarray(forced.meas.mask[k, n], bool)
            R_j = scn.filter.r_scale * np.einsum("ja,ab->jab", forced.meas.R_meas[k, n][sel], np.eye(5))
            np.testing.assert_allclose(R_j, np.broadcast_to(run.filters[n].R, R_j.shape), rtol=1e-12)
            a = run.filters[n].step(Z, spd, tr, None)
            b = forced.filters[n].step(Z, spd, tr, R_j)
            np.testing.assert_allclose(a.mean, b.mean, rtol=1e-9)
            run.upload(k, n, a)
            forced.upload(k, n, b)


def test_report_lists_each_variants_label_and_what_it_runs():
    from mmslam.pipelines.report import _variants_html

    out = _variants_html(["baseline", "proposed", "gone"])
    assert out.startswith('<table id="variants">') and out.count("<tr data-variant=") == 3
    assert "baseline (TWC2020)" in out and "maps VA, SP; AA fusion of every map (eq. 8)" in out
    assert "countermeasures: ego-VS averaging (eq. 11), prediction at the BS (eq. 15)" in out
    assert "not registered" in out  # an old ablation's variant from a plugin not loaded now
    assert V.get_variant("odometry").describe().startswith("dead reckoning")


def test_variants_choose_the_vs_fusion_operator_when_the_fusion_centre_is_built():
    """cm1 fuses the VS map with F_AA, a variant with vs_fusion with eqs. 16-20; ego averaging (eq. 11)
    wraps either; the fusion centre holds the chosen operator per type (no flag read at fuse time)."""
    from mmslam.slam.filter.fusion_center import FusionCenter

    vs = L.landmark_type("VS")
    assert vs.fusion_operator(V.get_variant("cm1")) is L.fuse_aa
    assert L.vs_fusion_operator(V.VariantSpec("t", "t", ("VS",), vs_fusion=True)) is L.fuse_vs
    assert L.landmark_type("VA").fusion_operator(V.get_variant("proposed")) is L.fuse_aa
    scn = load_preset("paper")
    fc = FusionCenter(scn, "proposed")
    op = fc.operators[vs.code]
    assert op not in (L.fuse_aa, L.fuse_vs)  # the ego-averaging wrapper
    # the wrapper is fuse_vs of the ego-averaged upload
    from mmslam.slam.core.gm import GM

    bs_map = GM(np.array([0.2]), np.array([[60.0, 5.0, 1.0, 3.0, 0.0, 0.0, 0.0]]), np.eye(7)[None], np.array([True]))
    up = GM(np.array([0.9]), np.array([[61.0, 5.0, 1.0, 3.0, 0.0, 0.0, 0.0]]), np.eye(7)[None], np.array([True]))
    ego = np.array([10.0, 0.0, 1.5, 0.0, 8.0, 0.0, 0.0])
    ctx = L.FusionInput(scn, V.get_variant("proposed"), ego, np.eye(7) * 0.1, 0)
    inside = np.array([True])
    got, pairs = op(bs_map, up, inside, ctx)
    ref, ref_pairs = L.fuse_vs(bs_map, L.ego_averaged(up, ctx), inside, ctx)
    np.testing.assert_array_equal(got.w, ref.w)
    np.testing.assert_array_equal(got.m, ref.m)
    np.testing.assert_array_equal(pairs, ref_pairs)
    assert L.ego_averaged(up, ctx).capacity == up.capacity + 1  # the ego Gaussian joined the upload
