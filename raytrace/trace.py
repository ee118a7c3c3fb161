"""Trace a scenario into a resumable path cache (docs/design.md section 7).

:func:`trace_scenario` computes the true vehicle states, then asks a path source for the paths
of every step not yet in the cache, writing one chunk of ``chunk_steps`` steps at a time (each
chunk aligned to multiples of ``chunk_steps``). Killing the process at any moment and running
it again continues after the last complete chunk; the final table contents equal those of an
uninterrupted run. A larger ``steps`` extends an existing shorter cache; ``force`` deletes the
cache directory and traces from scratch. One writer at a time: a lock file
``.<cachedir>.lock`` (holding the writer's pid) next to the cache refuses a second live writer;
the lock of a killed writer is taken over. An existing cache of an older readable schema version
(:data:`~mmslam.raytrace.schema.READABLE_SCHEMA_VERSIONS`) is resumed and extended in its own
version (its new chunks lack the columns later versions added, as its older ones do).
"""
from __future__ import annotations

import importlib.metadata
import os
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, KeysView

import numpy as np

from mmslam.errors import (BackendError, CacheError, ConfigError, EnvironmentFailure, Interrupted, check_interrupt,
                           deferred_sigint, environment_failure, was_interrupted)
from mmslam.outputs import acquire_lock, lock_path, release_lock  # noqa: F401  (lock_path: public)
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.raytrace.cache import (
    FORCE_HINT, MANIFEST, TABLES, cache_dir_for, check_paths_finite, check_tx_columns, checked_chunks, config_hash,
    file_metadata, read_manifest, remove_temp_files, sha256_file, vehicle_columns, write_chunk, write_manifest,
)
from mmslam.raytrace.schema import PATH_COLUMNS, RAY_COLUMNS, SCHEMA_VERSION, PathSource, sort_paths, sort_rays
from mmslam.scenes.geometry import check_bs_position, check_vehicle_overlaps, check_vehicle_poses
from mmslam.scenes.scenario import Scenario, default_settings, scenario_settings, settings_diff
from mmslam.scenes.trajectory import true_trajectories

SourceFactory = Callable[..., PathSource]
"""``factory(scn, max_depth=1, samples=1_000_000, seed=0) -> PathSource``; raises ConfigError /
BackendError for bad settings or a missing backend."""

_SOURCES: dict[str, SourceFactory] = {}
SOURCES: KeysView[str] = _SOURCES.keys()
"""Names of the registered path sources (a live view of the registry: ``sionna``, ``analytic``, ...)."""


def register_source(name: str, factory: SourceFactory, *, replace: bool = False) -> SourceFactory:
    """Register a path source factory under ``name`` (``--source name``); returns the factory.

    Raises:
        ConfigError: ``name`` is taken (unless ``replace``) or not a plain identifier.
    """
    if not name.isidentifier():
        raise ConfigError(f"source name {name!r}: expected a plain identifier")
    if name in _SOURCES and not replace:
        raise ConfigError(f"source {name!r} is already registered; pick another name")
    _SOURCES[name] = factory
    return factory


def unregister_source(name: str) -> None:
    """Remove a registered source (tests)."""
    _SOURCES.pop(name, None)


def make_source(name: str, scn: Scenario, max_depth: int = 1, samples: int = 1_000_000,
                seed: int = 0) -> PathSource:
    """A path source by name from the registry (:func:`register_source`): ``analytic`` (closed
    form) or ``sionna`` (Sionna RT, lazily imported).

    ``max_depth`` (1..3), ``samples`` (rays per source) and ``seed`` only affect ``sionna``.

    Raises:
        ConfigError: unknown name or bad settings; BackendError: the backend is not installed.
    """
    factory = _SOURCES.get(name)
    if factory is None:
        raise ConfigError(f"unknown source '{name}'; expected one of {', '.join(SOURCES)}")
    return factory(scn, max_depth=max_depth, samples=samples, seed=seed)


def _analytic_source(scn: Scenario, **_ignored: Any) -> PathSource:
    """Closed-form paths; with an external XML scene, its triangles (blockage, first-order reflections)."""
    if scn.xml_scene:
        from mmslam.raytrace.mesh_analytic import MeshAnalyticSource

        return MeshAnalyticSource(scn)
    return AnalyticSource(scn)


def _sionna_source(scn: Scenario, max_depth: int = 1, samples: int = 1_000_000, seed: int = 0) -> PathSource:
    """Sionna RT PathSolver (imported lazily; BackendError if it is not installed)."""
    if not 1 <= int(max_depth) <= 3:
        raise ConfigError(f"--max-depth {max_depth}: expected 1, 2 or 3")
    if int(samples) < 1:
        raise ConfigError(f"--samples {samples}: expected a positive number of rays per source")
    try:
        from mmslam.raytrace.sionna_adapter import SionnaSource
    except ImportError as e:
        raise BackendError(f"the sionna source is unavailable ({e}); install sionna-rt or use "
                           "--source analytic") from None
    return SionnaSource(scn, max_depth=int(max_depth), samples_per_src=int(samples), seed=int(seed))


register_source("sionna", _sionna_source)
register_source("analytic", _analytic_source)


def _versions(source: PathSource) -> dict[str, str]:
    out = {}
    for pkg in ("mmslam", "numpy", "pyarrow"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    out.update({k: str(v) for k, v in source.versions().items()})
    out["python"] = sys.version.split()[0]
    return out


def _new_manifest(scn: Scenario, source: PathSource, steps: int) -> dict:
    return {
        "schema_version": SCHEMA_VERSION,
        "scenario": scn.name,
        "geometry_hash": scn.geometry_hash(),
        "config_hash": config_hash(scn, source.name, source.settings()),
        "source": source.name,
        "settings": source.settings(),
        "versions": _versions(source),
        "resolved_scenario": scn.to_dict(),
        "scenario_settings": scenario_settings(scn),
        "settings_defaults": default_settings(),
        "vehicle_names": scn.vehicle_names,
        "dt": scn.dt,
        "steps_completed": 0,
        "steps_requested": steps,
        "chunks": [],
        "created_unix": time.time(),
    }


def _check_existing(cache_dir: Path, m: dict, scn: Scenario, source: PathSource) -> None:
    """Verify a resumed cache belongs to this config and that its chunks are intact."""
    mp = cache_dir / MANIFEST
    want = config_hash(scn, source.name, source.settings())
    if m["config_hash"] != want or m["source"] != source.name:
        raise CacheError(f"{mp}: config hash {m['config_hash']} ({m['source']}) differs from this run's "
                         f"{want} ({source.name}); {FORCE_HINT}")
    for c in checked_chunks(m, mp):
        for table in TABLES:
            f = cache_dir / c["files"][table]
            if not f.is_file():
                raise CacheError(f"{f}: chunk file missing; {FORCE_HINT}")
            if sha256_file(f) != c["sha256"][table]:
                raise CacheError(f"{f}: sha256 mismatch (truncated or modified); {FORCE_HINT}")


def _check_step_output(tables: dict[str, dict[str, np.ndarray]], step: int, source: PathSource
                       ) -> dict[str, dict[str, np.ndarray]]:
    """A source's ``{"rays", "paths"}`` output at one step, checked (all columns, equal lengths)."""
    out = {}
    for table, schema in (("rays", RAY_COLUMNS), ("paths", PATH_COLUMNS)):
        cols = tables.get(table) if isinstance(tables, dict) else None
        if cols is None:
            raise CacheError(f"source '{source.name}' returned no {table} table at step {step}")
        miss = [k for k in schema if k not in cols]
        if miss:
            raise CacheError(f"source '{source.name}' returned no {table} columns {miss} at step {step}")
        n = len(cols["rx"])
        t = {k: np.asarray(cols[k]) for k in schema}
        if any(len(v) != n for v in t.values()):
            raise CacheError(f"source '{source.name}' returned {table} columns of unequal length at step {step}")
        t["step"] = np.full(n, step, dtype=np.int32)
        out[table] = t
    return out


CACHE_ROOT_KIND = "cache"
"""Output-marker kind of a cache root (a folder of caches, :mod:`mmslam.outputs`)."""


def _holds_only_caches(root: Path) -> bool:
    """A cache root written before output markers existed: only caches, locks and temp files."""
    return all((p / MANIFEST).is_file() or p.name.endswith((".lock", ".tmp")) for p in root.iterdir())


def check_cache_root(out_root: str | Path, force: bool = False, option: str = "--out") -> Path:
    """Raise a one-line error (naming ``option``) unless ``out_root`` may hold caches (missing, empty, or a cache
    root).

    Any other folder is refused whatever ``force`` (:mod:`mmslam.outputs`: mmslam never writes
    into a folder it did not make).
    """
    from mmslam.outputs import check_target

    p = Path(out_root)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{option} {p}: is a file, not a folder; choose a writable path for the cache root")
    if (p / MANIFEST).is_file():  # a cache itself, where its folder is meant
        raise ConfigError(f"{option} {p}: is a cache, not a folder of caches; give the folder that holds it "
                          f"({p.parent})")
    return check_target(p, CACHE_ROOT_KIND, force, option=option, accept=_holds_only_caches)


def _is_own_files(d: Path, suffixes: tuple[str, ...]) -> bool:
    return d.is_dir() and not d.is_symlink() and all(
        f.is_file() and not f.is_symlink() and f.name.endswith(suffixes) for f in d.iterdir())


def _is_own_cache(cache_dir: Path) -> bool:
    """``cache_dir`` holds only what a trace writes (the manifest, table folders of chunk files, temp files)
    and the ``estimates/<key>/`` folders of the estimated sensor model (``.npz`` and temp files)."""
    for e in cache_dir.iterdir():
        if e.name == MANIFEST or (e.name.startswith(".") and e.name.endswith(".tmp") and e.is_file()):
            continue
        if e.name == "estimates" and e.is_dir() and not e.is_symlink() and all(
                _is_own_files(k, (".npz", ".tmp")) for k in e.iterdir()):
            continue
        if e.name in TABLES and e.is_dir() and not e.is_symlink() and all(
                f.is_file() and not f.is_symlink() and f.name.endswith((".parquet", ".tmp")) for f in e.iterdir()):
            continue
        return False
    return True


def check_scene(scn: Scenario, steps: int | None = None) -> None:
    """Refuse, in one line (:class:`ConfigError`), a scene that cannot be traced as meant, before any work.

    A vehicle within ``BS_CLEARANCE_M`` of the BS, two vehicle bodies that overlap at some step
    (:func:`~mmslam.scenes.geometry.check_vehicle_overlaps`; also cars drawn by ``n_vehicles``) and a
    BS inside an object (:func:`~mmslam.scenes.geometry.check_bs_position`: Sionna would still find a
    line-of-sight path out of a closed mesh). The car poses against the meshes are checked by
    :func:`~mmslam.scenes.geometry.check_vehicle_poses` when the trace starts.
    """
    from mmslam.scenes.trajectory import check_bs_clearance

    states = true_trajectories(scn, scn.steps if steps is None else int(steps))
    check_bs_clearance(scn, states)
    check_vehicle_overlaps(scn, states)
    check_bs_position(scn)


NO_PATH_WARN = 0.5
"""Warn when a vehicle gets no path at all in more than this fraction of the steps."""
LOS_WARN = 0.25
"""Warn when a vehicle has the line-of-sight path in fewer than this fraction of the steps."""


def coverage_warnings(paths: dict[str, np.ndarray], steps: int, vehicle_names: list[str] | tuple[str, ...]
                      ) -> list[str]:
    """One line per vehicle that gets no path in most steps or rarely sees the BS (``paths`` of a cache).

    Counted over ``steps`` steps: steps in which the vehicle receives no path at all (above
    :data:`NO_PATH_WARN` of them) and steps with its line-of-sight path (below :data:`LOS_WARN`).
    Such a vehicle localises from dead reckoning alone for long stretches: move the BS (``mmslam
    scene coverage`` draws where it reaches) or the route.
    """
    from mmslam.model import LandmarkType

    out = []
    step = np.asarray(paths["step"], np.int64)
    rx = np.asarray(paths["rx"], np.int64)
    typ = np.asarray(paths["type"], np.int64)
    for i, name in enumerate(vehicle_names):
        mine = rx == i
        n_any = np.unique(step[mine]).size
        n_los = np.unique(step[mine & (typ == int(LandmarkType.BS))]).size
        none, los = steps - n_any, n_los
        if none > NO_PATH_WARN * steps or los < LOS_WARN * steps:
            out.append(f"vehicle '{name}': no path in {none} of {steps} steps, line of sight to the BS in {los}; "
                       "move the BS or the route (mmslam scene coverage draws where the BS reaches)")
    return out


def trace_scenario(scn: Scenario, source: PathSource, out_root: str | Path, steps: int | None = None,
                   chunk_steps: int = 5, force: bool = False, progress: bool = True,
                   executor: "DaskExecutor | None" = None, notice: Callable[[str], None] | None = None) -> Path:
    """Trace ``steps`` steps of ``scn`` with ``source`` into a cache under ``out_root``.

    Args:
        scn: the scenario.
        source: a :class:`~mmslam.raytrace.schema.PathSource`.
        out_root: root directory; the cache goes to :func:`cache_dir_for` ``(out_root, scn, source)``.
        steps: number of steps (default ``scn.steps``).
        chunk_steps: steps per Parquet chunk (chunks are aligned to multiples of it).
        force: delete an existing cache for this config first (only if it holds nothing but what a
            trace writes). An ``out_root`` that is not a cache root (a user's folder) is refused
            before any work, with or without it.
        progress: show a progress bar (steps, rays/s, ETA) on stderr.
        executor: trace the chunks on a Dask cluster (:class:`DaskExecutor`); ``None`` traces them here.
            Either way this process alone writes the cache, chunk by chunk in step order, so the
            tables are the same and an interrupted run resumes after the last written chunk.
        notice: gets one line when an existing cache of this configuration stored other run parameters (``seed``,
            ``[sensor]``, ``[filter]``, ``[fusion]``, ``[evaluation]``): they follow this run, the traced paths do not
            change, and a later ``mmslam slam`` on the cache uses them.

    Returns:
        The cache directory.
    """
    n_steps = scn.steps if steps is None else int(steps)
    if n_steps < 1:
        raise ConfigError(f"--steps {steps}: expected a positive number of steps")
    if chunk_steps < 1:
        raise ConfigError(f"chunk_steps {chunk_steps}: expected >= 1")
    from mmslam.outputs import output_kind, write_marker

    check_scene(scn, n_steps)  # before anything is written
    check_cache_root(out_root, force)
    cache_dir = cache_dir_for(out_root, scn, source)
    root = cache_dir.parent
    made = [p for p in (root, *root.parents) if not os.path.lexists(p)]  # the folders this trace creates, deepest first
    root.mkdir(parents=True, exist_ok=True)
    marked = output_kind(root) != CACHE_ROOT_KIND
    if marked:
        write_marker(root, CACHE_ROOT_KIND)
    try:
        return _trace_locked(scn, source, cache_dir, n_steps, chunk_steps, force, progress, executor, notice)
    except BaseException:
        if marked:  # a first trace that left no cache: its marker goes, and the folders it made
            _unmark_if_empty(root, made)
        raise


def _unmark_if_empty(root: Path, made: list[Path]) -> None:
    """Delete the output marker of ``root`` if it is all the folder (or the folder a link ``root`` points to) holds:
    a trace marked it and traced nothing; then the folders of ``made`` (deepest first) that are empty."""
    from mmslam.outputs import MARKER

    try:
        if root.is_dir() and [p.name for p in root.iterdir()] == [MARKER]:
            (root / MARKER).unlink()
            for d in made:
                if d.is_symlink() or any(d.iterdir()):
                    break
                d.rmdir()
    except OSError:  # cleaning up after a failure must not hide it
        pass


def _trace_locked(scn: Scenario, source: PathSource, cache_dir: Path, n_steps: int, chunk_steps: int, force: bool,
                  progress: bool, executor: "DaskExecutor | None", notice: Callable[[str], None] | None) -> Path:
    """:func:`trace_scenario`'s work under the cache's writer lock (arguments as there)."""
    lock = acquire_lock(cache_dir, "trace", CacheError)
    try:
        if os.path.lexists(cache_dir) and (cache_dir.is_symlink() or not cache_dir.is_dir()
                                           or not _is_own_cache(cache_dir)):
            raise CacheError(f"{cache_dir}: exists and is not a cache mmslam wrote (it holds other files); move it "
                             "away or choose another --out (mmslam never writes into, replaces or deletes what it "
                             "did not write, even with --force)")
        if force and cache_dir.exists():
            shutil.rmtree(cache_dir)
        created = not cache_dir.exists()
        cache_dir.mkdir(parents=True, exist_ok=True)
        remove_temp_files(cache_dir)
        try:
            return _trace_into(scn, source, cache_dir, n_steps, chunk_steps, progress, executor, notice)
        except BaseException:
            if created and _steps_on_disk(cache_dir) == 0:  # nothing traced: leave no empty cache behind
                shutil.rmtree(cache_dir, ignore_errors=True)
            raise
    finally:
        release_lock(lock)


def _steps_on_disk(cache_dir: Path) -> int:
    """The completed steps the manifest in ``cache_dir`` records (0 without a readable one)."""
    try:
        return int(read_manifest(cache_dir)["steps_completed"])
    except (CacheError, KeyError, TypeError, ValueError, OSError):
        return 0


def _trace_into(scn: Scenario, source: PathSource, cache_dir: Path, n_steps: int, chunk_steps: int,
                progress: bool, executor: "DaskExecutor | None" = None,
                notice: Callable[[str], None] | None = None) -> Path:
    """Resume / extend the cache in ``cache_dir`` (writer lock held) up to ``n_steps`` steps."""

    states = None
    if (cache_dir / MANIFEST).is_file():
        m = read_manifest(cache_dir)
        _check_existing(cache_dir, m, scn, source)
        diff = settings_diff(m.get("resolved_scenario") or {}, scn.to_dict())
        if diff and notice is not None:
            more = f" and {len(diff) - 3} more" if len(diff) > 3 else ""
            notice(f"{cache_dir}: its stored settings now follow this scenario ({'; '.join(diff[:3])}{more}); the "
                   "traced paths are unchanged, and mmslam slam on this cache uses the new settings")
        m["resolved_scenario"] = scn.to_dict()  # non-geometry parameters follow the latest run
        m["scenario_settings"], m["settings_defaults"] = scenario_settings(scn), default_settings()
        m["steps_requested"] = max(n_steps, int(m["steps_completed"]))
    else:  # a new cache: every pose against the scene meshes before its manifest is written
        states = true_trajectories(scn, n_steps)
        check_vehicle_poses(scn, states)
        m = _new_manifest(scn, source, n_steps)
    done = int(m["steps_completed"])
    # orphaned chunk files past the manifest (killed between chunk write and manifest write)
    known = {f for c in m["chunks"] for f in c["files"].values()}
    for p in [f for t in TABLES for f in cache_dir.glob(f"{t}/part-*.parquet")]:
        if p.relative_to(cache_dir).as_posix() not in known:
            p.unlink()
    write_manifest(cache_dir, m)
    if done >= n_steps:
        return cache_dir

    if states is None:
        states = true_trajectories(scn, n_steps)
        check_vehicle_poses(scn, states)  # every pose against the scene meshes, before any tracing
    bar = None
    if progress:
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                   TimeElapsedColumn, TimeRemainingColumn)
        from rich.console import Console

        bar = Progress(TextColumn(f"trace {scn.name} ({source.name})"), BarColumn(), MofNCompleteColumn(),
                       TextColumn("steps"), TextColumn("{task.fields[rate]:.0f} rays/s"),
                       TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                       console=Console(stderr=True), transient=False)
        task = bar.add_task("trace", total=n_steps, completed=done, rate=0.0)
        bar.start()
    versions = _versions(source)
    t0, n_rows = time.perf_counter(), 0
    bounds, start = [], done
    while start < n_steps:
        stop = min((start // chunk_steps + 1) * chunk_steps, n_steps)
        bounds.append((start, stop))
        start = stop

    def local_chunks():
        for start, stop in bounds:
            parts = []
            for k in range(start, stop):
                check_interrupt()  # a Ctrl-C swallowed by library code still stops here
                with deferred_sigint():  # Sionna / Dr.Jit cannot unwind a Python exception from a handler
                    tables = source.trace_tables(k, states[k])
                parts.append(_check_step_output(tables, k, source))
                if bar is not None:
                    bar.update(task, advance=1, rate=(n_rows + sum(len(p["rays"]["rx"]) for p in parts))
                               / max(time.perf_counter() - t0, 1e-9))
            yield start, stop, _chunk_tables(parts)

    chunks = local_chunks() if executor is None else executor.chunks(scn, source, states, bounds)
    try:
        for start, stop, (paths, rays) in chunks:
            n_rows += len(rays["rx"])
            if bar is not None and executor is not None:
                bar.update(task, advance=stop - start, rate=n_rows / max(time.perf_counter() - t0, 1e-9))
            where, hint = f"source '{source.name}' output", "nothing was written for these steps; fix the source"
            check_paths_finite(paths, where, hint=hint)
            for cols in (paths, rays):
                check_tx_columns(cols, scn.bs_array, where, hint=hint)
            tables = {"vehicles": vehicle_columns(states[start:stop], start, scn.dt), "rays": rays, "paths": paths}
            # a chunk is kept only once the manifest on disk names it; Ctrl-C waits for that write,
            # so the "kept" count of the message is the one on disk
            with deferred_sigint():
                # an older cache (schema version 2) grows in its own version: one version per cache
                entry = write_chunk(cache_dir, len(m["chunks"]), start, tables, {**file_metadata(m), "versions": versions},
                                    version=int(m["schema_version"]))
                entry["versions"] = versions  # a resumed trace may run under other library versions
                new = {**m, "chunks": m["chunks"] + [entry], "steps_completed": stop}
                write_manifest(cache_dir, new)
                m = new
    except BaseException as e:
        kept = f"{m['steps_completed']} of {n_steps} steps are kept in {cache_dir}"
        if not was_interrupted(e):
            failure = environment_failure(e)  # out of memory, a lost Dask scheduler
            if failure is None:
                raise
            raise EnvironmentFailure(f"{failure[0]}; {kept}; {failure[1]}, then re-run the same command to "
                                     "resume") from None
        raise Interrupted(f"{kept} (the chunk in progress was dropped); re-run the same command to resume"
                          ) from None
    finally:
        if bar is not None:
            bar.stop()
    return cache_dir


# ====================================================================== Dask
_WORKER_SOURCES: dict[tuple, PathSource] = {}
_WORKER_LOCK = threading.Lock()


def _trace_chunk(spec: dict, scn: Scenario, states: np.ndarray, start: int) -> tuple[dict, dict]:
    """On a worker: the sorted ``(paths, rays)`` columns of steps ``start .. start + len(states) - 1``.

    The worker builds the source from ``spec`` (:func:`make_source` arguments) once per process
    and reuses it for later chunks; chunks run one at a time per process (use process workers,
    one per GPU or core, for parallel Sionna traces).
    """
    key = (scn.geometry_hash(), tuple(sorted(spec.items())))
    with _WORKER_LOCK:  # Sionna / Dr.Jit: one trace at a time per process (threads of one worker wait)
        src = _WORKER_SOURCES.get(key)
        if src is None:
            src = _WORKER_SOURCES[key] = make_source(spec["name"], scn, max_depth=spec["max_depth"],
                                                     samples=spec["samples"], seed=spec["seed"])
        parts = [_check_step_output(src.trace_tables(start + i, states[i]), start + i, src) for i in range(len(states))]
    return _chunk_tables(parts)


def _chunk_tables(parts: list[dict[str, dict[str, np.ndarray]]]) -> tuple[dict, dict]:
    """Per-step checked outputs -> one chunk's sorted ``(paths, rays)`` columns."""
    paths = sort_paths({c: np.concatenate([p["paths"][c] for p in parts]) for c in PATH_COLUMNS})
    rays = sort_rays({c: np.concatenate([p["rays"][c] for p in parts]) for c in RAY_COLUMNS})
    return paths, rays


class DaskExecutor:
    """Trace chunks of steps on a Dask cluster (one worker per GPU or CPU core), through the shared
    executor module :mod:`mmslam.executor` (the same address check and pool as ``mmslam ablate``).

    Args:
        spec: how a worker builds the source: ``{"name", "max_depth", "samples", "seed"}``
            (:func:`make_source` arguments; the source itself is not sent).
        client: a ``distributed.Client``; else one is made for ``scheduler`` (an address, checked by
            :func:`mmslam.executor.check_executor`) or for a ``LocalCluster`` of ``workers`` processes
            (at most one per chunk) with one thread each, closed at the end.

    ``with DaskExecutor(...) as ex:`` connects to ``scheduler`` on entry (an unreachable one fails
    before any work) and closes that connection on exit. Chunks are submitted at once and written by
    the caller in step order as they finish, so at most the chunks in flight are lost when the run
    is interrupted.
    """

    def __init__(self, spec: dict, client: Any = None, scheduler: str | None = None,
                 workers: int | None = None) -> None:
        from mmslam.executor import check_executor

        check_executor("dask", scheduler, workers)
        self.spec = {k: spec[k] for k in ("name", "max_depth", "samples", "seed")}
        self.client, self.scheduler, self.workers = client, scheduler, workers
        self._own_client = False

    def __enter__(self) -> "DaskExecutor":
        from mmslam.executor import connect_dask

        if self.client is None and self.scheduler:
            self.client, self._own_client = connect_dask(self.scheduler), True
        return self

    def __exit__(self, *exc: object) -> None:
        from mmslam.executor import close_client

        if self._own_client:
            close_client(self.client)
            self.client, self._own_client = None, False

    def chunks(self, scn: Scenario, source: PathSource, states: np.ndarray, bounds: list[tuple[int, int]]):
        """Yield ``(start, stop, (paths, rays))`` for every chunk in ``bounds``, in order."""
        from mmslam.executor import dask_pool

        if not bounds:
            return
        with dask_pool(self.scheduler, self.workers, len(bounds), client=self.client) as pool:
            futs = [pool.submit(_trace_chunk, self.spec, scn, states[a:b], a, key=f"trace-steps{a}-{b}")
                    for a, b in bounds]
            try:
                for (a, b), f in zip(bounds, futs):
                    yield a, b, f.result()
            finally:
                pool.cancel(futs)
