"""``mmslam demo``: the main job on the built-in default scenario, end to end.

Traces the ``paper`` preset (Sionna RT by default, ``analytic`` for the closed form; the cache
under ``OUT/cache`` is reused), runs ``baseline`` / ``cm1`` / ``proposed`` for ``mc`` Monte Carlo
runs through the ablation machinery (:mod:`mmslam.pipelines.ablate`: resumable, one process
per core), writes the summary and the HTML report (:mod:`mmslam.pipelines.report`).
"""
from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path

from mmslam.pipelines.ablate import (VARIANTS, AblationRun, check_run_args, particles_for, prepare_cache,
                                     run_ablation)

DEMO_SCENARIO = "paper"
"""The built-in default scenario (docs/design.md section 5)."""


@dataclass
class DemoResult:
    """What :func:`run_demo` produced."""

    out_dir: Path
    cache_dir: Path
    ablation: AblationRun
    report: Path
    particles: int
    """the particle count it ran with"""


def demo_command(source: str, mc: int, particles: int, out: str | Path) -> str:
    """The ``mmslam demo`` command line that reproduces a demo run."""
    return shlex.join(["mmslam", "demo", "--source", source, "--mc", str(mc), "--particles", str(particles),
                       "--out", str(out)])


def run_demo(source: str = "sionna", mc: int = 10, particles: int | None = None, out: str | Path = "out/demo",
             executor: str = "local", workers: int | None = None, progress: bool = True,
             force: bool = False) -> DemoResult:
    """Trace (or reuse) the ``paper`` preset, run odometry and the three variants ``mc`` times, write the report.

    Args:
        source: ``sionna`` (ray traced) or ``analytic`` (closed form).
        mc: Monte Carlo runs per variant (seeds ``0..mc-1``).
        particles: particles per vehicle filter (None: the ``paper`` preset's ``filter.particles``).
        out: output directory (cache, jobs, summary, figures, report).
        executor, workers: as in :func:`mmslam.pipelines.ablate.run_ablation`.
        progress: progress bars on stderr.
        force: kept for callers; a folder mmslam did not write is refused whatever it (:mod:`mmslam.outputs`).
    """
    from mmslam.pipelines.report import write_report

    check_run_args(mc, particles, None, executor, None, workers)
    from mmslam.scenes.scenario import load_preset

    particles = particles_for(load_preset(DEMO_SCENARIO), (), particles)
    from mmslam.outputs import locked
    from mmslam.pipelines.ablate import precheck_ablation, start_ablation_dir

    out = Path(out)
    with locked(out, "ablation"):
        precheck_ablation(out, DEMO_SCENARIO, source, None, particles, (), load_preset(DEMO_SCENARIO).to_dict())
        start_ablation_dir(out, force)  # checked before the trace
        cache = prepare_cache(DEMO_SCENARIO, source, out, progress=progress)
        run = run_ablation(cache, out, VARIANTS, mc=mc, particles=particles, executor=executor, workers=workers,
                           progress=progress, command=demo_command(source, mc, particles, out))
        return DemoResult(out, cache, run, write_report(out), particles)
