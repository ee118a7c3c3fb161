"""Path cache: layout, resume after interruption, extension, validation errors (docs/design.md section 7)."""
from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from mmslam.cli import main
from mmslam.errors import CacheError, MmslamError
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.raytrace.cache import (
    MANIFEST, cache_dir_for, file_metadata, load_cache, vehicle_columns, write_chunk, write_manifest,
)
from mmslam.raytrace.schema import PATH_COLUMNS, SCHEMA_VERSION, VEHICLE_COLUMNS
from mmslam.raytrace.trace import make_source, trace_scenario
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import true_trajectories, vehicle_trajectories
from mmslam.slam.models.measurement import BS, VA


@pytest.fixture(scope="module")
def paper():
    return load_preset("paper")


class FailingSource(AnalyticSource):
    """The analytic source, but it raises at one step (a crash mid-trace)."""

    def __init__(self, scn, fail_at: int) -> None:
        super().__init__(scn)
        self.fail_at = fail_at
        self.calls: list[int] = []

    def trace_tables(self, step, states):
        self.calls.append(step)
        if step == self.fail_at:
            raise RuntimeError("boom")
        return super().trace_tables(step, states)


def _tables(c):
    return c.vehicles, c.paths


def _assert_same_tables(a, b):
    for ta, tb in zip(_tables(a), _tables(b)):
        assert list(ta) == list(tb)
        for k in ta:
            np.testing.assert_array_equal(ta[k], tb[k], err_msg=k)


def test_roundtrip_matches_source(tmp_path, paper):
    src = AnalyticSource(paper)
    d = trace_scenario(paper, src, tmp_path, steps=7, chunk_steps=3, progress=False)
    assert d == cache_dir_for(tmp_path, paper, src) and d.parent == tmp_path
    assert d.name.startswith("paper-analytic-")
    files = sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file())
    assert files == [MANIFEST] + [f"{t}/part-{i:05d}.parquet" for t in ("paths", "rays", "vehicles")
                                  for i in range(3)]
    c = load_cache(tmp_path)  # a root holding exactly one cache is accepted
    assert c.path == d and c.steps == 7
    m = c.manifest
    assert m["schema_version"] == SCHEMA_VERSION and m["source"] == "analytic"
    assert m["steps_completed"] == 7 and m["steps_requested"] == 7
    assert [(ch["step_start"], ch["step_stop"]) for ch in m["chunks"]] == [(0, 3), (3, 6), (6, 7)]
    assert m["geometry_hash"] == paper.geometry_hash()
    assert c.vehicle_names == ["veh1", "veh2"]
    assert c.scenario.to_dict() == {**paper.to_dict(), "steps": 7}
    np.testing.assert_array_equal(c.states, true_trajectories(paper, 7))  # with the preset's process noise
    assert c.states.shape == (7, 2, 7)
    assert set(c.vehicles) == set(VEHICLE_COLUMNS) and len(c.vehicles["step"]) == 14
    np.testing.assert_allclose(c.vehicles["t"], np.repeat(np.arange(7) * 0.5, 2))
    want = [src.trace_step(k, c.states[k]) for k in range(7)]
    for k, t in PATH_COLUMNS.items():
        got = c.paths[k]
        exp = np.concatenate([w[k] for w in want])
        if t == "string":
            assert got.dtype == object and got.tolist() == exp.tolist()
        else:
            assert got.dtype == np.dtype(t), k
            np.testing.assert_array_equal(got, exp, err_msg=k)


def test_resume_after_crash_equals_uninterrupted_run(tmp_path, paper):
    ref = load_cache(trace_scenario(paper, AnalyticSource(paper), tmp_path / "ref", steps=12,
                                    chunk_steps=3, progress=False))
    bad = FailingSource(paper, fail_at=7)
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, bad, tmp_path / "run", steps=12, chunk_steps=3, progress=False)
    d = cache_dir_for(tmp_path / "run", paper, bad)
    m = json.loads((d / MANIFEST).read_text())
    assert m["steps_completed"] == 6 and len(m["chunks"]) == 2  # chunk [6, 9) was lost
    assert "holds 6 of the 12 steps its trace was asked for" in load_cache(d).partial_notice()
    again = FailingSource(paper, fail_at=-1)
    trace_scenario(paper, again, tmp_path / "run", steps=12, chunk_steps=3, progress=False)
    assert again.calls == list(range(6, 12))  # only the missing steps are traced
    got = load_cache(d)
    assert got.partial_notice() is None and ref.partial_notice() is None  # asked for 12 steps of paper's 40: whole
    _assert_same_tables(got, ref)
    # chunk files byte-identical too
    assert [c["sha256"] for c in got.manifest["chunks"]] == [c["sha256"] for c in ref.manifest["chunks"]]



def test_a_trace_that_stops_before_its_first_chunk_leaves_no_empty_cache(tmp_path, paper):
    """A failure (or Ctrl-C) before the first chunk used to leave a cache of 0 steps, on which `mmslam paths` crashed
    with exit 1; now the new, empty cache is removed, and an old one of 0 steps is a one-line CacheError."""
    bad = FailingSource(paper, fail_at=1)
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, bad, tmp_path / "run", steps=6, chunk_steps=3, progress=False)
    d = cache_dir_for(tmp_path / "run", paper, bad)
    assert not d.exists()
    assert not (tmp_path / "run").exists()  # nor the cache root it made (it held only its marker)
    # nested folders it made go too; a link to a user's empty folder stays, and so does the folder, empty
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, bad, tmp_path / "a" / "b", steps=6, chunk_steps=3, progress=False)
    assert not (tmp_path / "a").exists()
    (tmp_path / "empty").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "empty")
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, bad, tmp_path / "link", steps=6, chunk_steps=3, progress=False)
    assert (tmp_path / "link").is_symlink() and not any((tmp_path / "empty").iterdir())
    # a folder the user made stays, as empty as it was; a root of caches keeps its marker and its caches
    (tmp_path / "mine").mkdir()
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, FailingSource(paper, fail_at=1), tmp_path / "mine", steps=6, chunk_steps=3,
                       progress=False)
    assert (tmp_path / "mine").is_dir() and not any((tmp_path / "mine").iterdir())
    root = tmp_path / "kept"
    moved = dataclasses.replace(paper, bs=(1.0, 0.0, 40.0))
    other = trace_scenario(moved, AnalyticSource(moved), root, steps=3,
                           chunk_steps=3, progress=False)
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, FailingSource(paper, fail_at=1), root, steps=6, chunk_steps=3, progress=False)
    assert load_cache(other).steps == 3 and (root / ".mmslam-output.json").is_file()
    assert not cache_dir_for(root, paper, bad).exists()
    # a root of caches an older mmslam wrote (no marker): the failing trace marks it and leaves its caches whole
    (root / ".mmslam-output.json").unlink()
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, FailingSource(paper, fail_at=1), root, steps=6, chunk_steps=3, progress=False)
    assert load_cache(other).steps == 3 and sorted(p.name for p in root.iterdir()) == sorted(
        [".mmslam-output.json", other.name])
    # a cache of 0 steps an earlier version left behind: refused in one line naming it and the fix
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path / "old", steps=3, chunk_steps=3, progress=False)
    m = json.loads((d / MANIFEST).read_text())
    m.update(steps_completed=0, chunks=[])
    (d / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(CacheError, match="holds no traced step") as e:
        load_cache(d)
    assert "\n" not in str(e.value) and "mmslam trace" in str(e.value)
    # a failure after a chunk keeps the chunk (resumable)
    bad = FailingSource(paper, fail_at=4)
    with pytest.raises(RuntimeError, match="boom"):
        trace_scenario(paper, bad, tmp_path / "run2", steps=6, chunk_steps=3, progress=False)
    assert load_cache(cache_dir_for(tmp_path / "run2", paper, bad)).steps == 3

def test_longer_steps_extend_a_shorter_cache(tmp_path, paper):
    ref = load_cache(trace_scenario(paper, AnalyticSource(paper), tmp_path / "ref", steps=12,
                                    chunk_steps=5, progress=False))
    trace_scenario(paper, AnalyticSource(paper), tmp_path / "ext", steps=7, chunk_steps=5, progress=False)
    src = FailingSource(paper, fail_at=-1)
    d = trace_scenario(paper, src, tmp_path / "ext", steps=12, chunk_steps=5, progress=False)
    assert src.calls == list(range(7, 12))
    got = load_cache(d)
    assert got.steps == 12 and got.manifest["steps_requested"] == 12
    _assert_same_tables(got, ref)
    # a shorter request on a longer cache traces nothing and keeps everything
    src2 = FailingSource(paper, fail_at=-1)
    trace_scenario(paper, src2, tmp_path / "ext", steps=4, progress=False)
    assert src2.calls == [] and load_cache(d).steps == 12


def test_orphan_chunk_and_temp_files_are_cleaned_on_resume(tmp_path, paper):
    src = AnalyticSource(paper)
    d = trace_scenario(paper, src, tmp_path, steps=6, chunk_steps=3, progress=False)
    # simulate a kill after chunk 1 was renamed but before the manifest recorded it
    m = json.loads((d / MANIFEST).read_text())
    m["chunks"] = m["chunks"][:1]
    m["steps_completed"] = 3
    write_manifest(d, m)
    (d / "paths" / ".part-00002.parquet.abc.tmp").write_bytes(b"partial")
    trace_scenario(paper, src, tmp_path, steps=6, chunk_steps=3, progress=False)
    assert not list(d.rglob("*.tmp")) and load_cache(d).steps == 6


def test_kill_at_any_moment_then_rerun(tmp_path, paper):
    """SIGKILL a real trace process mid-run, re-run, compare with an uninterrupted run."""
    script = tmp_path / "slow_trace.py"
    script.write_text(textwrap.dedent(f"""
        import sys, time
        from mmslam.raytrace.analytic import AnalyticSource
        from mmslam.raytrace.trace import trace_scenario
        from mmslam.scenes.scenario import load_preset

        class Slow(AnalyticSource):
            def trace_step(self, step, states):
                time.sleep(0.03)
                return super().trace_step(step, states)

        scn = load_preset("paper")
        print("start", flush=True)
        trace_scenario(scn, Slow(scn), sys.argv[1], steps=40, chunk_steps=2, progress=False)
    """))
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"start"
    d = cache_dir_for(out, paper, AnalyticSource(paper))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # wait until a few chunks are done, then kill
        mp = d / MANIFEST
        if mp.is_file() and json.loads(mp.read_text())["steps_completed"] >= 6:
            break
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    n_done = json.loads((d / MANIFEST).read_text())["steps_completed"]
    assert 6 <= n_done < 40  # really interrupted mid-trace
    src = FailingSource(paper, fail_at=-1)
    trace_scenario(paper, src, out, steps=40, chunk_steps=2, progress=False)
    assert src.calls[0] == n_done
    ref = load_cache(trace_scenario(paper, AnalyticSource(paper), tmp_path / "ref", steps=40,
                                    chunk_steps=2, progress=False))
    _assert_same_tables(load_cache(d), ref)


def test_force_retraces(tmp_path, paper):
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=4, progress=False)
    (d / "paths" / "part-00000.parquet").write_bytes(b"garbage")
    with pytest.raises(CacheError, match="--force"):
        trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=4, progress=False)
    src = FailingSource(paper, fail_at=-1)
    trace_scenario(paper, src, tmp_path, steps=4, force=True, progress=False)
    assert src.calls == [0, 1, 2, 3] and load_cache(d).steps == 4


def test_truncated_chunk_is_a_one_line_cache_error_and_exit_2(tmp_path, paper, capsys):
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=8, chunk_steps=4, progress=False)
    f = d / "paths" / "part-00001.parquet"
    f.write_bytes(f.read_bytes()[:100])
    with pytest.raises(CacheError) as e:
        load_cache(d)
    msg = str(e.value)
    assert "paths/part-00001.parquet" in msg and "--force" in msg and "\n" not in msg
    capsys.readouterr()
    assert main(["paths", str(d)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "paths/part-00001.parquet" in err and len(err.splitlines()) == 1


def test_corrupt_parquet_with_matching_sha_and_missing_chunk(tmp_path, paper):
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=4, chunk_steps=2, progress=False)
    m = json.loads((d / MANIFEST).read_text())
    junk = b"PAR1" + b"\x00" * 64 + b"PAR1"
    (d / "vehicles" / "part-00001.parquet").write_bytes(junk)
    import hashlib

    m["chunks"][1]["sha256"]["vehicles"] = hashlib.sha256(junk).hexdigest()
    write_manifest(d, m)
    with pytest.raises(CacheError, match=r"vehicles/part-00001\.parquet: unreadable Parquet"):
        load_cache(d)
    (d / "vehicles" / "part-00001.parquet").unlink()
    with pytest.raises(CacheError, match=r"vehicles/part-00001\.parquet: chunk file missing"):
        load_cache(d)


def test_manifest_problems(tmp_path, paper):
    with pytest.raises(CacheError, match="no such cache directory"):
        load_cache(tmp_path / "nope")
    with pytest.raises(CacheError, match="no manifest.json"):
        load_cache(tmp_path)
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=4, chunk_steps=2, progress=False)
    m = json.loads((d / MANIFEST).read_text())
    # other schema version
    write_manifest(d, {**m, "schema_version": SCHEMA_VERSION + 1})
    with pytest.raises(CacheError, match="schema_version"):
        load_cache(d)
    # stale manifest: claims more steps than its chunks hold
    write_manifest(d, {**m, "steps_completed": 6})
    with pytest.raises(CacheError, match="chunks cover 4 steps but steps_completed is 6"):
        load_cache(d)
    # invalid JSON
    (d / MANIFEST).write_text("{not json")
    with pytest.raises(CacheError, match="not valid JSON"):
        load_cache(d)
    (d / MANIFEST).unlink()
    with pytest.raises(CacheError, match="no manifest.json"):
        load_cache(tmp_path)


def test_root_with_two_caches_lists_candidates(tmp_path, paper):
    trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=2, progress=False)
    other = dataclasses.replace(paper, bs=(1.0, 0.0, 40.0))
    trace_scenario(other, AnalyticSource(other), tmp_path, steps=2, progress=False)
    with pytest.raises(CacheError, match="holds 2 caches") as e:
        load_cache(tmp_path)
    for p in tmp_path.iterdir():
        if p.is_dir():  # the two caches (beside them: the cache root's output marker)
            assert p.name in str(e.value)
    assert len([p for p in tmp_path.iterdir() if p.is_dir()]) == 2


def test_cache_dir_keyed_by_config(tmp_path, paper):
    src = AnalyticSource(paper)
    base = cache_dir_for(tmp_path, paper, src)
    moved = dataclasses.replace(paper, bs=(0.0, 0.0, 41.0))
    assert cache_dir_for(tmp_path, moved, AnalyticSource(moved)) != base
    fov = dataclasses.replace(paper, sensor=dataclasses.replace(paper.sensor, fov_range=60.0))
    assert cache_dir_for(tmp_path, fov, AnalyticSource(fov)) != base
    # parameters acting after the cache (filter, steps, noise) share the trace
    filt = dataclasses.replace(paper, steps=10, filter=dataclasses.replace(paper.filter, particles=10),
                               sensor=dataclasses.replace(paper.sensor, toa_std=1.0))
    assert cache_dir_for(tmp_path, filt, AnalyticSource(filt)) == base

    class OtherSettings(AnalyticSource):
        def settings(self):
            return {**super().settings(), "extra": 1}

    assert cache_dir_for(tmp_path, paper, OtherSettings(paper)) != base
    # a changed scenario traced into the same root never reads the other cache
    d1 = trace_scenario(paper, src, tmp_path, steps=2, progress=False)
    d2 = trace_scenario(moved, AnalyticSource(moved), tmp_path, steps=2, progress=False)
    assert d1 != d2
    assert load_cache(d2).scenario.bs == (0.0, 0.0, 41.0)
    assert load_cache(d2).paths["toa_m"][0] != load_cache(d1).paths["toa_m"][0]


def test_manifest_with_other_config_hash_is_refused(tmp_path, paper):
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=2, progress=False)
    m = json.loads((d / MANIFEST).read_text())
    write_manifest(d, {**m, "config_hash": "0" * 16})
    with pytest.raises(CacheError, match="config hash"):
        trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=4, progress=False)


def _rewrite_chunk(d: Path, idx: int, mutate) -> None:
    """Rewrite chunk ``idx`` (valid sha) with ``mutate(paths)`` applied."""
    c = load_cache(d)
    m = c.manifest
    ch = m["chunks"][idx]
    sel = (c.paths["step"] >= ch["step_start"]) & (c.paths["step"] < ch["step_stop"])
    paths = {k: v[sel].copy() for k, v in c.paths.items()}
    mutate(paths)
    rays = c.read_rays()
    rsel = (rays["step"] >= ch["step_start"]) & (rays["step"] < ch["step_stop"])
    veh = vehicle_columns(c.states[ch["step_start"]:ch["step_stop"]], ch["step_start"], c.scenario.dt)
    m["chunks"][idx] = write_chunk(d, idx, ch["step_start"],
                                   {"vehicles": veh, "rays": {k: v[rsel] for k, v in rays.items()},
                                    "paths": paths}, file_metadata(m))
    write_manifest(d, m)


def test_nan_in_path_row_is_a_one_line_error(tmp_path, paper, capsys):
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=6, chunk_steps=3, progress=False)

    def nan_power_and_los_bounce(p):
        p["power_db"][:] = np.nan  # allowed anywhere
        assert np.isnan(p["bounce_x"][p["type"] == BS]).all()  # allowed for LOS

    _rewrite_chunk(d, 1, nan_power_and_los_bounce)
    assert load_cache(d).steps == 6

    def nan_toa(p):
        p["toa_m"][np.flatnonzero(p["step"] == 4)[2]] = np.nan

    _rewrite_chunk(d, 1, nan_toa)
    with pytest.raises(CacheError, match=r"column 'toa_m' is nan at step 4") as e:
        load_cache(d)
    assert "\n" not in str(e.value)
    capsys.readouterr()
    assert main(["paths", str(d)]) == 2
    assert "toa_m" in capsys.readouterr().err

    d2 = trace_scenario(paper, AnalyticSource(paper), tmp_path / "b", steps=3, progress=False)

    def nan_va_bounce(p):
        p["bounce_y"][np.flatnonzero(p["type"] == VA)[0]] = np.nan

    _rewrite_chunk(d2, 0, nan_va_bounce)
    with pytest.raises(CacheError, match=r"column 'bounce_y' is nan at step 0"):
        load_cache(d2)


def test_trace_refuses_nan_from_a_source(tmp_path, paper):
    class NanSource(AnalyticSource):
        def trace_tables(self, step, states):
            c = super().trace_tables(step, states)
            if step == 3:
                c["paths"]["aoa_el"][0] = np.nan
            return c

    with pytest.raises(CacheError, match="'aoa_el' is nan at step 3"):
        trace_scenario(paper, NanSource(paper), tmp_path, steps=6, chunk_steps=3, progress=False)
    assert load_cache(tmp_path).steps == 3  # the good chunk is kept


def test_make_source_errors(paper):
    assert make_source("analytic", paper).name == "analytic"
    with pytest.raises(MmslamError, match="unknown source 'raytracer'"):
        make_source("raytracer", paper)
    with pytest.raises(MmslamError, match="max-depth"):
        make_source("sionna", paper, max_depth=4)


def test_writer_lock_blocks_a_live_writer_and_takes_over_a_dead_ones(tmp_path, paper):
    from mmslam.raytrace.trace import lock_path

    src = AnalyticSource(paper)
    d = cache_dir_for(tmp_path, paper, src)
    lock = lock_path(d)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        lock.write_text(f"{live.pid}\n")
        with pytest.raises(CacheError, match=f"another trace \\(pid {live.pid}\\)"):
            trace_scenario(paper, src, tmp_path, steps=2, progress=False)
    finally:
        live.kill()
        live.wait()
    # that process is gone now: its lock is stale and taken over
    trace_scenario(paper, src, tmp_path, steps=2, progress=False)
    assert load_cache(d).steps == 2 and not lock.exists()


def test_chunk_gap_is_refused_on_load_and_on_resume(tmp_path):
    paper = load_preset("paper")
    d = trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=6, chunk_steps=2, progress=False)
    m = json.loads((d / MANIFEST).read_text())
    del m["chunks"][1]  # steps 2..3 missing: chunk 2 then starts at 4, not 2
    write_manifest(d, m)
    with pytest.raises(CacheError, match=r"chunk 2 starts at step 4, expected 2; .*--force"):
        load_cache(d)
    with pytest.raises(CacheError, match=r"chunk 2 starts at step 4, expected 2"):
        trace_scenario(paper, AnalyticSource(paper), tmp_path, steps=8, chunk_steps=2, progress=False)
