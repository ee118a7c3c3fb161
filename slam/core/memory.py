"""Process heap settings for the filter loop (glibc only).

Every local step allocates and frees NumPy arrays of 0.1-10 MB (the corrected and merged maps of
``P`` particles). With glibc's defaults, blocks above the dynamic mmap threshold are mapped and
unmapped per call and freed heap top is trimmed back to the kernel, so each vehicle-step takes
~870 fresh page faults (measured on ``paper``, P = 300: about 0.6-1.3 ms of a 10 ms step).
:func:`retain_freed_memory` asks glibc to keep freed memory for reuse instead.
"""
from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
"""glibc ``mallopt`` parameter codes (``malloc.h``)."""

TRIM_THRESHOLD_BYTES = 256 << 20
"""Free heap top kept before it is returned to the kernel (bytes)."""
MMAP_THRESHOLD_BYTES = 64 << 20
"""Blocks at least this large are mapped per allocation; smaller ones come from the heap (bytes)."""

_ENV = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_")
_done: bool | None = None


def retain_freed_memory() -> bool:
    """Keep freed memory in the process for reuse: glibc ``mallopt`` trim threshold 256 MiB, mmap
    threshold 64 MiB (once per process; later calls return the first answer).

    A no-op (returns False) off Linux, without glibc's ``mallopt``, or when the user set one of
    glibc's ``MALLOC_*_`` tuning variables (their choice wins). The cost is that up to 256 MiB of
    freed heap stays mapped while the process runs. Returns True if both settings were applied.
    """
    global _done
    if _done is not None:
        return _done
    _done = False
    if not sys.platform.startswith("linux") or any(v in os.environ for v in _ENV):
        return _done
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl has no mallopt)
        return _done
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _done = bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)) and bool(mallopt(M_MMAP_THRESHOLD,
                                                                                   MMAP_THRESHOLD_BYTES))
    return _done
