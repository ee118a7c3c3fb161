"""User-facing errors.

Every error a user can cause (bad config, missing cache, NaN in data, ...) is raised as a
:class:`MmslamError` whose message is one line naming the thing and the fix. The CLI prints
``error: <message>`` and exits with :attr:`MmslamError.exit_code` (2 by default); no traceback.
"""
from __future__ import annotations


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
