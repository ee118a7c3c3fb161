"""Upper bounds of the numeric command-line options and scenario sizes, declared once.

They keep a typo (``--steps 1000000000``, ``--particles 1e9``) from running out of memory after
minutes of work: the CLI refuses values outside them at parse time (one line, exit 2) and shows
them in ``--help``; the library functions check them too.
"""
from __future__ import annotations

MAX_STEPS = 100_000
"""Time steps of a scenario or a run."""
MAX_PARTICLES = 100_000
"""Particles per vehicle filter."""
MAX_MC = 10_000
"""Monte Carlo runs per variant."""
MAX_WORKERS = 4096
"""Worker processes."""
MAX_SAMPLES = 1_000_000_000
"""Sionna rays per source."""
MAX_SEED = 2**32 - 1
"""Largest seed (NumPy seeds are unsigned 32-bit here)."""
MAX_CHUNK_STEPS = 10_000
"""Steps per Parquet chunk of a path cache."""
COORD_MAX = 1e6
"""Largest absolute coordinate in a scenario (m)."""


def check_int(option: str, value: int | None, lo: int, hi: int, what: str = "") -> None:
    """One-line :class:`~mmslam.errors.ConfigError` unless ``value`` (if given) is in ``lo..hi``."""
    from mmslam.errors import ConfigError

    if value is not None and not lo <= int(value) <= hi:
        raise ConfigError(f"{option} {value}: expected {what + ' ' if what else ''}in {lo}..{hi}")


def span(lo: int, hi: int) -> str:
    """`` [lo..hi]`` for an option's help text."""
    return f" [{lo}..{hi}]"
