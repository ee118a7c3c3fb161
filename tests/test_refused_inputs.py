"""Issue 25, items 5 and 9: inputs that used to be accepted silently or end in a traceback.

Each is refused with one line ``error: ...`` naming the thing, exit 2, before any work.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from mmslam.cli import main
from mmslam.raytrace.cache import MANIFEST, load_cache
from cli_errors import one_line

TRACE = ["trace", "paper", "--source", "analytic", "--steps", "4", "--chunk-steps", "2", "--quiet"]


@pytest.fixture(scope="module")
def clean_cache(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("c")
    assert main(TRACE + ["--out", str(root)]) == 0
    (d,) = [p for p in root.iterdir() if p.is_dir()]
    return d


# ============================================================ fusion.start after the last step
def test_fusion_start_after_the_last_step_is_refused(tmp_path, capsys):
    # before: accepted; every GOSPA / RMSE table covers steps >= fusion.start, so it came out empty
    toml = tmp_path / "late.toml"
    text = (Path(__file__).resolve().parents[1] / "scenes" / "presets" / "paper.toml").read_text()
    assert text.count("start = [5, 6]") == 1
    toml.write_text(text.replace("start = [5, 6]", "start = [40, 41]"))  # the paper preset has 40 steps: 0..39
    for argv in (["scene", "show", str(toml), "--out", str(tmp_path / "p.png")],
                 ["trace", str(toml), "--source", "analytic", "--steps", "2", "--quiet", "--out", str(tmp_path / "c")]):
        capsys.readouterr()
        assert main(argv) == 2
        one_line(capsys, "fusion.start", "first fusion step 40", "last step 39")
    assert not (tmp_path / "c").exists() and not (tmp_path / "p.png").exists()
    capsys.readouterr()
    assert main(["ablate", "paper", "--source", "analytic", "--steps", "2", "--mc", "1", "--particles", "3",
                 "--set", "fusion.start=[40]", "--quiet", "--out", str(tmp_path / "a")]) == 2
    one_line(capsys, "fusion.start", "first fusion step 40")
    toml.write_text(text.replace("start = [5, 6]", "start = [39, 41]"))  # the last step still evaluates
    assert main(["scene", "show", str(toml), "--out", str(tmp_path / "p.png")]) == 0


# ============================================================ deeply nested TOML
@pytest.mark.parametrize("where", ["file", "set"])
def test_a_5000_deep_toml_array_is_a_one_line_error(tmp_path, capsys, where):
    # before: RecursionError inside tomllib, exit 1 ("this is a bug")
    deep = "[" * 5000 + "]" * 5000
    if where == "file":
        toml = tmp_path / "deep.toml"
        toml.write_text(f'name = "deep"\nbs = {deep}\n')
        argv = ["scene", "show", str(toml), "--out", str(tmp_path / "p.png")]
    else:
        argv = ["ablate", "paper", "--source", "analytic", "--steps", "2", "--mc", "1", "--set",
                f"filter.merge={deep}", "--quiet", "--out", str(tmp_path / "a")]
    assert main(argv) == 2
    one_line(capsys, "nested too deeply")
    assert not (tmp_path / "a").exists()


# ============================================================ edited and re-hashed caches
def _edit_paths(src: Path, dst: Path, edit) -> Path:
    """Copy cache ``src`` to ``dst`` with chunk 0's paths table edited by ``edit(table) -> table``, re-hashed."""
    import shutil

    shutil.copytree(src, dst)
    m = json.loads((dst / MANIFEST).read_text())
    c = m["chunks"][0]
    f = dst / c["files"]["paths"]
    pq.write_table(edit(pq.read_table(f)), f)
    c["sha256"]["paths"] = hashlib.sha256(f.read_bytes()).hexdigest()
    (dst / MANIFEST).write_text(json.dumps(m))
    return dst


def _set(col: str, value: float):
    import pyarrow as pa

    def edit(t):
        v = t.column(col).to_numpy().copy()
        v[1] = value
        return t.set_column(t.schema.get_field_index(col), t.schema.field(col), pa.array(v))
    return edit


@pytest.mark.parametrize("edit, needle", [
    (_set("toa_m", 1e300), "'toa_m' is 1e+300"),
    (_set("toa_m", -5.0), "'toa_m' is -5.0"),
    (_set("aoa_az", 7.0), "'aoa_az' is 7.0"),
    (_set("aod_el", -2.0), "'aod_el' is -2.0"),
    (lambda t: __import__("pyarrow").concat_tables([t, t.slice(2, 1)]), "duplicated row"),
])
def test_an_edited_and_rehashed_cache_is_refused_on_load(tmp_path, capsys, clean_cache, edit, needle):
    # before: a re-hashed cache with toa = 1e300, a negative toa or a duplicated row loaded and ran
    load_cache(clean_cache)  # the original is fine
    bad = _edit_paths(clean_cache, tmp_path / clean_cache.name, edit)
    assert main(["slam", str(bad), "--particles", "3", "--out", str(tmp_path / "r")]) == 2
    one_line(capsys, str(bad), needle, "--force")
    assert not (tmp_path / "r").exists()


# ============================================================ item 9: manifest types, messages
@pytest.mark.parametrize("key, value, needle", [
    ("steps_completed", "forty", "'steps_completed' is \"forty\", expected an integer"),
    ("chunks", None, "'chunks' is null, expected a list"),
    ("vehicle_names", [1, 2], "'vehicle_names' is [1, 2]"),
    ("dt", -1, "'dt' is -1"),
    ("chunks.0.step_start", "0", "'chunks[0].step_start' is \"0\""),
    ("chunks.0.rows", None, "'chunks[0].rows' is null"),
    ("chunks.0.files.paths", "../../etc/passwd", "'chunks[0].files.paths'"),
    ("steps_completed", True, "'steps_completed' is true"),
])
def test_a_manifest_with_wrongly_typed_values_is_a_one_line_error(tmp_path, capsys, clean_cache, key, value, needle):
    # before: steps_completed "forty" or chunks null gave exit 1 (ValueError / TypeError: "this is a bug")
    import shutil

    d = tmp_path / clean_cache.name
    shutil.copytree(clean_cache, d)
    m = json.loads((d / MANIFEST).read_text())
    *path, last = key.split(".")
    node = m
    for k in path:
        node = node[int(k)] if isinstance(node, list) else node[k]
    node[last] = value
    (d / MANIFEST).write_text(json.dumps(m))
    for argv in (["paths", str(d)], ["slam", str(d), "--particles", "3", "--out", str(tmp_path / "r")],
                 ["export", str(d), "--cfr", "--out", str(tmp_path / "h.npz")]):
        capsys.readouterr()
        assert main(argv) == 2, argv
        one_line(capsys, str(d / MANIFEST), needle, "--force")
    assert main(TRACE + ["--out", str(tmp_path)]) == 2  # resuming it: refused too
    one_line(capsys, needle)


def test_set_errors_name_the_option_not_a_literal_manifest(tmp_path, capsys):
    # before: "error: <manifest> with --set: key 'filter.merge': ..."
    assert main(["ablate", "paper", "--source", "analytic", "--steps", "2", "--mc", "1", "--particles", "3",
                 "--set", "filter.merge=-1", "--quiet", "--out", str(tmp_path / "a")]) == 2
    err = one_line(capsys, "--set", "filter.merge")
    assert "<" not in err and "manifest" not in err


def test_export_far_negative_l_min_is_a_one_line_error_before_any_work(tmp_path, capsys, clean_cache):
    # before: --l-min -100000000 passed the size guard and ran out of memory (38.7 GiB), and the message then
    # named --particles, --steps and --workers
    out = tmp_path / "h.npz"
    assert main(["export", str(clean_cache), "--cir", "--l-min", "-100000000", "--out", str(out)]) == 2
    one_line(capsys, "--l-min -100000000", "100001024 taps", f"at most {1 << 20}", "raise --l-min")
    assert not out.exists()
    # the bound counts the taps: l_min .. subcarriers - 1 with 2^20 taps in all is allowed past this check
    assert main(["export", str(clean_cache), "--cir", "--subcarriers", "1024", "--l-min", str(1024 - (1 << 20)),
                 "--steps", "0", "--rx", "0", "--out", str(out)]) == 0
    capsys.readouterr()


def test_export_l_min_error_names_existing_options(tmp_path, capsys, clean_cache):
    # before: "error: --l-max 1023 < --l-min 2000: ..." although export has no --l-max option
    assert main(["export", str(clean_cache), "--cir", "--l-min", "2000", "--out", str(tmp_path / "h.npz")]) == 2
    err = one_line(capsys, "--l-min 2000", "--subcarriers - 1 = 1023")
    assert "--l-max" not in err
    assert not (tmp_path / "h.npz").exists()


# ============================================================ the wrong kind of path: the right diagnosis
def test_a_file_given_as_a_cache_is_named_a_file(tmp_path, capsys):
    # before: "no such cache directory; run `mmslam trace <scenario> --out f.txt`", which would be refused
    f = tmp_path / "f.txt"
    f.write_text("hi")
    assert main(["paths", str(f)]) == 2
    err = one_line(capsys, f"{f}: is a file, not a cache folder")
    assert "mmslam trace <scenario> --out" not in err
    assert f.read_text() == "hi"


def test_a_cache_root_without_that_source_reads_well(capsys, clean_cache):
    # before: "no a cache traced by 'sionna'"
    assert main(["paths", str(clean_cache.parent), "--source", "sionna"]) == 2
    one_line(capsys, "no cache traced by 'sionna' here or directly under it")


def test_a_cache_two_levels_down_is_pointed_to(tmp_path, capsys, clean_cache):
    # before: "no manifest.json here or in its sub-directories" for an ablation's folder, whose cache is in cache/
    import shutil

    top = tmp_path / "abl"
    shutil.copytree(clean_cache, top / "cache" / clean_cache.name)
    assert main(["slam", str(top), "--out", str(tmp_path / "r")]) == 2
    one_line(capsys, f"{top}: no manifest.json here or directly under it, but 1 cache a level further down "
                     f"({top / 'cache' / clean_cache.name}); give that folder")
    assert not (tmp_path / "r").exists()


def test_report_on_a_cache_says_it_is_a_cache(capsys, clean_cache):
    # before: "not an ablation results directory; run `mmslam ablate <scenario> --out <the cache>`", which would be
    # refused (the folder is a cache)
    assert main(["report", str(clean_cache)]) == 2
    err = one_line(capsys, f"{clean_cache}: is a path cache, not an ablation's results")
    assert f"--out {clean_cache}" not in err


@pytest.mark.parametrize("argv", [["scene", "show", "paper", "--out", "{d}"], ["paths", "{c}", "--plot", "{d}"]])
def test_a_folder_given_as_a_figure_is_named_a_folder(tmp_path, capsys, clean_cache, argv):
    # before: "unknown figure format '.'"
    d = tmp_path / "figs"
    d.mkdir()
    assert main([a.replace("{d}", str(d)).replace("{c}", str(clean_cache)) for a in argv]) == 2
    one_line(capsys, f"--{'out' if 'show' in argv else 'plot'} {d}: is a folder; give a figure file name")
    assert list(d.iterdir()) == []
