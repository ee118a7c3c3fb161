"""Per-run truth for the analytic source (issue 23): each Monte Carlo run draws its own true world.

A trace's truth (the vehicles' trajectories with process noise, scatterer heights drawn from
``z_range``, random street routes) is drawn from the *scenario* seed, so a cache holds one truth
and every Monte Carlo run on it shares that one trajectory: every confidence interval is then
conditional on it. With per-run truth (``mmslam ablate --truth per-run``, the default for the
analytic source) run ``s`` resolves the scenario file again with seed ``s``
(:func:`mmslam.scenes.scenario.load_scenario` with ``seed_override``: trajectory process noise,
SP heights and routes drawn from ``s``) and traces it in memory with the closed-form source; the
filter's own random streams (``SeedSequence(s)`` in :mod:`mmslam.slam.filter.run`) are independent
of those draws. A Sionna cache cannot do this without a re-trace per run, so its truth stays the
traced one (``fixed``); the summary says which (``config.truth``).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import ConfigError

TRUTH_MODES = ("per-run", "fixed")


def truth_scenario(truth_file: str | Path, seed: int, base: Any) -> Any:
    """The scenario of run ``seed``: ``base`` (the cache's scenario with the run's overrides) with the
    randomly drawn geometry (scatterers, vehicles) and the seed of ``truth_file`` resolved with ``seed``."""
    from mmslam.scenes.scenario import load_scenario

    drawn = load_scenario(truth_file, seed_override=int(seed))
    return dataclasses.replace(base, scatterers=drawn.scatterers, vehicles=drawn.vehicles, seed=drawn.seed)


def truth_of_run(scn: Any, steps: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """True states ``(steps, n_veh, 7)`` and the analytic ``paths`` table of ``scn`` (its seed's truth)."""
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.scenes.trajectory import true_trajectories

    states = true_trajectories(scn, steps)
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(steps)]
    return states, {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


def check_truth_file(truth_file: str | Path, cache_scenario: Any) -> None:
    """Refuse a truth file that does not resolve, with the cache's seed, to the cache's geometry."""
    from mmslam.scenes.scenario import load_scenario

    again = load_scenario(truth_file, seed_override=int(cache_scenario.seed))
    if again.geometry_hash() != cache_scenario.geometry_hash():
        raise ConfigError(f"{truth_file}: its scene is not the cache's (geometry hash {again.geometry_hash()} vs "
                          f"{cache_scenario.geometry_hash()}); use --truth fixed or a new --out")
