"""Running the grid: the cache, the worker-side job, the driver that saves each result as it arrives."""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mmslam.errors import (ConfigError, EnvironmentFailure, Interrupted, deferred_sigint, environment_failure,
                           was_interrupted)
from mmslam.slam.specs.variants import COMPARED_WITH
from mmslam.executor import THREAD_VARS, Pool, open_pool
from mmslam.pipelines.ablate.options import (ABLATION_FILE, JOBS_DIR, Job, VARIANTS, check_grid_clash,
                                             check_run_args, default_command, is_finished, job_dir, parse_grid,
                                             parse_sets, parse_variants, plan_jobs, SUMMARY_JSON,
                                             SUMMARY_PARQUET)
from mmslam.pipelines.ablate.store import (_cache_info, _check_compatible, _check_job_meta, _holding_out_lock,
                                           _write_json, read_ablation, remove_stale_temps, start_ablation_dir)
from mmslam.pipelines.ablate.command import check_overrides, particles_for
from mmslam.pipelines.ablate.aggregation import Summary, aggregate, check_result_finite


def prepare_cache(scenario: Any, source: str, out_dir: str | Path, steps: int | None = None,
                  progress: bool = True, max_depth: int = 1, samples: int = 1_000_000,
                  seed: int = 0, cache_root: str | Path | None = None) -> Path:
    """Trace ``scenario`` with ``source`` into ``out_dir/cache``, or ``cache_root``, (reused / resumed if present).

    ``out_dir`` must be missing, empty or an ablation (:func:`start_ablation_dir`, which marks it).

    Args:
        scenario: a preset name, a TOML path or a :class:`~mmslam.scenes.scenario.Scenario`.
        source: ``analytic`` or ``sionna``.
        out_dir: the ablation directory.
        steps: steps to trace (default: the scenario's).
        progress: show the trace progress bar.
        max_depth, samples, seed: Sionna solver settings (ignored by ``analytic``); the defaults
            are those of ``mmslam trace``, so a cache traced by it under ``out_dir/cache`` is reused.
        cache_root: a folder of caches to trace into or reuse instead of ``out_dir/cache`` (e.g. the ``--out`` of
            ``mmslam trace``: the ablation then runs on the cache it wrote, and several ablations share one trace);
            a folder that is not a cache root is refused (:func:`~mmslam.raytrace.trace.check_cache_root`).

    Returns:
        The cache directory.
    """
    from mmslam.raytrace.trace import make_source, trace_scenario
    from mmslam.scenes.scenario import resolve_scenario

    scn = resolve_scenario(scenario)
    root = Path(out_dir) / "cache" if cache_root is None else Path(cache_root)
    if cache_root is not None:
        from mmslam.raytrace.trace import check_cache_root

        check_cache_root(root, option="--cache")  # a user's folder: refused before the ablation folder is made (the
        # CLI also refuses a --cache that overlaps --out before it makes that folder)
    start_ablation_dir(out_dir)  # out_dir is (or becomes) an ablation: never a user's folder (mmslam.outputs)
    with deferred_sigint():  # the Sionna scene load is C++: Ctrl-C is raised after it
        src = make_source(source, scn, max_depth=max_depth, samples=samples, seed=seed)
    return Path(trace_scenario(scn, src, root, steps=steps, progress=progress))


def run_job(cache_dir: str, variant: str, seed: int, particles: int, steps: int | None,
            overrides: Sequence[str] = (), truth_file: str | None = None) -> Any:
    """Run one filter job (in a worker process) and return its :class:`Result`.

    ``truth_file``: per-run truth (:mod:`mmslam.pipelines.truth`): the run's world is ``truth_file``
    resolved with ``seed``, traced analytically in memory; None: the cache's truth.

    Pins BLAS/OpenMP pools to one thread when ``threadpoolctl`` is available (the environment
    variables are set by the parent for the local pool; dask's nanny sets them for its workers).
    """
    for k in THREAD_VARS:
        os.environ.setdefault(k, "1")
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    from mmslam.slam.filter import run_slam

    if truth_file is None:
        return run_slam(cache_dir, variant=variant, particles=int(particles), seed=int(seed),
                        steps=None if steps is None else int(steps), overrides=tuple(overrides))
    from mmslam.pipelines.truth import truth_of_run, truth_scenario
    from mmslam.raytrace.cache import load_cache
    from mmslam.scenes.scenario import with_overrides
    from mmslam.slam.filter import run_filter

    cache = load_cache(cache_dir)
    n = int(cache.steps) if steps is None else int(steps)
    scn = truth_scenario(truth_file, int(seed), with_overrides(cache.scenario, list(overrides)))
    states, paths = truth_of_run(scn, n)
    meta = {"cache": cache.manifest.get("config_hash"), "source": cache.manifest.get("source"),
            "cache_path": str(cache.path), "overrides": list(overrides), "truth": "per_run", "truth_seed": int(seed)}
    return run_filter(scn, states, paths, variant=variant, particles=int(particles), seed=int(seed), steps=n,
                      meta=meta, source="analytic")  # truth_of_run traces the run's world analytically


def _truth_mode(out: Path, info: dict[str, Any], truth: str, truth_scenario: str | Path | None
                ) -> tuple[str, str, str | None]:
    """``(mode, note, truth file or None)`` of an ablation (see :func:`run_ablation`'s ``truth``)."""
    from mmslam.pipelines.truth import TRUTH_MODES, check_truth_file
    from mmslam.scenes.scenario import scenario_from_resolved

    if truth not in TRUTH_MODES:
        raise ConfigError(f"--truth {truth!r}: expected one of {', '.join(TRUTH_MODES)}")
    if truth == "fixed":
        return "fixed", "every run uses the cache's truth, drawn once from the scenario seed (--truth fixed)", None
    if info["source"] != "analytic":
        return "fixed", (f"{info['source']} cache: every run uses the traced truth (scenario seed); per-run truth "
                         "would need one trace per run"), None
    if truth_scenario is None:
        return "fixed", "no scenario file given (a Scenario object): every run uses the cache's truth", None
    dst = Path(truth_scenario).resolve()
    check_truth_file(dst, scenario_from_resolved(info["scenario"]))
    return "per_run", "run s draws its own truth (trajectory noise, random scatterer heights / routes) from seed s", str(dst)


@dataclass
class AblationRun:
    """What :func:`run_ablation` did.

    ``jobs`` is the asked grid, ``ran`` the jobs run now (in completion order), ``skipped`` those
    found finished; ``wall_time_s`` covers running and aggregating; ``executor`` describes the
    pool used (e.g. ``"local pool, 2 processes"``).
    """

    out_dir: Path
    jobs: list[Job]
    ran: list[Job]
    skipped: list[Job]
    wall_time_s: float
    summary: "Summary"
    executor: str = "local"


@_holding_out_lock
def run_ablation(cache_dir: str | Path, out_dir: str | Path, variants: Sequence[str] | str = VARIANTS,
                 mc: int = 10, particles: int | None = None, steps: int | None = None,
                 executor: str = "local", scheduler: str | None = None, workers: int | None = None,
                 progress: bool = True, command: str | None = None, seed0: int = 0,
                 sets: Sequence[str] = (), grid: Sequence[str] = (), truth: str = "per-run",
                 truth_scenario: str | Path | None = None) -> AblationRun:
    """Run the (variant x seed) grid on ``cache_dir``, store each job under ``out_dir/jobs``.

    Finished jobs are skipped. When all jobs are stored, :func:`aggregate` writes the summary.
    ``DIR/ablation.json`` records the grid of this call (variants x seeds); the summary and
    ``mmslam report`` cover that grid. A different trace, ``particles`` or ``steps`` than the
    stored ones is refused (use another ``out_dir``); more seeds or variants extend the grid.

    Args:
        cache_dir: a path cache (see :func:`prepare_cache`).
        out_dir: the ablation directory.
        variants: subset of :data:`VARIANTS` (a sequence or ``"a,b"``).
        mc: Monte Carlo runs per variant (seeds ``seed0..seed0+mc-1``).
        particles: particles per vehicle filter (None: the cached scenario's ``filter.particles``
            after ``sets``).
        steps: time steps to run (default: all steps in the cache).
        executor: ``local`` (process pool) or ``dask``.
        scheduler: dask scheduler address (``tcp://host:8786``); None starts a LocalCluster.
        workers: processes (local) or LocalCluster workers; default: all cores.
        progress: show a progress bar on stderr.
        command: the shell command that reproduces this ablation (stored for the report).
        seed0: first seed (check results on seeds the code was not tuned on).
        sets: ``section.key=value`` parameter overrides for every job (``--set``; filter, fusion,
            sensor and evaluation parameters; never ones that change the trace).
        grid: ``section.key=v1,v2`` (``--grid``): every variant runs once per combination of
            the listed values; the summary labels each arm ``variant[key=value,...]``.
        truth: ``per-run`` (default): on an analytic cache, run ``s`` draws its own truth from seed ``s``
            (:mod:`mmslam.pipelines.truth`; needs ``truth_scenario``); ``fixed``: every run uses the
            cache's truth. A Sionna cache, or no ``truth_scenario``, is always ``fixed``; ``config.truth``
            of the summary says which was used, ``config.truth_note`` why.
        truth_scenario: the scenario file (TOML) the cache was traced from (checked against the cache's
            geometry with the cache's seed); None on a folder holding a per-run ablation: the file it
            recorded (``ablation.json`` ``truth_scenario``), so a resume keeps its truth.

    Raises:
        MmslamError: bad arguments, a results directory made with other settings, an unreachable
            scheduler. Jobs finished before an error stay stored.
    """
    variants = parse_variants(variants)
    check_run_args(mc, particles, steps, executor, scheduler, workers, seed0)
    sets = parse_sets(sets)
    arms = parse_grid(grid)
    check_grid_clash(sets, arms)
    out = Path(out_dir)
    info = _cache_info(Path(cache_dir))
    check_overrides(info, sets, arms)
    particles = particles_for(info["scenario"], sets, particles)
    old = read_ablation(out) if (out / ABLATION_FILE).is_file() else None
    n_steps = info["cache_steps"] if steps is None else int(steps)
    if steps is None and old is not None and 0 < int(old.get("steps") or 0) <= n_steps:
        n_steps = int(old["steps"])  # resume what was asked, even if the cache has grown since
    if n_steps > info["cache_steps"]:
        raise ConfigError(f"--steps {n_steps}: the cache {info['cache_dir']} holds only "
                          f"{info['cache_steps']} steps; trace more steps first")
    if truth_scenario is None and old is not None and old.get("truth") == "per_run" and old.get("truth_scenario"):
        truth_scenario = old["truth_scenario"]  # resuming (e.g. from Python) the per-run truth the folder holds
    truth_mode, truth_note, truth_file = _truth_mode(out, info, truth, truth_scenario)
    seeds = list(range(int(seed0), int(seed0) + int(mc)))
    spec = {**info, "truth": truth_mode, "truth_note": truth_note, "truth_scenario": truth_file,
            "variants": list(variants), "mc": int(mc), "seed0": int(seed0), "seeds": seeds,
            "particles": int(particles), "steps": n_steps, "sets": list(sets), "grid": list(grid),
            "arms": [list(a) for a in arms],
            "command": command or default_command(info["scenario_name"], variants, mc, particles,
                                                  info["source"], out, steps, executor, seed0=seed0,
                                                  sets=sets, grid=grid, scheduler=scheduler)}
    if old is not None:
        _check_compatible(out, old, spec)
    start_ablation_dir(out, force=True)
    remove_stale_temps(out, (ABLATION_FILE, SUMMARY_PARQUET, SUMMARY_JSON))
    (out / JOBS_DIR).mkdir(exist_ok=True)
    _write_json(out / ABLATION_FILE, spec)

    jobs = plan_jobs(variants, mc, seed0, arms)
    done = [j for j in jobs if is_finished(out, j)]
    for j in done:
        _check_job_meta(out, j, int(particles), n_steps, sets + j.arm)
    # longest first (variants with a VS map cost more than baseline): less idle time at the end;
    # the order never changes a job's result
    pending = sorted((j for j in jobs if j not in done), key=lambda j: (j.variant == COMPARED_WITH, j.seed))
    t0 = time.perf_counter()
    ran: list[Job] = []
    desc = "nothing to run"
    if pending:
        if executor == "local" or scheduler is None:  # workers on this machine: compile once, here, not in each
            from mmslam.slam.filter.precompile import compile_for_workers

            compile_for_workers({j.variant for j in pending}, progress)
            _compile_estimator_for_workers(info, sets, {j.arm for j in pending}, progress)
        with open_pool(executor, scheduler, workers, len(pending)) as pool:
            desc = pool.describe
            ran = _drive(pool, pending, out, str(info["cache_dir"]), int(particles),
                         None if steps is None else n_steps, progress, len(done), len(jobs), sets,
                         truth_file)
    summary = aggregate(out)
    return AblationRun(out, jobs, ran, done, time.perf_counter() - t0, summary, desc)


def _compile_estimator_for_workers(info: dict[str, Any], sets: Sequence[str], arms: set[tuple[str, ...]],
                                   progress: bool) -> None:
    """Before starting workers on this machine: if some job runs ``sensor.model = "estimated"``, compile the
    channel estimator's kernels once here (the workers then load them) with a notice when they are not
    cached yet (:func:`mmslam.slam.sim.estimated_sensor.warm_up_estimator`)."""
    from mmslam.scenes.scenario import scenario_from_resolved, with_overrides

    base = scenario_from_resolved(info["scenario"])
    for arm in sorted(arms):
        scn = with_overrides(base, list(sets) + list(arm))
        if scn.sensor.model != "estimated":
            continue
        from mmslam.slam.sim.estimated_sensor import estimator_kernels_cached, warm_up_estimator

        if not estimator_kernels_cached() and progress:
            print("compiling the channel estimator's numba kernels once for this install (~20 s of CPU); "
                  "later runs load them", flush=True)
        warm_up_estimator(scn.sensor, scn.frequency_hz)
        return


def _drive(pool: Pool, pending: list[Job], out: Path, cache_dir: str, particles: int,
           steps: int | None, progress: bool, n_done: int, n_total: int, sets: Sequence[str] = (),
           truth_file: str | None = None) -> list[Job]:
    """Submit ``pending``, save each result as it arrives; cancel the rest on error.

    Ctrl-C / SIGTERM: :class:`Interrupted`; a failure of the machine or the cluster (out of memory, a
    worker killed, the Dask scheduler lost): :class:`EnvironmentFailure`. Both say how many jobs are
    kept (finished results not yet collected are saved first) and how to resume.
    """
    futs: dict[Any, Job] = {}
    ran: list[Job] = []
    bar = None
    if progress:
        from rich.console import Console
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                   TimeElapsedColumn, TimeRemainingColumn)

        bar = Progress(TextColumn("ablation [dim]{task.fields[last]}"), BarColumn(), MofNCompleteColumn(),
                       TextColumn("jobs"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                       console=Console(stderr=True))
        task = bar.add_task("jobs", total=n_total, completed=n_done, last=pool.describe)
        bar.start()
    def save(fut: Any, job: Job) -> None:
        result = fut.result()
        check_result_finite(result, f"job {job.name}", "the filter failed numerically (this is a bug); nothing "
                            "was stored for this job", exit_code=1)
        result.meta.setdefault("variant", job.variant)
        result.meta.setdefault("seed", job.seed)
        result.save(job_dir(out, job))
        ran.append(job)

    def keep_collected() -> None:
        for fut, job in futs.items():  # finished but not yet collected: keep them
            with contextlib.suppress(Exception):  # a lost scheduler cannot hand them over
                if job not in ran and fut.done() and not fut.cancelled() and fut.exception() is None:
                    save(fut, job)

    try:
        for j in pending:
            futs[pool.submit(run_job, cache_dir, j.variant, j.seed, particles, steps, tuple(sets) + j.arm,
                             truth_file, key=j.name)] = j
        for fut in pool.as_completed(list(futs)):
            job = futs[fut]
            save(fut, job)
            if bar is not None:
                bar.update(task, advance=1, last=f"{job.name} done")
    except BaseException as e:
        interrupted = was_interrupted(e)
        failure = None if interrupted else environment_failure(e)
        with contextlib.suppress(Exception):
            pool.cancel(list(futs))
        if not interrupted and failure is None:
            raise
        keep_collected()
        if bar is not None:
            bar.stop()
            bar = None
        left = len(pending) - len(ran)
        kept = (f"{n_done + len(ran)} of {n_total} jobs are kept in {out / JOBS_DIR} ({len(ran)} finished in "
                f"this run); {left} unfinished jobs were cancelled")
        if interrupted:
            raise Interrupted(f"{kept}; re-run the same command to resume") from None
        raise EnvironmentFailure(f"{failure[0]}; {kept}; {failure[1]}, then re-run the same command to resume"
                                 ) from None
    finally:
        if bar is not None:
            bar.stop()
    return ran
