"""Trace a scenario into a resumable path cache (DESIGN.md section 7).

:func:`trace_scenario` computes the true vehicle states, then asks a path source for the paths
of every step not yet in the cache, writing one chunk of ``chunk_steps`` steps at a time (each
chunk aligned to multiples of ``chunk_steps``). Killing the process at any moment and running
it again continues after the last complete chunk; the final table contents equal those of an
uninterrupted run. A larger ``steps`` extends an existing shorter cache; ``force`` deletes the
cache directory and traces from scratch. One writer at a time: a lock file
``.<cachedir>.lock`` (holding the writer's pid) next to the cache refuses a second live writer;
the lock of a killed writer is taken over.
"""
from __future__ import annotations

import importlib.metadata
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import BackendError, CacheError, ConfigError
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.raytrace.cache import (
    FORCE_HINT, MANIFEST, TABLES, cache_dir_for, check_paths_finite, checked_chunks, config_hash, file_metadata,
    read_manifest, remove_temp_files, sha256_file, vehicle_columns, write_chunk, write_manifest,
)
from mmslam.raytrace.schema import PATH_COLUMNS, RAY_COLUMNS, SCHEMA_VERSION, sort_paths, sort_rays
from mmslam.scenes.geometry import check_vehicle_poses
from mmslam.scenes.scenario import Scenario
from mmslam.scenes.trajectory import true_trajectories

SOURCES = ("sionna", "analytic")


def make_source(name: str, scn: Scenario, max_depth: int = 1, samples: int = 1_000_000,
                seed: int = 0) -> Any:
    """A path source by name: ``analytic`` (closed form) or ``sionna`` (Sionna RT, lazily imported).

    ``max_depth`` (1..3), ``samples`` (rays per source) and ``seed`` only affect ``sionna``.
    """
    if name == "analytic":
        if scn.xml_scene:  # the external scene's triangles: blockage and first-order reflections
            from mmslam.raytrace.mesh_analytic import MeshAnalyticSource

            return MeshAnalyticSource(scn)
        return AnalyticSource(scn)
    if name == "sionna":
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
    raise ConfigError(f"unknown source '{name}'; expected one of {', '.join(SOURCES)}")


def _versions(source: Any) -> dict[str, str]:
    out = {}
    for pkg in ("mmslam", "numpy", "pyarrow"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    out.update({k: str(v) for k, v in source.versions().items()})
    out["python"] = sys.version.split()[0]
    return out


def _new_manifest(scn: Scenario, source: Any, steps: int) -> dict:
    return {
        "schema_version": SCHEMA_VERSION,
        "scenario": scn.name,
        "geometry_hash": scn.geometry_hash(),
        "config_hash": config_hash(scn, source.name, source.settings()),
        "source": source.name,
        "settings": source.settings(),
        "versions": _versions(source),
        "resolved_scenario": scn.to_dict(),
        "vehicle_names": scn.vehicle_names,
        "dt": scn.dt,
        "steps_completed": 0,
        "steps_requested": steps,
        "chunks": [],
        "created_unix": time.time(),
    }


def _check_existing(cache_dir: Path, m: dict, scn: Scenario, source: Any) -> None:
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


def _check_step_output(tables: dict[str, dict[str, np.ndarray]], step: int, source: Any
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


def trace_scenario(scn: Scenario, source: Any, out_root: str | Path, steps: int | None = None,
                   chunk_steps: int = 5, force: bool = False, progress: bool = True) -> Path:
    """Trace ``steps`` steps of ``scn`` with ``source`` into a cache under ``out_root``.

    Args:
        scn: the scenario.
        source: a :class:`~mmslam.raytrace.schema.PathSource`.
        out_root: root directory; the cache goes to :func:`cache_dir_for` ``(out_root, scn, source)``.
        steps: number of steps (default ``scn.steps``).
        chunk_steps: steps per Parquet chunk (chunks are aligned to multiples of it).
        force: delete an existing cache for this config first.
        progress: show a progress bar (steps, rays/s, ETA) on stderr.

    Returns:
        The cache directory.
    """
    n_steps = scn.steps if steps is None else int(steps)
    if n_steps < 1:
        raise ConfigError(f"--steps {steps}: expected a positive number of steps")
    if chunk_steps < 1:
        raise ConfigError(f"chunk_steps {chunk_steps}: expected >= 1")
    cache_dir = cache_dir_for(out_root, scn, source)
    cache_dir.parent.mkdir(parents=True, exist_ok=True)
    lock = _acquire_lock(cache_dir)
    try:
        if force and cache_dir.exists():
            shutil.rmtree(cache_dir)
        cache_dir.mkdir(parents=True, exist_ok=True)
        remove_temp_files(cache_dir)
        return _trace_into(scn, source, cache_dir, n_steps, chunk_steps, progress)
    finally:
        _release_lock(lock)


def lock_path(cache_dir: Path) -> Path:
    """The writer lock of a cache: ``.<dirname>.lock`` next to the cache directory."""
    return cache_dir.parent / f".{cache_dir.name}.lock"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _acquire_lock(cache_dir: Path) -> Path:
    """Create the writer lock (holding our pid); a lock of a dead process is taken over."""
    lock = lock_path(cache_dir)
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or "0")
            except (OSError, ValueError):
                pid = 0
            if pid > 0 and _pid_alive(pid):
                raise CacheError(f"{cache_dir}: another trace (pid {pid}) is writing this cache; wait for it, "
                                 f"or delete {lock} if that process is gone") from None
            lock.unlink(missing_ok=True)  # stale: its writer was killed
            continue
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()}\n")
        return lock
    raise CacheError(f"{lock}: could not take the writer lock; delete it and re-run")


def _release_lock(lock: Path) -> None:
    try:
        if lock.read_text().strip() == str(os.getpid()):
            lock.unlink()
    except FileNotFoundError:
        pass


def _trace_into(scn: Scenario, source: Any, cache_dir: Path, n_steps: int, chunk_steps: int,
                progress: bool) -> Path:
    """Resume / extend the cache in ``cache_dir`` (writer lock held) up to ``n_steps`` steps."""

    if (cache_dir / MANIFEST).is_file():
        m = read_manifest(cache_dir)
        _check_existing(cache_dir, m, scn, source)
        m["resolved_scenario"] = scn.to_dict()  # non-geometry parameters follow the latest run
        m["steps_requested"] = max(n_steps, int(m["steps_completed"]))
    else:
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
    try:
        start = done
        while start < n_steps:
            stop = min((start // chunk_steps + 1) * chunk_steps, n_steps)
            parts = []
            for k in range(start, stop):
                parts.append(_check_step_output(source.trace_tables(k, states[k]), k, source))
                n_rows += len(parts[-1]["rays"]["rx"])
                if bar is not None:
                    bar.update(task, advance=1, rate=n_rows / max(time.perf_counter() - t0, 1e-9))
            paths = sort_paths({c: np.concatenate([p["paths"][c] for p in parts]) for c in PATH_COLUMNS})
            rays = sort_rays({c: np.concatenate([p["rays"][c] for p in parts]) for c in RAY_COLUMNS})
            check_paths_finite(paths, f"source '{source.name}' output",
                               hint="nothing was written for these steps; fix the source")
            tables = {"vehicles": vehicle_columns(states[start:stop], start, scn.dt), "rays": rays, "paths": paths}
            entry = write_chunk(cache_dir, len(m["chunks"]), start, tables, file_metadata(m))
            entry["versions"] = versions  # a resumed trace may run under other library versions
            m["chunks"].append(entry)
            m["steps_completed"] = stop
            write_manifest(cache_dir, m)
            start = stop
    finally:
        if bar is not None:
            bar.stop()
    return cache_dir
