"""Schema version 3 (issue 26, item 6): the transmitter (BS) position as columns ``tx_x, tx_y, tx_z`` of
``rays`` and ``paths``, equal to the scenario's BS on every row; version-2 caches still load (the columns
filled from the manifest's BS, the files untouched) and grow in version 2; a wrong tx value, a newer or
unknown version, or a manifest that claims 3 over version-2 files is refused in one line."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from mmslam.cli import main
from mmslam.errors import CacheError
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.raytrace.cache import MANIFEST, config_hash, file_metadata, load_cache, write_chunk, write_manifest
from mmslam.raytrace.schema import (PATH_COLUMNS, RAY_COLUMNS, SCHEMA_VERSION, TX_POSITION_COLUMNS, table_columns)
from mmslam.raytrace.trace import make_source, trace_scenario
from mmslam.scenes.scenario import load_preset

V2_ROOT = Path(__file__).resolve().parent / "fixtures" / "cache_v2"
"""A version-2 cache written by main's code before version 3 (commit 1b6f414): ``paper``, analytic
source, 3 steps in 2 chunks (``trace_scenario(load_preset("paper"), AnalyticSource(...), root,
steps=3, chunk_steps=2)``)."""
V2 = next(V2_ROOT.iterdir())
BS = (1.5, -2.25, 38.0)  # paper's BS moved off the axes: a tx_x / tx_y of 0 would pass by chance


def _tx(cols: dict) -> np.ndarray:
    return np.stack([cols[c] for c in TX_POSITION_COLUMNS], axis=1)


FRESH_RTOL = 1e-14
"""Stored files against a fresh trace made on this machine: floats to 1e-14 relative (measured: 2e-16 at most), the rest exactly. The
analytic source's angles come from NumPy's SIMD arctan2 / arcsin, which may differ by an ulp between NumPy builds
and CPUs (the fixture was written on another machine); a real change moves them by far more."""


def _same_as_fresh(got: np.ndarray, want: np.ndarray, name: str) -> None:
    got, want = np.asarray(got), np.asarray(want)
    if want.dtype.kind == "f":
        np.testing.assert_allclose(got, want, rtol=FRESH_RTOL, atol=0.0, err_msg=name)
    else:
        np.testing.assert_array_equal(got, want, err_msg=name)


def _files_state(d: Path) -> dict[str, tuple[str, int]]:
    return {p.relative_to(d).as_posix(): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    scn = dataclasses.replace(load_preset("paper"), bs=BS)
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path_factory.mktemp("tx"), steps=5, chunk_steps=2,
                       progress=False)
    return scn, d


def test_tx_columns_are_the_bs_on_every_row_of_each_table(moved):
    pd = pytest.importorskip("pandas")
    scn, d = moved
    assert SCHEMA_VERSION == 3 and json.loads((d / MANIFEST).read_text())["schema_version"] == 3
    # what a user reading the files with pandas alone finds
    for table in ("paths", "rays"):
        df = pd.read_parquet(d / table)
        assert list(df.columns) == list(PATH_COLUMNS if table == "paths" else RAY_COLUMNS)
        assert len(df) > 20 and set(df["type"].astype(str)) >= {"BS", "VA", "SP", "VS"}
        np.testing.assert_array_equal(df[list(TX_POSITION_COLUMNS)].to_numpy(), np.tile(BS, (len(df), 1)))
        f = sorted((d / table).glob("*.parquet"))[0]
        field = pq.read_schema(f).field("tx_y")
        assert field.metadata[b"unit"] == b"m" and b"BS" in field.metadata[b"doc"]
        assert json.loads(pq.read_schema(f).metadata[b"mmslam"])["schema_version"] == 3
    c = load_cache(d)
    np.testing.assert_array_equal(_tx(c.paths), np.tile(BS, (len(c.paths["rx"]), 1)))
    np.testing.assert_array_equal(_tx(c.read_rays()), np.tile(BS, (len(c.read_rays()["rx"]), 1)))
    # the LOS rows' landmark is the BS: the two ways of reading it agree
    los = c.paths["type"] == 0
    np.testing.assert_array_equal(np.c_[c.paths["lm_x"], c.paths["lm_y"], c.paths["lm_z"]][los], _tx(c.paths)[los])


def test_mesh_analytic_source_writes_the_bs_too():
    base = load_preset("paper")
    veh = dataclasses.replace(base.vehicles[0], name="car", initial_state=(1.2, -0.5, 1.2, 0.0, 0.0, 0.0, 0.0),
                              length=0.5, width=0.5, height=0.5)
    scn = dataclasses.replace(base, xml_scene="sionna:floor_wall", buildings=(), scatterers=(), vehicles=(veh,),
                              bs=(1.5, 0.0, 2.0))
    src = make_source("analytic", scn)
    assert type(src).__name__ == "MeshAnalyticSource"
    t = src.trace_tables(0, np.array([scn.vehicles[0].initial_state]))
    assert any(i.startswith("plane(") for i in t["paths"]["landmark_id"])  # a row of the XML-plane branch
    for table in ("paths", "rays"):
        n = len(t[table]["rx"])
        assert n >= 2
        np.testing.assert_array_equal(_tx(t[table]), np.tile([1.5, 0.0, 2.0], (n, 1)))


def test_version_2_cache_loads_with_the_bs_columns_filled_and_files_untouched(tmp_path):
    m = json.loads((V2 / MANIFEST).read_text())
    assert m["schema_version"] == 2 and m["steps_completed"] == 3 and len(m["chunks"]) == 2
    assert pq.read_schema(V2 / "paths" / "part-00000.parquet").names == table_columns("paths", 2)
    assert "tx_x" not in table_columns("paths", 2) and "tx_x" not in table_columns("rays", 2)
    before = _files_state(V2)
    c = load_cache(V2)
    rays = c.read_rays()
    assert _files_state(V2) == before  # read only
    assert c.manifest["schema_version"] == 2 and list(c.paths) == list(PATH_COLUMNS) and list(rays) == list(RAY_COLUMNS)
    bs = tuple(m["resolved_scenario"]["bs"])
    assert bs == (0.0, 0.0, 40.0)
    np.testing.assert_array_equal(_tx(c.paths), np.tile(bs, (len(c.paths["rx"]), 1)))
    np.testing.assert_array_equal(_tx(rays), np.tile(bs, (len(rays["rx"]), 1)))
    # every other column as the files hold it (read here with pyarrow alone, labels decoded)
    raw = pq.ParquetDataset(V2 / "paths").read().to_pandas()
    assert len(raw) == len(c.paths["rx"]) == 38
    order = np.lexsort((raw["landmark_id"].to_numpy().astype(str), raw["type"].cat.codes, raw["rx"].cat.codes,
                        raw["step"]))
    for k in table_columns("paths", 2):
        want = raw[k].to_numpy()[order]
        if k in ("rx", "type"):
            labels = {"rx": c.vehicle_names, "type": ["BS", "VA", "SP", "VS", "OTHER"]}[k]
            assert [labels[i] for i in c.paths[k]] == want.astype(str).tolist(), k
        else:
            np.testing.assert_array_equal(c.paths[k], want, err_msg=k)
    # and equal, column by column (tx included), to what this mmslam traces for the same configuration
    scn = load_preset("paper")
    assert m["config_hash"] == config_hash(scn, "analytic", AnalyticSource(scn).settings())
    fresh = load_cache(trace_scenario(scn, AnalyticSource(scn), tmp_path, steps=3, chunk_steps=2, progress=False))
    for got, want in ((c.paths, fresh.paths), (rays, fresh.read_rays()), (c.vehicles, fresh.vehicles)):
        assert list(got) == list(want)
        for k in want:
            _same_as_fresh(got[k], want[k], k)
    _same_as_fresh(c.states, fresh.states, "states")
    # the CLI reads it too
    assert main(["paths", str(V2)]) == 0


def test_a_version_2_cache_is_extended_in_version_2(tmp_path):
    root = tmp_path / "root"
    shutil.copytree(V2_ROOT, root)
    d = root / V2.name
    old = _files_state(d)
    scn = load_preset("paper")
    assert trace_scenario(scn, AnalyticSource(scn), root, steps=6, chunk_steps=2, progress=False) == d
    m = json.loads((d / MANIFEST).read_text())
    assert m["schema_version"] == 2 and m["steps_completed"] == 6 and len(m["chunks"]) == 4
    now = _files_state(d)
    assert all(now[f] == old[f] for f in old if f != MANIFEST)  # the old chunks are untouched
    for table in ("paths", "rays"):
        for f in sorted((d / table).glob("*.parquet")):
            assert pq.read_schema(f).names == table_columns(table, 2), f
            assert json.loads(pq.read_schema(f).metadata[b"mmslam"])["schema_version"] == 2
    got = load_cache(d)
    ref = load_cache(trace_scenario(scn, AnalyticSource(scn), tmp_path / "ref", steps=6, chunk_steps=2,
                                    progress=False))
    assert ref.manifest["schema_version"] == 3
    for k in PATH_COLUMNS:
        _same_as_fresh(got.paths[k], ref.paths[k], k)
    for k in RAY_COLUMNS:
        _same_as_fresh(got.read_rays()[k], ref.read_rays()[k], k)


def _rewrite_chunk(d: Path, idx: int, table: str, mutate) -> None:
    """Rewrite chunk ``idx`` with ``mutate`` applied to its ``table`` columns (a valid sha: a hand edit)."""
    c = load_cache(d)
    m = c.manifest
    ch = m["chunks"][idx]
    tables = {"vehicles": c.vehicles, "rays": c.read_rays(), "paths": c.paths}
    tables = {t: {k: v[(cols["step"] >= ch["step_start"]) & (cols["step"] < ch["step_stop"])].copy()
                  for k, v in cols.items()} for t, cols in tables.items()}
    mutate(tables[table])
    m["chunks"][idx] = write_chunk(d, idx, ch["step_start"], tables, file_metadata(m))
    write_manifest(d, m)


@pytest.mark.parametrize("table", ["paths", "rays"])
def test_a_wrong_tx_value_is_a_one_line_error_naming_the_file(tmp_path, table, capsys):
    scn = load_preset("paper")
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path, steps=4, chunk_steps=2, progress=False)

    def shift(cols):
        cols["tx_z"][np.flatnonzero(cols["step"] == 3)[1]] += 1e-6

    _rewrite_chunk(d, 1, table, shift)
    with pytest.raises(CacheError) as e:
        c = load_cache(d)
        c.read_rays()
    msg = str(e.value)
    assert f"{table}/part-00001.parquet: column 'tx_z' is 40.00000" in msg and "at step 3 (rx " in msg
    assert "expected the BS position 40.0 m" in msg and "--force" in msg and "\n" not in msg
    capsys.readouterr()
    if table == "paths":
        assert main(["paths", str(d)]) == 2
    else:  # the rays are read by the exporter
        assert main(["export", str(d), "--cfr", "--subcarriers", "4", "--out", str(tmp_path / "h.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "tx_z" in err and not (tmp_path / "h.npz").exists()


def test_a_source_writing_another_tx_is_refused_before_writing(tmp_path):
    scn = load_preset("paper")

    class Wrong(AnalyticSource):
        def trace_tables(self, step, states):
            t = super().trace_tables(step, states)
            if step == 2:
                t["rays"]["tx_x"] = t["rays"]["tx_x"] + 0.5
            return t

    with pytest.raises(CacheError, match=r"source 'analytic' output: column 'tx_x' is 0.5 at step 2 .*fix the source"):
        trace_scenario(scn, Wrong(scn), tmp_path, steps=4, chunk_steps=2, progress=False)
    assert load_cache(tmp_path).steps == 2  # the good chunk is kept


def test_newer_unknown_and_mislabelled_versions_are_refused_in_one_line(tmp_path):
    d = tmp_path / V2.name
    shutil.copytree(V2, d)
    m = json.loads((d / MANIFEST).read_text())
    for v, what in ((4, r"schema_version 4 \(written by a newer mmslam\), this mmslam reads 2 and 3; upgrade mmslam"),
                    (1, r"schema_version 1 \(an older cache"), ("2", "schema_version '2', this mmslam reads 2 and 3"),
                    (2.0, "schema_version 2.0, this"), (None, "schema_version None, this")):
        write_manifest(d, {**m, "schema_version": v})
        with pytest.raises(CacheError, match=what) as e:
            load_cache(d)
        assert "\n" not in str(e.value) and "--force" in str(e.value)
    # version-2 files under a manifest that claims 3: never read as version 3 with columns missing
    write_manifest(d, {**m, "schema_version": 3})
    with pytest.raises(CacheError, match=r"paths/part-00000\.parquet: columns \[.*\] differ from those of schema "
                                         r"version 3 \[.*'tx_x'") as e:
        load_cache(d)
    assert "\n" not in str(e.value)
    write_manifest(d, m)
    assert load_cache(d).steps == 3
