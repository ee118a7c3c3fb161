"""benchmarks/city_va.py's seed lists and paired summaries (the numbers docs/city-slam.md quotes)."""
from __future__ import annotations

import argparse
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats


def _bench():
    spec = importlib.util.spec_from_file_location("city_va", Path(__file__).parents[1] / "benchmarks" / "city_va.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_seed_lists_take_ranges_and_single_seeds():
    b = _bench()
    assert b.seeds_of("0-4") == [0, 1, 2, 3, 4]
    assert b.seeds_of("1,3") == [1, 3]
    assert b.seeds_of("0-2,10-11,7") == [0, 1, 2, 10, 11, 7]
    for bad in ("", "5-3", "0-5,3", "1,,2", "a-b", "1,"):
        with pytest.raises(argparse.ArgumentTypeError, match="without repeats"):
            b.seeds_of(bad)
    with pytest.raises(SystemExit) as e:
        b.main(["nowhere", "--seeds", "0-3,2"])
    assert e.value.code == 2


def test_paired_summary_by_hand():
    """Differences [-0.2, -0.1, 0.0, 0.15, 0.3, nan]: mean 0.03, half-width t(0.975, 4) x sd / sqrt(5) with sd =
    sqrt(0.158 / 4); median 0.0; lower on 2 of the 5 finite seeds; above +0.1 on 2 (0.15 and 0.3)."""
    p = _bench().paired([-0.2, -0.1, 0.0, 0.15, 0.3, math.nan])
    assert p["mean"] == pytest.approx(0.03, abs=1e-15)
    sd = math.sqrt((0.23 ** 2 + 0.13 ** 2 + 0.03 ** 2 + 0.12 ** 2 + 0.27 ** 2) / 4)
    assert sd == pytest.approx(math.sqrt(0.158 / 4), rel=1e-12)
    assert p["half"] == pytest.approx(stats.t.ppf(0.975, 4) * sd / math.sqrt(5), rel=1e-12)
    assert (p["n"], p["median"], p["lower"], p["hurt"]) == (5.0, 0.0, 0.4, 2.0)
    none = _bench().paired([math.nan])
    assert none["n"] == 0.0 and all(np.isnan(none[k]) for k in ("mean", "median", "lower", "hurt"))


def test_assigned_rms_from_gospa_split_by_hand():
    """c = 20, p = 2, alpha = 2: a missed truth costs 200 m^2. Step 1: 3 truths, one missed (200), the two assigned
    at 1 m and 2 m (loc 1 + 4 = 5); step 2: 2 truths, both assigned at 3 m (loc 18). Assigned 2 + 2 = 4, rms
    sqrt((5 + 18) / 4); no truth assigned -> NaN; alpha 1 (no split) -> NaN."""
    b = _bench()
    ev = argparse.Namespace(gospa_c=20.0, gospa_p=2.0, gospa_alpha=2.0)
    r = b.assigned_rms(np.array([5.0, 18.0]), np.array([200.0, 0.0]), np.array([3.0, 2.0]), ev)
    assert r == pytest.approx(math.sqrt(23.0 / 4.0), rel=1e-14)
    assert math.isnan(b.assigned_rms(np.array([0.0]), np.array([400.0]), np.array([2.0]), ev))
    assert math.isnan(b.assigned_rms(np.array([5.0]), np.array([0.0]), np.array([2.0]),
                                     argparse.Namespace(gospa_c=20.0, gospa_p=2.0, gospa_alpha=1.0)))


def test_save_refuses_a_users_file_before_any_run(tmp_path):
    """--save onto a file city_va.py did not write: one line on stderr, exit 2, the file untouched, and no run
    started (the cache given does not even exist: the check comes first). A folder is refused too."""
    import subprocess
    import sys

    script = Path(__file__).parents[1] / "benchmarks" / "city_va.py"
    mine = tmp_path / "notes.json"
    mine.write_text('{"my": "numbers"}')
    for target in (mine, tmp_path):
        p = subprocess.run([sys.executable, str(script), str(tmp_path / "no-cache"), "--save", str(target)],
                           capture_output=True, text=True)
        assert p.returncode == 2
        err = p.stderr.strip().splitlines()
        assert len(err) == 1 and "--save" in err[0] and str(target) in err[0], p.stderr
    assert mine.read_text() == '{"my": "numbers"}'


def test_save_recognises_only_its_own_files(tmp_path):
    """An earlier --save (a list of scenes with scene, cache, rows, summary) may be replaced; other JSON, a broken
    file or an empty list may not; a missing file in an existing folder may be written."""
    b = _bench()
    own = tmp_path / "run.json"
    own.write_text('[{"scene": "canyon", "cache": "C", "rows": [], "summary": {}}]')
    assert b.is_city_va_save(own)
    b.check_save_target(str(own))
    b.check_save_target(str(tmp_path / "new.json"))
    from mmslam.errors import MmslamError

    for text in ('{"scene": "canyon"}', "[]", "[{\"scene\": 1}]", "not json"):
        other = tmp_path / "other.json"
        other.write_text(text)
        assert not b.is_city_va_save(other)
        with pytest.raises(MmslamError, match="did not write"):
            b.check_save_target(str(other))
    with pytest.raises(MmslamError, match="does not exist"):
        b.check_save_target(str(tmp_path / "nowhere" / "x.json"))


def test_va_path_stats_by_hand():
    """Two vehicles, steps 0-3, kmin 1 (steps 1-3: six vehicle-steps). VA paths (type 1): vehicle 0 at steps 1 and 3
    (two at step 3), vehicle 1 at step 0 (before kmin) and step 2. LOS paths (type 0): vehicle 0 at steps 1 and 2,
    vehicle 1 at step 3. VA paths per vehicle-step: (1 + 2 + 1) / 6. Vehicle-steps without LOS in 1-3: (0, 3) with
    VAs, (1, 1) without, (1, 2) with: 2 of 3. An SP path (type 2) counts for neither."""
    b = _bench()
    paths = {"step": np.array([1, 3, 3, 0, 2, 1, 2, 3, 2]), "rx": np.array([0, 0, 0, 1, 1, 0, 0, 1, 1]),
             "type": np.array([1, 1, 1, 1, 1, 0, 0, 0, 2])}
    per_step, share = b.va_path_stats(paths, 4, 2, 1)
    assert per_step == pytest.approx(4 / 6)
    assert share == pytest.approx(2 / 3)
    has = b.va_path_mask(paths, 4, 2)
    assert has.tolist() == [[False, True], [True, False], [False, True], [True, False]]
    # rmse_nlos_va's vehicle-steps: without LOS and with a VA path
    assert (b.nlos_mask(paths, 4, 2) & has).tolist() == [[False, True], [False, False], [False, True], [True, False]]
    lit = {"step": np.array([1, 2, 3, 1, 2, 3]), "rx": np.array([0, 0, 0, 1, 1, 1]), "type": np.zeros(6, int)}
    per_step, share = b.va_path_stats(lit, 4, 2, 1)
    assert per_step == 0.0 and math.isnan(share)


def test_scores_rmse_over_the_masked_vehicle_steps_by_hand():
    """scores(): steps 0-2, two vehicles, kmin 1. Position errors (step, vehicle): (1, 0) 3, (1, 1) 4, (2, 0) 1,
    (2, 1) 2 (step 0's 100 m are before kmin). Without LOS: (1, 1), (2, 0), (2, 1); of those with a VA path: (2, 1).
    rmse = sqrt((9 + 16 + 1 + 4) / 4), rmse_nlos = sqrt((16 + 1 + 4) / 3), rmse_nlos_va = 2; the fused SP GOSPA
    and its false part are the means of the SP rows at k >= 1; nees the median NEES at k >= 1 without the NaN."""
    from types import SimpleNamespace

    b = _bench()
    steps = np.array([0, 1, 2])
    metrics = {"map": np.array(["fused"] * 6), "type": np.array(["VA"] * 3 + ["SP"] * 3),
               "step": np.concatenate([steps, steps]), "gospa": np.array([1.0, 2.0, 4.0, 9.0, 3.0, 5.0]),
               "loc": np.zeros(6), "missed": np.zeros(6), "false": np.array([0.0, 0, 0, 7, 2, 6]),
               "n_true": np.full(6, 2.0), "n_visible": np.ones(6), "card": np.ones(6)}
    vehicles = {"step": np.array([0, 0, 1, 1, 2, 2]), "vehicle": np.array([0, 1, 0, 1, 0, 1]),
                "pos_err": np.array([100.0, 100.0, 3.0, 4.0, 1.0, 2.0]),
                "pos_nees": np.array([1e6, 1e6, 5.0, 1.0, np.nan, 3.0])}
    nlos = np.array([[True, True], [False, True], [True, True]])
    nlos_va = np.array([[True, False], [False, False], [False, True]])
    ev = argparse.Namespace(gospa_c=20.0, gospa_p=2.0, gospa_alpha=2.0)
    out = b.scores(SimpleNamespace(metrics=metrics, vehicles=vehicles), 1, nlos, ev, nlos_va)
    assert out["rmse"] == pytest.approx(math.sqrt(30 / 4))
    assert out["rmse_nlos"] == pytest.approx(math.sqrt(21 / 3))
    assert out["rmse_nlos_va"] == pytest.approx(2.0)
    assert out["va"] == pytest.approx(3.0) and out["sp"] == pytest.approx(4.0) and out["sp_false"] == pytest.approx(4.0)
    assert out["nees"] == 3.0  # the median of 5, 1 and 3 at k >= 1 (a singular covariance's NaN left out)
    assert "rmse_nlos_va" not in b.scores(SimpleNamespace(metrics=metrics, vehicles=vehicles), 1, nlos, ev)


def _pool():
    here = Path(__file__).parents[1] / "benchmarks"
    import sys
    sys.path.insert(0, str(here))
    spec = importlib.util.spec_from_file_location("city_va_pool", here / "city_va_pool.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_pool_resumes_from_its_chunks_and_merges_them_in_seed_order(tmp_path):
    """Every chunk of a scene already there: nothing runs, and the merged file holds the rows of both chunks in seed
    order with the seed-independent summary (the paired statistics left to the reader)."""
    import json

    p = _pool()
    assert p.scene_of("/x/munich3-sionna-38b59ff16ca9961c") == "munich3" and p.chunks([1, 2, 3], 2) == [[1, 2], [3]]
    cache = tmp_path / "sf4-sionna-03c7ed2cd4377767"
    cache.mkdir()
    out = tmp_path / "run"
    (out / "chunks").mkdir(parents=True)
    for ss in ([7, 8], [9]):
        rows = [{"seed": s, "va": float(s)} for s in reversed(ss)]
        doc = [{"scene": "sf4", "cache": str(cache), "rows": rows,
                "summary": {"floor2": [0.5, 0.0], "va": [float(ss[0]), 0.1], "va-cmp_va": [1.0, 2.0]}}]
        (out / "chunks" / f"sf4.{ss[0]}-{ss[-1]}.json").write_text(json.dumps(doc))
    assert p.main([str(cache), "--seeds", "7-9", "--chunk", "2", "--out", str(out), "--", "--odometry"]) == 0
    merged = json.loads((out / "sf4.json").read_text())[0]
    assert [r["seed"] for r in merged["rows"]] == [7, 8, 9]
    assert merged["summary"] == {"floor2": [0.5, 0.0]}
    with pytest.raises(SystemExit) as e:
        p.main([str(tmp_path / "nowhere"), "--seeds", "1", "--out", str(out)])
    assert e.value.code == 2
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "sf4.json").write_text("my notes")
    with pytest.raises(SystemExit) as e:  # a file of the user's where the merged result would go: refused
        p.main([str(cache), "--seeds", "7-9", "--out", str(mine)])
    assert e.value.code == 2 and (mine / "sf4.json").read_text() == "my notes"
    assert p.main([str(cache), "--seeds", "7-9", "--out", str(tmp_path / "fresh"), "--", "--nonsense"]) == 2
    twin = tmp_path / "sf4-analytic-0123456789abcdef"
    twin.mkdir()
    with pytest.raises(SystemExit) as e:  # two caches of one scene would share their chunk files
        p.main([str(cache), str(twin), "--seeds", "7-9", "--out", str(out)])
    assert e.value.code == 2
