"""The numba kernel cache is dropped when a kernel source changes (numba alone only checks the
source file of the kernel itself, not of the functions it inlines)."""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import mmslam.slam as slam_pkg


def _copy_pkg(tmp_path: Path) -> Path:
    src = Path(slam_pkg.__file__).parent
    dst = tmp_path / "slam"
    dst.mkdir()
    for name in slam_pkg.KERNEL_SOURCES:
        (dst / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(src / name, dst / name)
    return dst


def test_stale_kernels_removed_only_after_a_source_change(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    pkg = _copy_pkg(tmp_path)
    cache = pkg / "phd" / "__pycache__"
    slam_pkg._invalidate_stale_kernels(pkg)  # first call: writes the stamp
    (cache / "ckf.innovate-1.py311.nbi").write_bytes(b"index")
    (cache / "ckf.innovate-1.py311.1.nbc").write_bytes(b"code")
    (cache / "ckf.cpython-311.pyc").write_bytes(b"pyc")
    assert slam_pkg._invalidate_stale_kernels(pkg) is False  # unchanged sources: the cache stays
    assert (cache / "ckf.innovate-1.py311.nbi").exists()
    with open(pkg / "models" / "measurement.py", "a") as f:  # an inlined callee in another folder changes
        f.write("\n# edited\n")
    assert slam_pkg._invalidate_stale_kernels(pkg) is True
    assert not list(cache.glob("*.nb[ic]"))
    assert (cache / "ckf.cpython-311.pyc").exists()  # only numba's files are removed
    assert slam_pkg._invalidate_stale_kernels(pkg) is False  # the new stamp is kept


def test_numba_cache_dir_and_user_cache_checked_too(tmp_path, monkeypatch):
    """With NUMBA_CACHE_DIR set (or the user-wide fallback of a read-only install) numba keeps the
    kernels in <dir>/<folder>_<sha1 of the folder path>: the same rule, the same invalidation."""
    from numba.core.caching import _CacheLocator

    pkg = _copy_pkg(tmp_path)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba-cache"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    sub = _CacheLocator.get_suitable_cache_subpath(str(pkg / "phd" / "ckf.py"))  # numba's own rule
    dirs = slam_pkg.kernel_cache_dirs(pkg / "phd")
    assert dirs == [pkg / "phd" / "__pycache__", tmp_path / "numba-cache" / sub, tmp_path / "xdg" / "numba" / sub]
    for d in dirs[1:]:
        d.mkdir(parents=True)
        (d / "ckf.innovate-1.py311.nbi").write_bytes(b"index")
    slam_pkg._invalidate_stale_kernels(pkg)  # no stamp yet: stale
    assert not any(list(d.glob("*.nbi")) for d in dirs)
    for d in dirs[1:]:
        (d / "ckf.innovate-1.py311.nbi").write_bytes(b"index")
    assert slam_pkg._invalidate_stale_kernels(pkg) is False  # stamps match: kept
    with open(pkg / "core" / "linalg.py", "a") as f:
        f.write("\n# edited\n")
    assert slam_pkg._invalidate_stale_kernels(pkg) is True
    assert not any(list(d.glob("*.nbi")) for d in dirs)


def test_every_slam_module_with_a_numba_kernel_is_a_kernel_source():
    pkg = Path(slam_pkg.__file__).parent
    with_kernels = {p.relative_to(pkg).as_posix() for p in pkg.rglob("*.py")
                    if re.search(r"@(nb\.njit|batch_kernel)\b", p.read_text())}
    # core/jit.py: the compile options of the batch kernels (a change there must drop the cached ones too)
    assert with_kernels | {"core/jit.py"} == set(slam_pkg.KERNEL_SOURCES)
    assert slam_pkg.kernel_dirs(pkg) == sorted({pkg / "core", pkg / "models", pkg / "phd", pkg / "filter", pkg / "sim"})


def test_a_new_numba_cache_dir_keeps_the_first_process_kernels(tmp_path, monkeypatch):
    """NUMBA_CACHE_DIR naming a folder that does not exist yet (a fresh CI cache, a new worker): the first
    process finds no folder, numba creates it and writes its kernels; the next process must keep them (same
    sources), not take the unstamped folder for stale and compile everything again (~20 s)."""
    pkg = _copy_pkg(tmp_path)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "fresh-cache"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    user = slam_pkg.kernel_cache_dirs(pkg / "phd")[1]
    assert not user.exists()
    assert slam_pkg._invalidate_stale_kernels(pkg) is False  # first process: nothing cached yet
    user.mkdir(parents=True, exist_ok=True)  # numba compiles and caches into it
    (user / "ckf.innovate-1.py311.nbi").write_bytes(b"index")
    assert slam_pkg._invalidate_stale_kernels(pkg) is False  # second process, same sources: kept
    assert (user / "ckf.innovate-1.py311.nbi").exists()
    with open(pkg / "phd" / "ckf.py", "a") as f:
        f.write("\n# edited\n")
    assert slam_pkg._invalidate_stale_kernels(pkg) is True  # still dropped after a source change
    assert not (user / "ckf.innovate-1.py311.nbi").exists()
    assert not (tmp_path / "xdg").exists()  # a folder numba does not use is not created


def test_the_user_wide_cache_of_a_read_only_install_keeps_the_first_process_kernels(tmp_path, monkeypatch):
    """Where ``__pycache__`` cannot be written numba caches in the user-wide folder: the same rule."""
    pkg = _copy_pkg(tmp_path)
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    (pkg / "phd" / "__pycache__").write_bytes(b"")  # not a folder: cannot be written (also as root)
    user = slam_pkg.kernel_cache_dirs(pkg / "phd")[-1]
    assert slam_pkg._invalidate_stale_kernels(pkg) is False
    user.mkdir(parents=True, exist_ok=True)
    (user / "ckf.innovate-1.py311.nbi").write_bytes(b"index")
    assert slam_pkg._invalidate_stale_kernels(pkg) is False
    assert (user / "ckf.innovate-1.py311.nbi").exists()
    with open(pkg / "phd" / "ckf.py", "a") as f:
        f.write("\n# edited\n")
    assert slam_pkg._invalidate_stale_kernels(pkg) is True
    assert not (user / "ckf.innovate-1.py311.nbi").exists()
