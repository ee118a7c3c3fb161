"""Monte Carlo ablation: the grid of (variant x seed) filter runs on one cached trace.

An ablation lives in one output directory ``DIR``::

    DIR/cache/<config>/          the path cache (written by :func:`prepare_cache`)
    DIR/ablation.json            what was asked (cache, variants, seeds, particles, steps, command)
    DIR/jobs/<variant>-seed<k>/  one finished filter run each (:class:`~mmslam.slam.result.Result`)
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
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import CacheError, ConfigError, MmslamError

VARIANTS: tuple[str, ...] = ("baseline", "cm1", "proposed")
"""Filter variants, in the order they are plotted (DESIGN.md section 6)."""

EXECUTORS: tuple[str, ...] = ("local", "dask")
TYPES: tuple[str, ...] = ("VA", "SP", "VS")
METRIC_QUANTITIES: tuple[str, ...] = ("gospa", "loc", "missed", "false", "n_est", "n_true")
STATE_QUANTITIES: tuple[str, ...] = ("pos_err", "heading_err", "bias_err")
ALL_VEHICLES = "all"
"""``map`` value of the state rows pooled over all vehicles."""

ABLATION_FILE = "ablation.json"
SUMMARY_PARQUET = "summary.parquet"
SUMMARY_JSON = "summary.json"
JOBS_DIR = "jobs"
CONNECT_TIMEOUT_S = 3.0
"""How long to wait for a dask scheduler before giving up (seconds)."""

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                "VECLIB_MAXIMUM_THREADS", "BLIS_NUM_THREADS")


# ====================================================================== jobs and validation
@dataclass(frozen=True, order=True)
class Job:
    """One filter run: a variant and an explicit seed."""

    variant: str
    seed: int

    @property
    def name(self) -> str:
        """Directory name under ``DIR/jobs``: ``<variant>-seed<k>``."""
        return f"{self.variant}-seed{self.seed}"


def job_dir(out_dir: str | Path, job: Job) -> Path:
    """Where ``job``'s result is stored."""
    return Path(out_dir) / JOBS_DIR / job.name


def parse_variants(spec: str | Sequence[str]) -> tuple[str, ...]:
    """``"baseline,cm1"`` or a sequence -> validated tuple (order kept, no duplicates)."""
    items = [s.strip() for s in spec.split(",")] if isinstance(spec, str) else [str(s).strip() for s in spec]
    items = [s for s in items if s]
    if not items:
        raise ConfigError(f"--variants: empty; expected a comma-separated subset of {','.join(VARIANTS)}")
    for v in items:
        if v not in VARIANTS:
            raise ConfigError(f"--variants: unknown variant '{v}'; expected a comma-separated subset of "
                              f"{','.join(VARIANTS)}")
    dup = sorted({v for v in items if items.count(v) > 1})
    if dup:
        raise ConfigError(f"--variants: '{dup[0]}' given twice; list each variant once")
    return tuple(items)


def check_run_args(mc: int, particles: int, steps: int | None, executor: str,
                   scheduler: str | None, workers: int | None) -> None:
    """Reject bad numbers / executor settings with a one-line :class:`ConfigError`."""
    if int(mc) < 1:
        raise ConfigError(f"--mc {mc}: expected at least 1 Monte Carlo run")
    if int(particles) < 1:
        raise ConfigError(f"--particles {particles}: expected at least 1 particle")
    if steps is not None and int(steps) < 1:
        raise ConfigError(f"--steps {steps}: expected a positive number of time steps")
    if executor not in EXECUTORS:
        raise ConfigError(f"--executor {executor}: expected one of {', '.join(EXECUTORS)}")
    if scheduler and executor != "dask":
        raise ConfigError("--scheduler is only used with --executor dask; add --executor dask or drop it")
    if workers is not None and int(workers) < 1:
        raise ConfigError(f"--workers {workers}: expected at least 1 worker")


def plan_jobs(variants: Sequence[str], mc: int) -> list[Job]:
    """The grid ``variants x seeds 0..mc-1``, variant-major."""
    return [Job(v, s) for v in variants for s in range(int(mc))]


def is_finished(out_dir: str | Path, job: Job) -> bool:
    """True if ``job``'s result directory is complete (``Result.save`` is atomic)."""
    d = job_dir(out_dir, job)
    return (d / "meta.json").is_file() and all((d / f"{t}.parquet").is_file()
                                               for t in ("vehicles", "metrics", "landmarks"))


# ====================================================================== the cache
def prepare_cache(scenario: Any, source: str, out_dir: str | Path, steps: int | None = None,
                  progress: bool = True, max_depth: int = 1, samples: int = 1_000_000,
                  seed: int = 0) -> Path:
    """Trace ``scenario`` with ``source`` into ``out_dir/cache`` (reused / resumed if present).

    Args:
        scenario: a preset name, a TOML path or a :class:`~mmslam.scenes.scenario.Scenario`.
        source: ``analytic`` or ``sionna``.
        out_dir: the ablation directory.
        steps: steps to trace (default: the scenario's).
        progress: show the trace progress bar.
        max_depth, samples, seed: Sionna solver settings (ignored by ``analytic``); the defaults
            are those of ``mmslam trace``, so a cache traced by it under ``out_dir/cache`` is reused.

    Returns:
        The cache directory.
    """
    from mmslam.raytrace.trace import make_source, trace_scenario
    from mmslam.scenes.scenario import resolve_scenario

    scn = resolve_scenario(scenario)
    src = make_source(source, scn, max_depth=max_depth, samples=samples, seed=seed)
    return Path(trace_scenario(scn, src, Path(out_dir) / "cache", steps=steps, progress=progress))


# ====================================================================== the worker side
def run_job(cache_dir: str, variant: str, seed: int, particles: int, steps: int | None) -> Any:
    """Run one filter job (in a worker process) and return its :class:`Result`.

    Pins BLAS/OpenMP pools to one thread when ``threadpoolctl`` is available (the environment
    variables are set by the parent for the local pool; dask's nanny sets them for its workers).
    """
    for k in _THREAD_VARS:
        os.environ.setdefault(k, "1")
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    from mmslam.slam.filter import run_slam

    return run_slam(cache_dir, variant=variant, particles=int(particles), seed=int(seed),
                    steps=None if steps is None else int(steps))


@contextlib.contextmanager
def _single_thread_env() -> Iterator[None]:
    """Set the BLAS/OpenMP thread variables to 1 while worker processes are started."""
    old = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _worker_init(parent_pid: int) -> None:
    """Local-pool worker start-up: one BLAS thread, and exit when the parent process is gone.

    A ``kill -9`` of the parent would otherwise leave the spawned workers blocked forever on
    their task queue (they hold its write end too, so they never see EOF).
    """
    import threading

    for k in _THREAD_VARS:
        os.environ[k] = "1"

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="mmslam-parent-watch", daemon=True).start()


class _Pool:
    """Uniform submit / as_completed / cancel over concurrent.futures and dask.distributed."""

    def __init__(self, submit: Callable[..., Any], as_completed: Callable[[list], Iterator[Any]],
                 cancel: Callable[[list], None], n_workers: int, describe: str) -> None:
        self.submit = submit
        self.as_completed = as_completed
        self.cancel = cancel
        self.n_workers = n_workers
        self.describe = describe


@contextlib.contextmanager
def _local_pool(workers: int | None, n_jobs: int) -> Iterator[_Pool]:
    import concurrent.futures as cf
    import multiprocessing as mp

    n = max(1, min(int(workers or os.cpu_count() or 1), n_jobs))
    with _single_thread_env():
        ex = cf.ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn"),
                                    initializer=_worker_init, initargs=(os.getpid(),))
        try:
            yield _Pool(lambda fn, *a: ex.submit(fn, *a), lambda fs: cf.as_completed(fs),
                        lambda fs: [f.cancel() for f in fs], n, f"local pool, {n} processes")
        except BaseException:
            ex.shutdown(wait=False, cancel_futures=True)
            raise
        else:
            ex.shutdown(wait=True)


def _one_line(e: BaseException) -> str:
    msg = " ".join(str(e).split()) or type(e).__name__
    return msg if len(msg) <= 200 else msg[:197] + "..."


def connect_dask(scheduler: str, timeout_s: float = CONNECT_TIMEOUT_S) -> Any:
    """A ``dask.distributed.Client`` for ``scheduler``; one-line :class:`MmslamError` if unreachable."""
    try:
        from distributed import Client
    except ImportError:
        raise MmslamError("--executor dask needs dask.distributed; install it with "
                          "`pip install 'mmslam[dask]'` or use --executor local") from None
    import logging

    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    try:
        return Client(scheduler, timeout=f"{timeout_s}s", set_as_default=False)
    except Exception as e:  # OSError / TimeoutError / ValueError for a malformed address
        raise MmslamError(f"cannot reach the dask scheduler at {scheduler} ({_one_line(e)}); start it "
                          "(`dask scheduler`) and check the address, or drop --scheduler to start a "
                          "local cluster") from None


@contextlib.contextmanager
def _dask_pool(scheduler: str | None, workers: int | None, n_jobs: int) -> Iterator[_Pool]:
    import uuid

    cluster = None
    if scheduler:
        client = connect_dask(scheduler)
    else:
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise MmslamError("--executor dask needs dask.distributed; install it with "
                              "`pip install 'mmslam[dask]'` or use --executor local") from None
        import logging

        n = max(1, min(int(workers or os.cpu_count() or 1), n_jobs))
        with _single_thread_env():
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster, set_as_default=False)
    try:
        from distributed import as_completed

        n_workers = len(client.scheduler_info().get("workers", {}))
        if n_workers == 0:
            import sys

            print(f"note: the dask scheduler at {scheduler} has no workers yet; jobs wait until workers "
                  "join (`dask worker <address>`)", file=sys.stderr)
        token = uuid.uuid4().hex[:8]
        where = "local cluster" if cluster is not None else scheduler

        def submit(fn: Callable[..., Any], *args: Any) -> Any:
            key = f"mmslam-{args[1]}-seed{args[2]}-{token}"
            return client.submit(fn, *args, pure=False, key=key)

        yield _Pool(submit, lambda fs: as_completed(fs, loop=client.loop), lambda fs: client.cancel(fs), n_workers,
                    f"dask ({where}), {n_workers} workers")
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# ====================================================================== the ablation
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


def _cache_info(cache_dir: Path) -> dict[str, Any]:
    from mmslam.raytrace.cache import load_cache

    c = load_cache(cache_dir)
    return {"cache_dir": str(Path(c.path).resolve()), "config_hash": c.manifest.get("config_hash"),
            "source": c.manifest.get("source"), "scenario": c.scenario.to_dict(),
            "scenario_name": c.scenario.name, "cache_steps": int(c.steps),
            "vehicle_names": list(c.vehicle_names)}


def read_ablation(out_dir: str | Path) -> dict[str, Any]:
    """``DIR/ablation.json``; :class:`CacheError` if ``DIR`` holds no ablation."""
    p = Path(out_dir)
    f = p / ABLATION_FILE
    if not p.is_dir():
        raise CacheError(f"{p}: no such results directory; run `mmslam ablate <scenario> --out {p}` "
                         "(or `mmslam demo`) first")
    if not f.is_file():
        raise CacheError(f"{p}: not an ablation results directory (no {ABLATION_FILE}); run "
                         f"`mmslam ablate <scenario> --out {p}` first")
    try:
        return json.loads(f.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CacheError(f"{f}: unreadable ({_one_line(e)}); delete it and re-run the ablation") from None


def _write_json(path: Path, data: Any) -> None:
    """Atomic JSON write (temp file + os.replace)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2, default=_jsonable, allow_nan=True))
    os.replace(tmp, path)


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def _check_compatible(out_dir: Path, old: dict[str, Any], new: dict[str, Any]) -> None:
    for key, flag in (("config_hash", "the trace (scenario / source)"), ("particles", "--particles"),
                      ("steps", "--steps")):
        if old.get(key) != new.get(key):
            raise ConfigError(f"{out_dir} holds an ablation with {key}={old.get(key)} but this run asks "
                              f"{key}={new.get(key)} ({flag}); use another --out or delete "
                              f"{out_dir / JOBS_DIR}")


def _check_job_meta(out_dir: Path, job: Job, particles: int, steps: int) -> None:
    meta_path = job_dir(out_dir, job) / "meta.json"
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CacheError(f"{meta_path}: unreadable ({_one_line(e)}); delete {meta_path.parent} and re-run") from None
    want = {"variant": job.variant, "seed": job.seed, "particles": particles}
    for k, v in want.items():
        if k in meta and meta[k] != v:
            raise CacheError(f"{meta_path.parent}: holds {k}={meta[k]}, expected {v}; delete that "
                             "directory and re-run")
    if meta.get("steps") is not None and meta["steps"] != steps:
        raise CacheError(f"{meta_path.parent}: holds steps={meta['steps']}, expected {steps}; delete "
                         "that directory and re-run")


def run_ablation(cache_dir: str | Path, out_dir: str | Path, variants: Sequence[str] | str = VARIANTS,
                 mc: int = 10, particles: int = 300, steps: int | None = None,
                 executor: str = "local", scheduler: str | None = None, workers: int | None = None,
                 progress: bool = True, command: str | None = None) -> AblationRun:
    """Run the (variant x seed) grid on ``cache_dir``, store each job under ``out_dir/jobs``.

    Finished jobs are skipped. When all jobs are stored, :func:`aggregate` writes the summary.
    ``DIR/ablation.json`` records the grid of this call (variants x seeds); the summary and
    ``mmslam report`` cover that grid. A different trace, ``particles`` or ``steps`` than the
    stored ones is refused (use another ``out_dir``); more seeds or variants extend the grid.

    Args:
        cache_dir: a path cache (see :func:`prepare_cache`).
        out_dir: the ablation directory.
        variants: subset of :data:`VARIANTS` (a sequence or ``"a,b"``).
        mc: Monte Carlo runs per variant (seeds ``0..mc-1``).
        particles: particles per vehicle filter.
        steps: time steps to run (default: all steps in the cache).
        executor: ``local`` (process pool) or ``dask``.
        scheduler: dask scheduler address (``tcp://host:8786``); None starts a LocalCluster.
        workers: processes (local) or LocalCluster workers; default: all cores.
        progress: show a progress bar on stderr.
        command: the shell command that reproduces this ablation (stored for the report).

    Raises:
        MmslamError: bad arguments, a results directory made with other settings, an unreachable
            scheduler. Jobs finished before an error stay stored.
    """
    variants = parse_variants(variants)
    check_run_args(mc, particles, steps, executor, scheduler, workers)
    out = Path(out_dir)
    info = _cache_info(Path(cache_dir))
    n_steps = info["cache_steps"] if steps is None else int(steps)
    if n_steps > info["cache_steps"]:
        raise ConfigError(f"--steps {n_steps}: the cache {info['cache_dir']} holds only "
                          f"{info['cache_steps']} steps; trace more steps first")
    spec = {**info, "variants": list(variants), "mc": int(mc), "seeds": list(range(int(mc))),
            "particles": int(particles), "steps": n_steps,
            "command": command or default_command(info["scenario_name"], variants, mc, particles,
                                                  info["source"], out, steps)}
    if (out / ABLATION_FILE).is_file():
        _check_compatible(out, read_ablation(out), spec)
    out.mkdir(parents=True, exist_ok=True)
    (out / JOBS_DIR).mkdir(exist_ok=True)
    _write_json(out / ABLATION_FILE, spec)

    jobs = plan_jobs(variants, mc)
    done = [j for j in jobs if is_finished(out, j)]
    for j in done:
        _check_job_meta(out, j, int(particles), n_steps)
    # longest first (variants with a VS map cost more than baseline): less idle time at the end;
    # the order never changes a job's result
    pending = sorted((j for j in jobs if j not in done), key=lambda j: (j.variant == "baseline", j.seed))
    t0 = time.perf_counter()
    ran: list[Job] = []
    desc = "nothing to run"
    if pending:
        pool_cm = (_local_pool(workers, len(pending)) if executor == "local"
                   else _dask_pool(scheduler, workers, len(pending)))
        with pool_cm as pool:
            desc = pool.describe
            ran = _drive(pool, pending, out, str(info["cache_dir"]), int(particles),
                         None if steps is None else n_steps, progress, len(done), len(jobs))
    summary = aggregate(out)
    return AblationRun(out, jobs, ran, done, time.perf_counter() - t0, summary, desc)


def _drive(pool: _Pool, pending: list[Job], out: Path, cache_dir: str, particles: int,
           steps: int | None, progress: bool, n_done: int, n_total: int) -> list[Job]:
    """Submit ``pending``, save each result as it arrives; cancel the rest on error."""
    futs = {pool.submit(run_job, cache_dir, j.variant, j.seed, particles, steps): j for j in pending}
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
    try:
        for fut in pool.as_completed(list(futs)):
            job = futs[fut]
            result = fut.result()
            result.meta.setdefault("variant", job.variant)
            result.meta.setdefault("seed", job.seed)
            result.save(job_dir(out, job))
            ran.append(job)
            if bar is not None:
                bar.update(task, advance=1, last=f"{job.name} done")
    except BaseException:
        pool.cancel(list(futs))
        raise
    finally:
        if bar is not None:
            bar.stop()
    return ran


def default_command(scenario: str, variants: Sequence[str], mc: int, particles: int, source: str | None,
                    out: Path, steps: int | None, executor: str = "local") -> str:
    """The ``mmslam ablate`` command line that reproduces an ablation."""
    import shlex

    argv = ["mmslam", "ablate", scenario, "--variants", ",".join(variants), "--mc", str(mc),
            "--particles", str(particles), "--source", str(source or "analytic"), "--out", str(out)]
    if steps is not None:
        argv += ["--steps", str(steps)]
    if executor != "local":
        argv += ["--executor", executor]
    return shlex.join(argv)


# ====================================================================== aggregation
@dataclass
class Summary:
    """Aggregated ablation results.

    ``table`` (long form, one row per variant, step, map, type and quantity):
        variant, map (vehicle name, ``"fused"``, or ``"all"`` for state rows pooled over
        vehicles), type (``VA``/``SP``/``VS`` for map metrics, ``"state"`` for vehicle-state
        errors), quantity (:data:`METRIC_QUANTITIES` or :data:`STATE_QUANTITIES`), step,
        mean, std (population std, ddof 0, over the pooled samples), rms (root mean square),
        n (samples pooled: seeds, times vehicles for ``map == "all"``).
    ``headline``: one row per variant and map (each vehicle, then ``fused``): mean GOSPA per
        type over seeds and steps ``>= fusion_start``, position RMSE over the same steps (the
        vehicle's, or all vehicles' for ``fused``), mean job wall time and the seed count.
    ``config``: the ablation settings (:data:`ABLATION_FILE`) plus ``fusion_start``.
    """

    table: dict[str, np.ndarray]
    headline: list[dict[str, Any]]
    config: dict[str, Any] = field(default_factory=dict)

    def series(self, variant: str, map: str, type: str, quantity: str) -> dict[str, np.ndarray]:
        """Per-step columns (step, mean, std, rms, n) of one (variant, map, type, quantity)."""
        t = self.table
        m = ((t["variant"] == variant) & (t["map"] == map) & (t["type"] == type)
             & (t["quantity"] == quantity))
        order = np.argsort(t["step"][m], kind="stable")
        return {k: np.asarray(t[k][m])[order] for k in ("step", "mean", "std", "rms", "n")}

    @property
    def variants(self) -> list[str]:
        present = set(np.asarray(self.table["variant"]).tolist())
        return [v for v in VARIANTS if v in present]


def _fusion_start(scenario: dict[str, Any]) -> int:
    try:
        return int(min(scenario["fusion"]["start"]))
    except (KeyError, TypeError, ValueError):
        return 0


def load_jobs(out_dir: str | Path, variants: Sequence[str] | None = None,
              seeds: Sequence[int] | None = None) -> dict[Job, Any]:
    """Finished jobs of the ablation in ``out_dir`` (default: its whole grid), loaded."""
    from mmslam.slam.result import Result

    spec = read_ablation(out_dir)
    variants = list(variants or spec.get("variants", VARIANTS))
    seeds = list(seeds if seeds is not None else spec.get("seeds", range(int(spec.get("mc", 0)))))
    out = {}
    for v in variants:
        for s in seeds:
            j = Job(v, int(s))
            if is_finished(out_dir, j):
                out[j] = Result.load(job_dir(out_dir, j))
    return out


def _group_stats(keys: list[tuple], values: np.ndarray) -> dict[tuple, tuple[float, float, float, int]]:
    """Key -> (mean, std, rms, n) of the values (NaNs ignored)."""
    acc: dict[tuple, list[float]] = {}
    for k, v in zip(keys, values.tolist()):
        acc.setdefault(k, []).append(v)
    out = {}
    for k, vs in acc.items():
        a = np.asarray(vs, dtype=float)
        a = a[np.isfinite(a)]
        if a.size:
            out[k] = (float(a.mean()), float(a.std()), float(np.sqrt(np.mean(a * a))), int(a.size))
        else:
            out[k] = (math.nan, math.nan, math.nan, 0)
    return out


def aggregate(out_dir: str | Path) -> Summary:
    """Mean / std / RMS over seeds of every per-step metric; writes ``summary.parquet`` / ``.json``.

    Uses the finished jobs of the ablation's grid (a partial grid is aggregated over the seeds
    present; ``n`` and the headline ``runs`` say how many). See :class:`Summary` for the columns.
    """
    out = Path(out_dir)
    spec = read_ablation(out)
    jobs = load_jobs(out)
    if not jobs:
        raise CacheError(f"{out}: no finished jobs under {out / JOBS_DIR}; run the ablation first")
    fusion_start = _fusion_start(spec.get("scenario", {}))
    rows: dict[str, list] = {k: [] for k in ("variant", "map", "type", "quantity", "step", "mean", "std",
                                             "rms", "n")}
    headline: list[dict[str, Any]] = []
    for variant in [v for v in VARIANTS if any(j.variant == v for j in jobs)]:
        res = [jobs[j] for j in sorted(jobs) if j.variant == variant]
        names = list(res[0].meta.get("vehicle_names") or spec.get("vehicle_names") or [])
        # ---- map metrics, grouped by (map, type, step)
        mkeys: list[tuple] = []
        mvals: dict[str, list[np.ndarray]] = {q: [] for q in METRIC_QUANTITIES}
        for r in res:
            m = r.metrics
            mkeys += list(zip(np.asarray(m["map"]).astype(str).tolist(), np.asarray(m["type"]).astype(str).tolist(),
                              np.asarray(m["step"]).astype(int).tolist()))
            for q in METRIC_QUANTITIES:
                mvals[q].append(np.asarray(m[q], dtype=float))
        for q in METRIC_QUANTITIES:
            for (mp, ty, st), (mu, sd, rm, n) in sorted(_group_stats(mkeys, np.concatenate(mvals[q])).items()):
                for k, v in zip(rows, (variant, mp, ty, q, st, mu, sd, rm, n)):
                    rows[k].append(v)
        # ---- vehicle-state errors, per vehicle and pooled
        vkeys: list[tuple] = []
        akeys: list[tuple] = []
        vvals: dict[str, list[np.ndarray]] = {q: [] for q in STATE_QUANTITIES}
        for r in res:
            vt = r.vehicles
            idx = np.asarray(vt["vehicle"]).astype(int)
            st = np.asarray(vt["step"]).astype(int).tolist()
            vn = [names[i] if i < len(names) else f"vehicle{i}" for i in idx.tolist()]
            vkeys += list(zip(vn, st))
            akeys += [(ALL_VEHICLES, s) for s in st]
            for q in STATE_QUANTITIES:
                vvals[q].append(np.asarray(vt[q], dtype=float))
        for q in STATE_QUANTITIES:
            vals = np.concatenate(vvals[q])
            for keys in (vkeys, akeys):
                for (mp, st), (mu, sd, rm, n) in sorted(_group_stats(keys, vals).items()):
                    for k, v in zip(rows, (variant, mp, "state", q, st, mu, sd, rm, n)):
                        rows[k].append(v)
        headline += _headline_rows(variant, res, names, fusion_start)
    table = {k: np.asarray(v, dtype=object if k in ("variant", "map", "type", "quantity") else None)
             for k, v in rows.items()}
    table["step"] = table["step"].astype(np.int32)
    table["n"] = table["n"].astype(np.int32)
    config = {**{k: v for k, v in spec.items() if k != "scenario"}, "fusion_start": fusion_start,
              "dt": spec.get("scenario", {}).get("dt"),
              "seeds_found": {v: sorted(j.seed for j in jobs if j.variant == v) for v in spec.get("variants", [])}}
    summary = Summary(table, headline, config)
    _write_summary(out, summary)
    return summary


def _headline_rows(variant: str, res: list[Any], names: list[str], fusion_start: int) -> list[dict[str, Any]]:
    """Mean GOSPA per (map, type) and position RMSE over steps >= fusion_start, over all seeds."""
    maps = list(names) + ["fused"]
    wall = [float(r.meta.get("wall_time_s", math.nan)) for r in res]
    rows = []
    for mp in maps:
        row: dict[str, Any] = {"variant": variant, "map": mp}
        for ty in TYPES:
            vals = []
            for r in res:
                m = r.metrics
                sel = ((np.asarray(m["map"]).astype(str) == mp) & (np.asarray(m["type"]).astype(str) == ty)
                       & (np.asarray(m["step"]) >= fusion_start))
                vals.append(np.asarray(m["gospa"], dtype=float)[sel])
            a = np.concatenate(vals) if vals else np.zeros(0)
            a = a[np.isfinite(a)]
            row[f"gospa_{ty}"] = float(a.mean()) if a.size else math.nan
        errs = []
        for r in res:
            vt = r.vehicles
            sel = np.asarray(vt["step"]) >= fusion_start
            if mp != "fused":
                sel &= np.asarray(vt["vehicle"]).astype(int) == names.index(mp)
            errs.append(np.asarray(vt["pos_err"], dtype=float)[sel])
        e = np.concatenate(errs) if errs else np.zeros(0)
        e = e[np.isfinite(e)]
        row["pos_rmse"] = float(np.sqrt(np.mean(e * e))) if e.size else math.nan
        row["wall_time_s"] = float(np.nanmean(wall)) if wall and np.isfinite(wall).any() else math.nan
        row["runs"] = len(res)
        rows.append(row)
    return rows


def _write_summary(out: Path, s: Summary) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    tab = pa.table({k: pa.array(v.tolist()) if v.dtype == object else pa.array(v) for k, v in s.table.items()})
    tmp = out / f".{SUMMARY_PARQUET}.{os.getpid()}.tmp"
    pq.write_table(tab, tmp)
    os.replace(tmp, out / SUMMARY_PARQUET)
    per_step = {k: [None if isinstance(x, float) and not math.isfinite(x) else x for x in v.tolist()]
                for k, v in s.table.items()}
    head = [{k: (None if isinstance(x, float) and not math.isfinite(x) else x) for k, x in r.items()}
            for r in s.headline]
    _write_json(out / SUMMARY_JSON, {"config": s.config, "headline": head, "per_step": per_step})


def load_summary(out_dir: str | Path) -> Summary:
    """Read ``summary.parquet`` / ``summary.json`` back (written by :func:`aggregate`)."""
    import pyarrow.parquet as pq

    out = Path(out_dir)
    pj, pp = out / SUMMARY_JSON, out / SUMMARY_PARQUET
    if not (pj.is_file() and pp.is_file()):
        raise CacheError(f"{out}: no {SUMMARY_PARQUET}/{SUMMARY_JSON}; run `mmslam report {out}` or the "
                         "ablation to create them")
    try:
        t = pq.read_table(pp)
        table = {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}
        j = json.loads(pj.read_text())
    except Exception as e:
        raise CacheError(f"{out}: unreadable summary ({_one_line(e)}); run `mmslam report {out}` to rebuild") from None
    for k in ("variant", "map", "type", "quantity"):
        table[k] = np.asarray(table[k], dtype=object)
    head = [{k: (math.nan if x is None else x) for k, x in r.items()} for r in j["headline"]]
    return Summary(table, head, j["config"])

