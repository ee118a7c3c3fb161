"""Compile the filter's numba kernels before a run, in parallel processes when none is cached yet.

Every kernel is compiled on first use and cached on disk (``cache=True``; where: see
:func:`mmslam.slam.kernel_cache_dirs`). On a fresh install (or a fresh ``NUMBA_CACHE_DIR``) the
first run would compile them one after the other, inside its first steps (~23 s of CPU for
``baseline``, silently, and counted in the run's ``wall_time_s``). :func:`ensure_compiled`
instead, before the run's clock starts:

1. looks up, for each kernel the variants use (:data:`mmslam.slam.filter.kernel_signatures.SIGNATURES`, the
   argument types each top-level kernel is called with, recorded by ``python -m
   mmslam.slam.filter.record_kernels``), whether the cache holds it;
2. if some are missing, prints one notice line and compiles them in ``processes`` spawned worker
   processes (numba's compiler holds a process-wide lock, so threads would not help), each
   kernel a task, most expensive first; the workers write the cache;
3. loads every kernel of the variants into this process (0.3 s from a warm cache), so the run
   itself neither compiles nor loads anything (checked by ``tests/test_precompile.py``).

A kernel called with argument types not in the table is compiled on first use as before (correct,
only slower); the test above fails when the table misses a kernel a variant calls.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import functools
import importlib
import multiprocessing as mp
import os
import pkgutil
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

#: modules of :mod:`mmslam.slam` that define no kernels and need not be imported to find them
_SKIP = ("cli", "precompile", "kernel_signatures", "record_kernels")


@functools.lru_cache(maxsize=1)
def kernel_dispatchers() -> dict[str, Any]:
    """Every numba dispatcher defined in :mod:`mmslam.slam` (sub-packages included), keyed
    ``"<module's last name>.<function's qualified name>"`` (e.g. ``"gmphd._type_terms_scatter"``)."""
    import numba.core.registry as reg

    slam_dir = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # mmslam.slam, found on disk
    out: dict[str, Any] = {}
    for info in pkgutil.walk_packages([slam_dir], "mmslam.slam."):
        if info.name.rsplit(".", 1)[-1] in _SKIP:
            continue
        mod = importlib.import_module(info.name)
        for obj in vars(mod).values():
            if isinstance(obj, reg.CPUDispatcher) and obj.py_func.__module__ == mod.__name__:
                out[f"{info.name.rsplit('.', 1)[-1]}.{obj.py_func.__qualname__}"] = obj
    return out


def _types_namespace() -> dict[str, Any]:
    from numba.core import types

    ns = {k: v for k, v in vars(types).items() if not k.startswith("_")}
    ns.update(bool=types.boolean, none=types.none, omitted=types.Omitted)
    return ns


@functools.lru_cache(maxsize=None)
def parse_signature(text: str) -> tuple[Any, ...]:
    """A signature as recorded (``repr`` of numba's argument types) back into numba types."""
    sig = eval(text, {"__builtins__": {}}, _types_namespace())  # noqa: S307 (our own table)
    return tuple(sig)


def wanted(variants: Iterable[str]) -> list[tuple[str, str, float]]:
    """``(kernel, signature, compile seconds when recorded)`` used by any of ``variants``, most
    expensive first (unknown variants: every kernel of the table)."""
    from .kernel_signatures import SIGNATURES

    vs = set(variants)
    known = {v for *_, used in SIGNATURES for v in used}
    every = not vs or not vs <= known  # a variant the table does not know: compile everything
    rows = [(k, s, c) for k, s, c, used in SIGNATURES if every or vs & set(used)]
    return sorted(rows, key=lambda r: (-r[2], r[0], r[1]))


def is_cached(disp: Any, sig: tuple[Any, ...]) -> bool:
    """Whether ``disp`` holds ``sig`` already (loaded, or in its on-disk cache index).

    Reads numba's cache index (private ``_cache`` API, numba 0.60 to 0.68); any error: False (the
    kernel is then compiled in a worker, which loads it from the cache if it is there after all)."""
    if tuple(sig) in disp.overloads:
        return True
    try:
        cache = disp._cache
        index = cache._cache_file._load_index()
        return cache._index_key(tuple(sig), disp.targetctx.codegen()) in index
    except Exception:  # noqa: BLE001 (a numba without these internals)
        return False


def _compile_one(name: str, sig_text: str) -> tuple[str, float]:
    """Worker task: compile (and so cache) one kernel; returns its name and CPU seconds."""
    t = time.process_time()
    kernel_dispatchers()[name].compile(parse_signature(sig_text))
    return name, time.process_time() - t


def default_processes() -> int:
    """Compile processes: ``$MMSLAM_COMPILE_PROCESSES`` if set, else the CPUs this process may use."""
    if os.environ.get("MMSLAM_COMPILE_PROCESSES", "").strip().isdigit():
        return max(1, int(os.environ["MMSLAM_COMPILE_PROCESSES"]))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def ensure_compiled(variants: Iterable[str] = (), processes: int | None = None,
                    notice: Callable[[str], None] | None = None, load: bool = True) -> int:
    """Compile what ``variants`` need and is not cached yet, then load all of it into this process.

    Args:
        variants: variant names (empty: every kernel in the table).
        processes: compile processes (None: :func:`default_processes`; 1: in this process, e.g. in a
            daemonic worker that may not start processes).
        notice: called once with a one-line message before compiling (not called when all is cached).
        load: load the kernels into this process too (False: only make sure the cache holds them).

    Returns:
        The number of kernels compiled (0: everything came from the cache).
    """
    disp = kernel_dispatchers()
    rows = [(k, s, c) for k, s, c in wanted(variants) if k in disp]
    missing = [(k, s) for k, s, _ in rows if not is_cached(disp[k], parse_signature(s))]
    if missing:
        if processes is None and mp.current_process().daemon:  # e.g. a dask worker: may not start processes
            processes = 1
        n = max(1, min(processes or default_processes(), len(missing)))
        if notice is not None:
            notice(f"compiling {len(missing)} numba kernels of the filter once for this install"
                   + (f" ({n} processes)" if n > 1 else "") + f"; later runs load them from {cache_location()}")
        if n > 1:
            _compile_parallel(missing, n)
    if load or (missing and n == 1):
        for k, s, _ in rows:  # load (or, where a worker failed to cache it, compile) into this process
            disp[k].compile(parse_signature(s))
    return len(missing)


def compile_for_workers(variants: Iterable[str], progress: bool = True) -> int:
    """Before starting worker processes on this machine (``mmslam ablate``): compile what the
    variants need once, in parallel, so that the workers only load it (instead of each compiling the
    same kernels while the first jobs wait). Prints the notice on stdout when ``progress`` (stderr is
    for the one-line errors)."""
    return ensure_compiled(variants, notice=(lambda m: print(m, flush=True)) if progress else None, load=False)


def _compile_parallel(todo: Sequence[tuple[str, str]], n: int) -> None:
    from mmslam.executor import single_thread_env, starting_workers, worker_init

    with single_thread_env():  # the workers only compile: one BLAS thread each
        ex = cf.ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn"), initializer=worker_init,
                                    initargs=(os.getpid(),))
        with starting_workers():  # a Ctrl-C reaches this process only, not a half-started worker
            futs = [ex.submit(_compile_one, k, s) for k, s in todo]
    try:
        for f in cf.as_completed(futs):
            f.result()
    except BaseException:
        procs = list((getattr(ex, "_processes", None) or {}).values())
        ex.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            p.terminate()
        raise
    ex.shutdown(wait=True)


def cache_location() -> str:
    """Where numba caches this install's kernels (its own locator's choice, for the notice): the folder
    of the first kernel's cache, or with ``NUMBA_CACHE_DIR`` set, that folder."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return os.environ["NUMBA_CACHE_DIR"]
    for d in kernel_dispatchers().values():
        return str(os.path.dirname(d.stats.cache_path)) if d.stats.cache_path else "numba's cache"
    return "numba's cache"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m mmslam.slam.filter.precompile``: compile every kernel of the table (e.g. at install
    time, ``make setup``). Re-recording the table: ``python -m mmslam.slam.filter.record_kernels CACHE``."""
    ap = argparse.ArgumentParser(prog="python -m mmslam.slam.filter.precompile", description=main.__doc__)
    ap.add_argument("--processes", type=int, default=None)
    a = ap.parse_args(argv)
    t = time.perf_counter()
    n = ensure_compiled((), a.processes, notice=lambda m: print(m, file=sys.stderr, flush=True))
    print(f"{n} kernels compiled, all loaded in {time.perf_counter() - t:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
