"""What the ``ablate`` / ``demo`` commands check and settle before any work (CLI glue).

Every check that :func:`~mmslam.pipelines.ablate.jobs.run_ablation` would make after the trace is made here
first, so a refused run traces nothing and writes nothing.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mmslam.errors import ConfigError
from mmslam.pipelines.ablate.options import ABLATION_FILE, parse_sets
from mmslam.pipelines.ablate.store import _check_compatible, read_ablation


def particles_for(scenario: dict[str, Any] | Any, sets: Sequence[str], particles: int | None) -> int:
    """``particles``, or the ``filter.particles`` of ``scenario`` (a Scenario or its resolved dict) with
    the ``--set`` overrides applied: the one default of the particle count."""
    from mmslam.scenes.scenario import Scenario, scenario_from_resolved, with_overrides
    from mmslam.slam.filter.run import resolve_particles

    if particles is not None:
        return int(particles)
    scn = scenario if isinstance(scenario, Scenario) else scenario_from_resolved(scenario)
    return resolve_particles(with_overrides(scn, list(sets)), None)


def check_overrides(info: dict[str, Any] | Any, sets: Sequence[str], arms: Sequence[tuple[str, ...]]) -> None:
    """Validate ``sets`` + every arm on the cached scenario (bounds, names) before anything is written.

    ``info``: the cache's information (its ``scenario``: the resolved dict) or, before the trace, the
    :class:`~mmslam.scenes.scenario.Scenario` to be traced (the CLI checks the values before any work).
    """
    from mmslam.scenes.scenario import Scenario, scenario_from_resolved, with_overrides

    base = info if isinstance(info, Scenario) else scenario_from_resolved(
        info["scenario"], str(Path(info["cache_dir"]) / "manifest.json"))
    with_overrides(base, list(sets))  # an error here is --set's (a misspelt type row too: the loader's)
    for arm in arms:
        try:
            scn = with_overrides(base, list(sets) + list(arm))
        except ConfigError as e:  # the arm's own values come from --grid
            msg = str(e)
            raise ConfigError("--grid" + msg[len("--set"):] if msg.startswith("--set") else msg) from None
        if scn.geometry_hash() != base.geometry_hash():
            raise ConfigError(f"--set/--grid {', '.join(list(sets) + list(arm))}: changes the traced scenario "
                              "(the cache's truth); write it in a scenario file and trace a new cache")


def precheck_ablation(out_dir: str | Path, scenario_name: str, source: str, steps: int | None, particles: int,
                      sets: Sequence[str], scenario: dict[str, Any] | None = None) -> None:
    """Refuse, before the trace, a run that :func:`run_ablation` would refuse after it.

    An existing ablation in ``out_dir`` asked for other steps, particles (resolved: see
    :func:`particles_for`), ``--set`` values, scenario or source, or ran with other scenario settings
    (``scenario``: the resolved scenario's :meth:`~mmslam.scenes.scenario.Scenario.to_dict`, e.g. a ``[filter]``
    table edited in its file): nothing is traced (the cache is not extended) and nothing is written.
    """
    out = Path(out_dir)
    if not (out / ABLATION_FILE).is_file():
        return
    new: dict[str, Any] = {"scenario_name": scenario_name, "source": source, "particles": int(particles),
                           "sets": list(parse_sets(sets))}
    if scenario is not None:
        new["scenario"] = scenario
    if steps is not None:
        new["steps"] = int(steps)
    _check_compatible(out, read_ablation(out), new)
