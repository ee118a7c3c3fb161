"""User-facing errors.

Every error a user can cause (bad config, missing cache, NaN in data, ...) is raised as a
:class:`MmslamError` whose message is one line naming the thing and the fix. The CLI prints
``error: <message>`` and exits with :attr:`MmslamError.exit_code` (2 by default); no traceback.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator


class MmslamError(Exception):
    """A one-line, user-actionable error. ``exit_code`` is what the CLI exits with."""

    exit_code: int = 2

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class ConfigError(MmslamError):
    """A scenario / configuration file is invalid (unknown key, wrong type, bad value)."""


class CacheError(MmslamError):
    """A path cache or results directory is missing, stale, corrupt or of another schema."""


class BackendError(MmslamError):
    """No usable ray-tracing backend (e.g. no LLVM >= 16 for Dr.Jit on the CPU)."""


class Interrupted(BaseException):
    """Ctrl-C (SIGINT): the CLI prints ``interrupted: <message>`` and exits 130.

    The message says what was kept and how to resume. A :class:`BaseException` like
    :class:`KeyboardInterrupt`, so ``except Exception`` clean-up code never swallows it.
    """

    exit_code: int = 130
    DEFAULT = "finished work is kept (atomic writes); re-run the same command to resume"

    def __init__(self, message: str = "") -> None:
        super().__init__(message or self.DEFAULT)


_INTERRUPT_SEEN = False


def note_interrupt(seen: bool = True) -> None:
    """Record that Ctrl-C arrived (the CLI's SIGINT handler calls this before raising); ``False`` resets."""
    global _INTERRUPT_SEEN
    _INTERRUPT_SEEN = seen


def was_interrupted(exc: BaseException) -> bool:
    """True if ``exc`` is, or was caused by, Ctrl-C.

    Some libraries re-raise an exception raised inside their callbacks as another type (Dr.Jit's
    ``dr.while_loop`` turns it into ``RuntimeError``), so the chain is searched, and an exception
    raised after the SIGINT handler ran counts too.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, (KeyboardInterrupt, Interrupted)):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return _INTERRUPT_SEEN


def check_interrupt() -> None:
    """Raise :class:`Interrupted` if Ctrl-C arrived and was swallowed or deferred (call between work units)."""
    if _INTERRUPT_SEEN:
        raise Interrupted()


@contextlib.contextmanager
def deferred_sigint() -> Iterator[None]:
    """Within the block, Ctrl-C is noted instead of raised; on leaving it, :class:`Interrupted` is raised.

    For calls into C++ (Sionna / Mitsuba / Dr.Jit) that cannot unwind a Python exception raised by a
    signal handler (it aborts the process or is re-raised as another type). A second Ctrl-C raises at
    once. Does nothing outside the main thread or when SIGINT is not handled by Python's default or the
    CLI's handler (e.g. ignored).
    """
    import signal
    import threading

    old = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if old is not signal.default_int_handler and not getattr(old, "mmslam_raises", False):
        yield
        return
    pending: list[int] = []

    def note(signum: int, frame: object) -> None:
        note_interrupt()
        if pending:
            raise Interrupted()
        pending.append(signum)

    signal.signal(signal.SIGINT, note)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)  # type: ignore[arg-type]
    if pending:
        raise Interrupted()
