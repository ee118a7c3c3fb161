"""The runtime-free batch kernels (:mod:`mmslam.slam.core.jit`): no reference counting, same results."""
from __future__ import annotations

import re

import numba as nb
import numpy as np
import pytest

from mmslam.slam.phd import birth
from mmslam.slam.phd import ckf
from mmslam.slam.phd import gmphd
from mmslam.slam.core import jit
from mmslam.slam.phd import reduction
from mmslam.slam.models import vs
from mmslam.slam.core.gm import GM
from mmslam.slam.core.jit import RUNTIME_FREE, batch_kernel
from mmslam.slam.models.measurement import SP, VA, VS
from mmslam.model import Bounce
from mmslam.slam.specs.landmarks import landmark_type


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

    with pytest.raises(nb.core.errors.TypingError, match="zeros"):  # the allocation itself is refused
        batch_kernel(cache=False)(alloc)(3)
    assert nb.njit(cache=False)(alloc)(3) == 0.0  # the same function compiles with the runtime


def test_hot_loops_are_batch_kernels() -> None:
    """The filter's hot loops take their scratch from the caller (they would not compile otherwise)."""
    hot = (*gmphd._TYPE_TERMS, *ckf._CKF_BATCH, gmphd._write_corrected, gmphd._bs_loglik, reduction._plan_batch,
           reduction._write_batch, reduction._merge_pairs, birth._moments_batch, birth._births, vs._predict_batch)
    for fn in hot:
        assert fn.targetoptions.get("_nrt", True) is (not RUNTIME_FREE), fn


def test_without_the_runtime_option_batch_kernel_is_plain_njit(monkeypatch) -> None:
    """The fallback for a numba without ``_nrt`` (``RUNTIME_FREE`` False): plain ``njit`` with the same
    options, reference counting back in, the same results (the filter runs on it unchanged: the kernels
    take their scratch from the caller either way)."""
    monkeypatch.setattr(jit, "RUNTIME_FREE", False)
    fb = jit.batch_kernel(cache=False)(_norms)
    assert "_nrt" not in fb.targetoptions and fb.targetoptions["error_model"] == "numpy"
    assert jit.batch_kernel(error_model="python", cache=False)(_norms).targetoptions["error_model"] == "python"
    x = np.random.default_rng(2).normal(size=(20, 7))
    out = np.empty(20)
    assert fb(x, out, (np.empty(7), np.empty(7))) == -1
    np.testing.assert_allclose(out, np.linalg.norm(x, axis=1), rtol=1e-14)
    assert _increfs(fb) > 0  # compiled with the runtime


_S = np.array([[70.73, 0, 0, np.pi / 2, 22.22, np.pi / 10, 300.0]])
_BS = np.array([0.0, 0.0, 40.0])
_R = np.diag([0.3, 0.03, 0.03, 0.03, 0.03]) ** 2


def _one(m: list[float], P: np.ndarray, w: float = 1.0) -> GM:
    return GM(np.array([[w]]), np.array([[m]], float), P[None, None].astype(float), np.ones((1, 1), bool))


def _pd(u, x, t):  # noqa: ANN001, ANN202
    return np.full(np.shape(x)[:-1], 0.9)


_INDEFINITE = np.diag([1.0, -1.0, 1.0])
_HUGE7 = GM(np.ones((1, 1)), np.full((1, 1, 7), 1e308), 1e308 * np.eye(7)[None, None], np.ones((1, 1), bool))
_SINGULAR = GM(np.array([0.5, 0.5]), np.array([[0.0, 0, 0], [1, 1, 1]]), np.stack([np.eye(3), np.zeros((3, 3))]),
               np.ones(2, bool))
_OVERFLOW = GM(np.array([1e308, 1e308]), np.zeros((2, 3)), np.stack([np.eye(3)] * 2), np.ones(2, bool))

# (call, the whole message): each an error code of a runtime-free kernel turned into its Python error
_KERNEL_ERRORS = {
    "type_terms position": (lambda: gmphd.type_terms(_one([10.0, 0, 0], _INDEFINITE), landmark_type(SP), _S, np.zeros((1, 5)), _R,
                                                     _BS, _pd), "covariance not positive definite in SP correction"),
    "type_terms innovation": (lambda: gmphd.type_terms(_one([10.0, 0, 0], np.eye(3)), landmark_type(VA), _S, np.zeros((1, 5)),
                                                       -np.eye(5), _BS, _pd),
                              "covariance not positive definite in VA correction (innovation covariance)"),
    "innovate position": (lambda: ckf.innovate(np.array([[10.0, 0, 0]]), _INDEFINITE[None], _S, 1, _BS,
                                               np.zeros((1, 5)), _R, "stage X"),
                          "covariance not positive definite in stage X"),
    "innovate innovation": (lambda: ckf.innovate(np.array([[10.0, 0, 0]]), np.eye(3)[None], _S, 2, _BS,
                                                 np.zeros((1, 5)), -np.eye(5), "stage X"),
                            "covariance not positive definite in stage X (innovation covariance)"),
    "merge singular": (lambda: reduction.prune_merge(_SINGULAR, 1e-4, 49.0, 5),
                       "singular or indefinite covariance in Gaussian-mixture merging"),
    "merge overflow": (lambda: reduction.prune_merge(_OVERFLOW, 1e-4, 49.0, 5),
                       "non-finite Gaussian component after prune_merge"),
    "vs prediction": (lambda: vs.predict_vs(_HUGE7, 0.1, 0.9, np.full(7, 0.1), None),
                      "non-finite Gaussian component after VS prediction"),
}


@pytest.mark.parametrize("case", sorted(_KERNEL_ERRORS))
def test_error_codes_of_runtime_free_kernels_are_one_line_errors(case: str) -> None:
    call, message = _KERNEL_ERRORS[case]
    with pytest.raises(FloatingPointError) as err:
        call()
    assert str(err.value) == message


def _fresh(fn):  # noqa: ANN001, ANN202
    """A new, uncached compile of the kernel ``fn`` with its options (numba's cached code cannot be inspected)."""
    return nb.njit(**{k: v for k, v in fn.targetoptions.items() if k != "nopython"}, cache=False)(fn.py_func)


_ALLOCATION = re.compile(r"@NRT_(MemInfo_alloc\w*|MemInfo_new\w*|Allocate\w*|MemInfo_varsize\w*)\b")


@pytest.mark.skipif(not RUNTIME_FREE, reason="this numba has no _nrt option")
def test_runtime_free_kernels_reach_no_allocation(monkeypatch) -> None:
    """A runtime-free kernel may call ordinary ``njit`` functions (compiled with the runtime); none that
    it reaches may allocate (nor so return a new array, which the kernel would never release). Only a
    callee inlined at numba IR level is refused at compile time (test_batch_kernel_cannot_allocate):
    this checks the linked machine code. Each kernel is compiled afresh (numba's cached code cannot be
    inspected) with the argument types the library passes it; one CKF kernel stands for all six (the
    same ``ckf_update``).

    And none of the numba functions a runtime-free kernel calls returns an array: a callee first compiled
    from such a kernel inherits its flags (numba's flag inheritance: no runtime), is cached so and reused
    by callers with the runtime, which would release a returned array that was never counted for them."""
    fresh: dict[str, object] = {}

    def recorded(fn):  # noqa: ANN001, ANN202
        def call(*args):  # noqa: ANN002, ANN202
            f = fresh.setdefault(fn.__name__, _fresh(fn))
            return f(*args)
        return call

    for mod, name in ((gmphd, "_bs_loglik"), (reduction, "_plan_batch"), (reduction, "_write_batch"),
                      (reduction, "_merge_pairs"), (birth, "_moments_batch"), (birth, "_births"),
                      (vs, "_predict_batch")):
        monkeypatch.setattr(mod, name, recorded(getattr(mod, name)))
    monkeypatch.setattr(gmphd, "_TYPE_TERMS", (*gmphd._TYPE_TERMS[:2], recorded(gmphd._TYPE_TERMS[2])))
    Z = np.array([[100.0, 0.1, -0.1, 0.2, 0.1], [90.0, 0.2, 0.0, -0.3, 0.1]])
    g = GM(np.ones((2, 2)), np.full((2, 2, 7), 20.0), np.broadcast_to(np.eye(7), (2, 2, 7, 7)).copy(),
           np.ones((2, 2), bool), np.ones((2, 2, 2)), np.arange(4).reshape(2, 2))
    s = np.repeat(_S, 2, 0)
    t = gmphd.type_terms(g, landmark_type(VS), s, Z, _R, _BS, _pd)  # the scatter CKF kernel
    lp = gmphd.log_psi([t], gmphd.bs_logterm(s, Z, _R, _BS, np.full(2, 0.9)), -10.0, (2, 2))
    out = gmphd.corrected_gm(t, Z, lp)
    reduction.prune_merge(out, 1e-5, 4.0, 3)
    reduction.average_map(out, np.full(2, 0.5), 1e-5, 4.0, 5, by_label=True)
    reduction.merge_pairs(GM(g.w[0], g.m[0], g.P[0], g.mask[0], g.pd_beta[0]), np.array([[0, 1]]))
    vs.predict_vs(g, 0.1, 0.9, np.full(7, 0.1), None)
    m, c, ok = birth.birth_moments(s, Z, _R, Bounce.SCATTER, _BS)
    birth.birth_from_moments(s, m, c, ok, landmark_type(VS), 0.01, _pd)
    # _write_corrected is called from compiled code (_corrected_components): its types by hand, P = 0
    f8, b1, i8 = np.float64, np.bool_, np.int64
    wc = _fresh(gmphd._write_corrected)
    e = np.empty
    assert wc(e((0, 2), b1), e((0, 2)), e((0, 2, 2)), e((0, 2)), e((0, 2, 7)), e((0, 2, 7, 7)), e((0, 2), i8),
              e((0, 2, 7)), e((0, 1, 7, 7)), e((0, 2, 2)), True, 0.0, True, e((0, 2), i8), e((0, 6)), e((0, 6, 7)),
              e((0, 6, 7, 7)), e((0, 6), b1), e((0, 6, 2)), e((0, 6), i8))
    fresh["_write_corrected"] = wc
    assert sorted(fresh) == sorted(["_type_terms_scatter", "_write_corrected", "_bs_loglik", "_plan_batch",
                                    "_write_batch", "_merge_pairs", "_moments_batch", "_births", "_predict_batch"])
    for name, fn in fresh.items():
        assert fn.targetoptions["_nrt"] is False
        for sig in fn.signatures:
            assert not _ALLOCATION.findall(fn.inspect_llvm(sig)), name
    callees = _callees(fresh.values())
    typed = {f.__name__ for f in callees if f.signatures}  # callees of a callee loaded from the cache are not
    assert {"cholesky", "gaussian_loglik", "measure_point", "beta_pool", "missed_beta", "detected_beta"} <= typed
    for f in callees:
        for cres in f.overloads.values():
            rt = cres.signature.return_type
            assert not any(isinstance(t, nb.types.Array) for t in (rt.types if isinstance(rt, nb.types.BaseTuple)
                                                                     else (rt,))), (f, rt)


def _callees(kernels) -> list:  # noqa: ANN001
    """The numba functions not inlined at IR level that ``kernels`` reach by global name (through inlined ones)."""
    from numba.core.registry import CPUDispatcher

    out, seen, stack = [], set(), [k.py_func for k in kernels]
    while stack:
        py = stack.pop()
        code = [py.__code__]
        names = set()
        while code:
            c = code.pop()
            names.update(c.co_names)
            code.extend(k for k in c.co_consts if hasattr(k, "co_names"))
        for n in names:
            f = py.__globals__.get(n)
            if isinstance(f, CPUDispatcher) and id(f) not in seen:
                seen.add(id(f))
                stack.append(f.py_func)
                if f.targetoptions.get("inline", "never") != "always":
                    out.append(f)
    return out


def test_no_compiled_function_indexes_with_a_bare_none() -> None:
    """``a[None]`` in compiled code fails to lower on numba 0.60-0.61 (numba#10370; pyproject allows 0.60):
    ``merge_pairs``, so the ``proposed`` variant, raised NotImplementedError there. ``a[None, ...]`` works."""
    import ast
    from pathlib import Path

    import mmslam.slam as slam_pkg

    bad = []
    for path in sorted(Path(slam_pkg.__file__).parent.glob("*.py")):
        for fn in ast.walk(ast.parse(path.read_text())):
            if isinstance(fn, ast.FunctionDef) and any(re.search(r"njit|batch_kernel", ast.unparse(d))
                                                       for d in fn.decorator_list):
                bad += [f"{path.name}:{s.lineno}" for s in ast.walk(fn) if isinstance(s, ast.Subscript)
                        and isinstance(s.slice, ast.Constant) and s.slice.value is None]
    assert not bad
