"""LLVM discovery for Dr.Jit: picks the newest libLLVM >= 16, refuses 15, explains the fix."""
from __future__ import annotations

import pytest

from mmslam import backend
from mmslam.errors import BackendError


def test_find_prefers_newest_and_ignores_old(tmp_path, monkeypatch):
    for v in ("14", "15", "17", "19"):
        (tmp_path / f"libLLVM-{v}.so").write_bytes(b"")
    monkeypatch.setattr(backend, "_SEARCH", (str(tmp_path),))
    assert backend.find_libllvm().endswith("libLLVM-19.so")
    assert backend.find_libllvm(min_version=20) is None


def test_only_llvm15_gives_install_hint(tmp_path, monkeypatch):
    (tmp_path / "libLLVM-15.so.1").write_bytes(b"")
    monkeypatch.setattr(backend, "_SEARCH", (str(tmp_path),))
    monkeypatch.setattr(backend.glob, "glob", lambda pat: [str(p) for p in tmp_path.iterdir()
                                                           if p.match(pat.rsplit("/", 1)[-1])])
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setitem(__import__("sys").modules, "mitsuba", None)
    monkeypatch.delitem(__import__("sys").modules, "mitsuba")
    monkeypatch.delitem(__import__("sys").modules, "drjit", raising=False)
    with pytest.raises(BackendError, match=r"need libLLVM >= 16.*apt-get install -y libllvm19"):
        backend.ensure_llvm()


def test_user_path_must_exist(monkeypatch, tmp_path):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing.so"))
    with pytest.raises(BackendError, match="DRJIT_LIBLLVM_PATH=.*does not exist"):
        backend.ensure_llvm()


def test_variant_is_llvm_without_gpu(monkeypatch):
    monkeypatch.setenv("MMSLAM_FORCE_CPU", "1")
    assert backend.select_variant() == "llvm_ad_mono_polarized"
