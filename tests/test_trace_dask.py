"""`mmslam trace --executor dask`: chunks of steps traced on a Dask LocalCluster into the same cache."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.cache import load_cache, read_manifest
from mmslam.raytrace.trace import DaskExecutor, make_source, trace_scenario
from mmslam.scenes.scenario import load_preset

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None)
    c = distributed.Client(cluster, set_as_default=False)
    yield c
    c.close()
    cluster.close()



def _equal(a: dict, b: dict) -> None:
    assert set(a) == set(b)
    for k in a:
        x, y = np.asarray(a[k]), np.asarray(b[k])
        if x.dtype.kind == "f":
            np.testing.assert_array_equal(x, y)
        else:
            assert x.tolist() == y.tolist(), k


def test_dask_trace_equals_local_trace_table_for_table(tmp_path, client):
    spec = {"name": "analytic", "max_depth": 1, "samples": 1, "seed": 0}
    scn = load_preset("street")
    local = trace_scenario(scn, make_source("analytic", scn), tmp_path / "local", steps=17, chunk_steps=4,
                           progress=False)
    dask = trace_scenario(scn, make_source("analytic", scn), tmp_path / "dask", steps=17, chunk_steps=4,
                          progress=False, executor=DaskExecutor(spec, client=client))
    ml, md = read_manifest(local), read_manifest(dask)
    assert md["steps_completed"] == ml["steps_completed"] == 17
    assert [c["sha256"] for c in md["chunks"]] == [c["sha256"] for c in ml["chunks"]]  # byte-identical Parquet
    _equal(load_cache(local).paths, load_cache(dask).paths)


def test_dask_trace_resumes_a_partial_cache(tmp_path, client):
    spec = {"name": "analytic", "max_depth": 1, "samples": 1, "seed": 0}
    scn = load_preset("paper")
    full = trace_scenario(scn, make_source("analytic", scn), tmp_path / "full", steps=20, progress=False)
    part = trace_scenario(scn, make_source("analytic", scn), tmp_path / "part", steps=7, progress=False)
    again = trace_scenario(scn, make_source("analytic", scn), tmp_path / "part", steps=20, progress=False,
                           executor=DaskExecutor(spec, client=client))
    assert again == part and read_manifest(again)["steps_completed"] == 20
    assert read_manifest(again)["chunks"][0]["step_stop"] == 5  # the first chunks were kept, not retraced
    a, f = load_cache(again), load_cache(full)
    _equal(a.paths, f.paths)
    _equal(a.vehicles, f.vehicles)


@pytest.mark.slow
def test_dask_sionna_trace_on_two_worker_processes_equals_local(tmp_path):
    """Sionna on a LocalCluster of 2 processes (each builds its own source): the same tables as a local trace."""
    spec = {"name": "sionna", "max_depth": 1, "samples": 10**5, "seed": 0}
    scn = load_preset("paper")
    local = trace_scenario(scn, make_source("sionna", scn, samples=10**5), tmp_path / "local", steps=6,
                           chunk_steps=2, progress=False)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
            distributed.Client(cl, set_as_default=False) as c:
        dask = trace_scenario(scn, make_source("sionna", scn, samples=10**5), tmp_path / "dask", steps=6,
                              chunk_steps=2, progress=False, executor=DaskExecutor(spec, client=c))
    _equal(load_cache(local).paths, load_cache(dask).paths)
