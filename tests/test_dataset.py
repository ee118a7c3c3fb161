"""The cache as a dataset (issue 11): self-describing tables readable in one call by pandas,
pyarrow and duckdb; rays <-> paths link; old caches refused in one line; `mmslam export`."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from mmslam.cli import main
from mmslam.errors import CacheError
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.raytrace.cache import MANIFEST, load_cache, write_manifest
from mmslam.raytrace.channel import channel_response, subcarrier_frequencies
from mmslam.raytrace.schema import RAY_COLUMNS, RAY_SPEC, TYPE_LABELS
from mmslam.raytrace.trace import trace_scenario
from mmslam.scenes.scenario import load_preset, scenario_from_dict

C = 299_792_458.0


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    scn = load_preset("paper")
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path_factory.mktemp("ds"), steps=7, chunk_steps=3,
                       progress=False)
    return scn, d


def test_pandas_reads_each_table_in_one_call_with_labels(cache):
    pd = pytest.importorskip("pandas")
    scn, d = cache
    c = load_cache(d)
    rays = pd.read_parquet(d / "rays")
    paths = pd.read_parquet(d / "paths")
    veh = pd.read_parquet(d / "vehicles")
    assert list(rays.columns) == list(RAY_COLUMNS) and len(rays) == len(c.read_rays()["rx"])
    assert len(paths) == len(c.paths["rx"]) and len(veh) == 14
    assert set(rays["type"].astype(str)) <= set(TYPE_LABELS) and "BS" in set(rays["type"].astype(str))
    assert set(rays["rx"].astype(str)) == {"veh1", "veh2"} and set(veh["vehicle"].astype(str)) == {"veh1", "veh2"}
    assert set(rays["bounce1_type"].astype(str)) == {"none", "specular", "diffuse"}
    # paths -> rays link: the strongest ray of each row, same delay and power
    j = paths.merge(rays, on=["step", "rx", "ray"], suffixes=("", "_ray"))
    assert len(j) == len(paths)
    np.testing.assert_allclose(j["toa_m"], j["delay_s"] * C, rtol=1e-12)
    assert (j["landmark_id"] == j["landmark_id_ray"]).all()
    np.testing.assert_allclose(veh["vx"], veh["speed"] * np.cos(veh["heading"]))


def test_units_docs_and_settings_in_the_arrow_schema(cache):
    scn, d = cache
    sch = ds.dataset(d / "rays", format="parquet").schema
    assert sch.field("delay_s").metadata[b"unit"] == b"s"
    assert sch.field("doppler_hz").metadata[b"unit"] == b"Hz"
    assert sch.field("aoa_az").metadata[b"unit"] == b"rad" and b"heading" in sch.field("aoa_az").metadata[b"doc"]
    assert str(sch.field("type").type).startswith("dictionary<values=string")
    for k, col in RAY_SPEC.items():
        assert sch.field(k).metadata[b"doc"].decode() == col.doc
    f = sorted((d / "paths").glob("*.parquet"))[0]
    meta = json.loads(pq.read_schema(f).metadata[b"mmslam"])
    assert meta["table"] == "paths" and meta["schema_version"] == 3 and meta["source"] == "analytic"
    assert meta["scenario"] == "paper" and meta["vehicle_names"] == ["veh1", "veh2"]
    assert meta["settings"]["model_version"] == 2 and meta["resolved_scenario"]["bs"] == list(scn.bs)
    assert "x east" in meta["frame"]


def test_duckdb_reads_each_table_in_one_call(cache):
    duckdb = pytest.importorskip("duckdb")
    _, d = cache
    con = duckdb.connect()
    rows = con.execute(f"SELECT type, count(*) FROM read_parquet('{d}/rays/*.parquet') GROUP BY type "
                       "ORDER BY type").fetchall()
    assert {r[0] for r in rows} == {"BS", "VA", "SP", "VS"}
    n_los = con.execute(f"SELECT count(*) FROM read_parquet('{d}/paths/*.parquet') WHERE type = 'BS'").fetchone()[0]
    assert n_los == 7 * 2
    # a join through the link, in SQL
    j = con.execute(f"SELECT count(*) FROM read_parquet('{d}/paths/*.parquet') p JOIN "
                    f"read_parquet('{d}/rays/*.parquet') r USING (step, rx, ray)").fetchone()[0]
    assert j == len(load_cache(d).paths["rx"])


def test_rays_roundtrip_through_the_cache(cache):
    scn, d = cache
    c = load_cache(d)
    src = AnalyticSource(scn)
    got = c.read_rays()
    want = [src.trace_tables(k, c.states[k])["rays"] for k in range(7)]
    for k, t in RAY_COLUMNS.items():
        exp = np.concatenate([w[k] for w in want])
        assert got[k].dtype == (object if t == "string" else np.dtype(t)), k
        np.testing.assert_array_equal(got[k], exp, err_msg=k)


def test_old_schema_cache_is_a_one_line_error(tmp_path, capsys):
    scn = load_preset("paper")
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path, steps=2, progress=False)
    m = json.loads((d / MANIFEST).read_text())
    write_manifest(d, {**m, "schema_version": 1})
    with pytest.raises(CacheError, match=r"schema_version 1 \(an older cache.*--force") as e:
        load_cache(d)
    assert "\n" not in str(e.value)
    capsys.readouterr()
    assert main(["paths", str(d)]) == 2
    assert main(["trace", "paper", "--source", "analytic", "--out", str(tmp_path), "--steps", "2", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("schema_version 1" in e and "--force" in e for e in err)


def _two_ray_scenario():
    """BS [0, 0, 10], one wall x = 20; a receiver at [5, 0, 10] moving -x: LOS (5 m) + VA (35 m).

    dt = 0.25 s: at step 1 the receiver is 2.5 m from the BS (with 0.5 s it would sit on the BS,
    a degenerate link that the trace refuses)."""
    return scenario_from_dict({
        "name": "tworay", "bs": [0.0, 0.0, 10.0], "dt": 0.25, "steps": 2,
        "buildings": [{"name": "w", "min": [20.0, -5.0, 0.0], "max": [25.0, 5.0, 20.0]}],
        "vehicles": [{"name": "car0", "initial_state": [5.0, 0.0, 10.0, np.pi, 10.0, 0.0, 0.0]}],
        "sensor": {"fov_range": 1.0},
    })


def test_export_cfr_and_cir_hand_computed(tmp_path, capsys):
    scn = _two_ray_scenario()
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path / "c", progress=False)
    c = load_cache(d)
    r = c.read_rays()
    s0 = r["step"] == 0
    assert s0.sum() == 2  # LOS + the wall
    a = (r["a_re"] + 1j * r["a_im"])[s0]
    tau = r["delay_s"][s0] - r["delay_s"][s0].min()
    assert tau[0] == 0.0 and tau[1] == pytest.approx(30.0 / C)
    fc = scn.frequency_hz
    W, N = 100e6, 16
    f = (np.arange(N) - N // 2) * W / N
    want = (a[:, None] * np.exp(-2j * np.pi * (fc + f)[None, :] * tau[:, None])).sum(0)
    out = tmp_path / "h.npz"
    capsys.readouterr()
    assert main(["export", str(d), "--cfr", "--bandwidth", str(W), "--subcarriers", str(N), "--out", str(out)]) == 0
    z = np.load(out)
    assert z["h"].shape == (2, 1, 1, N) and z["h"].dtype == np.complex64
    np.testing.assert_allclose(z["axis"], f)
    np.testing.assert_allclose(z["h"][0, 0, 0], want, rtol=1e-5, atol=1e-6 * np.abs(want).max())
    assert json.loads(str(z["meta"]))["bandwidth_hz"] == W and list(z["rx_names"]) == ["car0"]
    assert json.loads(str(z["meta"]))["tx_position_m"] == [0.0, 0.0, 10.0]  # the BS
    # CIR taps: tap l = sum_i a_i^b sinc(l - W tau_i); 30 m = 10.007 taps at 100 MHz
    h, ax, _, _ = channel_response(r, kind="cir", carrier_hz=fc, bandwidth_hz=W, n_subcarriers=N, n_rx=1)
    ab = a * np.exp(-2j * np.pi * fc * tau)
    np.testing.assert_allclose(h[0, 0, 0], (ab[:, None] * np.sinc(ax[None, :] - W * tau[:, None])).sum(0))
    assert np.argmax(np.abs(h[0, 0, 0][5:])) + 5 == 10  # the echo's tap
    # Doppler evolution: a single LOS ray turns at +10/lambda Hz
    h_t, _, t, _ = channel_response({k: v[s0][:1] for k, v in r.items()}, kind="cfr", carrier_hz=fc,
                                    bandwidth_hz=W, n_subcarriers=4, n_rx=1, num_time_steps=3,
                                    sampling_frequency_hz=1e4)
    lam = C / fc
    np.testing.assert_allclose(h_t[0, 0, :, 0], a[0] * np.exp(2j * np.pi * (10 / lam) * t))
    # output safety (issue 25): an earlier export is replaced; a user's file never, even with --force;
    # both/neither flag refused
    assert main(["export", str(d), "--cir", "--out", str(out)]) == 0
    assert np.load(out)["h"].shape == (2, 1, 1, 1024)
    user = tmp_path / "user.npz"
    np.savez(user, h=np.zeros(3))
    before = user.read_bytes()
    for force in ([], ["--force"]):
        capsys.readouterr()
        assert main(["export", str(d), "--cir", "--out", str(user), *force]) == 2
        assert "did not write" in capsys.readouterr().err
        assert user.read_bytes() == before
    assert main(["export", str(d), "--cir", "--cfr", "--out", str(tmp_path / "x.npz")]) == 2
    assert main(["export", str(d), "--out", str(tmp_path / "x.npz")]) == 2
    assert main(["export", str(d), "--cfr", "--bandwidth", "-1", "--out", str(tmp_path / "x.npz")]) == 2
    assert not (tmp_path / "x.npz").exists()


def test_subcarrier_frequencies_like_sionna():
    np.testing.assert_allclose(subcarrier_frequencies(4, 1.0), [-2, -1, 0, 1])
    np.testing.assert_allclose(subcarrier_frequencies(5, 2.0), [-4, -2, 0, 2, 4])


def test_docs_list_every_column_with_its_unit():
    from mmslam.raytrace.schema import schema_markdown

    doc = (Path(__file__).parents[1] / "docs" / "dataset.md").read_text()
    for line in schema_markdown().splitlines():
        assert line in doc, line


def test_rays_columns_fill_every_bounce_slot_and_refuse_too_many():
    from mmslam.raytrace.schema import rays_columns

    it = np.array([[1, 2, 0], [0, 0, 0]])
    obj = np.array([["w", "s", ""], ["", "", ""]], dtype=object)
    v = np.arange(18, dtype=float).reshape(2, 3, 3)
    r = rays_columns(step=3, rx=np.array([1, 0]), typ=np.array([4, 0]), landmark_id=np.array(["w+s", "bs"], object),
                     a=np.array([1e-6 + 1e-6j, 2e-5]), delay_s=np.array([2e-7, 1e-7]), angles=np.zeros((2, 4)),
                     doppler_hz=np.array([5.0, -1.0]), itype=it, objects=obj, verts=v, ray=np.array([0, 0]),
                     tx_pos=(1.0, -2.0, 30.0))
    # sorted by (rx, ray): the LOS ray of rx 0 first
    assert r["rx"].tolist() == [0, 1] and r["bounces"].tolist() == [0, 2]
    assert r["bounce1_object"].tolist() == ["", "w"] and r["bounce2_object"].tolist() == ["", "s"]
    assert r["bounce2_type"].tolist() == [0, 2] and r["bounce3_type"].tolist() == [0, 0]
    assert r["bounce2_x"][1] == 3.0 and np.isnan(r["bounce2_x"][0]) and np.isnan(r["bounce3_z"]).all()
    assert r["power_db"][0] == pytest.approx(20 * np.log10(2e-5))
    assert r["tx_x"].tolist() == [1.0, 1.0] and r["tx_y"].tolist() == [-2.0, -2.0] and r["tx_z"].tolist() == [30.0, 30.0]
    assert r["power_db"][1] == pytest.approx(20 * np.log10(np.sqrt(2) * 1e-6))
    with pytest.raises(ValueError, match="4 interaction slots"):
        rays_columns(step=0, rx=np.array([0]), typ=np.array([4]), landmark_id=np.array(["x"], object),
                     a=np.array([1.0]), delay_s=np.array([1.0]), angles=np.zeros((1, 4)), doppler_hz=np.zeros(1),
                     itype=np.ones((1, 4)), objects=np.full((1, 4), "o", object), verts=np.zeros((1, 4, 3)),
                     ray=np.zeros(1), tx_pos=np.zeros(3))


def test_export_steps_rx_and_sampling_frequency_select_from_the_full_export(cache, tmp_path, capsys):
    cache = cache[1]
    """``--steps a:b,c`` / ``--rx name`` give exactly those rows of the full export; ``--sampling-frequency``
    sets the sample times t = n / fs (default 1 / bandwidth); bad values: one line, exit 2."""
    c = load_cache(cache)
    full, part = tmp_path / "full.npz", tmp_path / "part.npz"
    base = ["export", str(cache), "--cfr", "--subcarriers", "32", "--time-steps", "3"]
    assert main(base + ["--out", str(full)]) == 0
    name = c.vehicle_names[-1]
    assert main(base + ["--steps", "1:3,4", "--rx", name, "--sampling-frequency", "2000", "--out", str(part)]) == 0
    f, p = np.load(full), np.load(part)
    assert p["steps"].tolist() == [1, 2, 4] and p["rx_names"].tolist() == [name]
    np.testing.assert_allclose(f["times_s"], np.arange(3) / 400e6)
    np.testing.assert_allclose(p["times_s"], np.arange(3) / 2000.0)
    np.testing.assert_array_equal(p["h"][:, 0, 0], f["h"][[1, 2, 4], len(c.vehicle_names) - 1, 0])  # t = 0
    assert json.loads(str(p["meta"]))["sampling_frequency_hz"] == 2000.0
    capsys.readouterr()
    for bad in (["--steps", "0:999"], ["--steps", "x"], ["--rx", "nobody"], ["--sampling-frequency", "0"]):
        assert main(base + bad + ["--out", str(tmp_path / "bad.npz")]) == 2, bad
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and bad[0] in err
    assert not (tmp_path / "bad.npz").exists()


def test_every_file_carries_the_software_versions_of_the_run_that_wrote_it(cache):
    import mmslam

    _, d = cache
    m = json.loads((d / MANIFEST).read_text())
    files = sorted(d.glob("*/*.parquet"))
    assert len(files) == 3 * len(m["chunks"])
    for f in files:
        meta = json.loads(pq.read_schema(f).metadata[b"mmslam"])
        v = meta["versions"]
        assert v["mmslam"] == mmslam.__version__ and v["numpy"] == np.__version__ and v["python"]
        assert v == m["chunks"][0]["versions"]
