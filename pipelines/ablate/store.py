"""The ablation directory on disk: ``ablation.json``, finished jobs' metadata, the output marker and lock."""
from __future__ import annotations

import contextlib
import functools
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import CacheError, ConfigError, MmslamError
from mmslam.scenes.scenario import settings_diff
from mmslam.pipelines.ablate.executors import _one_line
from mmslam.pipelines.ablate.options import ABLATION_FILE, JOBS_DIR, SUMMARY_JSON, SUMMARY_PARQUET, Job, job_dir


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
        if (p / "manifest.json").is_file():  # a path cache: an ablation into it would be refused
            raise CacheError(f"{p}: is a path cache, not an ablation's results (no {ABLATION_FILE}); run "
                             "`mmslam ablate <scenario> --out <new folder>` and give that folder")
        raise CacheError(f"{p}: not an ablation results directory (no {ABLATION_FILE}); run "
                         f"`mmslam ablate <scenario> --out {p}` first")
    try:
        return json.loads(f.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CacheError(f"{f}: unreadable ({_one_line(e)}); delete it and re-run the ablation") from None


def _write_json(path: Path, data: Any) -> None:
    """Atomic JSON write (temp file :func:`temp_path` + os.replace; the temp file is removed on failure)."""
    tmp = temp_path(path)
    try:
        tmp.write_text(json.dumps(data, indent=2, default=_jsonable, allow_nan=True))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def temp_path(path: Path) -> Path:
    """The temp file an ablation writes before renaming it to ``path``: ``.<name>.<pid>.tmp`` next to it."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def remove_stale_temps(out_dir: str | Path, names: Sequence[str]) -> list[Path]:
    """Delete the temp files ``.<name>.<pid>.tmp`` (:func:`temp_path`) of ``names`` in ``out_dir`` whose
    writer is gone (a killed run, or a write that failed, e.g. on a full disk or past a file-size limit).

    Only this exact naming pattern of our own files is touched; a temp file of a live process is kept.
    Returns the files removed.
    """
    import re

    from mmslam.outputs import _pid_alive

    out = Path(out_dir)
    pat = re.compile("|".join(rf"\.{re.escape(n)}\.(\d+)\.tmp" for n in names))
    gone = []
    with contextlib.suppress(OSError):
        for p in out.iterdir():
            m = pat.fullmatch(p.name)
            if m is None or not p.is_file() or p.is_symlink():
                continue
            pid = int(next(g for g in m.groups() if g is not None))
            if pid == os.getpid() or not _pid_alive(pid):
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
                    gone.append(p)
    return gone


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def _check_compatible(out_dir: Path, old: dict[str, Any], new: dict[str, Any]) -> None:
    if isinstance(old.get("scenario"), dict) and isinstance(new.get("scenario"), dict):
        diff = settings_diff(old["scenario"], new["scenario"])
        if diff:  # e.g. a [filter] table edited in the scenario file: the stored jobs ran with the old values
            more = f" and {len(diff) - 3} more" if len(diff) > 3 else ""
            raise ConfigError(f"{out_dir} holds an ablation run with other scenario settings ({'; '.join(diff[:3])}"
                              f"{more}); use another --out, or delete {out_dir / JOBS_DIR} and {out_dir / ABLATION_FILE} "
                              "to start it over")
    for key, flag in (("config_hash", "the trace (scenario / source)"), ("scenario_name", "the scenario"),
                      ("source", "--source"), ("particles", "--particles"), ("steps", "--steps"),
                      ("sets", "--set"), ("truth", "--truth")):
        if key not in new:
            continue
        if old.get(key, {"sets": [], "truth": "fixed"}.get(key)) != new.get(key):
            raise ConfigError(f"{out_dir} holds an ablation with {key}={old.get(key)} but this run asks "
                              f"{key}={new.get(key)} ({flag}); use another --out, or delete "
                              f"{out_dir / JOBS_DIR} and {out_dir / ABLATION_FILE} to start it over")


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
        check_ablation_outputs(out)  # a user's summary / report / figure of the same name (issue 25)
    out.mkdir(parents=True, exist_ok=True)
    if output_kind(out) != ABLATION_KIND:
        write_marker(out, ABLATION_KIND)
    return out


def _holding_out_lock(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Run ``fn(first, out_dir, ...)`` holding the writer lock of ``out_dir`` (one writer per directory)."""

    @functools.wraps(fn)
    def wrapper(first: Any, out_dir: str | Path, *args: Any, **kwargs: Any) -> Any:
        from mmslam.outputs import locked

        with locked(out_dir, "ablation"):
            return fn(first, out_dir, *args, **kwargs)

    return wrapper


# ====================================================================== files an ablation (re)writes
REPORT_FILE = "report.html"
FIGURES_DIR = "figures"
FIGURE_NAMES = ("fig2a_gospa_vs", "fig2b_gospa_va", "fig3_position_rmse", "fig2a_paired_vs", "fig2b_paired_va",
                "fig3_paired_position", "gospa_sp", "cardinality_vs", "cardinality_va")
"""The figures :func:`make_figures` always draws (``figures/<name>.png``; plus ``map_<label>.png``)."""


def _json_with(path: Path, keys: tuple[str, ...]) -> bool:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(d, dict) and all(k in d for k in keys)


def _is_summary_parquet(path: Path) -> bool:
    import pyarrow.parquet as pq

    try:
        names = set(pq.read_schema(path).names)
    except Exception:  # not a Parquet file at all
        return False
    return {"variant", "map", "type", "step"} <= names


def _is_report_html(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return b"<title>mmslam ablation:" in f.read(4096)
    except OSError:
        return False


def check_ablation_outputs(out_dir: str | Path) -> None:
    """Refuse (one line) if a file an ablation rewrites in ``out_dir`` exists and is not mmslam's.

    An ablation folder is mmslam's (its marker), but one that an older mmslam wrote into with
    ``--force`` may hold a user's ``summary.json``, ``summary.parquet``, ``report.html``,
    ``ablation.json`` or a figure of the same name: each is recognised by its content (keys,
    columns, title, figure tag) before any work, and never overwritten (:mod:`mmslam.outputs`).
    """
    from mmslam.outputs import NEVER, is_mmslam_figure

    out = Path(out_dir)
    checks = [(out / ABLATION_FILE, lambda p: _json_with(p, ("variants", "config_hash"))),
              (out / SUMMARY_JSON, lambda p: _json_with(p, ("config", "headline", "per_step"))),
              (out / SUMMARY_PARQUET, _is_summary_parquet), (out / REPORT_FILE, _is_report_html)]
    fdir = out / FIGURES_DIR
    if fdir.is_dir():
        checks += [(p, is_mmslam_figure) for p in sorted(fdir.iterdir())
                   if p.stem in FIGURE_NAMES or p.name.startswith("map_")]
    for p, ours in checks:
        if p.is_symlink() or (p.exists() and (p.is_dir() or not ours(p))):
            raise MmslamError(f"{p}: exists and is not a file mmslam wrote; move it out of {out} or choose "
                              f"another folder ({NEVER})")
