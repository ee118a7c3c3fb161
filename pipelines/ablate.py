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
"""
from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import CacheError, ConfigError, Interrupted, MmslamError, deferred_sigint, was_interrupted
from mmslam.limits import MAX_MC, MAX_PARTICLES, MAX_SEED, MAX_STEPS, MAX_WORKERS
from mmslam.slam.specs.landmarks import mapped_types
from mmslam.slam.specs.variants import BUILTIN_VARIANTS, COMPARED_WITH, REFERENCES, variant_names  # noqa: F401
from mmslam.slam.specs.variants import VARIANTS as FILTER_VARIANTS  # noqa: F401

VARIANTS: tuple[str, ...] = BUILTIN_VARIANTS
"""Everything an ablation runs by default, in the order it is plotted (the built-in variant specs
of :mod:`mmslam.slam.specs.variants`: the reference ``odometry``, then the filter variants)."""

EXECUTORS: tuple[str, ...] = ("local", "dask")
TYPES: tuple[str, ...] = tuple(s.name for s in mapped_types())
"""Map types scored (the built-in mapped landmark types of :mod:`mmslam.slam.specs.landmarks`)."""
METRIC_QUANTITIES: tuple[str, ...] = ("gospa", "loc", "missed", "false", "n_est", "n_true", "card", "n_visible")
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
    """One filter run: a variant, an explicit seed and the grid arm's parameter settings.

    ``arm`` holds ``section.key=value`` strings of one point of an ``--grid`` (empty without a
    grid); the ablation's ``--set`` overrides apply to every job and are not part of the name.
    """

    variant: str
    seed: int
    arm: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """The variant, with its grid settings: ``proposed`` or ``proposed[fusion.vs_reduction=gate]``."""
        return arm_label(self.variant, self.arm)

    @property
    def name(self) -> str:
        """Directory name under ``DIR/jobs``: ``<label>-seed<k>``."""
        return f"{self.label}-seed{self.seed}"


def arm_label(variant: str, arm: Sequence[str]) -> str:
    """``variant`` or ``variant[key=value,key2=value2]`` (the summary's ``variant`` column)."""
    return f"{variant}[{','.join(arm)}]" if arm else variant


def parse_label(label: str) -> tuple[str, tuple[str, ...]]:
    """Inverse of :func:`arm_label`."""
    if label.endswith("]") and "[" in label:
        v, _, rest = label.partition("[")
        return v, tuple(x for x in rest[:-1].split(",") if x)
    return label, ()


def _canonical_setting(text: str) -> str:
    """``section.key=value`` with the key and value normalised (``filter.merge = 4`` -> ``filter.merge=4``)."""
    from mmslam.scenes.params import parse_override

    try:
        key, value = parse_override(text)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if isinstance(value, bool):
        v = str(value).lower()
    elif isinstance(value, (list, tuple)):
        v = "[" + ",".join(str(x) for x in value) + "]"
    else:
        v = str(value)
    if "/" in v or "," in v and not v.startswith("["):
        raise ConfigError(f"--set/--grid {text!r}: value must not contain '/' or ','")
    return f"{key}={v}"


def job_dir(out_dir: str | Path, job: Job) -> Path:
    """Where ``job``'s result is stored."""
    return Path(out_dir) / JOBS_DIR / job.name


def parse_sets(sets: Sequence[str]) -> tuple[str, ...]:
    """``--set`` values (repeatable ``section.key=value``) -> canonical strings, each key once."""
    out = tuple(_canonical_setting(t) for t in sets)
    keys = [t.split("=", 1)[0] for t in out]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise ConfigError(f"--set {dup[0]}: given twice; set each parameter once")
    return out


def parse_grid(grid: Sequence[str]) -> list[tuple[str, ...]]:
    """``--grid key=v1,v2`` values (repeatable) -> the arms: every combination, in order.

    No ``--grid`` gives one empty arm ``()``. A grid key may not also be a ``--set`` key (the
    caller checks).
    """
    import itertools

    axes: list[list[str]] = []
    keys: list[str] = []
    for text in grid:
        if "=" not in text:
            raise ConfigError(f"--grid {text!r}: expected section.key=v1,v2 (e.g. fusion.vs_reduction=matched,gate)")
        key, raw = (x.strip() for x in text.split("=", 1))
        vals = [x.strip() for x in raw.split(",") if x.strip()] if not raw.startswith("[") else [raw]
        if not key or not vals:
            raise ConfigError(f"--grid {text!r}: expected section.key=v1,v2 (e.g. fusion.vs_reduction=matched,gate)")
        if key in keys:
            raise ConfigError(f"--grid {key}: given twice; list all its values in one --grid")
        keys.append(key)
        axis = [_canonical_setting(f"{key}={v}") for v in vals]
        if len(set(axis)) != len(axis):
            raise ConfigError(f"--grid {key}: a value is listed twice")
        axes.append(axis)
    return [tuple(c) for c in itertools.product(*axes)] if axes else [()]


def parse_variants(spec: str | Sequence[str]) -> tuple[str, ...]:
    """``"baseline,cm1"`` or a sequence -> validated tuple (order kept, no duplicates)."""
    items = [s.strip() for s in spec.split(",")] if isinstance(spec, str) else [str(s).strip() for s in spec]
    items = [s for s in items if s]
    if not items:
        raise ConfigError(f"--variants: empty; expected a comma-separated subset of {','.join(variant_names())}")
    for v in items:
        if v not in variant_names():
            raise ConfigError(f"--variants: unknown variant '{v}'; expected a comma-separated subset of "
                              f"{','.join(variant_names())}")
    dup = sorted({v for v in items if items.count(v) > 1})
    if dup:
        raise ConfigError(f"--variants: '{dup[0]}' given twice; list each variant once")
    return tuple(items)


def check_run_args(mc: int, particles: int | None, steps: int | None, executor: str,
                   scheduler: str | None, workers: int | None, seed0: int = 0) -> None:
    """Reject bad numbers / executor settings with a one-line :class:`ConfigError`
    (``particles`` None: the scenario's ``filter.particles``, checked by the scenario)."""
    if not 1 <= int(mc) <= MAX_MC:
        raise ConfigError(f"--mc {mc}: expected 1..{MAX_MC} Monte Carlo runs")
    if not 0 <= int(seed0) <= MAX_SEED - int(mc) + 1:
        raise ConfigError(f"--seed0 {seed0}: expected a seed in 0..{MAX_SEED - int(mc) + 1} (seeds seed0..seed0+mc-1)")
    if particles is not None and not 1 <= int(particles) <= MAX_PARTICLES:
        raise ConfigError(f"--particles {particles}: expected 1..{MAX_PARTICLES} particles")
    if steps is not None and not 1 <= int(steps) <= MAX_STEPS:
        raise ConfigError(f"--steps {steps}: expected 1..{MAX_STEPS} time steps")
    if executor not in EXECUTORS:
        raise ConfigError(f"--executor {executor}: expected one of {', '.join(EXECUTORS)}")
    if scheduler and executor != "dask":
        raise ConfigError("--scheduler is only used with --executor dask; add --executor dask or drop it")
    if scheduler:
        check_dask_address(scheduler)
    if workers is not None and not 1 <= int(workers) <= MAX_WORKERS:
        raise ConfigError(f"--workers {workers}: expected 1..{MAX_WORKERS} workers")


def plan_jobs(variants: Sequence[str], mc: int, seed0: int = 0,
              arms: Sequence[tuple[str, ...]] = ((),)) -> list[Job]:
    """The grid ``variants x arms x seeds seed0..seed0+mc-1``, variant-major."""
    return [Job(v, s, tuple(a)) for v in variants for a in arms for s in range(int(seed0), int(seed0) + int(mc))]


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
    with deferred_sigint():  # the Sionna scene load is C++: Ctrl-C is raised after it
        src = make_source(source, scn, max_depth=max_depth, samples=samples, seed=seed)
    return Path(trace_scenario(scn, src, Path(out_dir) / "cache", steps=steps, progress=progress))


# ====================================================================== the worker side
def run_job(cache_dir: str, variant: str, seed: int, particles: int, steps: int | None,
            overrides: Sequence[str] = ()) -> Any:
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
                    steps=None if steps is None else int(steps), overrides=tuple(overrides))


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
    import signal
    import threading

    for k in _THREAD_VARS:
        os.environ[k] = "1"
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it saves, then stops us

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
            procs = list((getattr(ex, "_processes", None) or {}).values())  # shutdown() forgets them
            ex.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.terminate()  # in-flight jobs: cancelled now (they re-run on resume), not awaited
            raise
        else:
            ex.shutdown(wait=True)


def _one_line(e: BaseException) -> str:
    msg = " ".join(str(e).split()) or type(e).__name__
    return msg if len(msg) <= 200 else msg[:197] + "..."


DASK_SCHEMES: tuple[str, ...] = ("tcp", "tls", "ws", "wss", "ucx")


def check_dask_address(scheduler: str) -> str:
    """``scheduler`` if it reads ``[scheme://]host:port`` (port 1..65535); one-line :class:`ConfigError` otherwise.

    Checked before a ``Client`` is made: a malformed address would otherwise hang for the
    connect timeout and print a ``Client.__del__`` traceback.
    """
    import re

    m = re.fullmatch(r"(?:([a-z]+)://)?(\[[0-9a-fA-F:]+\]|[A-Za-z0-9._-]+):(\d{1,5})", scheduler.strip())
    if m is None or (m.group(1) is not None and m.group(1) not in DASK_SCHEMES) or not 1 <= int(m.group(3)) <= 65535:
        raise ConfigError(f"--scheduler {scheduler!r}: expected an address like tcp://host:8786 (scheme one of "
                          f"{', '.join(DASK_SCHEMES)}, port 1..65535)")
    return scheduler.strip()


def connect_dask(scheduler: str, timeout_s: float = CONNECT_TIMEOUT_S) -> Any:
    """A ``dask.distributed.Client`` for ``scheduler``; one-line :class:`MmslamError` if unreachable."""
    check_dask_address(scheduler)
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


def particles_for(scenario: dict[str, Any] | Any, sets: Sequence[str], particles: int | None) -> int:
    """``particles``, or the ``filter.particles`` of ``scenario`` (a Scenario or its resolved dict) with
    the ``--set`` overrides applied: the one default of the particle count."""
    from mmslam.scenes.scenario import Scenario, scenario_from_resolved, with_overrides
    from mmslam.slam.filter.run import resolve_particles

    if particles is not None:
        return int(particles)
    scn = scenario if isinstance(scenario, Scenario) else scenario_from_resolved(scenario)
    return resolve_particles(with_overrides(scn, list(sets)), None)


def check_overrides(info: dict[str, Any], sets: Sequence[str], arms: Sequence[tuple[str, ...]]) -> None:
    """Validate ``sets`` + every arm on the cached scenario (bounds, names) before anything is written."""
    from mmslam.scenes.scenario import scenario_from_resolved, with_overrides

    base = scenario_from_resolved(info["scenario"])
    for arm in arms:
        scn = with_overrides(base, list(sets) + list(arm))
        if scn.geometry_hash() != base.geometry_hash():
            raise ConfigError(f"--set/--grid {', '.join(list(sets) + list(arm))}: changes the traced scenario "
                              "(the cache's truth); write it in a scenario file and trace a new cache")


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
    for key, flag in (("config_hash", "the trace (scenario / source)"), ("scenario_name", "the scenario"),
                      ("source", "--source"), ("particles", "--particles"), ("steps", "--steps"),
                      ("sets", "--set")):
        if key not in new:
            continue
        if old.get(key, [] if key == "sets" else None) != new.get(key):
            raise ConfigError(f"{out_dir} holds an ablation with {key}={old.get(key)} but this run asks "
                              f"{key}={new.get(key)} ({flag}); use another --out or delete "
                              f"{out_dir / JOBS_DIR}")


def _check_job_meta(out_dir: Path, job: Job, particles: int, steps: int, overrides: Sequence[str]) -> None:
    meta_path = job_dir(out_dir, job) / "meta.json"
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CacheError(f"{meta_path}: unreadable ({_one_line(e)}); delete {meta_path.parent} and re-run") from None
    want = {"variant": job.variant, "seed": job.seed, "particles": particles}
    if meta.get("overrides") is not None:
        want["overrides"] = list(overrides)
    for k, v in want.items():
        if k in meta and meta[k] != v:
            raise CacheError(f"{meta_path.parent}: holds {k}={meta[k]}, expected {v}; delete that "
                             "directory and re-run")
    if meta.get("steps") is not None and meta["steps"] != steps:
        raise CacheError(f"{meta_path.parent}: holds steps={meta['steps']}, expected {steps}; delete "
                         "that directory and re-run")


ABLATION_KIND = "ablation"
"""Output-marker kind of an ablation directory (:mod:`mmslam.outputs`)."""


def start_ablation_dir(out_dir: str | Path, force: bool = False) -> Path:
    """Check ``out_dir`` may hold an ablation (before any work), create it and mark it.

    Allowed: missing, empty, or a previous ablation (marker or ``ablation.json``). Raises a one-line
    error otherwise, whatever ``force`` (:mod:`mmslam.outputs`: never into a folder mmslam did not make).
    """
    from mmslam.outputs import check_target, output_kind, write_marker

    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ConfigError(f"--out {out_dir}: is a file, not a folder; choose a writable path for the ablation")
    out = check_target(out_dir, ABLATION_KIND, force, accept=lambda p: (p / ABLATION_FILE).is_file())
    if out.is_dir():
        from mmslam.pipelines.report import check_ablation_outputs

        check_ablation_outputs(out)  # a user's summary / report / figure of the same name (issue 25)
    out.mkdir(parents=True, exist_ok=True)
    if output_kind(out) != ABLATION_KIND:
        write_marker(out, ABLATION_KIND)
    return out


def precheck_ablation(out_dir: str | Path, scenario_name: str, source: str, steps: int | None, particles: int,
                      sets: Sequence[str]) -> None:
    """Refuse, before the trace, a run that :func:`run_ablation` would refuse after it.

    An existing ablation in ``out_dir`` asked for other steps, particles (resolved: see
    :func:`particles_for`), ``--set`` values, scenario or source: nothing is traced (the cache is
    not extended) and nothing is written.
    """
    out = Path(out_dir)
    if not (out / ABLATION_FILE).is_file():
        return
    new: dict[str, Any] = {"scenario_name": scenario_name, "source": source, "particles": int(particles),
                           "sets": list(parse_sets(sets))}
    if steps is not None:
        new["steps"] = int(steps)
    _check_compatible(out, read_ablation(out), new)


def _holding_out_lock(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Run ``fn(first, out_dir, ...)`` holding the writer lock of ``out_dir`` (one writer per directory)."""

    @functools.wraps(fn)
    def wrapper(first: Any, out_dir: str | Path, *args: Any, **kwargs: Any) -> Any:
        from mmslam.outputs import locked

        with locked(out_dir, "ablation"):
            return fn(first, out_dir, *args, **kwargs)

    return wrapper


@_holding_out_lock
def run_ablation(cache_dir: str | Path, out_dir: str | Path, variants: Sequence[str] | str = VARIANTS,
                 mc: int = 10, particles: int | None = None, steps: int | None = None,
                 executor: str = "local", scheduler: str | None = None, workers: int | None = None,
                 progress: bool = True, command: str | None = None, seed0: int = 0,
                 sets: Sequence[str] = (), grid: Sequence[str] = ()) -> AblationRun:
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

    Raises:
        MmslamError: bad arguments, a results directory made with other settings, an unreachable
            scheduler. Jobs finished before an error stay stored.
    """
    variants = parse_variants(variants)
    check_run_args(mc, particles, steps, executor, scheduler, workers, seed0)
    sets = parse_sets(sets)
    arms = parse_grid(grid)
    clash = sorted({a.split("=", 1)[0] for arm in arms for a in arm} & {x.split("=", 1)[0] for x in sets})
    if clash:
        raise ConfigError(f"--grid {clash[0]}: also given with --set; use one of them")
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
    seeds = list(range(int(seed0), int(seed0) + int(mc)))
    spec = {**info, "variants": list(variants), "mc": int(mc), "seed0": int(seed0), "seeds": seeds,
            "particles": int(particles), "steps": n_steps, "sets": list(sets), "grid": list(grid),
            "arms": [list(a) for a in arms],
            "command": command or default_command(info["scenario_name"], variants, mc, particles,
                                                  info["source"], out, steps, seed0=seed0, sets=sets,
                                                  grid=grid)}
    if old is not None:
        _check_compatible(out, old, spec)
    start_ablation_dir(out, force=True)
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
        pool_cm = (_local_pool(workers, len(pending)) if executor == "local"
                   else _dask_pool(scheduler, workers, len(pending)))
        with pool_cm as pool:
            desc = pool.describe
            ran = _drive(pool, pending, out, str(info["cache_dir"]), int(particles),
                         None if steps is None else n_steps, progress, len(done), len(jobs), sets)
    summary = aggregate(out)
    return AblationRun(out, jobs, ran, done, time.perf_counter() - t0, summary, desc)


def _drive(pool: _Pool, pending: list[Job], out: Path, cache_dir: str, particles: int,
           steps: int | None, progress: bool, n_done: int, n_total: int, sets: Sequence[str] = ()) -> list[Job]:
    """Submit ``pending``, save each result as it arrives; cancel the rest on error."""
    futs = {pool.submit(run_job, cache_dir, j.variant, j.seed, particles, steps, tuple(sets) + j.arm): j
            for j in pending}
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
        result.meta.setdefault("variant", job.variant)
        result.meta.setdefault("seed", job.seed)
        result.save(job_dir(out, job))
        ran.append(job)

    try:
        for fut in pool.as_completed(list(futs)):
            job = futs[fut]
            save(fut, job)
            if bar is not None:
                bar.update(task, advance=1, last=f"{job.name} done")
    except BaseException as e:
        if not was_interrupted(e):
            pool.cancel(list(futs))
            raise
        pool.cancel(list(futs))
        for fut, job in futs.items():  # finished but not yet collected: keep them
            if job not in ran and fut.done() and not fut.cancelled() and fut.exception() is None:
                save(fut, job)
        if bar is not None:
            bar.stop()
            bar = None
        left = len(pending) - len(ran)
        raise Interrupted(f"{n_done + len(ran)} of {n_total} jobs are kept in {out / JOBS_DIR} "
                          f"({len(ran)} finished in this run); {left} unfinished jobs were cancelled; re-run "
                          "the same command to resume") from None
    finally:
        if bar is not None:
            bar.stop()
    return ran


def default_command(scenario: str, variants: Sequence[str], mc: int, particles: int, source: str | None,
                    out: Path, steps: int | None, executor: str = "local", seed0: int = 0,
                    sets: Sequence[str] = (), grid: Sequence[str] = ()) -> str:
    """The ``mmslam ablate`` command line that reproduces an ablation."""
    import shlex

    argv = ["mmslam", "ablate", scenario, "--variants", ",".join(variants), "--mc", str(mc),
            "--particles", str(particles), "--source", str(source or "analytic"), "--out", str(out)]
    if steps is not None:
        argv += ["--steps", str(steps)]
    if seed0:
        argv += ["--seed0", str(seed0)]
    for x in sets:
        argv += ["--set", x]
    for x in grid:
        argv += ["--grid", x]
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
    ``headline``: one row per variant (or grid arm, ``variant[key=value]``) and map (each
        vehicle, then ``fused``): mean GOSPA per type over seeds and steps ``>= fusion_start``,
        position RMSE over the same steps (the vehicle's, or all vehicles' for ``fused``), mean
        job wall time and the seed count; for each of :data:`SCORED` the 95% CI half-width
        ``_ci`` of the mean over runs (per-run scores: mean GOSPA, RMSE), the paired difference
        ``_diff`` to ``reference`` (baseline on the same seeds) with its CI ``_diff_ci`` and
        ``_sig`` (True when that CI excludes 0); ``card_<type>``: mean PHD mass (estimated
        number of landmarks) over the same steps and runs.
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
        """Variant / arm labels present, in :data:`VARIANTS` order (arms after their variant)."""
        present = list(dict.fromkeys(np.asarray(self.table["variant"]).tolist()))
        order = {v: i for i, v in enumerate(variant_names())}
        return sorted(present, key=lambda lab: (order.get(parse_label(lab)[0], 99), present.index(lab)))


def _fusion_start(scenario: dict[str, Any]) -> int:
    try:
        return int(min(scenario["fusion"]["start"]))
    except (KeyError, TypeError, ValueError):
        return 0


def spec_arms(spec: dict[str, Any]) -> list[tuple[str, ...]]:
    """The grid arms recorded in ``ablation.json`` (one empty arm for an ablation without ``--grid``)."""
    return [tuple(a) for a in spec.get("arms", [[]])] or [()]


def load_jobs(out_dir: str | Path, variants: Sequence[str] | None = None,
              seeds: Sequence[int] | None = None) -> dict[Job, Any]:
    """Finished jobs of the ablation in ``out_dir`` (default: its whole grid), loaded."""
    from mmslam.slam.filter.result import Result

    spec = read_ablation(out_dir)
    variants = list(variants or spec.get("variants", VARIANTS))
    seeds = list(seeds if seeds is not None else spec.get("seeds", range(int(spec.get("mc", 0)))))
    out = {}
    for v in variants:
        for a in spec_arms(spec):
            for s in seeds:
                j = Job(v, int(s), a)
                if is_finished(out_dir, j):
                    out[j] = Result.load(job_dir(out_dir, j))
    return out


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
    labels = _labels_in_order(jobs, spec_arms(spec))
    per_run: dict[str, dict[int, dict[str, dict[str, float]]]] = {}
    for variant in labels:
        res = [jobs[j] for j in sorted(jobs) if j.label == variant]
        names = list(res[0].meta.get("vehicle_names") or spec.get("vehicle_names") or [])
        # ---- map metrics, grouped by (map, type, step)
        mkeys: list[tuple] = []
        mvals: dict[str, list[np.ndarray]] = {q: [] for q in METRIC_QUANTITIES}
        for r in res:
            m = r.metrics
            mkeys += list(zip(np.asarray(m["map"]).astype(str).tolist(), np.asarray(m["type"]).astype(str).tolist(),
                              np.asarray(m["step"]).astype(int).tolist()))
            for q in METRIC_QUANTITIES:
                mvals[q].append(np.asarray(m[q], dtype=float) if q in m  # results saved before a column existed
                                else np.full(len(m["step"]), math.nan))
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
        per_run[variant] = {int(r.meta.get("seed", i)): _run_scores(r, names, fusion_start)
                            for i, r in enumerate(res)}
        headline += _headline_rows(variant, res, names, fusion_start)
    _add_intervals(headline, per_run)
    table = {k: np.asarray(v, dtype=object if k in ("variant", "map", "type", "quantity") else None)
             for k, v in rows.items()}
    table["step"] = table["step"].astype(np.int32)
    table["n"] = table["n"].astype(np.int32)
    config = {**{k: v for k, v in spec.items() if k != "scenario"}, "fusion_start": fusion_start,
              "dt": spec.get("scenario", {}).get("dt"),
              "seeds_found": {v: sorted(j.seed for j in jobs if j.label == v) for v in labels}}
    summary = Summary(table, headline, config)
    _write_summary(out, summary)
    return summary


def _labels_in_order(jobs: dict[Job, Any], arms: Sequence[tuple[str, ...]]) -> list[str]:
    """Job labels: variants in :data:`VARIANTS` order, each followed by its grid arms in ``arms`` order."""
    order = {v: i for i, v in enumerate(variant_names())}
    arm_pos = {tuple(a): i for i, a in enumerate(arms)}
    ranked = sorted(jobs, key=lambda j: (order.get(j.variant, 99), arm_pos.get(j.arm, len(arm_pos)), j.arm))
    return list(dict.fromkeys(j.label for j in ranked))


OTHERS_MAP = "fused_others"
"""The fused VS map without the vehicles' own uploads (:meth:`mmslam.slam.eval.evaluation.MapScorer.record_others`):
VS mapping of *other* vehicles, a headline row of its own where the runs have it."""


def _maps(names: list[str], res: Sequence[Any]) -> list[str]:
    """Headline maps: each vehicle, ``fused``, then :data:`OTHERS_MAP` where some run scored it."""
    has = any(np.any(np.asarray(r.metrics["map"]).astype(str) == OTHERS_MAP) for r in res)
    return list(names) + ["fused"] + ([OTHERS_MAP] if has else [])


def _run_scores(r: Any, names: list[str], fusion_start: int) -> dict[str, dict[str, float]]:
    """One run's scalar scores per map: mean GOSPA and PHD mass per type, position RMSE (steps >= fusion_start)."""
    m = r.metrics
    mp_col = np.asarray(m["map"]).astype(str)
    ty_col = np.asarray(m["type"]).astype(str)
    late = np.asarray(m["step"]) >= fusion_start
    vt = r.vehicles
    vlate = np.asarray(vt["step"]) >= fusion_start
    out: dict[str, dict[str, float]] = {}
    for mp in _maps(names, [r]):
        row: dict[str, float] = {}
        for ty in TYPES:
            sel = (mp_col == mp) & (ty_col == ty) & late
            g = np.asarray(m["gospa"], float)[sel]
            row[f"gospa_{ty}"] = float(g.mean()) if g.size else math.nan
            c = np.asarray(m["card"], float)[sel] if "card" in m else np.zeros(0)
            row[f"card_{ty}"] = float(c.mean()) if c.size else math.nan
        if mp == OTHERS_MAP:  # a VS score only: no vehicle state behind it
            row["pos_rmse"] = math.nan
            out[mp] = row
            continue
        sel = vlate if mp == "fused" else vlate & (np.asarray(vt["vehicle"]).astype(int) == names.index(mp))
        e = np.asarray(vt["pos_err"], float)[sel]
        e = e[np.isfinite(e)]
        row["pos_rmse"] = float(np.sqrt(np.mean(e * e))) if e.size else math.nan
        out[mp] = row
    return out


SCORED: tuple[str, ...] = tuple(f"gospa_{t}" for t in TYPES) + ("pos_rmse",)
"""Headline scores that get a 95% CI over runs and a paired difference to ``baseline``."""


def _reference(label: str, labels: Sequence[str]) -> str | None:
    """The arm a label is compared with: :data:`~mmslam.slam.specs.variants.COMPARED_WITH` (``baseline``) with the
    same grid settings, else plain ``baseline``."""
    variant, arm = parse_label(label)
    if variant == COMPARED_WITH:
        return None
    for cand in (arm_label(COMPARED_WITH, arm), COMPARED_WITH):
        if cand in labels:
            return cand
    return None


def _add_intervals(headline: list[dict[str, Any]], per_run: dict[str, dict[int, dict[str, dict[str, float]]]]) -> None:
    """Add ``<score>_ci`` (95% CI half-width over runs), ``<score>_diff`` / ``_diff_ci`` / ``_sig`` (paired
    difference to the reference arm over the seeds both ran; ``_sig`` says whether the CI excludes 0)
    and ``card_<type>`` (mean PHD mass) to every headline row."""
    labels = list(per_run)
    for row in headline:
        label, mp = row["variant"], row["map"]
        runs = per_run[label]
        ref = _reference(label, labels)
        row["reference"] = ref
        for ty in TYPES:
            row[f"card_{ty}"] = ci95(np.array([runs[s][mp][f"card_{ty}"] for s in runs]))[0]
        for q in SCORED:
            row[q + "_ci"] = ci95(np.array([runs[s][mp][q] for s in runs]))[1]
            row[q + "_diff"] = row[q + "_diff_ci"] = math.nan
            row[q + "_sig"] = None
            if ref is None:
                continue
            common = [s for s in sorted(set(runs) & set(per_run[ref])) if mp in per_run[ref][s]]
            d = np.array([runs[s][mp][q] - per_run[ref][s][mp][q] for s in common])
            mean, half = ci95(d)
            row[q + "_diff"], row[q + "_diff_ci"] = mean, half
            row[q + "_sig"] = bool(math.isfinite(half) and abs(mean) > half) if math.isfinite(mean) else None


def _headline_rows(variant: str, res: list[Any], names: list[str], fusion_start: int) -> list[dict[str, Any]]:
    """Mean GOSPA per (map, type) and position RMSE over steps >= fusion_start, over all seeds."""
    maps = _maps(names, res)
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
        for r in res if mp != OTHERS_MAP else ():
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

