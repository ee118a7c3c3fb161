"""Output targets that never clobber what the user made.

Every directory mmslam writes carries a marker file naming what kind of output it is
(:data:`MARKER`, a small JSON object ``{"kind": ..., "format": ...}``). An existing target is
replaced only when it is empty or a previous output of the same kind; anything else (a user's
folder, a file, another kind of mmslam output such as the cache just read) is refused with one
line naming ``--force``. Checks run before any computation (:func:`check_target`) and again at
the moment of writing (:func:`replace_dir`), since the target can change in between.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Callable, Iterator
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
    atomic_write_bytes(Path(path) / MARKER, (json.dumps({"kind": kind, "format": 1}) + "\n").encode(), fsync=False)


def check_target(path: str | Path, kind: str, force: bool = False, *, protect: tuple[Path, ...] = (),
                 option: str = "--out", accept: "Callable[[Path], bool] | None" = None,
                 force_does: str = "replace it") -> Path:
    """Raise a one-line :class:`MmslamError` unless ``path`` may be (re)written as a ``kind`` output.

    Allowed: a missing path, an empty directory, or a directory whose marker says ``kind``.
    ``force`` also allows any other directory or file, except the paths in ``protect`` (e.g. the
    input cache) and their ancestors or descendants, which are never replaced. ``accept(path)``
    may recognise outputs of ``kind`` written before markers existed (e.g. a folder of caches).
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
        if output_kind(out) == kind or not any(out.iterdir()) or (accept is not None and accept(out)):
            return out
    if force:
        return out
    what = "a file" if not out.is_dir() else (
        f"an mmslam {output_kind(out)} output" if output_kind(out) else "a directory that is not an mmslam "
        f"{kind} output")
    raise MmslamError(f"{option} {out}: exists and is {what}; choose another path, or pass --force to "
                      f"{force_does}")


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


# ====================================================================== permissions (the user's umask)
def _umask() -> int:
    old = os.umask(0)
    os.umask(old)
    return old


def apply_umask(path: str | Path, is_dir: bool | None = None) -> None:
    """Give ``path`` the mode a plain ``open`` / ``mkdir`` would: 0o666 (files) or 0o777 (dirs) & ~umask.

    ``tempfile.mkstemp`` / ``mkdtemp`` create 0600 / 0700 whatever the umask, which hides a shared
    dataset from a lab group or from Dask workers running as another user.
    """
    p = Path(path)
    d = p.is_dir() if is_dir is None else is_dir
    os.chmod(p, (0o777 if d else 0o666) & ~_umask())


def atomic_write_bytes(path: str | Path, data: bytes, fsync: bool = True) -> Path:
    """Write ``data`` to ``path`` via a temp file in the same directory, fsync, ``os.replace``.

    The file gets the user's umask (:func:`apply_umask`). A reader never sees a partial file.
    """
    import tempfile

    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        apply_umask(tmp, is_dir=False)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def make_temp_dir(parent: Path, name: str) -> Path:
    """A fresh temporary directory ``parent/.name.XXXX`` with the user's umask (for :func:`replace_dir`)."""
    import tempfile

    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=parent))
    apply_umask(tmp, is_dir=True)
    return tmp


# ====================================================================== figures
FIGURE_FORMATS = ("png", "pdf", "svg")
FIGURE_TOKEN = "mmslam-figure"
"""Written into every figure's metadata (PNG text chunk, PDF / SVG creator): recognises our own figures."""


def figure_format(path: str | Path, option: str = "--out", formats: tuple[str, ...] = FIGURE_FORMATS) -> str:
    """The figure format named by ``path``'s suffix (one of ``formats``); one-line error otherwise."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in formats:
        raise MmslamError(f"{option} {path}: unknown figure format '.{suffix}'; use a file name ending in "
                          f"{', '.join('.' + f for f in formats)}")
    return suffix


def is_mmslam_figure(path: str | Path) -> bool:
    """True if ``path`` is a figure mmslam wrote (its metadata holds :data:`FIGURE_TOKEN`)."""
    try:
        with open(path, "rb") as f:
            return FIGURE_TOKEN.encode() in f.read(50_000_000)
    except OSError:
        return False


def check_figure_target(path: str | Path, force: bool = False, option: str = "--out",
                        formats: tuple[str, ...] = FIGURE_FORMATS) -> str:
    """Check a figure file target before any computation; returns its format.

    Allowed: a missing file, or a figure mmslam wrote before; ``force`` allows any other file.
    A directory is always refused. The parent directory must exist.
    """
    p = Path(path)
    fmt = figure_format(p, option, formats)
    if p.is_dir():
        raise MmslamError(f"{option} {p}: is a directory; give a file name ending in .{fmt}")
    if not p.parent.is_dir():
        raise MmslamError(f"{option} {p}: the directory {p.parent} does not exist; create it first")
    if os.path.lexists(p) and not force and not is_mmslam_figure(p):
        raise MmslamError(f"{option} {p}: exists and is not a figure mmslam wrote; choose another path, or "
                          "pass --force to replace it")
    return fmt


def save_figure(fig: object, path: str | Path, dpi: int = 120, **kwargs: object) -> Path:
    """Write matplotlib ``fig`` atomically in the format of ``path``'s suffix, tagged as an mmslam figure."""
    import io

    from mmslam import __version__

    p = Path(path)
    fmt = figure_format(p)
    meta = {"png": {"Software": f"{FIGURE_TOKEN} {__version__}"},
            "pdf": {"Creator": f"{FIGURE_TOKEN} {__version__}"},
            "svg": {"Creator": f"{FIGURE_TOKEN} {__version__}"}}[fmt]
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=dpi, metadata=meta, **kwargs)  # type: ignore[attr-defined]
    return atomic_write_bytes(p, buf.getvalue(), fsync=False)


# ====================================================================== locks
_HELD: dict[Path, int] = {}
"""Locks this process holds (lock path -> nesting depth): a lock is re-entrant within a process."""


def lock_path(path: str | Path) -> Path:
    """The writer lock of directory ``path``: ``.<name>.lock`` next to it."""
    p = Path(path).absolute()
    return p.parent / f".{p.name}.lock"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def acquire_lock(path: str | Path, what: str = "mmslam command", exc: type[MmslamError] = MmslamError) -> Path:
    """Take the writer lock of directory ``path`` (an ``O_EXCL`` file holding our pid).

    A lock whose process is gone (killed) is taken over; a live one raises a one-line
    :class:`MmslamError`. Re-entrant within one process. Returns the lock file.
    """
    lock = lock_path(path)
    if lock in _HELD:
        _HELD[lock] += 1
        return lock
    lock.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or "0")
            except (OSError, ValueError):
                pid = 0
            if pid == os.getpid() or (pid > 0 and _pid_alive(pid)):
                raise exc(f"{path}: another {what} (pid {pid}) is writing here; wait for it to finish, "
                                  f"or delete {lock} if that process is gone") from None
            if pid == 0:  # being written right now, or garbage: give its writer a moment
                import time

                time.sleep(0.05)
                try:
                    pid = int(lock.read_text().strip() or "0")
                except (OSError, ValueError):
                    pid = 0
                if pid > 0 and _pid_alive(pid):
                    continue
            lock.unlink(missing_ok=True)  # stale: its writer was killed
            continue
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()}\n")
        _HELD[lock] = 1
        return lock
    raise exc(f"{lock}: could not take the writer lock; delete it if no mmslam command is running, "
                      "and re-run")


def release_lock(lock: Path) -> None:
    """Release a lock taken by :func:`acquire_lock` (only the owner's file is deleted)."""
    n = _HELD.get(lock, 0)
    if n > 1:
        _HELD[lock] = n - 1
        return
    _HELD.pop(lock, None)
    try:
        if lock.read_text().strip() == str(os.getpid()):
            lock.unlink()
    except FileNotFoundError:
        pass


@contextlib.contextmanager
def locked(path: str | Path, what: str = "mmslam command") -> Iterator[Path]:
    """``with locked(dir):`` hold the writer lock of ``dir`` (see :func:`acquire_lock`)."""
    lock = acquire_lock(path, what)
    try:
        yield lock
    finally:
        release_lock(lock)
