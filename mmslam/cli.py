"""The ``mmslam`` command line: a thin layer over the library API.

Each subpackage owns its commands in its own ``cli.py`` (``register(app)``); heavy imports
(Sionna, matplotlib) happen inside the commands, so ``mmslam --help`` is fast.
User errors (:class:`~mmslam.errors.MmslamError`) print one line ``error: ...`` and exit non-zero.
"""
from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import typer

from mmslam import __version__
from mmslam.errors import (Interrupted, MmslamError, environment_cause, interrupt_signal, note_interrupt,
                           was_interrupted)

EXIT_CODES = ("Exit codes: 0 success; 2 a user error (one line naming the thing and the fix) or an environment "
              "failure (out of memory, a lost Dask scheduler: one line naming the cause, what was kept, how to "
              "resume); 130 interrupted by Ctrl-C, 143 by SIGTERM (one line: what was kept, how to resume); 1 a "
              "bug (one line with the path of a log file holding the traceback).")

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None,
                  help="Ray-traced mmWave multipath datasets and cooperative MM-PHD-SLAM.\n\n" + EXIT_CODES)


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"mmslam {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """Ray-traced mmWave multipath datasets and cooperative MM-PHD-SLAM."""


def _register_all() -> None:
    from mmslam.pipelines import cli as pipelines_cli
    from mmslam.raytrace import cli as raytrace_cli
    from mmslam.scenes import cli as scenes_cli
    from mmslam.slam import cli as slam_cli

    scenes_cli.register(app)
    raytrace_cli.register(app)
    slam_cli.register(app)
    pipelines_cli.register(app)


_register_all()


def _log_traceback(exc: BaseException) -> Path:
    """Write ``exc``'s traceback to a fresh log file; return its path."""
    import tempfile
    import traceback

    fd, name = tempfile.mkstemp(prefix="mmslam-crash-", suffix=".log")
    with os.fdopen(fd, "w") as f:
        f.write(f"mmslam {__version__}, python {sys.version.split()[0]}\nargv: {sys.argv!r}\n\n")
        f.write("".join(traceback.format_exception(exc)))
    return Path(name)


def _interrupted(e: BaseException | None = None) -> int:
    """Print the one-line ``interrupted: ...`` (``terminated: ...`` for SIGTERM); return 128 + the signal number."""
    import signal

    msg = str(e) if isinstance(e, Interrupted) else Interrupted.DEFAULT
    sig = interrupt_signal()
    word = "terminated" if sig == signal.SIGTERM else "interrupted"
    print(f"{word}: {' '.join(msg.split())}", file=sys.stderr)
    return 128 + sig


def _raise_interrupted(signum: int, frame: object) -> None:
    note_interrupt(True, signum)
    raise Interrupted()


_raise_interrupted.mmslam_raises = True  # type: ignore[attr-defined]  (see errors.deferred_sigint)


def _late_signal(signum: int, frame: object) -> None:
    """SIGINT / SIGTERM after the command's work (while the process exits): say so and exit 128 + signum.

    Raising here would surface in the interpreter's exit code (threads joined, atexit callbacks) as a
    traceback and an exit by signal (-2); everything the command wrote is already in place.
    """
    note_interrupt(True, signum)
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    with contextlib.suppress(Exception):
        _interrupted()
        sys.stderr.flush()
    os._exit(128 + int(signum))


_SIGNALS = ("SIGINT", "SIGTERM")


def _install_signals() -> dict[int, object]:
    """Ctrl-C and SIGTERM raise :class:`Interrupted` (click would print a blank line for KeyboardInterrupt;
    SIGTERM would kill the process with nothing kept or said). Only signals left to their defaults are
    taken (Python's SIGINT handler, the system's SIGTERM action); returns those replaced."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    old: dict[int, object] = {}
    for name in _SIGNALS:
        sig = getattr(signal, name)
        h = signal.getsignal(sig)
        if h is (signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL):
            old[sig] = h
            signal.signal(sig, _raise_interrupted)
    return old


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit code.

    0 success; 2 a user error (one line ``error: ...``, no traceback) or an environment failure (out of
    memory, a lost Dask scheduler or worker: one line naming the cause); 130 interrupted by Ctrl-C, 143
    by SIGTERM (one line: what was kept, how to resume); 1 a bug (one line with the path of a log file
    holding the traceback). Called without ``argv`` (the ``mmslam`` command), a signal arriving after
    the command's work, while the process exits, still gives the one line and 130 / 143.
    """
    import signal

    note_interrupt(False)
    old = _install_signals()
    try:
        rc = app(args=argv, standalone_mode=False, prog_name="mmslam")
    except Interrupted as e:
        return _interrupted(e)
    except MmslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    except (KeyboardInterrupt, typer.Abort):
        return _interrupted()
    except typer.Exit as e:
        return int(e.exit_code or 0)
    except SystemExit as e:  # --help and explicit exits
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    except OSError as e:  # an output path that is a file, a missing or read-only directory, a full disk
        where = e.filename if e.filename is not None else "output"
        print(f"error: {where}: {e.strerror or e}; choose a writable path (parent directories must exist "
              "and not be files)", file=sys.stderr)
        return 2
    except typer.TyperException as e:  # usage errors: bad option values, missing arguments
        ctx = getattr(e, "ctx", None)
        cmd = ctx.command_path if ctx is not None else "mmslam"
        msg = " ".join(e.format_message().split()) if hasattr(e, "format_message") else str(e)
        print(f"error: {cmd}: {msg} (see '{cmd} --help')", file=sys.stderr)
        return 2
    except Exception as e:  # a bug: one line, the traceback in a log file
        if was_interrupted(e):  # Ctrl-C re-raised as another type by a library (e.g. Dr.Jit)
            return _interrupted()
        cause = environment_cause(e)
        if cause is not None:  # the machine failed, not mmslam: say what to change
            print(f"error: {cause}; finished work is kept (atomic writes): free memory or lower --particles, "
                  "--steps or --workers (or restart the Dask cluster), then re-run the same command to resume",
                  file=sys.stderr)
            return 2
        log = _log_traceback(e)
        print(f"error: internal error ({type(e).__name__}: {' '.join(str(e).split())[:200]}); this is a bug, "
              f"the traceback is in {log}", file=sys.stderr)
        return 1
    finally:
        for sig, h in old.items():
            signal.signal(sig, _late_signal if argv is None else h)  # type: ignore[arg-type]
    if rc == 130:  # click turns Ctrl-C into exit code 130 when not standalone
        return _interrupted()
    return int(rc or 0) if isinstance(rc, int) else 0


if __name__ == "__main__":
    sys.exit(main())
