"""How the filter's outermost compiled loops are built: :func:`batch_kernel`.

Every kernel of :mod:`mmslam.slam` is a numba ``njit`` function with ``cache=True`` (compiled
once, cached on disk). Those called from Python to loop over a whole batch (particles x
Gaussians x measurements) take all their arrays, scratch included, from the caller and allocate
nothing; :func:`batch_kernel` compiles them without numba's runtime (NRT).

Why: with the runtime, every array view taken inside a loop (``m[p, q]``, a tuple of scratch
arrays passed to an inlined function) increments and later decrements its buffer's reference
count with an atomic instruction (``lock incq``). numba's reference-count pruning removes such
pairs only within simple control flow; in the CKF loop (:func:`mmslam.slam.phd.gmphd.type_terms`),
with its early returns, about 25 pairs per Gaussian remained: ~200 of its ~800 ns. Without the
runtime there is nothing to count: the caller's arrays outlive the call. The machine code and so
the results are otherwise the same (``tests/test_jit.py``).

A kernel built with :func:`batch_kernel` cannot allocate (``np.empty`` inside fails to compile),
return an array, or call a function that does; it may call ordinary ``njit`` functions that
allocate nothing and return no array (a callee first compiled from such a kernel inherits its
no-runtime flags and is cached so: ``tests/test_jit.py`` checks every callee the kernels reach).
The switch is numba's private ``_nrt`` target option (numba 0.60 to 0.68 tested; numba's own tests
use it); where a numba has no such option, :func:`batch_kernel` is plain ``njit``.
"""
from __future__ import annotations

from typing import Any, Callable

import numba as nb
from numba.core.cpu import CPUTargetOptions

RUNTIME_FREE = hasattr(CPUTargetOptions, "_nrt")
"""Whether this numba can compile a kernel without its runtime (the ``_nrt`` target option)."""


def batch_kernel(fn: Callable | None = None, **options: Any) -> Any:
    """``numba.njit(cache=True, error_model="numpy", **options)`` without numba's runtime (see the module
    docstring): for an outermost batch loop called from Python that allocates nothing.

    Usable bare (``@batch_kernel``) or with options (``@batch_kernel(error_model="python")``).
    """
    opts: dict[str, Any] = {"cache": True, "error_model": "numpy", **options}
    if RUNTIME_FREE:
        opts["_nrt"] = False
    jit = nb.njit(**opts)
    return jit if fn is None else jit(fn)
