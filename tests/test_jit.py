"""The runtime-free batch kernels (:mod:`mmslam.slam.jit`): no reference counting, same results."""
from __future__ import annotations

import re

import numba as nb
import numpy as np
import pytest

from mmslam.slam import birth, ckf, gmphd, reduction, vs
from mmslam.slam.jit import RUNTIME_FREE, batch_kernel


@nb.njit
def _squares(row: np.ndarray, a: np.ndarray) -> bool:
    for i in range(row.shape[0]):
        a[i] = row[i] * row[i]
    return True


@nb.njit(inline="always")
def _row_norm(row: np.ndarray, scratch: tuple) -> float:
    a, b = scratch
    if not _squares(row, a):
        return -1.0
    t = 0.0
    for i in range(row.shape[0]):
        b[i] = a[i]
        t += b[i]
    return np.sqrt(t)


def _norms(x: np.ndarray, out: np.ndarray, scratch: tuple) -> int:
    """The pattern of the CKF loop: a view per row, a tuple of scratch arrays, an early return."""
    for n in range(x.shape[0]):
        out[n] = _row_norm(x[n], scratch)
        if not out[n] < np.inf:
            return n
    return -1


def _increfs(fn) -> int:  # noqa: ANN001
    return len(re.findall(r"NRT_incref", fn.inspect_asm(fn.signatures[0])))


@pytest.mark.skipif(not RUNTIME_FREE, reason="this numba has no _nrt option")
def test_batch_kernel_has_no_reference_counting_and_same_results() -> None:
    x = np.random.default_rng(1).normal(size=(50, 7))
    plain, free = nb.njit(cache=False)(_norms), batch_kernel(cache=False)(_norms)
    outs = []
    for fn in (plain, free):
        out = np.empty(50)
        assert fn(x, out, (np.empty(7), np.empty(7))) == -1
        outs.append(out)
    np.testing.assert_array_equal(outs[0], outs[1])
    np.testing.assert_allclose(outs[1], np.linalg.norm(x, axis=1), rtol=1e-14)
    assert _increfs(plain) > 0  # what the runtime-free build removes (the reason it exists)
    assert _increfs(free) == 0


@pytest.mark.skipif(not RUNTIME_FREE, reason="this numba has no _nrt option")
def test_batch_kernel_cannot_allocate() -> None:
    def alloc(n: int) -> float:
        return np.zeros(n).sum()

    with pytest.raises(Exception):
        batch_kernel(cache=False)(alloc)(3)


def test_hot_loops_are_batch_kernels() -> None:
    """The filter's hot loops take their scratch from the caller (they would not compile otherwise)."""
    hot = (*gmphd._TYPE_TERMS, *ckf._CKF_BATCH, gmphd._write_corrected, gmphd._bs_loglik, reduction._plan_batch,
           reduction._write_batch, reduction._merge_pairs, birth._moments_batch, birth._births, vs._predict_batch)
    for fn in hot:
        assert fn.targetoptions.get("_nrt", True) is (not RUNTIME_FREE), fn
