"""docs/extending.md: the worked example (a new landmark type) runs as written and plumbs through."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from mmslam.slam import landmarks as L
from mmslam.slam import variants as V
from mmslam.slam.filter import run_filter

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


@pytest.fixture
def example():
    """Namespace after running the doc's two Python blocks; the toy type and variant are removed after."""
    blocks = _python_blocks()
    assert len(blocks) == 2
    ns: dict = {}
    try:
        for b in blocks:
            exec(compile(b, str(DOC), "exec"), ns)  # noqa: S102 (our own documentation)
        yield ns
    finally:
        V.unregister_variant("cm1_lp")
        L.unregister_landmark_type("LP")


def test_the_documented_new_type_runs_and_behaves_as_the_type_it_copies(example):
    """The LP map (SP's functions, code 5, the relabelled SP paths) gives what cm1's SP map gives on
    the original labels: the same estimates counts, GOSPA and vehicle errors (to 1e-5; the only
    difference is the birth kernel's FOV gate, keyed on the SP/VS codes)."""
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
