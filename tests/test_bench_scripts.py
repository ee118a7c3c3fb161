"""The benchmark scripts `make bench` runs, on tiny sizes: they run against the current library, and their output
options (bench_ckf --save, bench_ablation --keep) never replace what they did not write."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "bench_ckf.py"
ABLATION = Path(__file__).parents[1] / "benchmarks" / "bench_ablation.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), "--steps", "7", "--first", "6", "--repeats", "1", *args],
                          capture_output=True, text=True, timeout=300)


def _counts(out: str) -> dict[str, int]:
    return {m[0]: int(m[1]) for m in re.findall(r"^(\w+)\s+(\d+) Gaussians", out, re.M)}


def test_capture_save_and_load_time_the_same_batches(tmp_path):
    """A capture of step 6 of the paper run times VA (mirror) and SP (scatter) batches; --save then --load of the
    same file times the same number of Gaussians per geometry, and a second --save may replace the first."""
    f = tmp_path / "batches.npz"
    a = _run("--save", str(f))
    assert a.returncode == 0, a.stderr
    got = _counts(a.stdout)
    assert got.get("mirror", 0) > 0 and got.get("scatter", 0) > 0, a.stdout
    b = _run("--load", str(f))
    assert b.returncode == 0, b.stderr
    assert _counts(b.stdout) == got
    assert _run("--save", str(f)).returncode == 0


def test_save_refuses_a_users_file_before_the_capture(tmp_path):
    mine = tmp_path / "mine.npz"
    mine.write_bytes(b"not mmslam's")
    p = _run("--save", str(mine))
    assert p.returncode == 2
    assert len(p.stderr.strip().splitlines()) == 1 and "--save" in p.stderr and "did not write" in p.stderr
    assert mine.read_bytes() == b"not mmslam's"
    assert p.stdout == ""
    p = _run("--load", str(mine))  # not a batch file: one line naming it and the fix
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "--load" in p.stderr


def _ablation(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ABLATION), "--mc", "1", "--steps", "6", "--particles", "20",
                           "--workers", "1", *args], capture_output=True, text=True, timeout=300)


def test_ablation_bench_runs_and_keeps_only_its_own_folder(tmp_path):
    """bench_ablation runs the 4 x 1 grid; --keep onto a user's folder is refused before any work (exit 2, one line,
    the folder untouched); a new --keep folder receives the ablation, and a second run replaces it."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    p = _ablation("--keep", str(mine))
    assert p.returncode == 2 and p.stdout == ""
    assert len(p.stderr.strip().splitlines()) == 1 and "--keep" in p.stderr
    assert [f.name for f in mine.iterdir()] == ["notes.txt"] and (mine / "notes.txt").read_text() == "keep me"
    kept = tmp_path / "kept"
    for _ in range(2):
        p = _ablation("--keep", str(kept))
        assert p.returncode == 0, p.stderr
        assert "4 jobs" in p.stdout
        assert (kept / "ablation.json").is_file() and (kept / "summary.json").is_file()
    assert sorted(f.name for f in tmp_path.iterdir()) == ["kept", "mine"]  # no temporary sibling left
    # a file the user adds to the kept ablation makes it theirs: refused before any work, nothing deleted
    (kept / "notes.txt").write_text("mine now")
    p = _ablation("--keep", str(kept))
    assert p.returncode == 2 and p.stdout == "" and "notes.txt" in p.stderr
    assert (kept / "notes.txt").read_text() == "mine now" and (kept / "ablation.json").is_file()
    # a folder that only looks like an ablation (no marker) is refused before any work too
    lookalike = tmp_path / "lookalike"
    lookalike.mkdir()
    (lookalike / "ablation.json").write_text("{}")
    p = _ablation("--keep", str(lookalike))
    assert p.returncode == 2 and p.stdout == "" and "--keep" in p.stderr
    assert [f.name for f in lookalike.iterdir()] == ["ablation.json"]
    assert sorted(f.name for f in tmp_path.iterdir()) == ["kept", "lookalike", "mine"]


def test_cache_bench_json_replaces_only_its_own_file(tmp_path):
    """bench_cache --json onto a user's file: exit 2, one line, the file untouched, nothing timed; a new file gets
    the results (tagged), and a second run may replace it."""
    script = Path(__file__).parents[1] / "benchmarks" / "bench_cache.py"

    def run(target: Path) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(script), "--steps", "3", "--repeats", "1", "--json", str(target)],
                              capture_output=True, text=True, timeout=300)

    mine = tmp_path / "mine.json"
    mine.write_text('{"mine": 1}')
    p = run(mine)
    assert p.returncode == 2 and p.stdout == "" and len(p.stderr.strip().splitlines()) == 1 and "--json" in p.stderr
    assert mine.read_text() == '{"mine": 1}'
    out = tmp_path / "res.json"
    for _ in range(2):
        p = run(out)
        assert p.returncode == 0, p.stderr
        data = json.loads(out.read_text())
        assert data["benchmark"] == "bench_cache" and data["steps"] == 3


def test_compare_estimated_reads_the_stored_estimator_columns(tmp_path):
    """compare_estimated.py on a tiny `--grid sensor.model=link,estimated` ablation of the analytic paper scene: both
    arms and the paired differences are printed, and the estimator's counts carry the columns the runs stored (it
    assumed five and crashed on the sixth, `suppressed`)."""
    out = tmp_path / "abl"
    p = subprocess.run([sys.executable, "-m", "mmslam", "ablate", "paper", "--variants", "proposed", "--grid",
                        "sensor.model=link,estimated", "--mc", "2", "--steps", "6", "--particles", "20", "--workers",
                        "1", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    script = Path(__file__).parents[1] / "benchmarks" / "compare_estimated.py"
    p = subprocess.run([sys.executable, str(script), str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout.strip().splitlines()[-1])
    assert res["link"]["runs"] == 2 and res["estimated"]["runs"] == 2
    assert res["diff_pos_rmse"][2] == 2
    counts = res["estimator_counts_mean_per_vehicle_step"]
    assert list(counts) == ["estimates", "detected", "merged", "false", "missed", "suppressed"]
    assert counts["detected"] <= counts["estimates"]


FILTER = Path(__file__).parents[1] / "benchmarks" / "bench_filter.py"


def _bench_filter(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(FILTER), "--steps", "8", "--warmup", "6", "--particles", "20",
                           "--variants", "proposed", *args], capture_output=True, text=True, timeout=300)


def test_bench_filter_set_times_the_changed_setting_and_refuses_a_bad_one():
    """bench_filter --set runs the paper data with the setting changed and says so in its header; a value out of its
    bounds, or a key that does not exist, is argparse's error (its usage line, then one line naming the key; exit 2),
    before any timing."""
    ok = _bench_filter("--set", "filter.types.VA.tail_weight=0.2")
    assert ok.returncode == 0, ok.stderr
    assert "--set filter.types.VA.tail_weight=0.2" in ok.stdout.splitlines()[0]
    assert re.search(r"proposed\s+P=\s*20: median\s+[\d.]+ ms", ok.stdout), ok.stdout
    for bad in ("filter.types.VA.tail_weight=0.9", "filter.types.VA.no_such_key=1"):
        p = _bench_filter("--set", bad)
        assert p.returncode == 2 and p.stdout == "", (bad, p.stdout)
        last = p.stderr.strip().splitlines()[-1]
        assert "error:" in last and bad.split("=")[0].split(".")[-1] in last, (bad, p.stderr)


def test_bench_filter_city_times_the_built_in_va_row():
    """bench_filter --city gives the paper data the built-in VA row (every field of DEFAULT_TYPE_PARAMS["VA"], where
    the paper preset pins its own) and says so; a --set still applies on top."""
    import importlib.util

    from mmslam.scenes.scenario import DEFAULT_TYPE_PARAMS, load_preset, with_overrides

    spec = importlib.util.spec_from_file_location("bench_filter", FILTER)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    paper = load_preset("paper")
    assert paper.filter.type_params("VA") != DEFAULT_TYPE_PARAMS["VA"]
    assert with_overrides(paper, mod.city_va_row()).filter.type_params("VA") == DEFAULT_TYPE_PARAMS["VA"]
    ok = _bench_filter("--city", "--set", "filter.types.VA.weight_share=0.5")
    assert ok.returncode == 0, ok.stderr
    head = ok.stdout.splitlines()[0]
    assert "with the built-in VA row, --set filter.types.VA.weight_share=0.5" in head, head
    assert re.search(r"proposed\s+P=\s*20: median\s+[\d.]+ ms", ok.stdout), ok.stdout


def test_compare_traces_matches_rows_and_reports_the_differences(tmp_path):
    """benchmarks/compare_traces.py: a table against a copy with one row dropped, one ToA moved by 1e-4 m and one
    azimuth moved across the -pi / pi cut by 2e-6 rad: one row only in A, the rest matched, max |dToA| 1e-4 m and
    max |d az| 2e-6 rad (wrapped, not 2 pi); a missing cache is one line and exit 2."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("compare_traces", SCRIPT.parent / "compare_traces.py")
    ct = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ct)

    n = 4
    a = {"step": np.arange(n), "rx": np.zeros(n, int), "type": np.ones(n, int), "lm_x": np.arange(n) * 10.0,
         "lm_y": np.full(n, 5.0), "lm_z": np.full(n, 2.0), "toa_m": np.full(n, 50.0), "aod_az": np.zeros(n),
         "aod_el": np.zeros(n), "aoa_az": np.array([np.pi - 1e-6, 0, 0, 0]), "aoa_el": np.zeros(n),
         "power_db": np.full(n, -100.0), "doppler_hz": np.zeros(n)}
    b = {k: v[:3].copy() for k, v in a.items()}
    b["toa_m"][1] += 1e-4
    b["aoa_az"][0] = -np.pi + 1e-6
    r = ct.compare(a, b)
    assert r["rows"] == (4, 3, 3) and r["only_a"] == [(3, 0, 1, 30.0, 5.0, 2.0)] and r["only_b"] == []
    assert r["shared_keys"] == (0, 0)
    assert r["diff"]["toa_m"][0] == pytest.approx(1e-4, rel=1e-6)
    assert r["diff"]["aoa_az"][0] == pytest.approx(2e-6, rel=1e-6)
    assert r["diff"]["power_db"] == (0.0, 0.0)
    p = subprocess.run([sys.executable, str(SCRIPT.parent / "compare_traces.py"), str(tmp_path / "none"),
                        str(tmp_path / "none")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
