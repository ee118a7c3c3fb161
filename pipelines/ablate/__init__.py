"""Monte Carlo ablation: the grid of (variant x seed) filter runs on one cached trace.

An ablation lives in one output directory ``DIR``::

    DIR/cache/<config>/          the path cache (written by :func:`prepare_cache`)
    DIR/ablation.json            what was asked (cache, variants, seeds, particles, steps, command)
    DIR/jobs/<variant>-seed<k>/  one finished filter run each (:class:`~mmslam.slam.filter.result.Result`)
    DIR/summary.parquet          per-step mean / std / RMS over seeds (see :func:`aggregate`)
    DIR/summary.json             the same table, the headline table and the configuration

A job is ``(variant, seed)``; its seed is explicit, so its result does not depend on the
executor, the worker count or the order in which jobs finish. Each finished job is saved at once
(atomically, by the parent process) and re-running the same ablation skips finished jobs: a
``kill -9`` loses at most the jobs in flight.

Executors: ``local`` is a process pool (``spawn`` context, BLAS/OpenMP threads pinned to 1);
``dask`` submits to a ``dask.distributed`` scheduler at an address, or to a ``LocalCluster``
started here (processes, one thread each) when no address is given. Workers of a remote
scheduler must see ``DIR`` at the same path (shared file system) and have mmslam installed.

Library use (e.g. from a notebook)::

    from mmslam.pipelines.ablate import prepare_cache, run_ablation
    cache = prepare_cache("paper", "analytic", "out/abl")
    run = run_ablation(cache, "out/abl", mc=10, particles=300)
    run.summary.headline

Package layout (each module imports only those listed before it):

- :mod:`~mmslam.pipelines.ablate.executors`: where jobs run (local process pool, Dask);
- :mod:`~mmslam.pipelines.ablate.options`: variants, ``--set`` / ``--grid`` arms, the job grid, names on disk;
- :mod:`~mmslam.pipelines.ablate.store`: ``ablation.json``, stored jobs' metadata, the directory marker and lock;
- :mod:`~mmslam.pipelines.ablate.command`: the checks the CLI makes before any work;
- :mod:`~mmslam.pipelines.ablate.aggregation`: the summary over seeds (``summary.parquet`` / ``.json``);
- :mod:`~mmslam.pipelines.ablate.jobs`: the cache, the worker-side job and the driver (:func:`run_ablation`).

Every public name is re-exported here: ``from mmslam.pipelines.ablate import run_ablation`` keeps working.
"""
from __future__ import annotations

from mmslam.errors import CacheError, ConfigError, Interrupted, MmslamError  # noqa: F401  (re-exported)
from mmslam.pipelines.ablate.aggregation import (NEES_CONSISTENT, PAIRED_QUANTITIES, SCORED, Summary,  # noqa: F401
                                                 _add_intervals, _fusion_start, _run_scores, aggregate, ci95, load_jobs,
                                                 load_summary, paired_steps, spec_arms, upload_steps)
from mmslam.pipelines.ablate.command import check_overrides, particles_for, precheck_ablation  # noqa: F401
from mmslam.pipelines.ablate.executors import (CONNECT_TIMEOUT_S, DASK_SCHEMES, check_dask_address,  # noqa: F401
                                               connect_dask)
from mmslam.pipelines.ablate.jobs import AblationRun, _truth_mode, prepare_cache, run_ablation, run_job  # noqa: F401
from mmslam.pipelines.ablate.options import (ABLATION_FILE, ALL_VEHICLES, EXECUTORS, JOBS_DIR,  # noqa: F401
                                             METRIC_QUANTITIES, STATE_QUANTITIES, SUMMARY_JSON, SUMMARY_PARQUET,
                                             TYPES, VARIANTS, Job, arm_label, check_grid_clash, check_run_args,
                                             default_command, is_finished, job_dir, parse_grid, parse_label,
                                             parse_sets, parse_variants, plan_jobs)
from mmslam.pipelines.ablate.store import ABLATION_KIND, read_ablation, start_ablation_dir  # noqa: F401
from mmslam.slam.specs.variants import BUILTIN_VARIANTS, COMPARED_WITH, REFERENCES, variant_names  # noqa: F401
from mmslam.slam.specs.variants import VARIANTS as FILTER_VARIANTS  # noqa: F401
