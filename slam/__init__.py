"""MM-PHD-SLAM: sensor model, RBPF with GM-PHD maps per landmark type, map fusion, GOSPA.

Never imports Sionna, Mitsuba or Dr.Jit.

The kernels are compiled by numba with ``cache=True``; numba re-validates a cached kernel only
against its own source file, not against the files of the functions it inlines (e.g.
``measurement.measure_point`` inside ``ckf.ckf_update``). :func:`_invalidate_stale_kernels` keeps
the on-disk cache consistent with the sources: it runs once, on the first import of
:mod:`mmslam.slam`, before any kernel module is imported.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import mmslam.model as _model

KERNEL_SOURCES = ("birth.py", "ckf.py", "detection.py", "dynamics.py", "gmphd.py", "linalg.py", "measurement.py",
                  "reduction.py", "vs.py")
"""The ``slam/`` modules that define numba kernels (one hash over all of them)."""

_STAMP = "mmslam-kernels.sha256"


def _invalidate_stale_kernels(pkg: Path = Path(__file__).parent) -> bool:
    """Delete the cached numba kernels of ``slam/__pycache__`` when any kernel source changed.

    Compares a SHA-256 of :data:`KERNEL_SOURCES` (plus ``mmslam/model.py``) with the stamp written
    next to the cache; on a mismatch removes every ``*.nbi`` / ``*.nbc`` there and writes the new
    stamp (atomically). A read-only install or a ``NUMBA_CACHE_DIR`` elsewhere is left alone.
    Returns True if cached kernels were removed.
    """
    cache = pkg / "__pycache__"
    if os.environ.get("NUMBA_CACHE_DIR"):
        return False
    try:
        h = hashlib.sha256()
        for src in [pkg / name for name in KERNEL_SOURCES] + [Path(_model.__file__)]:
            h.update(src.read_bytes())
        digest = h.hexdigest()
        stamp = cache / _STAMP
        if stamp.is_file() and stamp.read_text().strip() == digest:
            return False
        cache.mkdir(exist_ok=True)
        stale = list(cache.glob("*.nbi")) + list(cache.glob("*.nbc"))
        for p in stale:
            p.unlink(missing_ok=True)
        tmp = cache / f".{_STAMP}.{os.getpid()}"
        tmp.write_text(digest + "\n")
        os.replace(tmp, stamp)
        return bool(stale)
    except OSError:  # read-only install: numba uses its own user cache there
        return False


_invalidate_stale_kernels()
