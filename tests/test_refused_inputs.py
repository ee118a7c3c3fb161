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

TRACE = ["trace", "paper", "--source", "analytic", "--steps", "4", "--chunk-steps", "2", "--quiet"]


def one_line(capsys, *needles: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    for n in needles:
        assert n in err, (n, err)
    return err


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
