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


class EnvironmentFailure(MmslamError):
    """The machine or the cluster failed, not mmslam or its input: out of memory, a worker process
    killed by the system, the Dask scheduler lost. The message names the cause, what was kept and how
    to resume; exit 2 like a user error (fix the environment, then re-run the same command)."""


class Interrupted(BaseException):
    """Ctrl-C (SIGINT) or SIGTERM: the CLI prints ``interrupted: <message>`` (``terminated: ...`` for
    SIGTERM) and exits 128 + the signal number (130, 143).

    The message says what was kept and how to resume. A :class:`BaseException` like
    :class:`KeyboardInterrupt`, so ``except Exception`` clean-up code never swallows it.
    """

    exit_code: int = 130
    DEFAULT = "finished work is kept (atomic writes); re-run the same command to resume"

    def __init__(self, message: str = "") -> None:
        super().__init__(message or self.DEFAULT)


_INTERRUPT_SEEN = False
_INTERRUPT_SIGNAL: int | None = None

INTERRUPT_SIGNALS: tuple[str, ...] = ("SIGINT", "SIGTERM")
"""Signals handled like Ctrl-C (keep what is done, say how to resume, exit 128 + signal number)."""


def note_interrupt(seen: bool = True, signum: int | None = None) -> None:
    """Record that Ctrl-C (or ``signum``, e.g. SIGTERM) arrived (the CLI's handler calls this before
    raising); the first signal is kept for the exit code. ``False`` resets."""
    global _INTERRUPT_SEEN, _INTERRUPT_SIGNAL
    _INTERRUPT_SEEN = seen
    if not seen:
        _INTERRUPT_SIGNAL = None
    elif _INTERRUPT_SIGNAL is None and signum is not None:
        _INTERRUPT_SIGNAL = int(signum)


def interrupt_signal() -> int:
    """The signal that interrupted this run (SIGINT when none was recorded, e.g. a KeyboardInterrupt)."""
    import signal

    return int(_INTERRUPT_SIGNAL) if _INTERRUPT_SIGNAL is not None else int(signal.SIGINT)


def environment_cause(exc: BaseException) -> str | None:
    """A short phrase if ``exc`` (or an exception in its chain) is a failure of the machine or the
    cluster rather than of mmslam or its input; ``None`` otherwise.

    Out of memory (:class:`MemoryError`), a worker process that died (``BrokenProcessPool``: killed by
    the system, e.g. the out-of-memory killer), a lost Dask scheduler or worker (``distributed``'s
    comm / cancellation errors). Judged by type only, so nothing here imports ``distributed``.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        name, module = type(e).__name__, type(e).__module__ or ""
        if isinstance(e, MemoryError):
            return f"out of memory ({name}: {_short(e)})"
        if name == "BrokenProcessPool":
            return ("a worker process died (killed by the system, e.g. out of memory, or by a signal sent "
                    "to it alone)")
        if module.startswith(("distributed", "tornado")) and name in (
                "CommClosedError", "FutureCancelledError", "CancelledError", "StreamClosedError", "KilledWorker",
                "TimeoutError", "FutureLost"):
            return f"lost the Dask cluster ({name}: {_short(e)})"
        e = e.__cause__ or e.__context__
    return None


def _short(e: BaseException) -> str:
    msg = " ".join(str(e).split()) or type(e).__name__
    return msg if len(msg) <= 150 else msg[:147] + "..."


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
    """Within the block, Ctrl-C (and SIGTERM) is noted instead of raised; on leaving it, :class:`Interrupted`
    is raised.

    For calls into C++ (Sionna / Mitsuba / Dr.Jit) that cannot unwind a Python exception raised by a
    signal handler (it aborts the process or is re-raised as another type), and for steps that must not
    be cut in half (starting a worker process). A second signal raises at once. Does nothing outside the
    main thread; a signal is deferred only when Python's default SIGINT handler or the CLI's handler
    handles it (not when it is ignored or left to the system).
    """
    import signal
    import threading

    old: list[tuple[int, object]] = []
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            h = signal.getsignal(sig)
            if (sig == signal.SIGINT and h is signal.default_int_handler) or getattr(h, "mmslam_raises", False):
                old.append((sig, h))
    if not old:
        yield
        return
    pending: list[int] = []

    def note(signum: int, frame: object) -> None:
        note_interrupt(True, signum)
        if pending:
            raise Interrupted()
        pending.append(signum)

    for sig, _ in old:
        signal.signal(sig, note)
    try:
        yield
    finally:
        for sig, h in old:
            signal.signal(sig, h)  # type: ignore[arg-type]
    if pending:
        raise Interrupted()
