"""Interval statistics of the ablation summaries."""
from __future__ import annotations

import math

import numpy as np


def ci95(x: np.ndarray) -> tuple[float, float]:
    """Mean and half-width of its two-sided 95% Student-t confidence interval (NaNs dropped).

    ``n < 2`` gives a NaN half-width (no interval from one run).
    """
    from scipy.stats import t as student_t

    a = np.asarray(x, float)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return math.nan, math.nan
    if a.size < 2:
        return float(a.mean()), math.nan
    return float(a.mean()), float(student_t.ppf(0.975, a.size - 1) * a.std(ddof=1) / math.sqrt(a.size))
