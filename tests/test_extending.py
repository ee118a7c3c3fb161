"""docs/extending.md: the worked example (a new landmark type) is one spec module, runs as written
and plumbs through without any edit of slam/."""
from __future__ import annotations

import hashlib
import importlib
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from mmslam.slam.specs import landmarks as L
from mmslam.slam.specs import variants as V
from mmslam.slam.filter import run_filter

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
SLAM = Path(__file__).resolve().parents[1] / "slam"


def _slam_digest() -> str:
    h = hashlib.sha256()
    for p in sorted(SLAM.rglob("*.py")):
        h.update(str(p.relative_to(SLAM)).encode() + p.read_bytes())
    return h.hexdigest()


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


@pytest.fixture
def example(tmp_path, monkeypatch):
    """The doc's first block written as the module ``lamp_posts.py`` and imported (the whole extension),
    then its second block run; the namespace of the run. The toy type and variant are removed after."""
    blocks = _python_blocks()
    assert len(blocks) == 2
    before = _slam_digest()
    (tmp_path / "lamp_posts.py").write_text(blocks[0])
    monkeypatch.syspath_prepend(str(tmp_path))
    ns: dict = {}
    try:
        mod = importlib.import_module("lamp_posts")
        exec(compile(blocks[1], str(DOC), "exec"), ns)  # noqa: S102 (our own documentation)
        ns["module"] = mod
        yield ns
    finally:
        sys.modules.pop("lamp_posts", None)
        V.unregister_variant("cm1_lp")
        L.unregister_landmark_type("LP")
    assert _slam_digest() == before  # nothing in slam/ was written


def test_the_extension_is_one_module_and_edits_no_slam_file(example):
    mod = example["module"]
    assert mod.LP is L.landmark_type("LP") is L.landmark_type(5) and mod.CM1_LP is V.get_variant("cm1_lp")
    assert not any(re.search(r"\bLP\b|lamp", p.read_text()) for p in SLAM.rglob("*.py"))


def test_errors_name_the_new_type_by_its_name(example):
    """The building blocks are handed the spec, so a bad map of the new type is reported as 'LP' (the
    old code read the fixed enum of mmslam/model.py and said '5')."""
    from mmslam.slam.core.gm import empty
    from mmslam.slam.phd.gmphd import check_phd_mass, type_terms

    lp = L.landmark_type("LP")
    g = empty((2,), 1, 3)
    with pytest.raises(ValueError, match=r"^LP correction: shapes"):
        type_terms(g, lp, np.zeros((3, 7)), np.zeros((1, 5)), np.eye(5), np.zeros(3), lambda u, x, t: np.ones(x.shape[:-1]))
    bad = empty((1,), 1, 3)
    bad.w[:], bad.mask[:] = 5.0, True
    with pytest.raises(FloatingPointError, match="in the LP correction at step 3"):
        check_phd_mass(empty((1,), 1, 3), bad, 1, lp.name, 3)


def test_the_documented_new_type_runs_and_behaves_as_the_type_it_copies(example):
    """The LP map (SP's functions, code 5, the relabelled SP paths) gives what cm1's SP map gives on
    the original labels: the same estimates counts, GOSPA and vehicle errors (to 1e-5)."""
    res, scn, states, paths = example["res"], example["scn"], example["states"], example["paths"]
    m = res.metrics
    types = np.asarray(m["type"]).astype(str)
    assert set(types) == {"VA", "SP", "LP", "VS"}  # every registered type is scored; SP unmapped here
    lp = types == "LP"
    assert m["n_true"][lp].max() > 0 and m["n_est"][lp].sum() > 0
    assert np.all(m["n_est"][types == "SP"] == 0)  # the variant has no SP map
    orig = dict(paths)
    orig["type"] = np.where(paths["type"] == 5, L.SP_SPEC.code, paths["type"]).astype(paths["type"].dtype)
    ref = run_filter(scn, states, orig, variant="cm1", particles=30, seed=0, include_types=(0, 1, 2))
    r = ref.metrics
    sp = np.asarray(r["type"]).astype(str) == "SP"
    np.testing.assert_array_equal(m["n_est"][lp], r["n_est"][sp])
    np.testing.assert_array_equal(m["n_true"][lp], r["n_true"][sp])
    np.testing.assert_array_equal(m["n_visible"][lp], r["n_visible"][sp])
    np.testing.assert_allclose(m["gospa"][lp], r["gospa"][sp], rtol=0, atol=1e-5)
    np.testing.assert_allclose(res.vehicles["pos_err"], ref.vehicles["pos_err"], rtol=0, atol=1e-5)


def test_the_example_cleans_up_after_itself():
    assert "LP" not in {s.name for s in L.landmark_types()} and "cm1_lp" not in V.variant_names()


def test_a_registered_type_may_have_its_own_row_and_leaves_none_behind(example):
    """The doc's ``[filter.types.LP]`` / ``--set filter.types.LP.p_detect=0.9`` works once LP is registered; the
    loader refuses that row for a name nobody registered (a misspelt row would set nothing)."""
    from mmslam.errors import ConfigError
    from mmslam.model import landmark_type_names
    from mmslam.scenes.scenario import load_preset, with_overrides

    assert landmark_type_names()[-1] == "LP"
    scn = with_overrides(load_preset("paper"), ["filter.types.LP.p_detect=0.9"])
    assert scn.filter.types["LP"].p_detect == 0.9
    with pytest.raises(ConfigError, match="no landmark type 'LQ' is registered; use one of BS, VA, SP, VS, LP"):
        with_overrides(load_preset("paper"), ["filter.types.LQ.p_detect=0.9"])


def test_unregistering_a_type_removes_its_row_name():
    from mmslam.model import landmark_type_names

    assert landmark_type_names() == ("BS", "VA", "SP", "VS")  # the example fixture's LP is gone
