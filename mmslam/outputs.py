"""Output targets that never clobber what the user made.

The one policy of every writing command: **mmslam writes into, replaces or deletes only what it
wrote itself.** A directory is mmslam's when it carries the marker file :data:`MARKER` (a small
JSON object ``{"kind": ..., "format": ...}``) naming the kind of output; a file when it carries
mmslam's tag (:data:`FIGURE_TOKEN` in a figure's metadata, :data:`NPZ_TAG` in an ``.npz``). A marker
also records the digest (SHA-256) of every file mmslam wrote there (:func:`write_marker`, :func:`record_files`), so
a file the user edited or added under one of mmslam's names after the fact is recognised as the user's. An
existing target is used only when it is empty or a previous output of the same kind; anything else
(a user's folder or file, the folder or file a symbolic link points to, another kind of mmslam
output such as the cache just read) is refused with one line, **with or without** ``--force``.
A directory that is replaced as a whole (a SLAM result) must moreover hold nothing but the files
that kind writes, so a file the user added to it is never deleted; and a file mmslam is about to
replace must be the one it wrote (its recorded digest), so a file the user edited there is never
overwritten. ``--force`` never widens what may be touched: it only asks ``mmslam trace`` to rebuild a
cache mmslam wrote.

Checks run before any computation (:func:`check_target`) and again at the moment of writing
(:func:`replace_dir`), since the target can change in between. A symbolic link at the target is
followed: the link stays, what it points to is checked and (if allowed) written.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Callable, Collection, Iterator
from pathlib import Path

from mmslam.errors import MmslamError

MARKER = ".mmslam-output.json"
NEVER = "mmslam never writes into, replaces or deletes what it did not write, even with --force"
"""The reason given in every refusal of a foreign target."""


def output_kind(path: Path) -> str | None:
    """The kind recorded in ``path``'s marker (``None`` if ``path`` is no mmslam output)."""
    try:
        return str(json.loads((Path(path) / MARKER).read_text())["kind"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def file_digest(path: str | Path) -> str:
    """SHA-256 of the file's bytes, hex (read in 1 MiB blocks)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_record(path: Path, kind: str, files: dict[str, str] | None) -> None:
    rec: dict[str, object] = {"kind": kind, "format": 1 if files is None else 2}
    if files is not None:
        rec["files"] = dict(sorted(files.items()))
    atomic_write_bytes(Path(path) / MARKER, (json.dumps(rec, indent=1) + "\n").encode(), fsync=False)


def write_marker(path: Path, kind: str, files: Collection[str] | None = None) -> None:
    """Mark directory ``path`` as an mmslam output of ``kind``.

    Only for a directory mmslam created or found empty (or one already marked ``kind``): a marker
    makes the directory mmslam's. ``files``: the names (relative paths) of the files mmslam wrote there;
    their digests are recorded (:func:`file_digest`; names not present are skipped), and only a recorded
    file with its recorded content may later be replaced (:func:`edited_entries`). None: a marker without
    a record (format 1, as written before records existed: every file in it counts as mmslam's).
    """
    p = Path(path)
    _write_record(p, kind, None if files is None else
                  {n: file_digest(p / n) for n in files if (p / n).is_file()})


def recorded_files(path: str | Path) -> dict[str, str] | None:
    """The marker's record ``{name: digest}`` of the files mmslam wrote in ``path`` (None: no record)."""
    try:
        files = json.loads((Path(path) / MARKER).read_text()).get("files")
    except (OSError, ValueError, AttributeError):
        return None
    return {str(k): str(v) for k, v in files.items()} if isinstance(files, dict) else None


def record_files(path: str | Path, kind: str, names: Collection[str]) -> None:
    """Add (or update) the digests of ``names``, just written by mmslam into ``path``, to its marker's record.

    A marker without a record (format 1) first records every file then in the folder: under the old rule each
    of them counted as mmslam's, so an upgrade takes nothing away that a rebuild could replace before.
    """
    p = Path(path)
    rec = recorded_files(p)
    if rec is None:
        rec = {f.relative_to(p).as_posix(): file_digest(f) for f in sorted(p.rglob("*"))
               if f.is_file() and f.name != MARKER and not f.name.startswith(".")}
    rec.update({n: file_digest(p / n) for n in names if (p / n).is_file()})
    _write_record(p, kind, rec)


def edited_entries(path: str | Path, names: Collection[str]) -> list[str]:
    """The names among ``names`` present in ``path`` that mmslam did not write as they are now (sorted).

    A name counts as mmslam's when the marker's record holds it with the file's current digest; a file
    edited after mmslam wrote it, or one the user put there under a name mmslam writes, does not. A folder
    whose marker has no record (format 1) cannot tell: nothing is reported.
    """
    p = Path(path)
    rec = recorded_files(p)
    if rec is None:
        return []
    return sorted(n for n in names if (p / n).is_file() and rec.get(n) != file_digest(p / n))


def foreign_entries(path: Path, own_names: Collection[str]) -> list[str]:
    """Names in directory ``path`` that are neither :data:`MARKER` nor in ``own_names`` (sorted)."""
    return sorted(e.name for e in Path(path).iterdir() if e.name != MARKER and e.name not in own_names)


def resolve_link(path: str | Path, option: str = "--out") -> Path:
    """``path`` with a symbolic link in its last component followed (a dangling link is refused)."""
    p = Path(path)
    if not p.is_symlink():
        return p
    target = p.resolve()
    if not os.path.lexists(target):
        raise MmslamError(f"{option} {p}: is a symbolic link to {target}, which does not exist; give a real path")
    return target


def check_target(path: str | Path, kind: str, force: bool = False, *, protect: tuple[Path, ...] = (),
                 option: str = "--out", accept: "Callable[[Path], bool] | None" = None,
                 own_names: Collection[str] | None = None, is_dir: bool = True,
                 recognise: "Callable[[Path], bool] | None" = None, writes: Collection[str] = ()) -> Path:
    """Raise a one-line :class:`MmslamError` unless ``path`` may be (re)written as a ``kind`` output.

    Directory outputs (``is_dir``): allowed are a missing path, an empty directory, or a directory
    whose marker says ``kind`` (with ``own_names``: holding nothing else than those names, for an
    output replaced as a whole; and each of ``writes``, the names the command is about to write, absent
    or as mmslam wrote it: :func:`edited_entries`). ``accept(path)`` may recognise outputs of ``kind`` written before
    markers existed (e.g. a folder of caches). File outputs (``not is_dir``): a missing path or a
    file ``recognise(path)`` says mmslam wrote. A symbolic link is followed (:func:`resolve_link`).
    The paths in ``protect`` (e.g. the input cache) and their ancestors or descendants are never
    targets. ``force`` changes nothing here (see the module docstring); it is accepted so that
    callers pass their option through. Returns the path to write (the link's target for a link).
    """
    del force
    out = Path(path)
    res = out.resolve()
    for p in protect:
        pr = Path(p).resolve()
        if res == pr or pr in res.parents or res in pr.parents:
            raise MmslamError(f"{option} {out}: overlaps the input {p}; choose another output path")
    real = resolve_link(out, option)
    shown = f"{out} (a link to {real})" if real != out else f"{out}"
    if not os.path.lexists(real):
        return real
    if is_dir:
        if not real.is_dir():
            raise MmslamError(f"{option} {shown}: exists and is a file, not a folder; choose another path "
                              f"({NEVER})")
        mine = output_kind(real)
        if mine == kind or (mine is None and accept is not None and accept(real)):
            extra = foreign_entries(real, own_names) if own_names is not None else []
            if extra:
                raise MmslamError(f"{option} {shown}: holds {', '.join(extra[:3])}{' ...' if len(extra) > 3 else ''}, "
                                  f"which mmslam did not write; move them out or choose another path ({NEVER})")
            edited = edited_entries(real, writes)
            if edited:
                raise MmslamError(f"{option} {shown}: {', '.join(edited[:3])}{' ...' if len(edited) > 3 else ''} "
                                  f"changed or appeared after mmslam wrote this folder; move "
                                  f"{'it' if len(edited) == 1 else 'them'} out or choose another path ({NEVER})")
            return real
        if mine is None and not any(real.iterdir()):
            return real
        what = f"an mmslam {mine} output, not a {kind} output" if mine else "a folder mmslam did not write"
        raise MmslamError(f"{option} {shown}: exists and is {what}; choose a new or empty folder ({NEVER})")
    if real.is_dir():
        raise MmslamError(f"{option} {shown}: is a folder; give a file name")
    if recognise is not None and recognise(real):
        return real
    raise MmslamError(f"{option} {shown}: exists and is a file mmslam did not write; choose another path "
                      f"({NEVER})")


def replace_dir(tmp: Path, out: Path, kind: str, force: bool = False, *,
                own_names: Collection[str] | None = None, writes: Collection[str] = ()) -> None:
    """Move the finished directory ``tmp`` to ``out``, replacing ``out`` only as :func:`check_target` allows.

    ``own_names``: the names an output of ``kind`` holds; an old ``out`` holding anything else is
    refused (so only files mmslam wrote are deleted), and so is one whose files among ``writes`` differ from
    what mmslam wrote (:func:`edited_entries`). A symbolic link at ``out`` stays and then points to the new
    directory.
    """
    real = check_target(out, kind, force, own_names=own_names, writes=writes)
    if os.path.lexists(real):
        old = real.with_name(f".{real.name}.old-{os.getpid()}")
        os.replace(real, old)
        try:
            os.replace(tmp, real)
        except BaseException:
            os.replace(old, real)
            raise
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, real)


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
    A symbolic link at ``path`` is followed (the link stays, its target is replaced).
    """
    import tempfile

    path = resolve_link(path, "output")  # a link stays a link: its target is written
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


def check_file_target(path: str | Path, kind: str, recognise: "Callable[[Path], bool]", option: str = "--out",
                      protect: tuple[Path, ...] = ()) -> Path:
    """Check a file target before any computation: its directory exists, and the file is missing or one
    ``recognise(path)`` says mmslam wrote as ``kind`` (:func:`check_target`); a one-line :class:`MmslamError`
    otherwise. Returns the path to write (a link's target)."""
    p = Path(path)
    if not resolve_link(p, option).parent.is_dir():
        raise MmslamError(f"{option} {p}: the directory {p.parent} does not exist; create it first")
    return check_target(p, kind, option=option, protect=protect, is_dir=False, recognise=recognise)


def check_figure_target(path: str | Path, force: bool = False, option: str = "--out",
                        formats: tuple[str, ...] = FIGURE_FORMATS) -> str:
    """Check a figure file target before any computation; returns its format.

    Allowed: a missing file, or a figure mmslam wrote before (:func:`is_mmslam_figure`); any other
    file, a directory, or what a symbolic link points to when it is no mmslam figure is refused,
    with or without ``force`` (see the module docstring). The parent directory must exist.
    """
    if resolve_link(Path(path), option).is_dir():  # before the suffix: a folder has none to name
        raise MmslamError(f"{option} {path}: is a folder; give a figure file name ending in "
                          f"{', '.join('.' + f for f in formats)}")
    fmt = figure_format(path, option, formats)
    check_file_target(path, "figure", is_mmslam_figure, option=option)
    return fmt


# ====================================================================== tagged .npz files
NPZ_TAG = "mmslam_output"
"""Name of the array (a string: the kind) that marks an ``.npz`` file as written by mmslam."""


def npz_kind(path: str | Path) -> str | None:
    """The kind in ``path``'s :data:`NPZ_TAG` entry (``None`` if it is no mmslam ``.npz``); reads only that entry."""
    import zipfile

    import numpy as np

    try:
        with zipfile.ZipFile(path) as z, z.open(f"{NPZ_TAG}.npy") as f:
            return str(np.lib.format.read_array(f, allow_pickle=False))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return None


def check_npz_target(path: str | Path, kind: str, force: bool = False, option: str = "--out",
                     protect: tuple[Path, ...] = ()) -> Path:
    """Check an ``.npz`` file target: missing, or an mmslam ``.npz`` of ``kind``; refused otherwise (any ``force``)."""
    p = Path(path)
    if p.suffix != ".npz":
        raise MmslamError(f"{option} {p}: expected a file name ending in .npz")
    other = npz_kind(p) if p.is_file() else None
    if other is not None and other != kind:  # mmslam's, but another command's output: say which
        raise MmslamError(f"{option} {p}: exists and is an mmslam {other} file, not a {kind} file; choose another "
                          "path (mmslam replaces a file only with the same kind of output)")
    return check_file_target(p, kind, lambda q: npz_kind(q) == kind, option=option, protect=protect)


def npz_bytes(kind: str, compressed: bool = False, **arrays: object) -> bytes:
    """``numpy.savez`` of ``arrays`` plus the :data:`NPZ_TAG` entry ``kind``, as bytes (for :func:`atomic_write_bytes`)."""
    import io

    import numpy as np

    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays, **{NPZ_TAG: np.array(kind)})
    return buf.getvalue()


def save_figure(fig: object, path: str | Path, dpi: int = 120, **kwargs: object) -> Path:
    """Write matplotlib ``fig`` atomically in the format of ``path``'s suffix, tagged as an mmslam figure.

    An existing file is replaced only if it is a figure mmslam wrote (one-line error otherwise)."""
    import io

    from mmslam import __version__

    p = Path(path)
    fmt = figure_format(p)
    if os.path.lexists(p) and not is_mmslam_figure(resolve_link(p)):  # the last-moment check (callers check first)
        raise MmslamError(f"{p}: exists and is not a figure mmslam wrote; choose another path ({NEVER})")
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
