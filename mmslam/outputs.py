"""Output targets that never clobber what the user made.

Every directory mmslam writes carries a marker file naming what kind of output it is
(:data:`MARKER`, a small JSON object ``{"kind": ..., "format": ...}``). An existing target is
replaced only when it is empty or a previous output of the same kind; anything else (a user's
folder, a file, another kind of mmslam output such as the cache just read) is refused with one
line naming ``--force``. Checks run before any computation (:func:`check_target`) and again at
the moment of writing (:func:`replace_dir`), since the target can change in between.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from mmslam.errors import MmslamError

MARKER = ".mmslam-output.json"


def output_kind(path: Path) -> str | None:
    """The kind recorded in ``path``'s marker (``None`` if ``path`` is no mmslam output)."""
    try:
        return str(json.loads((Path(path) / MARKER).read_text())["kind"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def write_marker(path: Path, kind: str) -> None:
    """Mark directory ``path`` as an mmslam output of ``kind``."""
    (Path(path) / MARKER).write_text(json.dumps({"kind": kind, "format": 1}) + "\n")


def check_target(path: str | Path, kind: str, force: bool = False, *, protect: tuple[Path, ...] = (),
                 option: str = "--out") -> Path:
    """Raise a one-line :class:`MmslamError` unless ``path`` may be (re)written as a ``kind`` output.

    Allowed: a missing path, an empty directory, or a directory whose marker says ``kind``.
    ``force`` also allows any other directory or file, except the paths in ``protect`` (e.g. the
    input cache) and their ancestors or descendants, which are never replaced.
    """
    out = Path(path)
    res = out.resolve()
    for p in protect:
        pr = Path(p).resolve()
        if res == pr or pr in res.parents or res in pr.parents:
            raise MmslamError(f"{option} {out}: overlaps the input {p}; choose another output path")
    if not os.path.lexists(out):
        return out
    if out.is_dir() and not out.is_symlink():
        if output_kind(out) == kind or not any(out.iterdir()):
            return out
    if force:
        return out
    what = "a file" if not out.is_dir() else (
        f"an mmslam {output_kind(out)} output" if output_kind(out) else "a directory that is not an mmslam "
        f"{kind} output")
    raise MmslamError(f"{option} {out}: exists and is {what}; choose another path, or pass --force to "
                      "replace it")


def replace_dir(tmp: Path, out: Path, kind: str, force: bool = False) -> None:
    """Move the finished directory ``tmp`` to ``out``, replacing ``out`` only as :func:`check_target` allows."""
    check_target(out, kind, force)
    if os.path.lexists(out):
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        os.replace(out, old)
        try:
            os.replace(tmp, out)
        except BaseException:
            os.replace(old, out)
            raise
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink(missing_ok=True)
    else:
        os.replace(tmp, out)
