"""MM-PHD-SLAM: sensor model, RBPF with GM-PHD maps per landmark type, map fusion, GOSPA.

Sub-packages, one per layer; a module imports only from its own layer's package or the layers
below (checked by ``tests/test_layers.py``; docs/architecture.md)::

    core  <-  models  <-  phd, fusion, reference  <-  specs  <-  eval  <-  filter  <-  cli

Never imports Sionna, Mitsuba or Dr.Jit.

The kernels are compiled by numba with ``cache=True``; numba re-validates a cached kernel only
against its own source file, not against the files of the functions it inlines (e.g.
``models/measurement.measure_point`` inside ``phd/ckf.ckf_update``). :func:`_invalidate_stale_kernels` keeps
the on-disk cache consistent with the sources: it runs once, on the first import of
:mod:`mmslam.slam`, before any kernel module is imported.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import mmslam.model as _model

KERNEL_SOURCES = ("core/gm.py", "core/jit.py", "core/linalg.py", "core/trig.py", "models/dynamics.py",
                  "models/measurement.py", "models/vs.py", "phd/birth.py", "phd/ckf.py",
                  "phd/detection.py", "phd/merging.py", "phd/reduction.py", "phd/tail.py", "phd/terms.py",
                  "filter/rbpf.py", "sim/dft_kernels.py", "sim/nomp_kernels.py", "sim/sensor.py")
"""The ``slam/`` modules that define numba kernels, relative to the package (one hash over all of them)."""

_STAMP = "mmslam-kernels.sha256"


def kernel_dirs(pkg: Path = Path(__file__).parent) -> list[Path]:
    """The folders of ``pkg`` that hold kernel sources (each has its own numba cache)."""
    return sorted({(pkg / name).parent for name in KERNEL_SOURCES})


def kernel_cache_dirs(src_dir: Path) -> list[Path]:
    """Where numba may keep the compiled kernels of the modules in ``src_dir`` (numba's own locator rules).

    ``src_dir/__pycache__`` (the default), ``$NUMBA_CACHE_DIR/<dir>_<sha1 of the directory path>`` when
    that variable is set, and the user-wide cache ``$XDG_CACHE_HOME/numba/<same>`` (``~/.cache``)
    that numba falls back to when ``__pycache__`` is not writable (a read-only install).
    """
    src = os.path.abspath(src_dir)
    sub = f"{os.path.split(src)[-1]}_{hashlib.sha1(src.encode()).hexdigest()}"
    dirs = [Path(src_dir) / "__pycache__"]
    if os.environ.get("NUMBA_CACHE_DIR"):
        dirs.append(Path(os.environ["NUMBA_CACHE_DIR"]) / sub)
    dirs.append(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "numba" / sub)
    return dirs


def _invalidate_stale_kernels(pkg: Path = Path(__file__).parent) -> bool:
    """Delete the cached numba kernels of ``pkg`` wherever they are when any kernel source changed.

    Compares a SHA-256 of :data:`KERNEL_SOURCES` (plus ``mmslam/model.py``) with the stamp kept in
    each of :func:`kernel_cache_dirs` of every :func:`kernel_dirs` folder that exists or that numba
    will write this time (``__pycache__``, ``$NUMBA_CACHE_DIR``'s folder when set, the user-wide one
    when ``__pycache__`` cannot be written: created and stamped now, or the next process would take
    the kernels this one caches there for stale); on a mismatch removes every ``*.nbi`` / ``*.nbc``
    there and writes the new stamp (atomically). One hash over all folders: a kernel inlines callees
    of other folders (``phd/ckf.py`` inlines ``models/measurement.py``). A folder that cannot be
    written is skipped. Returns True if cached kernels were removed.

    Not covered: a process that imported the old sources and compiles a kernel after the edit.
    """
    try:
        h = hashlib.sha256()
        for src in [pkg / name for name in KERNEL_SOURCES] + [Path(_model.__file__)]:
            h.update(src.read_bytes())
    except OSError:
        return False
    digest = h.hexdigest()
    removed = False
    for src_dir in kernel_dirs(pkg):
        removed = _refresh(kernel_cache_dirs(src_dir), digest) or removed
    return removed


def _refresh(dirs: list[Path], digest: str) -> bool:
    """:func:`_invalidate_stale_kernels` for the cache folders ``dirs`` of one source folder."""
    removed = False
    user_dir = bool(os.environ.get("NUMBA_CACHE_DIR"))  # numba's first choice when set
    in_tree = False  # __pycache__ written (numba's next choice)
    for i, cache in enumerate(dirs):
        numba_writes = i == 0 or (i == 1 and user_dir) or (i == len(dirs) - 1 and not (user_dir or in_tree))
        if not (numba_writes or cache.is_dir()):
            continue
        try:
            stamp = cache / _STAMP
            if not (stamp.is_file() and stamp.read_text().strip() == digest):
                cache.mkdir(parents=True, exist_ok=True)
                stale = list(cache.glob("*.nbi")) + list(cache.glob("*.nbc"))
                for p in stale:
                    p.unlink(missing_ok=True)
                tmp = cache / f".{_STAMP}.{os.getpid()}"
                tmp.write_text(digest + "\n")
                os.replace(tmp, stamp)
                removed = removed or bool(stale)
            in_tree = in_tree or (i == 0 and os.access(cache, os.W_OK))
        except OSError:  # read-only folder: numba does not write there either
            continue
    return removed


_invalidate_stale_kernels()
