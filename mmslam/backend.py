"""Dr.Jit / Mitsuba backend selection for Sionna RT.

Call :func:`ensure_llvm` before Mitsuba is imported (``sionna_adapter`` does): when
``DRJIT_LIBLLVM_PATH`` is unset, it finds the newest ``libLLVM`` >= 16 on the system and sets it.
Debian 12's default libLLVM-15 makes Dr.Jit abort with ``LLVM ERROR: Cannot select ... fmaximum``;
with no usable LLVM this raises :class:`~mmslam.errors.BackendError` saying what to install.
:func:`select_variant` then picks ``cuda_ad_mono_polarized`` when a CUDA device works, else
``llvm_ad_mono_polarized``.
"""
from __future__ import annotations

import glob
import os
import re
import sys

from mmslam.errors import BackendError

MIN_LLVM = 16
_SEARCH = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
           "/usr/local/lib", "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib")
INSTALL_HINT = ("install LLVM >= 16 (Debian/Ubuntu: 'apt-get install -y libllvm19'), or set "
                "DRJIT_LIBLLVM_PATH to a libLLVM >= 16 shared library")


def _version_of(path: str) -> int | None:
    m = re.search(r"libLLVM[-.]?(\d+)", os.path.basename(path))
    if m:
        return int(m.group(1))
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_libllvm(min_version: int = MIN_LLVM) -> str | None:
    """Path of the newest ``libLLVM`` shared library with major version >= ``min_version``."""
    cands: list[tuple[int, str]] = []
    pats = []
    for d in _SEARCH:
        pats += [f"{d}/libLLVM-*.so*", f"{d}/libLLVM.so.*", f"{d}/llvm-*/lib/libLLVM*.so*",
                 f"{d}/libLLVM*.dylib"]
    pats += ["/usr/lib/llvm-*/lib/libLLVM*.so*"]
    for pat in pats:
        for p in glob.glob(pat):
            v = _version_of(p)
            if v is not None and v >= min_version and os.path.isfile(p):
                cands.append((v, p))
    if not cands:
        return None
    cands.sort(key=lambda t: (t[0], -len(t[1])))
    return cands[-1][1]


def ensure_llvm() -> str:
    """Make Dr.Jit use a libLLVM >= 16; returns the library path in use.

    Respects a user-set ``DRJIT_LIBLLVM_PATH`` (it must exist). Must run before ``import mitsuba``.
    """
    user = os.environ.get("DRJIT_LIBLLVM_PATH")
    if user:
        if not os.path.isfile(user):
            raise BackendError(f"DRJIT_LIBLLVM_PATH={user} does not exist; {INSTALL_HINT}")
        return user
    if "mitsuba" in sys.modules or "drjit" in sys.modules:
        # too late to steer Dr.Jit; it found its own LLVM (or will fail on first use)
        return ""
    lib = find_libllvm()
    if lib is None:
        raise BackendError(f"no usable LLVM found for Sionna RT on the CPU (need libLLVM >= {MIN_LLVM}, "
                           f"Debian 12 ships 15); {INSTALL_HINT}")
    os.environ["DRJIT_LIBLLVM_PATH"] = lib
    return lib


def cuda_works() -> bool:
    """True when a CUDA driver with at least one device is present (no Dr.Jit import)."""
    if os.environ.get("MMSLAM_FORCE_CPU"):
        return False
    try:
        import ctypes

        lib = ctypes.CDLL("libcuda.so.1")
        if lib.cuInit(0) != 0:
            return False
        n = ctypes.c_int(0)
        return lib.cuDeviceGetCount(ctypes.byref(n)) == 0 and n.value > 0
    except OSError:
        return False


def select_variant() -> str:
    """``cuda_ad_mono_polarized`` with a working CUDA device, else ``llvm_ad_mono_polarized``."""
    if cuda_works():
        return "cuda_ad_mono_polarized"
    ensure_llvm()
    return "llvm_ad_mono_polarized"


def import_mitsuba():
    """Import Mitsuba with the selected variant set (after pointing Dr.Jit at LLVM)."""
    variant = select_variant()
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


def _main(argv: list[str]) -> int:
    """``python -m mmslam.backend --check``: exit 0 and print the libLLVM path if usable, else 1."""
    if argv[:1] == ["--check"]:
        lib = os.environ.get("DRJIT_LIBLLVM_PATH") or find_libllvm()
        if lib and os.path.isfile(lib):
            print(lib)
            return 0
        print(f"no libLLVM >= {MIN_LLVM} found; {INSTALL_HINT}", file=sys.stderr)
        return 1
    print(select_variant())
    return 0


if __name__ == "__main__":
    raise SystemExit(_main(sys.argv[1:]))
